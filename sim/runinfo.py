"""Provenance written beside every run's outputs: resolved config, seed, git commit, versions."""

from __future__ import annotations

import importlib.metadata
import json
import platform
import subprocess
import sys
import time
from pathlib import Path

from sim.errors import AdvobjError

__all__ = ["RUN_INFO_NAME", "RunInfoError", "git_commit", "write_run_info", "read_run_info"]

RUN_INFO_NAME = "run.json"


class RunInfoError(AdvobjError, ValueError):
    """A run's ``run.json`` is missing or is not run info; the message names the file."""


def git_commit() -> str:
    """The source tree's commit (``+dirty`` if modified), or ``"unknown"`` outside a checkout."""
    root = Path(__file__).resolve().parent.parent
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=5)
        if sha.returncode != 0:
            return "unknown"
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=root,
            capture_output=True,
            text=True,
            timeout=5,
        )
        return sha.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.TimeoutExpired):
        return "unknown"


def read_run_info(run_dir: str | Path, name: str = RUN_INFO_NAME) -> dict:
    """A run's provenance (``run.json``: a mapping with ``config``); one :class:`RunInfoError`
    naming the file when it is missing, unreadable or not run info."""
    path = Path(run_dir) / name
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise RunInfoError(f"{path}: missing") from None
    except OSError as err:
        raise RunInfoError(f"{path}: unreadable ({err.strerror or err})") from None
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as err:
        raise RunInfoError(f"{path}: not run info ({type(err).__name__})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("config"), dict):
        raise RunInfoError(f"{path}: not run info (no 'config' mapping)")
    return doc


def write_run_info(out_dir: str | Path, config: dict, seed: int | None, name: str = RUN_INFO_NAME) -> Path:
    """Write ``out_dir/run.json`` with the resolved ``config`` (JSON-able), seed and provenance."""
    # Torch's version from the package metadata: importing torch costs seconds in jobs that never
    # use it (trial plans, reports); its thread count only when the job already imported it.
    torch = sys.modules.get("torch")
    try:
        torch_version = torch.__version__ if torch is not None else importlib.metadata.version("torch")
    except importlib.metadata.PackageNotFoundError:
        torch_version = None
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    doc = {
        "config": config,
        "seed": seed,
        "git_commit": git_commit(),
        "argv": sys.argv,
        "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "python": platform.python_version(),
        "torch": torch_version,
        "numpy": sys.modules["numpy"].__version__ if "numpy" in sys.modules else importlib.metadata.version("numpy"),
        "torch_threads": torch.get_num_threads() if torch is not None else None,
        "machine": platform.machine(),
    }
    path = out / name
    path.write_text(json.dumps(doc, indent=2, default=str))
    return path
