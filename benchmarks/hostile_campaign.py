"""Run the hostile-input CLI campaign and commit its record: ``results/hostile/``.

Run: ``.venv/bin/python benchmarks/hostile_campaign.py [--out results/hostile]`` from a clean tree.
It runs ``pytest -m slow tests/hostile/test_cli_campaign.py`` (every CLI command x every hostile
input kind, in one process, a per-case timeout) with ``ADVOBJ_CAMPAIGN_OUT`` set, so the campaign
writes ``cases.csv`` (one row per case: command, parameter, kind, exit code, stderr lines, the
first line, problems, files touched outside, seconds, the process's peak RSS so far) and
``figures.json``; this script adds ``run.json`` (command, commit, machine, wall and CPU time).
The record is always the whole campaign: ``ADVOBJ_CAMPAIGN_KINDS`` (which runs some kinds of input
alone) is dropped from the environment. ``tests/hostile/binding_files.py`` builds the well-formed
inputs that do not fit together (a card binding an input the model lacks, a camera no scene has or
another image size; a scene camera of another size than the policy's input; a scene camera
without a pose), ``tests/policy_files.py`` the policy files the white-box path refuses.
``docs/safety.md`` quotes the figures; ``tests/hostile/test_campaign_record.py`` recomputes them
from ``cases.csv``.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # this checkout's packages (and its commit in run.json), not an installed copy


def main() -> None:
    from sim.runinfo import write_run_info
    from trials.experiments.tradeoff import machine_info

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "hostile")
    a = ap.parse_args()
    out = a.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-s", "-m", "slow", "tests/hostile/test_cli_campaign.py"],
        cwd=ROOT,
        env={**{k: v for k, v in os.environ.items() if k != "ADVOBJ_CAMPAIGN_KINDS"}, "ADVOBJ_CAMPAIGN_OUT": str(out)},
    )
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    write_run_info(
        out,
        {
            "command": "python benchmarks/hostile_campaign.py",
            "pytest_exit": proc.returncode,
            "wall_s": round(wall, 1),
            "cpu_s": round(cpu, 1),
            "machine_info": machine_info(),
        },
        seed=None,
    )
    print(f"hostile campaign: pytest exit {proc.returncode}, {wall:.0f} s wall, {cpu:.0f} s CPU -> {out}")
    sys.exit(proc.returncode)


if __name__ == "__main__":
    main()
