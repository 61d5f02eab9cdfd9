"""The attack job behind ``advobj attack run`` and the demo: build, resume, run, write outputs."""

from __future__ import annotations

import json
from pathlib import Path

from pydantic import Field

from attack.artifact import write_config_record
from attack.optimize import AttackError, AttackRun, fixed_light_warning, resolve_config, run_attack
from attack.outputs import texture_trail, write_outputs
from attack.state import find_checkpoint
from sim.configio import StrictModel, file_error, read_yaml
from sim.configs import PoolError, in_part, load_pool, save_pool, spec_fingerprint
from sim.policies.checkpoint import load_policy
from sim.policies.competence import DEFAULT_MIN_CLEAN_SUCCESS, require_competence
from sim.policies.pool import build_feasible, built_pool_path, feasible_pool_path
from sim.runinfo import write_run_info
from sim.spec import load_spec

__all__ = ["AttackJob", "attack_job", "top_up_attack_pool", "MIN_ATTACK_CONFIGS"]

# Fewer attack-part configurations than this and EOT sees too few viewpoints: build more.
MIN_ATTACK_CONFIGS = 32


def top_up_attack_pool(
    policy,
    spec,
    pool: list,
    cfg,
    out: Path,
    progress: bool = True,
    min_clean_success: float = DEFAULT_MIN_CLEAN_SUCCESS,
    name: str = "policy",
    log=None,
) -> list:
    """``pool`` plus task-feasible configurations built for the parts the attack uses ("attack",
    and "validation" when validation is on) that hold too few (saved as ``out/feasible_pool.json``
    and reused on resume). The evaluation part is never touched. Before the first clean rollout,
    the competence gate (:func:`sim.policies.competence.require_competence`, ``min_clean_success``;
    ``name`` names the policy in its refusal) refuses a policy that does not do the task."""
    path = built_pool_path(out)
    if path.is_file():
        return load_pool(path, spec)
    want = {"attack": MIN_ATTACK_CONFIGS, "validation": cfg.validation_episodes if cfg.validation_every > 0 else 0}
    shortfall = {part: n - len(in_part(pool, part)) for part, n in want.items() if n > len(in_part(pool, part))}
    if shortfall:
        figure = require_competence(
            policy, spec, min_clean_success, part=next(iter(shortfall)), seed=cfg.seed, progress=progress, name=name
        )
        if figure is not None and log is not None:
            log(f"attack: clean success {figure.describe()}")
    extra = []
    for part, short in shortfall.items():
        got, tried = build_feasible(
            policy,
            spec,
            part,
            short,
            cfg.seed,
            8,
            exclude=[c.seed for c in pool],
            progress=progress,
            desc=f"feasible pool ({part})",
        )
        if not got and not in_part(pool, part):
            raise AttackError(
                f"feasible pool: the clean policy reached the goal in none of the {tried} configurations of this "
                f"scene tried for the {part} part, so there is nothing to attack from: it does not do the task "
                "in this scene (check the scene's objects, their sizes and the camera), or give --pool"
            )
        extra += got
    if not extra:
        return pool
    pool = pool + extra
    save_pool(
        path,
        spec,
        pool,
        meta={"definition": "configs where the clean policy reaches the goal", "topped_up": len(extra)},
    )
    return pool


def pool_matches_scene(path: Path, spec) -> bool:
    """Whether the pool file at ``path`` was made for ``spec`` (its fingerprint); False if unreadable."""
    try:
        return json.loads(Path(path).read_text(encoding="utf-8")).get("spec_fingerprint") == spec_fingerprint(spec)
    except (OSError, ValueError, AttributeError):
        return False


