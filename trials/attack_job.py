"""The attack job behind ``advobj attack run`` and the demo: build, resume, run, write outputs."""

from __future__ import annotations

from pathlib import Path

__all__ = ["attack_job", "feasible_pool_path"]


def feasible_pool_path(policy_dir: Path) -> Path:
    """The task-feasible pool of a policy: ``<dir>/feasible_pool.json`` (written by ``advobj policy
    train``), else ``<dir>/eval/feasible_pool.json`` (written by ``advobj policy eval``)."""
    own = Path(policy_dir) / "feasible_pool.json"
    evaluated = Path(policy_dir) / "eval" / "feasible_pool.json"
    return evaluated if not own.is_file() and evaluated.is_file() else own


def attack_job(policy_dir, preset: str, config_path, scene_path, pool_path, out, resume: bool, progress: bool = True) -> dict:
    import yaml

    from attack.optimize import AttackError, AttackRun, find_checkpoint, resolve_config, run_attack
    from attack.outputs import write_outputs
    from sim.configs import load_pool
    from sim.policies.checkpoint import load_policy
    from sim.runinfo import write_run_info
    from trials.scene_tools import load_spec

    overrides = {}
    if config_path is not None:
        try:
            overrides = yaml.safe_load(Path(config_path).read_text()) or {}
        except (OSError, yaml.YAMLError) as err:
            raise AttackError(f"{config_path}: cannot read attack config ({err})") from None
        if not isinstance(overrides, dict):
            raise AttackError(f"{config_path}: an attack config must be a mapping of fields")
    cfg = resolve_config(preset, overrides, source=str(config_path or "<preset>"))
    spec = load_spec(scene_path)
    policy = load_policy(policy_dir, cfg.device)
    pool_file = Path(pool_path) if pool_path is not None else feasible_pool_path(policy_dir)
    pool = load_pool(pool_file, spec) if pool_file.is_file() else None
    out = Path(out)
    run = AttackRun(policy, spec, cfg, pool=pool, out_dir=out)
    try:
        before = run.texture.clone()
        if resume:
            ckpt = find_checkpoint(out)
            if ckpt is None:
                raise AttackError(f"{out}: --resume given but no checkpoint found there")
            run.load_checkpoint(ckpt)
        write_run_info(out, {"job": "attack", "preset": preset, "attack": cfg.model_dump(), "policy": str(policy_dir),
                             "pool": str(pool_file) if pool is not None else None, "scene": spec.model_dump(mode="json")}, cfg.seed)
        run_attack(run, progress=progress)
        return write_outputs(run, out, before)
    finally:
        run.close()
