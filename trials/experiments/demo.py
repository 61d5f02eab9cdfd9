"""The main job on the built-in scene (``make demo``), with quick settings.

1. render the scene and roll out the privileged expert (``scene.png``, ``expert_rollout.gif``);
2. train the reference policy (``advobj policy train --preset quick``), or reuse ``<out>/policy``;
3. optimise the 3D adversarial object and the 2D patch baseline (``advobj attack run`` quick
   preset, shortened), or reuse finished runs under ``<out>/attacks``;
4. evaluate clean vs 3D object vs 2D patch on the same task-feasible configurations
   (``<out>/eval``) and write ``<out>/report.md`` with the Table I layout, plots and GIFs.

Every stage is cached or resumable: re-running after an interruption continues where it stopped.
"""

from __future__ import annotations

import re
from pathlib import Path

import imageio.v3 as iio

from sim.htmlreport import REPORT_HTML
from sim.imaging import contact_sheet, write_gif
from sim.runinfo import write_run_info
from sim.runtime import set_torch_threads
from sim.spec import load_spec
from trials.experiments.recipes import (
    Context,
    ensure_attack,
    ensure_eval,
    ensure_policy,
    eval_rows,
    resolve_experiment,
    table1_markdown,
    verdicts_once,
)
from trials.jobs.scene import expert_rollout

__all__ = ["run_demo", "DEMO_BUDGET", "demo_report_markdown", "verdicts_once"]

# Sized for <= 15 minutes on 2 CPU cores including setup (measured figures: docs/evaluation.md).
DEMO_BUDGET = dict(attack_overrides={"iterations": 60}, episodes=40, max_steps=60, num_envs=8, gifs=2)


def run_demo(out: Path, seed: int = 0, log=print, executor=None) -> dict:
    """Run the demo into ``out``; returns the evaluation summary plus the expert's outcome."""
    set_torch_threads()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    spec = load_spec(None)
    cfg = resolve_experiment("quick", seed=seed, **DEMO_BUDGET)
    write_run_info(
        out, {"job": "demo", "experiment": cfg.model_dump(mode="json"), "scene": spec.model_dump(mode="json")}, seed
    )

    log("[1/4] scene and expert rollout")
    frames, info = expert_rollout(spec, seed)
    write_gif(out / "expert_rollout.gif", frames)
    iio.imwrite(out / "contact_sheet.png", contact_sheet(frames))
    iio.imwrite(out / "scene.png", frames[0])
    reached = int(info["reached"][0])

    ctx = Context(cfg, out, log=log, executor=executor)
    log("[2/4] jobs: the reference policy, the 3D object and 2D patch attacks, the evaluation")
    policy = ensure_policy(ctx, "reference")
    att = ensure_attack(ctx, policy, "c2f", {"schedule": "c2f"})
    pat = ensure_attack(ctx, policy, "patch", {"schedule": "c2f", "adversarial_mesh": "patch"})
    summary = ensure_eval(ctx, policy, "demo", ["attack", "patch"], attack=att, patch=pat)
    log(f"[3/4] running {len(ctx.grid.jobs)} jobs (finished ones are reused; logs in {out / 'logs'})")
    ctx.run_jobs()
    log("[4/4] report: clean vs 3D object vs 2D patch")
    eval_dir = out / "evals" / "demo"
    table = table1_markdown(summary, ctx, eval_rows(ctx, "demo"))
    (out / "report.md").write_text(
        demo_report_markdown(out, policy, eval_dir, table, (eval_dir / "report.md").read_text())
    )
    return {
        "summary": summary,
        "expert_reached": spec.objects[reached].name if reached >= 0 else None,
        "report": out / "report.md",
    }


def demo_report_markdown(out: Path, policy: Path, eval_dir: Path, table: str, eval_report: str) -> str:
    """The demo's ``report.md`` in folder ``out``: a head naming the reference policy ``policy``, the
    attacks and the evaluation folder ``eval_dir`` (and its ``report.html``, the page to open), then
    the Table I layout ``table`` (:func:`table1_markdown`'s text, its title dropped for the page's own
    heading), then the evaluation's ``eval_report`` (its ``report.md``) as a section, its links made
    relative to ``out``. The 3D-vs-patch verdict is printed once on the whole page (:func:`verdicts_once`)."""
    rel = eval_dir.relative_to(out).as_posix()
    body = re.sub(r"\]\((?!http)([^)]+)\)", lambda m: f"]({rel}/{m.group(1)})", eval_report)
    body = body.replace("# Evaluation report", "## Evaluation", 1)
    page = f"{rel}/{REPORT_HTML}"
    head = [
        "# advobj demo: 3D adversarial object vs 2D patch",
        "",
        f"Reference policy `{policy.relative_to(out) if policy.is_relative_to(out) else policy}`, attacks in "
        "`attacks/`, "
        f"evaluation in `{rel}/`. Quick budget: this is a smoke-scale reproduction, "
        "not the paper's numbers.",
        "",
        "The evaluation's page, to open in a browser (paired tests, T-ASR by angle and distance with n on every bar, "
        f"the rollouts): [{page}]({page}).",
        "",
        "![scene](scene.png) ![expert](expert_rollout.gif)",
        "",
        "## Table I layout (by viewing angle)",
        "",
    ]
    return verdicts_once("\n".join(head) + table.split("\n", 2)[2] + "\n" + body)
