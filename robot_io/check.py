"""What ``advobj hw check`` measures: camera frame rate and latency, the arm's pose, for an arm a
URDF describes its joints (:func:`joint_readings`: value, unit and distance to each limit, to check
a servo's ``sign`` and ``offset_ticks``), an optional jog.

The kinematics check a joint-capable UR or serial arm runs on connect is the drivers' own:
:func:`robot_io.arms.base.check_kinematics_agree`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from sim.geometry import so3_log

if TYPE_CHECKING:
    from sim.ik import SceneArm

__all__ = [
    "CameraStats",
    "measure_camera",
    "format_pose",
    "jog_z",
    "JointReading",
    "joint_readings",
    "format_joint",
]


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
