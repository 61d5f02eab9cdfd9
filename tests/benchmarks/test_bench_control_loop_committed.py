"""docs/safety.md's control-loop figures are the committed ``results/bench_control_loop/*.json``
records (read with json alone), each from a clean commit, 300 timed loops, under the 30 ms target."""

from __future__ import annotations

import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "results" / "bench_control_loop"
DOC = ROOT / "docs" / "safety.md"


def _rec(name: str) -> dict:
    return json.loads((RESULTS / f"{name}.json").read_text())


def _ms(name: str, stage: str = "loop", figure: str = "wall_median_ms") -> str:
    return f"{_rec(name)['stages'][stage][figure]:.2f} ms"


def test_the_quoted_figures_are_the_committed_records():
    text = " ".join(DOC.read_text().split())  # the paragraph as one line
    for quoted in (
        f"from frame to arm command **{_ms('joint')}** median wall ({_ms('joint', figure='cpu_median_ms')} CPU; p95 "
        f"{_ms('joint', figure='wall_p95_ms')})",
        f"of which FK and the joint checks with the command {_ms('joint', 'safety_arm_command')}",
        f"the TCP quick policy {_ms('tcp')}",
        f"an untrained ResNet-18 joint policy at 128 px {_ms('joint_resnet18_128')} "
        f"({_ms('joint_resnet18_128', 'policy')} of it the policy)",
    ):
        assert quoted in text, quoted


def test_each_record_is_a_clean_run_of_the_benchmark_under_the_target():
    recs = sorted(RESULTS.glob("*.json"))
    assert {p.stem for p in recs} >= {"joint", "tcp", "joint_resnet18_128"}
    for p in recs:
        r = json.loads(p.read_text())
        assert r["command"].startswith("python benchmarks/bench_control_loop.py ")
        assert re.fullmatch(r"[0-9a-f]{40}", r["commit"]), r["commit"]  # no +dirty
        assert r["steps"] == 300 and r["machine"]["cpu_count"] == 2
        loop = r["stages"]["loop"]
        assert 0 < loop["wall_median_ms"] <= loop["wall_p95_ms"] and loop["wall_median_ms"] <= 30.0
        assert ("--arm joint" in r["command"]) == (r["arm"] == "joint")
