"""The paper's experiments as recipes: locate or train policies, run the attacks, evaluate, tabulate.

Every recipe has a ``quick`` and a ``paper`` preset and writes ``<out>/table.md`` in the paper's
layout with the paper's numbers beside ours. Work is cached under ``<out>``: a finished policy,
attack or evaluation is reused, an interrupted one resumes, so a recipe can be re-run after a
crash and continues where it stopped.

``<out>/policies/<name>/``  trained policies (unless given with ``--policy`` / ``--target``)
``<out>/attacks/<name>/``   attack runs (``advobj attack run`` layout)
``<out>/evals/<name>/``     evaluations (``advobj eval`` layout, with report.md)
"""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Literal

import yaml
from pydantic import Field, ValidationError, field_validator

from sim.configio import StrictModel
from sim.errors import AdvobjError, format_validation_error
from sim.policies.competence import DEFAULT_MIN_CLEAN_SUCCESS
from sim.runinfo import write_run_info
from trials.eval.episodes import has_manifest, read_rows, read_summary

__all__ = [
    "ExperimentError",
    "ExperimentConfig",
    "PRESETS",
    "RECIPES",
    "resolve_experiment",
    "run_experiment",
    "PAPER",
    "table1_markdown",
    "verdicts_once",
]


class ExperimentError(AdvobjError, ValueError):
    """Bad recipe name, preset or inputs."""


class ExperimentConfig(StrictModel):
    """The budget of a recipe run (a preset plus overrides)."""

    preset: str
    policy_preset: str = Field(description="training preset of the reference (source) policy when none is given")
    target_policy_preset: str = Field(
        description="training preset of the black-box target policies when none are given"
    )
    attack_preset: str
    attack_overrides: dict = Field(default_factory=dict, description="AttackConfig fields applied to every attack")
    episodes: int = Field(ge=1)
    max_steps: int = Field(60, ge=1)
    num_envs: int = Field(8, ge=1)
    shapes: tuple[str, ...] = ("dog", "duck")
    gifs: int = Field(2, ge=0)
    pool: str | None = Field(None, description="task-feasible pool for every evaluation (default: each policy's)")
    transfer_targets: tuple[Literal["resnet34", "vgg16", "inception_v3"], ...] = Field(
        ("resnet34", "vgg16", "inception_v3"), description="black-box target architectures of the transfer recipe"
    )
    device: str = Field("cpu", description="torch device of every job (cuda jobs ask the executor for a GPU)")
    seed: int = 0
    attack_seeds: tuple[int, ...] = Field(
        (0,),
        min_length=1,
        description="independent attack runs per arm (the attack's seed); each is evaluated on the same configurations",
    )
    rows: tuple[str, ...] | None = Field(None, description="Table II rows to run (default: all)")
    min_clean_success: float = Field(
        DEFAULT_MIN_CLEAN_SUCCESS,
        ge=0.0,
        le=1.0,
        description="the competence gate of every pool, attack and evaluation job: refuse a policy whose clean "
        "success on the scene is below this fraction (sim.policies.competence; 0: off)",
    )

    @field_validator("attack_seeds")
    @classmethod
    def _distinct_seeds(cls, v: tuple[int, ...]) -> tuple[int, ...]:
        if len(set(v)) != len(v) or any(s < 0 for s in v):
            raise ValueError("attack seeds must be distinct and >= 0")
        return tuple(v)

    @field_validator("rows")
    @classmethod
    def _known_rows(cls, v):
        if v is None:
            return v
        known = [r[0] for r in TABLE2_ROWS]
        bad = [r for r in v if r not in known]
        if bad or not v:
            raise ValueError(f"unknown Table II row {bad[0] if bad else ''!r}; choose from {', '.join(known)}")
        return tuple(v)


PRESETS: dict[str, dict] = {
    # Runnable on 2 CPU cores: the small-CNN reference policy (advobj policy train --preset quick),
    # short attacks, 100 episodes per condition.
    # Targets train with the quick budget too: the 'ci' budget gives a policy that reaches nothing.
    "quick": dict(
        policy_preset="quick",
        target_policy_preset="quick",
        attack_preset="quick",
        episodes=100,
        max_steps=60,
        num_envs=8,
        shapes=("dog", "duck"),
    ),
    # The paper's budget: ResNet-18 at 128 px, 10k-iteration attacks, 500 episodes of 60 steps.
    "paper": dict(
        policy_preset="paper",
        target_policy_preset="paper",
        attack_preset="paper",
        episodes=500,
        max_steps=60,
        num_envs=16,
        shapes=("dog", "duck", "cube", "cylinder"),
    ),
}


def resolve_experiment(preset: str, **overrides) -> ExperimentConfig:
    if preset not in PRESETS:
        raise ExperimentError(f"preset: unknown preset {preset!r}; choose one of {sorted(PRESETS)}")
    try:
        return ExperimentConfig(
            preset=preset, **{**PRESETS[preset], **{k: v for k, v in overrides.items() if v is not None}}
        )
    except ValidationError as err:
        raise ExperimentError(format_validation_error(err, "experiment config")) from None


# ----------------------------------------------------------------------------- the paper's numbers
PHI_LABELS = ["0-10", "10-20", "20-30", "30-40", "40-50", "50-60", "60-70", "70-90"]
DIST_LABELS = ["25-36", "36-47", "47-58", "58-69", "69-80"]
PAPER = {
    # Table I: (T-ASR per phi bin, ASR per phi bin, T-ASR avg, ASR avg), %
    "table1": {
        "patch": (
            [73.00, 61.40, 54.80, 46.40, 31.00, 27.00, 15.00, 10.60],
            [77.00, 74.40, 66.80, 65.00, 56.60, 51.80, 48.80, 44.20],
            39.90,
            60.58,
        ),
        "attack": (
            [78.00, 74.00, 62.00, 64.00, 60.00, 51.00, 40.00, 34.20],
            [79.00, 80.00, 77.00, 74.00, 70.00, 62.00, 55.00, 56.60],
            57.90,
            69.20,
        ),
    },
    # Table II: per distance bin then Avg: (T-ASR, ASR) pairs and (E_trans, E_rot) pairs
    "table2": {
        "ns": (
            [56.00, 59.60, 69.20, 70.40, 73.80, 75.20, 75.00, 76.80, 94.60, 95.20, 73.72, 75.44],
            [0.33, 0.042, 0.34, 0.040, 0.31, 0.036, 0.29, 0.034, 0.26, 0.033, 0.31, 0.037],
        ),
        "f2c": (
            [54.40, 55.80, 59.20, 61.60, 67.40, 70.60, 64.80, 67.40, 89.40, 91.40, 67.04, 69.36],
            [0.32, 0.034, 0.32, 0.034, 0.30, 0.032, 0.28, 0.030, 0.26, 0.029, 0.30, 0.032],
        ),
        "c2f_untargeted": (
            [0.20, 15.00, 0.00, 8.00, 0.00, 10.20, 0.00, 8.40, 0.00, 34.40, 0.04, 15.20],
            [0.05, 0.006, 0.04, 0.005, 0.03, 0.005, 0.03, 0.004, 0.02, 0.004, 0.04, 0.005],
        ),
        "c2f_no_pose": (
            [60.60, 63.80, 72.20, 73.60, 73.80, 75.60, 72.60, 73.60, 89.80, 91.40, 73.80, 75.60],
            [0.21, 0.030, 0.22, 0.032, 0.24, 0.035, 0.24, 0.035, 0.26, 0.038, 0.23, 0.034],
        ),
        "c2f_no_saliency": (
            [59.20, 62.60, 73.80, 74.20, 78.60, 79.80, 82.00, 82.80, 96.80, 97.40, 78.08, 79.36],
            [0.49, 0.061, 0.48, 0.057, 0.43, 0.050, 0.37, 0.045, 0.33, 0.041, 0.42, 0.051],
        ),
        "c2f": (
            [61.60, 65.60, 76.60, 77.00, 82.20, 83.40, 84.20, 85.20, 97.40, 97.60, 80.36, 81.76],
            [0.53, 0.066, 0.51, 0.060, 0.45, 0.054, 0.40, 0.048, 0.35, 0.044, 0.45, 0.055],
        ),
    },
    # Table III: (T-ASR, ASR) %; cube and cylinder are not in the paper's table
    "table3": {
        "attack": (79.80, 81.12),
        "shape_dog": (60.04, 65.80),
        "shape_duck": (63.20, 68.32),
        "stereo": (63.28, 78.91),
        "light_bright": (77.04, 84.70),
        "light_dim": (67.80, 72.20),
        "noise": (75.57, 80.41),
        "bkg_varied": (77.91, 85.64),
    },
    # Table V: (T-ASR, ASR) %
    "transfer": {
        "resnet18": (79.08, 81.12),
        "resnet34": (71.20, 78.32),
        "vgg16": (59.68, 70.08),
        "inception_v3": (56.68, 70.28),
    },
}

