"""Cameras: OpenCV against a fake cv2.VideoCapture, OAK against a fake depthai, replay from files."""

from __future__ import annotations

import logging
import sys
import time

import numpy as np
import pytest

from calibration.intrinsics import CameraIntrinsics
from robot_io.cameras.base import scale_intrinsics
from robot_io.cameras.depthai import DepthAICamera
from robot_io.cameras.opencv import OpenCVCamera, resolve_device
from robot_io.cameras.replay import ReplayCamera
from robot_io.errors import CameraLostError, MissingExtraError, MissingIntrinsicsError, RobotIOError
from tests.robot_io.fakes import FakeCaptureDevice, install_depthai, install_video_capture

CALIB = CameraIntrinsics(np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]]), np.zeros(5), 640, 480)


@pytest.mark.parametrize("size", [(640, 480), (1280, 720), (320, 240)])
def test_opencv_delivers_rgb_frames_of_the_negotiated_size(monkeypatch, size):
    dev = install_video_capture(monkeypatch)
    with OpenCVCamera(0, width=size[0], height=size[1], fourcc="YUYV", intrinsics=CALIB) as cam:
        f = cam.read()
        assert f.rgb.shape == (size[1], size[0], 3) and f.rgb.dtype == np.uint8
        assert (f.rgb[0, 0] == [255, 0, 0]).all()  # BGR from the driver became RGB
        if size[0] * 480 == size[1] * 640:
            K = cam.intrinsics.K
            assert K[0, 2] == pytest.approx((319.5 + 0.5) * size[0] / 640 - 0.5)
            assert K[0, 0] / K[1, 1] == pytest.approx(1.0)  # the same camera, scaled: square pixels stay square
        else:  # 16:9 from a 4:3 calibration is a crop of the sensor: no K describes it
            with pytest.raises(
                MissingIntrinsicsError, match=r"frames are 1280x720 but the intrinsics are for 640x480, another aspect"
            ):
                cam.intrinsics
    assert dev.released.is_set()


def test_opencv_sets_fourcc_before_the_size_and_asks_for_one_buffer(monkeypatch):
    import cv2

    dev = install_video_capture(monkeypatch)
    with OpenCVCamera(0, width=1280, height=720, fps=30, fourcc="MJPG"):
        pass
    props = [p for p, _ in dev.set_calls]
    assert props.index(cv2.CAP_PROP_FOURCC) < props.index(cv2.CAP_PROP_FRAME_WIDTH)
    assert props.index(cv2.CAP_PROP_FOURCC) < props.index(cv2.CAP_PROP_FRAME_HEIGHT)
    assert (cv2.CAP_PROP_BUFFERSIZE, 1.0) in dev.set_calls
    assert dev.opened_with[0][1] == cv2.CAP_V4L2


def test_opencv_warns_about_every_ignored_setting(monkeypatch, caplog):
    install_video_capture(monkeypatch, FakeCaptureDevice(sizes=[(640, 480)], honours_fps=False, fourccs=("YUYV",)))
    with caplog.at_level(logging.WARNING, logger="robot_io.cameras.opencv"):
        with OpenCVCamera(0, width=1920, height=1080, fps=60, fourcc="MJPG") as cam:
            assert cam.read().rgb.shape == (480, 640, 3)
    text = " ".join(r.getMessage() for r in caplog.records)
    for key in ("fourcc=MJPG", "width=1920", "height=1080", "fps=60"):
        assert key in text


def test_opencv_keeps_only_the_newest_frame(monkeypatch):
    install_video_capture(monkeypatch, FakeCaptureDevice(fps=500.0))
    with OpenCVCamera(0) as cam:
        first = cam.read()
        time.sleep(0.1)  # ~50 frames arrive meanwhile
        f = cam.read()
        assert f.seq - first.seq > 5  # the backlog was skipped, not queued
        assert cam.read().seq > f.seq  # and the next read waits for a new frame, not an old one


def test_opencv_reads_never_repeat_a_frame(monkeypatch):
    install_video_capture(monkeypatch, FakeCaptureDevice(fps=300.0))
    with OpenCVCamera(0) as cam:
        seqs = [cam.read().seq for _ in range(20)]
    assert all(b > a for a, b in zip(seqs, seqs[1:]))


def test_opencv_unplugged_camera_raises_camera_lost(monkeypatch):
    dev = FakeCaptureDevice(fps=500.0)
    dev.fail_after = 3
    install_video_capture(monkeypatch, dev)
    with OpenCVCamera(0, timeout_ms=500) as cam:
        with pytest.raises(CameraLostError, match="consecutive failed reads"):
            for _ in range(10):
                cam.read()


