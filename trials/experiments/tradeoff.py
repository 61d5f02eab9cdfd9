"""Speed vs accuracy: one-knob-at-a-time sweep of the attack, evaluation and deployment knobs.

The sweep is data (:func:`build_rows`): a baseline (the ``quick`` attack preset on the given
policy) and variants that change one knob each. Every attack row is measured the same way:

1. the attack runs in-process (:class:`attack.optimize.AttackRun`, ``step()`` by ``step()``),
   sampling its EOT configurations from the attack part of the policy's task-feasible pool
   (:func:`sim.configs.config_part`; at least 20 are required);
2. its texture is evaluated with :func:`trials.eval.evaluate.run_eval` (paired clean/attack arms) on
   ONE fixed evaluation set per policy: the first ``episodes`` (default 300) evaluation-part
   configurations of its task-feasible pool, topped up by the evaluation's own pool builder
   (:func:`trials.eval.evaluate.resolve_pool`) when the pool holds fewer. The set is built once,
   before any row runs (timed), written to ``<out>/eval_sets/<policy>.json`` and used by every row
   of that policy, so all rows of a policy are paired on the same configurations and the report
   tests each against the baseline with McNemar's exact test.

Attack seeds (``attack_seeds``, e.g. ``(0, 1, 2)``): every row that changes the attack (the
baseline, the attack knobs and the baseline's ``iterations`` snapshots) runs once per attack seed,
as independent optimisations evaluated on the same set; its key carries ``@seed<k>`` for seeds
other than 0 (``eot_envs=1@seed2``). A row is paired with the baseline run of its own attack seed.
Rows that do not change the attack run once: ``eval_episodes`` (the first seed's baseline texture
evaluated again on the first N configurations of the same set, N = ``big_episodes``), the
``deployment`` rows (the policy forward as torch fp32, ONNX fp32, ONNX int8 dynamic quantisation,
ONNX fp16, with its actions compared with torch fp32 on rendered frames) and the
``policy_resolution`` rows (another policy, on its own fixed set: not paired with the baseline).

The ``iterations`` rows cost nothing extra: the baseline run snapshots its texture at
``snapshots`` (e.g. 30 and 60 of 120) and these rows only evaluate the snapshots, charging the
attack time the baseline had spent at that iteration.

Each row runs in a child process (peak RSS per row; a crash only loses that row) and is appended
as one JSON line to ``<out>/rows.jsonl`` when it finishes, with wall and CPU time of its attack,
its evaluation and the whole row; a re-run skips rows already there with ``status == "ok"`` (the
settings must match ``<out>/sweep.json``). Each row is a ``tradeoff-row`` job of
:mod:`trials.jobs.dag` in ``<out>/rows/<row>/``; its child process reads its spec from
``<out>/jobs/<row>/row.json``.

The committed evidence (``results/tradeoff/``) comes from this module's command line::

    python -m trials.experiments.tradeoff evidence --policy runs/evidence/policy-quick \\
        --out runs/evidence/tradeoff --episodes 300 --attack-seeds 0,1,2 --train-missing --workers 2
    python -m trials.experiments.tradeoff collect --out runs/evidence/tradeoff   # the copy only

``evidence`` refuses a checkout with uncommitted changes, runs ``sweep`` (the same options as
``advobj bench tradeoff``, plus ``--attack-seeds``) as a child process, records the attempt
(command, commit, machine, wall and CPU time, exit code) in ``results/tradeoff/run.json`` and then
runs :func:`collect`: ``rows.jsonl`` (every record as measured; paths relative, no tracebacks),
``episodes.csv`` (every row's per-episode outcomes, its evaluation's name in the first column),
``summary.json``, the fixed evaluation sets (``eval_sets/``), every attack's configuration record
(``attack_configs/``) and texture (``textures/``), ``sweep.json``, ``machine.json``, ``report.md``
and the Pareto plots. ``docs/speed-vs-accuracy.md``'s tables are generated from that folder by
``python -m trials.experiments.tradeoff_report`` (``--check``: exit 1 if the doc is stale).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import resource
import shlex
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
from pydantic import Field, ValidationError, field_validator

from attack.artifact import CONFIG_RECORD, TEXTURE_NPY, TEXTURE_PNG, AttackArtifact, write_config_record
from attack.optimize import AttackRun, resolve_config, run_attack
from sim.configio import StrictModel
from sim.configs import config_id, in_part, load_pool, save_pool
from sim.errors import AdvobjError, format_validation_error
from sim.policies.card import load_card
from sim.policies.checkpoint import is_checkpoint, load_checkpoint
from sim.policies.onnx_policy import OnnxPolicy, export_onnx
from sim.policies.pool import built_pool_path, feasible_pool_path
from sim.policies.presets import resolve_preset
from sim.policies.train import train_policy
from sim.runinfo import git_commit, write_run_info
from sim.runtime import set_torch_threads
from sim.spec import load_spec
from sim.stats import proportion
from trials.eval.conditions import Condition
from trials.eval.episodes import collect_evals, read_rows
from trials.eval.evaluate import load_eval_config, resolve_pool, rollout_condition, run_eval
from trials.experiments.record import check_evidence, read_record, run_attempt, write_record
from trials.experiments.tradeoff_report import KNOBS, attack_outcomes, latest_records, write_report
from trials.jobs.dag import Grid, GridError, RayExecutor, SerialExecutor, clear_finished, is_finished, usable_cpus

__all__ = [
    "TradeoffError",
    "TradeoffConfig",
    "Row",
    "KNOBS",
    "DEPLOYMENTS",
    "QUICK_CHECK",
    "load_tradeoff_config",
    "baseline_key",
    "build_rows",
    "build_eval_set",
    "set_size",
    "select_rows",
    "run_sweep",
    "read_results",
    "machine_info",
    "train_resolution_policy",
    "TradeoffJob",
    "collect",
    "evidence",
    "main",
]

DEPLOYMENTS = ("torch-fp32", "onnx-fp32", "onnx-int8", "onnx-fp16")
BASELINE_KEY = "baseline=quick"  # the baseline row of attack seed 0 with the default preset
ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "results" / "tradeoff"  # the committed evidence (:func:`collect`)
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
    episodes: int = Field(
        300, ge=1, description="paired episodes per row: the first N configurations of the policy's fixed set"
    )
    big_episodes: int | None = Field(
        None,
        ge=1,
        description="episodes of the eval_episodes row: the baseline texture evaluated again on the first N "
        "configurations of the same fixed set (default: a third of episodes; N > episodes makes the set that large)",
    )
    attack_seeds: tuple[int, ...] = Field(
        (0,),
        min_length=1,
        description="attack seeds: every row that changes the attack runs once per seed (independent "
        "optimisations, each evaluated on the same configurations)",
    )
    max_steps: int = Field(60, ge=1)
    eval_num_envs: int = Field(8, ge=1)
    deploy_episodes: int = Field(50, ge=0, description="clean episodes per deployment variant")
    latency_reps: int = Field(200, ge=1, description="timed forward calls per batch size")
    pool: str | None = Field(None, description="task-feasible pool for the baseline policy (default: the policy's own)")
    scene: str | None = None
    threads: int = Field(1, ge=1, description="torch / onnxruntime intra-op threads in every row")
    seed: int = Field(
        0, ge=0, description="first candidate seed when a fixed set needs more configurations than the pool holds"
    )

    @field_validator("attack_seeds")
    @classmethod
    def _distinct_seeds(cls, v: tuple[int, ...]) -> tuple[int, ...]:
        if len(set(v)) != len(v) or any(s < 0 for s in v):
            raise ValueError("attack seeds must be distinct and >= 0")
        return tuple(v)


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
    big_episodes=2,
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
    if "seed" in cfg.attack_overrides:
        raise TradeoffError("attack_overrides: the attack's seed is set per row by attack_seeds, not here")
    return cfg


# ----------------------------------------------------------------------------- the sweep as data
@dataclass(frozen=True)
class Row:
    """One line of the table: a knob at one value (under one attack seed), and how to measure it.

    ``kind``: ``attack`` (attack + evaluation), ``snapshot`` (evaluate the baseline's texture at an
    earlier iteration), ``episodes`` (evaluate the baseline's texture on the first N configurations
    of the same fixed set), ``deployment`` (policy forward variants). ``attack_seed``: the attack's
    seed (None for rows without an attack); seeds other than 0 are part of the key.
    """

    knob: str
    value: str
    kind: str
    policy: str  # label of the policy: "ref" or "px<S>"
    overrides: dict = field(default_factory=dict)
    depends: str | None = None
    note: str = ""
    attack_seed: int | None = None

    @property
    def name(self) -> str:
        """The knob setting, the same for every attack seed: ``eot_envs=1``."""
        return f"{self.knob}={self.value}"

    @property
    def key(self) -> str:
        return self.name + (f"@seed{self.attack_seed}" if self.attack_seed else "")


def baseline_key(cfg: TradeoffConfig, attack_seed: int = 0) -> str:
    """The key of the baseline row of ``attack_seed`` (``baseline=quick``, ``baseline=quick@seed1``)."""
    return f"baseline={cfg.attack_preset}" + (f"@seed{attack_seed}" if attack_seed else "")


def _policy_dir(cfg: TradeoffConfig, label: str) -> str | None:
    if label == "ref":
        return cfg.policy
    return cfg.resolution_policies.get(int(label[2:]))


def _on_off(v):
    """A switch as on/off; anything else as it is (1 is not "on")."""
    return ("on" if v else "off") if isinstance(v, bool) else v


def build_rows(cfg: TradeoffConfig) -> list[Row]:
    """Every row of the sweep, in run order (dependencies first): per attack seed the baseline, its
    snapshots and the attack knobs; then the rows that run once (deployment, eval_episodes,
    policy_resolution), on the first attack seed where they need one."""
    vals = {**DEFAULT_VALUES, **cfg.values}
    base = resolve_config(cfg.attack_preset, cfg.attack_overrides)
    bad = [k for k in cfg.snapshots if not 0 < k < base.iterations]
    if bad:
        raise TradeoffError(f"snapshots: {bad} not inside the baseline's 1..{base.iterations - 1} iterations")
    knob_rows = []  # (knob, value, overrides, note), the same for every attack seed
    for knob, (fname, conv) in _ATTACK_FIELD.items():
        for v in vals[knob]:
            try:
                value = conv(v)
            except (KeyError, ValueError):
                raise TradeoffError(f"values.{knob}: bad value {v!r}") from None
            if value == getattr(base, fname):
                continue  # that is the baseline itself
            knob_rows.append((knob, str(v), {fname: value}, f"baseline: {_on_off(getattr(base, fname))}"))
    rows = []
    for seed in cfg.attack_seeds:
        rows.append(
            Row(
                "baseline",
                cfg.attack_preset,
                "attack",
                "ref",
                note=f"{base.iterations} it, {base.num_envs} envs x {base.rollout_steps} steps, "
                f"texture {base.texture_size}, {base.sampler}, saliency {_on_off(base.use_saliency)}, pcgrad "
                f"{_on_off(base.pcgrad)}",
                attack_seed=seed,
            )
        )
        rows += [
            Row(
                "iterations",
                str(k),
                "snapshot",
                "ref",
                depends=baseline_key(cfg, seed),
                note=f"snapshot of the baseline run (baseline: {base.iterations})",
                attack_seed=seed,
            )
            for k in sorted(cfg.snapshots)
        ]
        rows += [Row(k, v, "attack", "ref", ov, note=note, attack_seed=seed) for k, v, ov, note in knob_rows]
    for s in vals["deployment"]:
        if s not in DEPLOYMENTS:
            raise TradeoffError(f"values.deployment: unknown variant {s!r}; choose from {', '.join(DEPLOYMENTS)}")
        rows.append(Row("deployment", s, "deployment", "ref"))
    first = cfg.attack_seeds[0]
    for n in _eval_episodes_values(cfg):
        rows.append(
            Row(
                "eval_episodes",
                str(n),
                "episodes",
                "ref",
                depends=baseline_key(cfg, first),
                note=f"the baseline texture on the first {n} configurations of the same fixed set",
                attack_seed=first,
            )
        )
    for s in vals["policy_resolution"]:
        rows.append(
            Row(
                "policy_resolution",
                str(int(s)),
                "attack",
                f"px{int(s)}",
                note="quick preset on a quick-trained policy at this size (its own fixed set: not paired)",
                attack_seed=first,
            )
        )
    keys = [r.key for r in rows]
    if len(set(keys)) != len(keys):
        raise TradeoffError(f"duplicate rows: {sorted(k for k in keys if keys.count(k) > 1)}")
    return rows


def _eval_episodes_values(cfg: TradeoffConfig) -> list[int]:
    vals = {**DEFAULT_VALUES, **cfg.values}["eval_episodes"] or [
        cfg.big_episodes if cfg.big_episodes is not None else max(1, cfg.episodes // 3)
    ]
    try:
        out = [int(v) for v in vals]
    except (TypeError, ValueError):
        raise TradeoffError(f"values.eval_episodes: expected episode counts, got {vals!r}") from None
    if any(v < 1 for v in out):
        raise TradeoffError(f"values.eval_episodes: counts must be >= 1, got {out}")
    return out


def set_size(cfg: TradeoffConfig, label: str) -> int:
    """Configurations in the fixed evaluation set of policy ``label``: ``episodes``, or more for the
    reference policy when an ``eval_episodes`` row asks for more (every row uses a prefix of it)."""
    return max([cfg.episodes, *_eval_episodes_values(cfg)]) if label == "ref" else cfg.episodes


def select_rows(rows: list[Row], wanted: list[str] | None) -> list[Row]:
    """Rows named by key (``eot_envs=1@seed2``), setting (``eot_envs=1``: every attack seed) or knob
    (``eot_envs``), plus their dependencies."""
    if not wanted:
        return list(rows)
    by_key = {r.key: r for r in rows}
    chosen: set[str] = set()
    for w in wanted:
        hits = [r.key for r in rows if w in (r.key, r.name, r.knob)]
        if not hits:
            knob = w.split("=")[0]
            if knob not in KNOBS:
                raise TradeoffError(f"rows: unknown knob {knob!r}; knobs are {', '.join(KNOBS)}")
            names = dict.fromkeys(r.name for r in rows if r.knob == knob)
            raise TradeoffError(f"rows: no row {w!r}; rows of that knob: {', '.join(names)}")
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
    return latest_records(_result_lines(Path(out)))


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
            if rows and (r.key in rows or r.name in rows or r.knob in rows):
                raise TradeoffError(f"{r.key}: needs a {r.policy[2:]} px policy (--res-policy {r.policy[2:]}=DIR)")
            log(f"{r.key}: no {r.policy[2:]} px policy given (--res-policy {r.policy[2:]}=DIR), not run")
        else:
            todo.append(r)
    info_path = out / "machine.json"
    machine = json.loads(info_path.read_text()) if info_path.is_file() else {"runs": []}
    machine["runs"].append(
        {
            "start": machine_info(cfg.threads),
            "executor": "serial" if executor is None else type(executor).__name__,
            "workers": 1 if executor is None else int(getattr(executor, "slots", 1)),
        }
    )
    info_path.write_text(json.dumps(machine, indent=2))
    write_run_info(out, {"job": "tradeoff", "settings": settings, "rows": [r.key for r in todo]}, cfg.seed)
    # The fixed evaluation set of each policy, once, before any row (every row then only reads it).
    for label in dict.fromkeys(r.policy for r in todo):
        if not eval_set_path(out, label).is_file():
            log(f"evaluation set of the {label} policy: the first {set_size(cfg, label)} task-feasible configurations")
            build_eval_set(cfg, label, out, _eval_spec(cfg), progress)

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
    rec["runner"] = mode  # worker: a Ray worker, possibly beside another row; child/inline: one at a time
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / "result.json.tmp"
    tmp.write_text(json.dumps(rec, default=_json_default))
    tmp.replace(out / "result.json")


def _base_record(cfg: TradeoffConfig, row: Row) -> dict:
    return {
        "key": row.key,
        "name": row.name,
        "knob": row.knob,
        "value": row.value,
        "kind": row.kind,
        "attack_seed": row.attack_seed,
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
    proc = subprocess.run([sys.executable, "-m", "trials.experiments.tradeoff", "row", str(spec), str(result)], env=env)
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
    """A row's folder name: ``eot_envs=1@seed2`` -> ``eot_envs_1_seed2``."""
    return key.replace("=", "_").replace("/", "_").replace("@", "_")


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


