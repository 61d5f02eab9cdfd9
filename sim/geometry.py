"""Rigid-body geometry: the one place that states the project's conventions.

Conventions (every module follows these):

* Units: metres and radians everywhere; angles in degrees only at user-facing edges (CLI, reports).
* Frames are right-handed. The world frame is the table frame: origin on the table top, +z up.
* Camera frames follow OpenCV: +x right, +y down, +z forward (optical axis).
* The TCP frame has +z along the approach direction (out of the gripper, between the fingers).
* A pose is a 4x4 homogeneous matrix named ``T_parent_child``: it maps points expressed in
  ``child`` into ``parent`` (``p_parent = T_parent_child @ p_child``). Composition chains names:
  ``T_a_c = T_a_b @ T_b_c``.
* Rotations are exchanged as axis-angle vectors (``rotvec``, norm = angle in rad) or 3x3 matrices.
* Every function is pure and batch-first: leading ``...`` dimensions broadcast.

``skew``, ``so3_exp`` and ``so3_log`` accept numpy arrays or torch tensors (the attack needs
gradients through the action semantics); the remaining helpers are numpy (float64).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = [
    "skew",
    "so3_exp",
    "so3_log",
    "se3_exp",
    "se3_log",
    "make_T",
    "invert_T",
    "compose",
    "transform_points",
    "look_at",
    "rotation_angle",
    "rot_z",
]

_SMALL = 1e-6  # below this angle (rad) the Taylor branches are used


def _is_torch(x: Any) -> bool:
    return type(x).__module__.startswith("torch")


def _stack(xs: list, axis: int, like: Any):
    if _is_torch(like):
        import torch  # lazy: robot_io start-up (torch)

        return torch.stack(xs, dim=axis)
    return np.stack(xs, axis=axis)


def skew(v):
    """Skew-symmetric matrix of ``v: (..., 3)`` -> ``(..., 3, 3)`` with ``skew(a) @ b = a x b``."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = x * 0
    rows = [
        _stack([o, -z, y], -1, v),
        _stack([z, o, -x], -1, v),
        _stack([-y, x, o], -1, v),
    ]
    return _stack(rows, -2, v)


def so3_exp(rotvec):
    """Rotation matrix from axis-angle ``rotvec: (..., 3)`` rad -> ``(..., 3, 3)``.

    Rodrigues' formula with Taylor coefficients near zero, so the value and its gradient are
    finite at ``rotvec = 0``.
    """
    if _is_torch(rotvec):
        import torch  # lazy: robot_io start-up (torch)

        theta2 = (rotvec * rotvec).sum(-1)
        small = theta2 < _SMALL**2
        safe2 = torch.where(small, torch.ones_like(theta2), theta2)
        theta = torch.sqrt(safe2)
        a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
        b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / safe2)
        eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device)
    else:
        rotvec = np.asarray(rotvec, dtype=np.float64)
        theta2 = (rotvec * rotvec).sum(-1)
        small = theta2 < _SMALL**2
        safe2 = np.where(small, 1.0, theta2)
        theta = np.sqrt(safe2)
        a = np.where(small, 1.0 - theta2 / 6.0, np.sin(theta) / theta)
        b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(theta)) / safe2)
        eye = np.eye(3)
    K = skew(rotvec)
    return eye + a[..., None, None] * K + b[..., None, None] * (K @ K)


def so3_log(R):
    """Axis-angle ``(..., 3)`` of rotation matrices ``R: (..., 3, 3)`` (numpy), angle in [0, pi].

    Stable at both ends: near 0 it uses the first-order vee map; near pi, where ``sin`` vanishes,
    the axis comes from the symmetric part ``(sym(R) - cos I) / (1 - cos) = n n^T``.
    """
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R, axis1=-2, axis2=-1)
    cos = np.clip((tr - 1.0) / 2.0, -1.0, 1.0)
    vee = 0.5 * np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1
    )  # = sin(theta) * axis
    sin = np.linalg.norm(vee, axis=-1)
    # atan2 keeps full precision at both ends, where arccos loses half the digits.
    theta = np.arctan2(sin, cos)
    near_zero = theta < 1e-4
    near_pi = (np.pi - theta) < 1e-3
    generic = ~(near_zero | near_pi)
    scale = np.where(generic, theta / np.where(generic, sin, 1.0), 1.0 + theta**2 / 6.0)
    out = vee * scale[..., None]
    if np.any(near_pi):
        sym = 0.5 * (R + np.swapaxes(R, -1, -2))
        B = (sym - cos[..., None, None] * np.eye(3)) / (1.0 - cos)[..., None, None]
        diag = np.clip(np.diagonal(B, axis1=-2, axis2=-1), 0.0, None)
        k = np.argmax(diag, axis=-1)
        col = np.take_along_axis(B, k[..., None, None].repeat(3, -1), axis=-2)[..., 0, :]
        denom = np.sqrt(np.take_along_axis(diag, k[..., None], -1))
        axis = col / np.where(denom > 0, denom, 1.0)
        axis = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
        # The symmetric part fixes the axis only up to sign; the antisymmetric part breaks the tie.
        sign = np.where((axis * vee).sum(-1) < 0, -1.0, 1.0)
        out = np.where(near_pi[..., None], axis * (sign * theta)[..., None], out)
    return out


