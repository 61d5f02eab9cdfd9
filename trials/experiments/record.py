"""The evidence record ``results/<name>/run.json``: every attempt at a committed recipe run.

Each attempt holds the command, the commit it ran at (``+dirty`` when the checkout had uncommitted
changes), the machine, start and end times, wall and CPU time and the exit code; ``collect`` adds the
row count, the jobs' CPU time and the trained policies' clean success. ``tools/evidence.py`` writes
it; the findings read it through :func:`read_record`. :func:`run_attempt` runs one attempt as a
child process and appends it (``trials.experiments.formats`` records its evidence so).
"""

from __future__ import annotations

import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

from sim.runinfo import git_commit

__all__ = [
    "RECORD_NAME",
    "record_path",
    "read_record",
    "write_record",
    "is_dirty",
    "check_evidence",
    "attempt_machine",
    "run_attempt",
]

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


def check_evidence(problems: list[str]) -> tuple[str, int | None]:
    """The checkout's commit, and whether an evidence run may start: ``None`` when it may, ``2`` when
    it is refused. Refused for the caller's ``problems`` (e.g. too few episodes) and for a checkout with
    uncommitted changes (a committed result must name the code that made it: commit first, or run from
    a clean clone); every reason is printed as one ``evidence: ...`` line on stderr."""
    problems = list(problems)
    commit = git_commit()
    if commit.endswith("+dirty"):
        problems.append(f"the checkout has uncommitted changes ({commit}); commit them first")
    if problems:
        print("evidence: " + "; ".join(problems), file=sys.stderr)
        return commit, 2
    return commit, None


def attempt_machine() -> dict:
    """The machine as an attempt records it: cores, CPU model, architecture, system, Python, load now."""
    model = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "cpus": os.cpu_count(),
        "cpu_model": model,
        "machine": platform.machine(),
        "system": platform.system(),
        "python": platform.python_version(),
        "load_avg_start": list(os.getloadavg()),
    }


def run_attempt(folder: str | Path, argv: list[str], command: str, commit: str, cwd=None, env=None) -> dict:
    """Run ``argv`` as a child process (in ``cwd``, with ``env``) and append the attempt to
    ``folder``'s record: ``command`` (as a reader types it), ``commit`` (the caller's, read before it
    refused a dirty checkout), the machine, start and end, wall time, the CPU time of the child and
    every process it waited for, and the exit code. Returns the attempt."""
    attempt = {
        "command": command,
        "commit": commit,
        "machine": attempt_machine(),
        "start_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    rc = subprocess.call(argv, cwd=cwd, env=env)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    attempt.update(
        wall_s=round(time.perf_counter() - t0, 1),
        cpu_s=round((after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), 1),
        exit_code=rc,
        end_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        load_avg_end=list(os.getloadavg()),
    )
    record = read_record(folder)
    record["attempts"].append(attempt)
    write_record(folder, record)
    return attempt
