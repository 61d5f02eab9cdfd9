"""The shared base of every configuration and file schema, and the one way to change a config.

:class:`StrictModel` is what every config model of the project derives from (sim, calibration,
robot_io, trials): unknown keys are errors, values are immutable, and every float, wherever it
sits (a field, a tuple, a list, a dict value), must be a finite number: ``.nan``, ``.inf`` and
``-.inf`` are refused at validation. A field that really means "unbounded" says so itself with
``Field(allow_inf_nan=True)``.

:func:`merged` replaces fields of a validated model and validates the result again: pydantic's
``model_copy(update=...)`` skips validation, so a value merged in from a plan or another file
(``control_hz: 1e-6`` becoming a safety period) would bypass every bound.

:func:`read_yaml` is the one YAML reader behind every config loader (scenes, hardware, plans,
answers, calibration files): whatever the file holds (binary, not UTF-8, malformed or deeply
nested YAML, a list where a mapping belongs, nothing at all) or whatever the path is (missing, a
directory, unreadable), it raises one error of the caller's kind, in one line naming the file.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

from sim.errors import AdvobjError, format_validation_error

__all__ = ["STRICT_CONFIG", "StrictModel", "ConfigError", "merged", "read_yaml", "file_error"]

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


def merged(
    model: M, update: Mapping, *, what: str, source: str | None = None, error: type[Exception] = ConfigError
) -> M:
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


def file_error(cls: Callable[[str], Exception]) -> Callable[[Path, str], Exception]:
    """An ``error`` for :func:`read_yaml`: ``cls("<path>: <problem>")``."""
    return lambda path, problem: cls(f"{path}: {problem}")


_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # the C loader when available: ~10x faster on large plans


def read_yaml(
    path: str | Path,
    what: str,
    *,
    error: Callable[[Path, str], Exception] = file_error(ConfigError),
    mapping: bool = True,
) -> object:
    """The parsed YAML of ``path`` (a ``dict`` unless ``mapping=False``); any failure raises ``error(path, problem)``.

    ``what`` names the kind of file in the message ("hardware config", "trial plan"). The problem
    is one line: unreadable or missing file, a directory, not UTF-8 text, not valid YAML (with its
    line), nested too deeply, empty, or (``mapping``) a top level that is no mapping.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except IsADirectoryError:
        raise error(path, f"is a directory, expected a {what} file") from None
    except UnicodeDecodeError as err:
        raise error(path, f"not a {what}: not UTF-8 text (byte {err.start}), is it a binary file?") from None
    except OSError as err:
        raise error(path, f"cannot read {what} ({err.strerror or err})") from None
    if "\x00" in text:
        raise error(path, f"not a {what}: a binary file (NUL bytes)")
    try:
        data = yaml.load(text, Loader=_LOADER)
    except RecursionError:
        raise error(path, f"not a usable {what}: YAML nested too deeply") from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        problem = getattr(err, "problem", None)
        raise error(
            path, f"not valid YAML{where}" + (f" ({' '.join(str(problem).split())})" if problem else "")
        ) from None
    except (
        ValueError,
        TypeError,
        OverflowError,
    ) as err:  # a scalar the constructor cannot build (e.g. a huge timestamp)
        raise error(path, f"not a usable {what}: {' '.join(str(err).split())}") from None
    if mapping and not isinstance(data, dict):
        got = "nothing (the file is empty)" if data is None else type(data).__name__
        raise error(path, f"a {what} must be a mapping, got {got}")
    return data
