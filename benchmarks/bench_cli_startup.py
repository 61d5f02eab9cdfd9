"""Start-up cost of the CLI: ``advobj --help`` (and ``advobj <group> --help``) from a cold process.

Run: ``.venv/bin/python benchmarks/bench_cli_startup.py [--repeats 7]``. Prints the median wall and
CPU time over the repeats (CPU beside wall: the machine is noisy), and the ten slowest imports of
one run (``python -X importtime``). The budget is ``advobj --help`` <= 1.0 s on an idle machine;
it is the reason the CLI modules import heavy packages (torch, pyrender, cv2, ray) inside the
commands that use them.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import time

BUDGET_S = 1.0


def _one(argv: list[str]) -> tuple[float, float]:
    """(wall s, CPU s) of one cold ``python -m trials.cli.main <argv>``."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(
        [sys.executable, "-c", "from trials.cli.main import main; main()", *argv],
        check=True,
        stdout=subprocess.DEVNULL,
        env={**os.environ, "COLUMNS": "120"},
    )
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def _slowest_imports(argv: list[str], k: int = 10) -> list[tuple[int, str]]:
    out = subprocess.run(
        [sys.executable, "-X", "importtime", "-c", "from trials.cli.main import main; main()", *argv],
        capture_output=True,
        text=True,
    ).stderr
    rows = []
    for line in out.splitlines():
        if not line.startswith("import time:") or "|" not in line:
            continue
        parts = [p.strip() for p in line[len("import time:") :].split("|")]
        if parts[1].isdigit():
            rows.append((int(parts[1]), parts[2]))
    return sorted(rows, reverse=True)[:k]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    a = ap.parse_args()
    print(f"# cold start, median of {a.repeats} runs (budget for advobj --help: {BUDGET_S} s)")
    print("| command | wall s | CPU s |")
    print("|---|---|---|")
    for argv in (["--help"], ["attack", "--help"], ["trial", "--help"], ["calibrate", "--help"]):
        runs = [_one(argv) for _ in range(a.repeats)]
        wall = statistics.median(r[0] for r in runs)
        cpu = statistics.median(r[1] for r in runs)
        print(f"| advobj {' '.join(argv)} | {wall:.3f} | {cpu:.3f} |")
    print("\n# slowest imports of one `advobj --help` (cumulative us, module)")
    for us, mod in _slowest_imports(["--help"]):
        print(f"{us:>10}  {mod}")


if __name__ == "__main__":
    main()
