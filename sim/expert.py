"""Privileged scripted expert: knows the goal's position and steers the TCP to it.

Translation: a unit attraction toward the goal centre plus a repulsion from every other object
closer than ``avoid_radius_m`` (so the path never "reaches" the wrong object on the way), scaled
to one full step. Rotation: turn the approach axis (TCP +z, which the wrist camera looks along)
toward the goal, so the goal stays centred in the image the policy learns from.
"""

from __future__ import annotations

import numpy as np

__all__ = ["expert_actions"]


def _rotation_toward(z_axis: np.ndarray, target_dir: np.ndarray) -> np.ndarray:
    """Axis-angle (B, 3) that turns unit vectors ``z_axis`` onto ``target_dir`` (world frame)."""
    axis = np.cross(z_axis, target_dir)
    s = np.linalg.norm(axis, axis=-1, keepdims=True)
    c = np.sum(z_axis * target_dir, axis=-1, keepdims=True)
    angle = np.arctan2(s, c)
    return np.where(s > 1e-9, axis / np.maximum(s, 1e-12) * angle, 0.0)


def expert_actions(
    T_world_tcp: np.ndarray,
    object_centers: np.ndarray,
    goal_index: int,
    max_step_m: float,
    max_step_rad: float,
    avoid_radius_m: float = 0.17,
    min_height_m: float = 0.03,
) -> np.ndarray:
    """Expert actions ``(B, 6)`` in [-1, 1] for TCP poses ``(B, 4, 4)`` and centres ``(B, K, 3)`` m."""
    T_world_tcp = np.asarray(T_world_tcp, dtype=np.float64)
    centers = np.asarray(object_centers, dtype=np.float64)
    R = T_world_tcp[:, :3, :3]
    p = T_world_tcp[:, :3, 3]
    to_goal = centers[:, goal_index] - p
    dist_goal = np.linalg.norm(to_goal, axis=-1, keepdims=True)
    direction = to_goal / np.maximum(dist_goal, 1e-9)

    others = np.delete(centers, goal_index, axis=1)
    away = p[:, None, :] - others
    d = np.linalg.norm(away, axis=-1, keepdims=True)
    # Barrier that grows without bound toward an object, biased upward so the path climbs over
    # an object standing between the TCP and the goal instead of stalling in front of it.
    gain = np.clip(avoid_radius_m / np.maximum(d, 1e-9) - 1.0, 0.0, 10.0)
    push = gain * (away / np.maximum(d, 1e-9) + np.array([0.0, 0.0, 0.7]))
    direction = direction + 1.5 * push.sum(axis=1)
    # Keep clear of the table top.
    direction[:, 2] += np.clip((min_height_m - p[:, 2]) / min_height_m, 0.0, None)
    direction /= np.maximum(np.linalg.norm(direction, axis=-1, keepdims=True), 1e-9)

    # Full steps while far; slow down near the goal instead of overshooting it.
    step_m = np.minimum(max_step_m, dist_goal)
    dp_world = direction * step_m
    dp_tcp = np.einsum("bji,bj->bi", R, dp_world) / max_step_m

    look = to_goal / np.maximum(dist_goal, 1e-9)
    rot_world = _rotation_toward(R[:, :, 2], look)
    rot_tcp = np.einsum("bji,bj->bi", R, rot_world)
    angle = np.linalg.norm(rot_tcp, axis=-1, keepdims=True)
    rot_tcp = rot_tcp * np.minimum(1.0, max_step_rad / np.maximum(angle, 1e-12)) / max_step_rad
    return np.clip(np.concatenate([dp_tcp, rot_tcp], -1), -1.0, 1.0)