def _left_jacobian(rotvec):
    theta2 = (rotvec * rotvec).sum(-1)
    small = theta2 < _SMALL**2
    safe2 = np.where(small, 1.0, theta2)
    theta = np.sqrt(safe2)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(theta)) / safe2)
    c = np.where(small, 1.0 / 6.0 - theta2 / 120.0, (theta - np.sin(theta)) / (safe2 * theta))
    K = skew(rotvec)
    return np.eye(3) + b[..., None, None] * K + c[..., None, None] * (K @ K)


def se3_exp(xi):
    """Pose from a twist ``xi: (..., 6) = [v (m), omega (rad)]`` -> ``(..., 4, 4)``."""
    xi = np.asarray(xi, dtype=np.float64)
    v, w = xi[..., :3], xi[..., 3:]
    return make_T(so3_exp(w), (_left_jacobian(w) @ v[..., None])[..., 0])


def se3_log(T):
    """Twist ``(..., 6) = [v, omega]`` of poses ``T: (..., 4, 4)``; inverse of :func:`se3_exp`."""
    T = np.asarray(T, dtype=np.float64)
    w = so3_log(T[..., :3, :3])
    v = np.linalg.solve(_left_jacobian(w), T[..., :3, 3:4])[..., 0]
    return np.concatenate([v, w], -1)


def make_T(R, t):
    """Homogeneous pose from ``R: (..., 3, 3)`` and ``t: (..., 3)`` m -> ``(..., 4, 4)``."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    batch = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = np.zeros(batch + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def invert_T(T_a_b):
    """``T_b_a`` from ``T_a_b: (..., 4, 4)`` using the rigid-body structure (no general inverse)."""
    T_a_b = np.asarray(T_a_b, dtype=np.float64)
    R = np.swapaxes(T_a_b[..., :3, :3], -1, -2)
    return make_T(R, -(R @ T_a_b[..., :3, 3:4])[..., 0])


def compose(*Ts):
    """``compose(T_a_b, T_b_c, ...) = T_a_b @ T_b_c @ ...``."""
    out = np.asarray(Ts[0], dtype=np.float64)
    for T in Ts[1:]:
        out = out @ np.asarray(T, dtype=np.float64)
    return out


def transform_points(T_a_b, points_b):
    """Map ``points_b: (..., N, 3)`` m through ``T_a_b: (..., 4, 4)`` -> ``points_a: (..., N, 3)``."""
    T_a_b = np.asarray(T_a_b, dtype=np.float64)
    points_b = np.asarray(points_b, dtype=np.float64)
    return points_b @ np.swapaxes(T_a_b[..., :3, :3], -1, -2) + T_a_b[..., None, :3, 3]


def look_at(eye, target, up=(0.0, 0.0, 1.0)):
    """``T_world_cam`` of an OpenCV camera at ``eye: (..., 3)`` looking at ``target: (..., 3)``.

    The camera's +z points at the target and its +y (image down) is as close to ``-up`` as the
    geometry allows. When the view is parallel to ``up`` a fallback up axis (+y) is used, so
    straight-down views are well defined.
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    z = target - eye
    n = np.linalg.norm(z, axis=-1, keepdims=True)
    if np.any(n < 1e-12):
        raise ValueError("look_at: eye and target coincide")
    z = z / n
    up = np.broadcast_to(np.asarray(up, dtype=np.float64), z.shape)
    # x = y x z with y = -up  =>  x = z x up; then y = z x x is -up with its z component removed.
    x = np.cross(z, up)
    xn = np.linalg.norm(x, axis=-1, keepdims=True)
    alt = np.cross(z, np.broadcast_to([0.0, 1.0, 0.0], z.shape))
    x = np.where(xn < 1e-9, alt, x)
    x = x / np.linalg.norm(x, axis=-1, keepdims=True)
    y = np.cross(z, x)
    return make_T(np.stack([x, y, z], -1), eye)


def rotation_angle(R_a, R_b):
    """Geodesic angle (rad) between rotations ``R_a, R_b: (..., 3, 3)``."""
    R = np.swapaxes(np.asarray(R_a), -1, -2) @ np.asarray(R_b)
    return np.linalg.norm(so3_log(R), axis=-1)


def rot_z(yaw):
    """Rotation about +z by ``yaw: (...)`` rad -> ``(..., 3, 3)``."""
    yaw = np.asarray(yaw, dtype=np.float64)
    return so3_exp(np.stack([np.zeros_like(yaw), np.zeros_like(yaw), yaw], -1))
