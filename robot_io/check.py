"""What ``advobj hw check`` measures: camera frame rate and latency, the arm's pose, an optional jog."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from sim.geometry import so3_log

__all__ = ["CameraStats", "measure_camera", "format_pose", "jog_z"]


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
