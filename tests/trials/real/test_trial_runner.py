"""The trial runner on sim hardware: placement check, operator override, abort/resume, pause, plan guard."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.trials.real.trial_session_helpers import sim_hardware, small_plan, straight_ahead_onnx, tiny_onnx
from trials.real.locate import LocatedObject, TagLocator, placement_issues
from trials.real.operator import AnswersError, AutoOperator, ScriptedOperator, TerminalOperator, load_answers
from trials.real.plan import ObjectPlacement, load_plan
from trials.real.session import SessionOptions, file_sha256, run_session
from trials.real.store import SessionMismatch, TrialStore


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("trial_runner")
    return {
        "policy": tiny_onnx(d / "p.onnx"),
        "plan": small_plan(d / "plan.yaml", d),
        "hw": sim_hardware(d / "hw.yaml"),
    }


def _opts(files, db, session="s", **options) -> SessionOptions:
    """The options of a session of the module's sim cell, without rate limiting."""
    return SessionOptions(
        hardware=files["hw"],
        policy=files["policy"],
        plan=files["plan"],
        session=session,
        db=db,
        rate_limit=False,
        **options,
    )


def _run(files, db, session="s", *, operator=None, on_ready=None, log=print, **options):
    operator = AutoOperator(log=None) if operator is None else operator
    return run_session(_opts(files, db, session, **options), operator=operator, on_ready=on_ready, log=log)


def test_placement_check_catches_a_misplaced_object_and_passes_after_correction(files, tmp_path):
    db = tmp_path / "t.sqlite"

    def misplace(runner, world):
        runner.stage.misplace("adversarial", dx_m=0.03, dyaw_rad=0.3)

    summary = _run(files, db, max_trials=1, on_ready=misplace)
    assert len(summary.committed) == 1
    store = TrialStore(db)
    row = store.trial_rows()[0]
    assert row["placement_checks"] == 2 and not row["placement_skipped"]
    ev = store.con.execute("SELECT kind, action, reason FROM events WHERE kind = 'placement'").fetchall()
    assert (
        len(ev) == 1 and "adversarial: move 3.0 cm toward -x" in ev[0]["reason"] and "rotate -17 deg" in ev[0]["reason"]
    )
    plan = load_plan(files["plan"])
    layout = plan.object_layout(plan.trial(row["trial_id"]).object_layout).objects
    placed = {r["role"]: r for r in store.con.execute("SELECT * FROM object_poses WHERE phase = 'placement'")}
    for role in ("goal", "adversarial"):
        assert (
            math.hypot(
                placed[role]["table_x_m"] - layout[role].xy_m[0], placed[role]["table_y_m"] - layout[role].xy_m[1]
            )
            < 1e-9
        )
        assert placed[role]["source"] == "sim"


def test_operator_override_and_note_are_stored(files, tmp_path):
    db = tmp_path / "t.sqlite"
    first = sorted(load_plan(files["plan"]).trials, key=lambda t: t.order)[0].trial_id
    # The sim locator sees every object, so the automatic outcome is never 'unknown': a real override.
    op = ScriptedOperator({first: load_answers_entry("unknown", "tag fell off")}, log=None)
    _run(files, db, operator=op, max_trials=1)
    row = TrialStore(db).trial_rows()[0]
    assert row["trial_id"] == first and row["operator_outcome"] == "unknown" and row["final_outcome"] == "unknown"
    assert row["auto_outcome"] != "unknown" and row["note"] == "tag fell off"


def load_answers_entry(outcome, note):
    from trials.real.operator import Decision

    return Decision(outcome, note)


class _AbortAt(AutoOperator):
    """Aborts (like the q key) at the ``at``-th poll, i.e. in the middle of a policy loop."""

    def __init__(self, at: int, pause_at: int | None = None):
        super().__init__(log=None)
        self.at, self.pause_at, self.n = at, pause_at, 0

    def poll(self):
        self.n += 1
        if self.n == self.pause_at:
            return "pause"
        return "abort" if self.n == self.at else None


