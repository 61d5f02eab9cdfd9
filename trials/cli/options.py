"""Option types shared by the commands: one KEY=VALUE parser for every repeatable mapping flag."""

from __future__ import annotations

from sim.errors import AdvobjError

__all__ = ["OptionError", "key_values"]


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
