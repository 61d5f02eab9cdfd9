"""``benchmarks/bench_control_loop.py --out``: the printed figures also written as a JSON record.

The script is run as a reader runs it (a child process from the clone's root), with a few steps.
"""

import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = "benchmarks/bench_control_loop.py"
TINY = ["--steps", "5", "--warmup", "1", "--size", "32"]
STAGES = ("camera", "policy", "decode", "safety_arm_command", "loop")
FIGURES = ("wall_median_ms", "wall_p95_ms", "cpu_median_ms", "cpu_p95_ms")
# One printed stage: "  <label>  median X ms   p95 Y ms   (process CPU median Z ms, p95 W ms)".
PRINTED = re.compile(
    r"^  (?P<label>.+?)\s+median\s+(?P<wall_median_ms>[\d.]+) ms\s+p95\s+(?P<wall_p95_ms>[\d.]+) ms\s+"
    r"\(process CPU median\s+(?P<cpu_median_ms>[\d.]+) ms, p95\s+(?P<cpu_p95_ms>[\d.]+) ms\)"
)


def _run(args: list[str]) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYOPENGL_PLATFORM="egl")
    return subprocess.run(
        [sys.executable, SCRIPT, *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300
    )


@pytest.fixture(scope="module", params=["tcp", "joint"])
def bench_run(request, tmp_path_factory):
    """One tiny run of an arm mode with --out: (arguments, printed lines, JSON record, its folder)."""
    folder = tmp_path_factory.mktemp(f"bench_{request.param}")
    args = ["--arm", request.param, *TINY, "--out", str(folder / "loop.json")]
    r = _run(args)
    assert r.returncode == 0, r.stderr[-2000:]
    return args, r.stdout.splitlines(), json.loads((folder / "loop.json").read_text()), folder


def test_out_records_the_run_its_commit_and_machine(bench_run):
    args, _, doc, folder = bench_run
    assert doc["command"] == "python benchmarks/bench_control_loop.py " + " ".join(args)
    assert re.fullmatch(r"[0-9a-f]{40}(\+dirty)?", doc["commit"]), doc["commit"]
    machine = doc["machine"]
    for key in ("cpu_count", "cpu_model", "loadavg", "python", "torch", "onnxruntime", "numpy", "time_utc"):
        assert machine.get(key) not in (None, ""), key
    assert len(machine["loadavg"]) == 3
    assert doc["arm"] == args[1]
    assert (doc["steps"], doc["warmup"], doc["image_size"], doc["threads"]) == (5, 1, 32, 1)
    assert "resnet18" in doc["policy"] and "small stem" in doc["policy"] and "32 px" in doc["policy"]
    assert doc["wall_s"] > 0 and doc["cpu_s"] > 0
    assert sorted(p.name for p in folder.iterdir()) == ["loop.json"]  # no temporary left beside it


def test_out_holds_every_stage_with_finite_medians_below_their_p95(bench_run):
    _, _, doc, _ = bench_run
    assert set(doc["stages"]) == set(STAGES)
    for name, stage in doc["stages"].items():
        for fig in FIGURES:
            assert math.isfinite(stage[fig]) and stage[fig] >= 0, (name, fig, stage[fig])
        assert stage["wall_p95_ms"] >= stage["wall_median_ms"], name
        assert stage["cpu_p95_ms"] >= stage["cpu_median_ms"], name
    commands = doc["commands"]
    assert 0 <= commands["clipped"] + commands["refused"] <= 5


def test_printed_figures_are_the_ones_in_the_json(bench_run):
    _, lines, doc, _ = bench_run
    printed = {m["label"]: m for m in map(PRINTED.match, lines) if m}
    loop = printed["frame -> arm command"]
    assert loop["wall_median_ms"] == f"{doc['stages']['loop']['wall_median_ms']:.2f}"
    shown = [s for s in doc["stages"].values() if s["label"] in printed]
    assert len(shown) == (5 if doc["arm"] == "joint" else 4)  # --arm tcp shows no decode stage
    for stage in shown:
        for fig in FIGURES:
            assert printed[stage["label"]][fig] == f"{stage[fig]:.2f}", (stage["label"], fig)
    clipped = next(line for line in lines if "commands clipped" in line)
    assert clipped.split() == [
        "commands",
        "clipped",
        f"{doc['commands']['clipped']},",
        "refused",
        str(doc["commands"]["refused"]),
    ]


def test_out_in_a_missing_folder_is_one_line_naming_out_and_writes_nothing(tmp_path):
    out = tmp_path / "missing" / "loop.json"
    r = _run(["--arm", "tcp", *TINY, "--out", str(out)])
    assert r.returncode == 2
    errors = [line for line in r.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1 and "--out" in errors[0] and f"{out.parent} does not exist" in errors[0], r.stderr
    assert r.stderr.splitlines()[-1] == errors[0]
    assert r.stdout == ""  # refused before any work: nothing measured or printed
    assert list(tmp_path.iterdir()) == []


def test_out_naming_a_folder_is_one_line_naming_out_and_measures_nothing(tmp_path):
    r = _run(["--arm", "tcp", *TINY, "--out", str(tmp_path)])
    assert r.returncode == 2
    errors = [line for line in r.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1 and "--out" in errors[0] and "is a folder" in errors[0], r.stderr
    assert r.stdout == "" and list(tmp_path.iterdir()) == []


def test_the_machine_block_records_the_threads_the_loop_ran_with(bench_run):
    args, _, rec, _ = bench_run
    assert rec["machine"]["torch_threads"] == rec["threads"] == 1
