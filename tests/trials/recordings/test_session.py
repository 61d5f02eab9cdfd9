"""A trial session run on the project's own sim cell (SimCamera + SimArm, a real ONNX policy on
onnxruntime, a real SQLite store), imported into a recording: every frame the session stored, at
the pose the sim camera really rendered it from, with the cell's calibration."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from PIL import Image

from robot_io.cameras.sim import SimCamera
from sim.geometry import make_T, so3_exp
from sim.recording import RecordingError, read_recording
from sim.spec import default_scene
from tests.trials.real.trial_session_helpers import sim_hardware, small_plan, straight_ahead_onnx
from trials.real.operator import AutoOperator
from trials.real.session import SessionOptions, run_session
from trials.real.store import TrialStore
from trials.recordings.calib import RecordImportError
from trials.recordings.importer import ImportJob, run_import

MOUNT = {"translation_m": [0.0, -0.04, -0.06], "rotvec_rad": [0.0, 0.0, 0.05]}  # not the scene's own mount


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    """A two-trial session on a sim cell whose hardware YAML names a hand-eye file, as a real cell's
    does; ``rendered`` holds, per frame the sim camera delivered, the TCP pose it rendered from."""
    d = tmp_path_factory.mktemp("session")
    hand_eye = d / "T_tcp_cam.yaml"
    hand_eye.write_text(yaml.safe_dump({"T_tcp_cam": MOUNT}))
    hw = sim_hardware(d / "hw.yaml")
    data = yaml.safe_load(hw.read_text())
    data["T_tcp_cam"] = hand_eye.name  # resolved beside the hardware YAML
    hw.write_text(yaml.safe_dump(data))
    opts = SessionOptions(
        hardware=hw,
        policy=straight_ahead_onnx(d / "p.onnx"),
        plan=small_plan(d / "plan.yaml", d, n_tcp=2, n_layouts=1, max_steps=5, conditions=("clean",)),
        session="day1",
        db=d / "trials.sqlite",
        rate_limit=False,
    )
    rendered = _run_noting_renders(opts)
    return {"dir": d, "db": d / "trials.sqlite", "hand_eye": hand_eye, "rendered": rendered}


def _run_noting_renders(opts: SessionOptions) -> dict:
    """Run the session ``opts``; ``{frame seq: T_world_tcp}`` of every frame the sim camera rendered."""
    rendered = {}
    original = SimCamera._read

    def read(self):
        frame = original(self)
        rendered[frame.seq] = self.world.T_world_tcp.copy()
        return frame

    SimCamera._read = read
    try:
        run_session(opts, operator=AutoOperator(log=None), log=None)
    finally:
        SimCamera._read = original
    return rendered


def _files(folder):
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.rglob("*") if p.is_file()
    }


def test_a_session_imports_every_frame_at_the_pose_it_was_taken_from(cell, tmp_path):
    before = _files(cell["dir"])
    rec = run_import(ImportJob(source="session", src=cell["db"], out=tmp_path / "rec"))
    assert _files(cell["dir"]) == before  # read through the store: the database and its frames unchanged
    with TrialStore(cell["db"], create=False) as store:
        trials = store.trial_rows(["day1"])
        steps = {t["trial_id"]: store.steps("day1", t["trial_id"]) for t in trials}
    assert [e.id for e in rec.episodes] == [t["trial_id"] for t in trials]
    assert [e.n_frames for e in rec.episodes] == [t["n_steps"] for t in trials]
    assert rec.source["kind"] == "session" and rec.source["session"] == "day1"
    cam = rec.cameras["wrist"]
    assert (cam.width, cam.height, cam.mount) == (32, 32, "tcp")
    np.testing.assert_allclose(cam.K, default_scene().camera.K(32, 32), atol=1e-12)
    np.testing.assert_allclose(
        cam.T_tcp_cam, make_T(so3_exp(np.array(MOUNT["rotvec_rad"])), MOUNT["translation_m"]), atol=1e-12
    )
    np.testing.assert_allclose(rec.T_table_base, np.eye(4), atol=1e-12)  # the sim's base is the table frame
    n = 0
    for t in trials:
        for k, step in enumerate(rec.frames(t["trial_id"])):
            row = steps[t["trial_id"]][k]
            stored = np.asarray(Image.open(cell["db"].parent / row["frame_ref"]).convert("RGB"))
            np.testing.assert_array_equal(step.images["wrist"], stored)
            # the pose the sim camera really rendered this frame from (the world is the base frame)
            np.testing.assert_allclose(step.T_base_tcp, cell["rendered"][row["frame_seq"]], rtol=0, atol=1e-9)
            assert step.frame_t_s["wrist"] == row["t_frame_s"]
            n += 1
    assert n == sum(t["n_steps"] for t in trials) > 2


def test_the_session_is_named_and_its_calibration_checked(cell, tmp_path):
    with pytest.raises(RecordImportError, match="--session: no session 'day2'"):
        run_import(ImportJob(source="session", src=cell["db"], session="day2", out=tmp_path / "a"))
    other = tmp_path / "other_hand_eye.yaml"
    other.write_text(yaml.safe_dump({"T_tcp_cam": {"translation_m": [0.0, 0.0, 0.0], "rotvec_rad": [0.0, 0.0, 0.0]}}))
    with pytest.raises(RecordImportError, match="not the hand-eye file the session was recorded with") as err:
        run_import(ImportJob(source="session", src=cell["db"], extrinsics={"wrist": other}, out=tmp_path / "b"))
    assert "\n" not in str(err.value)
    # the recorded file itself, named on the command line (it could have moved): accepted
    rec = run_import(
        ImportJob(source="session", src=cell["db"], extrinsics={"wrist": cell["hand_eye"]}, out=tmp_path / "c")
    )
    assert len(rec.episodes) == 2
    with pytest.raises(RecordImportError, match="--intrinsics front=...: no camera 'front' is imported"):
        run_import(ImportJob(source="session", src=cell["db"], intrinsics={"front": other}, out=tmp_path / "d"))
    assert not any((tmp_path / x).exists() for x in "abd")


def test_a_session_whose_frame_is_gone_leaves_no_recording(cell, tmp_path):
    import shutil

    db = tmp_path / "copy" / "trials.sqlite"
    shutil.copytree(cell["dir"], db.parent)
    with TrialStore(db, create=False) as store:
        trial = store.trial_rows(["day1"])[-1]
        last = store.steps("day1", trial["trial_id"])[-1]
    (db.parent / last["frame_ref"]).unlink()
    with pytest.raises(RecordImportError, match="a frame of the session is missing"):
        run_import(ImportJob(source="session", src=db, out=tmp_path / "rec"))
    assert not (tmp_path / "rec").exists()  # the first trial was written, then all of it removed
    with pytest.raises(RecordingError, match="not a recording"):
        read_recording(tmp_path / "rec")


def test_a_session_with_a_fixed_scene_camera_imports_both_cameras(tmp_path):
    """A two-camera policy's session on the sim cell (the wrist camera and the scene's fixed 'front'
    camera): both cameras' frames, the front camera fixed in the table frame where the scene puts it."""
    from sim.spec import load_spec
    from tests.trials.real.trial_session_helpers import REPO, two_camera_onnx

    scene = REPO / "scenes" / "two-cameras.yaml"
    opts = SessionOptions(
        hardware=sim_hardware(tmp_path / "cell.yaml", scene_cameras={"front": {"type": "sim"}}),
        policy=two_camera_onnx(tmp_path / "two.onnx"),
        plan=small_plan(tmp_path / "plan.yaml", tmp_path, n_tcp=1, max_steps=3, conditions=("clean",), scene=scene),
        session="s",
        db=tmp_path / "t.sqlite",
        rate_limit=False,
    )
    run_session(opts, operator=AutoOperator(log=None), log=None)
    rec = run_import(ImportJob(source="session", src=tmp_path / "t.sqlite", out=tmp_path / "rec"))
    assert list(rec.cameras) == ["wrist", "front"]
    front, spec = rec.cameras["front"], load_spec(scene).camera_spec("front")
    assert front.mount == "table" and front.T_tcp_cam is None
    np.testing.assert_allclose(front.T_table_cam, spec.T_table_cam, atol=1e-12)
    np.testing.assert_allclose(front.K, spec.K(front.width, front.height), atol=1e-12)
    with TrialStore(tmp_path / "t.sqlite", create=False) as store:
        (trial,) = store.trial_rows(["s"])
        steps = store.steps("s", trial["trial_id"])
    got = list(rec.frames(trial["trial_id"]))
    assert len(got) == len(steps) > 0
    for step, row in zip(got, steps):
        for cam, ref, t in (
            ("wrist", row["frame_ref"], row["t_frame_s"]),
            ("front", row["camera_frames"]["front"]["frame_ref"], row["camera_frames"]["front"]["t_frame_s"]),
        ):
            stored = np.asarray(Image.open(tmp_path / ref).convert("RGB"))
            np.testing.assert_array_equal(step.images[cam], stored)
            assert step.frame_t_s[cam] == t
    # the fixed camera stands still while the wrist camera moves with the arm
    a, b = got[0].T_base_tcp, got[-1].T_base_tcp
    np.testing.assert_array_equal(rec.T_table_cam("front", a), rec.T_table_cam("front", b))
    assert not np.allclose(rec.T_table_cam("wrist", a), rec.T_table_cam("wrist", b))