def test_abort_discards_the_trial_in_progress_and_resume_skips_done_trials(files, tmp_path):
    db = tmp_path / "t.sqlite"
    plan = load_plan(files["plan"])
    ordered = [t.trial_id for t in sorted(plan.trials, key=lambda t: t.order)]
    # Trial 1 ends after at most max_steps polls (or earlier on reach), so poll max_steps + 2 is inside trial 2.
    summary = _run(
        files, db, operator=_AbortAt(plan.max_steps + 2), on_ready=lambda r, w: setattr(r, "stop_on_reach", False)
    )
    assert summary.aborted and summary.committed == ordered[:1]
    store = TrialStore(db)
    assert [r["trial_id"] for r in store.trial_rows()] == ordered[:1]
    frames = db.parent / "frames" / "s"
    assert (frames / ordered[0]).is_dir() and not (frames / ordered[1]).exists()
    summary = _run(files, db, max_trials=2)
    assert summary.already_done == 1 and summary.committed == ordered[1:3]
    assert [r["trial_id"] for r in TrialStore(db).trial_rows()] == ordered[:3]


def test_pause_restarts_the_trial(files, tmp_path):
    db = tmp_path / "t.sqlite"
    summary = _run(
        files,
        db,
        operator=_AbortAt(at=-1, pause_at=3),
        max_trials=1,
        on_ready=lambda r, w: setattr(r, "stop_on_reach", False),
    )
    assert not summary.aborted and len(summary.committed) == 1
    store = TrialStore(db)
    row = store.trial_rows()[0]
    steps = store.steps("s", row["trial_id"])
    assert row["n_steps"] == len(steps) == load_plan(files["plan"]).max_steps
    assert [s["step"] for s in steps] == list(range(len(steps)))


def test_a_changed_plan_is_refused_on_resume(files, tmp_path):
    db = tmp_path / "t.sqlite"
    _run(files, db, max_trials=1)
    changed = tmp_path / "plan.yaml"
    changed.write_text(files["plan"].read_text() + "\n# edited\n")
    with pytest.raises(SessionMismatch, match="original plan"):
        run_session(
            SessionOptions(
                hardware=files["hw"], policy=files["policy"], plan=changed, session="s", db=db, rate_limit=False
            ),
            operator=AutoOperator(log=None),
        )


def test_resume_with_another_policy_is_refused_naming_both_files(files, tmp_path):
    db = tmp_path / "t.sqlite"
    _run(files, db, max_trials=1)
    other = straight_ahead_onnx(tmp_path / "other.onnx")
    with pytest.raises(SessionMismatch) as err:
        run_session(
            SessionOptions(
                hardware=files["hw"], policy=other, plan=files["plan"], session="s", db=db, rate_limit=False
            ),
            operator=AutoOperator(log=None),
        )
    msg = str(err.value)
    assert f"policy: sha256 {file_sha256(files['policy'])[:12]}... ({files['policy']}) at the session's start" in msg
    assert f"now sha256 {file_sha256(other)[:12]}... ({other})" in msg
    assert len(TrialStore(db).trial_rows()) == 1


def test_resume_with_an_edited_hardware_yaml_warns_and_records_the_run(files, tmp_path):
    db = tmp_path / "t.sqlite"
    _run(files, db, max_trials=1)
    hw = tmp_path / "hw.yaml"
    hw.write_text(files["hw"].read_text() + "# moved the camera cable\n")
    logged = []
    run_session(
        SessionOptions(
            hardware=hw, policy=files["policy"], plan=files["plan"], session="s", db=db, rate_limit=False, max_trials=1
        ),
        operator=AutoOperator(log=None),
        log=logged.append,
    )
    assert any("hardware YAML" in line and "since the last run" in line for line in logged), logged
    store = TrialStore(db)
    runs = store.con.execute("SELECT id, hardware_text FROM runs ORDER BY id").fetchall()
    assert len(runs) == 2 and runs[1]["hardware_text"].endswith("# moved the camera cable\n")
    assert [r["run_id"] for r in store.trial_rows()] == [runs[0]["id"], runs[1]["id"]]
    # sim cells are in the table frame by construction; it is stored like an estimated one
    np.testing.assert_array_equal(store.stored_T_base_table("s"), np.eye(4))


