"""Safe names and safe joins: data never chooses where a file is written or removed.

Ids and names that end up in file paths (trial ids, session names, ...) must be one plain token:
1 to 64 characters from ``A-Z a-z 0-9 . _ -``, not starting with a dot (so never ``.`` or ``..``,
never hidden, never a path with ``/``). :data:`SafeName` applies that rule to a pydantic field,
:func:`check_name` to a command-line value.

:func:`safe_join` is the second line: every path built from data is resolved (symlinks followed)
and refused unless it lies inside its root, before anything is written there or removed.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated

from pydantic import AfterValidator

from sim.errors import AdvobjError

__all__ = ["UnsafePathError", "SAFE_NAME_RULE", "name_problem", "check_name", "SafeName", "safe_join"]

_SAFE_NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]{0,63}")
SAFE_NAME_RULE = "1-64 letters, digits, '.', '_' or '-', not starting with '.'"


class UnsafePathError(AdvobjError, ValueError):
    """A name is not a safe path component, or a path built from data leaves its root."""


def name_problem(value) -> str | None:
    """Why ``value`` is not a safe name (``None``: it is one)."""
    if not isinstance(value, str):
        return f"must be a string, got {type(value).__name__}"
    if _SAFE_NAME.fullmatch(value) is None:
        return f"{value!r} is not a safe name: use {SAFE_NAME_RULE}"
    return None


def check_name(value, what: str) -> str:
    """``value`` if it is a safe name, else :class:`UnsafePathError` naming ``what`` (a flag or field)."""
    problem = name_problem(value)
    if problem is not None:
        raise UnsafePathError(f"{what}: {problem}")
    return value


def _validate(value: str) -> str:
    problem = name_problem(value)
    if problem is not None:
        raise ValueError(problem)
    return value


#: A pydantic string field holding a safe name (see the module docstring).
SafeName = Annotated[str, AfterValidator(_validate)]


def safe_join(root: str | Path, *parts: str | Path, what: str | None = None) -> Path:
    """``root / parts`` resolved, refused unless it lies strictly inside ``root`` (resolved too).

    Symlinks are followed: a link under ``root`` that points outside it is refused like ``..``.
    An absolute part, or a result equal to ``root`` itself, is refused. ``what`` names the input
    the parts came from in the error message.
    """
    base = Path(root).resolve()
    label = f"{what}: " if what else ""
    if not parts:
        raise UnsafePathError(f"{label}no path below {base} given")
    for part in parts:
        if Path(part).is_absolute():
            raise UnsafePathError(f"{label}{str(part)!r} is an absolute path; expected a path inside {base}")
    target = base.joinpath(*parts).resolve()
    if base not in target.parents:
        shown = "/".join(str(p) for p in parts)
        raise UnsafePathError(f"{label}{shown!r} leads to {target}, outside {base}")
    return target
