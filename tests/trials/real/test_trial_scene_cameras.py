"""A cell with a fixed scene camera: a two-camera policy runs real-trial sessions on the sim twin,
every frame it reads is committed with its trial and checked for age, and the cell's bad inputs
(a camera it lacks, a frame of the wrong size, a fixed camera without extrinsics) are one line."""

from __future__ import annotations

import sqlite3
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from calibration.io import save_scene_camera_pose
from robot_io.cameras.base import Camera, Frame
from tests.trials.real.trial_session_helpers import REPO, sim_hardware, small_plan, two_camera_onnx
from trials.real.operator import AutoOperator
from trials.real.plan import load_plan
from trials.real.session import SessionOptions, run_session
from trials.real.stage import SimStage
from trials.real.store import TrialStore

TWO_CAMERAS = REPO / "scenes" / "two-cameras.yaml"


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    d = tmp_path_factory.mktemp("scene_cameras")
    return {
        "dir": d,
        "policy": two_camera_onnx(d / "two_cameras.onnx"),
        "plan": small_plan(d / "plan.yaml", d, n_tcp=2, max_steps=4, conditions=("clean", "adv3d"), scene=TWO_CAMERAS),
        "hw": sim_hardware(d / "cell.yaml", scene_cameras={"front": {"type": "sim"}}),
    }


def _opts(cell, db, **changes) -> SessionOptions:
    values = dict(hardware=cell["hw"], policy=cell["policy"], plan=cell["plan"], session="s", db=db, rate_limit=False)
    return SessionOptions(**{**values, **changes})


def test_a_two_camera_policy_runs_sessions_and_both_cameras_frames_are_committed(cell, tmp_path):
    db = tmp_path / "t.sqlite"
    runners = []
    summary = run_session(_opts(cell, db), operator=AutoOperator(log=None), on_ready=lambda r, w: runners.append(r))
    planned = load_plan(cell["plan"]).trials
    assert not summary.aborted and sorted(summary.committed) == sorted(t.trial_id for t in planned)
    runner = runners[0]
    assert runner.cameras == ("wrist", "front") and list(runner.scene_cameras) == ["front"]
    with TrialStore(db, create=False) as store:
        sess = store.session("s")
        assert '"scene_cameras": {"front": {"type": "sim", "serial": "sim", "camera": "front"}}' in sess["devices_json"]
        assert '"cameras": ["wrist", "front"]' in sess["config_json"]
        rows = store.trial_rows()
        assert {r["stop_reason"].split(":")[0] for r in rows} <= {"max_steps", "reached"}
        for row in rows:
            steps = store.steps("s", row["trial_id"])
            assert len(steps) == row["n_steps"] > 0
            for s in steps:
                wrist = iio.imread(db.parent / s["frame_ref"])
                front = s["camera_frames"]["front"]
                assert set(s["camera_frames"]) == {"front"} and front["frame_ref"] == s["frame_ref"].replace(
                    ".png", "_front.png"
                )
                # beside the wrist frame, at the front camera's own size (the wrist renders at the policy's 32 px)
                assert wrist.shape == (32, 32, 3) and iio.imread(db.parent / front["frame_ref"]).shape == (128, 128, 3)
                assert 0.0 <= front["t_frame_s"] <= s["t_command_s"]
            assert [s["camera_frames"]["front"]["frame_seq"] for s in steps] == sorted(
                {s["camera_frames"]["front"]["frame_seq"] for s in steps}
            )  # one new front frame per step
    with sqlite3.connect(db) as con:  # the export carries the column as stored
        (n,) = con.execute("SELECT COUNT(*) FROM steps WHERE camera_frames_json IS NULL").fetchone()
    assert n == 0


def test_the_sim_stage_shows_the_trial_texture_to_the_fixed_camera_too(cell):
    from robot_io.config import build_world, load_hardware_config
    from sim.spec import load_spec

    plan = load_plan(cell["plan"])
    clean = next(t for t in plan.trials if t.condition == "clean")
    adv = next(t for t in plan.trials if t.condition == "adv3d" and t.object_layout == clean.object_layout)
    views = {}
    for cameras in (("front",), ()):
        world = build_world(load_hardware_config(cell["hw"]))
        world.set_scene(load_spec(TWO_CAMERAS))
        stage = SimStage(world, plan, cell["plan"].parent, cameras=cameras)
        try:
            for trial in (clean, adv):
                stage.prepare(trial)
                views[cameras, trial.condition] = world.render(camera="front", with_ids=False).rgb.astype(int)
        finally:
            stage.close()
            world.close()
    # same layout, same fixed pose: the textured cube differs from the benign one in the front view ...
    assert np.abs(views[("front",), "adv3d"] - views[("front",), "clean"]).max() > 50
    # ... which only the texture on the front camera's renderer makes it show
    np.testing.assert_array_equal(views[(), "adv3d"], views[(), "clean"])


