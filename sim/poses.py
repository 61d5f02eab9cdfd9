"""A pose as files store it, and the one check of a rigid transform handed in as an array.

Every file of the project that holds a pose ``T_parent_child`` stores it the same way,
``{translation_m: [x, y, z], rotvec_rad: [rx, ry, rz]}`` (metres; axis-angle in radians, the
project's rotation exchange format, :mod:`sim.geometry`). :class:`Pose` is that entry's schema with
its bounds: every value finite (:class:`~sim.configio.StrictModel`), each translation component
within :data:`MAX_TRANSLATION_M` (a cell is metres across: beyond is a unit mistake, millimetres
given as metres, or garbage) and the rotation vector no longer than :data:`MAX_ROTVEC_RAD` (any
rotation needs at most pi; a wound-up value is fine, ``1e200`` would overflow the exponential map).
:func:`check_T` holds a ``(4, 4)`` array (or a batch) to being a rigid transform.

It lives in ``sim``, the ground floor, so that the recording format (:mod:`sim.recording`) and the
calibration files (:mod:`calibration.io`) share one implementation: ``calibration`` imports
``sim``, ``sim`` never imports ``calibration``.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import field_validator

from sim.configio import StrictModel
from sim.geometry import make_T, so3_exp, so3_log

__all__ = ["MAX_TRANSLATION_M", "MAX_ROTVEC_RAD", "ROTATION_TOL", "Pose", "check_T"]

MAX_TRANSLATION_M = 1000.0  # per component; a cell is metres across
MAX_ROTVEC_RAD = 100.0  # norm; a rotation needs at most pi
ROTATION_TOL = 1e-6  # how far R R^T may be from I, and the last row from [0, 0, 0, 1]


class Pose(StrictModel):
    """A rigid transform ``T_parent_child`` as translation (m) + axis-angle rotation (rad), both
    required (a schema that defaults them to the identity redeclares the fields with defaults)."""

    translation_m: tuple[float, float, float]
    rotvec_rad: tuple[float, float, float]

    @field_validator("translation_m")
    @classmethod
    def _bounded_translation(cls, v):
        if max(abs(x) for x in v) > MAX_TRANSLATION_M:
            raise ValueError(f"each component must lie within +-{MAX_TRANSLATION_M:g} m")
        return v

    @field_validator("rotvec_rad")
    @classmethod
    def _bounded_rotvec(cls, v):
        if math.sqrt(sum(x * x for x in v)) > MAX_ROTVEC_RAD:
            raise ValueError(f"norm must be at most {MAX_ROTVEC_RAD:g} rad (a rotation needs at most pi)")
        return v

    @property
    def T(self) -> np.ndarray:
        """The (4, 4) homogeneous transform."""
        return make_T(so3_exp(np.asarray(self.rotvec_rad)), np.asarray(self.translation_m))

    @classmethod
    def of(cls, T: np.ndarray):
        """The entry of the (4, 4) rigid transform ``T`` (hold an untrusted one to :func:`check_T`
        first: the rotation vector is read off ``T[:3, :3]`` as it is)."""
        return cls(
            translation_m=tuple(float(x) for x in T[:3, 3]), rotvec_rad=tuple(float(x) for x in so3_log(T[:3, :3]))
        )


def check_T(
    T,
    name: str,
    tol: float = ROTATION_TOL,
    *,
    single: bool = False,
    max_translation_m: float | None = None,
) -> np.ndarray:
    """``T`` as a float64 ``(..., 4, 4)`` rigid transform (``(4, 4)`` with ``single``), or
    ValueError naming ``name`` in one line: not numbers, the wrong shape, NaN or inf, a rotation part
    that is no proper rotation (``R R^T`` off ``I`` by more than ``tol``, or a reflection), a last
    row other than ``[0, 0, 0, 1]`` (within ``tol``) or, with ``max_translation_m``, a translation
    component beyond it. An empty batch passes."""
    try:
        T = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"{name}: not a 4x4 array of numbers") from None
    if (T.shape != (4, 4)) if single else (T.shape[-2:] != (4, 4)):
        raise ValueError(f"{name}: expected shape {'(4, 4)' if single else '(..., 4, 4)'}, got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{name}: contains NaN or inf")
    R = T[..., :3, :3]
    with np.errstate(over="ignore", invalid="ignore"):  # huge entries overflow: no rotation, refused below
        off = np.abs(R @ np.swapaxes(R, -1, -2) - np.eye(3))
        if not np.all(off <= tol) or np.any(np.linalg.det(R) < 0):
            raise ValueError(f"{name}: the rotation part is not a proper rotation matrix")
    if np.any(np.abs(T[..., 3, :] - [0.0, 0.0, 0.0, 1.0]) > tol):
        raise ValueError(f"{name}: the last row must be [0, 0, 0, 1]")
    if max_translation_m is not None and np.any(np.abs(T[..., :3, 3]) > max_translation_m):
        raise ValueError(f"{name}: each translation component must lie within +-{max_translation_m:g} m")
    return T
