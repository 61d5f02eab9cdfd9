"""The reach criterion, one pure function shared by simulation and real trials.

An object is *reached* when the TCP is within ``radius_m`` of its centre **and** it is strictly
the closest object. A tie for closest means no object is reached (the outcome would be a guess).
The comparison is inclusive: exactly ``radius_m`` away counts as within.
"""

from __future__ import annotations

import numpy as np

__all__ = ["NONE", "reach_outcome", "object_distances"]

NONE = -1


def object_distances(tcp_pos, object_pos) -> np.ndarray:
    """Euclidean distances ``(B, K)`` m from ``tcp_pos: (B, 3)`` m to ``object_pos: (B, K, 3)`` m."""
    tcp_pos = np.asarray(tcp_pos, dtype=np.float64)
    object_pos = np.asarray(object_pos, dtype=np.float64)
    return np.linalg.norm(object_pos - tcp_pos[:, None, :], axis=-1)


def reach_outcome(tcp_pos, object_pos, radius_m: float) -> np.ndarray:
    """Index ``(B,)`` of the reached object per row, or ``NONE`` (-1).

    ``object_pos`` rows may contain NaN for objects whose position is unknown (e.g. an undetected
    tag in a real trial); such an object can never be reached, and a row where the closest known
    object could be beaten by an unknown one is the caller's business (see calibration).
    """
    d = object_distances(tcp_pos, object_pos)
    if d.shape[1] == 0:
        return np.full(d.shape[0], NONE, dtype=np.int64)
    d = np.where(np.isnan(d), np.inf, d)
    k = np.argmin(d, axis=1)
    dmin = np.take_along_axis(d, k[:, None], 1)[:, 0]
    ties = (d == dmin[:, None]).sum(axis=1) > 1
    reached = (dmin <= radius_m) & ~ties
    return np.where(reached, k, NONE).astype(np.int64)