class LaggingCamera(Camera):
    """A fixed camera whose driver hands its frames out ``lag_s`` after taking them (a stalled USB
    queue): the wrapped camera's frames, stamped when they were taken."""

    name = "lagging"

    def __init__(self, inner, lag_s: float):
        super().__init__()
        self.inner, self.lag_s, self.label = inner, float(lag_s), inner.label

    def _open(self) -> None:
        pass

    def _close(self) -> None:
        pass

    def _read(self) -> Frame:
        f = self.inner.read()
        return Frame(f.rgb, f.timestamp_s - self.lag_s, f.seq)

    def identity(self) -> dict[str, str]:
        return self.inner.identity()

    @property
    def intrinsics(self):
        return self.inner.intrinsics


def test_a_stale_scene_camera_frame_stops_the_step_through_the_safety_layer(cell, tmp_path):
    db = tmp_path / "t.sqlite"

    def stall_front(runner, world):
        runner.scene_cameras["front"] = LaggingCamera(runner.scene_cameras["front"], lag_s=1.0)
        runner.scene_cameras["front"].connect()

    summary = run_session(_opts(cell, db, max_trials=1), operator=AutoOperator(log=None), on_ready=stall_front)
    assert len(summary.committed) == 1
    with TrialStore(db, create=False) as store:
        (row,) = store.trial_rows()
        (step,) = store.steps("s", row["trial_id"])  # the first command was refused: the trial stopped there
        events = store.con.execute("SELECT action, reason FROM events WHERE kind = 'safety'").fetchall()
    assert (
        row["stop_reason"].startswith("refused: camera 'front' frame is 1")
        and "ms old (limit 500 ms)" in (row["stop_reason"])
    )
    assert step["safety_status"] == "refused" and step["cmd_base_x_m"] is None  # NaN: nothing sent
    assert ("refused", step["safety_reason"]) in [tuple(e) for e in events]
    assert (db.parent / step["camera_frames"]["front"]["frame_ref"]).is_file()  # what it acted on is kept


# ----------------------------------------------------------------------------- one line, exit 2
def _trial_run(monkeypatch, capsys, hw, policy, plan, db):
    from trials.cli.main import main

    argv = ["trial", "run", "--hardware", hw, "--policy", policy, "--plan", plan, "--session", "s", "--db", db]
    monkeypatch.setattr(sys, "argv", ["advobj", *map(str, argv), "--auto-confirm", "--no-rate-limit"])
    with pytest.raises(SystemExit) as ex:
        main()
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert ex.value.code == 2 and len(lines) == 1, lines
    return lines[0]


def test_a_policy_reading_a_camera_the_cell_lacks_is_one_line_before_anything_is_written(
    cell, tmp_path, monkeypatch, capsys
):
    hw = sim_hardware(tmp_path / "wrist_only.yaml")
    db = tmp_path / "run" / "t.sqlite"
    line = _trial_run(monkeypatch, capsys, hw, cell["policy"], cell["plan"], db)
    assert line == (
        f"error: --policy: {cell['policy']} reads camera 'front', which the hardware config {hw} does not have "
        "(its cameras: wrist); add it under scene_cameras"
    )
    assert not db.parent.exists()


def test_a_sim_scene_camera_rendering_another_size_than_the_policy_takes_is_one_line(
    cell, tmp_path, monkeypatch, capsys
):
    policy = two_camera_onnx(tmp_path / "front64.onnx", front_px=64)
    db = tmp_path / "run" / "t.sqlite"
    line = _trial_run(monkeypatch, capsys, cell["hw"], policy, cell["plan"], db)
    assert line == (
        f"error: --policy: {policy} takes 64x64 px images of camera 'front', but the sim scene renders camera "
        "'front' at 128x128 px: give the scene camera that size"
    )
    assert not db.parent.exists()


