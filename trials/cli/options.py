"""Option types shared by the commands: one KEY=VALUE parser for every repeatable mapping flag, one
parser of comma-separated integers (``--attack-seeds 0,1,2``), one of comma-separated names
(``--cameras wrist,front``), and the competence gate's option
(``--min-clean-success``) of the commands that attack or evaluate a policy."""

from __future__ import annotations

import typer

from sim.errors import AdvobjError
from sim.policies.competence import CHECK_EPISODES, DEFAULT_MIN_CLEAN_SUCCESS

__all__ = ["OptionError", "int_list", "key_values", "name_list", "MIN_CLEAN_SUCCESS"]

MIN_CLEAN_SUCCESS = typer.Option(
    DEFAULT_MIN_CLEAN_SUCCESS,
    min=0.0,
    max=1.0,
    help="refuse a policy whose clean success on the scene is below this fraction: from its card, else measured on "
    f"at most {CHECK_EPISODES} clean episodes before a task-feasible pool is built; 0 turns the check off",
)


class OptionError(AdvobjError, ValueError):
    """A command-line option's value is malformed; the message names the flag."""


def key_values(items, option: str, key: str = "KEY", value: str = "VALUE") -> dict[str, str]:
    """``["k=v", ...]`` -> ``{k: v}``; a malformed or repeated item is one error naming ``option``.

    ``key``/``value`` name the parts in the message (``--target: expected ARCH=PATH``).
    """
    out: dict[str, str] = {}
    for item in items:
        k, sep, v = str(item).partition("=")
        if not sep or not k or not v:
            raise OptionError(f"{option}: expected {key}={value}, got {item!r}")
        if k in out:
            raise OptionError(f"{option}: {k!r} given twice")
        out[k] = v
    return out


def name_list(text: str | None) -> tuple[str, ...] | None:
    """``"a, b,"`` -> ``("a", "b")`` (None when not given): a comma-separated list of names, each
    stripped, empty ones dropped (so ``","`` is ``()``: the caller says whether none is allowed)."""
    return None if text is None else tuple(n.strip() for n in text.split(",") if n.strip())


def int_list(text: str | None, option: str) -> tuple[int, ...] | None:
    """``"0,1,2"`` -> ``(0, 1, 2)`` (None when not given); anything else is one error naming ``option``."""
    if text is None:
        return None
    try:
        return tuple(int(x) for x in str(text).split(","))
    except ValueError:
        raise OptionError(f"{option}: expected comma-separated integers such as 0,1,2, got {text!r}") from None