# Table II's rows: label, opt. strategy, (targeted, pose, saliency), AttackConfig overrides
TABLE2_ROWS = [
    ("ns", "(a)", "NS", (1, 1, 1), {"schedule": "ns"}),
    ("f2c", "(b)", "F2C", (1, 1, 1), {"schedule": "f2c"}),
    ("c2f_untargeted", "(c)", "C2F", (0, 1, 1), {"schedule": "c2f", "loss": "untargeted"}),
    ("c2f_no_pose", "(d)", "C2F", (1, 0, 1), {"schedule": "c2f", "use_pose": False}),
    ("c2f_no_saliency", "(e)", "C2F", (1, 1, 0), {"schedule": "c2f", "use_saliency": False}),
    ("c2f", "(f)", "C2F", (1, 1, 1), {"schedule": "c2f"}),
    # Not in the paper's table: one schedule stage for the whole run (far only / near only), which
    # tells whether C2F's gain comes from the ordering or from either end of the distance range.
    ("coarse", "(g)", "coarse only", (1, 1, 1), {"schedule": "coarse"}),
    ("fine", "(h)", "fine only", (1, 1, 1), {"schedule": "fine"}),
    # Controls, not attacks: the starting texture left as it is (one step of 1e-9 moves no 8-bit
    # texel), uniform noise or mid grey. They separate "any unfamiliar look draws the policy" from
    # what the optimisation adds.
    (
        "random_texture",
        "(ctl)",
        "none",
        (0, 0, 0),
        {"init_texture": "random", "iterations": 1, "lr": 1e-9, "validation_every": 0},
    ),
    (
        "gray_texture",
        "(ctl)",
        "none",
        (0, 0, 0),
        {"init_texture": "gray", "iterations": 1, "lr": 1e-9, "validation_every": 0},
    ),
]
TRANSFER_TARGETS = ("resnet34", "vgg16", "inception_v3")


# ----------------------------------------------------------------------------- orchestration
@dataclass
class Context:
    """A recipe run: its config, output folder, inputs and the grid of jobs it declares.

    The ``ensure_*`` functions declare jobs (:mod:`trials.jobs.dag`) and return where their outputs
    will be; reading an evaluation's summary runs every job declared so far (``run_jobs``), so a
    recipe declares all its work first and the executor runs it serially or on Ray.
    """

    cfg: ExperimentConfig
    out: Path
    policy: Path | None = None
    targets: dict = field(default_factory=dict)
    scene: str | None = None
    progress: bool = True
    log: Callable[[str], None] = print
    pools: dict = field(default_factory=dict)  # policy dir -> its evaluation pool file (ensure_pool)
    executor: object = None
    shards: int = 1
    grid: object = None

    def __post_init__(self):
        from trials.jobs.dag import Grid, SerialExecutor  # lazy: CLI start-up (+15 ms)

        self.grid = self.grid or Grid(self.out)
        self.executor = self.executor or SerialExecutor(self.log, tee=self.progress)

    def spec(self):
        from sim.spec import load_spec  # lazy: CLI start-up (+22 ms)

        return load_spec(self.scene)

    def eval_spec(self):
        """The scene with the recipe's episode length: what its evaluations (and pools) are made for."""
        spec = self.spec()
        return spec.with_updates(episode={**spec.episode.model_dump(), "max_steps": self.cfg.max_steps})

    def resources(self) -> dict:
        return job_resources(self.cfg.device)

    def run_jobs(self) -> None:
        self.executor.run(self.grid)


def gate_params(min_clean_success: float) -> dict:
    """The competence gate's job parameter (``min_clean_success``, :mod:`sim.policies.competence`)
    of a pool, attack or evaluation job. It is given to the job function but kept out of the job's
    key (``Grid.add``'s ``key_params``): the gate refuses work before it starts and changes no
    output, so a finished job is reused at any threshold, and a job refused at one threshold resumes
    at another in the same folder."""
    return {"min_clean_success": float(min_clean_success)}


def job_resources(device: str) -> dict:
    """What one job asks the executor for: a CPU (torch threads follow it), a GPU on CUDA."""
    return {"num_cpus": 1.0, "num_gpus": 1.0 if str(device).startswith("cuda") else 0.0}


def add_eval_jobs(
    grid,
    prefix: str,
    d: Path,
    fields: dict,
    inputs: dict,
    shards: int,
    resources: dict,
    min_clean_success: float = DEFAULT_MIN_CLEAN_SUCCESS,
) -> None:
    """An evaluation into ``d``: one ``eval`` job, or ``shards`` ``eval-shard`` jobs under
    ``d/shards`` plus their merge (an ``eval`` job run in the driver, with the whole one's key).
    ``min_clean_success``: the competence gate each evaluating job applies (:func:`job_eval`); a
    check before work, not part of the jobs' keys (:func:`gate_params`)."""
    key = {"fields": fields}
    gate = gate_params(min_clean_success)
    if shards <= 1:
        grid.add(
            prefix,
            "eval",
            "trials.experiments.recipes:job_eval",
            d,
            {"fields": fields, **gate},
            inputs,
            key_params=key,
            **resources,
        )
        return
    n = int(shards)
    parts = [
        grid.add(
            f"{prefix}-shard{k}of{n}",
            "eval-shard",
            "trials.experiments.recipes:job_eval",
            d / "shards" / f"{k}-of-{n}",
            {"fields": fields, "shard": [k, n], **gate},
            inputs,
            key_params={"fields": fields, "shard": [k, n]},
            **resources,
        )
        for k in range(n)
    ]
    grid.add(
        prefix,
        "eval",
        "trials.experiments.recipes:job_eval",
        d,
        {"fields": fields, "merge": n},
        inputs,
        local=True,
        after=tuple(parts),
        key_params=key,
    )


class EvalResult(dict):
    """An evaluation's summary, read from ``summary.json`` once the grid has run."""

    def __init__(self, ctx: Context, path: Path):
        super().__init__()
        self._ctx, self._path = ctx, path

    def _load(self):
        if not dict.__len__(self):  # dict's own length: not the override below
            self._ctx.run_jobs()
            self.update(read_summary(self._path))


def _loading(name: str):
    base = getattr(dict, name)

    def method(self, *args):
        self._load()
        return base(self, *args)

    method.__name__ = name
    return method


# Every way of reading the dict runs the grid first (once): a recipe declares, then reads.
for _name in ("__getitem__", "get", "__contains__", "__iter__", "__len__", "keys", "items", "values"):
    setattr(EvalResult, _name, _loading(_name))
del _name


def _scene_input(ctx: Context) -> dict:
    return {} if ctx.scene is None else {"scene": ctx.scene}


def ensure_policy(
    ctx: Context,
    name: str = "reference",
    arch: str | None = None,
    preset: str | None = None,
    cameras: tuple[str, ...] | None = None,
) -> Path:
    """A policy checkpoint: the one given, else a ``train-policy`` job into ``out/policies/<name>``
    (reading ``cameras`` of the recipe's scene when given, else the wrist camera)."""
    if name == "reference" and ctx.policy is not None:
        return ctx.policy
    if name in ctx.targets:
        return Path(ctx.targets[name])
    d = ctx.out / "policies" / name
    preset = preset or ctx.cfg.policy_preset
    from sim.policies.presets import resolve_preset  # lazy: CLI start-up (torch, trimesh)

    try:
        resolve_preset(
            preset, arch=arch, seed=ctx.cfg.seed, cameras=cameras, spec=None if cameras is None else ctx.spec()
        )
    except ValueError as err:
        raise ExperimentError(str(err)) from None
    params = {"preset": preset, "arch": arch, "seed": ctx.cfg.seed, "device": ctx.cfg.device}
    if cameras is not None:  # only then: the one-camera jobs keep their keys (finished ones are reused)
        params["cameras"] = list(cameras)
    ctx.grid.add(
        f"policy-{name}",
        "train-policy",
        "trials.experiments.recipes:job_train_policy",
        d,
        params,
        _scene_input(ctx),
        **ctx.resources(),
    )
    return d


def job_train_policy(
    out: Path,
    inputs: dict,
    preset: str,
    arch: str | None,
    seed: int,
    device: str = "cpu",
    cameras: list[str] | None = None,
) -> None:
    """The ``train-policy`` job: train (or resume, or reuse a finished) policy into ``out``."""
    from sim.policies.checkpoint import is_checkpoint  # lazy: CLI start-up (torch, onnxruntime)
    from sim.policies.presets import resolve_preset  # lazy: CLI start-up (torch, trimesh)
    from sim.policies.train import train_policy  # lazy: CLI start-up (torch, onnxruntime)
    from sim.spec import load_spec  # lazy: CLI start-up (+22 ms)

    if is_checkpoint(out):
        print(f"policy: reusing {out}")
        return
    from trials.jobs.dag import show_progress  # lazy: CLI start-up (+15 ms)

    spec = load_spec(inputs.get("scene"))
    train_policy(
        resolve_preset(preset, arch=arch, seed=seed, cameras=cameras, spec=spec),
        out,
        spec,
        device=device,
        progress=show_progress(),
    )


