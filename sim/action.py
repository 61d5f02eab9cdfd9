"""What an action does: the single definition shared by the env, the expert and the attack.

An action ``a in [-1, 1]^6`` is a TCP-frame motion: ``a[:3] * max_step_m`` is the translation
(m) and ``a[3:] * max_step_rad`` the axis-angle rotation (rad), both expressed in the current TCP
frame. The next pose is ``T_world_tcp @ [exp(a[3:] * max_step_rad) | a[:3] * max_step_m]``:
translate along the current axes, then rotate about the new TCP origin.

The functions accept numpy arrays or torch tensors so the attack can differentiate the intended
position ``p_next`` and heading ``v_ee`` with respect to the action.
"""

from __future__ import annotations

import numpy as np

from sim.errors import AdvobjError
from sim.geometry import _is_torch, so3_exp

__all__ = [
    "ActionError",
    "POLICY_ERROR",
    "nonfinite_rows",
    "check_actions",
    "next_tcp_pose",
    "intended_position",
    "intended_heading",
]


class ActionError(AdvobjError, ValueError):
    """Actions that are not finite or have the wrong shape."""


# The one rule, in the sim and on the real arm: a policy output with any NaN or +-inf is a policy
# error. The episode (or trial) ends there with this outcome; nothing is clipped into a motion.
POLICY_ERROR = "policy_error"


def nonfinite_rows(actions) -> np.ndarray:
    """``(B,)`` bool: the rows of ``actions: (B, ...)`` holding any NaN or +-inf (a policy error)."""
    a = np.asarray(actions, dtype=np.float64)
    return ~np.isfinite(a.reshape(len(a), -1)).all(axis=1)


def check_actions(actions: np.ndarray, num_envs: int) -> np.ndarray:
    """Validate ``actions: (num_envs, 6)`` and clip to [-1, 1]; NaN or Inf is an error."""
    a = np.asarray(actions, dtype=np.float64)
    if a.shape != (num_envs, 6):
        raise ActionError(f"actions must have shape ({num_envs}, 6), got {a.shape}")
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        raise ActionError(f"non-finite action (NaN or Inf) for env(s) {np.flatnonzero(bad).tolist()}")
    return np.clip(a, -1.0, 1.0)


def _split(T_world_tcp, action, max_step_m: float, max_step_rad: float):
    R = T_world_tcp[..., :3, :3]
    p = T_world_tcp[..., :3, 3]
    dp_tcp = action[..., :3] * max_step_m
    drot = action[..., 3:] * max_step_rad
    return R, p, dp_tcp, drot


def intended_position(T_world_tcp, action, max_step_m: float):
    """``p_next: (..., 3)`` m, the TCP position the action would move to (world frame)."""
    R = T_world_tcp[..., :3, :3]
    p = T_world_tcp[..., :3, 3]
    return p + (R @ (action[..., :3] * max_step_m)[..., None])[..., 0]


def intended_heading(T_world_tcp, action, max_step_rad: float):
    """``v_ee: (..., 3)``, the unit approach axis (TCP +z) after the action (world frame)."""
    R_next = T_world_tcp[..., :3, :3] @ so3_exp(action[..., 3:] * max_step_rad)
    return R_next[..., :, 2]


def next_tcp_pose(T_world_tcp, action, max_step_m: float, max_step_rad: float):
    """``T_world_tcp_next: (..., 4, 4)`` after applying ``action: (..., 6)`` in [-1, 1]."""
    R, _, _, drot = _split(T_world_tcp, action, max_step_m, max_step_rad)
    p_next = intended_position(T_world_tcp, action, max_step_m)
    R_next = R @ so3_exp(drot)
    if _is_torch(action):
        import torch  # lazy: robot_io start-up (torch)

        top = torch.cat([R_next, p_next[..., :, None]], -1)
        bottom = torch.zeros_like(top[..., :1, :])
        bottom[..., 0, 3] = 1.0
        return torch.cat([top, bottom], -2)
    T = np.zeros(np.broadcast_shapes(R_next.shape[:-2], p_next.shape[:-1]) + (4, 4))
    T[..., :3, :3] = R_next
    T[..., :3, 3] = p_next
    T[..., 3, 3] = 1.0
    return T
