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
A policy reading several cameras (:func:`sim.policies.contract.policy_cameras`) is rendered every
one of them, and only those, each through its own renderer with its own noise stream; the texture
is shown to every camera, or only to the ``attacked_cameras`` (which camera carries the attack).
"""

from __future__ import annotations

import zlib
from typing import Callable

import numpy as np

from sim.env import ReachEnv
from sim.policies.contract import (
    WRIST_CAMERA,
    call_policy,
    check_scene,
    decode_actions,
    policy_cameras,
    policy_contract,
)
from sim.policies.interface import PolicyError
from sim.policies.rollout import rollout
from sim.variations import Randomization

__all__ = ["noise_rng", "PairedViews", "rollout_paired"]


def noise_rng(seed: int, camera: str = WRIST_CAMERA) -> np.random.Generator:
    """Per-episode sensor-noise stream of ``camera``: a function of the config seed only (paired
    across arms); the wrist camera's as it always was, each scene camera's a stream of its own."""
    key = [int(seed), 0x5E75] + ([] if camera == WRIST_CAMERA else [zlib.crc32(camera.encode())])
    return np.random.default_rng(np.random.SeedSequence(key))


def _noisy(rgb: np.ndarray, z: np.ndarray | None) -> np.ndarray:
    if z is None:
        return rgb
    return np.clip(np.rint(rgb.astype(np.float32) + z), 0, 255).astype(np.uint8)


class PairedViews:
    """Renders the attacked and the clean observations of an env's worlds, through each camera.

    ``texture``: the attack texture on the adversarial object (``None``: the clean look only, and
    the attacked view is the clean one). ``stereo``: the wrist camera's right partner is rendered
    too (one-camera policies only). ``cameras``: the cameras rendered (each must be among the
    env's), the wrist camera first if read; ``attacked_cameras``: those whose attacked view shows
    the texture (None: all); the others show the benign look in both views.
    """

    def __init__(
        self,
        env,
        texture: np.ndarray | None = None,
        stereo: bool = False,
        cameras: tuple[str, ...] = (WRIST_CAMERA,),
        attacked_cameras: tuple[str, ...] | None = None,
    ):
        self.env = env
        self.adv = env.adv_index
        self.cameras = tuple(cameras)
        self.attacked = texture is not None
        self.stereo = bool(stereo)
        self.attacked_cameras = self.cameras if attacked_cameras is None else tuple(attacked_cameras)
        if self.attacked:
            # The color node keeps the benign look; the attack texture is a variant, so the
            # attacked and the clean view of one state come from the same scene setup.
            for name in self.attacked_cameras:
                env.renderers[name].add_variant(self.adv, "attack", texture)
        self.noise = [dict() for _ in range(env.num_envs)]

    def reset(self, i: int, seed: int) -> None:
        self.noise[i] = {name: noise_rng(seed, name) for name in self.cameras}

    def _camera_views(self, i: int, name: str) -> dict[str, np.ndarray]:
        w = self.env.worlds[i]
        r = self.env.renderers[name]
        w.prepare(r)
        if name == WRIST_CAMERA:
            poses = [w.camera_pose()] + ([w.camera_pose(right=True)] if self.stereo else [])
        else:
            poses = [w.camera_pose(name)]
        std = w.appearance.noise_std
        attacked = self.attacked and name in self.attacked_cameras
        out = {"adv": [], "clean": []}
        for T in poses:
            z = (
                self.noise[i][name].normal(0.0, std * 255.0, size=(r.height, r.width, 3)).astype(np.float32)
                if std > 0
                else None
            )
            clean = _noisy(r.render(T, with_ids=False).rgb, z)
            out["clean"].append(clean)
            out["adv"].append(
                _noisy(r.render(T, with_ids=False, variants={self.adv: "attack"}).rgb, z) if attacked else clean
            )
        return {k: np.stack(v) for k, v in out.items()}

    def views(self, i: int) -> dict:
        """``{"adv": (V, H, W, 3), "clean": (V, H, W, 3)}`` uint8 of the first camera (V = 1, or 2
        for the stereo pair) and ``"cameras": {camera: {"adv": ..., "clean": ...}}`` of each camera."""
        per = {name: self._camera_views(i, name) for name in self.cameras}
        first = per[self.cameras[0]]
        return {"adv": first["adv"], "clean": first["clean"], "cameras": per}


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
    attacked_cameras: tuple[str, ...] | None = None,
) -> None:
    """Roll out one episode per config, the policy acting on the attacked views (the clean ones
    when ``texture`` is None); ``on_done(j, slot, result)`` as each ends.

    Every camera the policy reads (:func:`sim.policies.contract.policy_cameras`) is rendered, and
    only those; each keeps its own sensor-noise stream.

    Args:
        policy: ``act(images[, state]) -> actions`` (:func:`sim.policies.contract.call_policy`:
            ``(B, S, S, 3)`` uint8 for a one-camera policy with ``image_size = S``, else
            ``{camera: (B, H_c, W_c, 3)}``). A joint-space policy (its contract's ``control`` is
            ``"joint"``) runs on the scene's arm (``ReachEnv(control="joint")``): it reads the
            joint positions and its joint targets are executed within the arm's limits, as in
            :func:`sim.policies.rollout.rollout`.
        spec: the scene as rendered (any mesh swap or stereo baseline already applied); it must
            have every camera the policy reads, at its input's size (:func:`sim.policies.contract.check_scene`).
        configs: initial configurations (:class:`sim.configs.InitialConfig`).
        num_envs: parallel slots; also the policy's batch size (times views, times 2 when
            attacked), whatever the number of slots that ask.
        on_done: ``on_done(j, slot, result)``, ``j`` the index into ``configs`` and ``result``
            :func:`sim.policies.rollout.rollout`'s.
        texture: the attack texture ((H, W, 3) uint8) on the adversarial object, or None.
        stereo: the policy sees the left and right wrist cameras; its action is the two views' mean.
        randomization: the worlds' appearance randomisation (default: none).
        on_fill: ``on_fill(slot, j)`` after a slot is reset to start ``configs[j]``.
        on_actions: ``on_actions(slots, T_world_tcp, steps, a_adv, a_clean, views)`` after each
            policy call: the asking slots, their ``(n, 4, 4)`` TCP poses and step counts, the
            decoded ``(n, K, A)`` actions on the attacked and on the clean views (``A``: 6 for a
            TCP action, one per joint for a joint action), and the views (:meth:`PairedViews.views`,
            one per slot). For a joint-space policy also ``q=`` the slots' ``(n, n_joints)`` joint
            positions and ``arm=`` the scene's :class:`sim.ik.SceneArm`, what
            :func:`sim.policies.contract.to_delta` needs to turn a joint action into its TCP motion.
        attacked_cameras: the cameras whose attacked view shows the texture (None: every camera
            the policy reads); each must be one the policy reads.
    """
    if not configs:
        return
    check_scene(policy, spec)
    cameras = policy_cameras(policy)
    if attacked_cameras is not None:
        for name in attacked_cameras:
            if name not in cameras:
                raise PolicyError(
                    f"attacked camera {name!r}: the policy reads {', '.join(cameras)}; the texture can only be shown "
                    "to a camera it reads"
                )
    if stereo and cameras != (WRIST_CAMERA,):
        raise PolicyError(
            f"stereo: the stereo pair is the wrist camera's, for a policy reading it alone; this one reads "
            f"{', '.join(cameras)}"
        )
    S = int(policy.image_size)
    N = max(1, min(int(num_envs), len(configs)))
    contract = policy_contract(policy)
    env = ReachEnv(
        spec,
        num_envs=N,
        image_size=S,
        seed=0,
        randomization=randomization,
        render_obs=False,
        cameras=cameras,
        control=contract.control,
    )
    try:
        obs = PairedViews(env, texture, stereo, cameras, attacked_cameras)

        def fill(i: int, j: int) -> None:
            obs.reset(i, configs[j].seed)
            if on_fill is not None:
                on_fill(i, j)

        def query(slots, state):
            views = [obs.views(i) for i in slots]
            V = views[0]["adv"].shape[0]
            n_rows = len(slots) * V * (2 if obs.attacked else 1)
            # A fixed batch size: conv kernels pick their blocking by batch size, so an image's
            # action would otherwise depend (in the last bits) on which other episodes share its
            # step, and an episode's row on how the evaluation was sharded.
            fixed = int(num_envs) * V * (2 if obs.attacked else 1)
            batches = {}
            for name in cameras:
                per = [v["cameras"][name] for v in views]
                b = np.concatenate([p["adv"] for p in per] + ([p["clean"] for p in per] if obs.attacked else []))
                if n_rows < fixed:
                    b = np.concatenate([b, np.zeros((fixed - n_rows, *b.shape[1:]), b.dtype)])
                batches[name] = b
            st = None if state is None else np.repeat(state, V, axis=0)
            if st is not None and obs.attacked:
                st = np.concatenate([st, st])
            if st is not None and n_rows < fixed:
                st = np.concatenate([st, np.zeros((fixed - n_rows, st.shape[1]), st.dtype)])
            B = n_rows
            images = batches[cameras[0]] if len(cameras) == 1 else batches
            raw = decode_actions(np.asarray(call_policy(policy, images, st), dtype=np.float64)[:B], contract, B)
            a = raw.reshape(B // V, V, *raw.shape[1:]).mean(1)  # stereo: the views' mean action
            a_adv = a[: len(slots)]
            a_clean = a[len(slots) :] if obs.attacked else a_adv
            if on_actions is not None:
                # a joint-space policy's actions mean nothing without the joints they move from
                joints = {} if env.arm is None else {"q": env.q[slots], "arm": env.arm}
                on_actions(slots, env.T_world_tcp[slots], env.steps[slots], a_adv, a_clean, views, **joints)
            return a_adv

        rollout(env, configs, policy, on_done, query=query, on_fill=fill)
    finally:
        env.close()