PANDA_SCENE = Path(__file__).resolve().parents[3] / "scenes" / "panda-joint.yaml"


@pytest.fixture(scope="module")
def joint_cell(tmp_path_factory):
    """A joint-space policy's two-trial session on the sim cell of ``scenes/panda-joint.yaml`` (its sim
    arm is the scene's Panda), whose first start is given as joint positions only; ``rendered`` holds,
    per frame the sim camera delivered, the TCP pose it rendered from."""
    from sim.policies.checkpoint import save_checkpoint
    from sim.spec import load_spec
    from tests.attack.test_joint_attack import joint_policy
    from tests.policy_zoo import card_of
    from trials.real.plan import load_plan, save_plan

    d = tmp_path_factory.mktemp("joint_session")
    spec = load_spec(PANDA_SCENE)
    arm = spec.arm.scene_arm()
    policy = joint_policy(spec)
    save_checkpoint(d / "ck", policy, card_of(policy))
    plan = load_plan(small_plan(d / "plan.yaml", d, n_tcp=2, max_steps=3, conditions=("clean",), scene=PANDA_SCENE))
    first, *rest = plan.tcp_poses
    res = arm.solve_start(torch.as_tensor(first.T_table_tcp.T())[None])
    assert bool(res.converged[0])
    q = res.q[0].numpy().copy()
    q[0] += 0.05  # another start than the drawn pose's: only the joints say where it is
    start = first.model_copy(update={"T_table_tcp": None, "joint_positions": tuple(float(v) for v in q)})
    plan_path = save_plan(plan.model_copy(update={"tcp_poses": [start, *rest]}), d / "plan.yaml")
    hw = sim_hardware(d / "hw.yaml")
    data = yaml.safe_load(hw.read_text())
    data["safety"]["max_frame_age_ms"] = 60_000.0  # a loaded machine's first inference is no frame-age test
    hw.write_text(yaml.safe_dump(data))
    opts = SessionOptions(
        hardware=hw, policy=d / "ck", plan=plan_path, session="j", db=d / "trials.sqlite", rate_limit=False
    )
    rendered = _run_noting_renders(opts)
    return {"dir": d, "db": d / "trials.sqlite", "rendered": rendered, "arm": arm, "q_start": q, "plan": plan_path}


