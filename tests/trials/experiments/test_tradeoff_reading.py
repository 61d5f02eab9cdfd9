"""docs/speed-vs-accuracy.md's reading of the committed sweep ("What the committed sweep shows on
this policy"), checked statement by statement against results/tradeoff/.

Each statement is recomputed here from ``rows.jsonl`` and ``episodes.csv`` with csv, json and
math.comb only, not with :mod:`trials.experiments.tradeoff_report`. The knob lists the doc gives
are read from the doc, so a list that no longer matches the data fails, and so does a knob added to
or dropped from the doc. The tests skip while ``results/tradeoff/`` is not committed.
"""

from __future__ import annotations

import json
import re

import pytest

# the sweep evidence's own independent readers (csv, json, math.comb only)
from tests.trials.experiments.test_tradeoff_evidence import DOC, RESULTS, ROOT, mcnemar_p, read_attacked, read_records

SECTION = "### What the committed sweep shows on this policy"
ALPHA = 0.05

pytestmark = pytest.mark.skipif(not (RESULTS / "rows.jsonl").is_file(), reason="results/tradeoff/ not committed yet")


def records() -> dict[str, dict]:
    """The newest record per key of rows.jsonl, finished rows only."""
    return {k: r for k, r in read_records(RESULTS).items() if r.get("status") == "ok"}


def seed_of(rec: dict) -> int:
    return rec.get("attack_seed") or 0


def runs_of(setting: str, recs: dict[str, dict]) -> list[dict]:
    """Every attack seed's run of ``setting`` (``knob=value``)."""
    return [r for k, r in recs.items() if k.split("@")[0] == setting]


def baseline_of(rec: dict, recs: dict[str, dict]) -> dict:
    (base,) = [r for r in runs_of("baseline=quick", recs) if seed_of(r) == seed_of(rec)]
    return base


def counts(rec: dict, recs: dict[str, dict], outcomes: dict[str, dict[int, bool]]) -> tuple[int, int, int]:
    """(targeted under the baseline of the same seed only, under the row only, pairs)."""
    row, base = outcomes[rec["eval_name"]], outcomes[baseline_of(rec, recs)["eval_name"]]
    common = set(row) & set(base)
    assert len(common) == 300, f"{rec['key']}: {len(common)} paired configurations, not 300"
    return sum(base[s] and not row[s] for s in common), sum(row[s] and not base[s] for s in common), len(common)


def direction(rec: dict, recs: dict[str, dict], outcomes: dict[str, dict[int, bool]]) -> str:
    """'lower', 'higher' or 'same' against the baseline of the same seed (exact McNemar)."""
    b, c, _ = counts(rec, recs, outcomes)
    if mcnemar_p(b, c) >= ALPHA:
        return "same"
    return "higher" if c > b else "lower"


def diff_pp(rec: dict, recs: dict[str, dict], outcomes: dict[str, dict[int, bool]]) -> float:
    b, c, n = counts(rec, recs, outcomes)
    return 100 * (c - b) / n


ATTACK_SETTINGS_KINDS = ("attack", "snapshot")


def paired_settings(recs: dict[str, dict]) -> set[str]:
    """The settings paired with the baseline: every attack-changing one but the baseline itself."""
    return {
        k.split("@")[0]
        for k, r in recs.items()
        if r["kind"] in ATTACK_SETTINGS_KINDS and not k.startswith(("baseline", "policy_resolution"))
    }


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
    return records(), read_attacked(RESULTS)


def test_no_run_was_higher_and_two_settings_were_numerically_higher_in_every_seed(data):
    recs, outcomes = data
    text = bullet("No run was higher than its seed's baseline")
    runs = [r for s in paired_settings(recs) for r in runs_of(s, recs)]
    assert len(runs) == 33
    assert [r["key"] for r in runs if direction(r, recs, outcomes) == "higher"] == []
    lead = text.split(" were numerically higher in all three seeds", 1)[0]
    up = {s for s in paired_settings(recs) if all(diff_pp(r, recs, outcomes) > 0 for r in runs_of(s, recs))}
    assert settings_in(lead) == up == {"texture_size=32", "saliency=off"}
    diffs = [diff_pp(r, recs, outcomes) for s in up for r in runs_of(s, recs)]
    assert f"(by {min(diffs):.1f} to {max(diffs):.1f} pp)" in text