def test_a_fixed_camera_without_extrinsics_is_one_line_before_anything_is_written(cell, tmp_path, monkeypatch, capsys):
    (tmp_path / "rec").mkdir()
    hw = sim_hardware(
        tmp_path / "cell.yaml", scene_cameras={"front": {"type": "replay", "path": str(tmp_path / "rec")}}
    )
    db = tmp_path / "run" / "t.sqlite"
    line = _trial_run(monkeypatch, capsys, hw, cell["policy"], cell["plan"], db)
    assert line.startswith(f"error: {hw}: invalid hardware config: scene_cameras.front.replay: T_table_cam missing")
    assert not db.parent.exists()


def test_a_real_fixed_camera_delivering_frames_of_another_size_is_one_line_and_records_no_session(
    cell, tmp_path, monkeypatch, capsys
):
    rec = tmp_path / "rec"
    rec.mkdir()
    for i in range(3):
        iio.imwrite(rec / f"{i:03d}.png", np.full((96, 96, 3), 60 * i, np.uint8))
    pose = save_scene_camera_pose(tmp_path / "front_pose.yaml", np.eye(4), 128, 128)
    hw = sim_hardware(
        tmp_path / "cell.yaml", scene_cameras={"front": {"type": "replay", "path": str(rec), "T_table_cam": str(pose)}}
    )
    db = tmp_path / "run" / "t.sqlite"
    line = _trial_run(monkeypatch, capsys, hw, cell["policy"], cell["plan"], db)
    assert line == (
        f"error: camera 'front': a 96x96 px frame, but its pose file {pose} holds for 128x128 px: set the camera to "
        "deliver that size, or calibrate it again at this one"
    )
    # read when the devices connect, after the session's lock (so the database exists) but before the
    # session is recorded: no session row, no run record, no frame
    with TrialStore(db, create=False) as store:
        assert store.session_names() == []
    assert not (db.parent / "frames").exists()


def test_a_missing_pose_file_of_a_fixed_camera_is_one_line_naming_it(cell, tmp_path, monkeypatch, capsys):
    (tmp_path / "rec").mkdir()
    missing = tmp_path / "nowhere.yaml"
    hw = sim_hardware(
        tmp_path / "cell.yaml",
        scene_cameras={"front": {"type": "replay", "path": str(tmp_path / "rec"), "T_table_cam": str(missing)}},
    )
    db = tmp_path / "run" / "t.sqlite"
    line = _trial_run(monkeypatch, capsys, hw, cell["policy"], cell["plan"], db)
    assert line.startswith(f"error: --hardware: scene_cameras.front.T_table_cam: {missing}: <file>: cannot read")
    assert not db.parent.exists()


def test_a_wrist_only_policy_on_a_cell_with_a_fixed_camera_opens_only_the_wrist_camera(tmp_path):
    from tests.trials.real.trial_session_helpers import tiny_onnx

    hw = sim_hardware(tmp_path / "cell.yaml", scene_cameras={"front": {"type": "sim"}})
    plan = small_plan(tmp_path / "plan.yaml", tmp_path, n_tcp=1, max_steps=2, conditions=("clean",), scene=TWO_CAMERAS)
    db = tmp_path / "t.sqlite"
    runners = []
    policy = tiny_onnx(tmp_path / "p.onnx")
    opts = SessionOptions(hardware=hw, policy=policy, plan=plan, session="s", db=db, rate_limit=False)
    run_session(opts, operator=AutoOperator(log=None), on_ready=lambda r, w: runners.append(r))
    assert runners[0].cameras == ("wrist",) and runners[0].scene_cameras == {}
    with TrialStore(db, create=False) as store:
        sess = store.session("s")
        (row,) = store.trial_rows()
        assert all(s["camera_frames"] == {} for s in store.steps("s", row["trial_id"]))
    assert "scene_cameras" not in sess["devices_json"] and "T_table_cam" not in sess["calibration_json"]
    assert sorted(p.name for p in (db.parent / Path(row["frames_dir"])).iterdir()) == [
        f"step_{k:03d}.png" for k in range(row["n_steps"])
    ]


