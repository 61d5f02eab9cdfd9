"""The shared base of every configuration and file schema, and the one way to change a config.

:class:`StrictModel` is what every config model of the project derives from (sim, calibration,
robot_io, trials): unknown keys are errors, values are immutable, and every float, wherever it
sits (a field, a tuple, a list, a dict value), must be a finite number: ``.nan``, ``.inf`` and
``-.inf`` are refused at validation. A field that really means "unbounded" says so itself with
``Field(allow_inf_nan=True)``.

:func:`merged` replaces fields of a validated model and validates the result again: pydantic's
``model_copy(update=...)`` skips validation, so a value merged in from a plan or another file
(``control_hz: 1e-6`` becoming a safety period) would bypass every bound.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError

from sim.errors import AdvobjError, format_validation_error

__all__ = ["STRICT_CONFIG", "StrictModel", "ConfigError", "merged"]

#: The pydantic settings of :class:`StrictModel` (for a model that cannot derive from it).
STRICT_CONFIG = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

M = TypeVar("M", bound=BaseModel)


class StrictModel(BaseModel):
    """Base of every config model: unknown keys refused, frozen, every float finite."""

    model_config = STRICT_CONFIG


class ConfigError(AdvobjError, ValueError):
    """A config file or a merged config value is invalid; the message names the file and field."""


def _plain(value):
    """``value`` with every model in it dumped, so validation sees (and checks) plain data."""
    if isinstance(value, BaseModel):
        return value.model_dump()
    if isinstance(value, (list, tuple)):
        return type(value)(_plain(v) for v in value)
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


def merged(model: M, update: Mapping, *, what: str, source: str | None = None,
           error: type[Exception] = ConfigError) -> M:
    """``model`` with the fields in ``update`` replaced, validated again as a whole.

    ``Model.model_validate({**model.model_dump(), **update})``: bounds, finiteness and model
    validators hold for the merged value. A failure raises ``error`` (an :class:`AdvobjError`)
    with :func:`~sim.errors.format_validation_error`'s message, ``what``/``source`` naming the input.
    """
    data = {**model.model_dump(), **{k: _plain(v) for k, v in update.items()}}
    try:
        return type(model).model_validate(data)
    except ValidationError as err:
        raise error(format_validation_error(err, what, source)) from None
