"""The README's findings table, recomputed from the committed CSVs with code independent of
``trials.experiments.findings``: the csv module, exact binomial sums and a pure-Python bootstrap.
What the module prints must agree with what this file computes on its own."""

import csv
import json
import math
import random
import re
from pathlib import Path

import pytest

from trials.experiments import findings as fd

ROOT = Path(__file__).resolve().parents[3]
RESULTS = ROOT / "results"

# Each finding's arms, written out here (not read from the module's registry):
# id -> (single-texture recipe, seeds recipe or None, [(eval a, cond a, eval b, cond b, claim)], phi at least)
ARMS = {
    "F1": ("table1", "table1-seeds", [("table1", "attack", "table1", "patch", ">")], None),
    "F1-oblique": ("table1", "table1-seeds", [("table1", "attack", "table1", "patch", ">")], 50.0),
    "F2": (
        "table2",
        "table2-seeds",
        [("table2_c2f", "attack", "table2_ns", "attack", ">="), ("table2_ns", "attack", "table2_f2c", "attack", ">")],
        None,
    ),
    "F3": ("table2-f3", "table2-f3", [("table2_c2f", "attack", "table2_c2f_untargeted", "attack", ">")], None),
    "F3-two-objects": ("table2", None, [("table2_c2f", "attack", "table2_c2f_untargeted", "attack", ">")], None),
    "F4": ("table2", "table2-f4", [("table2_c2f", "attack", "table2_c2f_no_saliency", "attack", ">")], None),
    "F6": (
        "cameras",
        "cameras",
        [
            ("cameras", "attack_wrist_only", "cameras", "attack", ">="),
            ("cameras", "attack_wrist_only", "cameras", "attack_front_only", ">"),
        ],
        None,
    ),
    # a ratio part: "ratio F" claims T-ASR(a) / T-ASR(b) above the floor F
    "F7": (
        "recordings",
        "recordings",
        [("recordings_nominal_80", "attack", "recordings_closed_loop", "attack", "ratio 0.7")],
        None,
    ),
}
# The follow-up over attack seeds at 40 iterations (results/findings.md), in its printed order.
FOLLOW_UP_40 = (
    "table2-40-seeds",
    [
        ("table2_c2f", "table2_ns", ">="),
        ("table2_ns", "table2_f2c", ">"),
        ("table2_c2f", "table2_f2c", ">"),
        ("table2_c2f", "table2_c2f_no_saliency", ">"),
        ("table2_c2f", "table2_c2f_untargeted", ">"),
    ],
)
NUM = r"[+-]?\d+(?:\.\d+)?"
PAIR = re.compile(
    rf"(?P<ra>{NUM})% vs [\w\- ]+? (?P<rb>{NUM})% \(difference (?P<d>{NUM}) pp, 95% CI \[(?P<lo>{NUM}), "
    rf"(?P<hi>{NUM})\]; discordant (?P<b>\d+)/(?P<c>\d+); n = (?P<n>\d+)\)"
)
RATIO = re.compile(
    rf"(?P<rb>{NUM})% \(n = (?P<nb>\d+)\); [^;]*? (?P<ra>{NUM})% \(n = (?P<na>\d+)\) = (?P<r>{NUM}) x [^\[;]+ "
    rf"\[(?P<lo>{NUM}), (?P<hi>{NUM})\]"
)
SEEDS_RATIO = re.compile(
    rf"(?P<ma>{NUM})% \(sd (?P<sa>{NUM}|n/a)\) vs [\w\- ()]+? (?P<mb>{NUM})% \(sd (?P<sb>{NUM}|n/a)\), ratio "
    rf"(?P<r>{NUM}), 95% CI \[(?P<lo>{NUM}), (?P<hi>{NUM})\] \((?P<k>\d+) seeds x (?P<n>\d+) configurations\)"
)
SEEDS = re.compile(
    rf"(?P<ma>{NUM})% \(sd (?P<sa>{NUM}|n/a)\) vs [\w\- ]+? (?P<mb>{NUM})% \(sd (?P<sb>{NUM}|n/a)\), difference "
    rf"(?P<d>{NUM}) pp, 95% CI \[(?P<lo>{NUM}), (?P<hi>{NUM})\] \((?P<k>\d+) seeds x (?P<n>\d+) configurations\)"
)


