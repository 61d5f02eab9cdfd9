"""The simulated arm: the floating gripper of a shared :class:`sim.world.SimWorld`.

Kinematic, like the sim itself, but speed-limited so motions take time: ``servo`` advances at
most ``max_speed * duration_s`` toward its target, and ``move_to`` either sleeps for the motion's
duration (``realtime=True``, for hardware-in-the-loop sessions) or only advances ``sim_time_s``.
Without ``realtime`` the arm reports ``sim_time_s`` as its :meth:`simulated_time_s`, so the
safety layer's speed caps count simulated time and sessions may run faster than real time.
The world frame plays the role of the robot base frame.

Given a ``scene_arm`` (:class:`sim.ik.SceneArm`), the arm is joint-driven: it holds joint
positions ``q``, :meth:`SimArm.servo_joints` and :meth:`SimArm.move_joints` set them exactly as
commanded (the safety layer in front of it enforces the limits; the twin records what it was
sent), and the gripper follows the scene arm's FK, ``T_world_tcp = T_world_base FK(q) T_tool_tcp``.
TCP commands to a joint-driven arm go through the scene arm's IK from the current joints (a
positioning move that does not converge from there tries the scene arm's start seeds). A TCP
target the IK does not reach within the joint limits is refused as the real drivers refuse one (the
serial arm's ``ERR RANGE unreachable``, the servo-bus arm's IK refusal): an
:class:`~robot_io.errors.ArmRefusedError` naming the target and the IK's errors; the arm does not
move and takes the next command, no fault is latched (:meth:`SimArm.fault` stays ``None``), and the
trial runner ends that trial (``refused: ...``), not the session.
"""

from __future__ import annotations

import time

import numpy as np

from robot_io.arms.base import Arm, Fault, tcp_from_joints
from robot_io.errors import ArmFaultError, ArmRefusedError
from robot_io.poses import interpolate_pose, is_valid_pose, pose_step

__all__ = ["SimArm"]