def test_a_plan_on_a_scene_with_a_fixed_camera_keeps_only_layouts_that_camera_sees():
    from sim.configs import object_local_centers, object_poses_world
    from sim.spec import load_spec
    from trials.real.plan import make_plan

    spec = load_spec(TWO_CAMERAS)
    narrow = spec.with_updates(scene_cameras=[{**spec.scene_cameras[0].model_dump(), "fov_deg": 22.0}])
    cam = narrow.scene_cameras[0]
    local = object_local_centers(narrow)

    def seen(layout) -> bool:
        xyy = np.zeros((len(narrow.objects), 3))
        for role, p in layout.objects.items():
            xyy[narrow.object_index(role)] = (*p.xy_m, p.yaw_rad)
        T = object_poses_world(xyy)
        centers = np.einsum("kij,kj->ki", T[:, :3, :3], local) + T[:, :3, 3]
        p = (centers - cam.T_table_cam[:3, 3]) @ cam.T_table_cam[:3, :3]  # in the camera frame
        uv = (cam.K() @ (p / p[:, 2:3]).T).T[:, :2]
        return bool(np.all(p[:, 2] > 0) and np.all((uv >= -0.5) & (uv <= cam.width - 0.5)))

    def layouts(s):
        return make_plan(s, 3, ["A"], ["cube"], ["clean"], {}, n_tcp_poses=1, n_object_layouts=6).object_layouts

    kept, drawn = layouts(narrow), layouts(narrow.with_updates(scene_cameras=[]))
    assert all(seen(x) for x in kept) and not all(seen(x) for x in drawn)  # the narrow view drops some draws


def test_the_docs_cell_snippet_is_a_valid_hardware_config():
    import yaml

    from robot_io.config import hardware_config_from_dict

    text = (REPO / "docs" / "real-trials.md").read_text()
    section = text[text.index("## A cell with a fixed scene camera") :]
    snippet = section[section.index("```yaml") + len("```yaml") : section.index("```", section.index("```yaml") + 7)]
    data = yaml.safe_load(snippet)
    cell = {"camera": {"type": "opencv", "device": 0}, "arm": {"type": "ur_rtde", "host": "ur"}, **data}
    cfg = hardware_config_from_dict({**cell, "safety": {"workspace_min_m": [0, 0, 0], "workspace_max_m": [1, 1, 1]}})
    front = cfg.scene_cameras["front"]
    assert (
        front.type == "opencv"
        and str(front.T_table_cam) == "front_pose.yaml"
        and (front.width, front.height)
        == (
            640,
            480,
        )
    )


def test_a_fixed_camera_off_the_scene_s_pose_or_field_of_view_is_warned_about(cell, tmp_path):
    from calibration.intrinsics import CameraIntrinsics, save_camera_yaml
    from robot_io.config import build_scene_camera, hardware_config_from_dict
    from sim.geometry import make_T
    from sim.spec import load_spec
    from trials.real.session import load_trial_policy, scene_camera_warnings

    spec = load_spec(TWO_CAMERAS)
    trained = spec.camera_spec("front")
    policy = load_trial_policy(cell["policy"])
    (tmp_path / "rec").mkdir()
    iio.imwrite(tmp_path / "rec" / "0.png", np.zeros((256, 256, 3), np.uint8))

    def warnings(T_table_cam, K):
        save_camera_yaml(tmp_path / "cam.yaml", CameraIntrinsics(K, np.zeros(5), 256, 256))
        save_scene_camera_pose(tmp_path / "pose.yaml", T_table_cam, 256, 256)
        front = {"type": "replay", "path": "rec", "intrinsics": "cam.yaml", "T_table_cam": "pose.yaml"}
        hw = hardware_config_from_dict(
            {
                "camera": {"type": "sim"},
                "arm": {"type": "sim"},
                "scene_cameras": {"front": front},
                "safety": {"workspace_min_m": [0, 0, 0], "workspace_max_m": [1, 1, 1]},
            },
            base=tmp_path,
        )
        return scene_camera_warnings("front", build_scene_camera(hw, "front"), policy, spec, hw)

    K = trained.K(256, 256)  # the scene camera's field of view at twice its size: as trained
    assert warnings(trained.T_table_cam, K) == []
    moved = trained.T_table_cam @ make_T(np.eye(3), [0.05, 0.0, 0.0])
    (w,) = warnings(moved, K)
    assert w.startswith("camera 'front' stands 5.0 cm and 0.0 deg from the scene's camera of that name")
    K_wide = K.copy()
    K_wide[:2, :2] *= 0.6
    (w,) = warnings(trained.T_table_cam, K_wide)
    assert w.startswith("camera 'front' (256x256, preprocess center_crop to 128x128): field of view")
