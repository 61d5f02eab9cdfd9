"""Batched reach environment with a gymnasium-style API.

``N`` :class:`sim.world.SimWorld` instances share one renderer (one GL context). An episode ends
at the first step where an object is reached (:func:`sim.outcome.reach_outcome`) or after
``spec.episode.max_steps`` steps. A finished env stays frozen (its observation and state no longer
change) until it is reset, so batches of episodes can be run to completion without auto-reset
surprises; :meth:`ReachEnv.reset_envs` restarts a subset.

**Joint control** (``control="joint"``, for joint-space policies; the scene must name an ``arm``):
the env tracks the arm's joint positions ``q (N, n)`` (:attr:`ReachEnv.q`, rad or m in the URDF's
chain order) and the TCP is ``FK(q)`` placed by the scene (:class:`sim.ik.SceneArm`), so the wrist
camera, mounted on the TCP, follows the arm. A reset solves the IK of the configuration's start
pose (:meth:`sim.ik.SceneArm.solve_start`); a start the arm does not reach within
:data:`sim.ik.START_TOL_M` / ``START_TOL_RAD`` is an :class:`EnvError` naming the seed, and one the IK
leaves short of its own tolerance but within those starts at FK of its best joints (a few mm away).
:meth:`ReachEnv.step` then takes joint position targets
``(N, n)``, enforced here and only here: :meth:`sim.ik.SceneArm.limit_step` clips each target to the
joint position limits and scales the motion down until no joint exceeds its URDF velocity limit
times ``arm.control_period_s``; a step that would take the TCP below ``episode.min_tcp_height_m`` is
shortened along the same joint-space line until it does not (the floating gripper's table clamp).
The expert's actions are joint targets: the expert's TCP motion solved by IK from the current
joints (:meth:`ReachEnv.expert_actions`). With ``control="tcp"`` (the default) nothing of this
exists: a scene's arm is ignored and the floating gripper moves as always, bit for bit.
"""

from __future__ import annotations

import numpy as np

from sim.action import ActionError, check_actions, next_tcp_pose
from sim.configs import InitialConfig
from sim.errors import AdvobjError
from sim.expert import expert_actions
from sim.outcome import NONE, object_distances, reach_outcome
from sim.render import SceneRenderer
from sim.spec import WRIST
from sim.variations import Randomization
from sim.world import SimWorld, _image_size, camera_renderer

__all__ = ["ReachEnv", "EnvError", "EXPERT_IK_ITERS"]

#: Iteration cap of the expert's IK under joint control (sim.ik's default tolerance). One expert step
#: is a small TCP motion from the current joints: a reachable one is solved in a few iterations
#: (measured over 16 expert episodes on scenes/panda-joint.yaml: median 2, at most 26), so the cap
#: bounds the time an unreachable one costs rather than the accuracy of a reachable one.
EXPERT_IK_ITERS = 30


class EnvError(AdvobjError, ValueError):
    """An env set up inconsistently with the policy that will read it."""


def _torch():
    import torch  # lazy: CLI start-up (torch: only joint control, the arm's FK and IK, needs it)

    return torch


