"""Evaluation metrics: ASR, T-ASR, action errors, the paper's bins, intervals and paired tests.

Definitions (used by every report; see ``docs/evaluation.md``):

* **ASR** (attack success rate): fraction of episodes in which the policy does *not* reach the
  goal object within the episode (``reached != goal``). 95% Wilson interval.
* **T-ASR** (targeted ASR): fraction of episodes that end by reaching the adversarial object.
  95% Wilson interval.
* **E_trans**: per step, ``|| a_adv[:3] - a_clean[:3] ||_2`` in normalised action units (an
  action component of 1 is ``max_step_m``; the largest possible value is ``2 * sqrt(3)``), where
  ``a_adv`` is the policy's action on the attacked observation and ``a_clean`` its action on the
  clean observation of the *same state*. An episode's value is the mean over its steps; a
  condition's value is the mean over episodes with a percentile-bootstrap interval (episodes are
  the independent units).
* **E_rot**: per step, the geodesic angle (rad) between the rotations the two actions command,
  ``angle(exp(a_adv[3:] * max_step_rad)^T exp(a_clean[3:] * max_step_rad))``; aggregated as
  E_trans.

All functions are pure and batch-first (numpy arrays in, numbers or arrays out).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from sim.geometry import rotation_angle, so3_exp
from sim.stats import Proportion, proportion

__all__ = [
    "DISTANCE_BINS_CM",
    "PHI_BINS_DEG",
    "bin_index",
    "bin_labels",
    "action_errors",
    "MeanCI",
    "bootstrap_mean_ci",
    "McNemar",
    "mcnemar_exact",
    "mcnemar_from_outcomes",
    "attack_rates",
]

# Paper Table II (initial TCP distance to the adversarial object, cm) and Table I (viewing angle,
# polar angle from the adversarial object's up axis, degrees). Bins are [lo, hi) except the last,
# which also holds its upper edge.
DISTANCE_BINS_CM = (25.0, 36.0, 47.0, 58.0, 69.0, 80.0)
PHI_BINS_DEG = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 90.0)


def bin_index(values, edges) -> np.ndarray:
    """Bin of each value: ``values (n,)`` -> ``(n,)`` int in ``[0, len(edges) - 2]``, -1 outside.

    Bins are half-open ``[edges[i], edges[i + 1])``; the last bin is closed on the right, so
    ``edges[-1]`` belongs to it. NaN is outside.
    """
    v = np.asarray(values, dtype=np.float64)
    e = np.asarray(edges, dtype=np.float64)
    if e.ndim != 1 or len(e) < 2 or np.any(np.diff(e) <= 0):
        raise ValueError(f"bin edges must be strictly increasing with at least 2 entries, got {edges}")
    idx = np.searchsorted(e, v, side="right") - 1
    idx = np.where(v == e[-1], len(e) - 2, idx)
    inside = (v >= e[0]) & (v <= e[-1])
    return np.where(inside, idx, -1).astype(np.int64)


def bin_labels(edges) -> list[str]:
    """``["25-36", "36-47", ...]`` for ``edges``."""
    fmt = lambda x: f"{x:g}"  # noqa: E731
    return [f"{fmt(a)}-{fmt(b)}" for a, b in zip(edges[:-1], edges[1:])]


def action_errors(a_adv, a_clean, max_step_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-step action deviations ``(e_trans (B,), e_rot (B,) rad)`` for actions ``(B, 6)``.

    ``e_trans``: L2 norm of the difference of the normalised translation parts ``a[:, :3]``.
    ``e_rot``: geodesic angle (rad) between the commanded rotations ``exp(a[:, 3:] * max_step_rad)``.
    """
    a = np.asarray(a_adv, dtype=np.float64)
    c = np.asarray(a_clean, dtype=np.float64)
    if a.shape != c.shape or a.ndim != 2 or a.shape[1] != 6:
        raise ValueError(f"actions must both be (B, 6), got {a.shape} and {c.shape}")
    e_trans = np.linalg.norm(a[:, :3] - c[:, :3], axis=-1)
    e_rot = rotation_angle(so3_exp(c[:, 3:] * max_step_rad), so3_exp(a[:, 3:] * max_step_rad))
    return e_trans, np.asarray(e_rot, dtype=np.float64).reshape(-1)


