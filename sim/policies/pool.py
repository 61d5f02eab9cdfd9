"""The task-feasible pool: initial configurations where the clean policy reaches the goal.

As in the paper (Sec. III-B, EOT), the attack and the attack evaluations start only from
configurations the clean policy solves, so a failure under attack is the attack's doing. The pool
is an ordinary config pool (:func:`sim.configs.save_pool` / :func:`sim.configs.load_pool`) whose
metadata records which policy and evaluation produced it.
"""

from __future__ import annotations

from pathlib import Path

from sim.configs import load_pool, save_pool
from sim.policies.rollout import EpisodeResults

__all__ = [
    "FEASIBLE_POOL_NAME",
    "built_pool_path",
    "feasible_pool_path",
    "feasible_configs",
    "write_feasible_pool",
    "load_feasible_pool",
]

FEASIBLE_POOL_NAME = "feasible_pool.json"


def built_pool_path(out_dir: str | Path) -> Path:
    """Where a command or job keeps the task-feasible pool it builds: ``<out_dir>/feasible_pool.json``."""
    return Path(out_dir) / FEASIBLE_POOL_NAME


def feasible_pool_path(policy_dir: Path) -> Path:
    """The task-feasible pool of a policy: ``<dir>/feasible_pool.json`` (written by ``advobj policy
    train``), else ``<dir>/eval/feasible_pool.json`` (written by ``advobj policy eval``)."""
    own = built_pool_path(policy_dir)
    evaluated = built_pool_path(Path(policy_dir) / "eval")
    return evaluated if not own.is_file() and evaluated.is_file() else own


def feasible_configs(results: EpisodeResults) -> list:
    """The :class:`sim.configs.InitialConfig` of every successful episode, in seed order."""
    return [c for c, ok in zip(results.configs, results.success) if ok]


def write_feasible_pool(path: str | Path, spec, results: EpisodeResults, meta: dict | None = None) -> Path:
    """Write the successful episodes' configurations to ``path`` (JSON config pool)."""
    configs = feasible_configs(results)
    info = {
        "kind": "task-feasible",
        "episodes": int(len(results.success)),
        "feasible": len(configs),
        "success": results.success_rate.to_dict(),
    }
    info.update(meta or {})
    return save_pool(path, spec, configs, meta=info)


def load_feasible_pool(path: str | Path, spec=None) -> list:
    """Read a task-feasible pool (refused if it was made for a different scene)."""
    return load_pool(path, spec)
