"""PCGrad (Yu et al., 2020) over the objective's N term gradients, and the normalised texture update."""

from __future__ import annotations

import torch

__all__ = ["pcgrad", "pcgrad_many", "sum_gradients", "normalized_step"]


def pcgrad_many(grads: list[torch.Tensor], eps: float = 1e-20) -> torch.Tensor:
    """Project each gradient off every other one it conflicts with, then **sum** (as the paper).

    For each term ``i`` in order, ``g_i'`` starts at ``g_i`` and, for every other term ``j`` in
    order with ``<g_i', g_j> < 0``, becomes ``g_i' - <g_i', g_j>/|g_j|^2 g_j`` (projections onto the
    original gradients, as Yu et al.; the order is the objective's, fixed, so a run needs no extra
    RNG). Averaging instead would shrink the step. A zero gradient is never projected onto, and one
    gradient passes through unchanged. Two gradients give exactly :func:`pcgrad`'s result.
    """
    if not grads:
        raise ValueError("pcgrad_many: no gradients")
    flat = [g.reshape(-1) for g in grads]
    sq = [torch.dot(f, f) for f in flat]
    dots: dict[tuple[int, int], torch.Tensor] = {}
    out = None
    for i, gi in enumerate(grads):
        p, projected = gi, False
        for j, gj in enumerate(grads):
            if j == i:
                continue
            if projected:
                dot = torch.dot(p.reshape(-1), flat[j])
            else:  # the original pair's dot, computed once for both orders (symmetric)
                key = (min(i, j), max(i, j))
                if key not in dots:
                    dots[key] = torch.dot(flat[key[0]], flat[key[1]])
                dot = dots[key]
            if dot < 0 and sq[j] > eps:
                p = p - (dot / sq[j].clamp_min(eps)) * gj
                projected = True
        out = p if out is None else out + p
    return out


def pcgrad(g1: torch.Tensor, g2: torch.Tensor, eps: float = 1e-20) -> torch.Tensor:
    """PCGrad of two gradients: if ``<g1, g2> < 0``, ``g1' = g1 - <g1, g2>/|g2|^2 g2`` and
    ``g2' = g2 - <g2, g1>/|g1|^2 g1`` (both from the original gradients), then ``g1' + g2'``."""
    return pcgrad_many([g1, g2], eps)


def sum_gradients(grads: list[torch.Tensor]) -> torch.Tensor:
    """The plain sum of the term gradients, in order (the objective without gradient surgery)."""
    if not grads:
        raise ValueError("sum_gradients: no gradients")
    out = grads[0]
    for g in grads[1:]:
        out = out + g
    return out


def normalized_step(texture: torch.Tensor, grad: torch.Tensor, lr: float) -> tuple[torch.Tensor, bool]:
    """``T <- clip(T - lr * g / ||g||_2, 0, 1)``; returns ``(T, updated)``.

    A zero or non-finite gradient skips the update (the texture is returned unchanged).
    """
    norm = torch.linalg.vector_norm(grad)
    if not torch.isfinite(norm) or norm <= 0:
        return texture, False
    return (texture - lr * grad / norm).clamp(0.0, 1.0), True