def ensure_attack(ctx: Context, policy_dir: Path, name: str, overrides: dict, recordings: Path | None = None) -> Path:
    """An ``attack`` job into ``out/attacks/<name>``: reused when finished with the same config,
    resumed if interrupted; with ``recordings`` (a recording folder, an input of the job), the attack
    on those recorded frames instead of simulator rollouts."""
    from attack.optimize import resolve_config  # lazy: CLI start-up (torch, trimesh)

    fields = {**ctx.cfg.attack_overrides, **overrides}
    if str(ctx.cfg.device) != "cpu":
        fields.setdefault("device", ctx.cfg.device)
    resolve_config(ctx.cfg.attack_preset, fields)  # a bad override fails now, not inside the grid
    d = ctx.out / "attacks" / name
    params = {"preset": ctx.cfg.attack_preset, "fields": fields}
    ctx.grid.add(
        f"attack-{name}",
        "attack",
        "trials.experiments.recipes:job_attack",
        d,
        {**params, **gate_params(ctx.cfg.min_clean_success)},
        {"policy": policy_dir, **_scene_input(ctx), **({} if recordings is None else {"recordings": recordings})},
        key_params=params,
        **ctx.resources(),
    )
    return d


def _below_cwd(path: Path) -> str:
    """``path`` relative to the working directory when it lies below it (what a run records), else as it is."""
    try:
        return str(Path(path).resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def job_attack(
    out: Path, inputs: dict, preset: str, fields: dict, min_clean_success: float = DEFAULT_MIN_CLEAN_SUCCESS
) -> None:
    """The ``attack`` job: run, resume or reuse the attack of ``fields`` into ``out`` (on the
    recording ``inputs["recordings"]`` when given), behind the competence gate at ``min_clean_success``."""
    from attack.artifact import TEXTURE_NPY, AttackArtifact  # lazy: CLI start-up (trimesh, PIL)
    from attack.optimize import resolve_config  # lazy: CLI start-up (torch, trimesh)
    from attack.state import find_checkpoint  # lazy: CLI start-up (torch, trimesh)
    from trials.jobs.attack import attack_job  # lazy: CLI start-up (torch, onnxruntime)

    if "recordings" in inputs:
        fields = {**fields, "recordings": _below_cwd(inputs["recordings"])}
    want = resolve_config(preset, fields).model_dump()
    if (out / "metrics.json").is_file() and (out / TEXTURE_NPY).is_file():
        have = AttackArtifact.load(out, error=ExperimentError).attack_config
        if have != json.loads(json.dumps(want)):
            raise ExperimentError(f"{out}: holds an attack with a different config; use another --out")
        print(f"attack: reusing {out}")
        return
    out.mkdir(parents=True, exist_ok=True)
    cfg_path = out / "attack_config.yaml"
    cfg_path.write_text(yaml.safe_dump(fields))
    resume = find_checkpoint(out) is not None
    from trials.jobs.dag import show_progress  # lazy: CLI start-up (+15 ms)

    attack_job(
        inputs["policy"],
        preset,
        cfg_path,
        inputs.get("scene"),
        None,
        out,
        resume,
        progress=show_progress(),
        min_clean_success=min_clean_success,
    )


def _eval_fields(ctx: Context) -> dict:
    c = ctx.cfg
    return {
        "episodes": c.episodes,
        "max_steps": c.max_steps,
        "num_envs": c.num_envs,
        "seed": c.seed,
        "gifs": c.gifs,
        "device": c.device,
    }


def ensure_pool(ctx: Context, policy_dir: Path) -> str:
    """The evaluation pool of a policy: a ``pool`` job (``<out>/pools/<policy>-<hash>/``) built once
    per recipe run and shared by all its evaluations, so every arm of every table is paired on the
    same configurations and the clean rollouts that find them are not repeated per evaluation."""
    from sim.policies.pool import built_pool_path  # lazy: CLI start-up (torch, trimesh)

    c = ctx.cfg
    if c.pool is not None:
        return c.pool
    key = str(policy_dir)
    if key not in ctx.pools:
        # Keyed by the resolved path too: two policies in folders of the same name must not share a pool.
        digest = hashlib.sha256(str(Path(policy_dir).resolve()).encode()).hexdigest()[:8]
        d = ctx.out / "pools" / f"{Path(policy_dir).name}-{digest}"
        params = {"fields": _eval_fields(ctx)}
        ctx.grid.add(
            f"pool-{d.name}",
            "pool",
            "trials.experiments.recipes:job_pool",
            d,
            {**params, **gate_params(c.min_clean_success)},
            {"policy": policy_dir, **_scene_input(ctx)},
            key_params=params,
            **ctx.resources(),
        )
        ctx.pools[key] = str(built_pool_path(d))
    return ctx.pools[key]


def job_pool(out: Path, inputs: dict, fields: dict, min_clean_success: float = DEFAULT_MIN_CLEAN_SUCCESS) -> None:
    """The ``pool`` job: the policy's task-feasible evaluation-part configurations, saved as
    ``out/feasible_pool.json`` (from the policy's own pool, topped up as ``advobj eval`` does, behind
    the competence gate at ``min_clean_success``)."""
    from sim.configs import save_pool  # lazy: CLI start-up (trimesh, PIL)
    from sim.policies.checkpoint import load_policy  # lazy: CLI start-up (torch, onnxruntime)
    from sim.policies.pool import built_pool_path  # lazy: CLI start-up (torch, trimesh)
    from sim.spec import load_spec  # lazy: CLI start-up (+22 ms)
    from trials.eval.evaluate import load_eval_config, resolve_pool  # lazy: CLI start-up (torch, onnxruntime)
    from trials.jobs.dag import show_progress  # lazy: CLI start-up (+15 ms)

    ecfg = load_eval_config(
        policy=str(inputs["policy"]),
        scene=None if "scene" not in inputs else str(inputs["scene"]),
        pool=None if "pool" not in inputs else str(inputs["pool"]),
        **fields,
    )
    base = load_spec(ecfg.scene)
    spec = base.with_updates(episode={**base.episode.model_dump(), "max_steps": ecfg.max_steps})
    out.mkdir(parents=True, exist_ok=True)
    configs, src = resolve_pool(
        ecfg,
        load_policy(ecfg.policy, ecfg.device),
        spec,
        out,
        progress=show_progress(),
        min_clean_success=min_clean_success,
    )
    if Path(src) != built_pool_path(out):  # the policy's own pool sufficed: keep a copy as this job's output
        save_pool(
            built_pool_path(out),
            spec,
            configs,
            meta={
                "definition": "configs where the clean policy reaches the goal",
                "part": "evaluation",
                "base": src,
                "from_base": len(configs),
            },
        )


def ensure_eval(
    ctx: Context, policy_dir: Path, name: str, conditions, attack=None, patch=None, shapes=None
) -> EvalResult:
    """An evaluation into ``out/evals/<name>``: one ``eval-shard`` job, or ``ctx.shards`` of them
    merged by an ``eval`` job; returns its summary (read once the grid has run)."""
    pool = ensure_pool(ctx, policy_dir)
    inputs = {"policy": policy_dir, "pool": pool, "attack": attack, "patch": patch, **_scene_input(ctx)}
    inputs.update({f"shape_{k}": v for k, v in (shapes or {}).items()})
    fields = {**_eval_fields(ctx), "conditions": list(conditions)}
    d = ctx.out / "evals" / name
    ctx.log(f"eval {name}: {', '.join(conditions)} x {ctx.cfg.episodes} episodes into {d}")
    add_eval_jobs(ctx.grid, f"eval-{name}", d, fields, inputs, ctx.shards, ctx.resources(), ctx.cfg.min_clean_success)
    return EvalResult(ctx, d)


def job_eval(
    out: Path,
    inputs: dict,
    fields: dict,
    shard: list | None = None,
    merge: int = 0,
    min_clean_success: float = DEFAULT_MIN_CLEAN_SUCCESS,
) -> None:
    """The ``eval-shard`` job (the whole evaluation, or configurations ``k::K`` with ``shard``),
    behind the competence gate at ``min_clean_success``, and their merge (``merge=K``: the K shards
    under ``out/shards`` into ``out``; it runs no policy)."""
    from trials.eval.evaluate import load_eval_config, merge_eval, run_eval  # lazy: CLI start-up (torch, onnxruntime)
    from trials.jobs.dag import show_progress  # lazy: CLI start-up (+15 ms)

    sv = lambda k: None if k not in inputs else str(inputs[k])  # noqa: E731
    cfg = load_eval_config(
        **fields,
        policy=str(inputs["policy"]),
        pool=sv("pool"),
        scene=sv("scene"),
        attack=sv("attack"),
        patch=sv("patch"),
        shapes={k[len("shape_") :]: str(v) for k, v in inputs.items() if k.startswith("shape_")},
    )
    if merge:
        merge_eval(cfg, out, [out / "shards" / f"{k}-of-{merge}" for k in range(merge)])
    else:
        run_eval(
            cfg,
            out,
            resume=has_manifest(out),
            progress=show_progress(),
            shard=None if shard is None else tuple(shard),
            final_pool=True,
            min_clean_success=min_clean_success,
        )


def run_eval_grid(
    cfg, out: str | Path, executor, shards: int, log=print, min_clean_success: float = DEFAULT_MIN_CLEAN_SUCCESS
) -> dict:
    """``advobj eval`` through the job layer: a ``pool`` job, then the evaluation into ``out`` (the
    folder ``run_eval`` writes), in ``shards`` jobs merged there. The pool job resolves the pool as
    ``run_eval`` does (``cfg.pool`` or the policy's own, topped up when short of ``cfg.episodes``),
    so the episodes do not depend on the executor; the shards take its pool as it is. Every job
    applies the competence gate at ``min_clean_success`` as ``run_eval`` does (the pool job before
    it builds configurations, each evaluating job on the card before it writes)."""
    from sim.policies.pool import built_pool_path  # lazy: CLI start-up (torch, trimesh)
    from trials.jobs.dag import Grid  # lazy: CLI start-up (+15 ms)

    out = Path(out)
    grid = Grid(out)
    res = job_resources(cfg.device)
    fields = {
        k: v
        for k, v in cfg.model_dump(mode="json").items()
        if k not in ("policy", "pool", "scene", "attack", "patch", "shapes")
    }
    scene = {} if cfg.scene is None else {"scene": cfg.scene}
    pf = {k: fields[k] for k in ("episodes", "max_steps", "num_envs", "seed", "pool_factor", "device")}
    grid.add(
        "pool",
        "pool",
        "trials.experiments.recipes:job_pool",
        out / "pool",
        {"fields": pf, **gate_params(min_clean_success)},
        {"policy": cfg.policy, "pool": cfg.pool, **scene},
        key_params={"fields": pf},
        **res,
    )
    pool = str(built_pool_path(out / "pool"))
    inputs = {
        "policy": cfg.policy,
        "pool": pool,
        "attack": cfg.attack,
        "patch": cfg.patch,
        **scene,
        **{f"shape_{k}": v for k, v in cfg.shapes.items()},
    }
    add_eval_jobs(grid, "eval", out, fields, inputs, shards, res, min_clean_success)
    executor.run(grid)
    return read_summary(out)


# ----------------------------------------------------------------------------- tables
def _pct(p: dict) -> str:
    return "n/a" if not p["n"] else f"{100 * p['rate']:.2f}"


def _ci(p: dict) -> str:
    return "" if not p["n"] else f" [{100 * p['lo']:.0f}, {100 * p['hi']:.0f}]"


def _err(m: dict, d: int) -> str:
    return "n/a" if not m["n"] or m["mean"] != m["mean"] else f"{m['mean']:.{d}f}"


def _header(title: str, ctx: Context, note: str = "") -> list[str]:
    c = ctx.cfg
    return [
        f"# {title}",
        "",
        f"Preset `{c.preset}`: {c.episodes} episodes per condition (paper: 500), at most {c.max_steps} steps, "
        f"attack preset `{c.attack_preset}`. Rates in %; overall (Avg) cells of ours carry 95% Wilson intervals in "
        "brackets; "
        "per-bin intervals and episode counts are in each evaluation's report.md (`evals/`). " + note,
        "",
    ]


def seeded(name: str, seed: int) -> str:
    """The name of attack seed ``seed``'s run of ``name`` (an attack or an evaluation folder):
    ``name`` itself for seed 0 (what single-seed runs wrote, so they are reused), else
    ``name-seed<k>``."""
    return name if int(seed) == 0 else f"{name}-seed{int(seed)}"


def seed_of(name: str) -> int:
    """The attack seed of a run folder named by :func:`seeded` (0 without a ``-seed<k>`` suffix)."""
    head, sep, tail = name.rpartition("-seed")
    return int(tail) if sep and head and tail.isdigit() else 0


def unseeded(name: str) -> str:
    """``name`` without its ``-seed<k>`` suffix (the arm a seed's run belongs to)."""
    head, sep, tail = name.rpartition("-seed")
    return head if sep and head and tail.isdigit() else name


def ensure_seeded_attack(
    ctx: Context, policy_dir: Path, name: str, overrides: dict, seed: int, recordings: Path | None = None
) -> Path:
    """:func:`ensure_attack` for attack seed ``seed``: an independent optimisation run (its own
    training configurations, sampling and validation draws) of the same method."""
    fields = overrides if seed == 0 else {**overrides, "seed": seed}
    return ensure_attack(ctx, policy_dir, seeded(name, seed), fields, recordings)


def table1(ctx: Context) -> str:
    ref = ensure_policy(ctx)
    first = None
    for seed in ctx.cfg.attack_seeds:
        att = ensure_seeded_attack(ctx, ref, "c2f", {"schedule": "c2f"}, seed)
        pat = ensure_seeded_attack(ctx, ref, "patch", {"schedule": "c2f", "adversarial_mesh": "patch"}, seed)
        s = ensure_eval(ctx, ref, seeded("table1", seed), ["attack", "patch"], attack=att, patch=pat)
        first = first or (s, seeded("table1", seed))
    s, name = first
    text = table1_markdown(s, ctx, eval_rows(ctx, name))
    return text + seeds_markdown(ctx, {"3D": ("table1", "attack"), "patch": ("table1", "patch")})


def seeds_markdown(ctx: Context, arms: dict[str, tuple[str, str]]) -> str:
    """Per-seed T-ASR of each arm (``label -> (evaluation name, condition)``), with the mean and
    the spread over attack seeds; empty for a single seed. The tests between arms that account
    for both the seeds and the configurations are in results/findings.md."""
    seeds = ctx.cfg.attack_seeds
    if len(seeds) < 2:
        return ""
    lines = [
        "",
        f"## T-ASR per attack seed ({len(seeds)} independent attack runs per arm, same configurations)",
        "",
        "| arm | " + " | ".join(f"seed {s}" for s in seeds) + " | mean | sd over seeds | n configs |",
        "|---|" + "---|" * (len(seeds) + 3),
    ]
    for label, (ev, cond) in arms.items():
        rates, ns = [], set()
        for seed in seeds:
            rows = eval_rows(ctx, seeded(ev, seed), cond)
            ns.add(len(rows))
            rates.append(sum(int(r["targeted"]) for r in rows.values()) / max(len(rows), 1))
        mean = sum(rates) / len(rates)
        sd = (sum((x - mean) ** 2 for x in rates) / (len(rates) - 1)) ** 0.5
        lines.append(
            f"| {label} | "
            + " | ".join(f"{100 * x:.2f}" for x in rates)
            + f" | {100 * mean:.2f} | {100 * sd:.2f} | {'/'.join(str(n) for n in sorted(ns))} |"
        )
    return "\n".join(lines) + "\n"


def eval_rows(ctx: Context, name: str, condition: str | None = None) -> list[dict] | dict[int, dict]:
    """The episode rows of evaluation ``name`` (``<out>/evals/<name>/episodes.csv``); with
    ``condition``, that arm's rows keyed by configuration seed (for paired comparisons)."""
    ctx.run_jobs()
    rows = read_rows(ctx.out / "evals" / name)
    return rows if condition is None else {r["seed"]: r for r in rows if r["condition"] == condition}


def verdicts_once(text: str) -> str:
    """``text`` with each verdict line (``**A vs B** (claim: ...``) kept where it first appears, and
    the blank line after a repeat dropped: the Table I layout's per-phi and per-distance sections
    each open with the same overall 3D-vs-patch verdict (:func:`table1_markdown`)."""
    seen, out, skip_blank = set(), [], False
    for line in text.split("\n"):
        if skip_blank and not line.strip():
            skip_blank = False
            continue
        skip_blank = False
        if line.startswith("**") and "** (claim: " in line:
            if line in seen:
                skip_blank = True
                continue
            seen.add(line)
        out.append(line)
    return "\n".join(out)


def table1_markdown(s: dict, ctx: Context, rows: list[dict] | None = None) -> str:
    """Table I's layout for an evaluation summary holding the ``attack`` and ``patch`` arms; with
    the evaluation's ``rows``, the paired 3D-vs-patch test per phi and per distance bin too (the
    overall verdict, which opens both, once: :func:`verdicts_once`)."""
    lines = _header("Table I: 3D object vs 2D patch by viewing angle phi (deg)", ctx)
    lines += [
        "| attack type | source | " + " | ".join(f"{b} T-ASR | {b} ASR" for b in PHI_LABELS + ["Avg"]) + " |",
        "|---|---|" + "---|---|" * (len(PHI_LABELS) + 1),
    ]
    for cond, label in (("patch", "2D Patch"), ("attack", "3D Object")):
        cs = s["conditions"][cond]
        ours = [f"{_pct(cs['by_phi'][b]['tasr'])} | {_pct(cs['by_phi'][b]['asr'])}" for b in PHI_LABELS]
        ours.append(f"{_pct(cs['tasr'])}{_ci(cs['tasr'])} | {_pct(cs['asr'])}{_ci(cs['asr'])}")
        t, a, ta, aa = PAPER["table1"][cond]
        paper = [f"{x:.2f} | {y:.2f}" for x, y in zip(t, a)] + [f"{ta:.2f} | {aa:.2f}"]
        lines += [f"| {label} | ours | " + " | ".join(ours) + " |", f"| {label} | paper | " + " | ".join(paper) + " |"]
    lines += [
        "",
        "Episodes per phi bin (ours): "
        + ", ".join(f"{b}: {s['conditions']['attack']['by_phi'][b]['n']}" for b in PHI_LABELS),
    ]
    pair = s.get("paired", {}).get("attack vs patch")
    if pair:
        lines += [
            "",
            f"Paired McNemar exact test, 3D object vs 2D patch on the same configurations: T-ASR "
            f"{pair['tasr']['b']} configs only 3D / {pair['tasr']['c']} only patch, p = {pair['tasr']['p_value']:.2g}; "
            f"ASR {pair['asr']['b']} / {pair['asr']['c']}, p = {pair['asr']['p_value']:.2g}.",
        ]
    if rows:
        from trials.experiments.findings import paired_markdown  # lazy: CLI start-up (+33 ms)

        a = {r["seed"]: r for r in rows if r["condition"] == "attack"}
        b = {r["seed"]: r for r in rows if r["condition"] == "patch"}
        lines += ["", "## Paired T-ASR test by viewing angle phi", ""] + paired_markdown("3D", "patch", a, b, "phi")
        lines += ["", "## Paired T-ASR test by initial distance r", ""] + paired_markdown("3D", "patch", a, b, "r")
    return verdicts_once("\n".join(lines)) + "\n"


def table2(ctx: Context) -> str:
    ref = ensure_policy(ctx)
    lines = _header(
        "Table II: optimisation strategies and loss ablations by initial distance (cm)",
        ctx,
        "Second line of each row: E_trans (normalised action units) and E_rot (rad), defined in docs/evaluation.md.",
    )
    lines += [
        "| row | strategy | targeted | pose | saliency | source | "
        + " | ".join(f"{b} T-ASR/E_trans | {b} ASR/E_rot" for b in DIST_LABELS + ["Avg"])
        + " |",
        "|---|---|---|---|---|---|" + "---|---|" * (len(DIST_LABELS) + 1),
    ]
    rows = [r for r in TABLE2_ROWS if ctx.cfg.rows is None or r[0] in ctx.cfg.rows]
    first = ctx.cfg.attack_seeds[0]
    evals = {}
    for key, *_, overrides in rows:
        for seed in ctx.cfg.attack_seeds:
            att = ensure_seeded_attack(ctx, ref, key, overrides, seed)
            e = ensure_eval(ctx, ref, seeded(f"table2_{key}", seed), ["attack"], attack=att)
            evals.setdefault(key, e)
    if len(ctx.cfg.attack_seeds) > 1:
        lines[2] += f" Rows and paired tests below: attack seed {first}; every seed in the last section."
    for key, row, strat, flags, overrides in rows:
        cs = evals[key]["conditions"]["attack"]
        chk = " | ".join("x" if f else "" for f in flags)
        rates = [f"{_pct(cs['by_distance'][b]['tasr'])} | {_pct(cs['by_distance'][b]['asr'])}" for b in DIST_LABELS]
        rates.append(f"{_pct(cs['tasr'])}{_ci(cs['tasr'])} | {_pct(cs['asr'])}{_ci(cs['asr'])}")
        errs = [
            f"{_err(cs['by_distance'][b]['e_trans'], 2)} | {_err(cs['by_distance'][b]['e_rot'], 3)}"
            for b in DIST_LABELS
        ]
        errs.append(f"{_err(cs['e_trans'], 2)} | {_err(cs['e_rot'], 3)}")
        lines += [
            f"| {row} | {strat} | {chk} | ours | " + " | ".join(rates) + " |",
            "| | | | | | ours | " + " | ".join(errs) + " |",
        ]
        if key in PAPER["table2"]:
            pr, pe = PAPER["table2"][key]
            lines += [
                "| | | | | | paper | " + " | ".join(f"{x:.2f}" for x in pr) + " |",
                "| | | | | | paper | "
                + " | ".join(f"{pe[i]:.2f} | {pe[i + 1]:.3f}" for i in range(0, len(pe), 2))
                + " |",
            ]
        else:
            lines.append("| | | | | | paper | " + " | ".join(["-"] * (2 * len(DIST_LABELS) + 2)) + " |")
    from trials.experiments.findings import paired_markdown  # lazy: CLI start-up (+33 ms)

    arms = {key: eval_rows(ctx, seeded(f"table2_{key}", first), "attack") for key, *_ in rows}
    for a, b, claim in (
        ("c2f", "ns", ">="),
        ("ns", "f2c", ">"),
        ("c2f", "f2c", ">"),
        ("c2f", "c2f_untargeted", ">"),
        ("c2f", "c2f_no_saliency", ">"),
        ("c2f", "c2f_no_pose", ">"),
        ("c2f", "coarse", ">="),
        ("c2f", "fine", ">="),
    ):
        if arms.get(a) and arms.get(b):
            lines += ["", f"## Paired T-ASR test: {a} vs {b}, by initial distance r", ""] + paired_markdown(
                a, b, arms[a], arms[b], "r", claim
            )
    return "\n".join(lines) + "\n" + seeds_markdown(ctx, {key: (f"table2_{key}", "attack") for key, *_ in rows})


def table3(ctx: Context) -> str:
    ref = ensure_policy(ctx)
    att = ensure_attack(ctx, ref, "c2f", {"schedule": "c2f"})
    shapes = {
        s: ensure_attack(ctx, ref, f"shape_{s}", {"schedule": "c2f", "adversarial_mesh": s}) for s in ctx.cfg.shapes
    }
    conds = (
        ["attack"]
        + [f"shape_{s}" for s in ctx.cfg.shapes]
        + ["stereo", "light_bright", "light_dim", "noise", "bkg_varied"]
    )
    s = ensure_eval(ctx, ref, "table3", conds, attack=att, shapes=shapes)
    labels = {
        "attack": "Ours",
        "stereo": "Stereo Cam",
        "light_bright": "Light: Bright",
        "light_dim": "Light: Dim",
        "noise": "Add Noise",
        "bkg_varied": "Bkg Varied",
        **{f"shape_{x}": f"Shape: {x.capitalize()}" for x in ctx.cfg.shapes},
    }
    lines = _header(
        "Table III: generalisation and robustness",
        ctx,
        "Stereo: the mono policy acts on both cameras of a 6 cm stereo pair and the two actions are averaged "
        "(docs/evaluation.md).",
    )
    lines += [
        "| condition | T-ASR (ours) | ASR (ours) | T-ASR (paper) | ASR (paper) | McNemar p vs clean (ASR) |",
        "|---|---|---|---|---|---|",
    ]
    for c in conds:
        cs = s["conditions"][c]
        pt, pa = PAPER["table3"].get(c, (None, None))
        p = cs.get("vs_clean", {}).get("asr", {}).get("p_value")
        lines.append(
            f"| {labels[c]} | {_pct(cs['tasr'])}{_ci(cs['tasr'])} | {_pct(cs['asr'])}{_ci(cs['asr'])} | "
            f"{'-' if pt is None else f'{pt:.2f}'} | {'-' if pa is None else f'{pa:.2f}'} | "
            f"{'-' if p is None else f'{p:.2g}'} |"
        )
    return "\n".join(lines) + "\n"


def transfer(ctx: Context) -> str:
    src = ensure_policy(ctx)
    att = ensure_attack(ctx, src, "c2f", {"schedule": "c2f"})
    # The source row is the white-box policy whatever its architecture (the paper's is ResNet-18).
    rows = [("source", src, "source (white-box)", "resnet18")]
    for arch in ctx.cfg.transfer_targets:
        rows.append(
            (arch, ensure_policy(ctx, arch, arch=arch, preset=ctx.cfg.target_policy_preset), "black-box target", arch)
        )
    lines = _header(
        "Table V: transfer from the source policy to other architectures",
        ctx,
        "Each target is evaluated on its own task-feasible configurations; the texture is the source policy's attack. "
        "McNemar p: the attack arm against the same policy's clean arm.",
    )
    lines += [
        "| policy | role | checkpoint arch | T-ASR (ours) | ASR (ours) | McNemar p vs clean (T-ASR) | T-ASR (paper) "
        "| ASR (paper) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    missing = [a for a in TRANSFER_TARGETS if a not in ctx.cfg.transfer_targets]
    evals = {name: ensure_eval(ctx, pdir, f"transfer_{name}", ["attack"], attack=att) for name, pdir, *_ in rows}
    for name, pdir, role, paper_row in rows:
        cs = evals[name]["conditions"]["attack"]
        pt, pa = PAPER["transfer"][paper_row]
        p = cs.get("vs_clean", {}).get("tasr", {}).get("p_value")
        lines.append(
            f"| {name} | {role} | {_arch(pdir)} | {_pct(cs['tasr'])}{_ci(cs['tasr'])} | "
            f"{_pct(cs['asr'])}{_ci(cs['asr'])} | "
            f"{'-' if p is None else f'{p:.2g}'} | {pt:.2f} | {pa:.2f} |"
        )
    for arch in missing:
        pt, pa = PAPER["transfer"][arch]
        lines.append(
            f"| {arch} | black-box target | not run (not in transfer_targets) | - | - | - | {pt:.2f} | {pa:.2f} |"
        )
    return "\n".join(lines) + "\n"


LIGHT_CONDITIONS = ("attack", "light_bright", "light_dim", "light_random")


def lighting(ctx: Context) -> str:
    """Lighting randomisation in the attack (the paper's sim-to-real measure): what it costs (attack
    time, T-ASR under the nominal light) and what it buys (T-ASR under the bright and dim presets
    and under held-out random lights), each texture on the same configurations."""
    from trials.experiments.findings import paired_markdown  # lazy: CLI start-up (+33 ms)

    ref = ensure_policy(ctx)
    runs = {
        "fixed light": ensure_attack(ctx, ref, "c2f", {"schedule": "c2f"}),
        "light randomisation": ensure_attack(ctx, ref, "c2f_light", {"schedule": "c2f", "light_randomization": True}),
    }
    evals = {}
    for label, run in runs.items():
        name = f"lighting_{run.name}"
        ensure_eval(ctx, ref, name, LIGHT_CONDITIONS, attack=run)
        evals[label] = name
    lines = _header(
        "Lighting randomisation in the attack: cost and benefit",
        ctx,
        "Both textures are evaluated on the same held-out configurations; light_random draws a new light per episode "
        "from the configuration's seed (never a light the attack saw).",
    )
    ctx.run_jobs()
    cost = {k: json.loads((v / "metrics.json").read_text()) for k, v in runs.items()}
    lines += [
        "| attack | seconds / iteration | attack wall (s) | final held-out validation T-ASR (nominal light) |",
        "|---|---|---|---|",
    ]
    for k, m in cost.items():
        v = (m.get("validation") or {}).get("t_asr") or [float("nan")]
        lines.append(f"| {k} | {m['seconds_per_iteration']:.3f} | {m['seconds']:.0f} | {v[-1]:.2f} |")
    for cond in LIGHT_CONDITIONS:
        a = eval_rows(ctx, evals["light randomisation"], cond)
        b = eval_rows(ctx, evals["fixed light"], cond)
        lines += ["", f"## Condition `{cond}`: with vs without lighting randomisation", ""]
        lines += paired_markdown("randomised", "fixed", a, b, "phi", ">")
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- which camera carries the attack
#: The scene of the ``cameras`` recipe (relative to the checkout): the built-in scene with the fixed ``front`` camera.
TWO_CAMERA_SCENE = "scenes/two-cameras.yaml"
#: The cameras of the two-camera reference policy the recipe trains when none is given.
TWO_CAMERAS = ("wrist", "front")


def _cameras_read(ctx: Context) -> tuple[str, ...]:
    """The cameras the ``cameras`` recipe's policy reads: the given one's (loaded with the recipe's
    scene, so a camera it lacks or of another size is one line), else :data:`TWO_CAMERAS`."""
    from sim.policies.checkpoint import load_policy  # lazy: CLI start-up (torch, onnxruntime)
    from sim.policies.contract import policy_cameras  # lazy: CLI start-up (torch)
    from sim.policies.policy import scene_camera_px  # lazy: CLI start-up (torch)

    spec = ctx.spec()
    if ctx.policy is None:
        try:
            scene_camera_px(spec, TWO_CAMERAS)
        except AdvobjError as err:
            raise ExperimentError(
                f"--scene: {err}; the cameras recipe trains a policy reading {', '.join(TWO_CAMERAS)}"
            ) from None
        return TWO_CAMERAS
    try:
        cams = policy_cameras(load_policy(ctx.policy, spec=spec))
    except AdvobjError as err:
        raise ExperimentError(f"--policy: {err}") from None
    if len(cams) < 2:
        raise ExperimentError(
            f"--policy: {ctx.policy} reads the {cams[0]} camera only; the cameras recipe compares the cameras of a "
            "policy reading several (advobj policy train --cameras wrist,front --scene scenes/two-cameras.yaml)"
        )
    return cams


def camera_conditions(cams: tuple[str, ...]) -> list[str]:
    """The ``cameras`` recipe's conditions: the texture in every camera, then in each camera alone."""
    return ["attack"] + [f"attack_{c}_only" for c in cams]


def cameras(ctx: Context) -> str:
    """Which camera carries the attack: the C2F attack against a policy reading several cameras
    (trained on the two-camera scene when none is given), each attack seed's texture evaluated with
    the texture in every camera (``attack``) and in one camera alone (``attack_<camera>_only``, the
    others seeing the benign look), all on the same held-out configurations, with paired McNemar
    tests between the conditions."""
    from trials.experiments.findings import paired, paired_markdown  # lazy: CLI start-up (+33 ms)

    cams = _cameras_read(ctx)
    ref = ensure_policy(ctx, cameras=None if ctx.policy is not None else cams)
    conds = camera_conditions(cams)
    evals = {}
    for seed in ctx.cfg.attack_seeds:
        att = ensure_seeded_attack(ctx, ref, "c2f", {"schedule": "c2f"}, seed)
        evals[seed] = ensure_eval(ctx, ref, seeded("cameras", seed), conds, attack=att)
    first = ctx.cfg.attack_seeds[0]
    seen = {"attack": ", ".join(cams), **{f"attack_{c}_only": c for c in cams}}
    lines = _header(
        f"Which camera carries the attack: a policy reading {', '.join(cams)}",
        ctx,
        "The C2F texture is rendered into every camera the policy reads (attack) or into one of them alone "
        "(attack_<camera>_only; the other cameras see the object's benign look), on the same held-out "
        "configurations. McNemar p vs clean: the condition against the same configurations' clean episodes.",
    )
    if len(ctx.cfg.attack_seeds) > 1:
        lines[2] += (
            f" Rows below: attack seed {first}; the paired tests of every seed and the spread over seeds follow."
        )
    lines += [
        "| condition | texture seen by | T-ASR (ours) | ASR (ours) | McNemar p vs clean (T-ASR) |",
        "|---|---|---|---|---|",
    ]
    s = evals[first]
    for c in conds:
        cs = s["conditions"][c]
        p = cs.get("vs_clean", {}).get("tasr", {}).get("p_value")
        lines.append(
            f"| {c} | {seen[c]} | {_pct(cs['tasr'])}{_ci(cs['tasr'])} | {_pct(cs['asr'])}{_ci(cs['asr'])} | "
            f"{'-' if p is None else f'{p:.2g}'} |"
        )
    pairs = [(conds[i], conds[j]) for i in range(len(conds)) for j in range(i + 1, len(conds))]
    lines += [
        "",
        "## Paired McNemar tests between the conditions (T-ASR, same configurations)",
        "",
        "| attack seed | A | B | n | A % | B % | only A / only B | A - B (pp) [95% CI] | p |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    rows = {seed: eval_rows(ctx, seeded("cameras", seed)) for seed in ctx.cfg.attack_seeds}
    for seed, rs in rows.items():
        arm = {c: {r["seed"]: r for r in rs if r["condition"] == c} for c in conds}
        for a, b in pairs:
            pr = paired(arm[a], arm[b])
            lo, hi = pr.diff_ci()
            if not pr.n:
                lines.append(f"| {seed} | {a} | {b} | 0 | n/a | n/a | - | n/a | n/a |")
                continue
            lines.append(
                f"| {seed} | {a} | {b} | {pr.n} | {100 * pr.rate_a:.2f} | {100 * pr.rate_b:.2f} | {pr.b} / {pr.c} | "
                f"{100 * pr.diff:+.1f} [{100 * lo:+.1f}, {100 * hi:+.1f}] | {pr.p:.2g} |"
            )
    arm = {c: {r["seed"]: r for r in rows[first] if r["condition"] == c} for c in conds}
    for a, b in pairs:
        lines += ["", f"## {a} vs {b} by viewing angle phi (attack seed {first})", ""]
        lines += paired_markdown(a, b, arm[a], arm[b], "phi")
    return "\n".join(lines) + "\n" + seeds_markdown(ctx, {c: ("cameras", c) for c in conds})


# ----------------------------------------------------------------------------- the attack on recorded frames
#: Episodes of the recordings attacked: the largest is recorded, each smaller one is its first episodes.
RECORDED_EPISODES = (5, 20, 80)
#: A recording's folder inside its job's output folder (beside the job's own files).
RECORDING_DIR = "recording"
#: What the recordings attack aims at: this share of the closed-loop attack's T-ASR (finding F7's floor).
RECORDINGS_AIM = 0.7


def ensure_recording(
    ctx: Context, policy_dir: Path, name: str, episodes: int, cell: str = "nominal", first_of: Path | None = None
) -> Path:
    """A recording in ``out/recordings/<name>/``: a ``record-sim`` job (clean episodes of the policy
    in the simulator's ``cell``, ``advobj record sim``), or with ``first_of`` (a recording) a
    ``record-prefix`` job copying its first ``episodes`` episodes; returns the recording's folder."""
    d = ctx.out / "recordings" / name
    if first_of is None:
        c = ctx.cfg
        params = {"episodes": episodes, "seed": c.seed, "max_steps": c.max_steps, "num_envs": c.num_envs}
        params |= {"cell": cell, "device": c.device}
        inputs = {"policy": policy_dir, **_scene_input(ctx)}
        fn, kind = "trials.experiments.recipes:job_record_sim", "record-sim"
    else:
        params, inputs = {"episodes": episodes}, {"recording": first_of}
        fn, kind = "trials.experiments.recipes:job_first_episodes", "record-prefix"
    ctx.grid.add(f"record-{name}", kind, fn, d, params, inputs, **ctx.resources())
    return d / RECORDING_DIR


def _recording_target(out: Path) -> Path | None:
    """Where a record job writes its recording (``out/recording``); None when a finished one is
    there (reused). What an interrupted write left (a staging folder) is removed first."""
    from sim.recording import is_recording  # lazy: CLI start-up (PIL)

    d = out / RECORDING_DIR
    if is_recording(d):
        print(f"recording: reusing {d}")
        return None
    if d.is_dir():
        shutil.rmtree(d)
    return d


def job_record_sim(
    out: Path, inputs: dict, episodes: int, seed: int, max_steps: int, num_envs: int, cell: str, device: str = "cpu"
) -> None:
    """The ``record-sim`` job: ``advobj record sim`` into ``out/recording`` (reused when finished)."""
    from trials.jobs.dag import show_progress  # lazy: CLI start-up (+15 ms)
    from trials.recordings.simulated import SimRecordJob, run_record_sim  # lazy: CLI start-up (torch, pyrender)

    target = _recording_target(out)
    if target is None:
        return
    job = SimRecordJob(
        policy=inputs["policy"],
        out=target,
        episodes=episodes,
        scene=inputs.get("scene"),
        seed=seed,
        max_steps=max_steps,
        num_envs=num_envs,
        cell=cell,
        device=device,
    )
    run_record_sim(job, log=print, progress=show_progress())


def job_first_episodes(out: Path, inputs: dict, episodes: int) -> None:
    """The ``record-prefix`` job: the first ``episodes`` episodes of ``inputs["recording"]`` into ``out/recording``."""
    from trials.recordings.simulated import first_episodes  # lazy: CLI start-up (PIL)

    target = _recording_target(out)
    if target is not None:
        first_episodes(inputs["recording"], target, episodes)


def _rate(rows: dict) -> float:
    return sum(int(r["targeted"]) for r in rows.values()) / len(rows) if rows else float("nan")


def _validation_cell(attack_dir: Path) -> str:
    """The last held-out validation of an attack run: T-ASR (simulator) or toward fraction (recordings)."""
    m = json.loads((attack_dir / "metrics.json").read_text())
    v = m.get("validation") or {}
    if not v.get("t_asr"):
        return "-"
    kind = "toward fraction" if str(v.get("measure", "")).startswith("toward") else "T-ASR"
    return f"{kind} {v['t_asr'][-1]:.2f}"


def recordings(ctx: Context) -> str:
    """The attack on recorded frames against the closed-loop simulator attack (issue 29's check).

    The simulator stands in for the real cell: clean episodes of the policy are recorded in it
    (``advobj record sim``: the adversarial object hidden, configurations of the split's attack part),
    the largest of :data:`RECORDED_EPISODES` and the others as its first episodes, and the largest
    again in the shifted cell (another light, another table). For every attack seed the closed-loop
    C2F attack runs first; its CPU time is the budget of the recordings attacks with the same preset
    and seed (``max_cpu_s``: the same iterations, ended at the first that reaches the budget), which
    never build a simulator env. Every texture is evaluated closed loop on the same held-out
    configurations with its paired clean arm, and the recordings' configurations are checked not to
    be among them."""
    from attack.optimize import read_cpu_record  # lazy: CLI start-up (torch, trimesh)
    from sim.recording import read_recording  # lazy: CLI start-up (PIL)
    from trials.experiments.findings import paired  # lazy: CLI start-up (+33 ms)
    from trials.recordings.simulated import RecordSimError, check_held_out  # lazy: CLI start-up (torch)

    ref = ensure_policy(ctx)
    sizes = tuple(sorted(set(RECORDED_EPISODES)))
    big = sizes[-1]
    recs = {f"nominal_{big}": ensure_recording(ctx, ref, f"nominal-{big}", big)}
    for n in sizes[:-1]:
        recs[f"nominal_{n}"] = ensure_recording(ctx, ref, f"nominal-{n}", n, first_of=recs[f"nominal_{big}"])
    recs[f"shifted_{big}"] = ensure_recording(ctx, ref, f"shifted-{big}", big, cell="shifted")
    arms = ["closed_loop"] + [f"nominal_{n}" for n in sizes] + [f"shifted_{big}"]
    seeds = ctx.cfg.attack_seeds
    c2f = {"schedule": "c2f"}
    attacks = {("closed_loop", s): ensure_seeded_attack(ctx, ref, "closed_loop", c2f, s) for s in seeds}
    evals = {
        ("closed_loop", s): ensure_eval(
            ctx, ref, seeded("recordings_closed_loop", s), ["attack"], attack=attacks["closed_loop", s]
        )
        for s in seeds
    }
    ctx.run_jobs()  # the closed-loop attacks' CPU time is the recordings attacks' budget
    budget = {}
    for s in seeds:
        cpu = read_cpu_record(attacks["closed_loop", s])
        if cpu is None:
            raise ExperimentError(f"{attacks['closed_loop', s]}: the closed-loop attack recorded no CPU time")
        budget[s] = float(cpu["cpu_s"])
    for arm in arms[1:]:
        for s in seeds:
            d = ensure_seeded_attack(ctx, ref, arm, {**c2f, "max_cpu_s": budget[s]}, s, recordings=recs[arm])
            attacks[arm, s] = d
            evals[arm, s] = ensure_eval(ctx, ref, seeded(f"recordings_{arm}", s), ["attack"], attack=d)
    ctx.run_jobs()
    rows = {(arm, s): eval_rows(ctx, seeded(f"recordings_{arm}", s), "attack") for arm in arms for s in seeds}
    first = seeds[0]
    eval_seeds = sorted(rows["closed_loop", first])
    c = ctx.cfg
    lines = _header(
        "Attacking recorded frames: the recordings attack against the closed-loop simulator attack",
        ctx,
        "The simulator stands in for the real cell. Recordings: clean episodes of the policy in the simulator "
        f"(advobj record sim: the adversarial object hidden; configurations of the attack part from seed {c.seed}, "
        f"at most {c.max_steps} steps), the {', '.join(str(n) for n in sizes[:-1])}-episode ones the first episodes "
        f"of the {big}-episode one; shifted: {big} episodes under another light and on another table than the "
        "evaluation's scene. The recordings attacks build no simulator env (open loop on the frames). CPU: each "
        "recordings attack runs the closed-loop attack's preset and iterations with its attack seed, ended at the "
        "first iteration whose CPU time reaches the closed-loop attack's (max_cpu_s), so it never has more CPU "
        "than the closed-loop attack. Every texture is evaluated closed loop in the simulator on the same held-out "
        "configurations, each with its paired clean arm.",
    )
    lines += [
        "## The recordings",
        "",
        "| recording | cell | episodes | steps | evaluation configurations among its configurations |",
        "|---|---|---|---|---|",
    ]
    for arm in arms[1:]:
        rec = read_recording(recs[arm])
        try:
            checked = check_held_out(rec, eval_seeds)
        except RecordSimError as err:
            raise ExperimentError(str(err)) from None
        steps = sum(e.n_frames for e in rec.episodes)
        lines.append(f"| {arm} | {rec.source.get('cell', '?')} | {len(rec.episodes)} | {steps} | 0 of {checked} |")
    lines += [
        "",
        "## CPU time of the attacks",
        "",
        "| attack seed | arm | CPU s | budget s | iterations done / planned | ended by the budget | last held-out "
        "validation |",
        "|---|---|---|---|---|---|---|",
    ]
    for s in seeds:
        for arm in arms:
            cpu = read_cpu_record(attacks[arm, s]) or {}
            cap = cpu.get("max_cpu_s")
            lines.append(
                f"| {s} | {arm} | {cpu.get('cpu_s', float('nan')):.1f} | {'-' if cap is None else f'{cap:.1f}'} | "
                f"{cpu.get('iterations', '?')} / {cpu.get('iterations_planned', '?')} | "
                f"{'yes' if cpu.get('stopped_at_budget') else 'no'} | {_validation_cell(attacks[arm, s])} |"
            )
    ref_rates = [_rate(rows["closed_loop", s]) for s in seeds]
    ref_mean = sum(ref_rates) / len(ref_rates)
    lines += [
        "",
        "## T-ASR (held-out configurations, closed loop in the simulator)",
        "",
        f"The aim: the recordings attack on {big} episodes keeps at least {RECORDINGS_AIM:.0%} of the closed-loop "
        "attack's T-ASR (ratio of the means over attack seeds; its interval and verdict: finding F7 in "
        "results/findings.md).",
        "",
        "| arm | " + " | ".join(f"seed {s} %" for s in seeds) + " | mean % | ratio to closed loop | "
        f"McNemar p vs clean (seed {first}) | n configs |",
        "|---|" + "---|" * (len(seeds) + 4),
    ]
    for arm in arms:
        rates = [_rate(rows[arm, s]) for s in seeds]
        mean = sum(rates) / len(rates)
        p = evals[arm, first]["conditions"]["attack"].get("vs_clean", {}).get("tasr", {}).get("p_value")
        ns = "/".join(str(n) for n in sorted({len(rows[arm, s]) for s in seeds}))
        ratio = mean / ref_mean if ref_mean > 0 else float("nan")
        lines.append(
            f"| {arm} | " + " | ".join(f"{100 * r:.2f}" for r in rates) + f" | {100 * mean:.2f} | {ratio:.2f} | "
            f"{'-' if p is None else f'{p:.2g}'} | {ns} |"
        )
    pairs = [(f"nominal_{big}", "closed_loop")]
    pairs += [(f"nominal_{b}", f"nominal_{a}") for a, b in zip(sizes, sizes[1:])]
    pairs += [(f"shifted_{big}", f"nominal_{big}")]
    lines += [
        "",
        "## Paired McNemar tests (T-ASR, same configurations)",
        "",
        "| attack seed | A | B | n | A % | B % | only A / only B | A - B (pp) [95% CI] | p |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for s in seeds:
        for a, b in pairs:
            pr = paired(rows[a, s], rows[b, s])
            if not pr.n:
                lines.append(f"| {s} | {a} | {b} | 0 | n/a | n/a | - | n/a | n/a |")
                continue
            lo, hi = pr.diff_ci()
            lines.append(
                f"| {s} | {a} | {b} | {pr.n} | {100 * pr.rate_a:.2f} | {100 * pr.rate_b:.2f} | {pr.b} / {pr.c} | "
                f"{100 * pr.diff:+.1f} [{100 * lo:+.1f}, {100 * hi:+.1f}] | {pr.p:.2g} |"
            )
    return "\n".join(lines) + "\n"


def _arch(pdir: Path) -> str:
    try:
        from sim.policies.card import load_card  # lazy: CLI start-up (torch)

        return load_card(pdir).arch.arch
    except Exception:
        return "onnx" if str(pdir).endswith(".onnx") else "?"


@dataclass(frozen=True)
class Recipe:
    """One experiment: the function that runs it, its one-line help, whether it attacks other
    policies (``--target``/``--archs``; such a recipe evaluates each target on its own pool), the
    scene it runs on when no ``--scene`` is given (a path relative to the checkout; None: the
    built-in scene) and a check of its inputs run before anything is written (``check(ctx)``)."""

    run: Callable[[Context], str]
    help: str
    transfer: bool = False
    scene: str | None = None
    check: Callable[[Context], object] | None = None


# The one list of recipes: the CLI (one generated ``advobj experiment NAME`` each) and
# tools/evidence.py read it.
RECIPES: dict[str, Recipe] = {
    "table1": Recipe(table1, "3D adversarial object vs 2D patch, by viewing angle (Table I)."),
    "table2": Recipe(
        table2,
        "C2F vs F2C vs NS and the targeted / pose / saliency ablations, by distance (Table II); a smaller "
        "--iterations budget shows the strategies before they saturate.",
    ),
    "table3": Recipe(table3, "Shapes, stereo camera, lighting, noise and background (Table III)."),
    "transfer": Recipe(
        transfer, "Black-box transfer: source attack against ResNet34, VGG16 and Inception-v3 (Table V).", True
    ),
    "lighting": Recipe(
        lighting,
        "Lighting randomisation in the attack: its cost and what it buys under bright, dim and held-out lights.",
    ),
    "cameras": Recipe(
        cameras,
        "Which camera carries the attack: a two-camera policy (wrist + front, trained on scenes/two-cameras.yaml "
        "unless --policy is given) with the texture in both cameras, the wrist camera only and the front camera only.",
        scene=TWO_CAMERA_SCENE,
        check=_cameras_read,
    ),
    "recordings": Recipe(
        recordings,
        "The attack on recorded frames (no simulator in the loop) against the closed-loop attack at equal CPU: "
        "recordings of 5, 20 and 80 clean episodes made in the simulator, and 80 in a shifted cell.",
    ),
}


def recipe_scene(name: str, scene=None) -> str | None:
    """The scene recipe ``name`` runs on: ``scene`` when given, else the recipe's own (its path
    relative to the working directory when it is there, else to the checkout), else None (built-in)."""
    if scene is not None:
        return str(scene)
    own = RECIPES[name].scene
    if own is None or Path(own).exists():
        return own
    return str(Path(__file__).resolve().parents[2] / own)


def _check_inputs(ctx: Context, recipe: Recipe) -> None:
    """Every input the recipe was given, checked before the first (long) job starts: the scene, the
    pool, the source policy and every target (a checkpoint's card, or an ONNX file that loads), and
    the recipe's own check."""
    from sim.configs import load_pool  # lazy: CLI start-up (trimesh, PIL)
    from sim.policies.card import load_card  # lazy: CLI start-up (torch)
    from sim.policies.checkpoint import load_policy  # lazy: CLI start-up (torch, onnxruntime)

    spec = ctx.eval_spec()  # also loads the scene: a bad --scene fails here
    if ctx.cfg.pool is not None:
        load_pool(ctx.cfg.pool, spec)
    for flag, path in [("--policy", ctx.policy)] + [(f"--target {k}", v) for k, v in ctx.targets.items()]:
        if path is None:
            continue
        try:
            load_policy(path) if str(path).lower().endswith((".onnx", ".pt2")) else load_card(path)
        except AdvobjError as err:
            raise ExperimentError(f"{flag}: {err}") from None
    if recipe.check is not None:
        recipe.check(ctx)


def run_experiment(
    name: str,
    cfg: ExperimentConfig,
    out: str | Path,
    policy=None,
    targets=None,
    scene=None,
    progress=True,
    log=print,
    executor=None,
    shards: int = 1,
) -> Path:
    """Run recipe ``name`` (its jobs on ``executor``, serial by default, each evaluation in
    ``shards`` jobs); returns the path of its ``table.md``."""
    if name not in RECIPES:
        raise ExperimentError(f"unknown experiment {name!r}; choose one of {', '.join(RECIPES)}")
    unknown = set(targets or {}) - set(cfg.transfer_targets)
    if unknown:
        raise ExperimentError(
            f"--target: unknown target {sorted(unknown)[0]!r}; choose from {', '.join(cfg.transfer_targets)}"
        )
    out = Path(out)
    ctx = Context(
        cfg,
        out,
        None if policy is None else Path(policy),
        dict(targets or {}),
        recipe_scene(name, scene),
        progress,
        log,
        executor=executor,
        shards=int(shards),
    )
    _check_inputs(ctx, RECIPES[name])
    write_run_info(
        out,
        {
            "job": f"experiment {name}",
            "experiment": cfg.model_dump(mode="json"),
            "policy": None if policy is None else str(policy),
            "targets": {k: str(v) for k, v in (targets or {}).items()},
            "scene": ctx.scene,
        },
        cfg.seed,
    )
    table = RECIPES[name].run(ctx)
    path = out / "table.md"
    path.write_text(table)
    return path
