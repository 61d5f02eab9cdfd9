"""Coarse-to-Fine pose scheduling: which initial configurations EOT samples when.

Configurations are weighted by a Beta density over their normalised camera-object distance
``u = (r - r_min) / (r_max - r_min)`` in [0, 1]. The paper's five stages go from
Beta(13.48, 2.39) (mean 0.85: **far**, coarse) to Beta(2.39, 13.48) (mean 0.15: near, fine).
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

__all__ = ["PAPER_STAGES", "STRATEGIES", "stage_params", "stage_index", "config_weights", "sample_configs"]

PAPER_STAGES: tuple[tuple[float, float], ...] = (
    (13.48, 2.39),
    (23.13, 10.49),
    (19.88, 19.88),
    (10.49, 23.13),
    (2.39, 13.48),
)

Strategy = Literal["c2f", "f2c", "ns", "coarse", "fine"]
STRATEGIES = ("c2f", "f2c", "ns", "coarse", "fine")


def stage_index(iteration: int, total_iterations: int, num_stages: int = len(PAPER_STAGES)) -> int:
    """Stage (0-based) of ``iteration`` when ``total_iterations`` are split into equal stages."""
    if total_iterations <= 0:
        raise ValueError("total_iterations must be positive")
    return min(num_stages - 1, int(iteration * num_stages // total_iterations))


def stage_params(strategy: str, iteration: int, total_iterations: int) -> tuple[float, float] | None:
    """Beta ``(alpha, beta)`` in force at ``iteration``, or ``None`` for uniform sampling (NS)."""
    if strategy not in STRATEGIES:
        raise ValueError(f"schedule: unknown strategy {strategy!r}; choose one of {STRATEGIES}")
    if strategy == "ns":
        return None
    if strategy == "coarse":
        return PAPER_STAGES[0]
    if strategy == "fine":
        return PAPER_STAGES[-1]
    k = stage_index(iteration, total_iterations)
    return PAPER_STAGES[k] if strategy == "c2f" else PAPER_STAGES[len(PAPER_STAGES) - 1 - k]


def _beta_logpdf(u: np.ndarray, a: float, b: float) -> np.ndarray:
    u = np.clip(u, 1e-6, 1 - 1e-6)
    return (a - 1) * np.log(u) + (b - 1) * np.log1p(-u) - (math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b))


def config_weights(r_m: np.ndarray, params: tuple[float, float] | None, r_range_m: tuple[float, float]) -> np.ndarray:
    """Sampling probabilities ``(N,)`` of configurations at distances ``r_m: (N,)`` m."""
    r_m = np.asarray(r_m, dtype=np.float64)
    if params is None:
        return np.full(len(r_m), 1.0 / len(r_m))
    lo, hi = r_range_m
    u = (r_m - lo) / max(hi - lo, 1e-9)
    logw = _beta_logpdf(u, *params)
    w = np.exp(logw - logw.max())  # stable even where the density is astronomically small
    return w / w.sum()


def sample_configs(r_m: np.ndarray, params, r_range_m, k: int, rng: np.random.Generator) -> np.ndarray:
    """Indices ``(k,)`` of configurations drawn (with replacement) by :func:`config_weights`."""
    return rng.choice(len(r_m), size=k, replace=True, p=config_weights(r_m, params, r_range_m))