def test_estimated_table_frame_is_stored_and_reused_on_resume(tmp_path, monkeypatch):
    """Without --table-frame the frame is estimated once, at the session's start; a resume reuses the stored one."""
    from types import SimpleNamespace

    from sim.geometry import make_T, rot_z
    from trials.real import session as session_mod
    from trials.real.store import SessionInfo

    T_est = make_T(rot_z(0.4), np.array([0.3, -0.1, 0.02]))
    estimates = []
    monkeypatch.setattr(session_mod, "load_registry", lambda path: "registry")
    monkeypatch.setattr(session_mod, "load_T_tcp_cam", lambda path: np.eye(4))
    monkeypatch.setattr(TagLocator, "observe", lambda self, frame: {})
    monkeypatch.setattr(
        TagLocator, "estimate_T_base_table", staticmethod(lambda obs, T_tcp, T_tcp_cam: estimates.append(1) or T_est)
    )
    hw = SimpleNamespace(T_tcp_cam="hand_eye.yaml")
    camera = SimpleNamespace(intrinsics=None, read=lambda: None)
    arm = SimpleNamespace(tcp_pose=lambda: np.eye(4))
    store = TrialStore(tmp_path / "t.sqlite")
    logged = []

    def start(stored):
        loc, T = session_mod._tag_locator(hw, camera, arm, "objects.yaml", None, stored, logged.append)
        info = SessionInfo(
            name="s",
            plan_sha256="a" * 64,
            plan_text="",
            hardware_text="",
            policy_path="p.onnx",
            policy_sha256="b" * 64,
            software_version="0",
            git_commit="c",
            devices={},
            calibration={},
            T_base_table=T,
        )
        store.open_session(info)
        return loc, T

    _, T = start(store.stored_T_base_table("s"))
    assert estimates == [1] and "estimated from the registry's table tags" in logged[-1]
    loc, T2 = start(store.stored_T_base_table("s"))  # the resume
    assert estimates == [1] and "not re-estimated" in logged[-1]
    np.testing.assert_array_equal(T2, T_est)
    np.testing.assert_array_equal(loc.T_base_table, T_est)


def test_answers_list_is_keyed_by_run_order_across_a_resume(files, tmp_path):
    db = tmp_path / "t.sqlite"
    ordered = [t.trial_id for t in sorted(load_plan(files["plan"]).trials, key=lambda t: t.order)]
    answers = tmp_path / "answers.yaml"
    answers.write_text("- {note: first}\n- {outcome: unknown, note: second}\n- {note: third}\n")
    for _ in range(3):  # one trial per sitting: every resume must read the next entry, not entry 0 again
        run_session(_opts(files, db, answers=answers, max_trials=1), log=None)
    rows = {r["trial_id"]: r for r in TrialStore(db).trial_rows()}
    assert [rows[t]["note"] for t in ordered[:3]] == ["first", "second", "third"]
    assert rows[ordered[1]]["final_outcome"] == "unknown" and rows[ordered[0]]["operator_outcome"] is None
    answers.write_text("".join(f"- {{note: n{i}}}\n" for i in range(len(ordered) + 1)))
    with pytest.raises(AnswersError, match=f"{len(ordered) + 1} answers for a plan of {len(ordered)} trials"):
        run_session(_opts(files, db, answers=answers), log=None)


