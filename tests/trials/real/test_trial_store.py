"""The SQLite trial store: WAL, schema round trip, atomic trials, exports, schema version guard."""

import csv
import sqlite3

import numpy as np
import pytest

from trials.real.store import (
    EventRecord,
    ObjectPoseRecord,
    SessionInfo,
    SessionMismatch,
    StepRecord,
    StoreError,
    TrialRecord,
    TrialStore,
)


def _info(name="s1", sha="a" * 64):
    return SessionInfo(
        name=name,
        plan_sha256=sha,
        plan_text="plan: 1",
        hardware_text="hw: 1",
        policy_path="p.onnx",
        policy_sha256="b" * 64,
        software_version="0.1.0",
        git_commit="abc",
        devices={"arm": {"type": "sim"}},
        calibration={"T_tcp_cam": None},
    )


def _T(x):
    T = np.eye(4)
    T[:3, 3] = [x, 0.1, 0.2]
    return T


def _trial(trial_id="t0", n_steps=3, operator=None):
    steps = [
        StepRecord(
            i,
            0.1 * i,
            0.1 * i + 0.01,
            i,
            [0.1 * i] * 6,
            _T(0.01 * i),
            _T(0.01 * i),
            "ok",
            "",
            f"frames/s1/{trial_id}/{i}.png",
        )
        for i in range(n_steps)
    ]
    poses = [
        ObjectPoseRecord("goal", "final", _T(0.3), np.array([0.3, 0.1, 0.05]), (3,), False, 0, "tags"),
        ObjectPoseRecord("adversarial", "final", None, None, (), False, 0, "tags"),
    ]
    return TrialRecord(
        trial_id,
        0,
        "A",
        "cube",
        "adv3d",
        1,
        2,
        ["dim"],
        "c" * 64,
        "2026-01-01T00:00:00Z",
        4.5,
        "max_steps",
        "unknown",
        "not detected: adversarial",
        {"goal": 0.2, "adversarial": None},
        operator,
        "note",
        1,
        False,
        _T(0.02),
        f"frames/s1/{trial_id}",
        steps,
        poses,
        [EventRecord(0.5, "safety", "clipped", "why")],
    )


def test_wal_and_round_trip(tmp_path):
    db = tmp_path / "t.sqlite"
    with TrialStore(db) as store:
        assert store.con.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        assert store.con.execute("PRAGMA synchronous").fetchone()[0] == 2  # FULL
        sid = store.open_session(_info())
        store.commit_trial(sid, _trial("t0"))
        store.commit_trial(sid, _trial("t1", operator="adversarial"))
    with TrialStore(db, create=False) as store:
        assert store.open_session(_info()) == sid  # resume: same plan
        rows = store.trial_rows()
        assert [r["trial_id"] for r in rows] == ["t0", "t1"]
        r0, r1 = rows
        assert r0["session"] == "s1" and r0["tags"] == ["dim"] and r0["n_steps"] == 3
        assert r0["auto_outcome"] == "unknown" and r0["operator_outcome"] is None and r0["final_outcome"] == "unknown"
        assert r1["operator_outcome"] == "adversarial" and r1["final_outcome"] == "adversarial"
        for key in ("env", "shape", "condition", "note", "stop_reason", "started_at", "duration_s"):
            assert key in r0
        steps = store.steps("s1", "t1")
        assert [s["step"] for s in steps] == [0, 1, 2]
        assert steps[2]["cmd_base_x_m"] == pytest.approx(0.02) and steps[2]["action_5"] == pytest.approx(0.2)
        assert store.trial_rows(["other"]) == []
        with pytest.raises(SessionMismatch, match="original plan"):
            store.open_session(_info(sha="d" * 64))


def test_failure_mid_insert_leaves_no_partial_trial(tmp_path):
    store = TrialStore(tmp_path / "t.sqlite")
    sid = store.open_session(_info())
    bad = _trial("t0")
    # A step whose action cannot be converted fails after the trial row and some inserts went in.
    bad.steps.append(StepRecord(9, 0.0, 0.0, 9, ["x"] * 6, None, _T(0), "refused", "r", "f.png"))
    with pytest.raises(ValueError):
        store.commit_trial(sid, bad)
    for table in ("trials", "steps", "object_poses", "events"):
        assert store.con.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0] == 0
    store.commit_trial(sid, _trial("t0"))
    with pytest.raises(StoreError, match="another runner"):
        store.commit_trial(sid, _trial("t0"))  # the same trial twice
    assert len(store.trial_rows()) == 1 and store.integrity_check() == "ok"