def test_the_settings_lower_in_every_seed_are_exactly_those_the_doc_names(data):
    recs, outcomes = data
    text = bullet("Lower in every attack seed")
    measured = {
        s
        for s in paired_settings(recs)
        if len(runs := runs_of(s, recs)) == 3 and all(direction(r, recs, outcomes) == "lower" for r in runs)
    }
    assert settings_in(text.split(". ", 1)[0]) == measured
    assert measured == {"iterations=30", "iterations=60", "eot_envs=1", "sampler=bilinear", "texture_size=256"}
    # "snapshots of the baseline's own 120-iteration runs": the last 60 iterations still buy T-ASR
    assert "snapshots of the baseline's own 120-iteration runs" in text
    assert all(r["kind"] == "snapshot" for s in ("iterations=30", "iterations=60") for r in runs_of(s, recs))
    assert {b["attack_config"]["iterations"] for b in runs_of("baseline=quick", recs)} == {120}


def test_the_settings_not_different_in_any_seed_are_exactly_those_the_doc_names(data):
    recs, outcomes = data
    measured = {
        s
        for s in paired_settings(recs)
        if len(runs := runs_of(s, recs)) == 3 and all(direction(r, recs, outcomes) == "same" for r in runs)
    }
    assert settings_in(bullet("Not different in any attack seed").split(". ", 1)[0]) == measured
    assert measured == {"eot_envs=2", "rollout_steps=5", "texture_size=32", "saliency=off", "pcgrad=off"}


def test_ten_rollout_steps_lower_in_one_seed_numerically_lower_in_all_and_slower_in_all(data):
    recs, outcomes = data
    assert "lower in one seed of three and numerically lower in all three" in bullet("`rollout_steps=10`")
    runs = runs_of("rollout_steps=10", recs)
    assert sorted(direction(r, recs, outcomes) for r in runs) == ["lower", "same", "same"]
    assert all(diff_pp(r, recs, outcomes) < 0 for r in runs)
    assert all(r["attack_wall_s"] > baseline_of(r, recs)["attack_wall_s"] for r in runs)


def test_the_attack_cpu_time_ratios(data):
    recs, outcomes = data
    text = bullet("Attack CPU time")
    base = [r["attack_cpu_s"] for r in runs_of("baseline=quick", recs)]
    mean = sum(base) / len(base)
    assert f"took {min(base) / mean:.2f} to {max(base) / mean:.2f} times their mean" in text

    def ratio(setting: str) -> str:
        runs = runs_of(setting, recs)
        assert len(runs) == 3
        return f"{sum(r['attack_cpu_s'] for r in runs) / 3 / mean:.2f}"

    assert f"`eot_envs=2` took {ratio('eot_envs=2')} and `rollout_steps=5` {ratio('rollout_steps=5')}" in text
    assert (
        f"`saliency=off` {ratio('saliency=off')}, `texture_size=32` {ratio('texture_size=32')} and "
        f"`pcgrad=off` {ratio('pcgrad=off')}"
    ) in text
    # "the one clear saving" of the settings that kept T-ASR
    assert "`eot_envs=2` is the one clear saving" in text
    kept = {"eot_envs=2", "rollout_steps=5", "texture_size=32", "saliency=off", "pcgrad=off"}
    # clear: below three quarters of the baseline's lowest run
    clear = {s for s in kept if float(ratio(s)) < 0.75 * min(base) / mean}
    assert clear == {"eot_envs=2"}


