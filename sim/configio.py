"""The shared base of every configuration and file schema.

:class:`StrictModel` is what every config model of the project derives from (sim, calibration,
robot_io, trials): unknown keys are errors, values are immutable, and every float, wherever it
sits (a field, a tuple, a list, a dict value), must be a finite number: ``.nan``, ``.inf`` and
``-.inf`` are refused at validation. A field that really means "unbounded" says so itself with
``Field(allow_inf_nan=True)``.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict

__all__ = ["STRICT_CONFIG", "StrictModel"]

#: The pydantic settings of :class:`StrictModel` (for a model that cannot derive from it).
STRICT_CONFIG = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class StrictModel(BaseModel):
    """Base of every config model: unknown keys refused, frozen, every float finite."""

    model_config = STRICT_CONFIG
