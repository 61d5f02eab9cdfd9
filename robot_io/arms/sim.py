"""The simulated arm: the floating gripper of a shared :class:`sim.world.SimWorld`.

Kinematic, like the sim itself, but speed-limited so motions take time: ``servo`` advances at
most ``max_speed * duration_s`` toward its target, and ``move_to`` either sleeps for the motion's
duration (``realtime=True``, for hardware-in-the-loop sessions) or only advances ``sim_time_s``.
Without ``realtime`` the arm reports ``sim_time_s`` as its :meth:`simulated_time_s`, so the
safety layer's speed caps count simulated time and sessions may run faster than real time.
The world frame plays the role of the robot base frame.
"""

from __future__ import annotations

import time

import numpy as np

from robot_io.arms.base import Arm, Fault
from robot_io.errors import ArmFaultError
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

    def __init__(self, world, max_speed_mps: float = 0.5, max_speed_radps: float = 2.0, realtime: bool = False):
        super().__init__()
        self.world = world
        self.max_speed_mps = float(max_speed_mps)
        self.max_speed_radps = float(max_speed_radps)
        self.realtime = bool(realtime)
        self.sim_time_s = 0.0
        self._fault: Fault | None = None
        self.commands: int = 0  # motion commands executed (tests check that nothing moved)

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
        self._advance(T, float(duration_s))
        self.sim_time_s += float(duration_s)

    def move_to(self, T_base_tcp: np.ndarray, speed_mps: float) -> None:
        T = self._check(T_base_tcp)
        if not speed_mps > 0:
            raise ValueError(f"sim arm: speed_mps must be positive, got {speed_mps}")
        dp, dr = pose_step(self.world.T_world_tcp, T)
        v = min(float(speed_mps), self.max_speed_mps)
        duration = max(dp / v, dr / self.max_speed_radps)
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
