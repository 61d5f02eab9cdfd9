"""The demo's report prints its 3D-vs-patch verdict once (trials.experiments.demo.verdicts_once)."""

import math

from trials.experiments.demo import verdicts_once
from trials.experiments.findings import paired_markdown


def _rows(targeted):
    """Episode rows by seed, spread over the phi and distance bins."""
    return {
        s: {"targeted": t, "phi_rad": math.radians(5 + 10 * (s % 8)), "r_m": 0.3 + 0.1 * (s % 5)}
        for s, t in enumerate(targeted)
    }


def test_the_overall_verdict_is_printed_once_and_both_bin_tables_stay():
    a = _rows([True] * 12 + [False] * 4)
    b = _rows([False] * 10 + [True] * 6)
    phi = paired_markdown("3D", "patch", a, b, "phi")
    r = paired_markdown("3D", "patch", a, b, "r")
    verdict = phi[0]
    assert verdict.startswith("**3D vs patch** (claim: ") and r[0] == verdict  # the same line, twice
    text = "\n".join(["## by phi", "", *phi, "", "## by r", "", *r])
    once = verdicts_once(text).split("\n")
    assert once.count(verdict) == 1 and once.index(verdict) < once.index("## by r")
    assert [x for x in once if x.startswith("|")] == [x for x in phi[1:] + r[1:] if x.startswith("|")]
    assert once[once.index("## by r") + 1 : once.index("## by r") + 3] == ["", r[2]]  # no double blank
    assert verdicts_once(verdicts_once(text)) == verdicts_once(text)
