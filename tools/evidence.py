"""Run a paper recipe for the committed evidence and collect its raw data under ``results/``.

    .venv/bin/python tools/evidence.py run table1 --episodes 500 --policy runs/evidence/policy-quick

runs ``advobj experiment table1 --preset quick --episodes 500 --policy ... --out runs/evidence/table1``
(resumable: a re-run continues, and its time is added as another attempt), then copies what a
reader needs into ``results/table1/``: every evaluation's per-episode rows (``episodes.csv``,
with the evaluation's name in the first column), ``summary.json``, ``table.md``, the attack
textures and their training curves' figures (``attacks.json``), and ``run.json`` (the command,
commit, machine, wall and CPU time of every attempt, n). Checkpoints and policies stay in
``runs/``. ``collect`` redoes only the copy.

    .venv/bin/python tools/evidence.py retable table1 table2      # or --all; --check: exit 1 if stale

rebuilds ``results/<name>/table.md`` from the committed ``summary.json``, ``episodes.csv`` and
``attacks.json`` alone (report only: no run folder, nothing recomputed outside the recipe's own
printing, no other file written), with the config of the command ``run.json`` records; a recipe
whose table reads more than ``results/`` holds is refused in one line
(``trials.experiments.retable``).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import sys
from pathlib import Path

from typer._click.exceptions import ClickException

from attack.artifact import CONFIG_RECORD, TEXTURE_PNG, AttackArtifact
from sim.configs import copy_pool
from sim.errors import AdvobjError
from sim.policies.card import CARD_NAME, load_card
from sim.policies.pool import built_pool_path
from sim.runinfo import RunInfoError, read_run_info
from trials.cli.experiment import experiment_targets, parse_experiment
from trials.eval.episodes import collect_evals
from trials.experiments.recipes import RECIPES as REGISTRY
from trials.experiments.recipes import recipe_scene
from trials.experiments.record import (
    RECORD_NAME,
    attempt_machine,
    check_evidence,
    read_record,
    run_attempt,
    write_record,
)
from trials.experiments.retable import REPORT_ONLY, TABLE_NAME, RetableError, check_report_only, committed_table
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


def recorded_command(folder: Path) -> list[str]:
    """The ``advobj experiment`` command of the last successful attempt in ``folder/run.json`` (the
    one whose results were collected), split into words; one :class:`RetableError` line naming the
    file when there is none or it is not a recipe run."""
    path = folder / RECORD_NAME
    if not path.is_file():
        raise RetableError(f"{path}: missing; {folder} is not a recipe run collected by tools/evidence.py")
    try:
        attempts = [a for a in read_record(folder).get("attempts", []) if a.get("exit_code") == 0]
        argv = shlex.split(attempts[-1]["command"])
    except (IndexError, KeyError, TypeError, AttributeError, ValueError):
        raise RetableError(f"{path}: no successful attempt with a command") from None
    if argv[:2] != ["advobj", "experiment"] or len(argv) < 3 or argv[2] not in REGISTRY:
        raise RetableError(f"{path}: the command {' '.join(argv[:3])!r} is not an 'advobj experiment' recipe")
    return argv


def recorded_experiment(folder: Path) -> dict:
    """What the table in ``folder`` was made with: the recipe, config, policy, targets and scene of
    :func:`recorded_command`, parsed by ``advobj experiment``'s own options
    (:func:`trials.cli.experiment.parse_experiment`). One
    :class:`RetableError` line naming the file when it does not parse, or the folder when its
    recipe has no report-only path."""
    path = folder / RECORD_NAME
    argv = recorded_command(folder)
    recipe = argv[2]
    check_report_only(recipe, folder)  # before the options: a recipe with none is refused for that
    try:
        cfg, p = parse_experiment(recipe, argv[3:])
        targets = experiment_targets(p["target"])
    except ClickException as err:
        raise RetableError(f"{path}: the recorded command does not parse ({err.format_message()})") from None
    except AdvobjError as err:
        raise RetableError(f"{path}: the recorded command: {err}") from None
    return {
        "recipe": recipe,
        "cfg": cfg,
        "policy": p["policy"],
        "targets": targets,
        "scene": recipe_scene(recipe, p["scene"]),
    }


def retable_text(folder: Path) -> str:
    """The ``table.md`` the recipe of ``folder`` writes now for its committed results."""
    return committed_table(folder, **recorded_experiment(folder))


def report_only_folders(results: Path) -> list[str]:
    """The folders under ``results`` holding a table and the record of a recipe run with a
    report-only path (other folders: another tool's results, or a recipe with none)."""
    names = []
    for d in sorted(p for p in results.iterdir() if (p / RECORD_NAME).is_file() and (p / TABLE_NAME).is_file()):
        try:
            recipe = recorded_command(d)[2]
        except RetableError:
            continue
        if recipe in REPORT_ONLY:
            names.append(d.name)
    return names


def retable(names: list[str], results: Path, check: bool) -> int:
    """Rebuild (or with ``check``, compare) ``results/<name>/table.md`` of every name; only that
    file is written. 0: done (or all current), 1: ``check`` found a stale table, 2: refused (one
    ``evidence: ...`` line on stderr, nothing written)."""
    try:
        texts = {name: retable_text(results / name) for name in names}
    except RetableError as err:
        print(f"evidence: {err}", file=sys.stderr)
        return 2
    stale = []
    for name, text in texts.items():
        path = results / name / TABLE_NAME
        current = path.is_file() and path.read_text() == text
        if not current:
            stale.append(name)
            if not check:
                path.write_text(text)
        print(f"{path}: {'current' if current else 'stale' if check else 'rewritten'}")
    return 1 if check and stale else 0


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
    t = sub.add_parser("retable", help="rebuild results/<name>/table.md from its committed data (report only)")
    t.add_argument("names", nargs="*", help="results folders, e.g. table1")
    t.add_argument("--all", action="store_true", help="every results folder whose recipe has a report-only path")
    t.add_argument("--check", action="store_true", help="write nothing; exit 1 if a table is not what it would be")
    t.add_argument("--results", type=Path, default=ROOT / "results")
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1 :] if "--" in argv else []
    a = ap.parse_args(argv[: argv.index("--")] if "--" in argv else argv)
    a.extra = extra
    if a.cmd == "card":
        print(card(a.policy_dir, a.results, a.command))
        return 0
    if a.cmd == "retable":
        if bool(a.names) == a.all:
            ap.error("retable: give results folder names or --all")
        return retable(report_only_folders(a.results) if a.all else a.names, a.results, a.check)
    if a.cmd == "run":
        return run(a.recipe, a.episodes, a.policy, a.work, a.results, a.extra, a.name)
    collect(a.name, a.work, a.results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
