"""LeRobot v2.1 and v3.0 datasets, built here with pyarrow and PyAV, imported into recordings and
checked frame by frame: decoded frames within the codec's error of the originals (and nearest to
their own step's), poses and gripper values exactly the table's, times the table's."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.intrinsics import CameraIntrinsics
from sim.geometry import invert_T, make_T, so3_exp, so3_log
from sim.recording import read_recording
from tests.trials.recordings.lerobot_datasets import (
    CAMERAS,
    FPS,
    K_FRONT,
    K_WRIST,
    T_BASE_TABLE,
    T_TABLE_CAM,
    T_TCP_CAM,
    build_v21,
    build_v30,
    calibration_files,
)
from trials.recordings.importer import ImportJob, run_import
from trials.recordings.lerobot import LeRobotError, PoseColumns, poses_from_vectors

CODEC_MEAN_ABS = 6.0  # mean |decoded - original| per channel value of these smooth frames (crf 8 / mpeg4)


def _pose(d) -> np.ndarray:
    return make_T(so3_exp(np.asarray(d["rotvec_rad"], dtype=np.float64)), np.asarray(d["translation_m"]))


def _job(src, out, files, **kw):
    args = dict(
        source="lerobot",
        src=src,
        out=out,
        pose_key="observation.state",
        pose_layout="xyz_rotvec",
        gripper_key="observation.state",
        gripper_index=6,
        intrinsics={"wrist": files["wrist_intrinsics"], "front": files["front_intrinsics"]},
        extrinsics={"wrist": files["T_tcp_cam"], "front": files["T_table_cam"]},
        table_frame=files["T_base_table"],
    )
    return ImportJob(**{**args, **kw})


def _check_frame_by_frame(rec, truth, episodes):
    assert [e.id for e in rec.episodes] == [f"episode_{i:06d}" for i in episodes]
    for i in episodes:
        state = truth[i]["state"].astype(np.float64)  # the table's float32 values, exactly
        steps = list(rec.frames(f"episode_{i:06d}"))
        assert len(steps) == len(state)
        for k, step in enumerate(steps):
            assert step.t_s == float(np.float32(k / FPS))
            np.testing.assert_allclose(
                step.T_base_tcp, make_T(so3_exp(state[k, 3:6]), state[k, :3]), rtol=0, atol=1e-12
            )
            assert step.gripper == state[k, 6]
            for cam in rec.cameras:
                assert abs(step.frame_t_s[cam] - step.t_s) <= rec.sync_tolerance_s
                originals = np.stack(truth[i]["frames"][cam]).astype(np.float64)
                err = np.abs(originals - step.images[cam].astype(np.float64)).mean(axis=(1, 2, 3))
                assert err[k] < CODEC_MEAN_ABS, (i, k, cam, err[k])
                assert int(np.argmin(err)) == k  # its own step's frame, not a neighbour's


def _check_cameras(rec):
    wrist, front = rec.cameras["wrist"], rec.cameras["front"]
    assert (wrist.width, wrist.height, wrist.mount) == (32, 24, "tcp")
    np.testing.assert_array_equal(wrist.K, K_WRIST)
    np.testing.assert_allclose(wrist.T_tcp_cam, _pose(T_TCP_CAM), atol=1e-12)
    assert (front.width, front.height, front.mount) == (48, 32, "table")
    # calibrated at 96 x 64, the frames are 48 x 32: the intrinsics are scaled with the image
    np.testing.assert_allclose(front.K, CameraIntrinsics(K_FRONT, np.zeros(5), 96, 64).scaled(48, 32).K, atol=1e-12)
    np.testing.assert_allclose(front.T_table_cam, _pose(T_TABLE_CAM), atol=1e-12)
    np.testing.assert_allclose(rec.T_table_base, invert_T(_pose(T_BASE_TABLE)), atol=1e-12)
    T = rec.poses(rec.episodes[0].id).T_base_tcp[1]
    np.testing.assert_allclose(
        rec.T_table_cam("wrist", T), invert_T(_pose(T_BASE_TABLE)) @ T @ _pose(T_TCP_CAM), atol=1e-12
    )


def test_a_v21_dataset_imports_frame_by_frame(tmp_path):
    truth = build_v21(tmp_path / "v21")
    rec = run_import(_job(tmp_path / "v21", tmp_path / "rec", calibration_files(tmp_path / "cal")))
    assert rec.source["codebase_version"] == "v2.1" and rec.gripper == "state"
    assert rec.sync_tolerance_s == 1e-4  # LeRobot's own
    _check_cameras(rec)
    _check_frame_by_frame(read_recording(tmp_path / "rec"), truth, [0, 1])


def test_a_v30_dataset_with_episodes_sharing_files_imports_frame_by_frame(tmp_path):
    """Episodes 0 and 1 share a table, episode 2 has its own; every camera's episodes share one
    video, so each episode's frames are found from its from_timestamp (a seek inside the file)."""
    truth = build_v30(tmp_path / "v30")
    rec = run_import(_job(tmp_path / "v30", tmp_path / "rec", calibration_files(tmp_path / "cal")))
    assert rec.source["codebase_version"] == "v3.0"
    _check_cameras(rec)
    _check_frame_by_frame(rec, truth, [0, 1, 2])


