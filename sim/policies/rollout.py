"""Closed-loop episodes of a policy in :class:`sim.env.ReachEnv`: clean evaluation.

Episodes are defined by their initial-configuration seeds, so an evaluation is reproducible and
its successful configurations can be written out as the task-feasible pool (:mod:`sim.policies.pool`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Literal

import numpy as np
from pydantic import Field
from tqdm.auto import tqdm

from sim.action import nonfinite_rows
from sim.configio import StrictModel
from sim.env import ReachEnv
from sim.policies.contract import (
    WRIST_CAMERA,
    ActionQueue,
    call_policy,
    decode_actions,
    policy_cameras,
    policy_contract,
    state_vector,
    to_delta,
    to_joint_target,
)
from sim.policies.interface import IMAGE_SIZE_MAX_PX, IMAGE_SIZE_MIN_PX, PolicyError
from sim.stats import Proportion, proportion
from sim.variations import Randomization

__all__ = [
    "EnvConfig",
    "make_env",
    "set_randomization",
    "EpisodeResults",
    "rollout",
    "run_episodes",
    "evaluate_policy",
    "EVAL_SEED_BASE",
]


class EnvConfig(StrictModel):
    """How the training/evaluation env renders: image size and appearance randomisation."""

    image_size: int = Field(64, ge=IMAGE_SIZE_MIN_PX, le=IMAGE_SIZE_MAX_PX)
    light: Literal["fixed", "bright", "dim", "random"] = "fixed"
    background: Literal["fixed", "varied", "mixed"] = "fixed"
    noise_std: float = Field(0.0, ge=0.0, le=0.5)

    def randomization(self):
        return Randomization(light=self.light, background=self.background, noise_std=self.noise_std)


def make_env(spec, cfg: EnvConfig, num_envs: int, seed: int = 0, cameras=(WRIST_CAMERA,), control: str = "tcp"):
    """A :class:`sim.env.ReachEnv` rendering ``cfg.image_size`` px with ``cfg``'s randomisation
    (the wrist camera at that size, each other camera in ``cameras`` at its own), moving the TCP or,
    with ``control="joint"``, the scene's arm (a joint-space policy's contract says which)."""
    return ReachEnv(
        spec,
        num_envs=num_envs,
        image_size=cfg.image_size,
        seed=seed,
        randomization=cfg.randomization(),
        cameras=tuple(cameras),
        control=control,
    )


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
    policy_error: np.ndarray | None = None  # (n,) bool ended by a non-finite action; None = all False

    def __post_init__(self):
        if self.policy_error is None:
            self.policy_error = np.zeros(len(self.seeds), bool)

    @property
    def success_rate(self) -> Proportion:
        return proportion(int(self.success.sum()), len(self.success))

    def summary(self, object_names: list[str] | None = None) -> dict:
        out = {
            "success": self.success_rate.to_dict(),
            "mean_steps": float(self.steps.mean()) if len(self.steps) else None,
            "mean_min_goal_dist_m": float(self.min_goal_dist.mean()) if len(self.steps) else None,
            "policy_errors": int(self.policy_error.sum()),
        }
        if object_names is not None:
            counts = {name: int((self.reached == k).sum()) for k, name in enumerate(object_names)}
            counts["none"] = int((self.reached < 0).sum())
            out["reached"] = counts
        return out


def rollout(
    env,
    starts,
    policy,
    on_done: Callable[[int, int, dict], None],
    query: Callable | None = None,
    on_fill: Callable[[int, int], None] | None = None,
    fixed_batch: bool = True,
) -> None:
    """The closed-loop rollout: one episode per start, ``env.num_envs`` at a time, each slot refilled
    as its episode ends. The one loop behind clean evaluation, ``advobj eval`` and the attack's
    validation; the policy's contract (:mod:`sim.policies.contract`) is applied here only.

    Args:
        env: a :class:`sim.env.ReachEnv`.
        starts: initial configurations (:class:`sim.configs.InitialConfig`) or seeds, one episode each.
        policy: what acts; its contract says what it reads and what its output means.
        on_done: ``on_done(j, slot, result)`` as episode ``j`` (index into ``starts``) ends, with
            ``result``: ``reached`` (object index, -1 none), ``policy_error`` (the policy output a
            non-finite action, which is never executed: the episode ended there), ``steps``, ``min_dist (K,)`` m,
            ``T_world_tcp (4, 4)`` final pose, ``config``.
        query: ``query(slots, state) -> raw outputs (len(slots), ...)`` for the slots that need a
            new chunk, ``state`` their ``(len(slots), D)`` state or None; default: the policy on
            the env's observations (all ``N`` rows when ``fixed_batch``, so an image's action never
            depends on how many episodes share its step); a policy reading several cameras gets
            ``env.images()`` (the env must render them: ``ReachEnv(cameras=...)``).
        on_fill: ``on_fill(slot, j)`` after a slot is reset to start ``j`` (per-episode state).
    """
    starts = list(starts)
    if not starts:
        return
    contract = policy_contract(policy)
    N = env.num_envs
    gripper_m = float(env.spec.gripper.opening_m)
    if contract.control != env.control:
        raise PolicyError(
            f"control: the policy ({contract.describe()}) moves the {'joints' if contract.is_joint_space else 'TCP'} "
            f"but the env is made with control={env.control!r}; make it with control={contract.control!r}"
        )
    if query is None:
        cameras = policy_cameras(policy)
        if cameras != (WRIST_CAMERA,):
            missing = [c for c in cameras if c not in env.cameras]
            if missing:
                raise PolicyError(
                    f"cameras: the policy reads {', '.join(cameras)} but the env renders {', '.join(env.cameras)}; "
                    f"make it with cameras={cameras}"
                )

        def query(slots, state):
            # one camera: the observation as always; several: every camera's images, by name
            obs = env.observe() if cameras == (WRIST_CAMERA,) else env.images()
            if fixed_batch:
                full = state_vector(contract, env.T_world_tcp, gripper_m, env.q)
                return np.asarray(call_policy(policy, obs, full))[slots]
            part = {k: v[slots] for k, v in obs.items()} if isinstance(obs, dict) else obs[slots]
            return np.asarray(call_policy(policy, part, state))

    queue = ActionQueue(contract, N)
    todo = list(range(len(starts)))[::-1]
    slot = [-1] * N

    def fill(i: int) -> None:
        j = todo.pop()
        slot[i] = j
        s = starts[j]
        if isinstance(s, (int, np.integer)):
            env.reset_envs([i], seeds=[int(s)])
        else:
            env.reset_envs([i], configs=[s])
        queue.clear(i)
        if on_fill is not None:
            on_fill(i, j)

    for i in range(min(N, len(starts))):
        fill(i)
    while any(j >= 0 for j in slot):
        active = [i for i in range(N) if slot[i] >= 0 and not env.done[i]]
        if active:
            need = queue.needs(active)
            if need:
                q = env.q
                raw = query(
                    need, state_vector(contract, env.T_world_tcp[need], gripper_m, None if q is None else q[need])
                )
                queue.push(need, decode_actions(np.asarray(raw, dtype=np.float64), contract, len(need)))
            chosen = queue.pop(active)
            bad = nonfinite_rows(chosen)
            if bad.any():  # a policy error (sim.action.POLICY_ERROR), as on the real arm: never executed
                env.end_with_policy_error([active[k] for k in np.flatnonzero(bad)])
                active = [i for k, i in enumerate(active) if not bad[k]]
                chosen = chosen[~bad]
            if active:
                actions = np.zeros((N, env.action_dim))
                if contract.is_joint_space:  # joint targets; the env enforces the limits (sim.env)
                    actions[~env.done] = env.q[~env.done]
                    actions[active] = to_joint_target(env.q[active], chosen, contract.action.kind)
                else:
                    actions[active] = to_delta(
                        env.T_world_tcp[active], chosen, contract.action.kind, env.max_step_m, env.max_step_rad
                    )
                env.step(actions)
        for i in range(N):
            if slot[i] >= 0 and env.done[i]:
                j = slot[i]
                on_done(
                    j,
                    i,
                    {
                        "reached": int(env.reached[i]),
                        "policy_error": bool(env.policy_error[i]),
                        "steps": int(env.steps[i]),
                        "min_dist": env.min_dist[i].copy(),
                        "T_world_tcp": env.worlds[i].T_world_tcp.copy(),
                        "config": env.worlds[i].config,
                    },
                )
                slot[i] = -1
                if todo:
                    fill(i)


def run_episodes(env, policy, seeds, progress=None) -> EpisodeResults:
    """Run one episode per seed to completion, ``env.num_envs`` at a time (:func:`rollout`).

    Args:
        env: a :class:`sim.env.ReachEnv` (its image size must match ``policy.image_size``).
        policy: anything behind the policy interface (``act(images[, state])``).
        seeds: initial-configuration seeds, one episode each.
        progress: optional callable ``progress(n_finished_episodes)`` (e.g. a tqdm update).
    """
    if (env.height, env.width) != (policy.image_size, policy.image_size):
        raise ValueError(f"env renders {env.height}x{env.width} px but the policy expects {policy.image_size} px")
    seeds = [int(s) for s in seeds]
    n = len(seeds)
    success = np.zeros(n, bool)
    reached = np.full(n, -1, np.int64)
    steps = np.zeros(n, np.int64)
    min_goal = np.zeros(n)
    perr = np.zeros(n, bool)
    configs = [None] * n
    goal = env.goal_index

    def done(j, _slot, res):
        reached[j] = res["reached"]
        success[j] = res["reached"] == goal
        steps[j] = res["steps"]
        perr[j] = res["policy_error"]
        min_goal[j] = res["min_dist"][goal]
        configs[j] = res["config"]
        if progress is not None:
            progress(1)

    rollout(env, seeds, policy, done)
    return EpisodeResults(np.asarray(seeds, np.int64), success, reached, steps, min_goal, configs, perr)


def evaluate_policy(
    policy,
    spec,
    episodes: int,
    seed: int = EVAL_SEED_BASE,
    num_envs: int = 16,
    env_cfg: EnvConfig | None = None,
    env=None,
    progress: bool = True,
) -> EpisodeResults:
    """Clean evaluation: ``episodes`` episodes from seeds ``seed .. seed + episodes - 1``.

    ``env_cfg`` defaults to no randomisation at the policy's image size. Pass ``env`` to reuse an
    existing :class:`sim.env.ReachEnv` (its randomisation is switched to ``env_cfg``).
    """
    env_cfg = env_cfg or EnvConfig(image_size=policy.image_size)
    own = env is None
    if own:
        control = policy_contract(policy).control
        env = make_env(spec, env_cfg, min(num_envs, max(1, episodes)), cameras=policy_cameras(policy), control=control)
    else:
        set_randomization(env, env_cfg)
    try:
        with tqdm(total=episodes, desc="eval", unit="ep", disable=not progress) as bar:
            return run_episodes(env, policy, range(seed, seed + episodes), progress=bar.update)
    finally:
        if own:
            env.close()
