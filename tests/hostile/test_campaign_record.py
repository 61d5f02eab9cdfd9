"""The hostile campaign's figures in docs/hostile-inputs.md, recomputed from the committed record.

``results/hostile/cases.csv`` holds one row per case as the campaign ran it
(``benchmarks/hostile_campaign.py``). This test counts from those rows with the csv module alone,
not from the campaign's own ``figures.json`` or its code, and checks every number the docs quote.
"""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
RECORD = ROOT / "results" / "hostile"
DOC = ROOT / "docs" / "hostile-inputs.md"

pytestmark = pytest.mark.skipif(not (RECORD / "cases.csv").is_file(), reason="no committed campaign record")


def _rows() -> list[dict]:
    with open(RECORD / "cases.csv", newline="") as f:
        return list(csv.DictReader(f))


def _recomputed() -> dict:
    rows = _rows()
    problems = [r["problems"] for r in rows]
    return {
        "cases": len(rows),
        "commands": len({r["command"] for r in rows}),
        "kinds": len({r["kind"] for r in rows}),
        "exit_2_one_line": sum(r["exit"] == "2" and r["stderr_lines"] == "1" and not r["problems"] for r in rows),
        "tracebacks": sum("Traceback" in p or "traceback" in p for p in problems),
        "hangs": sum("still running" in p for p in problems),
        "touched": sum(int(r["touched_outside"]) for r in rows),
        "peak_rss_mb": max(float(r["peak_rss_mb"]) for r in rows),
        "slowest_s": max(float(r["seconds"]) for r in rows),
    }


def _quoted() -> dict:
    """The numbers of the doc's figures line (the one starting 'Measured:')."""
    line = next(ln for ln in DOC.read_text().splitlines() if ln.startswith("Measured:"))
    pat = {
        "cases": r"([\d,]+) cases",
        "commands": r"over ([\d,]+) commands",
        "kinds": r"([\d,]+) kinds of input",
        "exit_2_one_line": r"([\d,]+) ended in one line with exit 2",
        "tracebacks": r"([\d,]+) tracebacks",
        "hangs": r"([\d,]+) hangs past",
        "touched": r"([\d,]+) files touched outside",
        "peak_rss_mb": r"peak RSS ([\d,.]+) MB",
        "slowest_s": r"slowest case ([\d,.]+) s",
        "wall_s": r"([\d,.]+) s wall",
        "cpu_s": r"([\d,.]+) s CPU",
        "commit": r"commit `([0-9a-f]{12})`",
    }
    out = {}
    for k, p in pat.items():
        m = re.search(p, line)
        assert m, f"docs/hostile-inputs.md: the Measured line lacks {k!r}"
        out[k] = m.group(1) if k == "commit" else float(m.group(1).replace(",", ""))
    return out


def test_the_docs_figures_equal_the_counts_recomputed_from_the_case_rows():
    got, doc = _recomputed(), _quoted()
    for k in ("cases", "commands", "kinds", "exit_2_one_line", "tracebacks", "hangs", "touched"):
        assert doc[k] == got[k], k
    assert doc["peak_rss_mb"] == pytest.approx(got["peak_rss_mb"], abs=0.5)
    assert doc["slowest_s"] == pytest.approx(got["slowest_s"], abs=0.05)


def test_the_record_is_clean_and_its_run_info_backs_the_time_and_commit():
    got = _recomputed()
    assert got["tracebacks"] == 0 and got["hangs"] == 0 and got["touched"] == 0
    assert got["exit_2_one_line"] == got["cases"]
    figures = json.loads((RECORD / "figures.json").read_text())
    assert got["peak_rss_mb"] < figures["rss_cap_mb"]
    run = json.loads((RECORD / "run.json").read_text())
    assert "+dirty" not in run["git_commit"] and run["config"]["pytest_exit"] == 0
    doc = _quoted()
    assert run["git_commit"].startswith(doc["commit"])
    assert doc["wall_s"] == pytest.approx(run["config"]["wall_s"], abs=0.5)
    assert doc["cpu_s"] == pytest.approx(run["config"]["cpu_s"], abs=0.5)
