"""The arm interface every driver implements, and the fault it reports.

Drivers are never used directly by trials: :func:`robot_io.config.build_arm` wraps them in
:class:`robot_io.safety.SafeArm`, which is the only path commands take to a driver.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

from robot_io.device import Device
from robot_io.errors import RobotIOError

if TYPE_CHECKING:
    from sim.ik import SceneArm

__all__ = ["Fault", "Arm", "check_joint_target"]

FaultKind = Literal[
    "protective_stop", "emergency_stop", "connection_lost", "program_stopped", "heartbeat_timeout", "device_fault"
]


@dataclass(frozen=True)
class Fault:
    """Why the arm cannot move, and what the operator should do about it."""

    kind: FaultKind
    message: str
    recovery: str = ""

    def __str__(self) -> str:
        text = f"arm fault ({self.kind}): {self.message}"
        return f"{text}. To recover: {self.recovery}" if self.recovery else text


class Arm(Device):
    """A robot arm moving a TCP in its base frame.

    Motion commands: :meth:`move_to` (blocking positioning move) and :meth:`servo` (one
    non-blocking step of a streamed trajectory, reached over ``duration_s``; the policy loop).
    An arm a URDF describes also takes joint commands: :meth:`kinematics`, :meth:`joint_positions`,
    :meth:`servo_joints` and :meth:`move_joints`.
    """

    name: str = "arm"

    def __exit__(self, exc_type, exc, tb):
        # An arm leaving a with-block on an exception is stopped before the link is released.
        try:
            if exc_type is not None and self._connected:
                self.stop()
        finally:
            self.disconnect()
        return False

    @abc.abstractmethod
    def _close(self) -> None:
        """Stop motion and release the connection (must not raise on a dead link)."""

    @abc.abstractmethod
    def tcp_pose(self) -> np.ndarray:
        """``T_base_tcp`` (4, 4), measured."""

    @abc.abstractmethod
    def move_to(self, T_base_tcp: np.ndarray, speed_mps: float) -> None:
        """Move linearly to ``T_base_tcp`` and return when there (positioning, not the policy loop)."""

    @abc.abstractmethod
    def servo(self, T_base_tcp: np.ndarray, duration_s: float) -> None:
        """Stream one target to be reached in ``duration_s``; returns immediately."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Stop any motion now (decelerating as fast as the arm allows)."""

    @abc.abstractmethod
    def fault(self) -> Fault | None:
        """The current fault, or ``None`` when the arm can move."""

    def keepalive(self) -> None:
        """Tell the arm's watchdog we are alive; called every control loop iteration."""

    # Joint commands: an arm a URDF describes (issue 31). An arm without them keeps these defaults,
    # and the safety layer refuses a joint command to it before anything reaches the driver.
    def kinematics(self) -> SceneArm | None:
        """The arm's :class:`sim.ik.SceneArm` (URDF chain, base placement, TCP in the tool link), or
        ``None`` when the arm takes TCP commands only. Its TCP is in the frame of :meth:`tcp_pose`."""
        return None

    def joint_positions(self) -> np.ndarray:
        """``q (n,)`` measured, in the order and units of :meth:`kinematics`' joints."""
        raise RobotIOError(f"the {self.name} arm takes no joint commands (it has no URDF)")

    def servo_joints(self, q: np.ndarray, duration_s: float) -> None:
        """Stream one joint target ``q (n,)`` to be reached in ``duration_s``; returns immediately."""
        raise RobotIOError(f"the {self.name} arm takes no joint commands (it has no URDF)")

    def move_joints(self, q: np.ndarray, duration_s: float) -> None:
        """Move to joint positions ``q (n,)`` over ``duration_s`` and return when there (positioning)."""
        raise RobotIOError(f"the {self.name} arm takes no joint commands (it has no URDF)")

    def simulated_time_s(self) -> float | None:
        """The arm's simulated clock, or ``None`` when it executes commands in wall-clock time.

        Every real arm returns ``None``. A simulation that runs faster than real time returns the
        time its commands have covered, so the safety layer measures the time between commands
        on that clock rather than throttling the simulation to the wall clock.
        """
        return None


def check_joint_target(who: str, scene_arm: SceneArm, q) -> np.ndarray:
    """``q`` as ``(n,)`` float64 when it is ``scene_arm.n_joints`` finite numbers, else one
    :class:`RobotIOError` line naming ``who`` (the driver: ``"UR 10.0.0.2"``, ``"serial arm /dev/ttyACM0"``)."""
    n = scene_arm.n_joints
    try:
        q = np.asarray(q, dtype=np.float64)
    except (TypeError, ValueError):
        raise RobotIOError(f"{who}: a joint target must be {n} numbers, got {type(q).__name__}") from None
    if q.shape != (n,):
        raise RobotIOError(
            f"{who}: a joint target must be {n} numbers ({', '.join(scene_arm.joint_names)}), got shape {q.shape}"
        )
    if not np.isfinite(q).all():
        raise RobotIOError(f"{who}: a joint target must be finite, got {q.tolist()}")
    return q