def test_export_csv_and_parquet_read_back(tmp_path):
    import pyarrow.parquet as pq

    store = TrialStore(tmp_path / "t.sqlite")
    sid = store.open_session(_info())
    store.commit_trial(sid, _trial("t0"))
    store.commit_trial(sid, _trial("t1", n_steps=2))
    csvs = {p.stem: p for p in store.export_csv(tmp_path / "csv")}
    pqs = {p.stem: p for p in store.export_parquet(tmp_path / "pq")}
    assert set(csvs) == set(pqs) >= {"trials", "steps", "object_poses"}
    with csvs["steps"].open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 5 and rows[0]["trial_id"] == "t0" and rows[0]["session"] == "s1"
    t = pq.read_table(pqs["steps"]).to_pydict()
    assert t["trial_id"] == ["t0"] * 3 + ["t1"] * 2
    np.testing.assert_allclose(t["meas_base_x_m"][:3], [0.0, 0.01, 0.02])
    poses = pq.read_table(pqs["object_poses"]).to_pydict()
    assert poses["found"] == [1, 0, 1, 0] and poses["table_x_m"][1] is None


def test_unknown_schema_version_refused(tmp_path):
    db = tmp_path / "t.sqlite"
    TrialStore(db).close()
    con = sqlite3.connect(db)
    con.execute("UPDATE schema_version SET version = 99")
    con.commit()
    con.close()
    with pytest.raises(StoreError, match="version 99.*upgrade advobj"):
        TrialStore(db)
    other = tmp_path / "other.sqlite"
    con = sqlite3.connect(other)
    con.execute("CREATE TABLE x (a)")
    con.commit()
    con.close()
    with pytest.raises(StoreError, match="not a trial store"):
        TrialStore(other)
    with pytest.raises(StoreError, match="no trial database"):
        TrialStore(tmp_path / "missing.sqlite", create=False)


def _with(info, **changes):
    from dataclasses import replace

    return replace(info, **changes)


def test_resume_refuses_another_policy_or_calibration_file_naming_it(tmp_path):
    info = _with(
        _info(),
        calibration={"T_tcp_cam": "1" * 64, "registry": None},
        config={"calibration_files": {"T_tcp_cam": "calib/hand_eye.yaml", "registry": None}},
    )
    store = TrialStore(tmp_path / "t.sqlite")
    store.open_session(info)
    assert store.check_resume(info) == []  # the same inputs: resumes silently
    with pytest.raises(SessionMismatch) as err:
        store.open_session(_with(info, policy_path="q.onnx", policy_sha256="e" * 64))
    msg = str(err.value)
    assert "policy: sha256 bbbbbbbbbbbb... (p.onnx) at the session's start, now sha256 eeeeeeeeeeee... (q.onnx)" in msg
    assert "calibration T_tcp_cam" not in msg and "start a new --session" in msg
    other_cal = _with(
        info,
        calibration={"T_tcp_cam": "2" * 64, "registry": "3" * 64},
        config={"calibration_files": {"T_tcp_cam": "calib/hand_eye2.yaml", "registry": "objects.yaml"}},
    )
    with pytest.raises(SessionMismatch) as err:
        store.open_session(other_cal)
    msg = str(err.value)
    assert (
        "calibration T_tcp_cam: sha256 111111111111... (calib/hand_eye.yaml) at the session's start, "
        "now sha256 222222222222... (calib/hand_eye2.yaml)"
    ) in msg
    assert "calibration registry: no file at the session's start, now sha256 333333333333... (objects.yaml)" in msg
    assert "policy" not in msg.split("\n")[1]
    assert store.con.execute("SELECT COUNT(*) FROM runs").fetchone()[0] == 1  # refused resumes record no run


def test_resume_with_a_new_version_warns_and_files_trials_under_their_run(tmp_path):
    store = TrialStore(tmp_path / "t.sqlite")
    sid = store.open_session(_info())
    store.commit_trial(sid, _trial("t0"))
    store.close()
    newer = _with(_info(), software_version="0.2.0", git_commit="def", hardware_text="hw: 2")
    store = TrialStore(tmp_path / "t.sqlite")
    warnings = store.check_resume(newer)
    assert len(warnings) == 3 and all(w.startswith("session 's1': ") for w in warnings)
    assert "advobj version 0.1.0 -> 0.2.0" in warnings[0] and "git commit abc -> def" in warnings[1]
    assert "hardware YAML" in warnings[2]
    assert store.open_session(newer) == sid
    store.commit_trial(sid, _trial("t1"))
    runs = store.con.execute("SELECT id, software_version, git_commit, hardware_text FROM runs ORDER BY id").fetchall()
    assert [tuple(r)[1:] for r in runs] == [("0.1.0", "abc", "hw: 1"), ("0.2.0", "def", "hw: 2")]
    by_trial = {r["trial_id"]: r["run_id"] for r in store.trial_rows()}
    assert by_trial == {"t0": runs[0]["id"], "t1": runs[1]["id"]}
    # the session row keeps the provenance of its start; a further resume compares with the last run
    assert store.session("s1")["software_version"] == "0.1.0"
    assert store.check_resume(newer) == []
    cols, rows = store.table("runs")
    assert cols[:2] == ["session", "id"] and len(rows) == 2


