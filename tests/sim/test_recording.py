"""The recording format (sim.recording): round trip, the checks on write and on read, atomic writes."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from sim.geometry import make_T, so3_exp
from sim.recording import (
    MANIFEST_NAME,
    STEPS_NAME,
    RecordedStep,
    RecordingCamera,
    RecordingError,
    is_recording,
    read_recording,
    write_recording,
)

K_WRIST = np.array([[40.0, 0.0, 15.5], [0.0, 41.0, 11.5], [0.0, 0.0, 1.0]])
K_FRONT = np.array([[60.0, 0.0, 23.5], [0.0, 60.0, 15.5], [0.0, 0.0, 1.0]])


def _pose(rng, angle=None) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = rng.uniform(0, math.pi) if angle is None else angle
    return make_T(so3_exp(axis * angle), rng.uniform(-0.8, 0.8, 3))


def _cameras(rng):
    wrist = RecordingCamera("wrist", K_WRIST, np.array([0.1, -0.02, 0.001, 0.0, 0.003]), 32, 24, "tcp", _pose(rng))
    front = RecordingCamera("front", K_FRONT, np.zeros(0), 48, 32, "table", None, _pose(rng))
    return [wrist, front]


def _episode(rng, n, cams, t0=0.0, dt=0.05, gripper=True, offset_s=0.0):
    steps = []
    for k in range(n):
        t = t0 + k * dt
        images = {c.name: rng.integers(0, 256, (c.height, c.width, 3), dtype=np.uint8) for c in cams}
        angle = math.pi - 10.0 ** -rng.integers(1, 9) if k == 1 else None  # one rotation near pi
        steps.append(
            RecordedStep(
                t, images, _pose(rng, angle), float(rng.uniform(0, 0.08)) if gripper else None, {"front": t + offset_s}
            )
        )
    return steps


def _write(path, rng, episodes=None, **kw):
    cams = kw.pop("cameras", None) or _cameras(rng)
    off = kw.pop("offset_s", 0.0)
    if episodes is None:
        episodes = {"a": _episode(rng, 4, cams, offset_s=off), "b": _episode(rng, 3, cams, offset_s=off)}
    opts = {"T_table_base": _pose(rng), "sync_tolerance_s": 0.002, "gripper": "opening_m", "source": {"kind": "test"}}
    opts.update(kw)
    return cams, episodes, write_recording(path, cams, list(episodes.items()), **opts)


def test_a_written_recording_reads_back_frame_by_frame(tmp_path):
    rng = np.random.default_rng(0)
    cams, episodes, rec = _write(tmp_path / "rec", rng, offset_s=0.0015)  # the front camera lags 1.5 ms
    again = read_recording(tmp_path / "rec")
    assert is_recording(tmp_path / "rec")
    assert [e.id for e in again.episodes] == ["a", "b"] and [e.n_frames for e in again.episodes] == [4, 3]
    assert again.episodes[0].duration_s == pytest.approx(0.15)
    assert list(again.cameras) == ["wrist", "front"] and again.gripper == "opening_m"
    assert again.source == {"kind": "test"}
    for cam in cams:
        got = again.cameras[cam.name]
        np.testing.assert_array_equal(got.K, cam.K)
        np.testing.assert_array_equal(got.dist, cam.dist)
        assert (got.width, got.height, got.mount) == (cam.width, cam.height, cam.mount)
        for name in ("T_tcp_cam", "T_table_cam"):
            if getattr(cam, name) is None:
                assert getattr(got, name) is None
            else:
                np.testing.assert_allclose(getattr(got, name), getattr(cam, name), rtol=0, atol=1e-12)
    for ep, steps in episodes.items():
        read = list(again.frames(ep))
        assert len(read) == len(steps)
        for want, got in zip(steps, read):
            assert got.t_s == want.t_s  # bit for bit
            assert got.gripper == want.gripper
            assert got.frame_t_s == {"wrist": want.t_s, "front": want.frame_t_s["front"]}
            np.testing.assert_allclose(got.T_base_tcp, want.T_base_tcp, rtol=0, atol=1e-12)
            for name, img in want.images.items():
                np.testing.assert_array_equal(got.images[name], img)
                assert got.images[name].dtype == np.uint8
        np.testing.assert_array_equal(again.image(ep, 1, "front"), steps[1].images["front"])
    only_front = next(again.frames("a", cameras=["front"]))
    assert list(only_front.images) == ["front"]


def test_the_camera_pose_in_the_table_frame_follows_its_mount(tmp_path):
    rng = np.random.default_rng(1)
    cams, episodes, rec = _write(tmp_path / "rec", rng)
    poses = rec.poses("a")
    T_base_tcp = poses.T_base_tcp  # (N, 4, 4): batch-first
    wrist = rec.T_table_cam("wrist", T_base_tcp)
    np.testing.assert_allclose(wrist, rec.T_table_base @ T_base_tcp @ cams[0].T_tcp_cam, rtol=0, atol=1e-12)
    front = rec.T_table_cam("front", T_base_tcp)
    assert front.shape == (4, 4, 4)
    np.testing.assert_allclose(front, np.broadcast_to(cams[1].T_table_cam, (4, 4, 4)), rtol=0, atol=1e-12)
    # one step: (4, 4) in, (4, 4) out; the wrist camera moves with the arm, the front camera does not
    assert not np.allclose(rec.T_table_cam("wrist", T_base_tcp[0]), rec.T_table_cam("wrist", T_base_tcp[1]))
    np.testing.assert_array_equal(rec.T_table_cam("front", T_base_tcp[0]), rec.T_table_cam("front", T_base_tcp[1]))
    with pytest.raises(RecordingError, match="no camera 'top'"):
        rec.T_table_cam("top", T_base_tcp[0])


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda c: c.update(K=None), "has no intrinsics"),
        (lambda c: c.update(T_tcp_cam=None), r"\(mount tcp\) has no extrinsics: T_tcp_cam missing"),
        (lambda c: c.update(mount="table"), r"\(mount table\) has no extrinsics: T_table_cam missing"),
        (lambda c: c.update(K=np.diag([-1.0, 1.0, 1.0])), "fx, fy > 0"),
        (lambda c: c.update(dist=np.zeros(3)), "distortion coefficients"),
        (lambda c: c.update(name="Wrist Cam"), "camera name"),
        (lambda c: c.update(T_tcp_cam=np.diag([1.0, 1.0, -1.0, 1.0])), "not a proper rotation"),
    ],
)
def test_a_camera_without_intrinsics_or_extrinsics_is_refused_in_one_line(change, message):
    fields = dict(
        name="wrist",
        K=K_WRIST,
        dist=np.zeros(5),
        width=32,
        height=24,
        mount="tcp",
        T_tcp_cam=np.eye(4),
        T_table_cam=None,
    )
    change(fields)
    with pytest.raises(RecordingError, match=message) as err:
        RecordingCamera(**fields)
    assert "\n" not in str(err.value)


def _misaligned(rng, cams):
    steps = _episode(rng, 3, cams)
    steps[2] = steps[2]._replace(frame_t_s={"front": steps[2].t_s + 0.0021})
    return steps


def _backwards(rng, cams):
    steps = _episode(rng, 3, cams)
    steps[2] = steps[2]._replace(t_s=steps[1].t_s, frame_t_s={"front": steps[1].t_s})
    return steps


def _nan_pose(rng, cams):
    steps = _episode(rng, 2, cams)
    T = steps[1].T_base_tcp.copy()
    T[0, 3] = np.nan
    steps[1] = steps[1]._replace(T_base_tcp=T)
    return steps


def _small_image(rng, cams):
    steps = _episode(rng, 2, cams)
    steps[1].images["wrist"] = steps[1].images["wrist"][:-1]
    return steps


def _missing_camera(rng, cams):
    steps = _episode(rng, 2, cams)
    del steps[0].images["front"]
    return steps


def _mm_as_m(rng, cams):
    steps = _episode(rng, 2, cams)
    T = steps[1].T_base_tcp.copy()
    T[:3, 3] = [1200.0, 0.0, 300.0]
    steps[1] = steps[1]._replace(T_base_tcp=T)
    return steps


@pytest.mark.parametrize(
    "make, message",
    [
        (_misaligned, r"step 2: camera front's frame .* 2\.1 ms apart, over the sync tolerance of 2 ms"),
        (_backwards, "t_s does not increase at step 2"),
        (_nan_pose, "step 1: T_base_tcp: contains NaN"),
        (_small_image, r"step 1: camera wrist: a uint8 image of shape \(23, 32, 3\), expected uint8 \(24, 32, 3\)"),
        (_missing_camera, r"step 0: images of cameras \['wrist'\], the recording has \['front', 'wrist'\]"),
        (_mm_as_m, r"within \+-1000 m"),
    ],
)
def test_bad_steps_are_refused_and_nothing_is_left_behind(tmp_path, make, message):
    rng = np.random.default_rng(2)
    cams = _cameras(rng)
    good = _episode(rng, 2, cams)
    with pytest.raises(RecordingError, match=message) as err:
        _write(tmp_path / "new" / "rec", rng, {"ok": good, "bad": make(rng, cams)}, cameras=cams)
    assert "\n" not in str(err.value)
    assert not (tmp_path / "new" / "rec").exists()  # made by the call, removed again
    (tmp_path / "empty").mkdir()
    with pytest.raises(RecordingError):
        _write(tmp_path / "empty", rng, {"ok": good, "bad": make(rng, cams)}, cameras=cams)
    assert list((tmp_path / "empty").iterdir()) == []  # an empty folder given: left empty


def test_a_failing_source_mid_episode_leaves_nothing(tmp_path):
    rng = np.random.default_rng(3)
    cams = _cameras(rng)

    def steps():
        yield from _episode(rng, 2, cams)
        raise OSError("the source broke")

    with pytest.raises(OSError, match="the source broke"):
        write_recording(
            tmp_path / "rec", cams, [("a", _episode(rng, 2, cams)), ("b", steps())], T_table_base=np.eye(4),
            sync_tolerance_s=0.01, gripper="opening_m",
        )  # fmt: skip
    assert not (tmp_path / "rec").exists()


def test_only_a_new_or_empty_folder_is_written_into(tmp_path):
    rng = np.random.default_rng(4)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "notes.txt").write_text("mine")
    with pytest.raises(RecordingError, match="not empty"):
        _write(tmp_path / "full", rng)
    assert [p.name for p in (tmp_path / "full").iterdir()] == ["notes.txt"]
    (tmp_path / "file").write_text("x")
    with pytest.raises(RecordingError, match="not a folder"):
        _write(tmp_path / "file", rng)
    with pytest.raises(RecordingError, match="given twice"):
        cams = _cameras(rng)
        write_recording(
            tmp_path / "twice", cams, [("a", _episode(rng, 1, cams)), ("a", _episode(rng, 1, cams))],
            T_table_base=np.eye(4), sync_tolerance_s=0.01, gripper="opening_m",
        )  # fmt: skip
    with pytest.raises(RecordingError, match="episode id: '../up' is not a safe name"):
        cams = _cameras(rng)
        write_recording(
            tmp_path / "unsafe", cams, [("../up", _episode(rng, 1, cams))], T_table_base=np.eye(4),
            sync_tolerance_s=0.01, gripper="opening_m",
        )  # fmt: skip
    assert not (tmp_path / "up").exists() and not (tmp_path / "unsafe").exists()


# ---------------------------------------------------------------------- the checks on read
@pytest.fixture()
def recording(tmp_path):
    _write(tmp_path / "rec", np.random.default_rng(5))
    return tmp_path / "rec"


def _edit_manifest(rec, change):
    path = rec / MANIFEST_NAME
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def _edit_steps(rec, episode, row, column, value):
    path = rec / "episodes" / episode / STEPS_NAME
    lines = [line.split(",") for line in path.read_text().splitlines()]
    lines[row + 1][lines[0].index(column)] = value
    path.write_text("\n".join(",".join(line) for line in lines) + "\n")


def _symlink_out(rec):
    frame = rec / "episodes" / "a" / "wrist" / "000001.png"
    outside = rec.parent / "outside.png"
    frame.rename(outside)
    frame.symlink_to(outside)


def _grey_frame(rec):
    from PIL import Image

    Image.fromarray(np.zeros((24, 32), np.uint8)).save(rec / "episodes" / "b" / "wrist" / "000002.png")


def _wrong_size(rec):
    from PIL import Image

    Image.fromarray(np.zeros((24, 30, 3), np.uint8)).save(rec / "episodes" / "b" / "front" / "000000.png")


@pytest.mark.parametrize(
    "damage, file, message",
    [
        (lambda r: _edit_manifest(r, lambda d: d.update(version=2)), MANIFEST_NAME, "format version 2; this advobj"),
        (lambda r: _edit_manifest(r, lambda d: d["cameras"][0].pop("K")), MANIFEST_NAME, "has no intrinsics"),
        (
            lambda r: _edit_manifest(r, lambda d: d["cameras"][1].pop("T_table_cam")),
            MANIFEST_NAME,
            "camera 'front' .mount table. has no extrinsics",
        ),
        (lambda r: _edit_manifest(r, lambda d: d["episodes"][0].update(n_frames=5)), "a/steps.csv", "4 steps, the"),
        (lambda r: (r / MANIFEST_NAME).write_text("{"), MANIFEST_NAME, "not valid JSON"),
        (lambda r: (r / MANIFEST_NAME).unlink(), "rec", "recording.json missing"),
        (lambda r: _edit_steps(r, "a", 2, "t_front_s", "0.1031"), "a/steps.csv", "frames and poses do not line up"),
        (lambda r: _edit_steps(r, "a", 2, "t_s", "0.05"), "a/steps.csv", "t_s does not increase at step 2"),
        (lambda r: _edit_steps(r, "b", 1, "rx_rad", "nan"), "b/steps.csv", "rx_rad: step 1 is nan"),
        (lambda r: _edit_steps(r, "b", 1, "gripper", "wide"), "b/steps.csv", "gripper: step 1: 'wide' is not"),
        (lambda r: (r / "episodes" / "b" / "front" / "000001.png").unlink(), "b/front/000001.png", "missing"),
        (_symlink_out, "rec", "outside"),
        (_grey_frame, "b/wrist/000002.png", "mode L, expected an RGB PNG"),
        (_wrong_size, "b/front/000000.png", "30x24 px, the camera's is 48x32"),
    ],
)
def test_a_damaged_recording_is_refused_in_one_line_naming_the_file(recording, damage, file, message):
    damage(recording)
    with pytest.raises(RecordingError, match=message) as err:
        read_recording(recording)
    text = str(err.value)
    assert "\n" not in text and file in text


def test_a_frame_changed_after_reading_is_refused_when_read(recording):
    rec = read_recording(recording)
    _wrong_size(recording)
    with pytest.raises(RecordingError, match="30x24 px"):
        rec.image("b", 0, "front")
    with pytest.raises(RecordingError, match="steps 0..2, not 3"):
        rec.image("b", 3, "front")
    with pytest.raises(RecordingError, match="no episode 'c'"):
        list(rec.frames("c"))


# ---------------------------------------------------------------------- numerical edges
ONE = [
    RecordingCamera("wrist", np.array([[2.0, 0, 0.5], [0, 2.0, 0.5], [0, 0, 1]]), np.zeros(0), 2, 2, "tcp", np.eye(4))
]


def _tiny(times, frame_times, tolerance_s, path):
    steps = [
        RecordedStep(t, {"wrist": np.full((2, 2, 3), k % 256, np.uint8)}, np.eye(4), None, {"wrist": f})
        for k, (t, f) in enumerate(zip(times, frame_times))
    ]
    return write_recording(path, ONE, [("e", steps)], T_table_base=np.eye(4), sync_tolerance_s=tolerance_s)


increasing = st.lists(
    st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False), min_size=1, max_size=6, unique=True
).map(sorted)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    times=increasing,
    tolerance_s=st.sampled_from([0.0, 1e-9, 1e-4, 0.5]),
    k=st.integers(0, 5),
    sign=st.sampled_from([-1.0, 1.0]),
)
@example(times=[0.0, 1.0, 2.0], tolerance_s=1e-4, k=1, sign=1.0)
@example(times=[-3.5, 1e6], tolerance_s=0.0, k=0, sign=-1.0)
def test_times_read_back_bit_for_bit_and_the_tolerance_is_exact_at_its_edge(
    tmp_path_factory, times, tolerance_s, k, sign
):
    """A frame exactly at the tolerance from its pose is accepted, the next float beyond it refused,
    at any time scale (1e-6 s to 1e6 s); times survive the round trip exactly."""
    k = k % len(times)
    frames = list(times)
    frames[k] = times[k] + sign * tolerance_s
    if not np.all(np.diff(frames) > 0) or abs(frames[k] - times[k]) > tolerance_s:
        return  # the offset collides with a neighbour, or rounding moved it beyond the tolerance
    path = tmp_path_factory.mktemp("edge")
    rec = _tiny(times, frames, tolerance_s, path / "ok")
    poses = rec.poses("e")
    assert poses.t_s.tolist() == times and poses.frame_t_s["wrist"].tolist() == frames
    beyond = list(times)
    beyond[k] = np.nextafter(frames[k], sign * np.inf)
    if abs(beyond[k] - times[k]) <= tolerance_s or not np.all(np.diff(beyond) > 0):
        return
    with pytest.raises(RecordingError, match="do not line up in time"):
        _tiny(times, beyond, tolerance_s, path / "beyond")
    assert not (path / "beyond").exists()


def test_timestamps_that_do_not_increase_strictly_are_refused_at_any_scale(tmp_path):
    for scale in (1e-9, 1.0, 1e6):
        t = [0.0, scale, scale]
        with pytest.raises(RecordingError, match="t_s does not increase at step 2"):
            _tiny(t, t, 0.0, tmp_path / f"same{scale:g}")
    t = [0.0, 1e-300, 2e-300]  # tiny but increasing: fine
    assert read_recording(_tiny(t, t, 0.0, tmp_path / "tiny").path).poses("e").t_s.tolist() == t
