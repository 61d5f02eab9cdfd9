"""docs/speed-vs-accuracy.md's reading of the committed sweep ("What the committed sweep shows on
this policy"), checked statement by statement against results/tradeoff/.

Each statement is recomputed here from ``rows.jsonl`` and ``episodes.csv`` with csv, json and
math.comb only, not with :mod:`trials.experiments.tradeoff_report`. The knob lists the doc gives
are read from the doc, so a list that no longer matches the data fails, and so does a knob added to
or dropped from the doc. The tests skip while ``results/tradeoff/`` is not committed.
"""

from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
RESULTS = ROOT / "results" / "tradeoff"
DOC = ROOT / "docs" / "speed-vs-accuracy.md"
SECTION = "### What the committed sweep shows on this policy"
ALPHA = 0.05

pytestmark = pytest.mark.skipif(not (RESULTS / "rows.jsonl").is_file(), reason="results/tradeoff/ not committed yet")


def mcnemar_p(b: int, c: int) -> float:
    n = b + c
    if n == 0:
        return 1.0
    return min(1.0, 2 * sum(math.comb(n, i) for i in range(min(b, c) + 1)) / 2**n)


def records() -> dict[str, dict]:
    out = {}
    for line in (RESULTS / "rows.jsonl").read_text().splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        out[rec["key"]] = rec
    return {k: r for k, r in out.items() if r.get("status") == "ok"}


def attacked() -> dict[str, dict[int, bool]]:
    out: dict[str, dict[int, bool]] = {}
    with open(RESULTS / "episodes.csv", newline="") as f:
        for row in csv.DictReader(f):
            if row["condition"] == "attack":
                out.setdefault(row["eval"], {})[int(row["seed"])] = row["targeted"] == "1"
    return out


def seed_of(rec: dict) -> int:
    return rec.get("attack_seed") or 0


def runs_of(setting: str, recs: dict[str, dict]) -> list[dict]:
    """Every attack seed's run of ``setting`` (``knob=value``)."""
    return [r for k, r in recs.items() if k.split("@")[0] == setting]


def baseline_of(rec: dict, recs: dict[str, dict]) -> dict:
    (base,) = [r for r in runs_of("baseline=quick", recs) if seed_of(r) == seed_of(rec)]
    return base


def direction(rec: dict, recs: dict[str, dict], outcomes: dict[str, dict[int, bool]]) -> str:
    """'lower', 'higher' or 'same' against the baseline of the same seed (exact McNemar)."""
    row, base = outcomes[rec["eval_name"]], outcomes[baseline_of(rec, recs)["eval_name"]]
    common = set(row) & set(base)
    assert len(common) == 300, f"{rec['key']}: {len(common)} paired configurations, not 300"
    b = sum(base[s] and not row[s] for s in common)
    c = sum(row[s] and not base[s] for s in common)
    if mcnemar_p(b, c) >= ALPHA:
        return "same"
    return "higher" if c > b else "lower"


def section() -> str:
    text = DOC.read_text()
    assert text.count(SECTION) == 1, f"{DOC.name} must hold the section {SECTION!r} once"
    body = text.split(SECTION, 1)[1]
    return body.split("\n## ", 1)[0]


def bullet(lead: str) -> str:
    """The bullet of the section that starts with ``**lead``, as one line."""
    bullets = re.split(r"\n- ", section())
    (hit,) = [b for b in bullets if b.startswith(f"**{lead}")]
    return " ".join(hit.split())


def settings_in(text: str) -> set[str]:
    return set(re.findall(r"`([a-z_]+=[a-z0-9]+)`", text))


@pytest.fixture(scope="module")
def data():
    return records(), attacked()


def test_no_setting_raised_t_asr_in_any_seed(data):
    recs, outcomes = data
    assert "No run of any knob scored higher" in bullet("No setting raised T-ASR")
    paired = [
        r
        for k, r in recs.items()
        if r["kind"] in ("attack", "snapshot") and not k.startswith(("baseline", "policy_resolution"))
    ]
    assert len(paired) == 33
    assert [r["key"] for r in paired if direction(r, recs, outcomes) == "higher"] == []


def test_the_settings_lower_in_every_seed_are_exactly_those_the_doc_names(data):
    recs, outcomes = data
    named = settings_in(bullet("Lower in every attack seed").split(". ", 1)[0])
    measured = {
        s
        for s in {k.split("@")[0] for k, r in recs.items() if r["kind"] in ("attack", "snapshot")}
        if not s.startswith(("baseline", "policy_resolution"))
        and len(runs := runs_of(s, recs)) == 3
        and all(direction(r, recs, outcomes) == "lower" for r in runs)
    }
    assert named == measured == {"iterations=30", "iterations=60", "eot_envs=1", "sampler=bilinear", "texture_size=256"}


