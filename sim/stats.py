"""Binomial proportions with Wilson score intervals: success rates, ASR, T-ASR.

The Wilson interval keeps its nominal coverage near 0 and 1 (where attack and clean success rates
live) and never leaves [0, 1], unlike the normal-approximation interval.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from statistics import NormalDist

__all__ = ["wilson_interval", "Proportion", "proportion"]


def _z(confidence: float) -> float:
    if not (0.0 < confidence < 1.0):
        raise ValueError(f"confidence must lie in (0, 1), got {confidence}")
    return NormalDist().inv_cdf(0.5 + confidence / 2.0)


def wilson_interval(k: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval ``(lo, hi)`` for ``k`` successes in ``n`` trials.

    ``n = 0`` carries no information and returns ``(0.0, 1.0)``. ``k = 0`` gives ``lo = 0`` and
    ``k = n`` gives ``hi = 1`` exactly (no rounding drift past the bounds).
    """
    if isinstance(k, bool) or isinstance(n, bool) or int(k) != k or int(n) != n:
        raise ValueError(f"k and n must be integers, got k={k!r}, n={n!r}")
    k, n = int(k), int(n)
    if n < 0 or k < 0 or k > n:
        raise ValueError(f"need 0 <= k <= n, got k={k}, n={n}")
    if n == 0:
        return 0.0, 1.0
    z = _z(confidence)
    p = k / n
    z2n = z * z / n
    centre = (p + z2n / 2.0) / (1.0 + z2n)
    half = z * math.sqrt(p * (1.0 - p) / n + z2n / (4.0 * n)) / (1.0 + z2n)
    lo = 0.0 if k == 0 else max(0.0, centre - half)
    hi = 1.0 if k == n else min(1.0, centre + half)
    return lo, hi


@dataclass(frozen=True)
class Proportion:
    """``k`` of ``n`` with its Wilson interval; ``rate`` is NaN when ``n = 0``."""

    k: int
    n: int
    rate: float
    lo: float
    hi: float
    confidence: float

    def to_dict(self) -> dict:
        return {
            "k": self.k,
            "n": self.n,
            "rate": self.rate,
            "lo": self.lo,
            "hi": self.hi,
            "confidence": self.confidence,
        }

    def __str__(self) -> str:
        pct = int(round(self.confidence * 100))
        if self.n == 0:
            return f"n/a (0 trials; {pct}% CI [0.0%, 100.0%])"
        return f"{100 * self.rate:.1f}% ({self.k}/{self.n}; {pct}% CI [{100 * self.lo:.1f}%, {100 * self.hi:.1f}%])"


def proportion(k: int, n: int, confidence: float = 0.95) -> Proportion:
    """A :class:`Proportion` for ``k`` successes in ``n`` trials."""
    lo, hi = wilson_interval(k, n, confidence)
    return Proportion(int(k), int(n), k / n if n else math.nan, lo, hi, confidence)