def eval_set_path(out: str | Path, label: str) -> Path:
    """Where the sweep keeps the fixed evaluation set of policy ``label``."""
    return Path(out) / "eval_sets" / f"{label}.json"


def build_eval_set(cfg: TradeoffConfig, label: str, out: Path, spec, progress: bool = True) -> Path:
    """Write the fixed evaluation set of policy ``label`` (timed): the first :func:`set_size`
    evaluation-part configurations of its task-feasible pool, topped up by
    :func:`trials.eval.evaluate.resolve_pool` (clean rollouts of the evaluation part's next seeds
    from ``cfg.seed``, kept where the policy reaches the goal) when the pool holds fewer."""
    path = eval_set_path(out, label)
    n = set_size(cfg, label)
    clock = _Clock()
    pool, src = _policy_pool(cfg, label, spec)
    configs, built = in_part(pool, "evaluation"), None
    if len(configs) < n:
        pdir = _policy_dir(cfg, label)
        policy, _ = load_checkpoint(pdir)
        ecfg = load_eval_config(
            policy=pdir,
            conditions=("clean",),
            episodes=n,
            max_steps=cfg.max_steps,
            num_envs=cfg.eval_num_envs,
            seed=cfg.seed,
            pool=src,
            scene=cfg.scene,
            gifs=0,
        )
        configs, built = resolve_pool(ecfg, policy, spec, _built_dir(out, label), progress)
    if len(configs) < n:
        raise TradeoffError(
            f"{label} policy ({_policy_dir(cfg, label)}): only {len(configs)} task-feasible evaluation-part "
            f"configurations found, the sweep needs {n} (--episodes / --big-episodes)"
        )
    wall, cpu = clock.read()
    save_pool(
        path,
        spec,
        configs[:n],
        meta={
            "kind": "task-feasible",
            "part": "evaluation",
            "definition": "the first evaluation-part configurations of the policy's task-feasible pool, topped up "
            "with clean rollouts of the part's next seeds where the pool held fewer",
            "policy": _policy_dir(cfg, label),
            "source": src,
            "from_source": min(n, len(in_part(pool, "evaluation"))),
            "built": built,
            "first": n,
            "build_wall_s": wall,
            "build_cpu_s": cpu,
        },
    )
    return path