@dataclass(frozen=True)
class MeanCI:
    """A mean over ``n`` values with its percentile-bootstrap interval (NaN when ``n = 0``)."""

    mean: float
    lo: float
    hi: float
    n: int
    confidence: float

    def to_dict(self) -> dict:
        return {"mean": self.mean, "lo": self.lo, "hi": self.hi, "n": self.n, "confidence": self.confidence}


def bootstrap_mean_ci(values, confidence: float = 0.95, n_boot: int = 2000, seed: int = 0) -> MeanCI:
    """Mean of ``values (n,)`` with a percentile bootstrap interval (``n_boot`` resamples).

    NaN values are dropped first. ``n = 0`` gives NaNs; ``n = 1`` (or constant values) gives a
    zero-width interval. Deterministic given ``seed``.
    """
    if not (0.0 < confidence < 1.0):
        raise ValueError(f"confidence must lie in (0, 1), got {confidence}")
    x = np.asarray(values, dtype=np.float64).reshape(-1)
    x = x[np.isfinite(x)]
    n = len(x)
    if n == 0:
        return MeanCI(math.nan, math.nan, math.nan, 0, confidence)
    m = float(x.mean())
    if n == 1 or np.all(x == x[0]):
        return MeanCI(m, m, m, n, confidence)
    rng = np.random.default_rng(seed)
    means = np.empty(n_boot)
    chunk = max(1, 2_000_000 // n)  # bound memory: at most ~2M indices at a time
    for s in range(0, n_boot, chunk):
        k = min(chunk, n_boot - s)
        means[s : s + k] = x[rng.integers(0, n, size=(k, n))].mean(axis=1)
    alpha = 1.0 - confidence
    lo, hi = np.quantile(means, [alpha / 2.0, 1.0 - alpha / 2.0])
    return MeanCI(m, float(min(lo, m)), float(max(hi, m)), n, confidence)


@dataclass(frozen=True)
class McNemar:
    """McNemar's exact test on paired binary outcomes.

    ``b``: pairs positive under A only; ``c``: positive under B only; ``n_pairs``: all pairs.
    ``p_value``: two-sided exact binomial p-value of ``b`` among ``b + c`` discordant pairs at 1/2.
    """

    b: int
    c: int
    n_pairs: int
    p_value: float

    def to_dict(self) -> dict:
        return {"b": self.b, "c": self.c, "n_pairs": self.n_pairs, "p_value": self.p_value}


def mcnemar_exact(b: int, c: int, n_pairs: int | None = None) -> McNemar:
    """Exact McNemar test from the discordant counts ``b`` (A only) and ``c`` (B only).

    ``p = min(1, 2 * sum_{i <= min(b, c)} C(b + c, i) / 2^(b + c))``, computed in exact rational
    arithmetic. No discordant pairs gives ``p = 1``.
    """
    b, c = int(b), int(c)
    if b < 0 or c < 0:
        raise ValueError(f"discordant counts must be >= 0, got b={b}, c={c}")
    n = b + c
    if n == 0:
        p = 1.0
    else:
        tail = sum(math.comb(n, i) for i in range(min(b, c) + 1))
        p = float(min(Fraction(1), Fraction(2 * tail, 2**n)))
    return McNemar(b, c, n if n_pairs is None else int(n_pairs), p)


def mcnemar_from_outcomes(x_a, x_b) -> McNemar:
    """McNemar's exact test on paired booleans ``x_a, x_b (n,)`` (same configs, same order)."""
    a = np.asarray(x_a, dtype=bool).reshape(-1)
    b = np.asarray(x_b, dtype=bool).reshape(-1)
    if a.shape != b.shape:
        raise ValueError(f"paired outcomes must have the same length, got {a.shape} and {b.shape}")
    return mcnemar_exact(int((a & ~b).sum()), int((~a & b).sum()), len(a))


def attack_rates(reached, goal_index: int, adv_index: int, confidence: float = 0.95) -> dict[str, Proportion]:
    """``{"asr": ..., "tasr": ...}`` from ``reached (n,)`` (object index per episode, -1 none)."""
    r = np.asarray(reached, dtype=np.int64).reshape(-1)
    n = len(r)
    return {
        "asr": proportion(int((r != goal_index).sum()), n, confidence),
        "tasr": proportion(int((r == adv_index).sum()), n, confidence),
    }
