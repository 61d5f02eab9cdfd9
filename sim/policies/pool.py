"""The task-feasible pool: initial configurations where the clean policy reaches the goal.

As in the paper (Sec. III-B, EOT), the attack and the attack evaluations start only from
configurations the clean policy solves, so a failure under attack is the attack's doing. The pool
is an ordinary config pool (:func:`sim.configs.save_pool` / :func:`sim.configs.load_pool`) whose
metadata records which policy and evaluation produced it. :func:`build_feasible` finds more
task-feasible configurations of one part of the split, for an evaluation or an attack that holds
too few.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from sim.configs import load_pool, object_local_centers, part_seeds, sample_config, save_pool
from sim.policies.paired import rollout_paired
from sim.policies.rollout import EpisodeResults

__all__ = [
    "FEASIBLE_POOL_NAME",
    "built_pool_path",
    "feasible_pool_path",
    "feasible_configs",
    "write_feasible_pool",
    "load_feasible_pool",
    "build_feasible",
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


def build_feasible(
    policy,
    spec,
    part: str,
    n: int,
    start_seed: int = 0,
    num_envs: int = 8,
    exclude=(),
    max_candidates: int | None = None,
    progress: bool = True,
    desc: str = "feasible pool",
) -> tuple[list, int]:
    """Up to ``n`` task-feasible configurations of ``part`` (:func:`sim.configs.config_part`).

    Candidates are the part's seeds from ``start_seed`` on, minus the seeds in ``exclude`` (those
    already in hand); each is rolled out once under the clean condition (no texture, no
    randomisation, the left camera: :func:`sim.policies.paired.rollout_paired`, the rollout of
    ``advobj eval``'s clean arm) and kept when the policy reaches the goal, the definition of
    task-feasible. At most ``max_candidates`` (default ``4 * n``) are tried. Returns
    ``(configs, candidates tried)``.
    """
    if n <= 0:
        return [], 0
    max_candidates = 4 * n if max_candidates is None else int(max_candidates)
    skip = {int(s) for s in exclude}
    seeds = (s for s in part_seeds(part, start_seed) if s not in skip)
    centers = object_local_centers(spec)
    goal = spec.object_index("goal")

    feasible: list = []
    tried = 0
    bar = tqdm(total=n, desc=desc, disable=not progress, dynamic_ncols=True)
    while len(feasible) < n and tried < max_candidates:
        # twice the shortfall per round: a policy reaching the goal half the time needs one round
        k = min(max(num_envs, 2 * (n - len(feasible))), max_candidates - tried)
        cands = [sample_config(spec, next(seeds), centers) for _ in range(k)]
        ok = np.zeros(k, bool)

        def done(j, _slot, res):
            ok[j] = res["reached"] == goal

        rollout_paired(policy, spec, cands, num_envs, done)
        tried += k
        new = [c for c, good in zip(cands, ok) if good][: n - len(feasible)]
        feasible += new
        bar.update(len(new))
    bar.close()
    return feasible, tried