def _built_dir(out: Path, label: str) -> Path:
    return Path(out) / "eval_sets" / label


def _eval_set(cfg: TradeoffConfig, label: str, out: Path, spec) -> tuple[Path, list, list]:
    """``(path, fixed set, attack configs)``: the fixed set of policy ``label`` (built by
    :func:`run_sweep` before any row) checked against the pool it came from, and the attack's pool."""
    path = eval_set_path(out, label)
    if not path.is_file():
        raise TradeoffError(f"{path}: no fixed evaluation set (run_sweep builds it before the rows)")
    eval_cfgs = load_pool(path, spec)
    pool, src = _policy_pool(cfg, label, spec)
    known = {config_id(c) for c in pool}
    built = built_pool_path(_built_dir(out, label))
    if built.is_file():
        known |= {config_id(c) for c in load_pool(built, spec)}
    stale = [c.seed for c in eval_cfgs if config_id(c) not in known]
    if stale:
        raise TradeoffError(
            f"{path}: evaluation set not task-feasible for {src} ({len(stale)} configurations are not in its pool; "
            "was the policy replaced?); move the file away to rebuild it"
        )
    if len(eval_cfgs) < set_size(cfg, label):
        raise TradeoffError(
            f"{path}: holds {len(eval_cfgs)} configurations, the settings need {set_size(cfg, label)}; move it away "
            "to rebuild it"
        )
    # The attack sees only the attack and validation parts (AttackRun filters), never eval_cfgs.
    attack_cfgs = in_part(pool, "attack") + in_part(pool, "validation")
    if len(in_part(pool, "attack")) < MIN_ATTACK_POOL:
        raise TradeoffError(
            f"{src}: only {len(in_part(pool, 'attack'))} attack-part configurations (need {MIN_ATTACK_POOL}); "
            "evaluate the policy on more episodes ('advobj policy eval --episodes N') or pass --pool"
        )
    return path, eval_cfgs, attack_cfgs


