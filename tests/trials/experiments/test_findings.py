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
    # p = 1 is not evidence: a ">=" claim needs its interval above the -5 pp margin, and 20 pairs all
    # discordant leave it far wider than that
    assert tie.p == 1.0 and fd.verdict(tie) == "inconclusive" and fd.verdict(tie, ">=") == "inconclusive"
    lo, hi = pr.diff_ci()
    assert lo < pr.diff == 0.6 < hi
    assert fd.verdict(fd.paired({}, {})) == "not measured"


def test_a_not_below_claim_is_non_inferiority_with_a_5pp_margin():
    def pair(b, c, n):
        return fd.Paired(n, 0, 0, b, c, 1.0)  # only n, b and c enter the interval

    assert fd.NI_MARGIN == 0.05
    assert fd.verdict(pair(4, 4, 500), ">=") == "holds"  # [-1.1, +1.1] pp: inside the margin
    assert fd.verdict(pair(10, 18, 500), ">=") == "holds"  # 1.6 pp below, interval [-3.7, +0.5]: within 5 pp
    assert fd.verdict(pair(5, 40, 300), ">=") == "does not hold"  # 11.7 pp below, interval wholly below -5 pp
    assert fd.verdict(pair(3, 9, 40), ">=") == "inconclusive"  # small n: the interval crosses both 0 and -5 pp
    # several bins at once: the same pair that holds alone is inconclusive at alpha / 8
    one = fd.paired(_arm([True] * 7 + [False] * 13), _arm([False] * 20))  # p = 2 / 2**7
    assert (
        one.p < 0.05 and fd.verdict(one) == "holds" and one.p > 0.05 / 8 and fd.verdict(one, ">", 8) == "inconclusive"
    )


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


#: Results with per-episode rows that no ``advobj experiment`` recipe writes, each with the test that
#: recomputes it from its own layout.
OWN_LAYOUT = {
    "formats": "tests/trials/experiments/test_formats_committed.py",
    "tradeoff": "tests/trials/experiments/test_tradeoff_evidence.py",
}
EPISODE_RESULTS = (
    sorted(p.name for p in RESULTS.iterdir() if (p / "episodes.csv").is_file()) if RESULTS.is_dir() else []
)


def test_every_result_with_episodes_is_a_recipes_or_has_its_own_recompute_test():
    from trials.experiments.recipes import RECIPES

    for name in EPISODE_RESULTS:
        if name.split("-")[0] not in RECIPES:
            assert name in OWN_LAYOUT, f"results/{name}: neither a recipe's results nor listed in OWN_LAYOUT"
            assert (ROOT / OWN_LAYOUT[name]).is_file(), OWN_LAYOUT[name]


@pytest.mark.parametrize("recipe", [r for r in EPISODE_RESULTS if r not in OWN_LAYOUT])
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


def test_registry_ids_are_unique_and_every_declared_arm_is_in_the_committed_results():
    ids = [f.id for f in fd.FINDINGS]
    assert len(ids) == len(set(ids)) and {"F1", "F2", "F3", "F4", "F5"} <= set(ids)
    declared = [(f.id, f.recipe, f.arms) for f in fd.FINDINGS] + [
        (n.title, n.recipe, {x for p in n.parts for x in (p.a, p.b)}) for n in fd.NOTES if isinstance(n, fd.FollowUp)
    ]
    optional = {f.id for f in fd.FINDINGS if f.optional}
    for name, recipe, arms in declared:
        rows = fd.load_rows(RESULTS, recipe)
        if name in optional and not rows:
            continue  # an optional finding is left out until its recipe has run
        assert rows, f"{name}: results/{recipe}/ has no rows"
        present = {(r["eval"], r["condition"]) for r in rows}
        assert not {(a.eval, a.condition) for a in arms} - present, name


def _direct_pair(rows, a, b, event, keep=lambda r: True):
    """A paired count written out independently of the module: (n, only a, only b)."""
    xa = {r["seed"]: r for r in rows if (r["eval"], r["condition"]) == a}
    xb = {r["seed"]: r for r in rows if (r["eval"], r["condition"]) == b}
    seeds = [s for s in set(xa) & set(xb) if keep(xa[s])]
    return (
        len(seeds),
        sum(bool(xa[s][event]) and not xb[s][event] for s in seeds),
        sum(bool(xb[s][event]) and not xa[s][event] for s in seeds),
    )