def test_opencv_device_paths_and_indices(tmp_path):
    assert resolve_device(2) == 2 and resolve_device("3") == 3
    target = tmp_path / "video7"
    target.write_text("")
    link = tmp_path / "usb-Intel_RealSense-video-index0"
    link.symlink_to(target)
    assert resolve_device(str(link)) == str(target)
    with pytest.raises(CameraLostError, match="does not exist"):
        resolve_device("/dev/v4l/by-id/usb-nothing-here")


def test_opencv_without_calibration_says_where_to_put_it(monkeypatch):
    install_video_capture(monkeypatch)
    with OpenCVCamera(0) as cam:
        with pytest.raises(RobotIOError, match="camera.intrinsics"):
            cam.intrinsics


def test_depthai_builds_the_v3_pipeline_and_reads_device_intrinsics(monkeypatch):
    oak = install_depthai(monkeypatch)
    with DepthAICamera("CAM_A", 640, 400, 30) as cam:
        f = cam.read()
        assert f.rgb.shape == (400, 640, 3) and (f.rgb[0, 0] == [0, 0, 200]).all()
        assert 0.0 <= f.age_s < 1.0
        K = cam.intrinsics.K
        assert K[0, 0] == pytest.approx(0.9 * 640) and cam.intrinsics.width == 640
    assert ("build", "CAM_A") in oak.requested
    assert ("output", (640, 400), "BGR888i", 30.0) in oak.requested
    assert ("queue", 1, False) in oak.requested
    # The host queue must exist before the pipeline starts, or the first frames have nowhere to go.
    assert oak.requested.index(("queue", 1, False)) < oak.requested.index(("start",))
    assert oak.started and oak.stopped


def test_depthai_without_an_oak_attached_is_a_clear_camera_error(monkeypatch):
    oak = install_depthai(monkeypatch)
    oak.attached = False
    with pytest.raises(CameraLostError, match=r"cannot open the OAK camera \(No available devices\).*plugged in"):
        DepthAICamera().connect()


@pytest.mark.parametrize("size", [(1280, 800), (416, 416)])
def test_depthai_frames_of_other_sizes(monkeypatch, size):
    install_depthai(monkeypatch)
    with DepthAICamera("CAM_A", *size) as cam:
        assert cam.read().rgb.shape == (size[1], size[0], 3)


def test_depthai_xlink_error_becomes_camera_lost(monkeypatch):
    oak = install_depthai(monkeypatch)
    oak.fail_after = 2
    with DepthAICamera() as cam:
        cam.read()
        cam.read()
        with pytest.raises(CameraLostError, match="OAK camera lost"):
            cam.read()


def test_depthai_missing_sdk_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "depthai", None)
    with pytest.raises(MissingExtraError, match=r"advobj\[oak\]"):
        DepthAICamera().connect()


def test_replay_plays_a_folder_in_name_order_then_ends(tmp_path):
    from PIL import Image

    for i in range(3):
        Image.fromarray(np.full((24, 32, 3), 40 * i, np.uint8)).save(tmp_path / f"frame_{i:03d}.png")
    with ReplayCamera(tmp_path, intrinsics=scale_intrinsics(CALIB, 32, 24)) as cam:
        vals = [int(cam.read().rgb[0, 0, 0]) for _ in range(3)]
        assert vals == [0, 40, 80]
        with pytest.raises(CameraLostError, match="ended after 3 frames"):
            cam.read()
    with ReplayCamera(tmp_path, loop=True) as cam:
        assert [int(cam.read().rgb[0, 0, 0]) for _ in range(4)] == [0, 40, 80, 0]


def test_replay_plays_a_video_file(tmp_path):
    import cv2

    path = tmp_path / "clip.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (32, 24))
    for i in range(5):
        w.write(np.full((24, 32, 3), (0, 0, 50 * i), np.uint8))  # red ramp, BGR
    w.release()
    with ReplayCamera(path) as cam:
        frames = [cam.read() for _ in range(5)]
    assert frames[0].rgb.shape == (24, 32, 3)
    assert frames[4].rgb[..., 0].mean() > frames[1].rgb[..., 0].mean() + 50  # red channel, RGB order


def test_replay_fps_paces_playback(tmp_path):
    from PIL import Image

    for i in range(4):
        Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(tmp_path / f"{i}.png")
    with ReplayCamera(tmp_path, fps=20.0) as cam:
        t0 = time.monotonic()
        for _ in range(4):
            cam.read()
        assert time.monotonic() - t0 >= 0.14  # 3 periods of 50 ms


def test_replay_bad_paths_are_named(tmp_path):
    with pytest.raises(RobotIOError, match="does not exist"):
        ReplayCamera(tmp_path / "nope").connect()
    with pytest.raises(RobotIOError, match="holds no images"):
        ReplayCamera(tmp_path).connect()