def test_episodes_and_cameras_can_be_chosen(tmp_path):
    truth = build_v30(tmp_path / "v30")
    files = calibration_files(tmp_path / "cal")
    rec = run_import(
        _job(
            tmp_path / "v30",
            tmp_path / "rec",
            files,
            episodes=(2, 0),
            cameras=("observation.images.front",),
            intrinsics={"front": files["front_intrinsics"]},
            extrinsics={"front": files["T_table_cam"]},
            gripper_key=None,
            gripper_index=None,
        )
    )
    assert list(rec.cameras) == ["front"] and rec.gripper is None
    assert [e.id for e in rec.episodes] == ["episode_000002", "episode_000000"]
    step = list(rec.frames("episode_000002"))[3]
    assert step.gripper is None and set(step.images) == {"front"}
    err = np.abs(step.images["front"].astype(float) - truth[2]["frames"]["front"][3]).mean()
    assert err < CODEC_MEAN_ABS


# ---------------------------------------------------------------------- pose layouts
def _quaternion_xyzw(rotvec: np.ndarray) -> np.ndarray:
    angle = np.linalg.norm(rotvec, axis=1, keepdims=True)
    axis = np.where(angle > 0, rotvec / np.where(angle > 0, angle, 1.0), [[1.0, 0.0, 0.0]])
    return np.concatenate([axis * np.sin(angle / 2), np.cos(angle / 2)], 1)


rotvecs = st.tuples(
    st.floats(-1, 1, allow_nan=False), st.floats(-1, 1, allow_nan=False), st.floats(-1, 1, allow_nan=False)
).filter(lambda v: math.hypot(*v) > 1e-3)
angles = st.one_of(st.sampled_from([0.0, 1e-12, 1e-6, math.pi - 1e-9, math.pi]), st.floats(0, math.pi))


@settings(max_examples=200, deadline=None)
@given(axis=rotvecs, angle=angles, sign=st.sampled_from([1.0, -1.0]), p=st.floats(-2, 2, allow_nan=False))
def test_quaternion_layouts_give_the_rotation_vectors_pose_at_every_angle(axis, angle, sign, p):
    """Either quaternion order, q or -q (the same rotation), angles from 0 to pi: the same
    T_base_tcp as the rotation vector gives, to 1e-12."""
    a = np.asarray(axis) / np.linalg.norm(axis)
    r = (a * angle)[None]
    xyz = np.array([[p, -p / 2, 0.3]])
    q = sign * _quaternion_xyzw(r)
    want = poses_from_vectors(np.concatenate([xyz, r], 1), PoseColumns("s", "xyz_rotvec"), "t")
    xyzw = poses_from_vectors(np.concatenate([xyz, q], 1), PoseColumns("s", "xyz_quat_xyzw"), "t")
    wxyz = poses_from_vectors(
        np.concatenate([[[9.0]], xyz, q[:, [3, 0, 1, 2]]], 1), PoseColumns("s", "xyz_quat_wxyz", 1), "t"
    )
    np.testing.assert_allclose(xyzw, want, rtol=0, atol=1e-12)
    np.testing.assert_allclose(wxyz, want, rtol=0, atol=1e-12)
    np.testing.assert_allclose(so3_log(xyzw[0, :3, :3]), so3_log(want[0, :3, :3]), atol=1e-6)


@pytest.mark.parametrize(
    "vectors, layout, message",
    [
        ([[0, 0, 0, 0, 0, 0, 2.0]], "xyz_quat_xyzw", "row 0: a quaternion of norm 2, not a unit quaternion"),
        (
            [[0, 0, 0, 0, 0, 0]],
            "xyz_quat_wxyz",
            "6 values per row; --pose-layout xyz_quat_wxyz from --pose-start 0 needs 7",
        ),
        ([[0, 0, 0, 0, 0, 0], [0, np.nan, 0, 0, 0, 0]], "xyz_rotvec", "row 1 holds NaN or inf"),
        ([[0, 0, 0, np.inf, 0, 0]], "xyz_rotvec", "row 0 holds NaN or inf"),
    ],
)
def test_a_pose_column_that_holds_no_pose_is_refused_in_one_line(vectors, layout, message):
    with pytest.raises(LeRobotError, match=message) as err:
        poses_from_vectors(np.asarray(vectors, dtype=np.float64), PoseColumns("observation.state", layout), "f.parquet")
    assert "\n" not in str(err.value) and "f.parquet: observation.state" in str(err.value)


def test_the_cameras_are_named_as_policies_bind_them(tmp_path):
    """observation.images.<camera> -> <camera>, the name a LeRobot policy's input binds to."""
    from trials.recordings.lerobot import LeRobotDataset

    build_v21(tmp_path / "v21", lengths=(2,))
    ds = LeRobotDataset(tmp_path / "v21")
    assert ds.cameras == {cam: f"observation.images.{cam}" for cam in CAMERAS}
    assert ds.select_cameras(["front"]) == {"front": "observation.images.front"}
    with pytest.raises(LeRobotError, match="--camera: 'side' is not a camera of"):
        ds.select_cameras(["side"])