def _write_texture_dir(d: Path, texture, attack_cfg, extra: dict) -> Path:
    config = {"job": "tradeoff-attack", "attack": attack_cfg.model_dump(), **extra}
    return AttackArtifact.from_tensor(texture, config, attack_cfg.seed).save(d, run="provenance")


def _attack(cfg: TradeoffConfig, row: Row, out: Path, spec, attack_cfgs: list) -> dict:
    """Run the row's attack; write the final texture (and the baseline's snapshots); return timings."""
    seed = {} if row.attack_seed is None else {"seed": row.attack_seed}
    acfg = resolve_config(cfg.attack_preset, {**cfg.attack_overrides, **row.overrides, **seed})
    policy, card = load_checkpoint(_policy_dir(cfg, row.policy))
    d = out / "attacks" / _slug(row.key)
    if d.exists():
        shutil.rmtree(d)  # an interrupted earlier try: start clean so the timing is whole
    snaps = set(cfg.snapshots) if row.knob == "baseline" else set()
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
        "eval_name": d.name,  # its rows' name in the committed episodes.csv
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


def _measure_row(cfg: TradeoffConfig, row: Row, out: Path) -> dict:
    rec = _base_record(cfg, row)
    rec["load_start"] = list(os.getloadavg())
    clock = _Clock()
    spec = _eval_spec(cfg)
    try:
        if row.kind == "deployment":
            rec.update(_deployment(cfg, row, out, spec))
        else:
            set_path, eval_cfgs, attack_cfgs = _eval_set(cfg, row.policy, out, spec)
            rec["eval_set"] = f"eval_sets/{set_path.name}"
            n = int(row.value) if row.kind == "episodes" else cfg.episodes  # a prefix of the fixed set
            if row.kind == "attack":
                rec.update(_attack(cfg, row, out, spec, attack_cfgs))
            else:
                base_dir = out / "attacks" / _slug(row.depends)
                if not (base_dir / TEXTURE_NPY).is_file():
                    raise TradeoffError(
                        f"{row.key}: needs the baseline row's texture in {base_dir}; run {row.depends} first"
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
                else:  # episodes: the baseline's texture again, on the first n configurations of the set
                    base_rec = _finished_record(out, row.depends)
                    rec.update(
                        attack_dir=str(base_dir),
                        attack_wall_s=base_rec and base_rec["attack_wall_s"],
                        attack_cpu_s=base_rec and base_rec["attack_cpu_s"],
                    )
                rec["image_size"] = _image_size(cfg, row.policy)
            rec.update(_evaluate(cfg, row, out, rec["attack_dir"], n, str(set_path), cfg.seed))
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


def _finished_record(out: Path, key: str) -> dict | None:
    """The newest ``ok`` record of row ``key``: its job's result (a row that ran earlier in this
    invocation is appended to rows.jsonl only when the invocation ends), else rows.jsonl's."""
    res = Path(out) / "rows" / _slug(key) / "result.json"
    if res.is_file():
        rec = json.loads(res.read_text())
        if rec.get("status") == "ok":
            return rec
    return next((r for r in read_results(out) if r["key"] == key and r.get("status") == "ok"), None)


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
    _, eval_cfgs, _ = _eval_set(cfg, row.policy, out, spec)
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
        given (``episodes``, ``big_episodes``, ``attack_seeds``, ``pool``, ``scene``, ``max_steps``;
        None = default)
        and the job's own (``rows``, ``train_missing``, ``train_iterations``, ``plot``,
        ``report_only``, ``redo``)."""
        settings = {
            k: fields.pop(k)
            for k in ("episodes", "big_episodes", "attack_seeds", "pool", "scene", "max_steps")
            if k in fields
        }
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
            load_spec(scene)  # and the scene (a SpecError names its file and field) before OUT is written
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
    """The sweep's ``report.md`` and Pareto plots from what ``out`` holds (rows, settings, the rows'
    per-episode outcomes for the paired tests)."""
    out = Path(out)
    expected = []
    if (out / SETTINGS_NAME).is_file():
        settings = json.loads((out / SETTINGS_NAME).read_text())["settings"]
        known = {k: v for k, v in settings.items() if k in TradeoffConfig.model_fields}
        expected = [r.key for r in build_rows(load_tradeoff_config(**known))]
    rows = read_results(out)
    return write_report(out, rows, expected, KNOBS, plot, outcomes=_sweep_outcomes(out, rows))


def _eval_name(rec: dict) -> str | None:
    if rec.get("eval_name"):
        return rec["eval_name"]
    return Path(rec["eval_dir"]).name if rec.get("eval_dir") else None


def _sweep_outcomes(out: Path, rows: list[dict]) -> dict[str, dict[int, bool]]:
    """Targeted or not, per configuration seed, of every finished row's attacked episodes."""
    episodes = []
    for r in rows:
        name = _eval_name(r)
        if r.get("status") == "ok" and name:
            episodes += [{**e, "eval": name} for e in read_rows(out / "evals" / name)]
    return attack_outcomes(episodes)