def test_a_session_whose_start_is_given_as_joints_imports_its_first_frame_at_their_tcp(joint_cell, tmp_path):
    from robot_io.poses import pose_step
    from sim.ik import TOL_M, TOL_RAD

    rec = run_import(ImportJob(source="session", src=joint_cell["db"], out=tmp_path / "rec"))
    with TrialStore(joint_cell["db"], create=False) as store:
        trials = store.trial_rows(["j"])
        steps = {t["trial_id"]: store.steps("j", t["trial_id"]) for t in trials}
    assert [e.id for e in rec.episodes] == [t["trial_id"] for t in trials] and len(trials) == 2
    arm, q = joint_cell["arm"], joint_cell["q_start"]
    T_joints = arm.tcp_pose(torch.as_tensor(q, dtype=torch.float64)).numpy()
    for t in trials:
        got = list(rec.frames(t["trial_id"]))
        rendered = [joint_cell["rendered"][row["frame_seq"]] for row in steps[t["trial_id"]]]
        assert len(got) == len(rendered) == t["n_steps"] > 1
        # after the first, each frame at the pose measured after the step before: where the camera rendered it
        for step, T in zip(got[1:], rendered[1:]):
            np.testing.assert_allclose(step.T_base_tcp, T, rtol=0, atol=1e-9)
        if t["tcp_pose"] == 0:  # the joints-only start: the first frame at their TCP, forward kinematics
            np.testing.assert_allclose(got[0].T_base_tcp, T_joints, rtol=0, atol=1e-9)
            np.testing.assert_allclose(got[0].T_base_tcp, rendered[0], rtol=0, atol=1e-9)
        else:  # a TCP start the runner solved by IK: its planned pose, within the IK's tolerance of the reached one
            dp, dr = pose_step(got[0].T_base_tcp, rendered[0])
            assert dp <= TOL_M and dr <= TOL_RAD


