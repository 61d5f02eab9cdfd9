"""Pose helpers for drivers: the ``[x, y, z, rx, ry, rz]`` vectors arms speak, and interpolation.

Built on :mod:`sim.geometry` (the project's one SE(3)/axis-angle implementation).
"""

from __future__ import annotations

import numpy as np

from sim.geometry import make_T, so3_exp, so3_log

__all__ = ["pose_from_vec", "pose_to_vec", "interpolate_pose", "pose_step", "is_valid_pose"]


def pose_from_vec(vec) -> np.ndarray:
    """``T_base_tcp`` from ``[x, y, z, rx, ry, rz]`` (m, axis-angle rad), the UR / serial format."""
    v = np.asarray(vec, dtype=np.float64)
    if v.shape != (6,):
        raise ValueError(f"a pose vector has 6 entries [x, y, z, rx, ry, rz], got shape {v.shape}")
    return make_T(so3_exp(v[3:]), v[:3])


def pose_to_vec(T) -> list[float]:
    """``[x, y, z, rx, ry, rz]`` of a 4x4 pose (plain floats, ready for a driver call)."""
    T = np.asarray(T, dtype=np.float64)
    return [float(x) for x in np.concatenate([T[:3, 3], so3_log(T[:3, :3])])]


def pose_step(T_a, T_b) -> tuple[float, float]:
    """Translation (m) and rotation angle (rad) from ``T_a`` to ``T_b``."""
    T_a, T_b = np.asarray(T_a, dtype=np.float64), np.asarray(T_b, dtype=np.float64)
    dp = float(np.linalg.norm(T_b[:3, 3] - T_a[:3, 3]))
    dr = float(np.linalg.norm(so3_log(T_a[:3, :3].T @ T_b[:3, :3])))
    return dp, dr


def interpolate_pose(T_a, T_b, s: float) -> np.ndarray:
    """The pose a fraction ``s`` in [0, 1] of the way from ``T_a`` to ``T_b`` (straight line + geodesic)."""
    T_a, T_b = np.asarray(T_a, dtype=np.float64), np.asarray(T_b, dtype=np.float64)
    p = T_a[:3, 3] + s * (T_b[:3, 3] - T_a[:3, 3])
    R = T_a[:3, :3] @ so3_exp(s * so3_log(T_a[:3, :3].T @ T_b[:3, :3]))
    return make_T(R, p)


def is_valid_pose(T, tol: float = 1e-6) -> bool:
    """A finite 4x4 rigid transform (orthonormal rotation with det +1, bottom row 0 0 0 1)."""
    T = np.asarray(T)
    if T.shape != (4, 4) or not np.issubdtype(T.dtype, np.number) or not np.isfinite(T).all():
        return False
    R = T[:3, :3].astype(np.float64)
    with np.errstate(over="ignore", invalid="ignore"):  # huge entries: overflow means "not a rotation"
        ortho = float(np.abs(R.T @ R - _EYE3).max())
        bottom = float(np.abs(T[3] - _BOTTOM).max())
        return bool(ortho <= tol and bottom <= tol and abs(np.linalg.det(R) - 1.0) < tol)


_EYE3 = np.eye(3)
_BOTTOM = np.array([0.0, 0.0, 0.0, 1.0])