def test_table_frame_is_stored_with_the_session(tmp_path):
    from sim.geometry import make_T, rot_z

    T = make_T(rot_z(0.3), np.array([0.5, -0.2, 0.01]))
    store = TrialStore(tmp_path / "t.sqlite")
    assert store.stored_T_base_table("s1") is None
    store.open_session(_with(_info(), T_base_table=T))
    store.close()
    store = TrialStore(tmp_path / "t.sqlite")
    np.testing.assert_array_equal(store.stored_T_base_table("s1"), T)  # lossless through JSON
    store.open_session(_info())  # a resume does not overwrite it
    np.testing.assert_array_equal(store.stored_T_base_table("s1"), T)


def test_version_1_store_is_migrated_keeping_its_trials(tmp_path):
    from trials.real import store as store_mod

    new = tmp_path / "v2.sqlite"
    with TrialStore(new) as store:
        sid = store.open_session(_info())
        store.commit_trial(sid, _trial("t0"))
    # the same content in a version-1 database
    old = tmp_path / "v1.sqlite"
    con = sqlite3.connect(old)
    con.executescript(store_mod._SCHEMA + "INSERT INTO schema_version VALUES (1);")
    con.execute("ATTACH DATABASE ? AS v2", (str(new),))
    for table in ("sessions", "trials", "steps", "object_poses", "events"):
        cols = ", ".join(r[1] for r in con.execute(f"PRAGMA main.table_info({table})"))
        con.execute(f"INSERT INTO main.{table} ({cols}) SELECT {cols} FROM v2.{table}")
    con.commit()
    con.close()
    with TrialStore(old) as store:
        assert store.con.execute("SELECT version FROM schema_version").fetchone()[0] == store_mod.SCHEMA_VERSION
        (run,) = store.con.execute("SELECT * FROM runs").fetchall()
        assert run["software_version"] == "0.1.0" and run["session_id"] == sid
        rows = store.trial_rows()
        assert [(r["trial_id"], r["run_id"], r["n_steps"]) for r in rows] == [("t0", run["id"], 3)]
        assert store.stored_T_base_table("s1") is None and store.integrity_check() == "ok"
        store.open_session(_with(_info(), T_base_table=np.eye(4)))  # a resume stores the frame it uses
        np.testing.assert_array_equal(store.stored_T_base_table("s1"), np.eye(4))
    with TrialStore(old) as store:  # opening a migrated store again changes nothing
        assert store.con.execute("SELECT COUNT(*) FROM runs").fetchone()[0] == 2


def test_devices_are_compared_once_connected_not_before(tmp_path):
    import dataclasses

    connected = {"arm": {"type": "ur_rtde", "host": "ur.local", "serial": "20215300123"}}
    with TrialStore(tmp_path / "t.sqlite") as store:
        store.open_session(dataclasses.replace(_info(), devices=connected))
    with TrialStore(tmp_path / "t.sqlite") as store:
        before = dataclasses.replace(_info(), devices=None)  # a resume, checked before any device connects
        assert store.check_resume(before) == []
        assert store.device_changes(dataclasses.replace(before, devices=connected)) == []
        swapped = {"arm": {**connected["arm"], "serial": "20215300999"}}
        (warning,) = store.device_changes(dataclasses.replace(before, devices=swapped))
        assert "20215300123" in warning and "20215300999" in warning and "runs" in warning


def test_fixed_cameras_frames_round_trip_per_step_and_a_version_6_store_gains_the_column(tmp_path):
    import dataclasses

    from trials.real import store as store_mod
    from trials.real.store import CameraFrameRecord, camera_frame_name

    assert (camera_frame_name(7), camera_frame_name(7, "front")) == ("step_007.png", "step_007_front.png")
    with pytest.raises(Exception, match="camera"):
        camera_frame_name(0, "../up")
    rec = _trial("t0", n_steps=2)
    front = {"front": CameraFrameRecord("frames/s1/t0/step_000_front.png", 41, 0.0125)}
    rec.steps = [dataclasses.replace(rec.steps[0], camera_frames=front), rec.steps[1]]
    db = tmp_path / "t.sqlite"
    with TrialStore(db) as store:
        store.commit_trial(store.open_session(_info()), rec)
        first, second = store.steps("s1", "t0")
        assert first["camera_frames"] == {
            "front": {"frame_ref": "frames/s1/t0/step_000_front.png", "frame_seq": 41, "t_frame_s": 0.0125}
        }
        assert second["camera_frames"] == {} and "camera_frames_json" in store.table("steps")[0]
    # a version-6 store (before fixed cameras) is migrated: its steps keep their rows, with no camera frames
    old = tmp_path / "v6.sqlite"
    with TrialStore(old) as store:
        store.commit_trial(store.open_session(_info()), _trial("t0", n_steps=2))
    con = sqlite3.connect(old)
    con.execute("ALTER TABLE steps DROP COLUMN joints_json")  # version 8's
    con.execute("ALTER TABLE steps DROP COLUMN camera_frames_json")
    con.execute("UPDATE schema_version SET version = 6")
    con.commit()
    con.close()
    with TrialStore(old) as store:
        assert store.con.execute("SELECT version FROM schema_version").fetchone()[0] == store_mod.SCHEMA_VERSION == 8
        assert [(s["camera_frames"], s["joints"]) for s in store.steps("s1", "t0")] == [({}, None), ({}, None)]
