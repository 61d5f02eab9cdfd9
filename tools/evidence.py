"""Run a paper recipe for the committed evidence and collect its raw data under ``results/``.

    .venv/bin/python tools/evidence.py run table1 --episodes 500 --policy runs/evidence/policy-quick

runs ``advobj experiment table1 --preset quick --episodes 500 --policy ... --out runs/evidence/table1``
(resumable: a re-run continues, and its time is added as another attempt), then copies what a
reader needs into ``results/table1/``: every evaluation's per-episode rows (``episodes.csv``,
with the evaluation's name in the first column), ``summary.json``, ``table.md``, the attack
textures and their training curves' figures (``attacks.json``), and ``run.json`` (the command,
commit, machine, wall and CPU time of every attempt, n). Checkpoints and policies stay in
``runs/``. ``collect`` redoes only the copy.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

from attack.artifact import CONFIG_RECORD, TEXTURE_PNG, AttackArtifact
from sim.configs import copy_pool
from sim.policies.card import CARD_NAME, load_card
from sim.policies.pool import built_pool_path
from sim.runinfo import RunInfoError, read_run_info
from trials.eval.episodes import collect_evals
from trials.experiments.recipes import RECIPES as REGISTRY
from trials.experiments.record import attempt_machine, check_evidence, read_record, run_attempt, write_record
from trials.jobs.dag import read_markers

ROOT = Path(__file__).resolve().parent.parent
RECIPES = tuple(REGISTRY)  # the one list (trials.experiments.recipes.RECIPES)


def run(
    recipe: str, episodes: int, policy: str | None, work: Path, results: Path, extra: list[str], name: str | None = None
) -> int:
    name = name or recipe
    commit, refused = check_evidence([])
    if refused:
        return refused
    out = work / name
    # Paths relative to the checkout, so the recorded command is the one a reader types there.
    cmd = [
        str(ROOT / ".venv" / "bin" / "advobj"),
        "experiment",
        recipe,
        "--preset",
        "quick",
        "--episodes",
        str(episodes),
        "--out",
        os.path.relpath(out, ROOT),
    ]
    if policy:
        cmd += ["--policy", policy]
    scene = REGISTRY[recipe].scene  # a recipe's own scene goes on the recorded command, unless given there
    if scene is not None and not any(a == "--scene" or a.startswith("--scene=") for a in extra):
        cmd += ["--scene", scene]
    cmd += extra
    rc = run_attempt(results / name, cmd, " ".join(["advobj"] + cmd[1:]), commit, cwd=ROOT)["exit_code"]
    if rc == 0:
        collect(name, work, results)
    return rc


def _portable(path: str) -> str:
    """``path`` relative to the checkout (no machine path goes into results/); outside it, its name."""
    p = Path(path)
    try:
        return str(p.resolve().relative_to(ROOT))
    except ValueError:
        return f"<outside the checkout>/{p.name}"


def collect(name: str, work: Path, results: Path) -> Path:
    """Copy the finished run ``work/<name>`` into ``results/<name>``."""
    src, dst = work / name, results / name
    dst.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src / "table.md", dst / "table.md")
    n_rows = collect_evals(dst, sorted((src / "evals").iterdir()), relative_to=ROOT)
    attacks = {}
    (dst / "textures").mkdir(exist_ok=True)
    for at in sorted((src / "attacks").iterdir()):
        if not (at / "metrics.json").is_file():
            continue
        m = json.loads((at / "metrics.json").read_text())
        cfg = AttackArtifact.load(at).attack_config
        attacks[at.name] = {
            "config": cfg,
            "iterations": m["iterations"],
            "seconds": m["seconds"],
            "validation": m.get("validation"),
            "initial_loss_pose": m.get("initial_loss_pose"),
            "final_loss_pose": m.get("final_loss_pose"),
        }
        shutil.copyfile(at / TEXTURE_PNG, dst / "textures" / f"{at.name}.png")
    (dst / "attacks.json").write_text(json.dumps(attacks, indent=1))
    # What the held-out claim rests on: the evaluation pools and every attack's configuration record.
    for at in sorted((src / "attacks").iterdir()):
        if (at / CONFIG_RECORD).is_file():
            (dst / "attack_configs").mkdir(exist_ok=True)
            shutil.copyfile(at / CONFIG_RECORD, dst / "attack_configs" / f"{at.name}.json")
    for job in sorted((src / "pools").iterdir()) if (src / "pools").is_dir() else []:
        if built_pool_path(job).is_file():
            copy_pool(
                built_pool_path(job),
                dst / "pools" / f"{job.name}.json",
                meta=lambda m: {
                    k: _portable(v) if k in ("policy", "base") and isinstance(v, str) else v for k, v in m.items()
                },
            )
    policies = {}
    for card_path in sorted(src.glob(f"policies/*/{CARD_NAME}")):
        clean = load_card(card_path).clean_success
        policies[card_path.parent.name] = None if clean is None else clean.model_dump(mode="json")
    record = read_record(dst)
    record["episodes_rows"] = n_rows
    # Jobs that ran on Ray workers are not this process's children: their CPU time is in their finished markers.
    record["jobs_cpu_s"] = round(sum(m.get("cpu_s", 0.0) for m in read_markers(src)), 1)
    record["trained_policies_clean_success"] = policies
    write_record(dst, record)
    return dst


def card(policy_dir: Path, results: Path, command: str) -> Path:
    """Copy a trained policy's card (``policy.json``: config, training time, clean success with
    its interval; no weights) to ``results/policies/<name>.json`` with the command that trained it
    and the commit its run record names."""
    doc = load_card(policy_dir).model_dump(mode="json")
    doc["command"] = command
    try:  # the commit the training ran at, from the run's own record
        doc["commit"] = read_run_info(policy_dir).get("git_commit")
    except RunInfoError:
        doc["commit"] = None
    doc["machine"] = attempt_machine()
    dst = results / "policies" / f"{Path(policy_dir).name}.json"
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_text(json.dumps(doc, indent=1))
    return dst


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("recipe", choices=RECIPES)
    r.add_argument("--episodes", type=int, default=500)
    r.add_argument("--policy")
    r.add_argument("--name", help="run and results folder name (default: the recipe's), e.g. table2-40 for a variant")
    r.add_argument("--work", type=Path, default=Path("runs") / "evidence")
    r.add_argument("--results", type=Path, default=ROOT / "results")
    # More arguments for the recipe go after "--" (split off before parsing: argparse would read them as its own).
    c = sub.add_parser("collect")
    c.add_argument("name", help="run folder under --work")
    c.add_argument("--work", type=Path, default=ROOT / "runs" / "evidence")
    c.add_argument("--results", type=Path, default=ROOT / "results")
    k = sub.add_parser("card", help="copy a trained policy's card into results/policies/")
    k.add_argument("policy_dir", type=Path)
    k.add_argument("--command", required=True, help="the command that trained it")
    k.add_argument("--results", type=Path, default=ROOT / "results")
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1 :] if "--" in argv else []
    a = ap.parse_args(argv[: argv.index("--")] if "--" in argv else argv)
    a.extra = extra
    if a.cmd == "card":
        print(card(a.policy_dir, a.results, a.command))
        return 0
    if a.cmd == "run":
        return run(a.recipe, a.episodes, a.policy, a.work, a.results, a.extra, a.name)
    collect(a.name, a.work, a.results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
