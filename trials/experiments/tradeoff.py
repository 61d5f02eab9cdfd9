"""Speed vs accuracy: one-knob-at-a-time sweep of the attack, evaluation and deployment knobs.

The sweep is data (:func:`build_rows`): a baseline (the ``quick`` attack preset on the given
policy) and variants that change one knob each. Every attack row is measured the same way:

1. the attack runs in-process (:class:`attack.optimize.AttackRun`, ``step()`` by ``step()``),
   sampling its EOT configurations from the attack part of the policy's task-feasible pool
   (:func:`sim.configs.config_part`; at least 20 are required);
2. its texture is evaluated with :func:`trials.eval.evaluate.run_eval` (paired clean/attack arms) on
   one fixed evaluation set per policy: the first ``episodes`` evaluation-part configurations of its pool,
   written once to ``<out>/eval_sets/<policy>.json`` and reused by every row of that policy.

The ``iterations`` rows cost nothing extra: the baseline run snapshots its texture at
``snapshots`` (e.g. 30 and 60 of 120) and these rows only evaluate the snapshots, charging the
attack time the baseline had spent at that iteration. ``eval_episodes`` evaluates the baseline
texture on a larger feasible set (built by ``run_eval``), with the first ``episodes`` of it
summarised too, so the interval widths come from one run. ``deployment`` rows time the policy
forward (torch fp32, ONNX fp32, ONNX int8 dynamic quantisation, ONNX fp16) and compare its
actions with torch fp32 on rendered frames.

Each row runs in a child process (peak RSS per row; a crash only loses that row) and is appended
as one JSON line to ``<out>/rows.jsonl`` when it finishes; a re-run skips rows already there with
``status == "ok"`` (the settings must match ``<out>/sweep.json``). Each row is a ``tradeoff-row``
job of :mod:`trials.jobs.dag` in ``<out>/rows/<row>/``; its child process reads its spec from
``<out>/jobs/<row>/row.json``.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy
import numpy as np
import onnx
import onnxruntime
import torch
from onnxruntime.quantization import QuantType, quantize_dynamic
from onnxruntime.transformers.float16 import convert_float_to_float16
from pydantic import Field, ValidationError

from attack.artifact import TEXTURE_NPY, AttackArtifact, write_config_record
from attack.optimize import AttackRun, resolve_config, run_attack
from sim.configio import StrictModel
from sim.configs import in_part, load_pool, save_pool
from sim.errors import AdvobjError, format_validation_error
from sim.policies.card import load_card
from sim.policies.checkpoint import is_checkpoint, load_checkpoint
from sim.policies.onnx_policy import OnnxPolicy, export_onnx
from sim.policies.pool import feasible_pool_path
from sim.policies.presets import resolve_preset
from sim.policies.train import train_policy
from sim.runinfo import git_commit, read_run_info, write_run_info
from sim.runtime import set_torch_threads
from sim.spec import load_spec
from sim.stats import proportion
from trials.eval.conditions import Condition
from trials.eval.episodes import read_rows
from trials.eval.evaluate import load_eval_config, rollout_condition, run_eval
from trials.eval.report import summarize_rows
from trials.experiments.tradeoff_report import write_report
from trials.jobs.dag import Grid, GridError, SerialExecutor, clear_finished, is_finished, usable_cpus

__all__ = [
    "TradeoffError",
    "TradeoffConfig",
    "Row",
    "KNOBS",
    "DEPLOYMENTS",
    "QUICK_CHECK",
    "load_tradeoff_config",
    "build_rows",
    "select_rows",
    "run_sweep",
    "read_results",
    "machine_info",
    "train_resolution_policy",
    "TradeoffJob",
]

#: Every knob of the sweep, in table order (issue 9).
KNOBS = (
    "baseline",
    "iterations",
    "eot_envs",
    "rollout_steps",
    "sampler",
    "texture_size",
    "saliency",
    "pcgrad",
    "policy_resolution",
    "eval_episodes",
    "deployment",
)
DEPLOYMENTS = ("torch-fp32", "onnx-fp32", "onnx-int8", "onnx-fp16")
BASELINE_KEY = "baseline=quick"
SETTINGS_NAME = "sweep.json"  # the sweep's settings and their hash; a re-run must match them
ROW_SPEC_NAME = "row.json"  # what a row's child process measures (settings, row, sweep folder)
MIN_ATTACK_POOL = 20


class TradeoffError(AdvobjError, ValueError):
    """Bad sweep settings, an unknown row or knob, or a sweep directory made with other settings."""


class TradeoffConfig(StrictModel):
    """What the sweep measures and on how much (written to ``<out>/sweep.json``)."""

    policy: str = Field(description="the baseline (reference) policy checkpoint directory")
    resolution_policies: dict[int, str] = Field(
        default_factory=dict, description="image size -> checkpoint, for policy_resolution rows"
    )
    attack_preset: str = "quick"
    # The sweep judges the final texture on its own held-out evaluation set, so the attack's in-run
    # validation (quick preset: every 20 iterations) is off; it would only shrink the EOT pool.
    attack_overrides: dict = Field(
        default_factory=lambda: {"validation_every": 0},
        description="AttackConfig fields applied under every row's own knob",
    )
    values: dict[str, list] = Field(
        default_factory=dict, description="knob -> values to sweep (default: DEFAULT_VALUES)"
    )
    snapshots: tuple[int, ...] = Field((30, 60), description="baseline iterations evaluated as the 'iterations' rows")
    episodes: int = Field(100, ge=1, description="paired episodes per row (the fixed evaluation set)")
    big_episodes: int = Field(500, ge=1, description="episodes of the eval_episodes row")
    big_seed: int = Field(100_000, ge=0, description="first candidate seed of the eval_episodes row's feasible set")
    max_steps: int = Field(60, ge=1)
    eval_num_envs: int = Field(8, ge=1)
    deploy_episodes: int = Field(50, ge=0, description="clean episodes per deployment variant")
    latency_reps: int = Field(200, ge=1, description="timed forward calls per batch size")
    pool: str | None = Field(None, description="task-feasible pool for the baseline policy (default: the policy's own)")
    scene: str | None = None
    threads: int = Field(1, ge=1, description="torch / onnxruntime intra-op threads in every row")
    seed: int = 0


DEFAULT_VALUES: dict[str, list] = {
    "iterations": [],  # from snapshots (+ the baseline's own iterations)
    "eot_envs": [1, 2],
    "rollout_steps": [5, 10],
    "sampler": ["bilinear"],
    "texture_size": [32, 256],
    "saliency": ["off"],
    "pcgrad": ["off"],
    "policy_resolution": [96, 128],
    "eval_episodes": [],  # from big_episodes
    "deployment": list(DEPLOYMENTS),
}

# knob -> (AttackConfig field, value mapping)
_ATTACK_FIELD = {  # in run order
    "eot_envs": ("num_envs", int),
    "rollout_steps": ("rollout_steps", int),
    "saliency": ("use_saliency", lambda v: {"on": True, "off": False}[str(v)]),
    "pcgrad": ("pcgrad", lambda v: {"on": True, "off": False}[str(v)]),
    "sampler": ("sampler", str),
    "texture_size": ("texture_size", int),
}

#: Tiny settings for a smoke run (``--quick-check``): minutes become seconds.
QUICK_CHECK = dict(
    attack_overrides={
        "iterations": 4,
        "num_envs": 1,
        "rollout_steps": 2,
        "texture_size": 16,
        "checkpoint_every": 1000,
        "validation_every": 0,
    },
    snapshots=(2,),
    episodes=4,
    big_episodes=8,
    eval_num_envs=4,
    deploy_episodes=4,
    latency_reps=5,
    values={"eot_envs": [2], "rollout_steps": [3], "texture_size": [8]},
)


def load_tradeoff_config(**fields) -> TradeoffConfig:
    try:
        cfg = TradeoffConfig(**fields)
    except ValidationError as err:
        raise TradeoffError(format_validation_error(err, "tradeoff config")) from None
    unknown = sorted(set(cfg.values) - set(KNOBS))
    if unknown:
        raise TradeoffError(f"values: unknown knob(s) {', '.join(unknown)}; knobs are {', '.join(KNOBS)}")
    return cfg


# ----------------------------------------------------------------------------- the sweep as data
@dataclass(frozen=True)
class Row:
    """One line of the table: a knob at one value, and how to measure it.

    ``kind``: ``attack`` (attack + evaluation), ``snapshot`` (evaluate the baseline's texture at an
    earlier iteration), ``episodes`` (evaluate the baseline's texture on a larger set),
    ``deployment`` (policy forward variants).
    """

    knob: str
    value: str
    kind: str
    policy: str  # label of the policy: "ref" or "px<S>"
    overrides: dict = field(default_factory=dict)
    depends: str | None = None
    note: str = ""

    @property
    def key(self) -> str:
        return f"{self.knob}={self.value}"


def _policy_dir(cfg: TradeoffConfig, label: str) -> str | None:
    if label == "ref":
        return cfg.policy
    return cfg.resolution_policies.get(int(label[2:]))


def build_rows(cfg: TradeoffConfig) -> list[Row]:
    """Every row of the sweep, in run order (dependencies first)."""
    vals = {**DEFAULT_VALUES, **cfg.values}
    base = resolve_config(cfg.attack_preset, cfg.attack_overrides)
    bad = [k for k in cfg.snapshots if not 0 < k < base.iterations]
    if bad:
        raise TradeoffError(f"snapshots: {bad} not inside the baseline's 1..{base.iterations - 1} iterations")
    rows = [
        Row(
            "baseline",
            cfg.attack_preset,
            "attack",
            "ref",
            note=f"{base.iterations} it, {base.num_envs} envs x {base.rollout_steps} steps, "
            f"texture {base.texture_size}, {base.sampler}, saliency {'on' if base.use_saliency else 'off'}, pcgrad "
            f"{'on' if base.pcgrad else 'off'}",
        )
    ]
    rows += [
        Row(
            "iterations",
            str(k),
            "snapshot",
            "ref",
            depends=BASELINE_KEY,
            note=f"snapshot of the baseline run (baseline: {base.iterations})",
        )
        for k in sorted(cfg.snapshots)
    ]
    for knob, (fname, conv) in _ATTACK_FIELD.items():
        for v in vals[knob]:
            try:
                value = conv(v)
            except (KeyError, ValueError):
                raise TradeoffError(f"values.{knob}: bad value {v!r}") from None
            if value == getattr(base, fname):
                continue  # that is the baseline itself
            was = getattr(base, fname)
            rows.append(
                Row(
                    knob,
                    str(v),
                    "attack",
                    "ref",
                    {fname: value},
                    note=f"baseline: { ({True: 'on', False: 'off'}.get(was, was)) }",
                )
            )
    for s in vals["deployment"]:
        if s not in DEPLOYMENTS:
            raise TradeoffError(f"values.deployment: unknown variant {s!r}; choose from {', '.join(DEPLOYMENTS)}")
        rows.append(Row("deployment", s, "deployment", "ref"))
    big = vals["eval_episodes"] or [cfg.big_episodes]
    for n in big:
        rows.append(
            Row(
                "eval_episodes",
                str(int(n)),
                "episodes",
                "ref",
                depends=BASELINE_KEY,
                note=f"baseline texture; first {cfg.episodes} of the same run summarised too",
            )
        )
    for s in vals["policy_resolution"]:
        rows.append(
            Row(
                "policy_resolution",
                str(int(s)),
                "attack",
                f"px{int(s)}",
                note="quick preset on a quick-trained policy at this size",
            )
        )
    keys = [r.key for r in rows]
    if len(set(keys)) != len(keys):
        raise TradeoffError(f"duplicate rows: {sorted(k for k in keys if keys.count(k) > 1)}")
    return rows


def select_rows(rows: list[Row], wanted: list[str] | None) -> list[Row]:
    """Rows named by key (``eot_envs=1``) or knob (``eot_envs``), plus their dependencies."""
    if not wanted:
        return list(rows)
    by_key = {r.key: r for r in rows}
    chosen: set[str] = set()
    for w in wanted:
        hits = [r.key for r in rows if r.key == w or r.knob == w]
        if not hits:
            if w.split("=")[0] not in KNOBS:
                raise TradeoffError(f"rows: unknown knob {w.split('=')[0]!r}; knobs are {', '.join(KNOBS)}")
            raise TradeoffError(
                f"rows: no row {w!r}; rows of that knob: {', '.join(r.key for r in rows if r.knob == w.split('=')[0])}"
            )
        chosen.update(hits)
    for k in list(chosen):
        dep = by_key[k].depends
        while dep is not None:
            chosen.add(dep)
            dep = by_key[dep].depends
    return [r for r in rows if r.key in chosen]


# ----------------------------------------------------------------------------- machine and results
def machine_info(threads: int | None = None) -> dict:
    """Cores, CPU model, memory, library versions, thread settings and the load average now."""
    model = None
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        for line in cpuinfo.read_text(errors="replace").splitlines():
            if line.lower().startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    mem_gb = None
    meminfo = Path("/proc/meminfo")
    if meminfo.is_file():
        for line in meminfo.read_text().splitlines():
            if line.startswith("MemTotal:"):
                mem_gb = round(int(line.split()[1]) / 2**20, 1)

    return {
        "cpu_count": os.cpu_count(),
        "cpus_usable": usable_cpus(),
        "cpu_model": model or platform.processor() or "unknown",
        "mem_total_gb": mem_gb,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torch_threads": threads if threads is not None else torch.get_num_threads(),
        "onnxruntime": onnxruntime.__version__,
        "numpy": numpy.__version__,
        "platform": platform.platform(),
        "loadavg": list(os.getloadavg()),
        "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def read_results(out: str | Path) -> list[dict]:
    """The rows of ``<out>/rows.jsonl`` (the last record per key wins; a torn last line is ignored)."""
    path = Path(out) / "rows.jsonl"
    if not path.is_file():
        return []
    latest: dict[str, dict] = {}
    for line in path.read_text().splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        latest[rec["key"]] = rec
    return list(latest.values())


def _append(out: Path, rec: dict) -> None:
    with open(out / "rows.jsonl", "a") as f:
        f.write(json.dumps(rec, default=_json_default) + "\n")
        f.flush()
        os.fsync(f.fileno())


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON-able: {type(o).__name__}")


_FREE_SETTINGS = ("resolution_policies",)


def _settings_hash(cfg: TradeoffConfig) -> str:
    d = {k: v for k, v in cfg.model_dump(mode="json").items() if k not in _FREE_SETTINGS}
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


# ----------------------------------------------------------------------------- the sweep driver
def run_sweep(
    cfg: TradeoffConfig,
    out: str | Path,
    rows: list[str] | None = None,
    progress: bool = True,
    log: Callable[[str], None] = print,
    isolate: bool = True,
    redo: bool = False,
    executor=None,
) -> list[dict]:
    """Run the selected rows not yet done into ``out``; returns all result records.

    ``redo``: measure the selected rows again even if done (the new record supersedes the old one
    in :func:`read_results`; the old line stays in the JSONL).

    ``isolate``: run each row in a child process (peak RSS per row, crash isolation); ``False``
    runs in-process (peak RSS is then the process's so far, noted in the row).

    ``executor``: a :mod:`trials.jobs.dag` executor (Ray); each row is then a ``tradeoff-row`` job in
    a fresh worker process (so its peak RSS is its own), a snapshot row waiting for the row whose
    texture it reads. Rows read each other's outputs under ``out``: on a cluster, ``out`` must be
    on a filesystem every node shares.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    settings_file = out / SETTINGS_NAME
    settings = cfg.model_dump(mode="json")
    if settings_file.is_file():
        have = json.loads(settings_file.read_text()).get("settings", {})
        # Where the per-resolution policies live only matters to their own rows (each row records its policy).
        diff = sorted(
            k for k in settings if k not in _FREE_SETTINGS and have.get(k) != json.loads(json.dumps(settings[k]))
        )
        if diff:
            raise TradeoffError(
                f"{out}: holds a sweep with other settings (fields: {', '.join(diff)}); use another --out"
            )
    else:
        other = sorted({r.get("settings_hash") for r in read_results(out)} - {_settings_hash(cfg)}, key=str)
        if other:  # rows without a settings file: measured with settings no longer on record
            raise TradeoffError(
                f"{out}: holds rows measured with other settings (hash {', '.join(map(str, other))}); use another --out"
            )
        settings_file.write_text(json.dumps({"settings": settings, "hash": _settings_hash(cfg)}, indent=2))
    selected = select_rows(build_rows(cfg), rows)
    done = {r["key"] for r in read_results(out) if r.get("status") == "ok"}
    todo = []
    for r in selected:
        if r.key in done and not redo:
            log(f"{r.key}: done, skipped")
        elif _policy_dir(cfg, r.policy) is None:
            if rows and (r.key in rows or r.knob in rows):
                raise TradeoffError(f"{r.key}: needs a {r.policy[2:]} px policy (--res-policy {r.policy[2:]}=DIR)")
            log(f"{r.key}: no {r.policy[2:]} px policy given (--res-policy {r.policy[2:]}=DIR), not run")
        else:
            todo.append(r)
    info_path = out / "machine.json"
    machine = json.loads(info_path.read_text()) if info_path.is_file() else {"runs": []}
    machine["runs"].append({"start": machine_info(cfg.threads)})
    info_path.write_text(json.dumps(machine, indent=2))
    write_run_info(out, {"job": "tradeoff", "settings": settings, "rows": [r.key for r in todo]}, cfg.seed)

    # Serially each row runs in a child process (isolate) or in-process; on Ray in a fresh worker.
    mode = "worker" if executor is not None else ("child" if isolate else "inline")
    _run_rows_as_jobs(cfg, todo, out, executor or SerialExecutor(log, tee=progress), log, mode)
    machine["runs"][-1]["end"] = machine_info(cfg.threads)
    info_path.write_text(json.dumps(machine, indent=2))
    return read_results(out)


def _run_rows_as_jobs(cfg: TradeoffConfig, todo: list[Row], out: Path, executor, log, mode: str = "worker") -> None:
    """The rows as ``tradeoff-row`` jobs; every finished row's record appended in table order
    (a row that measured an error is recorded and runs again next time)."""
    grid = Grid(out)
    jobs = {}
    settings = cfg.model_dump(mode="json")
    for r in todo:
        pdir = _policy_dir(cfg, r.policy)
        after = (jobs[r.depends],) if r.depends in jobs else ()
        d = out / "rows" / _slug(r.key)
        clear_finished(d)  # a row is re-measured whenever it is selected to run
        jobs[r.key] = grid.add(
            f"row-{_slug(r.key)}",
            "tradeoff-row",
            "trials.experiments.tradeoff:job_row",
            d,
            {"cfg": settings, "row": asdict(r), "root": str(out.resolve()), "mode": mode},
            {"policy": pdir},
            after=after,
            num_cpus=max(1, cfg.threads),
            fresh_process=True,
        )
    err = None
    try:
        executor.run(grid)
    except GridError as e:
        err = e
    for r in todo:
        res = out / "rows" / _slug(r.key) / "result.json"
        if res.is_file() and is_finished(jobs[r.key]):
            rec = json.loads(res.read_text())
            _append(out, rec)
            log(f"{r.key}: {rec['status']}" + (f" ({rec.get('error')})" if rec["status"] != "ok" else ""))
            if rec["status"] != "ok":
                clear_finished(res.parent)
    if err is not None:
        raise err


def job_row(out: Path, inputs: dict, cfg: dict, row: dict, root: str, mode: str = "worker") -> None:
    """The ``tradeoff-row`` job: measure one row into ``out/result.json``, in a child process
    (``child``), in this process (``inline``) or in this fresh Ray worker (``worker``)."""
    c, r = TradeoffConfig(**cfg), Row(**row)
    if mode == "child":
        rec = _run_isolated(c, r, Path(root))
    elif mode == "inline":
        rec = _run_inline(c, r, Path(root))
    else:
        rec = _measure_row(c, r, Path(root))
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / "result.json.tmp"
    tmp.write_text(json.dumps(rec, default=_json_default))
    tmp.replace(out / "result.json")


def _base_record(cfg: TradeoffConfig, row: Row) -> dict:
    return {
        "key": row.key,
        "knob": row.knob,
        "value": row.value,
        "kind": row.kind,
        "policy": row.policy,
        "policy_dir": _policy_dir(cfg, row.policy),
        "note": row.note,
        "overrides": row.overrides,
        "settings_hash": _settings_hash(cfg),
        "git_commit": git_commit(),
        "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def _run_isolated(cfg: TradeoffConfig, row: Row, out: Path) -> dict:
    job = out / "jobs" / _slug(row.key)
    job.mkdir(parents=True, exist_ok=True)
    spec = job / ROW_SPEC_NAME
    spec.write_text(json.dumps({"cfg": cfg.model_dump(mode="json"), "row": asdict(row), "out": str(out)}))
    result = job / "result.json"
    result.unlink(missing_ok=True)
    root = str(Path(__file__).resolve().parents[2])
    env = {**os.environ, "PYTHONPATH": root + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.run([sys.executable, "-m", "trials.experiments.tradeoff", str(spec), str(result)], env=env)
    if proc.returncode == 0 and result.is_file():
        return json.loads(result.read_text())
    rec = _base_record(cfg, row)
    rec.update(status="error", error=f"row process exited with code {proc.returncode}")
    return rec


def _run_inline(cfg: TradeoffConfig, row: Row, out: Path) -> dict:
    rec = _measure_row(cfg, row, out)
    rec["note"] = (rec["note"] + "; " if rec["note"] else "") + "in-process run: peak RSS is the whole process's"
    return rec


def _slug(key: str) -> str:
    return key.replace("=", "_").replace("/", "_")


# ----------------------------------------------------------------------------- one row
class _Clock:
    """Wall and process CPU time (all threads, e.g. the renderer's) since construction."""

    def __init__(self):
        self.w0, self.c0 = time.perf_counter(), time.process_time()

    def read(self) -> tuple[float, float]:
        return time.perf_counter() - self.w0, time.process_time() - self.c0


def _peak_rss_mb() -> float:
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    return kb / 1024.0 if sys.platform != "darwin" else kb / 2**20


def _eval_spec(cfg: TradeoffConfig):
    base = load_spec(cfg.scene)
    return base.with_updates(episode={**base.episode.model_dump(), "max_steps": cfg.max_steps})


def _policy_pool(cfg: TradeoffConfig, label: str, spec) -> tuple[list, str]:
    if label == "ref" and cfg.pool is not None:
        path = Path(cfg.pool)
    else:
        path = feasible_pool_path(Path(_policy_dir(cfg, label)))
    if not path.is_file():
        raise TradeoffError(
            f"{path}: the policy has no task-feasible pool (run 'advobj policy eval' on it, or pass --pool)"
        )
    return load_pool(path, spec), str(path)


def _eval_set(cfg: TradeoffConfig, label: str, out: Path, spec) -> tuple[Path, list, list, str]:
    """``(path, eval configs, attack configs, note)``: the fixed set (written once) and the attack's pool."""
    pool, src = _policy_pool(cfg, label, spec)
    path = out / "eval_sets" / f"{label}.json"
    if path.is_file():
        eval_cfgs = load_pool(path, spec)
        stale = {c.seed for c in eval_cfgs} - {c.seed for c in pool}
        if stale:
            raise TradeoffError(
                f"{path}: evaluation set not task-feasible for {src} ({len(stale)} configurations are not in its pool; "
                "was the policy replaced?); move the file away to rebuild it"
            )
    else:
        eval_cfgs = in_part(pool, "evaluation")[: cfg.episodes]
        save_pool(
            path,
            spec,
            eval_cfgs,
            meta={
                "kind": "task-feasible",
                "source": src,
                "first": len(eval_cfgs),
                "part": "evaluation",
                "definition": "the first evaluation-part configurations of the policy's task-feasible pool",
            },
        )
    note = ""
    if len(eval_cfgs) < cfg.episodes:
        note = f"pool holds {len(eval_cfgs)} < {cfg.episodes} evaluation-part configurations; evaluated on all of them"
    # The attack sees only the attack and validation parts (AttackRun filters), never eval_cfgs.
    attack_cfgs = in_part(pool, "attack") + in_part(pool, "validation")
    if len(in_part(pool, "attack")) < MIN_ATTACK_POOL:
        raise TradeoffError(
            f"{src}: only {len(in_part(pool, 'attack'))} attack-part configurations (need {MIN_ATTACK_POOL}); "
            "evaluate the policy on more episodes ('advobj policy eval --episodes N') or pass --pool"
        )
    return path, eval_cfgs, attack_cfgs, note


def _write_texture_dir(d: Path, texture, attack_cfg, extra: dict) -> Path:
    config = {"job": "tradeoff-attack", "attack": attack_cfg.model_dump(), **extra}
    return AttackArtifact.from_tensor(texture, config, attack_cfg.seed).save(d, run="provenance")


def _attack(cfg: TradeoffConfig, row: Row, out: Path, spec, attack_cfgs: list) -> dict:
    """Run the row's attack; write the final texture (and the baseline's snapshots); return timings."""
    acfg = resolve_config(cfg.attack_preset, {**cfg.attack_overrides, **row.overrides})
    policy, card = load_checkpoint(_policy_dir(cfg, row.policy))
    d = out / "attacks" / _slug(row.key)
    if d.exists():
        shutil.rmtree(d)  # an interrupted earlier try: start clean so the timing is whole
    snaps = set(cfg.snapshots) if row.key == BASELINE_KEY else set()
    snap_times = {}
    clock = _Clock()
    run = AttackRun(policy, spec, acfg, pool=attack_cfgs, out_dir=None)

    def snapshot(run, info) -> None:
        if run.state.iteration in snaps:
            w, c = clock.read()  # writing the snapshot is not charged
            _write_texture_dir(
                d / f"iter{run.state.iteration:05d}",
                run.state.texture,
                acfg,
                {"iteration": run.state.iteration, "policy": _policy_dir(cfg, row.policy)},
            )
            snap_times[run.state.iteration] = {"wall_s": w, "cpu_s": c}
            clock.w0 += clock.read()[0] - w
            clock.c0 += clock.read()[1] - c

    try:
        setup_wall, setup_cpu = clock.read()
        run_attack(run, on_iteration=snapshot, desc=f"attack {row.key}")
        wall, cpu = clock.read()
        _write_texture_dir(
            d, run.state.texture, acfg, {"iteration": run.state.iteration, "policy": _policy_dir(cfg, row.policy)}
        )
        write_config_record(d, run.pool, run.val_pool)  # snapshots in d/iterNNNNN/ use it too
        h = run.state.history
    finally:
        run.close()
    (d / "snapshots.json").write_text(json.dumps({str(k): v for k, v in snap_times.items()}))
    return {
        "attack_dir": str(d),
        "attack_config": acfg.model_dump(),
        "attack_wall_s": wall,
        "attack_cpu_s": cpu,
        "attack_setup_wall_s": setup_wall,
        "image_size": int(card.arch.image_size),
        "loss_pose_first": h.loss_pose[0] if h.loss_pose else None,
        "loss_pose_last": h.loss_pose[-1] if h.loss_pose else None,
        "snapshots": snap_times,
    }


def _evaluate(
    cfg: TradeoffConfig, row: Row, out: Path, attack_dir: str, episodes: int, pool: str | None, seed: int
) -> dict:
    d = out / "evals" / _slug(row.key)
    if d.exists():
        shutil.rmtree(d)
    ecfg = load_eval_config(
        policy=_policy_dir(cfg, row.policy),
        conditions=("attack",),
        episodes=episodes,
        max_steps=cfg.max_steps,
        num_envs=cfg.eval_num_envs,
        seed=seed,
        pool=pool,
        scene=cfg.scene,
        gifs=0,
        attack=attack_dir,
    )
    clock = _Clock()
    summary = run_eval(ecfg, d, resume=False, progress=True, report=False)
    wall, cpu = clock.read()
    a, c = summary["conditions"]["attack"], summary["conditions"]["clean"]
    return {
        "eval_dir": str(d),
        "eval_wall_s": wall,
        "eval_cpu_s": cpu,
        "episodes": a["n"],
        "tasr": a["tasr"],
        "asr": a["asr"],
        "e_trans": a["e_trans"],
        "e_rot": a["e_rot"],
        "clean_success_rate": 1.0 - c["asr"]["rate"] if c["n"] else None,
        "mean_steps": a["mean_steps"],
        "eval_pool": summary["meta"]["pool"],
    }


def _subset_summary(eval_dir: str, n: int, spec) -> dict:
    """The first ``n`` configurations (in pool order) of an evaluation, summarised alone."""
    d = Path(eval_dir)
    seeds = read_run_info(d)["config"]["seeds"][:n]
    keep = set(seeds)
    rows = [r for r in read_rows(d) if r["condition"] == "attack" and int(r["seed"]) in keep]
    s = summarize_rows(rows, spec.object_index("goal"), spec.object_index("adversarial"))
    return {"episodes": s["n"], "tasr": s["tasr"], "asr": s["asr"], "e_trans": s["e_trans"], "e_rot": s["e_rot"]}


def _measure_row(cfg: TradeoffConfig, row: Row, out: Path) -> dict:
    rec = _base_record(cfg, row)
    rec["load_start"] = list(os.getloadavg())
    clock = _Clock()
    spec = _eval_spec(cfg)
    try:
        if row.kind == "deployment":
            rec.update(_deployment(cfg, row, out, spec))
        else:
            set_path, eval_cfgs, attack_cfgs, note = _eval_set(cfg, row.policy, out, spec)
            if note:
                rec["note"] = (rec["note"] + "; " if rec["note"] else "") + note
            if row.kind == "attack":
                rec.update(_attack(cfg, row, out, spec, attack_cfgs))
                rec.update(_evaluate(cfg, row, out, rec["attack_dir"], len(eval_cfgs), str(set_path), cfg.seed))
            else:
                base_dir = out / "attacks" / _slug(BASELINE_KEY)
                if not (base_dir / TEXTURE_NPY).is_file():
                    raise TradeoffError(
                        f"{row.key}: needs the baseline row's texture in {base_dir}; run the baseline row first"
                    )
                rec["attack_config"] = AttackArtifact.load(base_dir, error=TradeoffError).attack_config
                if row.kind == "snapshot":
                    k = int(row.value)
                    snap = json.loads((base_dir / "snapshots.json").read_text()).get(str(k))
                    if snap is None:
                        raise TradeoffError(f"{row.key}: the baseline run has no snapshot at iteration {k}")
                    rec.update(
                        attack_dir=str(base_dir / f"iter{k:05d}"),
                        attack_wall_s=snap["wall_s"],
                        attack_cpu_s=snap["cpu_s"],
                    )
                    rec.update(_evaluate(cfg, row, out, rec["attack_dir"], len(eval_cfgs), str(set_path), cfg.seed))
                else:  # episodes
                    n = int(row.value)
                    base_rec = next(
                        (r for r in read_results(out) if r["key"] == BASELINE_KEY and r["status"] == "ok"), None
                    )
                    rec.update(
                        attack_dir=str(base_dir),
                        attack_wall_s=base_rec and base_rec["attack_wall_s"],
                        attack_cpu_s=base_rec and base_rec["attack_cpu_s"],
                    )
                    rec.update(_evaluate(cfg, row, out, str(base_dir), n, None, cfg.big_seed))
                    rec["subset"] = _subset_summary(rec["eval_dir"], cfg.episodes, spec)
                    if rec["eval_pool"].startswith(str(out)):
                        rec["note"] += (
                            f"; its own feasible set (candidate seeds from {cfg.big_seed}), built inside the timed "
                            "evaluation"
                        )
                    else:
                        rec["note"] += "; the policy's own feasible pool (overlaps the attack's EOT pool)"
                rec["image_size"] = _image_size(cfg, row.policy)
        rec["status"] = "ok"
    except Exception as err:  # recorded in the row; the sweep goes on with the next row
        rec.update(
            status="error",
            error=f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}",
            input_error=isinstance(err, AdvobjError),  # the user's to fix (exit 2 when every row fails so)
            traceback=traceback.format_exc(),
        )
    rec["row_wall_s"], rec["row_cpu_s"] = clock.read()
    rec["peak_rss_mb"] = _peak_rss_mb()
    rec["load_end"] = list(os.getloadavg())
    return rec


def _image_size(cfg: TradeoffConfig, label: str) -> int:
    return int(load_card(_policy_dir(cfg, label)).arch.image_size)


# ----------------------------------------------------------------------------- deployment
class _Recorder:
    """Wraps a policy: records every image batch it acts on (up to ``cap`` images)."""

    def __init__(self, policy, cap: int):
        self.policy, self.image_size, self.cap = policy, policy.image_size, cap
        self.frames: list = []
        self.n = 0

    def act(self, images):
        if self.n < self.cap:
            self.frames.append(images[: self.cap - self.n].copy())
            self.n += len(self.frames[-1])
        return self.policy.act(images)


def _latency_ms(act, frames, batch: int, reps: int) -> dict:
    n = len(frames)
    for i in range(3):
        act(frames[(i * batch) % n : (i * batch) % n + batch])
    ts, cs = [], []
    for i in range(reps):
        j = (i * batch) % max(1, n - batch + 1)
        x = frames[j : j + batch]
        t0, c0 = time.perf_counter(), time.process_time()
        act(x)
        ts.append((time.perf_counter() - t0) / len(x))
        cs.append((time.process_time() - c0) / len(x))
    ts, cs = np.asarray(ts) * 1e3, np.asarray(cs) * 1e3
    # CPU time per call is what the forward costs; wall time adds whatever the shared CPU took away.
    return {
        "median": float(np.median(ts)),
        "p90": float(np.percentile(ts, 90)),
        "cpu_median": float(np.median(cs)),
        "cpu_mean": float(cs.mean()),
        "batch": batch,
        "reps": reps,
    }


def _clean_success(policy, spec, configs, num_envs: int) -> dict:
    goal = spec.object_index("goal")
    ok = [False] * len(configs)

    def done(j, res):
        ok[j] = res["reached"] == goal

    rollout_condition(policy, spec, Condition("clean"), configs, num_envs, done)
    return proportion(sum(ok), len(ok)).to_dict()


def _deployment(cfg: TradeoffConfig, row: Row, out: Path, spec) -> dict:
    torch_policy, card = load_checkpoint(_policy_dir(cfg, row.policy))
    _, eval_cfgs, _, _ = _eval_set(cfg, row.policy, out, spec)
    configs = eval_cfgs[: max(cfg.deploy_episodes, 1)]
    # Frames: what the torch fp32 policy sees on clean rollouts of the evaluation set.
    rec = _Recorder(torch_policy, cap=512)
    clock = _Clock()
    torch_success = _clean_success(rec, spec, configs, cfg.eval_num_envs)
    frames = np.concatenate(rec.frames)
    with torch.no_grad():
        ref = torch_policy.act(frames)
    d = out / "deploy" / row.value
    if d.exists():
        shutil.rmtree(d)
    d.mkdir(parents=True)
    variant = row.value
    model_bytes = None
    if variant == "torch-fp32":
        policy, success = torch_policy, torch_success
    else:
        fp32 = export_onnx(torch_policy, d / "policy_fp32.onnx", card=card)
        path = fp32
        if variant == "onnx-int8":
            path = d / "policy_int8.onnx"
            quantize_dynamic(str(fp32), str(path), weight_type=QuantType.QInt8)
        elif variant == "onnx-fp16":
            path = d / "policy_fp16.onnx"
            onnx.save(convert_float_to_float16(onnx.load(str(fp32)), keep_io_types=True), str(path))
        policy = OnnxPolicy(path, threads=cfg.threads)
        model_bytes = path.stat().st_size
        success = _clean_success(policy, spec, configs, cfg.eval_num_envs) if cfg.deploy_episodes else None
    measure_wall, measure_cpu = clock.read()
    act = policy.act if variant != "torch-fp32" else (lambda x: torch_policy.act(x))
    got = np.asarray(act(frames), dtype=np.float64)
    err = np.abs(got - np.asarray(ref, dtype=np.float64))
    lat = {f"b{b}": _latency_ms(act, frames, b, cfg.latency_reps) for b in (1, 8)}
    return {
        "image_size": int(card.arch.image_size),
        "frames": int(len(frames)),
        "action_err_max": float(err.max()),
        "action_err_mean": float(err.mean()),
        "latency_ms": lat,
        "clean_success": success,
        "torch_clean_success": torch_success,
        "model_bytes": model_bytes,
        "deploy_episodes": len(configs),
        "setup_wall_s": measure_wall,
        "setup_cpu_s": measure_cpu,
    }


# ----------------------------------------------------------------------------- policies per resolution
def train_resolution_policy(
    size: int,
    out_dir: str | Path,
    scene: str | None = None,
    preset: str = "quick",
    progress: bool = True,
    log: Callable[[str], None] = print,
    dagger_iterations: int | None = None,
) -> Path:
    """A ``preset`` policy retrained at ``size`` px (reused when ``out_dir`` already holds one).

    ``dagger_iterations`` shortens (or lengthens) the preset's DAgger run; the run length is not
    part of the training fingerprint, so an interrupted longer run in ``out_dir`` resumes.
    """
    d = Path(out_dir)
    if is_checkpoint(d):
        log(f"{size} px policy: reusing {d}")
        return d
    extra = {} if dagger_iterations is None else {"dagger": {"iterations": int(dagger_iterations)}}
    cfg = resolve_preset(preset, policy={"image_size": int(size)}, env={"image_size": int(size)}, **extra)
    log(f"{size} px policy: training ({preset} preset) into {d}")
    train_policy(cfg, d, load_spec(scene), progress=progress, log=log)
    return d


# ----------------------------------------------------------------------------- the benchmark
class TradeoffJob(StrictModel):
    """The whole benchmark behind ``advobj bench tradeoff`` and ``benchmarks/bench_tradeoff.py``:
    the sweep's settings and what to run of it. :meth:`run` sweeps (resumable), optionally trains
    the missing per-resolution policies, then writes the report."""

    config: TradeoffConfig
    out: Path
    rows: tuple[str, ...] = Field((), description="knobs or row keys to run (default: all)")
    train_missing: bool = False
    train_iterations: int | None = Field(None, ge=1)
    plot: Path | None = None
    report_only: bool = False
    redo: bool = False

    @classmethod
    def build(
        cls, policy, out, resolution_policies: dict | None = None, quick_check: bool = False, **fields
    ) -> "TradeoffJob":
        """A validated job from the command line's values; ``fields`` holds the sweep settings
        given (``episodes``, ``big_episodes``, ``pool``, ``scene``, ``max_steps``; None = default)
        and the job's own (``rows``, ``train_missing``, ``train_iterations``, ``plot``,
        ``report_only``, ``redo``)."""
        settings = {k: fields.pop(k) for k in ("episodes", "big_episodes", "pool", "scene", "max_steps") if k in fields}
        cfg_fields = dict(QUICK_CHECK) if quick_check else {}
        cfg_fields.update({k: (str(v) if isinstance(v, Path) else v) for k, v in settings.items() if v is not None})
        res = {}
        for size, d in (resolution_policies or {}).items():
            if not str(size).isdigit():
                raise TradeoffError(f"--res-policy: expected SIZE=DIR with SIZE in px, got {size!r}")
            res[int(size)] = str(d)
        cfg = load_tradeoff_config(policy=str(policy), resolution_policies=res, **cfg_fields)
        try:
            return cls(config=cfg, out=Path(out), **{k: v for k, v in fields.items() if v is not None})
        except ValidationError as err:
            raise TradeoffError(format_validation_error(err, "tradeoff job")) from None

    def run(self, log=print, progress: bool = True, executor=None) -> Path:
        set_torch_threads()
        cfg, out, res = self.config, Path(self.out), dict(self.config.resolution_policies)
        rows, train_missing, train_iterations, redo = (
            list(self.rows),
            self.train_missing,
            self.train_iterations,
            self.redo,
        )
        scene, plot = cfg.scene, self.plot
        ran_from = len(_result_lines(out))
        if not self.report_only:
            # every policy loaded before any row runs (card, weights and their hash, the arch they fit):
            # a bad --policy fails now, not as 17 failed rows

            for flag, d in [("--policy", cfg.policy)] + [
                (f"--res-policy {s}", v) for s, v in sorted(cfg.resolution_policies.items())
            ]:
                try:
                    load_checkpoint(d)
                except AdvobjError as err:
                    raise TradeoffError(f"{flag}: {err}") from None
            wanted = [r for item in rows for r in item.split(",") if r] or None
            selected = select_rows(build_rows(cfg), wanted)
            missing = sorted({int(r.value) for r in selected if r.knob == "policy_resolution"} - set(res))
            first = wanted
            if train_missing:  # everything else first, then train, then the rows of the new policies
                first = [r.key for r in selected if not (r.knob == "policy_resolution" and int(r.value) in missing)]
            if first is None or first:
                run_sweep(cfg, out, first, progress=progress, log=log, redo=redo, executor=executor)
            if train_missing and missing:
                for s in missing:
                    res[s] = str(
                        train_resolution_policy(
                            s,
                            out / "policies" / f"px{s}",
                            scene,
                            progress=progress,
                            log=log,
                            dagger_iterations=train_iterations,
                        )
                    )
                cfg = load_tradeoff_config(**{**cfg.model_dump(), "resolution_policies": res})
                run_sweep(
                    cfg,
                    out,
                    [f"policy_resolution={s}" for s in missing],
                    progress=progress,
                    log=log,
                    redo=redo,
                    executor=executor,
                )
        report = write_tradeoff_report(out, plot=Path(plot) if plot else None)
        log(report.read_text())
        log(f"report: {report}")
        _fail_if_every_row_failed(out, _result_lines(out)[ran_from:])
        return report


def _result_lines(out: Path) -> list[str]:
    path = Path(out) / "rows.jsonl"
    return path.read_text().splitlines() if path.is_file() else []


def _fail_if_every_row_failed(out: Path, lines: list[str]) -> None:
    """A run whose every row failed is a failed run (one line): exit 2 when each row failed on the
    user's input (:class:`~sim.errors.AdvobjError`), else 1. A run with one row measured is not."""
    records = []
    for line in lines:
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:
            continue  # a torn line (as read_results)
    if not records or any(r.get("status") == "ok" for r in records):
        return
    first = records[0]
    err = TradeoffError(
        f"all {len(records)} rows this run measured failed (the first, {first.get('key')}: "
        f"{first.get('error', '?')}); see {Path(out) / 'rows.jsonl'}"
    )
    err.exit_code = 2 if all(r.get("input_error") for r in records) else 1
    raise err


def write_tradeoff_report(out: str | Path, plot: str | Path | None = None) -> Path:
    """The sweep's ``report.md`` and Pareto plots from what ``out`` holds (rows, settings)."""
    out = Path(out)
    expected = []
    if (out / SETTINGS_NAME).is_file():
        settings = json.loads((out / SETTINGS_NAME).read_text())["settings"]
        expected = [r.key for r in build_rows(load_tradeoff_config(**settings))]
    return write_report(out, read_results(out), expected, KNOBS, plot)


# ----------------------------------------------------------------------------- child entry point
def _child(job_path: str, result_path: str) -> int:
    job = json.loads(Path(job_path).read_text())
    cfg = TradeoffConfig(**job["cfg"])
    set_torch_threads(cfg.threads)
    row = Row(**job["row"])
    rec = _measure_row(cfg, row, Path(job["out"]))
    tmp = Path(result_path).with_suffix(".tmp")
    tmp.write_text(json.dumps(rec, default=_json_default))
    tmp.replace(result_path)
    return 0


if __name__ == "__main__":
    sys.exit(_child(sys.argv[1], sys.argv[2]))
