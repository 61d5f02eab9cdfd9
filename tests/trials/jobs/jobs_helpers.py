"""Small job functions for the job-layer tests (importable by Ray workers: the repo root is on
their path). Each follows the job contract: ``fn(out, inputs, **params)``, resumable."""

import json
import os
import time
from pathlib import Path

from sim.errors import AdvobjError


def write_value(out: Path, inputs: dict, value: int, sleep_s: float = 0.0) -> None:
    """Writes ``value`` plus the sum of its inputs' values; records pid and attempt."""
    out.mkdir(parents=True, exist_ok=True)
    attempts = out / "attempts.txt"
    with open(attempts, "a") as f:
        f.write(f"{os.getpid()}\n")
    (out / "pid").write_text(str(os.getpid()))
    time.sleep(sleep_s)
    total = value + sum(json.loads((Path(p) / "value.json").read_text())["total"] for p in inputs.values())
    (out / "value.json").write_text(json.dumps({"value": value, "total": total, "torch_threads": _threads()}))


def _threads() -> int:
    import torch

    return torch.get_num_threads()


def slow_until_released(out: Path, inputs: dict, release: str, value: int = 1) -> None:
    """Writes a half output, then waits for the ``release`` file (the test kills it meanwhile)."""
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "attempts.txt", "a") as f:
        f.write(f"{os.getpid()}\n")
    (out / "half-written.json").write_text("{")
    (out / "pid").write_text(str(os.getpid()))
    deadline = time.time() + 120
    while not Path(release).exists() and time.time() < deadline:
        time.sleep(0.1)
    (out / "value.json").write_text(json.dumps({"value": value, "total": value}))


def bad_config(out: Path, inputs: dict, field: str) -> None:
    raise AdvobjError(f"attack config: {field}: must be positive")


def node_of(out: Path, inputs: dict) -> None:
    import ray

    out.mkdir(parents=True, exist_ok=True)
    (out / "node.json").write_text(
        json.dumps({"node": ray.get_runtime_context().get_node_id(), "gpus": ray.get_gpu_ids()})
    )
