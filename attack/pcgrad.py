"""PCGrad (Yu et al., 2020) for two objectives, and the normalised texture update."""

from __future__ import annotations

import torch

__all__ = ["pcgrad", "normalized_step"]


def pcgrad(g1: torch.Tensor, g2: torch.Tensor, eps: float = 1e-20) -> torch.Tensor:
    """Project each gradient off the other where they conflict, then **sum** (as the paper).

    If ``<g1, g2> < 0``: ``g1' = g1 - <g1, g2>/|g2|^2 g2`` and ``g2' = g2 - <g2, g1>/|g1|^2 g1``
    (both projections use the original gradients). Averaging instead would halve the step.
    Zero gradients pass through unchanged.
    """
    a, b = g1.reshape(-1), g2.reshape(-1)
    dot = torch.dot(a, b)
    if dot >= 0:
        return g1 + g2
    na, nb = torch.dot(a, a), torch.dot(b, b)
    p1 = g1 - (dot / nb.clamp_min(eps)) * g2 if nb > eps else g1
    p2 = g2 - (dot / na.clamp_min(eps)) * g1 if na > eps else g2
    return p1 + p2


def normalized_step(texture: torch.Tensor, grad: torch.Tensor, lr: float) -> tuple[torch.Tensor, bool]:
    """``T <- clip(T - lr * g / ||g||_2, 0, 1)``; returns ``(T, updated)``.

    A zero or non-finite gradient skips the update (the texture is returned unchanged).
    """
    norm = torch.linalg.vector_norm(grad)
    if not torch.isfinite(norm) or norm <= 0:
        return texture, False
    return (texture - lr * grad / norm).clamp(0.0, 1.0), True
