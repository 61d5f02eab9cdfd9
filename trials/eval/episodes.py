"""Episode storage: append-only CSV rows (one per episode) plus a manifest of the resolved config.

Layout of an evaluation directory::

    manifest.json     the resolved evaluation config and its hash (written once, before any row)
    episodes.csv      one row per finished episode, appended and flushed to disk per episode
    summary.json      aggregated metrics (rewritten at the end)

A crash leaves at worst one truncated last line, which is dropped on reopen; finished episodes are
never redone. Reopening a directory whose manifest holds a different config is refused.
:func:`collect_evals` puts several evaluations' rows (with an ``eval`` column) and summaries into
one folder, the form the committed evidence under ``results/`` has.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
from pathlib import Path

from sim.errors import AdvobjError

__all__ = [
    "StorageError",
    "EpisodeStore",
    "BASE_COLUMNS",
    "SUMMARY_NAME",
    "EPISODES_NAME",
    "MANIFEST_NAME",
    "config_hash",
    "read_rows",
    "has_rows",
    "read_manifest",
    "has_manifest",
    "has_summary",
    "read_collected",
    "write_summary",
    "read_summary",
    "collect_evals",
]

EPISODES_NAME = "episodes.csv"
MANIFEST_NAME = "manifest.json"
SUMMARY_NAME = "summary.json"


class StorageError(AdvobjError, ValueError):
    """An evaluation directory is malformed or belongs to a different config."""


# Per-object minimum distances follow as ``min_dist_<object name>`` (m).
BASE_COLUMNS = (
    "condition",
    "seed",
    "r_m",
    "theta_rad",
    "phi_rad",
    "outcome",
    "reached",
    "success",
    "targeted",
    "steps",
    "e_trans",
    "e_rot",
)

_INT = {"seed", "reached", "steps"}
_BOOL = {"success", "targeted"}
_STR = {"condition", "outcome", "eval"}  # "eval": the evaluation a row came from, in results/<recipe>/episodes.csv


def write_summary(out: str | Path, summary: dict, default=None) -> Path:
    """Write an evaluation's ``summary.json`` into ``out`` atomically (a temporary, then a rename)."""
    out = Path(out)
    tmp = out / f".{SUMMARY_NAME}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps(summary, indent=2, default=default))
    tmp.replace(out / SUMMARY_NAME)
    return out / SUMMARY_NAME


def read_summary(eval_dir: str | Path) -> dict:
    """An evaluation's summary (``summary.json``, a mapping with ``conditions``); one
    :class:`StorageError` naming the file when it is missing or is not an eval summary."""
    path = Path(eval_dir) / SUMMARY_NAME
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise StorageError(f"{path}: missing; is {path.parent} an 'advobj eval' directory?") from None
    except OSError as err:
        raise StorageError(f"{path}: unreadable ({err.strerror or err})") from None
    except UnicodeDecodeError:
        raise StorageError(f"{path}: not an eval summary (a binary file, not UTF-8 JSON)") from None
    except (json.JSONDecodeError, RecursionError) as err:
        raise StorageError(
            f"{path}: not an eval summary ({type(err).__name__}: {' '.join(str(err).split())})"
        ) from None
    if not isinstance(doc, dict) or not isinstance(doc.get("conditions"), dict):
        raise StorageError(f"{path}: not an eval summary (no 'conditions' mapping)")
    return doc


def has_rows(eval_dir: str | Path) -> bool:
    """Whether ``eval_dir`` holds an ``episodes.csv`` (an evaluation that has run, or a collection
    of :func:`collect_evals`)."""
    return (Path(eval_dir) / EPISODES_NAME).is_file()


def has_summary(eval_dir: str | Path) -> bool:
    """Whether ``eval_dir`` holds a ``summary.json`` (an evaluation that has finished)."""
    return (Path(eval_dir) / SUMMARY_NAME).is_file()


