"""The same attack through every format a policy ships in: its checkpoint, its ``.onnx``, its ``.pt2``.

A checkpoint policy is exported to ``.onnx`` and ``.pt2`` by ``advobj policy export`` (which checks
each file against the checkpoint), and ``advobj attack run`` is run on each of the three, as a user
would, with the same preset, overrides, scene and task-feasible pool (the checkpoint's), so the
same attack seed and configurations. Each texture is compared with the checkpoint's (largest
absolute difference, in [0, 1] and in 8-bit levels) and evaluated on the checkpoint policy on one
fixed set of held-out configurations (the first ``--episodes`` evaluation-part configurations of
the checkpoint's pool, topped up with clean rollouts where it holds fewer), so the three
evaluations are paired: each file's T-ASR is tested against the checkpoint's with McNemar's exact
test. The issue's criterion (issue 27) holds for a file when its texture agrees with the
checkpoint's within :data:`TEXTURE_ATOL`, or else when its held-out T-ASR is not different
(p >= :data:`ALPHA`). Each attack's wall and CPU time (the whole command, and the attack loop per
iteration from its ``metrics.json``) is reported with its ratio to the checkpoint's.

The work is a grid of jobs (:mod:`trials.jobs.dag`, run serially with a progress line and an ETA):
``export``, ``attack-<format>`` (each ``advobj attack run`` in a child process, timed), ``eval-set``
and ``eval-<format>``; a re-run resumes what is finished. The committed evidence
(``results/formats/``) comes from::

    python -m trials.experiments.formats evidence --policy runs/evidence/policy-quick \\
        --out runs/evidence/formats --episodes 300
    python -m trials.experiments.formats collect --out runs/evidence/formats   # the copy only

``evidence`` refuses a checkout with uncommitted changes and fewer than 300 episodes, runs ``run``
(the same options) as a child process, records the attempt in ``results/formats/run.json``
(:func:`trials.experiments.record.run_attempt`: command, commit, machine, wall and CPU time, exit
code) and then :func:`collect`: ``episodes.csv`` (every evaluation's episodes, its format in the
first column ``eval``), ``summary.json`` (the figures above, computed from that CSV and the
textures, plus each evaluation's own summary), ``eval_set.json`` (the fixed configurations),
``textures/<format>/`` (texture folders: ``texture.npy``, ``texture.png``, ``run.json``),
``attack_configs/<format>.json`` (the configurations each attack used), ``export.json`` (the
export's own check) and ``run.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from pydantic import Field, ValidationError

from attack.artifact import CONFIG_RECORD, AttackArtifact, texture_to_uint8
from attack.optimize import PRESETS, resolve_config
from sim.configio import StrictModel, file_error, read_yaml
from sim.configs import copy_pool, load_pool
from sim.errors import AdvobjError, format_validation_error
from sim.policies.checkpoint import load_checkpoint
from sim.policies.pool import feasible_pool_path
from sim.runinfo import read_run_info
from sim.spec import load_spec
from sim.stats import proportion
from trials.eval.episodes import collect_evals, has_summary, read_collected, read_rows, write_summary
from trials.eval.evaluate import load_eval_config, run_eval
from trials.eval.metrics import mcnemar_exact
from trials.experiments.record import check_evidence, read_record, run_attempt, write_record
from trials.experiments.tradeoff import TradeoffConfig, build_eval_set, eval_set_path
from trials.experiments.tradeoff_report import attack_outcomes
from trials.jobs.dag import Grid, SerialExecutor, read_markers

__all__ = [
    "FORMATS",
    "TEXTURE_ATOL",
    "ALPHA",
    "FormatsError",
    "FormatsConfig",
    "load_formats_config",
    "build_grid",
    "run_formats",
    "summarize",
    "collect",
    "evidence",
    "main",
]

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "results" / "formats"
#: The formats, the reference (the checkpoint) first; a file format's file as export writes it.
FORMATS = ("checkpoint", "onnx", "pt2")
FILES = {"onnx": "policy.onnx", "pt2": "policy.pt2"}
#: Texture values are in [0, 1]: 1e-4 is a fortieth of one 8-bit level (and what
#: tests/trials/cli/test_policy_files_cli.py asks of a short attack through the three formats).
TEXTURE_ATOL = 1e-4
ALPHA = 0.05
SETTINGS_NAME = "formats.json"  # the run's settings in --out; a re-run must give the same
EVIDENCE_MIN_EPISODES = 300


class FormatsError(AdvobjError, ValueError):
    """Bad settings, a folder holding another run, or a step of the run that failed (one line)."""


class FormatsConfig(StrictModel):
    """What the comparison runs (written to ``<out>/formats.json``); paths are absolute."""

    policy: str = Field(description="the checkpoint directory (the reference format)")
    episodes: int = Field(300, ge=1, description="held-out configurations each texture is evaluated on (paired)")
    preset: str = Field("quick", description="attack preset (advobj attack run --preset)")
    attack_config: str | None = Field(None, description="YAML of attack fields over the preset (--config)")
    pool: str | None = Field(None, description="task-feasible pool (default: the checkpoint's feasible_pool.json)")
    scene: str | None = Field(None, description="scene YAML (default: the built-in scene)")
    eval_num_envs: int = Field(8, ge=1, description="episodes rolled out in parallel in the evaluations")
    seed: int = Field(0, ge=0, description="first candidate seed when the fixed set needs more configurations")


def _abs(path, flag: str, kind: str) -> str:
    p = Path(path).resolve()
    if not (p.is_dir() if kind == "dir" else p.is_file()):
        raise FormatsError(f"{flag}: {path}: no such {'folder' if kind == 'dir' else 'file'}")
    return str(p)


def load_formats_config(
    policy, episodes: int = 300, attack_config=None, pool=None, scene=None, **fields
) -> FormatsConfig:
    """A validated config: the checkpoint loads, the pool, scene and attack overrides exist and
    read (one line naming the flag otherwise), paths made absolute."""
    try:
        load_checkpoint(policy)
    except AdvobjError as err:
        raise FormatsError(f"--policy: {err}") from None
    pool = pool if pool is not None else feasible_pool_path(Path(policy))
    if not Path(pool).is_file():
        raise FormatsError(f"--pool: {pool}: no pool file (run 'advobj policy eval' on the checkpoint, or give --pool)")
    spec = load_spec(None if scene is None else _abs(scene, "--scene", "file"))  # a SpecError names file and field
    try:
        load_pool(pool, spec)
    except AdvobjError as err:
        raise FormatsError(f"--pool: {err}") from None
    try:
        cfg = FormatsConfig(
            policy=_abs(policy, "--policy", "dir"),
            episodes=episodes,
            attack_config=None if attack_config is None else _abs(attack_config, "--config", "file"),
            pool=_abs(pool, "--pool", "file"),
            scene=None if scene is None else _abs(scene, "--scene", "file"),
            **fields,
        )
    except ValidationError as err:
        raise FormatsError(format_validation_error(err, "formats config")) from None
    if cfg.preset not in PRESETS:
        raise FormatsError(f"--preset: unknown preset {cfg.preset!r}; choose one of {', '.join(sorted(PRESETS))}")
    overrides = {}
    if cfg.attack_config is not None:
        overrides = read_yaml(cfg.attack_config, "attack config", error=file_error(FormatsError), mapping=False) or {}
        if not isinstance(overrides, dict):
            raise FormatsError(f"--config: {attack_config}: an attack config must be a mapping of fields")
    try:
        resolve_config(cfg.preset, overrides, source=str(cfg.attack_config or "<preset>"))
    except AdvobjError as err:
        raise FormatsError(f"--config: {err}") from None
    return cfg


# ----------------------------------------------------------------------------- the jobs
def _advobj(argv: list[str], capture: bool = False) -> dict:
    """Run ``advobj ARGV`` (this checkout's command line) as a child process; its command as a user
    types it, exit code, wall time, CPU time (it and its children) and, with ``capture``, its
    output lines. A non-zero exit is a :class:`FormatsError` naming the command."""
    exe = Path(sys.executable).with_name("advobj")
    cmd = [str(exe)] if exe.is_file() else [sys.executable, "-m", "trials.cli.main"]
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd + argv, cwd=ROOT, env=env, capture_output=capture, text=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = {
        "command": "advobj " + shlex.join(argv),
        "exit_code": proc.returncode,
        "wall_s": time.perf_counter() - t0,
        "cpu_s": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
    }
    if capture:
        done["stdout"] = proc.stdout.splitlines()
    if proc.returncode != 0:
        last = (proc.stderr or "").strip().splitlines()[-1:] if capture else []
        raise FormatsError(f"{done['command']} exited with code {proc.returncode}" + (f": {last[0]}" if last else ""))
    return done


def job_export(out: Path, inputs: dict) -> None:
    """The ``formats-export`` job: ``advobj policy export`` of the checkpoint to both files (checked)."""
    done = _advobj(
        [
            "policy",
            "export",
            str(inputs["policy"]),
            "--onnx",
            str(out / FILES["onnx"]),
            "--pt2",
            str(out / FILES["pt2"]),
        ],
        capture=True,
    )
    (out / "export.json").write_text(json.dumps(done, indent=1))


def job_attack(out: Path, inputs: dict, fmt: str, preset: str) -> None:
    """The ``formats-attack`` job: ``advobj attack run`` through format ``fmt`` into ``out``, timed
    (``timing.json``: the command's wall and CPU time, the attack loop's from ``metrics.json``)."""
    policy = inputs["policy"] if fmt == "checkpoint" else inputs["export"] / FILES[fmt]
    argv = ["attack", "run", "--policy", str(policy), "--preset", preset, "--pool", str(inputs["pool"])]
    for flag, role in (("--config", "config"), ("--scene", "scene")):
        if role in inputs:
            argv += [flag, str(inputs[role])]
    done = _advobj(argv + ["--out", str(out)])
    m = json.loads((out / "metrics.json").read_text())
    done.update(
        iterations=m["iterations"],
        loop_s=m["seconds"],
        seconds_per_iteration=m["seconds_per_iteration"],
        seconds_per_iteration_training=m["seconds_per_iteration_training"],
    )
    (out / "timing.json").write_text(json.dumps(done, indent=1))


def job_eval_set(out: Path, inputs: dict, episodes: int, num_envs: int, seed: int) -> None:
    """The ``formats-eval-set`` job: the fixed held-out set, as the tradeoff sweep builds its own
    (the first ``episodes`` evaluation-part configurations of the pool, topped up with clean
    rollouts of the checkpoint where it holds fewer; :func:`trials.experiments.tradeoff.build_eval_set`)."""
    scene = str(inputs["scene"]) if "scene" in inputs else None
    spec = load_spec(scene)
    cfg = TradeoffConfig(
        policy=str(inputs["policy"]),
        pool=str(inputs["pool"]),
        scene=scene,
        episodes=episodes,
        big_episodes=episodes,
        max_steps=spec.episode.max_steps,  # the scene's own: the pool was made for it
        eval_num_envs=num_envs,
        seed=seed,
    )
    build_eval_set(cfg, "ref", out, spec)


def job_eval(out: Path, inputs: dict, episodes: int, num_envs: int) -> None:
    """The ``formats-eval`` job: the texture of ``inputs["attack"]`` on the checkpoint policy, on the
    fixed set (every format's evaluation on the same configurations: paired)."""
    scene = str(inputs["scene"]) if "scene" in inputs else None
    cfg = load_eval_config(
        policy=str(inputs["policy"]),
        conditions=("attack",),
        episodes=episodes,
        max_steps=load_spec(scene).episode.max_steps,
        num_envs=num_envs,
        pool=str(eval_set_path(inputs["eval_set"], "ref")),
        scene=scene,
        gifs=0,
        attack=str(inputs["attack"]),
    )
    run_eval(cfg, out, resume=True, progress=True, report=False)


def build_grid(cfg: FormatsConfig, out: str | Path) -> tuple[Grid, dict]:
    """The run's jobs into ``out``: export, an attack per format, the fixed set, an evaluation per
    format. Returns the grid and its jobs by name."""
    out = Path(out)
    grid = Grid(out)
    fn = MODULE + ":job_"
    shared = {"pool": cfg.pool, "scene": cfg.scene}
    jobs = {"export": grid.add("export", "formats-export", fn + "export", out / "export", {}, {"policy": cfg.policy})}
    for fmt in FORMATS:
        src = {"policy": cfg.policy} if fmt == "checkpoint" else {"export": jobs["export"]}
        jobs[f"attack-{fmt}"] = grid.add(
            f"attack-{fmt}",
            "formats-attack",
            fn + "attack",
            out / "attacks" / fmt,
            {"fmt": fmt, "preset": cfg.preset},
            {**src, **shared, "config": cfg.attack_config},
        )
    jobs["eval-set"] = grid.add(
        "eval-set",
        "formats-eval-set",
        fn + "eval_set",
        out / "eval_set",
        {"episodes": cfg.episodes, "num_envs": cfg.eval_num_envs, "seed": cfg.seed},
        {"policy": cfg.policy, **shared},
    )
    for fmt in FORMATS:
        jobs[f"eval-{fmt}"] = grid.add(
            f"eval-{fmt}",
            "formats-eval",
            fn + "eval",
            out / "evals" / fmt,
            {"episodes": cfg.episodes, "num_envs": cfg.eval_num_envs},
            {"policy": cfg.policy, "scene": cfg.scene, "attack": jobs[f"attack-{fmt}"], "eval_set": jobs["eval-set"]},
        )
    return grid, jobs


def run_formats(cfg: FormatsConfig, out: str | Path, log=print, progress: bool = True) -> Path:
    """Run (or resume) the comparison into ``out``; returns ``out``."""
    out = Path(out)
    settings = cfg.model_dump(mode="json")
    path = out / SETTINGS_NAME
    if path.is_file() and json.loads(path.read_text()) != settings:
        raise FormatsError(f"{out}: holds a run with other settings ({path}); use another --out")
    out.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(settings, indent=1))
    grid, _ = build_grid(cfg, out)
    SerialExecutor(log, tee=progress).run(grid)
    return out


# ----------------------------------------------------------------------------- the figures
def _ratio(x, ref):
    return None if x is None or not ref else x / ref


def texture_difference(texture, reference) -> dict:
    """How far ``texture`` is from ``reference`` (both ``(H, W, 3)`` in [0, 1]): the largest and the
    mean absolute difference, the largest in 8-bit levels (as printed), the share of texels whose
    8-bit value differs, and whether they agree within :data:`TEXTURE_ATOL`."""
    a, b = np.asarray(texture, np.float64), np.asarray(reference, np.float64)
    if a.shape != b.shape:
        raise FormatsError(f"textures of different shapes: {a.shape} vs {b.shape}")
    d = np.abs(a - b)
    levels = np.abs(texture_to_uint8(a).astype(np.int16) - texture_to_uint8(b).astype(np.int16))
    return {
        "max_abs": float(d.max()),
        "mean_abs": float(d.mean()),
        "max_levels_8bit": int(levels.max()),
        "texels_differing_8bit": float((levels.max(axis=-1) > 0).mean()),
        "agrees": bool(d.max() <= TEXTURE_ATOL),
    }


def summarize(results: str | Path) -> dict:
    """The figures of a collected folder, from its ``episodes.csv``, ``textures/`` and ``timing``:
    T-ASR per format (Wilson 95%), each file format vs the checkpoint (paired McNemar, T-ASR
    difference, texture difference, the issue's criterion) and the attack's cost ratios."""
    results = Path(results)
    outcomes = attack_outcomes(read_rows(results))  # format -> configuration seed -> targeted
    timing = json.loads((results / "timing.json").read_text())
    textures = {f: AttackArtifact.load(results / "textures" / f, error=FormatsError).texture for f in FORMATS}
    ref, ref_time = outcomes["checkpoint"], timing["checkpoint"]
    out = {}
    for fmt in FORMATS:
        got, t = outcomes[fmt], timing[fmt]
        tasr = proportion(sum(got.values()), len(got))
        row = {
            "tasr": tasr.to_dict(),
            "attack": t,
            "ratio_to_checkpoint": {
                "wall": _ratio(t["wall_s"], ref_time["wall_s"]),
                "cpu": _ratio(t["cpu_s"], ref_time["cpu_s"]),
                "per_iteration": _ratio(t["seconds_per_iteration"], ref_time["seconds_per_iteration"]),
                "per_iteration_training": _ratio(
                    t["seconds_per_iteration_training"], ref_time["seconds_per_iteration_training"]
                ),
            },
        }
        if fmt != "checkpoint":
            if set(got) != set(ref):
                raise FormatsError(f"{results}: the {fmt} evaluation is not on the checkpoint's configurations")
            seeds = sorted(ref)
            b = sum(ref[s] and not got[s] for s in seeds)
            c = sum(got[s] and not ref[s] for s in seeds)
            test = mcnemar_exact(b, c, len(seeds))
            tex = texture_difference(textures[fmt], textures["checkpoint"])
            row.update(
                texture_vs_checkpoint=tex,
                mcnemar_vs_checkpoint=test.to_dict(),
                tasr_difference_pp=100.0 * (c - b) / len(seeds),
                criterion=(
                    "texture agrees"
                    if tex["agrees"]
                    else ("T-ASR not different" if test.p_value >= ALPHA else "T-ASR different")
                ),
            )
        out[fmt] = row
    return out


# ----------------------------------------------------------------------------- the committed evidence
def _shown(path) -> str:
    """``path`` as a committed record names it: relative to the checkout, else ``<outside the checkout>/<name>``."""
    p = Path(path).resolve()
    try:
        return p.relative_to(ROOT).as_posix()
    except ValueError:
        return f"<outside the checkout>/{p.name}"


def _portable(obj, out: Path, cfg: dict):
    """``obj`` with no machine path: the run folder and the run's inputs as :func:`_shown` names
    them, anything else under the checkout relative to it."""
    text = json.dumps(obj, default=str)
    paths = [str(Path(out).resolve())] + [cfg[k] for k in ("policy", "pool", "scene", "attack_config") if cfg.get(k)]
    for s in sorted(paths, key=len, reverse=True):
        text = text.replace(json.dumps(s)[1:-1], json.dumps(_shown(s))[1:-1])
    return json.loads(text.replace(json.dumps(str(ROOT) + os.sep)[1:-1], ""))


#: This module's name for ``python -m`` (``__name__`` is ``"__main__"`` when it is run that way).
MODULE = "trials.experiments.formats"


def _write_json(path: Path, doc) -> None:
    path.write_text(json.dumps(doc, indent=1) + "\n")


def collect(out: str | Path, results: str | Path = RESULTS) -> Path:
    """Copy what a reader needs of the finished run in ``out`` into ``results`` and compute its
    figures there (:func:`summarize`, from the copied CSV and textures); returns ``results``."""
    out, dst = Path(out), Path(results)
    if not (out / SETTINGS_NAME).is_file():
        raise FormatsError(f"{out}: no run of this module to collect ({SETTINGS_NAME} missing)")
    cfg = json.loads((out / SETTINGS_NAME).read_text())
    evals = [out / "evals" / f for f in FORMATS]
    missing = [f for f, d in zip(FORMATS, evals) if not has_summary(d)]
    if missing:
        raise FormatsError(f"{out}: the evaluation of {', '.join(missing)} is not finished; run it first")
    dst.mkdir(parents=True, exist_ok=True)
    for sub in ("textures", "attack_configs"):
        if (dst / sub).exists():
            shutil.rmtree(dst / sub)
    n_rows = collect_evals(dst, evals)
    evaluations = _portable(read_collected(dst), out, cfg)
    timing = {}
    for fmt in FORMATS:
        a = out / "attacks" / fmt
        art = AttackArtifact.load(a, error=FormatsError)
        AttackArtifact(art.texture, {"attack": art.attack_config}, art.seed).save(dst / "textures" / fmt)
        (dst / "attack_configs").mkdir(exist_ok=True)
        shutil.copyfile(a / CONFIG_RECORD, dst / "attack_configs" / f"{fmt}.json")
        timing[fmt] = _portable(json.loads((a / "timing.json").read_text()), out, cfg)
    _write_json(dst / "timing.json", timing)
    copy_pool(eval_set_path(out / "eval_set", "ref"), dst / "eval_set.json", meta=lambda m: _portable(m, out, cfg))
    _write_json(dst / "export.json", _portable(json.loads((out / "export" / "export.json").read_text()), out, cfg))
    records = {f: json.loads((dst / "attack_configs" / f"{f}.json").read_text()) for f in FORMATS}
    attack_cfgs = {f: AttackArtifact.load(dst / "textures" / f).attack_config for f in FORMATS}
    summary = {
        "settings": _portable(cfg, out, cfg),
        "texture_atol": TEXTURE_ATOL,
        "alpha": ALPHA,
        "episodes": {f: evaluations[f]["conditions"]["attack"]["n"] for f in FORMATS},
        "same_attack_config": all(attack_cfgs[f] == attack_cfgs["checkpoint"] for f in FORMATS),
        "same_attack_configurations": all(records[f] == records["checkpoint"] for f in FORMATS),
        "formats": summarize(dst),
        "evaluations": evaluations,
    }
    write_summary(dst, summary)  # the collection's summary.json, now with the comparison
    record = read_record(dst)
    markers = [m for m in read_markers(out) if str(m.get("kind", "")).startswith("formats-")]
    record.update(
        episodes_rows=n_rows,
        jobs_wall_s=round(sum(m.get("seconds", 0.0) for m in markers), 1),
        jobs_cpu_s=round(sum(m.get("cpu_s", 0.0) for m in markers), 1),
        attack_commits=sorted({str(read_run_info(out / "attacks" / f)["git_commit"]) for f in FORMATS}),
    )
    write_record(dst, record)
    return dst


def evidence(
    argv: list[str], results: str | Path = RESULTS, log=print, min_episodes: int = EVIDENCE_MIN_EPISODES
) -> int:
    """Run ``python -m trials.experiments.formats run <argv>`` for the committed evidence, record the
    attempt in ``results/run.json`` (:func:`trials.experiments.record.run_attempt`) and, when it
    succeeds, :func:`collect` it. Refused in one line (exit 2, nothing run or written): a checkout
    with uncommitted changes, fewer than ``min_episodes`` episodes, bad input (as ``run`` refuses
    it). A re-run resumes the run; its time is added as another attempt."""
    a = _run_parser(argparse.ArgumentParser(prog="evidence", add_help=False)).parse_args(argv)
    problems = []
    if a.episodes < min_episodes:
        problems.append(f"--episodes {a.episodes} < {min_episodes}")
    commit, refused = check_evidence(problems)
    if refused:
        return refused
    _config(a)  # bad input: one line now, before an attempt is recorded
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    attempt = run_attempt(
        results,
        [sys.executable, "-m", MODULE, "run", *_run_argv(a, str)],  # the child runs in the checkout
        f"python -m {MODULE} run " + shlex.join(_run_argv(a, _shown)),
        commit,
        cwd=ROOT,
        env=env,
    )
    if attempt["exit_code"] == 0:
        log(f"collected into {collect(a.out, results)}")
    return attempt["exit_code"]


# ----------------------------------------------------------------------------- command line
PATH_FLAGS = ("policy", "out", "config", "pool", "scene")


def _run_parser(ap: argparse.ArgumentParser) -> argparse.ArgumentParser:
    ap.add_argument("--policy", type=Path, required=True, help="checkpoint directory (exported to .onnx and .pt2)")
    ap.add_argument("--out", type=Path, required=True, help="run directory (resumable)")
    ap.add_argument("--episodes", type=int, default=300, help="held-out configurations per texture (default 300)")
    ap.add_argument("--preset", default="quick", help="attack preset (default quick)")
    ap.add_argument("--config", type=Path, default=None, help="YAML of attack fields over the preset")
    ap.add_argument("--pool", type=Path, default=None, help="task-feasible pool (default: the checkpoint's)")
    ap.add_argument("--scene", type=Path, default=None, help="scene YAML (default: the built-in scene)")
    ap.add_argument("--num-envs", type=int, default=8, help="episodes rolled out in parallel in the evaluations")
    return ap


def _run_argv(a: argparse.Namespace, path=str) -> list[str]:
    """The ``run`` options of ``a``, each path through ``path`` (absolute for a child process in the
    checkout, :func:`_shown` for the record)."""
    argv = []
    for name in ("policy", "out", "episodes", "preset", "config", "pool", "scene", "num_envs"):
        v = getattr(a, name)
        if v is not None:
            argv += ["--" + name.replace("_", "-"), path(Path(v).resolve()) if name in PATH_FLAGS else str(v)]
    return argv


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog=f"python -m {MODULE}",
        description="The same attack through the checkpoint, its .onnx and its .pt2; evidence under results/formats/.",
    )
    sub = ap.add_subparsers(dest="cmd", required=True)
    _run_parser(sub.add_parser("run", help="export, attack through each format, evaluate (resumable)"))
    ev = _run_parser(sub.add_parser("evidence", help="run from a clean checkout, record the attempt, collect"))
    ev.add_argument("--results", type=Path, default=RESULTS, help="where the evidence goes (default results/formats)")
    c = sub.add_parser("collect", help="copy a finished run into results/formats/ (what gets committed)")
    c.add_argument("--out", type=Path, required=True, help="the run directory")
    c.add_argument("--results", type=Path, default=RESULTS, help="default results/formats")
    return ap


def _config(a: argparse.Namespace) -> FormatsConfig:
    return load_formats_config(
        a.policy, a.episodes, a.config, a.pool, a.scene, preset=a.preset, eval_num_envs=a.num_envs
    )


def main(argv: list[str] | None = None) -> int:
    a = parser().parse_args(list(sys.argv[1:] if argv is None else argv))
    try:
        if a.cmd == "run":
            run_formats(_config(a), a.out)
        elif a.cmd == "evidence":
            return evidence(_run_argv(a), a.results)
        else:
            print(collect(a.out, a.results))
    except AdvobjError as err:
        print(f"error: {' '.join(str(err).split())}", file=sys.stderr)
        return getattr(err, "exit_code", None) or 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