def test_the_why_items_say_they_are_explanations_and_their_premises_hold(data):
    recs, _ = data
    tex = bullet("Why `texture_size=256` loses")
    assert "(likely, not tested: no run re-tuned `lr`)" in tex
    runs = [r for s in paired_settings(recs) for r in runs_of(s, recs) if r["kind"] == "attack"]
    runs += runs_of("baseline=quick", recs)
    assert len({r["attack_config"]["lr"] for r in runs}) == 1
    assert {r["attack_config"]["iterations"] for r in runs} == {120}
    (big,) = {r["attack_config"]["texture_size"] for r in runs_of("texture_size=256", recs)}
    (ref,) = {r["attack_config"]["texture_size"] for r in runs_of("baseline=quick", recs)}
    assert "each of 16 times as many texels" in tex and (big / ref) ** 2 == 16
    sam = bullet("Why `sampler=bilinear` loses")
    assert "(likely, not tested on its own)" in sam and "`tests/attack/test_render.py`" in sam
    assert 'errs["trilinear"] <= errs["bilinear"]' in (ROOT / "tests" / "attack" / "test_render.py").read_text()


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
    # measured one after another within half a minute, at the stated load
    times = sorted(r["time_utc"] for r in dep.values())
    starts = [int(t[11:13]) * 3600 + int(t[14:16]) * 60 + int(t[17:19]) for t in times]
    assert max(starts) - min(starts) <= 30 and "within half a minute" in text
    loads = [r["load_start"][0] for r in dep.values()]
    assert f"1-minute load {min(loads):.1f} to {max(loads):.1f}" in text
    assert "ONNX fp32 had lower wall latency per image than torch fp32 at batch 1 and at batch 8" in text
    assert all(lat["onnx-fp32"][b] < lat["torch-fp32"][b] for b in ("b1", "b8"))
    assert "ONNX int8 (dynamic quantisation) was slower than both fp32 variants at both batch sizes" in text
    assert all(lat["onnx-int8"][b] > max(lat["onnx-fp32"][b], lat["torch-fp32"][b]) for b in ("b1", "b8"))
    assert "changed the actions most" in text
    assert max(dep, key=lambda v: dep[v]["action_err_max"]) == "onnx-int8"
    assert max(dep, key=lambda v: dep[v]["action_err_mean"]) == "onnx-int8"
    assert "it has the smallest file" in text
    files = {v: r["model_bytes"] for v, r in dep.items() if r["model_bytes"]}
    assert min(files, key=files.get) == "onnx-int8"
    assert "ONNX fp16's file is about half of fp32's" in text
    assert 0.45 <= files["onnx-fp16"] / files["onnx-fp32"] <= 0.55
    assert "Every variant kept the clean success of torch fp32 on its 50 episodes" in text
    ref = dep["torch-fp32"]["clean_success"]
    assert ref["n"] == 50
    assert all(r["clean_success"]["k"] == ref["k"] and r["clean_success"]["n"] == 50 for r in dep.values())


def test_the_larger_policies_took_more_time_than_any_baseline_run_and_are_not_paired(data):
    recs, _ = data
    text = bullet("Policy resolution")
    assert "attack and evaluation each took more wall and more CPU time than any of the three baseline runs" in text
    bases = runs_of("baseline=quick", recs)
    assert len(bases) == 3
    for px in ("96", "128"):
        r = recs[f"policy_resolution={px}"]
        for m in ("attack_wall_s", "attack_cpu_s", "eval_wall_s", "eval_cpu_s"):
            assert r[m] > max(b[m] for b in bases), (px, m)
        # "on their own configuration sets"
        assert r["eval_set"] != bases[0]["eval_set"] and r["eval_set"].endswith(f"px{px}.json")


def test_the_policy_card_the_sweep_attacked_has_the_quick_cards_weights():
    cards = ROOT / "results" / "policies"
    sweep = json.loads((RESULTS / "sweep.json").read_text())["settings"]["policy"]
    assert sweep.endswith("policy-quick-2") and "`results/policies/policy-quick-2.json`" in section()
    a, b = (json.loads((cards / n).read_text())["weights_sha256"] for n in ("policy-quick-2.json", "policy-quick.json"))
    assert a == b
    assert "equal `weights_sha256`" in DOC.read_text()
