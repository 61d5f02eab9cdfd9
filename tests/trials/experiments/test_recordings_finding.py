"""Finding F7 (the attack on recorded frames against the closed-loop attack), declared before its data:
a ratio of T-ASR against the floor 0.7, over attack seeds by the two-level bootstrap of the ratio of the
arms' means, with the growth with recorded episodes and the shifted cell as extras."""

from __future__ import annotations

import math
import random
from pathlib import Path

import pytest

from tests.trials.experiments.test_findings_recompute import _bootstrap, _katz
from trials.experiments import findings as fd

RESULTS = Path(__file__).resolve().parents[3] / "results"


def _seeded(rates, n=300, seed=0):
    """``attack seed -> configuration -> row`` with the event drawn at each seed's rate."""
    rng = random.Random(seed)
    return {s: {c: {"targeted": rng.random() < p} for c in range(n)} for s, p in enumerate(rates)}


def test_f7_is_declared_as_a_ratio_against_the_closed_loop_attack_and_left_out_until_it_has_rows():
    (f,) = [f for f in fd.FINDINGS if f.id == "F7"]
    assert f.optional and f.recipe == f.seeds == "recordings" and f.floor == 0.7 and f.control == "clean"
    assert f.test == "ratio CI"
    (part,) = f.parts
    assert (part.a, part.b) == (fd.Arm("recordings_nominal_80"), fd.Arm("recordings_closed_loop"))
    assert [(p.a.eval, p.b.eval) for p in f.extras] == [
        ("recordings_nominal_20", "recordings_nominal_5"),
        ("recordings_nominal_80", "recordings_nominal_20"),
        ("recordings_shifted_80", "recordings_nominal_80"),
    ]
    if fd.load_rows(RESULTS, "recordings") is None:
        assert "F7" not in fd.findings(RESULTS)


@pytest.mark.parametrize(
    "rates_a, rates_b, want",
    [
        ((0.55, 0.6, 0.58), (0.6, 0.62, 0.6), "holds"),
        ((0.2, 0.18, 0.25), (0.6, 0.62, 0.6), "does not hold"),
        ((0.42, 0.48, 0.4), (0.6, 0.62, 0.6), "inconclusive"),
    ],
)
def test_the_ratio_over_seeds_is_the_plain_bootstrap_of_the_ratio_of_means(rates_a, rates_b, want):
    part = fd.Part(fd.Arm("a"), fd.Arm("b"), ("a", "b"), "ratio")
    a, b = _seeded(rates_a, seed=1), _seeded(rates_b, seed=2)
    o = fd.over_seeds(part, a, b, floor=0.7)
    xa = [[int(a[s][c]["targeted"]) for c in range(300)] for s in sorted(a)]
    xb = [[int(b[s][c]["targeted"]) for c in range(300)] for s in sorted(b)]
    ma, mb = sum(map(sum, xa)) / 900, sum(map(sum, xb)) / 900
    assert o.diff == pytest.approx(ma / mb, rel=1e-12)
    lo, hi = _bootstrap(xa, xb, ratio=True)
    assert o.lo == pytest.approx(lo, abs=0.02) and o.hi == pytest.approx(hi, abs=0.02)
    assert o.verdict == want
    # each seed's pair alone: the Katz interval of its two rates against the floor
    for s, v in zip(sorted(a), o.per_seed):
        _, klo, khi = _katz(sum(xa[s]), 300, sum(xb[s]), 300)
        assert v == ("holds" if klo > 0.7 else "does not hold" if khi < 0.7 else "inconclusive")


def test_a_reference_arm_that_never_hits_gives_no_ratio_and_no_verdict():
    part = fd.Part(fd.Arm("a"), fd.Arm("b"), ("a", "b"), "ratio")
    o = fd.over_seeds(part, _seeded((0.5, 0.5)), _seeded((0.0, 0.0)), floor=0.7)
    assert math.isnan(o.diff) and o.verdict == "inconclusive"
    assert fd.over_seeds(part, _seeded((0.5,)), _seeded((0.5,)), floor=0.7) is None  # one seed: no seed analysis