def test_a_new_paired_finding_declared_as_data_is_computed_and_rendered_with_its_subgroup_and_bins():
    made_up = fd.Finding(
        "X1",
        "coarse-only > fine-only in T-ASR from r = 50 cm on",
        "(not in the paper)",
        "table2",
        (fd.Part(fd.Arm("table2_coarse"), fd.Arm("table2_fine"), ("coarse", "fine")),),
        subgroup=fd.Subgroup("r", 50.0),
        complement=True,
        bins="r",
    )
    f = fd.findings(RESULTS, registry=(made_up,))
    e = f["X1"]
    pr = e.parts[0].pair
    rows = fd.load_rows(RESULTS, "table2")
    arms = ("table2_coarse", "attack"), ("table2_fine", "attack")
    far = _direct_pair(rows, *arms, "targeted", lambda r: r["r_m"] >= 0.5)
    assert (pr.n, pr.b, pr.c) == far and 0 < pr.n < 500
    assert e.verdict == fd.verdict(pr) != "not measured"
    assert e.complement.n + pr.n == e.binned[0].overall.n == 500
    row = fd.render(f).splitlines()[2]
    assert row.startswith("| **X1** coarse-only > fine-only in T-ASR from r = 50 cm on | (not in the paper) | coarse ")
    assert row.endswith(f"| **{e.verdict}** (one texture per arm; no seed runs) | [results/table2/](results/table2/) |")
    details = fd.render_details(f)
    assert "## X1 by initial distance r (cm)" in details and "\nBelow r = 50 cm: coarse " in details
    assert "| r bin | n | coarse T-ASR % | fine T-ASR % | only coarse / only fine | p |" in details
    assert "## X1 parts" not in details  # one part: no per-part section


def test_a_new_ratio_finding_declared_as_data_counts_its_event_and_lists_its_parts():
    made_up = fd.Finding(
        "X2",
        "the other targets keep half of ResNet-34's success under attack",
        "(not in the paper)",
        "transfer",
        tuple(
            fd.Part(fd.Arm(f"transfer_{t}"), fd.Arm("transfer_resnet34"), (t, "resnet34"), "ratio")
            for t in ("vgg16", "inception_v3")
        ),
        event="success",
        control="clean",
        parts_title="per target",
    )
    f = fd.findings(RESULTS, registry=(made_up,))
    e = f["X2"]
    rows = fd.load_rows(RESULTS, "transfer")
    for o, t in zip(e.parts, ("vgg16", "inception_v3")):
        tgt = [r for r in rows if r["eval"] == f"transfer_{t}" and r["condition"] == "attack"]
        ref = [r for r in rows if r["eval"] == "transfer_resnet34" and r["condition"] == "attack"]
        assert (o.ratio.k, o.ratio.n) == (sum(r["success"] for r in tgt), len(tgt))
        assert (o.ratio.k_ref, o.ratio.n_ref) == (sum(r["success"] for r in ref), len(ref))
        assert o.ratio.lo < o.ratio.ratio < o.ratio.hi
        assert o.verdict == ("holds" if o.ratio.lo > 0.5 else "does not hold" if o.ratio.hi < 0.5 else "inconclusive")
        clean = _direct_pair(rows, (f"transfer_{t}", "attack"), (f"transfer_{t}", "clean"), "success")
        assert (o.ratio.vs_control.n, o.ratio.vs_control.b, o.ratio.vs_control.c) == clean
    assert "| - (unpaired; ratio CI) |" in fd.render(f)
    details = fd.render_details(f)
    assert "## X2 per target" in details and "- vgg16: success " in details and "vs its clean arm p = " in details


def test_a_declaration_that_mixes_claim_kinds_or_binds_a_subgroup_to_several_parts_is_refused():
    a, b = fd.Arm("table2_c2f"), fd.Arm("table2_ns")
    paired, ratio = fd.Part(a, b, ("A", "B")), fd.Part(a, b, ("A", "B"), "ratio")
    with pytest.raises(ValueError, match="all paired or all ratio"):
        fd.Finding("X", "c", "p", "table2", (paired, ratio))
    with pytest.raises(ValueError, match="one part"):
        fd.Finding("X", "c", "p", "table2", (paired, paired), subgroup=fd.Subgroup("phi", 50.0))
    with pytest.raises(ValueError, match="claim"):
        fd.Part(a, b, ("A", "B"), "<")
