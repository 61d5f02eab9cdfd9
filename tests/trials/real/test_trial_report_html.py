"""The trial session's report (trials.real.report): one session shown once, the paired test between
arms, a clean arm that never succeeds flagged, the precision line at 0 % and 100 %, the chart, and
report.html in a real Chromium. The trials go through a real SQLite store and the real CLI."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest
from hypothesis import given
from hypothesis import strategies as st
from typer.testing import CliRunner

from sim.htmlreport import REPORT_HTML
from tests.sim.browser_helpers import assert_renders_cleanly, needs_chromium, outline, render_in_chromium
from tests.trials.real.test_trial_report import _record as trial_record
from trials.eval.metrics import mcnemar_exact
from trials.real.report import (
    audit,
    clean_flags,
    paired_arms,
    precision,
    precision_line,
    summarize_trials,
    write_trial_report,
)


def _row(session, condition, pose, layout, outcome, env="A", shape="cube", tags=()):
    return {
        "session": session,
        "trial_id": f"{env}-{shape}-{condition}-t{pose}-o{layout}",
        "env": env,
        "shape": shape,
        "condition": condition,
        "tcp_pose": pose,
        "object_layout": layout,
        "tags": list(tags),
        "final_outcome": outcome,
    }


OUT = st.sampled_from(["goal", "adversarial", "none", "unknown"])


@given(st.lists(st.tuples(OUT, OUT), min_size=1, max_size=30))
def test_the_paired_test_counts_discordant_rated_pairs_at_the_same_placement(pairs):
    rows = []
    for i, (adv, clean) in enumerate(pairs):
        rows += [_row("s", "adv3d", i, i % 3, adv), _row("s", "clean", i, i % 3, clean)]
    rows.append(_row("s", "clean", 99, 0, "goal"))  # no adv3d partner
    (p,) = paired_arms(rows)
    rated = [(a, c) for a, c in pairs if "unknown" not in (a, c)]
    b = sum(a == "adversarial" and c != "adversarial" for a, c in rated)
    c = sum(a != "adversarial" and c == "adversarial" for a, c in rated)
    assert (p["a"], p["b"], p["n_pairs"], p["unrated_pairs"]) == ("adv3d", "clean", len(rated), len(pairs) - len(rated))
    assert p["unpaired"] == 1 and p["tasr"] == mcnemar_exact(b, c, len(rated)).to_dict()
    b = sum(a != "goal" and c == "goal" for a, c in rated)
    c = sum(a == "goal" and c != "goal" for a, c in rated)
    assert p["asr"] == mcnemar_exact(b, c, len(rated)).to_dict()


def test_trials_pair_only_within_their_session_env_shape_tags_pose_and_layout():
    rows = [
        _row("s1", "adv3d", 0, 0, "adversarial"),
        _row("s2", "clean", 0, 0, "goal"),  # another session
        _row("s1", "clean", 0, 0, "goal", shape="cylinder"),  # another shape
        _row("s1", "clean", 0, 0, "goal", tags=["dim"]),  # another tag
        _row("s1", "clean", 0, 1, "goal"),  # another layout
        _row("s1", "patch", 0, 0, "none"),
    ]
    got = {(p["a"], p["b"]): (p["n_pairs"], p["unpaired"]) for p in paired_arms(rows)}
    assert got == {("adv3d", "clean"): (0, 5), ("patch", "clean"): (0, 5), ("adv3d", "patch"): (1, 0)}


def test_a_clean_arm_that_never_reaches_the_goal_is_flagged_per_object():
    rows = [_row("s", "clean", i, 0, o) for i, o in enumerate(["none", "adversarial", "unknown"])]
    rows += [_row("s", "clean", i, 0, "goal", shape="cylinder") for i in range(2)]
    rows += [_row("s", "clean", 0, 0, "unknown", env="B")]  # no rated trial: nothing said
    (flag,) = clean_flags(rows)
    assert "never reached the goal in A/cube (0 of 2 rated clean trials)" in flag


def test_the_precision_line_at_0_and_100_percent_gives_the_wilson_width_only():
    for k in (0, 4):
        line = precision_line(precision(k, 4))
        assert "±0.0 %" not in line and "the normal approximation has no width" in line
        assert f"the 4 trials here give ±{100 * precision(k, 4)['wilson_half_width']:.1f} % (Wilson" in line
    assert "(normal approximation z·√(p(1−p)/n))" in precision_line(precision(2, 4))


def _record(i, condition, outcome, pose):
    """test_trial_report's trial record, at TCP pose ``pose``."""
    return replace(
        trial_record(i, outcome, condition=condition), trial_id=f"A-cube-{condition}-t{pose}-o0", tcp_pose=pose
    )