def test_a_joints_only_start_without_the_arms_kinematics_is_refused_naming_the_trial(joint_cell, tmp_path):
    """The same session with its stored plan's scene dropped: the sim arm is then the built-in scene's,
    which has no arm, so nothing places that start's TCP and the import is refused in one line naming
    the trial."""
    import shutil
    import sqlite3

    db = tmp_path / "copy" / "trials.sqlite"
    shutil.copytree(joint_cell["dir"], db.parent)
    con = sqlite3.connect(db)
    (text,) = con.execute("SELECT plan_text FROM sessions WHERE name = 'j'").fetchone()
    plan = yaml.safe_load(text)
    plan["scene"] = None
    con.execute("UPDATE sessions SET plan_text = ? WHERE name = 'j'", (yaml.safe_dump(plan),))
    con.commit()
    con.close()
    with TrialStore(db, create=False) as store:
        (trial,) = [t["trial_id"] for t in store.trial_rows(["j"]) if t["tcp_pose"] == 0]
    with pytest.raises(
        RecordImportError,
        match=rf"^session 'j' in .*: trial {trial}: its start \(tcp_poses\.0\) is given as joint_positions only, "
        rf"and the session's sim arm \(its scene {default_scene().name!r} has no arm\) has no kinematics to place",
    ) as err:
        run_import(ImportJob(source="session", src=db, out=tmp_path / "rec"))
    assert "\n" not in str(err.value)
    assert not (tmp_path / "rec").exists()


def test_start_poses_take_a_start_given_both_ways_at_its_tcp_pose_when_no_kinematics_places_the_joints(
    joint_cell,
):
    from trials.real.plan import load_plan
    from trials.recordings.session import start_poses

    plan = load_plan(joint_cell["plan"])
    second = plan.tcp_poses[1]
    both = second.model_copy(update={"joint_positions": tuple(joint_cell["q_start"])})  # joints unchecked here
    plan = plan.model_copy(update={"tcp_poses": [plan.tcp_poses[0], both]})
    T_base_table = make_T(so3_exp(np.array([0.0, 0.0, 0.3])), [0.1, -0.2, 0.05])
    poses = start_poses(plan, [{"trial_id": "x", "tcp_pose": 1}], T_base_table, None, "an arm")
    np.testing.assert_allclose(poses["x"], T_base_table @ second.T_table_tcp.T(), rtol=0, atol=1e-15)
    # with the arm's kinematics the joints are checked against the pose, as the runner checked them
    with pytest.raises(RecordImportError, match=r"^trial plan: tcp_poses\.1 \(trial x\): joint_positions put the TCP"):
        start_poses(plan, [{"trial_id": "x", "tcp_pose": 1}], np.eye(4), joint_cell["arm"], "an arm")
