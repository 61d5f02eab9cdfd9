"""Closed-loop episodes of a policy in :class:`sim.env.ReachEnv`: clean evaluation.

Episodes are defined by their initial-configuration seeds, so an evaluation is reproducible and
its successful configurations can be written out as the task-feasible pool (:mod:`sim.policies.pool`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from pydantic import Field

from sim.configio import StrictModel
from sim.stats import Proportion, proportion

__all__ = ["EnvConfig", "make_env", "set_randomization", "EpisodeResults", "run_episodes", "evaluate_policy", "EVAL_SEED_BASE"]


class EnvConfig(StrictModel):
    """How the training/evaluation env renders: image size and appearance randomisation."""

    image_size: int = Field(64, ge=32, le=512)
    light: Literal["fixed", "bright", "dim", "random"] = "fixed"
    background: Literal["fixed", "varied", "mixed"] = "fixed"
    noise_std: float = Field(0.0, ge=0.0, le=0.5)

    def randomization(self):
        from sim.variations import Randomization

        return Randomization(light=self.light, background=self.background, noise_std=self.noise_std)


def make_env(spec, cfg: EnvConfig, num_envs: int, seed: int = 0):
    """A :class:`sim.env.ReachEnv` rendering ``cfg.image_size`` px with ``cfg``'s randomisation."""
    from sim.env import ReachEnv

    return ReachEnv(spec, num_envs=num_envs, image_size=cfg.image_size, seed=seed, randomization=cfg.randomization())


def set_randomization(env, cfg: EnvConfig) -> None:
    """Switch the appearance randomisation of ``env`` (applies from the next reset).

    One env (one GL context) then serves both randomised training and clean evaluation.
    """
    r = cfg.randomization()
    for w in env.worlds:
        w.randomization = r

# Evaluation seeds start at 0 by default; training draws its configurations from seeds at or
# above TRAIN_SEED_BASE (see sim.policies.dagger), so the two never overlap.
EVAL_SEED_BASE = 0


@dataclass
class EpisodeResults:
    """Per-episode outcomes of ``n`` episodes (index order = seed order)."""

    seeds: np.ndarray  # (n,) int initial-configuration seeds
    success: np.ndarray  # (n,) bool reached the goal
    reached: np.ndarray  # (n,) int index of the reached object, -1 = none
    steps: np.ndarray  # (n,) int steps taken
    min_goal_dist: np.ndarray  # (n,) m closest approach to the goal centre
    configs: list = field(default_factory=list)  # (n,) sim.configs.InitialConfig

    @property
    def success_rate(self) -> Proportion:
        return proportion(int(self.success.sum()), len(self.success))

    def summary(self, object_names: list[str] | None = None) -> dict:
        out = {"success": self.success_rate.to_dict(), "mean_steps": float(self.steps.mean()) if len(self.steps) else None,
               "mean_min_goal_dist_m": float(self.min_goal_dist.mean()) if len(self.steps) else None}
        if object_names is not None:
            counts = {name: int((self.reached == k).sum()) for k, name in enumerate(object_names)}
            counts["none"] = int((self.reached < 0).sum())
            out["reached"] = counts
        return out


def run_episodes(env, policy, seeds, progress=None) -> EpisodeResults:
    """Run one episode per seed to completion, ``env.num_envs`` at a time.

    Args:
        env: a :class:`sim.env.ReachEnv` (its image size must match ``policy.image_size``).
        policy: anything with ``act(images (B, H, W, 3) uint8) -> (B, 6)``.
        seeds: initial-configuration seeds, one episode each.
        progress: optional callable ``progress(n_finished_episodes)`` (e.g. a tqdm update).
    """
    if (env.height, env.width) != (policy.image_size, policy.image_size):
        raise ValueError(f"env renders {env.height}x{env.width} px but the policy expects {policy.image_size} px")
    seeds = [int(s) for s in seeds]
    n, N = len(seeds), env.num_envs
    success = np.zeros(n, bool)
    reached = np.full(n, -1, np.int64)
    steps = np.zeros(n, np.int64)
    min_goal = np.zeros(n)
    configs = [None] * n
    for start in range(0, n, N):
        chunk = seeds[start : start + N]
        # A short last chunk: pad with repeats of its first seed and ignore the padding.
        padded = chunk + [chunk[0]] * (N - len(chunk))
        env.reset_envs(range(N), seeds=padded)
        obs = env.observe()
        while not env.done.all():
            obs, *_ = env.step(policy.act(obs))
        m = len(chunk)
        success[start : start + m] = (env.reached == env.goal_index)[:m]
        reached[start : start + m] = env.reached[:m]
        steps[start : start + m] = env.steps[:m]
        min_goal[start : start + m] = env.min_dist[:m, env.goal_index]
        configs[start : start + m] = env.configs[:m]
        if progress is not None:
            progress(m)
    return EpisodeResults(np.asarray(seeds, np.int64), success, reached, steps, min_goal, configs)


def evaluate_policy(policy, spec, episodes: int, seed: int = EVAL_SEED_BASE, num_envs: int = 16, env_cfg: EnvConfig | None = None,
                    env=None, progress: bool = True) -> EpisodeResults:
    """Clean evaluation: ``episodes`` episodes from seeds ``seed .. seed + episodes - 1``.

    ``env_cfg`` defaults to no randomisation at the policy's image size. Pass ``env`` to reuse an
    existing :class:`sim.env.ReachEnv` (its randomisation is switched to ``env_cfg``).
    """
    from tqdm.auto import tqdm

    env_cfg = env_cfg or EnvConfig(image_size=policy.image_size)
    own = env is None
    if own:
        env = make_env(spec, env_cfg, min(num_envs, max(1, episodes)))
    else:
        set_randomization(env, env_cfg)
    try:
        with tqdm(total=episodes, desc="eval", unit="ep", disable=not progress) as bar:
            return run_episodes(env, policy, range(seed, seed + episodes), progress=bar.update)
    finally:
        if own:
            env.close()