# One session: the clean arm never reaches the goal (a policy that cannot do the task), adv3d
# reaches the adversarial object at poses 0-2 of 4.
ADV3D = ["adversarial", "adversarial", "adversarial", "none"]
CLEAN = ["none", "none", "none", "none"]


@pytest.fixture(scope="module")
def report_dir(tmp_path_factory):
    from trials.cli.main import app
    from trials.real.store import SessionInfo, TrialStore

    root = tmp_path_factory.mktemp("trials")
    db = root / "trials.sqlite"
    with TrialStore(db) as store:
        sid = store.open_session(
            SessionInfo(
                name="day1",
                plan_sha256="p",
                plan_text="",
                hardware_text="",
                policy_path="pol",
                policy_sha256="q",
                software_version="0",
                git_commit="g",
                devices={},
                calibration={},
            )
        )
        for i, (cond, out, pose) in enumerate(
            [("adv3d", o, k) for k, o in enumerate(ADV3D)] + [("clean", o, k) for k, o in enumerate(CLEAN)]
        ):
            store.commit_trial(sid, _record(i, cond, out, pose))
    res = CliRunner().invoke(app, ["trial", "report", "--db", str(db), "--out", str(root / "report")])
    assert res.exit_code == 0, res.output
    return root / "report"


def test_one_session_is_shown_once_with_its_paired_test_and_flag(report_dir):
    md = (report_dir / "report.md").read_text()
    assert md.count("## Session day1") == 1 and "## All sessions" not in md and "Session day1 (all trials)" in md
    assert "**Flag: the clean arm never reached the goal in A/cube (0 of 4 rated clean trials)" in md
    assert "| adv3d vs clean | 4 | 3 / 0 | 0.25 | 0 / 0 | 1 |" in md
    assert "±0.0 %" not in md and "![T-ASR and ASR by arm](rates_by_arm.png)" in md
    doc = json.loads((report_dir / "report.json").read_text())
    (p,) = doc["summary"]["paired"]
    assert p["tasr"] == mcnemar_exact(3, 0, 4).to_dict() and len(doc["summary"]["flags"]) == 1


def test_the_trial_page_holds_the_chart_the_paired_test_and_the_flag(report_dir):
    o = outline((report_dir / REPORT_HTML).read_text())
    assert o.headings["h1"] == ["Real-robot trial report"]
    assert o.headings["h2"] == [
        "Summary",
        "T-ASR and ASR by arm",
        "Paired tests between arms",
        "Table IV: sim-to-real transferability (%)",
        "Session day1 (all trials)",
        "Completeness, overrides, amendments and notes",
    ]
    assert "The clean arm never reached the goal in A/cube" in o.text and "adv3d vs clean" in o.text
    assert [i["src"][:22] for i in o.images] == ["data:image/png;base64,"]


@needs_chromium
def test_chromium_renders_the_trial_page_without_console_messages(tmp_path, report_dir):
    r = render_in_chromium(report_dir / REPORT_HTML, tmp_path, 1280, 2400)
    assert_renders_cleanly(r)
    assert r.outline.headings["h2"][:3] == ["Summary", "T-ASR and ASR by arm", "Paired tests between arms"]


def test_several_sessions_show_the_pooled_breakdown_and_each_session(tmp_path):
    rows = [_row("s1", "adv3d", 0, 0, "goal"), _row("s2", "adv3d", 0, 0, "goal")]
    s = summarize_trials(rows)
    assert s["flags"] == [] and s["paired"] == []
    md, _ = write_trial_report(tmp_path, s)
    heads = [x for x in md.read_text().splitlines() if x.startswith("## ")]
    assert heads[-3:] == ["## All sessions (pooled)", "## Session s1", "## Session s2"]
    assert "No two arms ran here" in md.read_text()


def test_a_hostile_note_is_text_on_the_page(tmp_path):
    note = "<script>alert(1)</script> <img src=x onerror=alert(2)> \x1b[31mred\x1b[0m"
    rows = [{**_row("s", "adv3d", 0, 0, "goal"), "note": note, "operator_outcome": None, "auto_outcome": "goal"}]
    s = summarize_trials(rows)
    s["audit"] = audit(rows, {"s": 1}, [])
    write_trial_report(tmp_path, s)
    page = (tmp_path / REPORT_HTML).read_text()
    o = outline(page)
    assert o.scripts == 0 and len(o.images) == 1  # the chart only
    assert "s/A-cube-adv3d-t0-o0: <script>alert(1)</script> <img src=x onerror=alert(2)> red" in o.text
    assert "\x1b" not in page