# ----------------------------------------------------------------------------- the committed evidence
def _portable(obj, out: Path):
    """``obj`` with the checkout's and the sweep folder's absolute paths made relative (a committed
    record names no machine path); tracebacks are left out (the error line stays)."""
    sweep = str(Path(out).resolve())
    try:
        rel = Path(sweep).relative_to(ROOT).as_posix()
    except ValueError:
        rel = Path(sweep).name
    root = str(ROOT) + os.sep

    def fix(x):
        if isinstance(x, dict):
            return {k: fix(v) for k, v in x.items() if k != "traceback"}
        if isinstance(x, list):
            return [fix(v) for v in x]
        if isinstance(x, str):
            return x.replace(sweep, rel).replace(root, "")
        return x

    return fix(obj)


def _write_json(path: Path, doc) -> None:
    path.write_text(json.dumps(doc, indent=1, default=_json_default) + "\n")


def collect(out: str | Path, results: str | Path = RESULTS) -> Path:
    """Copy what a reader needs of the sweep in ``out`` into ``results`` (``results/tradeoff/``).

    ``rows.jsonl`` (every record as measured, the newest per key being the one reported),
    ``episodes.csv`` and ``summary.json`` (every reported row's evaluation:
    :func:`trials.eval.episodes.collect_evals`, its name in the first column ``eval`` and in the
    record's ``eval_name``), ``eval_sets/`` (the fixed configuration sets), ``attack_configs/`` and
    ``textures/`` (each attack's configuration record and final texture), ``sweep.json``,
    ``machine.json``, ``report.md``, the Pareto plots, and ``run.json`` (the attempts recorded by
    :func:`evidence`, plus the rows, their commits and summed wall and CPU time). Returns ``results``.
    """
    out, dst = Path(out), Path(results)
    lines = []
    for line in _result_lines(out):
        try:
            lines.append(json.loads(line))
        except json.JSONDecodeError:
            continue  # a torn last line (as read_results)
    if not lines:
        raise TradeoffError(f"{out}: no rows.jsonl to collect")
    write_tradeoff_report(out)
    dst.mkdir(parents=True, exist_ok=True)
    for sub in ("eval_sets", "attack_configs", "textures"):
        if (dst / sub).exists():
            shutil.rmtree(dst / sub)
        (dst / sub).mkdir()
    (dst / "rows.jsonl").write_text("".join(json.dumps(_portable(r, out), default=_json_default) + "\n" for r in lines))
    latest = latest_records(_result_lines(out))
    ok = [r for r in latest if r.get("status") == "ok"]
    # the evaluations name the fixed set they read by its absolute path: committed relative to the sweep
    n_rows = collect_evals(dst, [out / "evals" / _eval_name(r) for r in ok if _eval_name(r)], relative_to=out)
    for name in (SETTINGS_NAME, "machine.json"):
        if (out / name).is_file():
            _write_json(dst / name, _portable(json.loads((out / name).read_text()), out))
    for name in ("report.md", "tradeoff_pareto.png", "tradeoff_pareto_cpu.png"):
        if (out / name).is_file():
            shutil.copyfile(out / name, dst / name)
    sets = {}
    for f in sorted((out / "eval_sets").glob("*.json")):
        doc = _portable(json.loads(f.read_text()), out)
        _write_json(dst / "eval_sets" / f.name, doc)
        meta = doc.get("meta", {})
        sets[f.stem] = {
            "configurations": len(doc.get("configs", [])),
            "build_wall_s": meta.get("build_wall_s"),
            "build_cpu_s": meta.get("build_cpu_s"),
        }
    for r in ok:
        d = out / "attacks" / _slug(r["key"])
        if r["kind"] != "attack" or not d.is_dir():
            continue
        if (d / TEXTURE_PNG).is_file():
            shutil.copyfile(d / TEXTURE_PNG, dst / "textures" / f"{_slug(r['key'])}.png")
        if (d / CONFIG_RECORD).is_file():
            shutil.copyfile(d / CONFIG_RECORD, dst / "attack_configs" / f"{_slug(r['key'])}.json")
    record = read_record(dst)
    record.update(
        episodes_rows=n_rows,
        rows_ok=len(ok),
        rows_failed=sorted(r["key"] for r in latest if r.get("status") != "ok"),
        rows_wall_s=round(sum(r.get("row_wall_s") or 0.0 for r in ok), 1),
        rows_cpu_s=round(sum(r.get("row_cpu_s") or 0.0 for r in ok), 1),
        row_commits=sorted({str(r.get("git_commit")) for r in ok}),
        eval_sets=sets,
    )
    write_record(dst, record)
    return dst


