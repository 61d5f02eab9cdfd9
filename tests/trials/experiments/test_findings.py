"""The findings table: recomputed from the committed per-episode data, verdict rules, provenance."""

import json
from pathlib import Path

import pytest

from trials.experiments import findings as fd

ROOT = Path(__file__).resolve().parents[3]
RESULTS = ROOT / "results"


def _arm(events: list[bool], phis=None) -> dict:
    return {
        s: {"seed": s, "targeted": e, "success": not e, "phi_rad": (phis or [0.5] * len(events))[s], "r_m": 0.5}
        for s, e in enumerate(events)
    }


def test_paired_counts_discordant_pairs_and_the_verdict_follows_alpha():
    a = _arm([True] * 12 + [False] * 8)
    b = _arm([False] * 12 + [False] * 8)
    pr = fd.paired(a, b)
    assert (pr.n, pr.b, pr.c, pr.k_a, pr.k_b) == (20, 12, 0, 12, 0) and pr.p < 0.001
    assert fd.verdict(pr) == "holds" and fd.verdict(fd.paired(b, a)) == "does not hold"
    tie = fd.paired(_arm([True, False] * 10), _arm([False, True] * 10))
    assert tie.p == 1.0 and fd.verdict(tie) == "inconclusive" and fd.verdict(tie, ">=") == "holds"
    lo, hi = pr.diff_ci()
    assert lo < pr.diff == 0.6 < hi
    assert fd.verdict(fd.paired({}, {})) == "not measured"


def test_bins_without_episodes_are_marked_not_zero():
    a = _arm([True, False, True], phis=[0.1, 0.1, 0.1])  # all in the 0-10 deg bin
    lines = fd.paired_markdown("A", "B", a, a, "phi")
    assert any("| 10-20 | 0 | (no episodes)" in l for l in lines) and any(l.startswith("| 0-10 | 3 |") for l in lines)


def test_transfer_ratio_interval_brackets_the_ratio():
    r, lo, hi = fd._ratio_ci(30, 100, 60, 100)
    assert r == pytest.approx(0.5) and 0 < lo < r < hi
    r0, lo0, hi0 = fd._ratio_ci(0, 100, 60, 100)  # an empty cell is handled, not a division by zero
    assert 0 <= lo0 <= r0 <= hi0 < 0.2


def test_readme_docs_and_findings_md_match_the_committed_data():
    stale = [
        str(p.relative_to(ROOT)) for p, text in fd.expected(RESULTS).items() if not p.is_file() or p.read_text() != text
    ]
    assert not stale, (
        f"regenerate with: python -m trials.experiments.findings ({', '.join(stale)} differ from what results/ gives)"
    )


@pytest.mark.parametrize(
    "recipe", sorted(p.name for p in RESULTS.iterdir() if (p / "episodes.csv").is_file()) if RESULTS.is_dir() else []
)
def test_every_committed_result_has_provenance_held_out_rows_and_at_least_300_pairs_per_arm(recipe):
    d = RESULTS / recipe
    run = json.loads((d / "run.json").read_text())
    ok = [a for a in run["attempts"] if a["exit_code"] == 0]
    assert ok, "no finished attempt"
    for a in run["attempts"]:
        assert (
            a["command"].startswith("advobj experiment " + recipe.split("-")[0])
            and a["commit"]
            and a["machine"]["cpus"]
        )
        assert a["wall_s"] > 0 and a["cpu_s"] > 0
    summaries = json.loads((d / "summary.json").read_text())
    rows = fd.load_rows(RESULTS, recipe)
    for name, s in summaries.items():
        assert set((s.get("overlap") or {}).values()) <= {0}, f"{name}: overlap {s['overlap']}"
        for cond, cs in s["conditions"].items():
            n = sum(1 for r in rows if r["eval"] == name and r["condition"] == cond)
            assert n == cs["n"] >= 300, (name, cond, n)


def test_the_readme_policy_figure_is_the_committed_card():
    import re

    card = json.loads((RESULTS / "policies" / "policy-quick.json").read_text())
    c, t = card["clean_success"], card["training"]
    want = (
        f"**{100 * c['rate']:.1f}% clean success ({c['k']}/{c['n']}, 95% CI "
        f"{100 * c['lo']:.1f}-{100 * c['hi']:.1f}%) after "
        f"{t['train_time_s'] / 60:.1f} min of training ({t['train_cpu_s'] / 60:.1f} min CPU)**"
    )
    block = re.search(
        r"<!-- policy:start[^>]*-->\n(.*?)\n<!-- policy:end -->", (ROOT / "README.md").read_text(), re.S
    ).group(1)
    assert block == want