def read_collected(dst: str | Path) -> dict:
    """The ``summary.json`` of a :func:`collect_evals` folder: evaluation name -> its summary; one
    :class:`StorageError` naming the file when it is missing or is not such a mapping."""
    path = Path(dst) / SUMMARY_NAME
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise StorageError(f"{path}: missing; collect the evaluations first") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as err:
        raise StorageError(f"{path}: not a collection of eval summaries ({type(err).__name__})") from None
    if not isinstance(doc, dict) or not all(isinstance(v, dict) and "conditions" in v for v in doc.values()):
        raise StorageError(f"{path}: not a collection of eval summaries (name -> summary with 'conditions')")
    return doc


def has_manifest(eval_dir: str | Path) -> bool:
    """Whether an evaluation was started in ``eval_dir`` (its ``manifest.json`` is written first)."""
    return (Path(eval_dir) / MANIFEST_NAME).is_file()


def read_manifest(eval_dir: str | Path) -> dict:
    """An evaluation's manifest (``manifest.json``: ``config`` and ``config_hash``); one
    :class:`StorageError` naming the file when it is missing or is not a manifest."""
    path = Path(eval_dir) / MANIFEST_NAME
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise StorageError(f"{path}: missing; is {path.parent} an 'advobj eval' directory?") from None
    except OSError as err:
        raise StorageError(f"{path}: unreadable ({err.strerror or err})") from None
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as err:
        raise StorageError(f"{path}: not an eval manifest ({type(err).__name__})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("config"), dict):
        raise StorageError(f"{path}: not an eval manifest (no 'config' mapping)")
    return doc


def collect_evals(dst: str | Path, eval_dirs, relative_to: str | Path | None = None) -> int:
    """Several evaluations in one folder (the committed evidence's form): ``dst/episodes.csv`` with
    every row of ``eval_dirs`` (those with rows, in order) as stored, after a first column ``eval``
    naming the directory (:func:`read_rows` reads it), and ``dst/summary.json`` mapping each
    directory's name to its summary plus its manifest's ``overlap``; with ``relative_to``, the
    summaries' paths under that folder are written relative to it (no machine path is committed).
    Returns the number of rows."""
    dst = Path(dst)
    dst.mkdir(parents=True, exist_ok=True)
    rows, header, summaries = [], None, {}
    for ev in map(Path, eval_dirs):
        if not has_rows(ev):
            continue
        with open(ev / EPISODES_NAME, newline="") as f:
            reader = csv.DictReader(f)
            header = header or ["eval"] + list(reader.fieldnames)
            rows += [{"eval": ev.name, **r} for r in reader]
        summaries[ev.name] = read_summary(ev)
        summaries[ev.name]["overlap"] = read_manifest(ev)["config"].get("overlap")
    with open(dst / EPISODES_NAME, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=header)
        w.writeheader()
        w.writerows(rows)
    text = json.dumps(summaries, indent=1)
    if relative_to is not None:
        root = str(Path(relative_to).resolve()).rstrip("/") + "/"
        text = text.replace(json.dumps(root)[1:-1], "")
    (dst / SUMMARY_NAME).write_text(text)
    return len(rows)


def config_hash(config: dict) -> str:
    """SHA-256 (first 16 hex digits) of a JSON-able config, key order independent."""
    return hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _parse(row: dict) -> dict:
    out = {}
    for k, v in row.items():
        if k in _STR:
            out[k] = v
        elif k in _INT:
            out[k] = int(v)
        elif k in _BOOL:
            out[k] = v == "1"
        else:
            out[k] = float(v) if v != "" else float("nan")
    return out


def read_rows(path: str | Path) -> list[dict]:
    """Parsed rows of an evaluation directory's ``episodes.csv`` (``path``: the directory, or the
    file itself); none when it has no rows yet. A truncated last line (crash mid-write) is ignored."""
    path = Path(path)
    if path.is_dir():
        path = path / EPISODES_NAME
    if not path.is_file():
        return []
    text = path.read_text()
    lines = text.splitlines(keepends=True)
    if lines and not lines[-1].endswith("\n"):
        lines = lines[:-1]
    if not lines:
        return []
    reader = csv.DictReader(io.StringIO("".join(lines)))
    rows = []
    for i, r in enumerate(reader, start=2):
        if None in r or any(v is None for v in r.values()):
            raise StorageError(f"{path}: line {i} has the wrong number of fields")
        try:
            rows.append(_parse(r))
        except ValueError as err:
            raise StorageError(f"{path}: line {i}: {err}") from None
    return rows


class EpisodeStore:
    """Append-only episode rows for one evaluation directory.

    Args:
        out_dir: the evaluation directory.
        config: the resolved, JSON-able evaluation config (its hash guards resumption).
        object_names: scene object names, for the ``min_dist_<name>`` columns.
        resume: allow a directory that already holds rows of the same config.
    """

    def __init__(self, out_dir: str | Path, config: dict, object_names, resume: bool = True):
        self.dir = Path(out_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.columns = list(BASE_COLUMNS) + [f"min_dist_{n}" for n in object_names]
        self.path = self.dir / EPISODES_NAME
        self.manifest_path = self.dir / MANIFEST_NAME
        h = config_hash(config)
        if self.manifest_path.is_file():
            try:
                old = json.loads(self.manifest_path.read_text())
            except json.JSONDecodeError as err:
                raise StorageError(f"{self.manifest_path}: unreadable manifest ({err})") from None
            if old.get("config_hash") != h:
                diff = sorted(
                    k for k in set(old.get("config", {})) | set(config) if old.get("config", {}).get(k) != config.get(k)
                )
                raise StorageError(
                    f"{self.dir}: holds an evaluation with a different config (fields: {', '.join(diff) or '?'}); "
                    "use another --out or delete the directory"
                )
            if not resume and self.path.is_file() and read_rows(self.path):
                raise StorageError(
                    f"{self.dir}: already holds episodes; pass --resume to continue, or use another --out"
                )
        else:
            tmp = self.manifest_path.with_suffix(".json.tmp")
            tmp.write_text(
                json.dumps({"format": "advobj-eval/1", "config_hash": h, "config": config}, indent=2, default=str)
            )
            tmp.replace(self.manifest_path)
        self.rows = read_rows(self.path)
        if self.rows and list(self.rows[0]) != self.columns:
            raise StorageError(f"{self.path}: columns differ from this scene's ({', '.join(self.columns)})")
        self._rewrite_clean()
        self._done = {(r["condition"], r["seed"]) for r in self.rows}

    def _rewrite_clean(self) -> None:
        """Drop a truncated last line (or write the header) so appends start on a fresh line."""
        text = self.path.read_text() if self.path.is_file() else ""
        if text and text.endswith("\n"):
            return
        buf = io.StringIO()
        w = csv.DictWriter(buf, self.columns, lineterminator="\n")
        w.writeheader()
        for r in self.rows:
            w.writerow(self._format(r))
        tmp = self.path.with_suffix(".csv.tmp")
        tmp.write_text(buf.getvalue())
        tmp.replace(self.path)

    @staticmethod
    def _format(row: dict) -> dict:
        out = {}
        for k, v in row.items():
            if isinstance(v, (bool,)) or k in _BOOL:
                out[k] = "1" if v else "0"
            elif isinstance(v, float):
                out[k] = "" if v != v else repr(v)
            else:
                out[k] = v
        return out

    def is_done(self, condition: str, seed: int) -> bool:
        return (condition, int(seed)) in self._done

    def append(self, rows: list[dict]) -> None:
        """Append finished episodes and flush them to disk (fsync) before returning."""
        if not rows:
            return
        buf = io.StringIO()
        w = csv.DictWriter(buf, self.columns, lineterminator="\n", extrasaction="raise")
        for r in rows:
            missing = set(self.columns) - set(r)
            if missing:
                raise StorageError(f"episode row lacks columns {sorted(missing)}")
            w.writerow(self._format(r))
        with open(self.path, "a") as f:
            f.write(buf.getvalue())
            f.flush()
            os.fsync(f.fileno())
        for r in rows:
            self.rows.append(dict(r))
            self._done.add((r["condition"], int(r["seed"])))

    def condition_rows(self, condition: str) -> list[dict]:
        return [r for r in self.rows if r["condition"] == condition]
