"""docs/workflow.md's table of the joint-space quick policies is what their committed cards say.

The cards (``results/policies/policy-panda-joint*.json``) are read here with json alone and the
table rows written out again: DAgger iterations and gradient steps per iteration from the card's
training config, clean success with its Wilson interval recomputed from k and n, and the training
wall and CPU time.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
CARDS = sorted((ROOT / "results" / "policies").glob("policy-panda-joint*.json"))
DOC = ROOT / "docs" / "workflow.md"
BLOCK = re.compile(r"<!-- joint-policies:start[^>]*-->\n(.*?)\n<!-- joint-policies:end -->", re.S)


def _wilson(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return centre - half, centre + half


def _rows() -> list[tuple]:
    rows = []
    for path in CARDS:
        card = json.loads(path.read_text())
        t, c = card["training"], card["clean_success"]
        d = t["dagger"]
        assert card["contract"]["action"]["kind"] == "joint_delta" and t["scene"]["name"] == "panda-joint-reach"
        rows.append((d["iterations"], d["grad_steps_per_iter"], path.name, c["k"], c["n"], t))
    return sorted(rows, key=lambda r: (r[0], r[1]))


def test_the_joint_policy_table_is_the_committed_cards():
    rows = _rows()
    assert len(rows) >= 2
    want = [
        "| card | DAgger iterations | gradient steps per iteration | clean success | training wall / CPU |",
        "|---|---|---|---|---|",
    ]
    for it, gs, name, k, n, t in rows:
        lo, hi = _wilson(k, n)
        want.append(
            f"| [{name}](../results/policies/{name}) | {it} | {gs} | {100 * k / n:.1f}% ({k}/{n}; 95% CI "
            f"{100 * lo:.1f}-{100 * hi:.1f}%) | {t['train_time_s'] / 60:.1f} / {t['train_cpu_s'] / 60:.1f} min |"
        )
    block = BLOCK.search(DOC.read_text())
    assert block, "docs/workflow.md has no joint-policies block"
    assert block.group(1) == "\n".join(want)


def test_the_cards_intervals_are_the_wilson_intervals_of_their_counts():
    for path in CARDS:
        c = json.loads(path.read_text())["clean_success"]
        lo, hi = _wilson(c["k"], c["n"])
        assert abs(lo - c["lo"]) < 1e-9 and abs(hi - c["hi"]) < 1e-9 and c["n"] >= 200