def test_closed_operator_input_aborts_like_q(files, tmp_path):
    """EOF on the operator's input (the terminal went away) stops the arm and drops the trial: no traceback."""
    import io

    db = tmp_path / "t.sqlite"
    first = sorted(load_plan(files["plan"]).trials, key=lambda t: t.order)[0].trial_id
    seen = {}
    op = TerminalOperator(stdin=io.StringIO(""), stdout=io.StringIO())  # a pipe already at its end
    summary = _run(files, db, operator=op, on_ready=lambda r, w: seen.setdefault("runner", r))
    assert summary.aborted and summary.abort_reason == "operator input closed" and not summary.committed
    assert TrialStore(db).trial_rows() == [] and not (db.parent / "frames" / "s" / first).exists()
    events = list(seen["runner"].arm.events)
    assert (events[-1].action, events[-1].reason) == ("stopped", "session aborted (operator input closed)")


def test_cli_exits_3_when_the_operator_input_closes(files, tmp_path):
    from typer.testing import CliRunner

    from trials.cli.main import app

    db = tmp_path / "t.sqlite"
    r = CliRunner().invoke(
        app,
        [
            "trial",
            "run",
            "--hardware",
            str(files["hw"]),
            "--policy",
            str(files["policy"]),
            "--plan",
            str(files["plan"]),
            "--session",
            "s",
            "--db",
            str(db),
            "--no-rate-limit",
        ],
        input="",
    )
    assert r.exit_code == 3, r.output
    assert r.exception is None or isinstance(r.exception, SystemExit)
    assert "aborted (operator input closed)" in r.output and TrialStore(db).trial_rows() == []


# ---------------------------------------------------------------------- pure pieces
def _obj(role, x, y, yaw):
    from sim.configs import object_poses_world

    T = object_poses_world([[x, y, yaw]])[0]
    return LocatedObject(role, T, T[:3, 3] + [0, 0, 0.05])


def test_placement_issues_words_the_correction():
    planned = {
        "goal": ObjectPlacement(xy_m=(0.1, 0.0), yaw_rad=0.0),
        "adversarial": ObjectPlacement(xy_m=(0.0, 0.2), yaw_rad=0.5),
    }
    located = {
        "goal": _obj("goal", 0.105, 0.0, 0.01),
        "adversarial": _obj("adversarial", 0.0, 0.223, 0.5 + math.radians(12)),
    }
    issues = placement_issues(planned, located, 0.01, math.radians(5))
    assert [i.role for i in issues] == ["adversarial"]
    assert issues[0].message.startswith("adversarial: move 2.3 cm toward -y, rotate -12 deg")
    missing = placement_issues(planned, {"goal": located["goal"]}, 0.01, 0.1)
    assert missing[0].missing and "not seen" in missing[0].message


def test_tag_locator_maps_camera_observations_to_the_table_frame():
    from calibration.registry import ObjectObservation
    from sim.geometry import invert_T, make_T, rot_z

    T_base_table = make_T(rot_z(0.3), np.array([0.5, -0.2, 0.01]))
    T_base_tcp = make_T(rot_z(-1.0), np.array([0.4, 0.1, 0.4]))
    T_tcp_cam = make_T(rot_z(0.1), np.array([0.0, -0.04, -0.06]))
    T_table_obj = make_T(rot_z(0.7), np.array([0.05, 0.1, 0.03]))
    T_cam_obj = invert_T(T_base_tcp @ T_tcp_cam) @ T_base_table @ T_table_obj
    alt = T_cam_obj.copy()
    alt[:3, 3] += 0.01
    obs = {"goal": ObjectObservation("goal", T_cam_obj, (3, 4), 0.2, True, (alt,))}
    loc = TagLocator(None, None, T_tcp_cam, T_base_table).from_observations(obs, T_base_tcp)
    assert set(loc) == {"goal"}
    np.testing.assert_allclose(loc["goal"].T_table_object, T_table_obj, atol=1e-12)
    assert loc["goal"].tag_ids == (3, 4) and loc["goal"].ambiguous and loc["goal"].centers_for_outcome().shape == (2, 3)
    np.testing.assert_allclose(
        TagLocator.estimate_T_base_table(
            {"table": ObjectObservation("table", invert_T(T_base_tcp @ T_tcp_cam) @ T_base_table, (0,), 0.1, False)},
            T_base_tcp,
            T_tcp_cam,
        ),
        T_base_table,
        atol=1e-12,
    )


