"""Correcting a committed trial (``advobj trial amend``) keeps the old value, and the report says
what a reader must know: an unfinished session, overrides, amendments and notes."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from tests.trials.real.trial_session_helpers import sim_hardware, small_plan, straight_ahead_onnx


@pytest.fixture(scope="module")
def session_db(tmp_path_factory):
    from trials.real.operator import Decision, ScriptedOperator
    from trials.real.session import SessionOptions, run_session

    d = tmp_path_factory.mktemp("amend")
    plan = small_plan(d / "plan.yaml", d / "tex", n_tcp=2, n_layouts=1, max_steps=4)  # 6 trials planned
    answers = [Decision("adversarial", "the arm brushed the can"), Decision(None, "")]
    opts = SessionOptions(
        hardware=sim_hardware(d / "hw.yaml"),
        policy=straight_ahead_onnx(d / "p.onnx"),
        plan=plan,
        session="s1",
        db=d / "t.sqlite",
        rate_limit=False,
        max_trials=2,
    )
    run_session(opts, operator=ScriptedOperator(answers, log=None), log=lambda _t: None)
    return d / "t.sqlite"


def _cli(monkeypatch, capsys, *args):
    from trials.cli.main import main

    monkeypatch.setattr("sys.argv", ["advobj", *args])
    try:
        main()
        code = 0
    except SystemExit as exc:
        code = exc.code
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def test_amend_corrects_a_trial_and_keeps_the_old_value(session_db, monkeypatch, capsys):
    from trials.real.store import TrialStore

    with TrialStore(session_db, create=False) as st:
        first, second = [r["trial_id"] for r in st.trial_rows()]
        before = {r["trial_id"]: r for r in st.trial_rows()}[second]
    code, out, err = _cli(
        monkeypatch,
        capsys,
        "trial",
        "amend",
        "--db",
        str(session_db),
        "--session",
        "s1",
        "--trial",
        second,
        "--outcome",
        "goal",
        "--note",
        "video shows the goal reached",
        "--reason",
        "operator pressed n by mistake",
    )
    assert code == 0, err
    assert f"s1/{second}: outcome {before['final_outcome']} -> goal" in out
    with TrialStore(session_db, create=False) as st:
        row = {r["trial_id"]: r for r in st.trial_rows()}[second]
        assert row["final_outcome"] == "goal" and row["note"] == "video shows the goal reached"
        assert row["operator_outcome"] == (None if before["auto_outcome"] == "goal" else "goal")
        (a,) = st.amendments()
        assert (a["trial_id"], a["old_final_outcome"], a["old_note"], a["new_final_outcome"]) == (
            second,
            before["final_outcome"],
            "",
            "goal",
        )
        assert a["reason"] == "operator pressed n by mistake"
        assert {r["trial_id"]: r for r in st.trial_rows()}[first][
            "final_outcome"
        ] == "adversarial"  # the other one untouched


@pytest.mark.parametrize(
    "args,flag",
    [
        (["--session", "nope", "--trial", "x", "--outcome", "goal"], "--session: no session 'nope'"),
        (["--session", "s1", "--trial", "x", "--outcome", "goal"], "--trial: no committed trial 'x'"),
        (["--session", "s1", "--trial", "x", "--outcome", "maybe"], "--outcome: 'maybe' is not one of"),
        (["--session", "s1", "--trial", "x"], "give --outcome and/or --note"),
    ],
)
def test_amend_refuses_bad_input_in_one_line_and_changes_nothing(session_db, monkeypatch, capsys, args, flag):
    from trials.real.store import TrialStore

    with TrialStore(session_db, create=False) as st:
        before = (st.trial_rows(), st.amendments())
    code, out, err = _cli(monkeypatch, capsys, "trial", "amend", "--db", str(session_db), *args)
    lines = [l for l in err.splitlines() if l.strip()]
    assert code == 2 and len(lines) == 1 and flag in lines[0] and "Traceback" not in err
    with TrialStore(session_db, create=False) as st:
        assert (st.trial_rows(), st.amendments()) == before


def test_the_report_says_the_session_is_incomplete_and_lists_overrides_amendments_and_notes(session_db, tmp_path):
    from trials.cli.main import app

    r = CliRunner().invoke(app, ["trial", "report", "--db", str(session_db), "--out", str(tmp_path / "rep")])
    assert r.exit_code == 0, r.output
    assert "INCOMPLETE: session s1: 2 of 6 planned trials committed" in r.output
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "**Incomplete: session s1: 2 of 6 planned trials committed.**" in md
    audit = json.loads((tmp_path / "rep" / "report.json").read_text())["summary"]["audit"]
    assert f"Operator overrides ({len(audit['overrides'])}):" in md and "-> adversarial (the arm brushed the can)" in md
    assert f"Notes ({len(audit['notes'])}):" in md and "s1/A-cube-clean-t0-o0: the arm brushed the can" in md
    assert audit["planned"] == {"s1": 6} and len(audit["overrides"]) >= 1
    assert f"Amendments after the session ({len(audit['amendments'])};" in md
    assert len(audit["amendments"]) == len([x for x in md.splitlines() if " at 20" in x and "->" in x])