def attack_job(
    policy_dir,
    preset: str,
    config_path,
    scene_path,
    pool_path,
    out,
    resume: bool,
    progress: bool = True,
    log=print,
    light_randomization: bool | None = None,
    warn_fixed_light: bool = False,
    recordings=None,
    min_clean_success: float = DEFAULT_MIN_CLEAN_SUCCESS,
) -> dict:
    """``light_randomization``: overrides the preset's and the config file's (None: theirs);
    ``warn_fixed_light``: say up front when the texture will be optimised under the fixed light;
    ``recordings``: a recording folder to attack on instead of simulator rollouts (overrides the
    config file's ``recordings``; :mod:`attack.recorded`): no pool is read or built, and ``run.json``
    records the recording's manifest hash and its episode split.

    ``min_clean_success``: the competence gate (:mod:`sim.policies.competence`; 0: off), for an
    attack in the simulator: once the inputs are checked, a card that records the policy's clean
    success on this scene below it refuses the attack (:class:`sim.policies.competence.IncompetentPolicyError`)
    before anything is written; without such a card, the success is measured before a task-feasible
    pool is topped up (:func:`top_up_attack_pool`)."""
    overrides = {}
    if config_path is not None:
        # An empty file is an empty set of overrides; anything else not a mapping is refused.
        overrides = read_yaml(config_path, "attack config", error=file_error(AttackError), mapping=False)
        overrides = {} if overrides is None else overrides
        if not isinstance(overrides, dict):
            raise AttackError(f"{config_path}: an attack config must be a mapping of fields")
    if light_randomization is not None:
        overrides = {**overrides, "light_randomization": light_randomization}
    if recordings is not None:
        overrides = {**overrides, "recordings": str(recordings)}
    cfg = resolve_config(preset, overrides, source=str(config_path or "<preset>"))
    spec = load_spec(scene_path)
    # White-box now: an ONNX file's conversion is checked here, before a pool is built or anything written.
    policy = load_policy(policy_dir, cfg.device, white_box=True, spec=spec)
    if pool_path is not None and not Path(pool_path).is_file():
        raise AttackError(f"--pool: {pool_path}: no such pool file")
    pool_file = Path(pool_path) if pool_path is not None else feasible_pool_path(policy_dir)
    out = Path(out)
    pool = None
    recorded = cfg.recordings is not None
    if recorded and pool_path is not None:
        raise AttackError("--pool: an attack on --recordings draws no simulator configurations; drop --pool")
    if pool_file.is_file() and not recorded:
        if pool_path is None and not pool_matches_scene(pool_file, spec):
            # The policy's own pool is for the scene it was trained in; an own scene gets its own
            # task-feasible configurations (attack and validation parts only), built and kept here.
            log(
                f"attack: {pool_file} is for another scene; building a task-feasible pool for "
                f"{scene_path or 'the built-in scene'} into {built_pool_path(out)}"
            )
            pool_file = built_pool_path(out)
            pool = []
        else:
            try:
                pool = load_pool(pool_file, spec)
            except PoolError as err:
                raise PoolError(
                    f"{err}; --pool: give a pool made for this scene, or omit --pool to build one"
                ) from None
    if not recorded:  # the inputs are checked: the card's figure, before anything is built or written
        require_competence(policy, spec, min_clean_success, measure=False, name=str(policy_dir))
    if warn_fixed_light and (note := fixed_light_warning(cfg)) is not None:
        log(f"attack: {note}")  # the inputs are checked; before anything is built or optimised
    if pool is not None:
        pool = top_up_attack_pool(
            policy, spec, pool, cfg, out, progress, min_clean_success, name=str(policy_dir), log=log
        )
    run = AttackRun(policy, spec, cfg, pool=pool, out_dir=out)
    try:
        before = run.state.texture.clone()
        if resume:
            ckpt = find_checkpoint(out)
            if ckpt is None:
                raise AttackError(f"{out}: --resume given but no checkpoint found there")
            run.load_checkpoint(ckpt)
        write_run_info(
            out,
            {
                "job": "attack",
                "preset": preset,
                "attack": cfg.model_dump(),
                "policy": str(policy_dir),
                "pool": str(pool_file) if pool is not None else None,
                "scene": spec.model_dump(mode="json"),
                **({"recordings": run.source.provenance()} if recorded else {}),
            },
            cfg.seed,
        )
        write_config_record(out, run.pool, run.val_pool)
        run_attack(run, progress=progress, on_iteration=texture_trail(out, cfg))
        return write_outputs(run, out, before)
    finally:
        run.close()


class AttackJob(StrictModel):
    """What ``advobj attack run`` runs (its options, validated): :meth:`run` is :func:`attack_job`."""

    policy: Path = Field(
        description="white-box policy: a checkpoint directory, a .pt2 file or an .onnx file (converted to torch)"
    )
    preset: str = "quick"
    config: Path | None = Field(None, description="YAML whose fields override the preset's")
    scene: Path | None = Field(None, description="scene YAML (default: the built-in paper scene)")
    pool: Path | None = Field(None, description="task-feasible pool JSON (default: the policy's, if any)")
    out: Path = Path("runs/attack")
    resume: bool = False
    light_randomization: bool | None = Field(
        None, description="randomise the lights during optimisation (None: the preset's and --config's setting)"
    )
    recordings: Path | None = Field(
        None, description="a recording folder: attack on its frames (object composited in) instead of sim rollouts"
    )
    min_clean_success: float = Field(
        DEFAULT_MIN_CLEAN_SUCCESS,
        ge=0.0,
        le=1.0,
        description="refuse a policy whose clean success on the scene is below this fraction (0: no check)",
    )

    def run(self, progress: bool = True, log=print) -> dict:
        return attack_job(
            self.policy,
            self.preset,
            self.config,
            self.scene,
            self.pool,
            self.out,
            self.resume,
            progress,
            log,
            light_randomization=self.light_randomization,
            warn_fixed_light=True,
            recordings=self.recordings,
            min_clean_success=self.min_clean_success,
        )
