"""The evidence record ``results/<name>/run.json``: every attempt at a committed recipe run.

Each attempt holds the command, the commit it ran at (``+dirty`` when the checkout had uncommitted
changes), the machine, start and end times, wall and CPU time and the exit code; ``collect`` adds the
row count, the jobs' CPU time and the trained policies' clean success. ``tools/evidence.py`` writes
it; the findings read it through :func:`read_record`.
"""

from __future__ import annotations

import json
from pathlib import Path

__all__ = ["RECORD_NAME", "record_path", "read_record", "write_record", "is_dirty"]

RECORD_NAME = "run.json"


def record_path(folder: str | Path) -> Path:
    """Where the record of the results folder ``folder`` is."""
    return Path(folder) / RECORD_NAME


def read_record(folder: str | Path) -> dict:
    """The record of ``folder`` (``{"attempts": []}`` when there is none yet)."""
    p = record_path(folder)
    return json.loads(p.read_text()) if p.is_file() else {"attempts": []}


def write_record(folder: str | Path, record: dict) -> Path:
    p = record_path(folder)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(record, indent=2))
    return p


def is_dirty(folder: str | Path) -> bool:
    """Whether any attempt in ``folder``'s record ran from a checkout with uncommitted changes."""
    return any(str(a.get("commit", "")).endswith("+dirty") for a in read_record(folder).get("attempts", []))