class ReachEnv:
    """``N`` reach environments rendered from the wrist camera and any of the scene's cameras.

    Args:
        spec: the :class:`sim.spec.SceneSpec`.
        num_envs: batch size ``N``.
        image_size: observation size: int (square), ``(H, W)`` or ``None`` (the spec camera's).
        seed: the first reset without explicit seeds uses seeds ``seed .. seed + N - 1``.
        randomization: per-episode appearance variation (lights, background, sensor noise).
        render_masks: also render the id pass each step (per-object masks in ``info``); off by
            default because policies need only RGB and the extra pass costs time.
        stereo: also render the right camera of the stereo pair (``info["rgb_right"]``).
        render_obs: render observations at all; callers that render their own views (the attack)
            turn it off to skip a color pass per step.
        policy_image_size: the square input size (px) of the policy that reads the observations.
            With it, ``image_size=None`` renders at that size (the spec camera's intrinsics are
            rescaled, so the field of view is kept), and any other size is refused: a larger
            render would only be downsampled (wasted render time), a smaller one upsampled.
        control: ``"tcp"`` (actions move the floating gripper's TCP) or ``"joint"`` (actions are
            joint position targets of the scene's arm; see the module docstring).

    Observations are ``(N, H, W, 3)`` uint8.
    """

    def __init__(
        self,
        spec,
        num_envs: int = 1,
        image_size=None,
        seed: int = 0,
        randomization: Randomization | None = None,
        render_masks: bool = False,
        stereo: bool = False,
        render_obs: bool = True,
        policy_image_size: int | None = None,
        cameras: tuple[str, ...] = (WRIST,),
        control: str = "tcp",
    ):
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if control not in ("tcp", "joint"):
            raise EnvError(f"control: 'tcp' or 'joint', got {control!r}")
        if control == "joint" and spec.arm is None:
            raise EnvError(
                f"control: joint control moves the scene's arm; scene {spec.name!r} has none (give it arm: urdf, "
                "base_link, tool_link)"
            )
        self.control = control
        #: the scene's arm (sim.ik.SceneArm) under joint control, else None
        self.arm = spec.arm.scene_arm() if control == "joint" else None
        cameras = (cameras,) if isinstance(cameras, str) else tuple(cameras)
        if not cameras or len(set(cameras)) != len(cameras):
            raise EnvError(f"cameras: name each camera to render once (at least one), got {list(cameras)}")
        for name in cameras:
            spec.camera_spec(name)  # an unknown name: one line listing the scene's cameras
        if stereo and WRIST not in cameras:
            raise EnvError("stereo=True renders the wrist camera's pair: add 'wrist' to cameras")
        self.cameras = cameras
        self.obs_camera = WRIST if WRIST in cameras else cameras[0]
        self.spec = spec
        self.num_envs = int(num_envs)
        if policy_image_size is not None:
            S = int(policy_image_size)
            if image_size is None:
                image_size = S
            if _image_size(spec, image_size) != (S, S):
                h, w = _image_size(spec, image_size)
                raise EnvError(
                    f"image_size: the env would render {h}x{w} px but the policy reads {S}x{S} px; render at the "
                    f"policy's size (image_size={S} or None) instead of resizing the observation"
                )
        self.height, self.width = _image_size(spec, image_size)
        self.render_masks = render_masks
        self.render_obs = render_obs
        self.stereo = stereo
        if stereo and spec.camera.stereo_baseline_m <= 0:
            raise ValueError("stereo=True needs camera.stereo_baseline_m > 0 in the scene spec")
        self.renderer = SceneRenderer(spec, self.width, self.height)
        # One renderer per camera (a renderer's size and intrinsics are fixed), shared by the worlds.
        # The wrist camera's is always built: the attack and the evaluation render through it.
        self.renderers: dict[str, SceneRenderer] = {WRIST: self.renderer}
        for name in cameras:
            if name != WRIST:
                self.renderers[name] = camera_renderer(spec, name)
        scene_renderers = {k: r for k, r in self.renderers.items() if k != WRIST}
        self.worlds = [
            SimWorld(
                spec,
                (self.height, self.width),
                seed + i,
                renderer=self.renderer,
                randomization=randomization,
                camera_renderers=scene_renderers,
            )
            for i in range(self.num_envs)
        ]
        self.goal_index = spec.object_index("goal")
        self.adv_index = spec.object_index("adversarial")
        ep = spec.episode
        self.max_steps, self.radius_m = ep.max_steps, ep.success_radius_m
        self.max_step_m, self.max_step_rad = ep.max_step_m, ep.max_step_rad
        self._seed = int(seed)
        self._images = {name: np.zeros((self.num_envs, *self.image_shape(name)), np.uint8) for name in cameras}
        self._obs = self._images[self.obs_camera]
        self._right = np.zeros((self.num_envs, self.height, self.width, 3), np.uint8) if stereo else None
        self._camera_masks: dict[str, list] = {name: [None] * self.num_envs for name in cameras}
        self._masks: list = self._camera_masks[self.obs_camera]
        self.steps = np.zeros(self.num_envs, np.int64)
        self.done = np.zeros(self.num_envs, bool)
        self.policy_error = np.zeros(self.num_envs, bool)  # ended by a non-finite action (sim.action.POLICY_ERROR)
        self.reached = np.full(self.num_envs, NONE, np.int64)
        self.min_dist = np.full((self.num_envs, len(spec.objects)), np.inf)
        n = self.arm.n_joints if self.arm is not None else 0
        self._q = np.zeros((self.num_envs, n))  # joint positions under joint control
        #: joint control: expert steps whose IK did not reach the expert's TCP target (it moved toward it)
        self.expert_ik_misses = 0

    # ------------------------------------------------------------------ helpers
    @property
    def T_world_tcp(self) -> np.ndarray:
        """(N, 4, 4) current TCP poses."""
        return np.stack([w.T_world_tcp for w in self.worlds])

    @property
    def q(self) -> np.ndarray | None:
        """(N, n) joint positions (rad or m, the arm's chain order) under joint control, else None."""
        return None if self.arm is None else self._q.copy()

    @property
    def action_dim(self) -> int:
        """Values per action :meth:`step` takes: 6 (TCP motion) or the arm's joints."""
        return 6 if self.arm is None else self.arm.n_joints

    @property
    def object_centers(self) -> np.ndarray:
        """(N, K, 3) m object centres."""
        return np.stack([w.object_center_array for w in self.worlds])

    @property
    def configs(self) -> list[InitialConfig]:
        return [w.config for w in self.worlds]

    def image_shape(self, name: str) -> tuple[int, int, int]:
        """``(H, W, 3)`` of camera ``name``'s images in this env."""
        if name == WRIST:
            return self.height, self.width, 3
        cam = self.spec.camera_spec(name)
        return cam.height, cam.width, 3

    def _render(self, i: int) -> None:
        if not self.render_obs:
            return
        w = self.worlds[i]
        # The wrist camera first, its stereo partner next: their noise draws come in the order they
        # always did; each scene camera draws from a stream of its own.
        for name in sorted(self.cameras, key=lambda n: n != WRIST):
            out = w.render(with_ids=self.render_masks, camera=name)
            self._images[name][i] = out.rgb
            self._camera_masks[name][i] = out.masks if self.render_masks else None
            if name == WRIST and self.stereo:
                self._right[i] = w.render(w.camera_pose(right=True), with_ids=False).rgb

    def _info(self) -> dict:
        tcp = self.T_world_tcp
        centers = self.object_centers
        info = {
            "T_world_tcp": tcp,
            "object_pos": centers,
            "distances": object_distances(tcp[:, :3, 3], centers),
            "min_distances": self.min_dist.copy(),
            "reached": self.reached.copy(),
            "success": self.reached == self.goal_index,
            "step": self.steps.copy(),
            "done": self.done.copy(),
            "policy_error": self.policy_error.copy(),
            "seeds": np.array([w.config.seed for w in self.worlds]),
        }
        if self.arm is not None:
            info["q"] = self._q.copy()
        info["images"] = self.images()
        if self.render_masks:
            info["masks"] = list(self._masks)
            info["camera_masks"] = {name: list(m) for name, m in self._camera_masks.items()}
        if self.stereo:
            info["rgb_right"] = self._right.copy()
        return info

    # ------------------------------------------------------------------ API
    def reset(self, seed: int | None = None, configs: list[InitialConfig] | None = None):
        """Reset all envs (seeds ``seed + i``, or the given ``configs``) -> ``(obs, info)``."""
        if configs is not None and len(configs) != self.num_envs:
            raise ValueError(f"reset: got {len(configs)} configs for {self.num_envs} envs")
        base = self._seed if seed is None else int(seed)
        if seed is None:
            self._seed += self.num_envs  # the next unseeded reset draws fresh configurations
        self.reset_envs(
            range(self.num_envs), None if configs is None else configs, seeds=[base + i for i in range(self.num_envs)]
        )
        return self._obs.copy(), self._info()

    def reset_envs(self, indices, configs=None, seeds=None) -> None:
        """Restart the envs in ``indices`` from ``configs`` (or ``seeds``)."""
        indices = list(indices)

        def start(j: int, i: int) -> None:
            w = self.worlds[i]
            if configs is not None:
                w.reset(config=configs[j])
            else:
                w.reset(seed=None if seeds is None else seeds[j])

        if self.arm is not None and indices:  # every start pose first, solved by IK together
            for j, i in enumerate(indices):
                start(j, i)
            self._start_joints(indices)
        for j, i in enumerate(indices):
            w = self.worlds[i]
            if self.arm is None:  # reset and render env by env, as always
                start(j, i)
            self.steps[i] = 0
            self.done[i] = False
            self.policy_error[i] = False
            self.reached[i] = NONE
            self.min_dist[i] = object_distances(w.T_world_tcp[None, :3, 3], w.object_center_array[None])[0]
            self._render(i)

    def _start_joints(self, indices: list[int]) -> None:
        """Joint control: solve the start poses of envs ``indices`` by IK and put their TCPs at FK(q); a
        pose the IK leaves unreached but within :data:`sim.ik.START_TOL_M` / ``START_TOL_RAD`` starts
        at FK of its best iterate (:meth:`sim.ik.IkResult.start_reached`), one further is an
        :class:`EnvError` naming its seed."""
        torch = _torch()
        from sim.ik import START_TOL_M, START_TOL_RAD  # lazy: CLI start-up (torch)

        T = torch.from_numpy(np.stack([self.worlds[i].T_world_tcp for i in indices]))
        res = self.arm.solve_start(T)
        near = res.start_reached()
        if not bool(near.all()):
            k = int((~near).nonzero()[0, 0])
            seed = self.worlds[indices[k]].config.seed
            raise EnvError(
                f"arm: the start pose of configuration seed {seed} is out of the arm's reach (IK: "
                f"{float(res.pos_err_m[k]):.3g} m, {float(res.rot_err_rad[k]):.3g} rad off after "
                f"{res.iterations} iterations, from q_home and the restarts; at most {START_TOL_M} m and "
                f"{START_TOL_RAD} rad are accepted); move the arm (arm.t_table_base_m) or narrow the scene's init "
                "ranges"
            )
        q = res.q.numpy()
        T_tcp = self.arm.tcp_pose(res.q).numpy()
        for k, i in enumerate(indices):
            self._q[i] = q[k]
            self.worlds[i].set_tcp_pose(T_tcp[k])

    def _joint_step(self, q_target: np.ndarray, active: np.ndarray) -> None:
        """Joint control: move the ``active`` envs toward ``q_target (N, n)`` within the joint limits
        (:meth:`sim.ik.SceneArm.limit_step`) and above the table (the step shortened along its line)."""
        torch = _torch()
        idx = np.flatnonzero(active)
        if idx.size == 0:
            return
        q = torch.from_numpy(self._q[idx])
        q_next = self.arm.limit_step(q, torch.from_numpy(q_target[idx]))
        T_next = self.arm.tcp_pose(q_next)
        z_min = self.spec.episode.min_tcp_height_m
        low = T_next[:, 2, 3] < z_min
        if bool(low.any()):
            # Bisect the fraction t of the step (q + t dq stays on the same joint-space line) that keeps
            # the TCP above the table; t = 0 (no motion) when even a sliver of it goes below.
            rows = low.nonzero()[:, 0]
            q0, dq = q[rows], (q_next - q)[rows]
            lo_t = torch.zeros(len(rows), 1, dtype=q.dtype)
            hi_t = torch.ones(len(rows), 1, dtype=q.dtype)
            for _ in range(12):  # the fraction to 1/4096 of the step
                mid = (lo_t + hi_t) / 2
                ok = self.arm.tcp_pose(q0 + mid * dq)[:, 2, 3] >= z_min
                lo_t = torch.where(ok[:, None], mid, lo_t)
                hi_t = torch.where(ok[:, None], hi_t, mid)
            q_next[rows] = q0 + lo_t * dq
            T_next[rows] = self.arm.tcp_pose(q_next[rows])
        q_np, T_np = q_next.numpy(), T_next.numpy()
        for k, i in enumerate(idx):
            self._q[i] = q_np[k]
            self.worlds[i].set_tcp_pose(T_np[k])

    def _check_joint_actions(self, actions) -> np.ndarray:
        a = np.asarray(actions, dtype=np.float64)
        n = self.arm.n_joints
        if a.shape != (self.num_envs, n):
            raise ActionError(
                f"actions must have shape ({self.num_envs}, {n}): joint position targets of "
                f"{', '.join(self.arm.joint_names)}; got {a.shape}"
            )
        bad = ~np.isfinite(a).all(axis=1)
        if bad.any():
            raise ActionError(f"non-finite action (NaN or Inf) for env(s) {np.flatnonzero(bad).tolist()}")
        return a

    def observe(self) -> np.ndarray:
        return self._obs.copy()

    def images(self) -> dict[str, np.ndarray]:
        """``{camera name: (N, H_c, W_c, 3) uint8}``: the current images of every requested camera."""
        return {name: im.copy() for name, im in self._images.items()}

    def step(self, actions):
        """Apply ``actions`` -> ``(obs, reward, terminated, truncated, info)``: ``(N, 6)`` in [-1, 1]
        (TCP control), or ``(N, n)`` joint position targets (joint control, module docstring).

        NaN/Inf actions raise :class:`sim.action.ActionError`; finished envs ignore their action.
        """
        a = check_actions(actions, self.num_envs) if self.arm is None else self._check_joint_actions(actions)
        active = ~self.done
        tcp = self.T_world_tcp
        centers = self.object_centers
        d_before = np.linalg.norm(centers[:, self.goal_index] - tcp[:, :3, 3], axis=-1)
        if self.arm is None:
            T_next = next_tcp_pose(tcp, a, self.max_step_m, self.max_step_rad)
            # Kinematic workspace limit: the floating gripper cannot pass through the table.
            T_next[:, 2, 3] = np.maximum(T_next[:, 2, 3], self.spec.episode.min_tcp_height_m)
            for i in np.flatnonzero(active):
                self.worlds[i].set_tcp_pose(T_next[i])
        else:
            self._joint_step(a, active)
        tcp = self.T_world_tcp
        d = object_distances(tcp[:, :3, 3], centers)
        outcome = reach_outcome(tcp[:, :3, 3], centers, self.radius_m)
        self.steps[active] += 1
        self.min_dist[active] = np.minimum(self.min_dist[active], d[active])
        newly = active & (outcome != NONE)
        self.reached[newly] = outcome[newly]
        terminated = newly
        truncated = active & ~newly & (self.steps >= self.max_steps)
        # Dense progress toward the goal (in steps), with a bonus or penalty at the end.
        reward = np.where(active, (d_before - d[:, self.goal_index]) / self.max_step_m, 0.0)
        reward = reward + np.where(newly & (outcome == self.goal_index), 10.0, 0.0)
        reward = reward - np.where(newly & (outcome != self.goal_index), 10.0, 0.0)
        self.done |= terminated | truncated
        for i in np.flatnonzero(active):
            self._render(i)
        return self._obs.copy(), reward, terminated, truncated, self._info()

    def end_with_policy_error(self, indices) -> None:
        """End the episodes in ``indices`` where they stand: their policy gave a non-finite action.

        The one rule shared with the real runner (:data:`sim.action.POLICY_ERROR`): such an action is
        never executed, clipped or replaced; the episode ends with no object reached.
        """
        idx = np.asarray(list(indices), dtype=np.int64)
        self.done[idx] = True
        self.reached[idx] = NONE
        self.policy_error[idx] = True

    def expert_actions(self) -> np.ndarray:
        """Privileged expert actions for the current states: ``(N, 6)`` TCP motions, or under joint
        control ``(N, n)`` joint targets: the TCP pose the expert's motion leads to (above the
        table), solved by IK from the current joints (:meth:`sim.ik.SceneArm.ik`, its default
        tolerance, at most :data:`EXPERT_IK_ITERS` iterations). Where the IK does not reach that
        pose (a joint limit, the edge of the workspace), the target is its best iterate, a step
        toward it within the limits, and :attr:`expert_ik_misses` counts it."""
        a = expert_actions(self.T_world_tcp, self.object_centers, self.goal_index, self.max_step_m, self.max_step_rad)
        if self.arm is None:
            return a
        torch = _torch()
        T_target = next_tcp_pose(self.T_world_tcp, a, self.max_step_m, self.max_step_rad)
        T_target[:, 2, 3] = np.maximum(T_target[:, 2, 3], self.spec.episode.min_tcp_height_m)
        res = self.arm.ik(torch.from_numpy(T_target), torch.from_numpy(self._q), max_iters=EXPERT_IK_ITERS)
        self.expert_ik_misses += int((~res.converged[~torch.from_numpy(self.done)]).sum())
        return res.q.numpy()

    def close(self) -> None:
        for w in self.worlds:
            w.close()  # closes only the renderers a world built itself
        for r in self.renderers.values():
            r.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
