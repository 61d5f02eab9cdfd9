"""The paper's adversarial losses (Sec. III-B), as pure batch-first torch functions.

Shapes: ``B`` image-action pairs; positions in metres, world frame.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from sim.action import intended_heading, intended_position

__all__ = [
    "safe_cosine",
    "pose_loss",
    "grad_cam",
    "masked_mean",
    "saliency_loss",
    "deviation_loss",
    "goal_attention_loss",
    "untargeted_loss",
]

_EPS = 1e-8


def safe_cosine(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Cosine similarity ``(B,)`` of ``a, b: (B, 3)``; 0 (not NaN) when either vector is zero.

    The norms are floored inside the square root so the gradient at a zero vector is finite too.
    """
    na = torch.sqrt((a * a).sum(-1).clamp_min(_EPS**2))
    nb = torch.sqrt((b * b).sum(-1).clamp_min(_EPS**2))
    return (a * b).sum(-1) / (na * nb)


def pose_loss(
    T_world_tcp: torch.Tensor,
    actions: torch.Tensor,
    p_adv: torch.Tensor,
    max_step_m: float,
    max_step_rad: float,
    lambda_dist: float,
) -> tuple[torch.Tensor, dict]:
    """``L_pose = L_ori + lambda_dist * L_dist`` per pair ``(B,)``.

    ``L_ori = 1 - cos(v_ee, v_target)`` with ``v_ee`` the heading the action would produce and
    ``v_target = p_adv - p_next``; ``L_dist = ||p_adv - p_next||``. ``p_next`` and ``v_ee`` come
    from :mod:`sim.action`, the env's own action semantics. ``actions`` is the executed-next motion
    as a normalised ``delta_tcp`` (:func:`sim.policies.contract.to_delta`); for a joint-space policy
    it is the motion to the TCP pose the arm's FK gives for the joint step, unclipped, so ``p_next``
    and ``v_ee`` are that pose's position and approach axis and the loss is differentiable through
    the FK to the joint action.
    T_world_tcp: (B, 4, 4); actions: (B, 6); p_adv: (B, 3) m.
    """
    T = T_world_tcp.to(actions.dtype)
    p_next = intended_position(T, actions, max_step_m)
    v_ee = intended_heading(T, actions, max_step_rad)
    v_target = p_adv.to(actions.dtype) - p_next
    l_ori = 1.0 - safe_cosine(v_ee, v_target)
    l_dist = torch.sqrt((v_target * v_target).sum(-1).clamp_min(_EPS**2))
    return l_ori + lambda_dist * l_dist, {"ori": l_ori.detach(), "dist": l_dist.detach()}


def grad_cam(A: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """Differentiable Grad-CAM ``S: (B, h, w)`` of feature maps ``A: (B, C, h, w)``.

    Channel weights are the spatial mean of ``d||a||_2 / dA`` computed with ``create_graph=True``
    (so ``S`` stays differentiable w.r.t. the input); ``S = ReLU(sum_k w_k A_k)``.
    """
    norm = torch.sqrt((actions * actions).sum(-1).clamp_min(_EPS**2))
    (dA,) = torch.autograd.grad(norm.sum(), A, create_graph=True)
    w = dA.mean(dim=(2, 3), keepdim=True)
    return F.relu((w * A).sum(1))


def masked_mean(S: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``sum(S * M) / sum(M)`` per image ``(B,)``; 0 where the mask is empty (not NaN).

    S: (B, h, w); mask: (B, h, w) float in [0, 1] (masks resized to the feature grid).
    """
    m = mask.to(S.dtype)
    total = m.sum(dim=(1, 2))
    return torch.where(total > 0, (S * m).sum(dim=(1, 2)) / total.clamp_min(_EPS), torch.zeros_like(total))


def resize_mask(mask: torch.Tensor, hw: tuple[int, int]) -> torch.Tensor:
    """Image masks ``(B, H, W)`` bool -> fractional coverage on the feature grid ``(B, h, w)``."""
    return F.adaptive_avg_pool2d(mask[:, None].float(), hw)[:, 0]


def saliency_loss(S: torch.Tensor, adv_mask: torch.Tensor, goal_mask: torch.Tensor) -> torch.Tensor:
    """``L_saliency = -mean_{M_adv}(S) + mean_{M_goal}(S)`` per image ``(B,)``.

    Masks are image-size bool ``(B, H, W)``; they are resized to the feature grid here.
    """
    hw = S.shape[-2:]
    return -masked_mean(S, resize_mask(adv_mask, hw)) + masked_mean(S, resize_mask(goal_mask, hw))


def deviation_loss(actions: torch.Tensor, actions_clean: torch.Tensor) -> torch.Tensor:
    """``-||a - a_gt||^2`` per pair ``(B,)``: push the action away from the clean one (untargeted).

    actions, actions_clean: (B, 6); the clean actions are constants (detached).
    """
    return -((actions - actions_clean.detach()) ** 2).sum(-1)


def goal_attention_loss(S: torch.Tensor, goal_mask: torch.Tensor, lambda_sal: float) -> torch.Tensor:
    """``lambda_sal * mean_{M_goal}(S)`` per image ``(B,)``: take attention off the goal (untargeted).

    S: (B, h, w); goal_mask: (B, H, W) bool, resized to the feature grid here.
    """
    return lambda_sal * masked_mean(S, resize_mask(goal_mask, S.shape[-2:]))


def untargeted_loss(
    actions: torch.Tensor, actions_clean: torch.Tensor, S: torch.Tensor, goal_mask: torch.Tensor, lambda_sal: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """The ablation's untargeted objective, split into its two terms ``(B,)`` each:
    :func:`deviation_loss` and :func:`goal_attention_loss`."""
    return deviation_loss(actions, actions_clean), goal_attention_loss(S, goal_mask, lambda_sal)