def test_answers_file_validation(tmp_path):
    p = tmp_path / "a.yaml"
    p.write_text("t1: {outcome: adversarial, note: hit}\nt2: accept\n")
    a = load_answers(p)
    assert a["t1"].outcome == "adversarial" and a["t1"].note == "hit" and a["t2"].outcome is None
    p.write_text("- {outcome: goal}\n- {outcome: sideways}\n")
    with pytest.raises(AnswersError, match=r"entry 1\.outcome: 'sideways'"):
        load_answers(p)
    p.write_text("t1: {outcome: goal, nose: x}\n")
    with pytest.raises(AnswersError, match="unknown keys"):
        load_answers(p)

    class _Plan:
        trials = []

    with pytest.raises(AnswersError, match="not in the plan: t9"):
        ScriptedOperator({"t9": None}, log=None).check_plan(_Plan())


@pytest.mark.parametrize("control_hz,clipped", [(10.0, False), (30.0, True)])
def test_safety_caps_use_the_plans_loop_period_and_warn_when_they_clip_the_policy(tmp_path, control_hz, clipped):
    """The sim hardware YAML says 33 ms (30 Hz) with 0.3 m/s: a 10 mm step cap. At the plan's 10 Hz
    the caps allow the policy's full 20 mm step; at 30 Hz every step is clipped, and the session says so."""
    import yaml

    plan = tmp_path / "plan.yaml"
    doc = yaml.safe_load(small_plan(plan, tmp_path, n_tcp=1, conditions=("clean",)).read_text())
    doc["control_hz"] = control_hz
    plan.write_text(yaml.safe_dump(doc))
    hw = sim_hardware(tmp_path / "hw.yaml")
    assert yaml.safe_load(hw.read_text())["safety"]["control_period_s"] == pytest.approx(1 / 30, rel=0.01)
    seen, logged = {}, []
    run_session(
        SessionOptions(
            hardware=hw,
            policy=straight_ahead_onnx(tmp_path / "ahead.onnx"),
            plan=plan,
            session="s",
            db=tmp_path / "t.sqlite",
            rate_limit=False,
        ),
        operator=AutoOperator(log=None),
        log=logged.append,
        on_ready=lambda runner, world: seen.update(period=runner.arm.limits.control_period_s),
    )
    assert seen["period"] == pytest.approx(1 / control_hz)
    warned = [line for line in logged if "steps are clipped" in line]
    assert bool(warned) == clipped, logged
    with TrialStore(tmp_path / "t.sqlite", create=False) as store:
        (row,) = store.trial_rows()
        statuses = {s["safety_status"] for s in store.steps("s", row["trial_id"])}
    assert ("clipped" in statuses) == clipped, statuses


def test_a_plan_pose_outside_the_workspace_is_refused_before_anything_moves(files, tmp_path):
    import yaml

    from trials.real.runner import PlanOutsideWorkspace

    plan = load_plan(files["plan"])
    z = [p.T_table_tcp.T()[2, 3] for p in plan.tcp_poses]
    doc = yaml.safe_load(files["hw"].read_text())
    doc["safety"]["workspace_max_m"][2] = float(min(z)) + 0.001 if max(z) > min(z) + 0.002 else float(min(z)) - 0.001
    hw = tmp_path / "hw.yaml"
    hw.write_text(yaml.safe_dump(doc))
    db = tmp_path / "t.sqlite"
    with pytest.raises(PlanOutsideWorkspace, match="TCP pose .* outside|outside the safety workspace") as info:
        run_session(
            SessionOptions(
                hardware=hw, policy=files["policy"], plan=files["plan"], session="s", db=db, rate_limit=False
            ),
            operator=AutoOperator(log=None),
        )
    assert "workspace_max_m" in str(info.value) and "TCP pose" in str(info.value)
    with TrialStore(db) as store:
        assert store.session("s") is None  # nothing recorded: the plan was refused before the session opened