class SimArm(Arm):
    """Drives ``world.set_tcp_pose``.

    Args:
        world: the :class:`sim.world.SimWorld` shared with the sim camera.
        max_speed_mps, max_speed_radps: the arm's own (hardware) speed limits.
        realtime: make ``move_to`` take wall-clock time.
    """

    name = "sim"

    def __init__(
        self,
        world,
        max_speed_mps: float = 0.5,
        max_speed_radps: float = 2.0,
        realtime: bool = False,
        scene_arm=None,
    ):
        super().__init__()
        self.world = world
        self.max_speed_mps = float(max_speed_mps)
        self.max_speed_radps = float(max_speed_radps)
        self.realtime = bool(realtime)
        self.sim_time_s = 0.0
        self._fault: Fault | None = None
        self.commands: int = 0  # motion commands executed (tests check that nothing moved)
        self.scene_arm = scene_arm
        self._q: np.ndarray | None = None
        if scene_arm is not None:
            self._set_q(np.asarray(scene_arm.q_home, dtype=np.float64))

    def _open(self) -> None:
        self._fault = None

    def _close(self) -> None:
        pass  # the world belongs to whoever created it

    def inject_fault(self, fault: Fault | None) -> None:
        """Simulate a protective stop, e-stop, ... (``None`` clears it)."""
        self._fault = fault

    def fault(self) -> Fault | None:
        if not self._connected:
            return Fault("connection_lost", "sim arm is not connected", "call connect()")
        return self._fault

    def tcp_pose(self) -> np.ndarray:
        return self.world.T_world_tcp

    # ------------------------------------------------------------------ joints
    def kinematics(self):
        return self.scene_arm

    def _set_q(self, q: np.ndarray) -> None:
        self.world.set_tcp_pose(tcp_from_joints(self.scene_arm, q))
        self._q = np.array(q, dtype=np.float64)

    def _check_q(self, q) -> np.ndarray:
        if self.scene_arm is None:
            return super().joint_positions()  # raises: no joint commands
        if self._fault is not None:
            raise ArmFaultError(self._fault)
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (self.scene_arm.n_joints,) or not np.isfinite(q).all():
            raise ValueError(f"sim arm: joint target must be {self.scene_arm.n_joints} finite numbers, got {q}")
        return q

    def joint_positions(self) -> np.ndarray:
        if self._q is None:
            return super().joint_positions()
        return self._q.copy()

    def servo_joints(self, q: np.ndarray, duration_s: float) -> None:
        self._set_q(self._check_q(q))
        self.commands += 1
        self.sim_time_s += float(duration_s)

    def move_joints(self, q: np.ndarray, duration_s: float) -> None:
        self._set_q(self._check_q(q))
        self.commands += 1
        self.sim_time_s += float(duration_s)
        if self.realtime:
            time.sleep(float(duration_s))

    def _ik(self, T_world_tcp: np.ndarray, positioning: bool = False) -> np.ndarray:
        """The joints that put the TCP at ``T_world_tcp``: IK from the current joints (the nearest
        solution, as a real arm's controller takes), and for a ``positioning`` move, when that does
        not converge, from the scene arm's start seeds (:meth:`sim.ik.SceneArm.solve_start`: its home
        joints, then fixed restarts), as the simulator solves a start pose, accepted as the simulator
        accepts one (:meth:`sim.ik.IkResult.start_reached`: a few mm short is a start). A target out of
        reach raises :class:`ArmRefusedError` (no fault: the arm has not moved)."""
        import torch  # lazy: robot_io start-up (torch)

        like = torch.as_tensor(self._q, dtype=torch.float64, device=self.scene_arm.device)[None]
        T = torch.as_tensor(T_world_tcp, dtype=torch.float64, device=like.device)[None]
        res = self.scene_arm.ik(T, like)
        seeds = "the current joints"
        reached = res.converged
        if positioning and not bool(reached[0]):
            res = self.scene_arm.solve_start(T)
            reached = res.start_reached()  # a start pose: the simulator's rule (sim.ik.START_TOL_M)
            seeds = "the current joints, then the arm's home joints and restarts"
        if not bool(reached[0]):
            p = ", ".join(f"{float(v):.3f}" for v in T_world_tcp[:3, 3])
            raise ArmRefusedError(
                f"sim arm: TCP target at [{p}] m (base frame) is out of reach within the joint limits (IK from "
                f"{seeds}: {float(res.pos_err_m[0]):.3g} m and {float(res.rot_err_rad[0]):.3g} rad off after "
                f"{res.iterations} iterations); the arm did not move"
            )
        return res.q[0].cpu().numpy()

    def _check(self, T: np.ndarray) -> np.ndarray:
        if self._fault is not None:
            raise ArmFaultError(self._fault)
        if not is_valid_pose(T):
            raise ValueError("sim arm: target must be a finite rigid (4, 4) transform")
        return np.asarray(T, dtype=np.float64)

    def _advance(self, T_target: np.ndarray, duration_s: float) -> float:
        T_now = self.world.T_world_tcp
        dp, dr = pose_step(T_now, T_target)
        need_s = max(dp / self.max_speed_mps, dr / self.max_speed_radps)
        s = 1.0 if need_s <= duration_s else duration_s / need_s
        self.world.set_tcp_pose(interpolate_pose(T_now, T_target, s))
        self.commands += 1
        return min(need_s, duration_s)

    def servo(self, T_base_tcp: np.ndarray, duration_s: float) -> None:
        T = self._check(T_base_tcp)
        if self.scene_arm is not None:
            self.servo_joints(self._ik(T), duration_s)
            return
        self._advance(T, float(duration_s))
        self.sim_time_s += float(duration_s)

    def move_to(self, T_base_tcp: np.ndarray, speed_mps: float) -> None:
        T = self._check(T_base_tcp)
        if not speed_mps > 0:
            raise ValueError(f"sim arm: speed_mps must be positive, got {speed_mps}")
        dp, dr = pose_step(self.world.T_world_tcp, T)
        v = min(float(speed_mps), self.max_speed_mps)
        duration = max(dp / v, dr / self.max_speed_radps)
        if self.scene_arm is not None:
            self.move_joints(self._ik(T, positioning=True), duration)
            return
        self._advance(T, duration + 1e-9)
        self.sim_time_s += duration
        if self.realtime:
            time.sleep(duration)

    def identity(self) -> dict[str, str]:
        return {"serial": "sim"}

    def simulated_time_s(self) -> float | None:
        # Non-realtime: each command takes simulated time only, so the safety layer uses this clock.
        return None if self.realtime else self.sim_time_s

    def stop(self) -> None:
        pass  # kinematic: motion ends with each command
