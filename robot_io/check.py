"""What ``advobj hw check`` measures, and the kinematics check a joint-capable arm runs on connect.

``advobj hw check``: camera frame rate and latency, the arm's pose, for an arm a URDF describes
its joints (:func:`joint_readings`: value, unit and distance to each limit, to check a servo's
``sign`` and ``offset_ticks``), an optional jog.

The connect check (:func:`check_kinematics_agree`): a UR or serial arm given a URDF reports its
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

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from robot_io.errors import HardwareConfigError
from robot_io.poses import pose_step
from sim.geometry import so3_log

if TYPE_CHECKING:
    from sim.ik import SceneArm

__all__ = [
    "CameraStats",
    "measure_camera",
    "format_pose",
    "jog_z",
    "KINEMATICS_TOL_M",
    "KINEMATICS_TOL_RAD",
    "tcp_from_joints",
    "kinematics_disagreement",
    "check_kinematics_agree",
    "JointReading",
    "joint_readings",
    "format_joint",
]

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


@dataclass(frozen=True)
class CameraStats:
    frames: int
    width: int
    height: int
    fps: float  # from frame timestamps
    read_ms_median: float  # time spent inside read()
    read_ms_p95: float
    age_ms_median: float  # frame age when read() returned (capture -> available to the policy)
    age_ms_p95: float
    dropped: int  # sequence gaps: frames the camera produced that we never saw


def measure_camera(camera, n_frames: int = 60) -> CameraStats:
    """Read ``n_frames`` from a connected camera as fast as possible."""
    if n_frames < 2:
        raise ValueError("n_frames must be at least 2 to measure a frame rate")
    read_s, age_s, stamps, seqs = [], [], [], []
    frame = None
    for _ in range(n_frames):
        t0 = time.monotonic()
        frame = camera.read()
        t1 = time.monotonic()
        read_s.append(t1 - t0)
        age_s.append(t1 - frame.timestamp_s)
        stamps.append(frame.timestamp_s)
        seqs.append(frame.seq)
    span = stamps[-1] - stamps[0]
    dropped = int(sum(max(0, b - a - 1) for a, b in zip(seqs, seqs[1:])))
    ms = lambda xs, q: float(np.percentile(np.asarray(xs) * 1000.0, q))  # noqa: E731
    return CameraStats(
        n_frames,
        frame.rgb.shape[1],
        frame.rgb.shape[0],
        (n_frames - 1) / span if span > 0 else float("inf"),
        ms(read_s, 50),
        ms(read_s, 95),
        ms(age_s, 50),
        ms(age_s, 95),
        dropped,
    )


def format_pose(T: np.ndarray) -> str:
    """``x y z`` in mm and the axis-angle rotation in degrees (user-facing units)."""
    p = np.asarray(T)[:3, 3] * 1000.0
    r = np.degrees(so3_log(np.asarray(T)[:3, :3]))
    return f"xyz = [{p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}] mm, rotvec = [{r[0]:.1f}, {r[1]:.1f}, {r[2]:.1f}] deg"


def jog_z(arm, distance_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Move the TCP ``distance_m`` along base +z and back, through the safety layer.

    Returns the start pose, the pose reached, and the pose after returning.
    """
    T0 = arm.tcp_pose()
    T1 = T0.copy()
    T1[2, 3] += distance_m
    arm.move_to(T1)
    reached = arm.tcp_pose()
    arm.move_to(T0)
    return T0, reached, arm.tcp_pose()


# ------------------------------------------------------------------------ the kinematics check
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


# ------------------------------------------------------------------------ joints
@dataclass(frozen=True)
class JointReading:
    """One measured joint: ``value`` in ``unit`` (``rad`` or ``m``, the URDF's) and its limits."""

    name: str
    value: float
    unit: str
    lower: float
    upper: float

    @property
    def above_lower(self) -> float:
        """How far above its lower limit (negative: below it)."""
        return self.value - self.lower

    @property
    def below_upper(self) -> float:
        """How far below its upper limit (negative: above it)."""
        return self.upper - self.value

    @property
    def inside(self) -> bool:
        """Within its limits (a limit itself included); a NaN is not."""
        return self.above_lower >= 0 and self.below_upper >= 0


def joint_readings(scene_arm: SceneArm, q: Sequence[float]) -> list[JointReading]:
    """The joints ``q (n,)`` of ``scene_arm``'s chain, in its order, with their URDF position limits."""
    q = np.asarray(q, dtype=np.float64)
    if q.shape != (scene_arm.n_joints,):
        raise ValueError(
            f"{scene_arm.n_joints} joint positions expected ({', '.join(scene_arm.joint_names)}), got shape {q.shape}"
        )
    lo = scene_arm.model.limits.q_min.detach().cpu().numpy()
    hi = scene_arm.model.limits.q_max.detach().cpu().numpy()
    return [
        JointReading(name, float(v), unit, float(a), float(b))
        for name, unit, v, a, b in zip(scene_arm.joint_names, scene_arm.units, q, lo, hi)
    ]


def format_joint(r: JointReading, name_width: int = 0) -> str:
    """One line: the joint's value (and degrees for a revolute one), its limits, and its distance to
    each, or by how much it is outside them (a wrong ``sign`` or ``offset_ticks``, or a wrong URDF).
    ``name_width``: the name is padded to it, so a list of joints lines up."""
    deg = f" ({math.degrees(r.value):+6.1f} deg)" if r.unit == "rad" else ""
    head = f"{r.name:<{name_width}} = {r.value:+.4f} {r.unit}{deg}; limits [{r.lower:+.4f}, {r.upper:+.4f}] {r.unit}"
    if r.inside:
        return f"{head}: {r.above_lower:.4f} above the lower, {r.below_upper:.4f} below the upper"
    if not math.isfinite(r.value):
        return f"{head}: OUTSIDE them, not a finite number"
    if r.above_lower < 0:
        return f"{head}: OUTSIDE them, {-r.above_lower:.4f} {r.unit} below the lower"
    return f"{head}: OUTSIDE them, {-r.below_upper:.4f} {r.unit} above the upper"