def _rows(recipe):
    with open(RESULTS / recipe / "episodes.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def _table_rows():
    text = (ROOT / "README.md").read_text()
    block = text.split("<!-- findings:start", 1)[1].split("<!-- findings:end -->", 1)[0]
    out = {}
    for line in block.splitlines():
        m = re.match(r"\| \*\*([\w-]+)\*\* ", line)
        if m:
            out[m.group(1)] = line.split(" | ")
    return out


def _arm(rows, ev, cond):
    return {int(r["seed"]): r for r in rows if r["eval"] == ev and r["condition"] == cond}


def _phi_deg(r):
    return math.degrees(float(r["phi_rad"]))


def _mcnemar_p(b, c):
    n = b + c
    if n == 0:
        return 1.0
    k = min(b, c)
    return min(1.0, 2 * sum(math.comb(n, i) for i in range(k + 1)) / 2**n)


def _single(rows, ev_a, c_a, ev_b, c_b, phi_min):
    a, b = _arm(rows, ev_a, c_a), _arm(rows, ev_b, c_b)
    keys = [s for s in a if s in b and (phi_min is None or _phi_deg(a[s]) >= phi_min)]
    ta = [a[s]["targeted"] in ("1", "True", "true") for s in keys]
    tb = [b[s]["targeted"] in ("1", "True", "true") for s in keys]
    n = len(keys)
    only_a = sum(x and not y for x, y in zip(ta, tb))
    only_b = sum(y and not x for x, y in zip(ta, tb))
    d = (only_a - only_b) / n
    half = 1.959964 * math.sqrt(max(0.0, (only_a + only_b) / n - d * d) / n)
    return dict(n=n, b=only_a, c=only_b, ra=sum(ta) / n, rb=sum(tb) / n, d=d, lo=d - half, hi=d + half)


def _by_seed(rows, ev, cond):
    out = {}
    for r in rows:
        if r["condition"] != cond:
            continue
        m = re.fullmatch(re.escape(ev) + r"(?:-seed(\d+))?", r["eval"])
        if m:
            out.setdefault(int(m.group(1) or 0), {})[int(r["seed"])] = r["targeted"] in ("1", "True", "true")
    return out


def _bootstrap(xa, xb, resamples=3000, seed=12345, ratio=False):
    """Two-level bootstrap written plainly: configurations, then each arm's seeds, with replacement;
    of the difference of the arms' mean rates, or with ``ratio`` of their ratio."""
    rng = random.Random(seed)
    k, n = len(xa), len(xa[0])
    stats = []
    for _ in range(resamples):
        cs = [rng.randrange(n) for _ in range(n)]
        sa = [rng.randrange(k) for _ in range(k)]
        sb = [rng.randrange(k) for _ in range(k)]
        ma = sum(sum(xa[s][c] for c in cs) / n for s in sa) / k
        mb = sum(sum(xb[s][c] for c in cs) / n for s in sb) / k
        stats.append((ma / mb if mb > 0 else math.nan) if ratio else ma - mb)
    stats.sort()
    return stats[int(0.025 * resamples)], stats[int(0.975 * resamples) - 1]


def _floor(claim):
    """The floor of a ``"ratio F"`` claim (None for a paired one)."""
    return float(claim.split()[1]) if claim.startswith("ratio") else None


def _katz(ka, na, kb, nb, z=1.959964):
    """rate(a) / rate(b) with the Katz log interval, 0.5 added to every cell when one is empty or full."""
    if ka in (0, na) or kb in (0, nb):
        ka, na, kb, nb = ka + 0.5, na + 1, kb + 0.5, nb + 1
    r = (ka / na) / (kb / nb)
    se = math.sqrt(1 / ka - 1 / na + 1 / kb - 1 / nb)
    return r, r * math.exp(-z * se), r * math.exp(z * se)


def _ratio_single(rows, ev_a, c_a, ev_b, c_b):
    """Each arm's events and episodes (unpaired: every episode of each), and their Katz ratio."""
    a, b = _arm(rows, ev_a, c_a), _arm(rows, ev_b, c_b)
    ka = sum(r["targeted"] in ("1", "True", "true") for r in a.values())
    kb = sum(r["targeted"] in ("1", "True", "true") for r in b.values())
    return (ka, len(a), kb, len(b), *_katz(ka, len(a), kb, len(b)))


def _committed(recipe):
    return recipe is not None and (RESULTS / recipe / "episodes.csv").is_file()


TABLE = _table_rows()


def _has_seed_runs(recipe, parts):
    rows = _rows(recipe)
    return all(_by_seed(rows, ea, ca) and _by_seed(rows, eb, cb) for ea, ca, eb, cb, _ in parts)


@pytest.mark.parametrize("fid", [f for f in ARMS if f in TABLE])
def test_the_single_texture_figures_recompute_from_the_csvs(fid):
    recipe, _, parts, phi_min = ARMS[fid]
    rows = _rows(recipe)
    if _floor(parts[0][4]) is not None:  # ratio parts: unpaired, each arm's episodes and the Katz interval
        printed = list(RATIO.finditer(TABLE[fid][2]))
        assert len(printed) == len(parts), TABLE[fid][2]
        for m, (ea, ca, eb, cb, _) in zip(printed, parts):
            ka, na, kb, nb, r, lo, hi = _ratio_single(rows, ea, ca, eb, cb)
            assert (int(m["na"]), int(m["nb"])) == (na, nb)
            assert float(m["ra"]) == pytest.approx(100 * ka / na, abs=0.051)
            assert float(m["rb"]) == pytest.approx(100 * kb / nb, abs=0.051)
            for key, want in (("r", r), ("lo", lo), ("hi", hi)):
                assert float(m[key]) == pytest.approx(want, abs=0.0051)
        return
    printed = list(PAIR.finditer(TABLE[fid][2]))
    assert len(printed) == len(parts), TABLE[fid][2]
    for m, (ea, ca, eb, cb, claim) in zip(printed, parts):
        got = _single(rows, ea, ca, eb, cb, phi_min)
        assert (int(m["n"]), int(m["b"]), int(m["c"])) == (got["n"], got["b"], got["c"])
        assert float(m["ra"]) == pytest.approx(100 * got["ra"], abs=0.051)
        assert float(m["rb"]) == pytest.approx(100 * got["rb"], abs=0.051)
        assert float(m["d"]) == pytest.approx(100 * got["d"], abs=0.051)
        assert float(m["lo"]) == pytest.approx(100 * got["lo"], abs=0.051)
        assert float(m["hi"]) == pytest.approx(100 * got["hi"], abs=0.051)


@pytest.mark.parametrize("fid", [f for f in ARMS if f in TABLE])
def test_the_verdict_follows_the_stated_rules(fid):
    recipe, seeds_recipe, parts, phi_min = ARMS[fid]
    cell = TABLE[fid][4]
    if _committed(seeds_recipe) and _has_seed_runs(seeds_recipe, parts):
        assert "over 3 attack seeds" in cell or re.search(r"over \d+ attack seeds", cell), cell
        return  # the over-seeds verdict is checked in the next test
    rows = _rows(recipe)
    verdicts = []
    for ea, ca, eb, cb, claim in parts:
        floor = _floor(claim)
        if floor is not None:  # holds when the ratio's interval lies above the floor
            *_, lo, hi = _ratio_single(rows, ea, ca, eb, cb)
            verdicts.append("holds" if lo > floor else "does not hold" if hi < floor else "inconclusive")
            continue
        g = _single(rows, ea, ca, eb, cb, phi_min)
        if claim == ">":
            sig = _mcnemar_p(g["b"], g["c"]) < 0.05
            verdicts.append("holds" if sig and g["d"] > 0 else "does not hold" if sig else "inconclusive")
        else:  # non-inferiority with a 5 pp margin on the 95% interval
            verdicts.append("holds" if g["lo"] > -0.05 else "does not hold" if g["hi"] < 0 else "inconclusive")
    want = (
        "does not hold"
        if "does not hold" in verdicts
        else "holds"
        if all(v == "holds" for v in verdicts)
        else "inconclusive"
    )
    assert cell.startswith(f"**{want}**"), (cell, verdicts)


@pytest.mark.parametrize(
    "fid", [f for f in ARMS if f in TABLE and _committed(ARMS[f][1]) and _has_seed_runs(ARMS[f][1], ARMS[f][2])]
)
def test_the_over_seeds_figures_recompute_with_an_independent_bootstrap(fid):
    _, seeds_recipe, parts, phi_min = ARMS[fid]
    rows = _rows(seeds_recipe)
    phi = {int(r["seed"]): _phi_deg(r) for r in rows}
    ratio = _floor(parts[0][4]) is not None
    printed = list((SEEDS_RATIO if ratio else SEEDS).finditer(TABLE[fid][2]))
    assert len(printed) == len(parts), TABLE[fid][2]
    verdicts = []
    for m, (ea, ca, eb, cb, claim) in zip(printed, parts):
        a, b = _by_seed(rows, ea, ca), _by_seed(rows, eb, cb)
        assert sorted(a) == sorted(b) and len(a) >= 3, "arms need the same attack seeds, at least 3"
        configs = sorted(set.intersection(*(set(x) for x in [*a.values(), *b.values()])))
        configs = [c for c in configs if phi_min is None or phi[c] >= phi_min]
        xa = [[int(a[s][c]) for c in configs] for s in sorted(a)]
        xb = [[int(b[s][c]) for c in configs] for s in sorted(b)]
        k, n = len(xa), len(configs)
        ra, rb = [sum(x) / n for x in xa], [sum(x) / n for x in xb]
        ma, mb = sum(ra) / k, sum(rb) / k
        sd = lambda v, m: math.sqrt(sum((x - m) ** 2 for x in v) / (len(v) - 1))  # noqa: E731
        assert (int(m["k"]), int(m["n"])) == (k, n)
        assert float(m["ma"]) == pytest.approx(100 * ma, abs=0.051)
        assert float(m["mb"]) == pytest.approx(100 * mb, abs=0.051)
        assert float(m["sa"]) == pytest.approx(100 * sd(ra, ma), abs=0.051)
        assert float(m["sb"]) == pytest.approx(100 * sd(rb, mb), abs=0.051)
        if ratio:  # the ratio of the means over seeds, and its interval against the floor
            floor = _floor(claim)
            assert float(m["r"]) == pytest.approx(ma / mb, abs=0.0051)
            lo, hi = _bootstrap(xa, xb, ratio=True)
            assert float(m["lo"]) == pytest.approx(lo, abs=0.03) and float(m["hi"]) == pytest.approx(hi, abs=0.03)
            plo, phi_ = float(m["lo"]), float(m["hi"])
            verdicts.append("holds" if plo > floor else "does not hold" if phi_ < floor else "inconclusive")
            continue
        assert float(m["d"]) == pytest.approx(100 * (ma - mb), abs=0.051)
        lo, hi = _bootstrap(xa, xb)
        # two bootstraps of a few thousand draws agree to Monte Carlo error, not digit for digit
        assert float(m["lo"]) == pytest.approx(100 * lo, abs=1.5) and float(m["hi"]) == pytest.approx(100 * hi, abs=1.5)
        plo, phi_ = float(m["lo"]) / 100, float(m["hi"]) / 100
        if claim == ">":
            verdicts.append("holds" if plo > 0 else "does not hold" if phi_ < 0 else "inconclusive")
        else:
            verdicts.append("holds" if plo > -0.05 else "does not hold" if phi_ < 0 else "inconclusive")
    want = (
        "does not hold"
        if "does not hold" in verdicts
        else "holds"
        if all(v == "holds" for v in verdicts)
        else "inconclusive"
    )
    assert TABLE[fid][4].startswith(f"**{want}** over {k} attack seeds"), TABLE[fid][4]


def test_every_committed_multi_seed_result_feeds_its_findings():
    for fid, (_, seeds_recipe, parts, _) in ARMS.items():
        if fid in TABLE and _committed(seeds_recipe) and _has_seed_runs(seeds_recipe, parts):
            assert "over attack seeds" in TABLE[fid][2], f"{fid}: results/{seeds_recipe}/ is committed but unused"


def _seeded(a, b, rates_a, rates_b, n=200, seed=0):
    rng = random.Random(seed)
    mk = lambda rates: {  # noqa: E731
        s: {c: {"targeted": rng.random() < p, "phi_rad": 0.5, "r_m": 0.5} for c in range(n)}
        for s, p in zip((0, 1, 2), rates)
    }
    return mk(rates_a), mk(rates_b)


def test_over_seeds_needs_equal_seed_sets_and_widens_with_the_seed_spread():
    part = fd.Part(fd.Arm("x"), fd.Arm("y"), ("x", "y"))
    a, b = _seeded("x", "y", (0.6, 0.6, 0.6), (0.4, 0.4, 0.4))
    with pytest.raises(ValueError, match="different attack seeds"):
        fd.over_seeds(part, a, {0: b[0], 1: b[1]})
    steady = fd.over_seeds(part, a, b)
    assert steady.verdict == "holds" and steady.lo > 0
    # one lucky seed: seed 0 alone would say "holds", the three together do not
    a2, b2 = _seeded("x", "y", (0.75, 0.35, 0.45), (0.5, 0.5, 0.5))
    spread = fd.over_seeds(part, a2, b2)
    one = fd.paired(a2[0], b2[0])
    assert fd.verdict(one) == "holds" and spread.verdict != "holds"
    assert spread.hi - spread.lo > steady.hi - steady.lo
    assert fd.over_seeds(part, {0: a[0]}, {0: b[0]}) is None  # one seed is not a seed analysis
    assert fd.over_seeds(part, a, {}) is None  # an arm the multi-seed run did not include


def test_over_seeds_interval_matches_the_plain_bootstrap():
    part = fd.Part(fd.Arm("x"), fd.Arm("y"), ("x", "y"), ">=")
    a, b = _seeded("x", "y", (0.55, 0.5, 0.6), (0.5, 0.52, 0.48), n=150, seed=3)
    o = fd.over_seeds(part, a, b)
    xa = [[int(a[s][c]["targeted"]) for c in range(150)] for s in (0, 1, 2)]
    xb = [[int(b[s][c]["targeted"]) for c in range(150)] for s in (0, 1, 2)]
    lo, hi = _bootstrap(xa, xb)
    assert o.lo == pytest.approx(lo, abs=0.015) and o.hi == pytest.approx(hi, abs=0.015)


@pytest.mark.parametrize("fid", [f for f in ARMS if f in TABLE])
def test_a_result_from_an_uncommitted_checkout_is_marked(fid):
    for recipe in {ARMS[fid][0], ARMS[fid][1]} - {None}:
        if not _committed(recipe) or f"results/{recipe}/" not in TABLE[fid][5]:
            continue
        attempts = json.loads((RESULTS / recipe / "run.json").read_text())["attempts"]
        dirty = any(a["commit"].endswith("+dirty") for a in attempts)
        assert (f"[results/{recipe}/](results/{recipe}/) (dirty)" in TABLE[fid][5]) == dirty, (recipe, TABLE[fid][5])


@pytest.mark.skipif(not _committed(FOLLOW_UP_40[0]), reason="results/table2-40-seeds/ is not committed")
def test_the_40_iteration_follow_up_over_seeds_recomputes_from_its_csv():
    recipe, parts = FOLLOW_UP_40
    text = (RESULTS / "findings.md").read_text()
    section = text.split("at a 40-iteration budget over attack seeds", 1)[1].split("\n## ", 1)[0]
    printed = [line for line in section.splitlines() if line.startswith("- ")]
    assert len(printed) == len(parts), section
    rows = _rows(recipe)
    for line, (ea, eb, claim) in zip(printed, parts):
        m = SEEDS.search(line)
        assert m, line
        a, b = _by_seed(rows, ea, "attack"), _by_seed(rows, eb, "attack")
        assert sorted(a) == sorted(b) and len(a) >= 3
        configs = sorted(set.intersection(*(set(x) for x in [*a.values(), *b.values()])))
        xa = [[int(a[s][c]) for c in configs] for s in sorted(a)]
        xb = [[int(b[s][c]) for c in configs] for s in sorted(b)]
        k, n = len(xa), len(configs)
        ma = sum(sum(x) / n for x in xa) / k
        mb = sum(sum(x) / n for x in xb) / k
        assert (int(m["k"]), int(m["n"])) == (k, n)
        assert float(m["ma"]) == pytest.approx(100 * ma, abs=0.051)
        assert float(m["mb"]) == pytest.approx(100 * mb, abs=0.051)
        assert float(m["d"]) == pytest.approx(100 * (ma - mb), abs=0.051)
        lo, hi = _bootstrap(xa, xb)
        assert float(m["lo"]) == pytest.approx(100 * lo, abs=1.5) and float(m["hi"]) == pytest.approx(100 * hi, abs=1.5)
        plo, phi_ = float(m["lo"]) / 100, float(m["hi"]) / 100
        margin = 0.0 if claim == ">" else -0.05
        want = "holds" if plo > margin else "does not hold" if phi_ < 0 else "inconclusive"
        assert f"**{want}**" in line, line


@pytest.mark.parametrize(
    "recipe, title, arms",
    [
        (
            "table2-seeds",
            "## F2 over attack seeds: where the textures agree",
            ("table2_c2f", "table2_f2c", "table2_ns"),
        ),
        ("table2-f4", "## F4 over attack seeds: where the textures agree", ("table2_c2f", "table2_c2f_no_saliency")),
    ],
)
def test_where_the_textures_agree_recomputes_from_the_csv(recipe, title, arms):
    """The agreement sections: configurations every texture diverts, none does, or that differ,
    counted here from the attacked rows of every arm and seed, and the mean start phi of the
    undiverted ones."""
    text = (RESULTS / "findings.md").read_text()
    assert text.count(title) == 1, title
    section = text.split(title, 1)[1].split("\n## ", 1)[0]
    rows = _rows(recipe)
    textures = {}
    for arm in arms:
        by_seed = _by_seed(rows, arm, "attack")
        assert len(by_seed) >= 3, (recipe, arm)
        for s, outcomes in by_seed.items():
            textures[(arm, s)] = outcomes
    # every arm ran under the same attack seeds
    assert len({frozenset(s for a, s in textures if a == arm) for arm in arms}) == 1
    configs = sorted(set.intersection(*(set(v) for v in textures.values())))
    hits = {c: sum(int(t[c]) for t in textures.values()) for c in configs}
    k = len(textures)
    n_all = sum(h == k for h in hits.values())
    n_none = sum(h == 0 for h in hits.values())
    n_differ = len(configs) - n_all - n_none
    phi = {int(r["seed"]): _phi_deg(r) for r in rows if r["condition"] == "attack"}
    none = [c for c, h in hits.items() if h == 0]
    want = (
        f"The {k} textures of this run ({', '.join(a.removeprefix('table2_') for a in arms)}; "
        f"{k // len(arms)} attack seeds each) on the same {len(configs)} configurations: every texture diverts the "
        f"policy to the adversarial object in {n_all} of them, none does in {n_none}, and the textures differ in only "
        f"{n_differ} ({100 * n_differ / len(configs):.1f}%)."
    )
    assert want in section, section
    rates = [100 * sum(int(t[c]) for c in configs) / len(configs) for t in textures.values()]
    assert (
        f"Their T-ASR spans {min(rates):.1f} to {max(rates):.1f}% ({max(rates) - min(rates):.1f} pp apart)" in section
    )
    assert f"could differ by more than {100 * n_differ / len(configs):.1f} pp" in section
    assert f"mean phi of {sum(phi[c] for c in none) / len(none):.1f} deg" in section
    assert f"(all {len(configs)}: {sum(phi[c] for c in configs) / len(configs):.1f} deg)" in section
