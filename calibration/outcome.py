"""The paper's reach criterion on a real robot, with *unknown* as an honest third answer.

The criterion itself is the sim's :func:`sim.outcome.reach_outcome` (within ``radius_m`` of the
object's centre and strictly the closest object). Here the TCP position comes from the arm and the
object centres from their tags. When an object's position is missing (its tag was not seen) the
outcome is :data:`UNKNOWN`: the missing object might be the closest one, or within reach. When an
object's pose is ambiguous, every plausible position is tried; if they disagree the outcome is
:data:`UNKNOWN` as well.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from sim.outcome import NONE, object_distances, reach_outcome

__all__ = ["NONE", "UNKNOWN", "real_reach_outcome", "RealReachResult", "measure_reach"]

UNKNOWN = -2
_MAX_COMBINATIONS = 4096


def real_reach_outcome(tcp_pos, object_pos, radius_m: float, object_pos_alternatives=None) -> np.ndarray:
    """Reached object index ``(B,)``, :data:`NONE` (-1) or :data:`UNKNOWN` (-2).

    tcp_pos: (B, 3) m; object_pos: (B, K, 3) m, NaN rows for objects not detected;
    object_pos_alternatives: optional (B, K, A, 3) other plausible positions per object (NaN where
    there are none). All in one frame (base or table: distances do not care).
    """
    tcp_pos = np.asarray(tcp_pos, dtype=np.float64)
    object_pos = np.asarray(object_pos, dtype=np.float64)
    if tcp_pos.ndim != 2 or tcp_pos.shape[-1] != 3:
        raise ValueError(f"tcp_pos: expected (B, 3), got {tcp_pos.shape}")
    if object_pos.ndim != 3 or object_pos.shape[0] != tcp_pos.shape[0] or object_pos.shape[-1] != 3:
        raise ValueError(f"object_pos: expected (B, K, 3) with B = {tcp_pos.shape[0]}, got {object_pos.shape}")
    B, K = object_pos.shape[:2]
    alts = None
    if object_pos_alternatives is not None:
        alts = np.asarray(object_pos_alternatives, dtype=np.float64)
        if alts.ndim != 4 or alts.shape[:2] != (B, K) or alts.shape[-1] != 3:
            raise ValueError(f"object_pos_alternatives: expected (B, K, A, 3) with (B, K) = {(B, K)}, got {alts.shape}")
    out = np.full(B, UNKNOWN, dtype=np.int64)
    for b in range(B):
        if np.isnan(tcp_pos[b]).any() or np.isnan(object_pos[b]).any():
            continue
        choices = [[object_pos[b, k]] for k in range(K)]
        if alts is not None:
            for k in range(K):
                choices[k] += [a for a in alts[b, k] if not np.isnan(a).any()]
        if np.prod([len(c) for c in choices], dtype=np.float64) > _MAX_COMBINATIONS:
            continue  # too many ambiguous objects to enumerate: unknown rather than a guess
        combos = np.array(list(itertools.product(*choices)))  # (C, K, 3)
        res = reach_outcome(np.repeat(tcp_pos[b : b + 1], len(combos), 0), combos, radius_m)
        if np.all(res == res[0]):
            out[b] = res[0]
    return out


@dataclass(frozen=True)
class RealReachResult:
    """One trial's outcome. ``reached`` is an object name, ``"none"`` or ``"unknown"``."""

    reached: str
    index: int
    distances_m: dict[str, float | None]
    missing: tuple[str, ...]
    ambiguous: tuple[str, ...]
    reason: str

    def to_dict(self) -> dict:
        return {
            "reached": self.reached,
            "index": self.index,
            "distances_m": self.distances_m,
            "missing": list(self.missing),
            "ambiguous": list(self.ambiguous),
            "reason": self.reason,
        }


def measure_reach(
    tcp_pos_base,
    object_positions_base: Mapping[str, Sequence | np.ndarray | None],
    objects: Sequence[str],
    radius_m: float,
) -> RealReachResult:
    """The outcome of one real trial.

    tcp_pos_base: (3,) m from the arm. object_positions_base: name -> (3,) position, or (A, 3)
    plausible positions (best first) when its pose is ambiguous, or None / absent if not detected.
    objects: the trial's objects in index order (every one of them matters).
    """
    tcp = np.asarray(tcp_pos_base, dtype=np.float64).reshape(3)
    K = len(objects)
    best = np.full((K, 3), np.nan)
    alts = []
    missing, ambiguous = [], []
    for k, name in enumerate(objects):
        p = object_positions_base.get(name)
        if p is None:
            missing.append(name)
            alts.append(np.zeros((0, 3)))
            continue
        p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        best[k] = p[0]
        alts.append(p[1:])
        if len(p) > 1:
            ambiguous.append(name)
    A = max((len(a) for a in alts), default=0)
    alt = np.full((1, K, max(A, 1), 3), np.nan)
    for k, a in enumerate(alts):
        alt[0, k, : len(a)] = a
    idx = int(real_reach_outcome(tcp[None], best[None], radius_m, alt)[0])
    d = object_distances(tcp[None], best[None])[0]
    distances = {n: (None if np.isnan(x) else float(x)) for n, x in zip(objects, d)}
    if idx == UNKNOWN:
        reason = (
            f"not detected: {', '.join(missing)}"
            if missing
            else f"ambiguous pose of {', '.join(ambiguous)} changes the outcome"
        )
        return RealReachResult("unknown", idx, distances, tuple(missing), tuple(ambiguous), reason)
    if idx == NONE:
        return RealReachResult(
            "none", idx, distances, (), tuple(ambiguous), f"no object strictly closest within {radius_m:g} m"
        )
    return RealReachResult(
        objects[idx],
        idx,
        distances,
        (),
        tuple(ambiguous),
        f"{objects[idx]} is the closest object, {d[idx]:.3f} m <= {radius_m:g} m",
    )
