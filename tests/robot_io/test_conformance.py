"""One conformance suite over every camera and every arm implementation.

Vendor SDKs are faked at their module boundary; the serial arm talks to its device simulator over
a pty; the sim devices use the shared sim world.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from robot_io.arms.base import Arm
from robot_io.cameras.base import Camera, Frame
from robot_io.poses import is_valid_pose, pose_step
from robot_io.safety import SafeArm
from tests.robot_io.fakes import install_depthai, install_ur, install_video_capture

CAMERAS = ["opencv", "depthai", "sim", "replay"]
ARMS = ["sim", "serial", "ur_rtde"]


@pytest.fixture(params=CAMERAS)
def camera(request, monkeypatch, tmp_path) -> Camera:
    kind = request.param
    if kind == "opencv":
        from calibration.intrinsics import CameraIntrinsics
        from robot_io.cameras.opencv import OpenCVCamera

        install_video_capture(monkeypatch)
        K = np.array([[500.0, 0, 319.5], [0, 500, 239.5], [0, 0, 1]])
        return OpenCVCamera(0, 640, 480, intrinsics=CameraIntrinsics(K, np.zeros(5), 640, 480))
    if kind == "depthai":
        from robot_io.cameras.depthai import DepthAICamera

        install_depthai(monkeypatch)
        return DepthAICamera("CAM_A", 320, 200)
    if kind == "sim":
        from robot_io.cameras.sim import SimCamera

        return SimCamera(request.getfixturevalue("fresh_world"))
    from PIL import Image

    from calibration.intrinsics import CameraIntrinsics
    from robot_io.cameras.replay import ReplayCamera

    for i in range(5):
        Image.fromarray(np.full((30, 40, 3), i, np.uint8)).save(tmp_path / f"{i}.png")
    K = np.array([[50.0, 0, 19.5], [0, 50, 14.5], [0, 0, 1]])
    return ReplayCamera(tmp_path, intrinsics=CameraIntrinsics(K, np.zeros(5), 40, 30))


@pytest.fixture(params=ARMS)
def arm(request, monkeypatch) -> Arm:
    kind = request.param
    if kind == "sim":
        from robot_io.arms.sim import SimArm

        return SimArm(request.getfixturevalue("fresh_world"))
    if kind == "serial":
        from robot_io.arms.serial import SerialArm
        from robot_io.arms.serial_sim import SerialArmSimulator

        sim, path = SerialArmSimulator.on_pty(boot_delay_s=0.02)
        request.addfinalizer(sim.close)
        return SerialArm(path, timeout_ms=100)
    from robot_io.arms.ur_rtde import URArm

    install_ur(monkeypatch)
    return URArm("10.0.0.2")


def test_camera_lifecycle_and_frames(camera):
    with pytest.raises(RuntimeError, match="before connect"):
        camera.read()
    with camera as cam:
        assert cam.connected
        frames = [cam.read() for _ in range(3)]
        intr = cam.intrinsics
    assert not camera.connected
    for f in frames:
        assert isinstance(f, Frame) and f.rgb.dtype == np.uint8 and f.rgb.ndim == 3 and f.rgb.shape[2] == 3
        assert f.timestamp_s <= time.monotonic() and f.age_s < 5.0
    assert all(b.seq > a.seq for a, b in zip(frames, frames[1:]))
    assert all(b.timestamp_s >= a.timestamp_s for a, b in zip(frames, frames[1:]))
    h, w = frames[0].rgb.shape[:2]
    assert (intr.width, intr.height) == (w, h) and intr.K.shape == (3, 3) and np.isfinite(intr.K).all()


def test_camera_reconnects(camera):
    with camera:
        camera.read()
    with camera:
        assert camera.read().rgb.size > 0


# What identity() must hold once connected (values: exact, or None for "present").
CAMERA_IDENTITY = {
    "opencv": {"device": "0", "node": "0", "backend": "V4L2"},
    "depthai": {"socket": "CAM_A", "serial": "18443010D116631200", "product": "OAK-D-PRO-W-97"},
    "sim": {"serial": "sim"},
    "replay": {"path": None},
}
ARM_IDENTITY = {
    "sim": {"serial": "sim"},
    "serial": {"port": None, "serial": "SIM-0001", "firmware": "advobj-sim-1.0", "protocol": "1"},
    "ur_rtde": {"host": "10.0.0.2", "serial": "20235500042", "model": "UR5"},
}


def _check_identity(device, expected):
    before = device.identity()
    with device:
        after = device.identity()
    for ident in (before, after):
        assert isinstance(ident, dict) and all(isinstance(k, str) and isinstance(v, str) for k, v in ident.items())
    assert before.items() <= after.items()  # connecting only adds what the device reports
    for key, value in expected.items():
        assert key in after and (value is None or after[key] == value), (key, after)
    return after


def test_camera_identity(camera):
    _check_identity(camera, CAMERA_IDENTITY[camera.name])


def test_arm_identity_reaches_the_session_record_through_the_safety_layer(arm, limits):
    from trials.real.session import device_identity

    after = _check_identity(arm, ARM_IDENTITY[arm.name])
    safe = SafeArm(arm, limits)
    assert safe.identity() == after
    assert device_identity(safe)["serial"] == after["serial"]


def _wait_near(arm, T, tol_m=1e-4, timeout_s=2.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        dp, dr = pose_step(arm.tcp_pose(), T)
        if dp < tol_m and dr < 1e-3:
            return True
        time.sleep(0.01)
    return False


def test_arm_lifecycle_pose_and_fault(arm):
    with arm:
        assert arm.connected and arm.fault() is None
        assert is_valid_pose(arm.tcp_pose())
        arm.keepalive()
        arm.stop()
    assert not arm.connected
    assert arm.fault().kind == "connection_lost"


def test_arm_move_to_and_servo_reach_their_targets(arm):
    with arm:
        T = arm.tcp_pose()
        T[0, 3] += 0.01
        arm.move_to(T, 0.1)
        assert _wait_near(arm, T)
        T2 = T.copy()
        T2[1, 3] -= 0.004
        arm.servo(T2, 0.05)
        assert _wait_near(arm, T2)


def test_arm_through_the_safety_layer(arm, limits):
    safe = SafeArm(arm, limits)
    with safe:
        T0 = safe.tcp_pose()
        res = safe.step_delta([0.0, 0.0, 0.005, 0.0, 0.0, 0.0], time.monotonic())
        assert res.status in ("ok", "clipped") and is_valid_pose(res.T_cmd)
        assert _wait_near(safe, res.T_cmd)
        assert pose_step(T0, safe.tcp_pose())[0] == pytest.approx(0.005, abs=2e-4)