#: What the committed evidence must have (issue 28): paired episodes per row and attack seeds.
EVIDENCE_MIN_EPISODES, EVIDENCE_MIN_SEEDS = 300, 3


def evidence(argv: list[str], results: str | Path = RESULTS, log=print) -> int:
    """Run ``python -m trials.experiments.tradeoff sweep <argv>`` for the committed evidence, record
    the attempt in ``results/run.json`` (the format of ``tools/evidence.py``: command, commit,
    machine, start, wall and CPU time of the sweep and the row processes it waited for (rows on Ray
    workers count only in their own records), exit code, end) and,
    when it succeeds, :func:`collect` it. Refused (exit 2): a checkout with uncommitted changes,
    ``--quick-check``, fewer than 300 episodes or 3 attack seeds. A re-run resumes the sweep; its
    time is added as another attempt."""
    a = sweep_parser(argparse.ArgumentParser(prog="evidence", add_help=False)).parse_args(argv)
    episodes = a.episodes or TradeoffConfig.model_fields["episodes"].default
    problems = []
    if a.quick_check:
        problems.append("--quick-check measures nothing")
    if episodes < EVIDENCE_MIN_EPISODES:
        problems.append(f"--episodes {episodes} < {EVIDENCE_MIN_EPISODES}")
    if a.attack_seeds is None or len(a.attack_seeds) < EVIDENCE_MIN_SEEDS:
        problems.append(f"--attack-seeds needs at least {EVIDENCE_MIN_SEEDS} seeds (e.g. 0,1,2)")
    commit, refused = check_evidence(problems)
    if refused:
        return refused
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    # its CPU time: the sweep process and every row process it waited for (its children's); rows on
    # Ray workers (--workers) are not its children: their CPU is in their records (collect: rows_cpu_s)
    rc = run_attempt(
        results,
        [sys.executable, "-m", "trials.experiments.tradeoff", "sweep", *argv],
        "python -m trials.experiments.tradeoff sweep " + shlex.join(argv),
        commit,
        cwd=ROOT,
        env=env,
    )["exit_code"]
    if rc == 0:
        out = Path(a.out) if Path(a.out).is_absolute() else ROOT / a.out
        log(f"collected into {collect(out, results)}")
    return rc


