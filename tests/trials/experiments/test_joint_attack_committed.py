"""docs/workflow.md's figures for the 3D attack on the joint-space policy, recomputed from the
committed per-episode rows (``results/table2-joint/episodes.csv``, and the TCP policy's
``results/table2-seeds/episodes.csv``) with csv and math.comb alone (not the findings module)."""

from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
JOINT = ROOT / "results" / "table2-joint"
TCP = ROOT / "results" / "table2-seeds"
DOC = ROOT / "docs" / "workflow.md"
BLOCK = re.compile(r"<!-- joint-attack:start[^>]*-->\n(.*?)\n<!-- joint-attack:end -->", re.S)

pytestmark = pytest.mark.skipif(not (JOINT / "episodes.csv").is_file(), reason="results/table2-joint/ not committed")


def _rows(path: Path) -> list[dict]:
    with open(path / "episodes.csv", newline="") as f:
        return list(csv.DictReader(f))


def _mcnemar(b: int, c: int) -> float:
    m = b + c
    return 1.0 if m == 0 else min(1.0, 2 * sum(math.comb(m, i) for i in range(min(b, c) + 1)) / 2**m)


def _g(x: float) -> str:
    return f"{x:.2g}" if x >= 1e-3 else f"{x:.1e}"


def _per_seed():
    by: dict = {}
    for r in _rows(JOINT):
        by.setdefault(r["eval"], {}).setdefault(r["condition"], {})[r["seed"]] = int(r["targeted"])
    out = []
    for name in sorted(by, key=lambda n: (n != "table2_c2f", n)):  # seed 0 first, then -seed1, -seed2
        clean, attack = by[name]["clean"], by[name]["attack"]
        seeds = sorted(set(clean) & set(attack))
        assert seeds == sorted(clean) == sorted(attack)  # paired: the same configurations in both arms
        b = sum(attack[s] and not clean[s] for s in seeds)
        c = sum(clean[s] and not attack[s] for s in seeds)
        out.append((sum(attack[s] for s in seeds), sum(clean[s] for s in seeds), len(seeds), _mcnemar(b, c)))
    return out


def test_the_joint_attack_figures_in_the_doc_recompute_from_the_committed_rows():
    per = _per_seed()
    assert len(per) == 3 and all(n == 300 for *_, n, _ in per)
    rates = [100 * k / n for k, _, n, _ in per]
    clean = 100 * sum(c for _, c, _, _ in per) / sum(n for *_, n, _ in per)
    tcp = [r for r in _rows(TCP) if r["condition"] == "attack" and r["eval"].startswith("table2_c2f")]
    tcp_mean = 100 * sum(int(r["targeted"]) for r in tcp) / len(tcp)
    sub = [r for r in tcp if float(r["r_m"]) < 0.38 and 10 <= math.degrees(float(r["phi_rad"])) <= 45]
    k_sub = sum(int(r["targeted"]) for r in sub)
    want = (
        "T-ASR " + " / ".join(f"{x:.1f}%" for x in rates) + f" per attack seed (mean {sum(rates) / 3:.1f}%; clean "
        f"{clean:.1f}%), McNemar against the paired clean arm p = " + " / ".join(_g(p) for *_, p in per) + " (n = 300 "
        f"each). The same attack on the TCP quick policy reaches {tcp_mean:.1f}% over its seeds "
        "(results/table2-seeds/), "
        f"and {100 * k_sub / len(sub):.1f}% ({k_sub}/{len(sub)} episodes) on its configurations within the joint "
        "scene's range (r < 38 cm, phi 10-45 deg)."
    )
    assert BLOCK.search(DOC.read_text()).group(1) == want


def test_the_joint_scenes_configurations_are_within_the_range_the_doc_states_and_held_out():
    rows = _rows(JOINT)
    assert all(0.25 <= float(r["r_m"]) < 0.38 and 10 <= math.degrees(float(r["phi_rad"])) <= 45 for r in rows)
    summaries = json.loads((JOINT / "summary.json").read_text())
    assert summaries and all(set((s.get("overlap") or {}).values()) <= {0} for s in summaries.values())
    run = json.loads((JOINT / "run.json").read_text())
    assert any(
        a["exit_code"] == 0 and "--scene scenes/panda-joint.yaml" in a["command"] and "+dirty" not in a["commit"]
        for a in run["attempts"]
    )
