"""The arm interface every driver implements, the fault it reports, and what the joint-capable
drivers share: the joint target check (:func:`check_joint_target`), the FK of joints as numpy
(:func:`tcp_from_joints`) and the kinematics check on connect (:func:`check_kinematics_agree`).

Drivers are never used directly by trials: :func:`robot_io.config.build_arm` wraps them in
:class:`robot_io.safety.SafeArm`, which is the only path commands take to a driver. A driver that
will not execute a target (out of reach, a joint past its range) raises
:class:`~robot_io.errors.ArmRefusedError`: nothing moved and the arm takes the next command; a
fault (protective stop, e-stop, lost link) is an :class:`~robot_io.errors.ArmFaultError`.

The kinematics check (:func:`check_kinematics_agree`): a UR or serial arm given a URDF reports its
TCP twice, once as its controller computes it and once as the joints it measures, whose FK the
safety layer uses to keep joint commands in the workspace box. Before anything moves, the two
must agree within :data:`KINEMATICS_TOL_M` and :data:`KINEMATICS_TOL_RAD`; otherwise the config's
URDF, base placement or TCP is wrong, and the safety layer would check the box on a wrong TCP.

The tolerances, 5 mm and 0.02 rad (1.1 deg). Above the honest disagreement: a UR controller
computes its TCP with its factory calibration, reported 1-2 mm from the nominal URDF's FK (UR's
``ur_calibration`` package turns the calibration into a URDF correction, and UR warns it may reach
centimetres: such an arm is refused until its URDF carries the correction), and the serial
protocol writes 6 decimals (5e-7 m, 5e-7 rad). Far below what the check is for: a base turned by
pi (a UR's base_link, ``rotvec_base_link``) moves the TCP by twice its distance from the base
axis, a missing or wrong tool offset by the tool's length (tens of mm), another arm's URDF (a UR5
for a UR5e) by tens of mm. The check sees one configuration: a base turned about its vertical axis
by less than 0.02 rad passes it and moves a TCP 0.85 m out (a UR5's reach) by at most 17 mm, which
a workspace box's margin absorbs; a base or tool offset under 5 mm stays under 5 mm everywhere.
"""

from __future__ import annotations

import abc
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

from robot_io.device import Device
from robot_io.errors import HardwareConfigError, RobotIOError
from robot_io.poses import pose_step

if TYPE_CHECKING:
    from sim.ik import SceneArm

__all__ = [
    "Fault",
    "Arm",
    "check_joint_target",
    "tcp_from_joints",
    "KINEMATICS_TOL_M",
    "KINEMATICS_TOL_RAD",
    "kinematics_disagreement",
    "check_kinematics_agree",
]

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


def check_joint_target(who: str, scene_arm: SceneArm | None, q) -> np.ndarray:
    """``q`` as ``(n,)`` float64 when it is ``scene_arm.n_joints`` finite numbers, else one
    :class:`RobotIOError` line naming ``who`` (the driver: ``"UR 10.0.0.2"``, ``"serial arm /dev/ttyACM0"``);
    with no ``scene_arm`` (no URDF describes the arm) every joint target is refused."""
    if scene_arm is None:
        raise RobotIOError(f"{who}: takes no joint commands (no URDF describes the arm)")
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


# ------------------------------------------------------------------------ the kinematics check
#: The connect check's position tolerance (m) between the FK of the measured joints and the
#: controller's TCP (module docstring: why 5 mm).
KINEMATICS_TOL_M = 5e-3
#: The connect check's orientation tolerance (rad), 1.1 deg (module docstring: why).
KINEMATICS_TOL_RAD = 0.02
#: The fields of the hardware config's ``kinematics`` block the connect check's refusal names.
_KINEMATICS_FIELDS = (
    "urdf (the arm's model), t_base_link_m / rotvec_base_link (where base_link stands in the controller's base "
    "frame), t_tool_tcp_m / rotvec_tool_tcp (the TCP the controller is set to)"
)


def tcp_from_joints(scene_arm: SceneArm, q) -> np.ndarray:
    """``T_base_tcp (4, 4)`` float64 of joint positions ``q (n,)``: the scene arm's FK
    (:meth:`sim.ik.SceneArm.tcp_pose`) as numpy."""
    import torch  # lazy: robot_io start-up (torch)

    q_t = torch.as_tensor(np.asarray(q, dtype=np.float64), dtype=torch.float64, device=scene_arm.device)
    return scene_arm.tcp_pose(q_t).detach().cpu().numpy()


def kinematics_disagreement(scene_arm: SceneArm, q, T_base_tcp) -> tuple[float, float]:
    """``(distance_m, angle_rad)`` from the FK of joints ``q (n,)`` to the reported ``T_base_tcp (4, 4)``;
    ``(inf, inf)`` when ``q`` or ``T_base_tcp`` holds a NaN or an infinity (nothing agrees with those)."""
    if not _finite(q, T_base_tcp):
        return math.inf, math.inf
    q, T = np.asarray(q, dtype=np.float64), np.asarray(T_base_tcp, dtype=np.float64)
    with np.errstate(over="ignore"):  # a TCP near the float range is inf away, and refused as such
        return pose_step(tcp_from_joints(scene_arm, q), T)


def check_kinematics_agree(
    who: str,
    scene_arm: SceneArm,
    q,
    T_base_tcp,
    tol_m: float = KINEMATICS_TOL_M,
    tol_rad: float = KINEMATICS_TOL_RAD,
    hint: str = "",
) -> None:
    """Refuse, in one :class:`~robot_io.errors.HardwareConfigError` line naming ``who`` (the driver:
    ``"UR 10.0.0.2"``), an arm whose measured joints ``q`` put the TCP, through ``scene_arm``'s FK,
    farther than ``tol_m`` or ``tol_rad`` from the ``T_base_tcp`` its controller reports (module
    docstring). The line gives both TCPs, names the config fields to check, and ends with ``hint``
    (what is special about this arm's kinematics, or nothing)."""
    dp, dr = kinematics_disagreement(scene_arm, q, T_base_tcp)
    if dp <= tol_m and dr <= tol_rad:
        return
    if _finite(q, T_base_tcp):
        how = (
            f"the FK of its joints puts the TCP at {_mm(tcp_from_joints(scene_arm, q))} mm, "
            f"{dp * 1000:.1f} mm and {math.degrees(dr):.2f} deg from the TCP it reports at "
            f"{_mm(T_base_tcp)} mm"
        )
    else:
        how = f"its joints {np.asarray(q).tolist()} or the TCP it reports hold a NaN or an infinity"
    raise HardwareConfigError(
        f"{who}: the arm's URDF kinematics disagree with its controller: {how} (tolerance {tol_m * 1000:g} mm, "
        f"{math.degrees(tol_rad):.2f} deg); check the hardware config's arm kinematics: {_KINEMATICS_FIELDS}"
        f"{'; ' + hint if hint else ''}. Nothing was moved"
    )


def _finite(*arrays) -> bool:
    return all(np.isfinite(np.asarray(a, dtype=np.float64)).all() for a in arrays)


def _mm(T) -> str:
    return "[" + ", ".join(f"{1000 * float(x):.1f}" for x in np.asarray(T, dtype=np.float64)[:3, 3]) + "]"