# ----------------------------------------------------------------------------- command line
def _int_list(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers such as 0,1,2, got {text!r}") from None


def _workers(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a number of worker CPUs >= 1, got {text!r}")
    return n


def sweep_parser(ap: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The sweep's options: those of ``advobj bench tradeoff`` plus ``--attack-seeds``."""
    ap.add_argument("--policy", required=True, help="baseline policy checkpoint directory")
    ap.add_argument("--out", required=True, help="sweep directory (resumable)")
    ap.add_argument("--res-policy", action="append", default=[], metavar="SIZE=DIR", help="policy_resolution policy")
    ap.add_argument("--train-missing", action="store_true", help="train missing policy_resolution policies")
    ap.add_argument("--train-iterations", type=int, default=None, help="DAgger iterations for --train-missing")
    ap.add_argument("--rows", action="append", default=[], help="knob, setting or row key to run (repeatable)")
    ap.add_argument("--episodes", type=int, default=None, help="paired episodes per row (default 300)")
    ap.add_argument(
        "--big-episodes", type=int, default=None, help="episodes of the eval_episodes row (default: episodes / 3)"
    )
    ap.add_argument(
        "--attack-seeds",
        type=_int_list,
        default=None,
        help="comma-separated attack seeds: the rows that change the attack run once per seed (default: 0)",
    )
    ap.add_argument("--pool", default=None, help="task-feasible pool of the baseline policy (default: its own)")
    ap.add_argument("--scene", default=None)
    ap.add_argument("--max-steps", type=int, default=None, help="steps per episode (default 60)")
    ap.add_argument("--quick-check", action="store_true", help="tiny settings: checks the machinery")
    ap.add_argument("--plot", default=None, help="Pareto plot PNG (default OUT/tradeoff_pareto.png)")
    ap.add_argument("--redo", action="store_true", help="measure the selected --rows again even if done")
    ap.add_argument("--report-only", action="store_true", help="only rebuild the report from OUT/rows.jsonl")
    ap.add_argument(
        "--workers",
        type=_workers,
        default=None,
        help="run the rows on a local Ray started for this run with N worker CPUs, one row (threads CPUs) per "
        "worker (default: one row at a time)",
    )
    return ap


def sweep_executor(a: argparse.Namespace, log=print):
    """The executor ``--workers`` asks for: a local Ray with N worker CPUs, or None (one row at a time)."""
    if a.workers is None:
        return None
    return RayExecutor(workers=a.workers, echo=log)


def job_from_args(a: argparse.Namespace) -> TradeoffJob:
    res = {}
    for item in a.res_policy:
        size, sep, d = item.partition("=")
        if not sep or not d:
            raise TradeoffError(f"--res-policy: expected SIZE=DIR, got {item!r}")
        res[size] = d
    return TradeoffJob.build(
        a.policy,
        a.out,
        res,
        a.quick_check,
        episodes=a.episodes,
        big_episodes=a.big_episodes,
        attack_seeds=a.attack_seeds,
        pool=a.pool,
        scene=a.scene,
        max_steps=a.max_steps,
        rows=tuple(a.rows),
        train_missing=a.train_missing,
        train_iterations=a.train_iterations,
        plot=a.plot,
        report_only=a.report_only,
        redo=a.redo,
    )


def _without(argv: list[str], flag: str) -> list[str]:
    """``argv`` without ``flag VALUE`` / ``flag=VALUE``."""
    out, skip = [], False
    for tok in argv:
        if skip:
            skip = False
        elif tok == flag:
            skip = True
        elif not tok.startswith(flag + "="):
            out.append(tok)
    return out


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m trials.experiments.tradeoff",
        description="The speed-vs-accuracy sweep, and its committed evidence under results/tradeoff/.",
    )
    sub = ap.add_subparsers(dest="cmd", required=True)
    sweep_parser(sub.add_parser("sweep", help="run the sweep (advobj bench tradeoff's options, + --attack-seeds)"))
    ev = sweep_parser(
        sub.add_parser("evidence", help="run the sweep from a clean checkout, record the attempt, collect the results")
    )
    ev.add_argument("--results", type=Path, default=RESULTS, help="where the evidence goes (default results/tradeoff)")
    c = sub.add_parser("collect", help="copy a finished sweep into results/tradeoff/ (what gets committed)")
    c.add_argument("--out", type=Path, required=True, help="the sweep directory")
    c.add_argument("--results", type=Path, default=RESULTS, help="default results/tradeoff")
    return ap


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["row"]:  # a row's child process (_run_isolated)
        return _child(argv[1], argv[2])
    a = parser().parse_args(argv)
    try:
        if a.cmd == "sweep":
            job_from_args(a).run(executor=sweep_executor(a))
        elif a.cmd == "evidence":
            return evidence(_without(argv[1:], "--results"), a.results)
        else:
            print(collect(a.out, a.results))
    except AdvobjError as err:
        print(f"error: {err}", file=sys.stderr)
        return getattr(err, "exit_code", None) or 2
    return 0


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
    sys.exit(main())
