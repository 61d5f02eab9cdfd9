"""Closed-loop episodes observed through the standard renderer, an attacked look beside the clean one.

The rollout core of ``advobj eval`` (:func:`trials.eval.evaluate.rollout_condition`, one call per
condition) and of the task-feasible pool (:func:`sim.policies.pool.build_feasible`, the clean
look only), so a configuration is task-feasible exactly when the evaluation's clean arm reaches
the goal from it. The loop is :func:`sim.policies.rollout.rollout`; this module supplies its
query: the views a policy acts on and one fixed-size policy call per step.

At every step the clean observation of a state (the adversarial object in its benign look) is
rendered, and, when a texture is given, the attacked observation of the same state (same light,
same background, same sensor-noise draw) in the same frame via a renderer variant. Rendering is
the standard pyrender path (:class:`sim.render.SceneRenderer`) with the texture on the mesh.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from sim.env import ReachEnv
from sim.policies.contract import call_policy, decode_actions, policy_contract
from sim.policies.rollout import rollout
from sim.variations import Randomization

__all__ = ["noise_rng", "PairedViews", "rollout_paired"]


def noise_rng(seed: int) -> np.random.Generator:
    """Per-episode sensor-noise stream: a function of the config seed only (paired across arms)."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), 0x5E75]))


def _noisy(rgb: np.ndarray, z: np.ndarray | None) -> np.ndarray:
    if z is None:
        return rgb
    return np.clip(np.rint(rgb.astype(np.float32) + z), 0, 255).astype(np.uint8)


class PairedViews:
    """Renders the attacked and the clean observations of an env's worlds.

    ``texture``: the attack texture on the adversarial object (``None``: the clean look only, and
    the attacked view is the clean one). ``stereo``: the right camera is rendered too.
    """

    def __init__(self, env, texture: np.ndarray | None = None, stereo: bool = False):
        self.env = env
        self.adv = env.adv_index
        self.attacked = texture is not None
        self.stereo = bool(stereo)
        if self.attacked:
            # The color node keeps the benign look; the attack texture is a variant, so the
            # attacked and the clean view of one state come from the same scene setup.
            env.renderer.add_variant(self.adv, "attack", texture)
        self.noise = [None] * env.num_envs

    def reset(self, i: int, seed: int) -> None:
        self.noise[i] = noise_rng(seed)

    def views(self, i: int) -> dict[str, np.ndarray]:
        """``{"adv": (V, H, W, 3), "clean": (V, H, W, 3)}`` uint8, V = 1 (mono) or 2 (stereo)."""
        w = self.env.worlds[i]
        r = self.env.renderer
        w.prepare()
        poses = [w.camera_pose()] + ([w.camera_pose(right=True)] if self.stereo else [])
        std = w.appearance.noise_std
        out = {"adv": [], "clean": []}
        for T in poses:
            z = (
                self.noise[i].normal(0.0, std * 255.0, size=(r.height, r.width, 3)).astype(np.float32)
                if std > 0
                else None
            )
            clean = _noisy(r.render(T, with_ids=False).rgb, z)
            out["clean"].append(clean)
            out["adv"].append(
                _noisy(r.render(T, with_ids=False, variants={self.adv: "attack"}).rgb, z) if self.attacked else clean
            )
        return {k: np.stack(v) for k, v in out.items()}


def rollout_paired(
    policy,
    spec,
    configs,
    num_envs: int,
    on_done: Callable[[int, int, dict], None],
    *,
    texture: np.ndarray | None = None,
    stereo: bool = False,
    randomization: Randomization | None = None,
    on_fill: Callable[[int, int], None] | None = None,
    on_actions: Callable | None = None,
) -> None:
    """Roll out one episode per config, the policy acting on the attacked view (the clean one
    when ``texture`` is None); ``on_done(j, slot, result)`` as each ends.

    Args:
        policy: ``act(images (B, S, S, 3) uint8[, state]) -> actions`` with ``image_size = S``.
        spec: the scene as rendered (any mesh swap or stereo baseline already applied).
        configs: initial configurations (:class:`sim.configs.InitialConfig`).
        num_envs: parallel slots; also the policy's batch size (times views, times 2 when
            attacked), whatever the number of slots that ask.
        on_done: ``on_done(j, slot, result)``, ``j`` the index into ``configs`` and ``result``
            :func:`sim.policies.rollout.rollout`'s.
        texture: the attack texture ((H, W, 3) uint8) on the adversarial object, or None.
        stereo: the policy sees the left and right cameras; its action is the two views' mean.
        randomization: the worlds' appearance randomisation (default: none).
        on_fill: ``on_fill(slot, j)`` after a slot is reset to start ``configs[j]``.
        on_actions: ``on_actions(slots, T_world_tcp, steps, a_adv, a_clean, views)`` after each
            policy call: the asking slots, their ``(n, 4, 4)`` TCP poses and step counts, the
            decoded ``(n, K, 6)`` actions on the attacked and on the clean views, and the views
            (:meth:`PairedViews.views`, one per slot).
    """
    if not configs:
        return
    S = int(policy.image_size)
    N = max(1, min(int(num_envs), len(configs)))
    env = ReachEnv(spec, num_envs=N, image_size=S, seed=0, randomization=randomization, render_obs=False)
    contract = policy_contract(policy)
    try:
        obs = PairedViews(env, texture, stereo)

        def fill(i: int, j: int) -> None:
            obs.reset(i, configs[j].seed)
            if on_fill is not None:
                on_fill(i, j)

        def query(slots, state):
            views = [obs.views(i) for i in slots]
            V = views[0]["adv"].shape[0]
            batch = np.concatenate([v["adv"] for v in views] + ([v["clean"] for v in views] if obs.attacked else []))
            st = None if state is None else np.repeat(state, V, axis=0)
            if st is not None and obs.attacked:
                st = np.concatenate([st, st])
            # A fixed batch size: conv kernels pick their blocking by batch size, so an image's
            # action would otherwise depend (in the last bits) on which other episodes share its
            # step, and an episode's row on how the evaluation was sharded.
            B = len(batch)
            fixed = int(num_envs) * V * (2 if obs.attacked else 1)
            if B < fixed:
                batch = np.concatenate([batch, np.zeros((fixed - B, *batch.shape[1:]), batch.dtype)])
                if st is not None:
                    st = np.concatenate([st, np.zeros((fixed - B, st.shape[1]), st.dtype)])
            raw = decode_actions(np.asarray(call_policy(policy, batch, st), dtype=np.float64)[:B], contract, B)
            a = raw.reshape(B // V, V, *raw.shape[1:]).mean(1)  # stereo: the views' mean action
            a_adv = a[: len(slots)]
            a_clean = a[len(slots) :] if obs.attacked else a_adv
            if on_actions is not None:
                on_actions(slots, env.T_world_tcp[slots], env.steps[slots], a_adv, a_clean, views)
            return a_adv

        rollout(env, configs, policy, on_done, query=query, on_fill=fill)
    finally:
        env.close()
