"""The same small grid serially and on a local Ray with ``--workers`` CPUs: speed-up and overhead.

    .venv/bin/python benchmarks/bench_grid.py --policy runs/evidence/policy-quick [--workers 2] [--out runs/bench-grid]

The grid is ``experiment table1`` at a small budget (2 attacks of ``--iterations``, one pool job,
an evaluation of 3 arms x ``--episodes`` in ``--workers`` shards and their merge): the recipe's own
jobs, not a synthetic load. Each mode runs into a fresh folder under ``--out``; the policy is
given, so no training is timed. Prints, per mode, wall and CPU time (the driver's own CPU plus
every job's, from their ``job.json``), the speed-up, and per Ray job the scheduling overhead: the
time from submission to the job's start on its worker, and from its end to the driver holding the
result. Also checks that both modes wrote the same episode rows.

Target (issue: scale out on Ray): speed-up >= 1.6x at 2 workers on 2 cores, overhead <= 1 s per job.
Run it on an otherwise idle machine; the figures are one run's.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def _job_cpu(out: Path) -> tuple[float, int]:
    docs = [json.loads(p.read_text()) for p in out.rglob("job.json")]
    return sum(d.get("cpu_s", 0.0) for d in docs), len(docs)


def _rows(d: Path):
    from trials.eval.episodes import read_rows

    return sorted(tuple(sorted((k, repr(v)) for k, v in r.items())) for r in read_rows(d / "episodes.csv"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--policy", required=True, help="policy checkpoint (e.g. a quick-preset policy)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--episodes", type=int, default=120)
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--out", default="runs/bench-grid")
    ap.add_argument("--record", default=None, help="where the figures go as JSON (default OUT/bench_grid.json)")
    ap.add_argument(
        "--write-docs", action="store_true", help="also rewrite the figures block of docs/scale-out.md from the record"
    )
    a = ap.parse_args()

    import torch

    from trials.experiments.recipes import resolve_experiment, run_experiment
    from trials.jobs.dag import RayExecutor, SerialExecutor

    torch.set_num_threads(1)
    cfg = resolve_experiment("quick", episodes=a.episodes, gifs=0, attack_overrides={"iterations": a.iterations})
    out = Path(a.out)
    results = {}
    for mode in ("serial", "ray"):
        d = out / mode
        shutil.rmtree(d, ignore_errors=True)
        ex = (
            SerialExecutor(None, tee=False)
            if mode == "serial"
            else RayExecutor(workers=a.workers, echo=None, poll_s=0.2)
        )
        t0, c0 = time.perf_counter(), os.times()
        run_experiment(
            "table1",
            cfg,
            d,
            policy=a.policy,
            progress=False,
            log=lambda m: None,
            executor=ex,
            shards=1 if mode == "serial" else a.workers,
        )
        wall = time.perf_counter() - t0
        c1 = os.times()
        driver_cpu = (c1.user - c0.user) + (c1.system - c0.system)
        job_cpu, n_jobs = _job_cpu(d)
        # Serial jobs run in this process: their CPU is the driver's already.
        cpu = driver_cpu if mode == "serial" else driver_cpu + job_cpu
        results[mode] = {"wall_s": wall, "cpu_s": cpu, "jobs": n_jobs, "timings": getattr(ex, "timings", {})}
        print(f"{mode:>6}: {n_jobs} jobs, wall {wall:.1f} s, CPU {cpu:.1f} s")
    same = _rows(out / "serial" / "evals" / "table1") == _rows(out / "ray" / "evals" / "table1")
    t = results["ray"]["timings"]
    # Submission to start, not counting time spent waiting for a CPU while every CPU ran another
    # job: measured from the later of the submission and the last end of a job before this start.
    ends = [v["end_unix"] for v in t.values()]
    starts = [v["start_unix"] - max([v["submit_unix"]] + [e for e in ends if e <= v["start_unix"]]) for v in t.values()]
    collects = [v["collect_s"] for v in t.values()]
    speedup = results["serial"]["wall_s"] / results["ray"]["wall_s"]
    print(f"speed-up at {a.workers} workers: {speedup:.2f}x (target >= 1.6x); same episode rows: {same}")
    print(
        f"overhead per Ray job (n={len(t)}): submission (or a CPU coming free) to start median "
        f"{statistics.median(starts):.2f} "
        f"s, max {max(starts):.2f} s; "
        f"end to result on the driver median {statistics.median(collects):.3f} s, max {max(collects):.3f} s "
        "(target <= 1 s)"
    )
    print(
        f"machine: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}; table1 budget: {a.iterations} "
        "attack iterations, "
        f"{a.episodes} episodes x 3 arms, {a.workers} shards on Ray"
    )
    from sim.runinfo import git_commit

    record = {
        "command": "python benchmarks/bench_grid.py " + " ".join(sys.argv[1:]),
        "commit": git_commit(),
        "machine": {"cpus": os.cpu_count(), "load_avg_end": list(os.getloadavg())},
        "args": vars(a),
        "speedup": speedup,
        "same_rows": same,
        "results": results,
        "overhead": {
            "start_delay_s_median": statistics.median(starts),
            "start_delay_s_max": max(starts),
            "collect_s_median": statistics.median(collects),
            "collect_s_max": max(collects),
            "n": len(t),
        },
    }
    path = Path(a.record) if a.record else out / "bench_grid.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=2))
    if a.write_docs:
        write_docs(record)


DOCS = Path(__file__).resolve().parent.parent / "docs" / "scale-out.md"
START, END = "<!-- bench-grid:start", "<!-- bench-grid:end -->"


def docs_block(rec: dict) -> str:
    """The figures of a record as the docs quote them."""
    r, o, g = rec["results"], rec["overhead"], rec["args"]
    return "\n".join(
        [
            f"Measured by `{rec['command']}` at commit `{rec['commit'][:12]}` on {rec['machine']['cpus']} CPUs "
            f"(`results/bench-grid/bench_grid.json`; one run):",
            "",
            "| mode | jobs | wall (s) | CPU (s) |",
            "|---|---|---|---|",
            f"| serial, in-process | {r['serial']['jobs']} | {r['serial']['wall_s']:.1f} | "
            f"{r['serial']['cpu_s']:.1f} |",
            f"| Ray, `--workers {g['workers']}` | {r['ray']['jobs']} | {r['ray']['wall_s']:.1f} | "
            f"{r['ray']['cpu_s']:.1f} |",
            "",
            f"- Speed-up: **{rec['speedup']:.2f}x** at {g['workers']} workers (target: at least 1.6x). Both modes "
            "wrote the same "
            f"episode rows: {'yes' if rec['same_rows'] else 'NO'}.",
            f"- Scheduling overhead per Ray job (n = {o['n']}), from submission to the job's start on its "
            "worker: median "
            f"{o['start_delay_s_median']:.2f} s, max {o['start_delay_s_max']:.2f} s, counted from the later of the "
            "submission and "
            "the moment a CPU came free (time queued behind other running jobs is not overhead). The maximum "
            "includes starting "
            "a worker process the first time.",
            f"- From the job's end to its result on the driver: median {o['collect_s_median']:.3f} s, max "
            f"{o['collect_s_max']:.3f} s "
            "(target: at most 1 s).",
            f"- Budget: {g['iterations']} attack iterations, {g['episodes']} episodes x 3 arms.",
            "- The Ray CPU time is the driver's own CPU plus every job's, from their `job.json`; Ray's own daemons "
            "are not counted.",
        ]
    )


def write_docs(rec: dict) -> None:
    text = DOCS.read_text()
    i, j = text.index(START), text.index(END)
    head = text[: text.index("\n", i) + 1]
    DOCS.write_text(head + docs_block(rec) + "\n" + text[j:])


if __name__ == "__main__":
    main()
