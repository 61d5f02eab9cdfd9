"""The scale-out options every grid command shares (``--workers``, ``--address``, ``--shards``)."""

from __future__ import annotations

from typing import Optional

import typer

WORKERS = typer.Option(
    None,
    min=1,
    help="run the jobs on a local Ray started for this run with N worker CPUs (default: serially in-process)",
)
ADDRESS = typer.Option(None, help="run the jobs on a running Ray cluster: 'auto' or HOST:PORT (docs/scale-out.md)")
SHARDS = typer.Option(
    None,
    min=1,
    help="split each evaluation into this many eval-shard jobs (default: 1 serially, else the worker count, "
    "4 on a cluster); the rows do not depend on it",
)


def executor(workers: Optional[int], address: Optional[str], log, progress: bool = True):
    """The executor the options ask for, and the default shard count that goes with it."""
    from trials.jobs.dag import GridError, RayExecutor, SerialExecutor  # lazy: CLI start-up (+15 ms)

    if workers is not None and address is not None:
        raise GridError("--workers/--address: give one of them (a local Ray with N workers, or a cluster to join)")
    if workers is None and address is None:
        return SerialExecutor(log, tee=progress), 1
    return RayExecutor(workers=workers, address=address, echo=log), (workers or 4)