def test_the_settings_not_different_in_any_seed_are_exactly_those_the_doc_names(data):
    recs, outcomes = data
    text = bullet("Not different in any attack seed")
    named = settings_in(text.split(". ", 1)[0])
    measured = {
        s
        for s in {k.split("@")[0] for k, r in recs.items() if r["kind"] == "attack"}
        if not s.startswith(("baseline", "policy_resolution"))
        and len(runs := runs_of(s, recs)) == 3
        and all(direction(r, recs, outcomes) == "same" for r in runs)
    }
    assert named == measured == {"eot_envs=2", "rollout_steps=5", "texture_size=32", "saliency=off", "pcgrad=off"}
    # "eot_envs=2 also took less attack CPU time than the baseline in every seed", and it is the only one
    cheaper = {
        s for s in measured if all(r["attack_cpu_s"] < baseline_of(r, recs)["attack_cpu_s"] for r in runs_of(s, recs))
    }
    lead = "Of them, `eot_envs=2`, `rollout_steps=5` and `texture_size=32` took less attack CPU time"
    assert lead in text
    assert cheaper == settings_in(text.split(lead[: len("Of them, ")], 1)[1].split(" took ", 1)[0])
    assert cheaper == {"eot_envs=2", "rollout_steps=5", "texture_size=32"}
    # "the clear saving is eot_envs=2, whose mean attack CPU time was about half the baseline's"
    assert "`eot_envs=2`, whose mean attack CPU time was about half the baseline's" in text

    def mean_cpu(setting: str) -> float:
        runs = runs_of(setting, recs)
        return sum(r["attack_cpu_s"] for r in runs) / len(runs)

    ratio = mean_cpu("eot_envs=2") / mean_cpu("baseline=quick")
    assert 0.4 <= ratio <= 0.6
    assert all(mean_cpu(s) / mean_cpu("baseline=quick") > 0.6 for s in cheaper - {"eot_envs=2"})


def test_ten_rollout_steps_lower_in_one_seed_and_slower_in_all(data):
    recs, outcomes = data
    assert "lower in one seed of three, and no run was higher" in bullet("`rollout_steps=10`")
    runs = runs_of("rollout_steps=10", recs)
    assert sorted(direction(r, recs, outcomes) for r in runs) == ["lower", "same", "same"]
    assert all(r["attack_wall_s"] > baseline_of(r, recs)["attack_wall_s"] for r in runs)


def test_the_evaluation_took_more_wall_time_than_the_attack_in_every_300_episode_row(data):
    recs, outcomes = data
    assert "took more wall time than the attack it scored" in bullet("The evaluation costs more")
    rows = [r for r in recs.values() if r.get("attack_wall_s") is not None and r.get("eval_wall_s") is not None]
    full = [r for r in rows if len(outcomes[r["eval_name"]]) == 300]
    assert len(full) == 38  # 36 attack-seed runs and the two resolution policies
    assert all(r["eval_wall_s"] > r["attack_wall_s"] for r in full)


def test_the_deployment_statements(data):
    recs, _ = data
    dep = {r["value"]: r for r in recs.values() if r["kind"] == "deployment"}
    assert set(dep) == {"torch-fp32", "onnx-fp32", "onnx-int8", "onnx-fp16"}
    lat = {v: {b: r["latency_ms"][b]["median"] for b in ("b1", "b8")} for v, r in dep.items()}
    text = bullet("Deployment")
    assert "ONNX fp32 had lower wall latency per image than torch fp32 at batch 1 and at batch 8" in text
    assert all(lat["onnx-fp32"][b] < lat["torch-fp32"][b] for b in ("b1", "b8"))
    assert "ONNX int8 (dynamic quantisation) was slower than ONNX fp32 at both batch sizes" in text
    assert all(lat["onnx-int8"][b] > lat["onnx-fp32"][b] for b in ("b1", "b8"))
    assert "changed the actions most" in text
    assert max(dep, key=lambda v: dep[v]["action_err_max"]) == "onnx-int8"
    assert max(dep, key=lambda v: dep[v]["action_err_mean"]) == "onnx-int8"
    assert "ONNX fp16's file is about half of fp32's" in text
    assert 0.45 <= dep["onnx-fp16"]["model_bytes"] / dep["onnx-fp32"]["model_bytes"] <= 0.55
    assert "Every variant kept the clean success of torch fp32 on its 50 episodes" in text
    ref = dep["torch-fp32"]["clean_success"]
    assert ref["n"] == 50
    assert all(r["clean_success"]["k"] == ref["k"] and r["clean_success"]["n"] == 50 for r in dep.values())


def test_the_larger_policies_cost_more_in_every_measure(data):
    recs, _ = data
    assert "cost more to attack and to evaluate than the 64 px one in every measure above" in bullet(
        "Policy resolution"
    )
    bases = runs_of("baseline=quick", recs)
    assert len(bases) == 3
    for px in ("96", "128"):
        r = recs[f"policy_resolution={px}"]
        for m in ("attack_wall_s", "attack_cpu_s", "eval_wall_s", "eval_cpu_s"):
            assert r[m] > max(b[m] for b in bases), (px, m)
