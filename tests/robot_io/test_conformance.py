"""One conformance suite over every camera and every arm implementation.

Vendor SDKs are faked at their module boundary; the serial arm and the servo-bus arms talk to their
byte-level twins over a pty; the sim devices use the shared sim world.

Every arm runs the TCP tests; the arms a URDF describes (``kinematics()`` not ``None``: the
joint-driven sim arm, the UR and the serial arm given a URDF, the Feetech and Dynamixel bus arms)
also run the joint tests. How close an arm gets to a target is derived from what it reports: whole
encoder ticks for a servo-bus arm, six decimals for the serial protocol, floats for the others.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import torch

from robot_io.arms.base import Arm
from robot_io.arms.serial import SerialArm
from robot_io.arms.servo_bus import BusArm
from robot_io.cameras.base import Camera, Frame
from robot_io.poses import is_valid_pose, pose_step
from robot_io.safety import SafeArm, SafetyRefusal
from sim.ik import TOL_M, TOL_RAD, SceneArm
from sim.kinematics import shipped_arm
from tests.robot_io.fakes import install_depthai, install_ur, install_video_capture, ur5_scene_arm

CAMERAS = ["opencv", "depthai", "sim", "replay"]
#: The arms a URDF describes: these also take joint commands.
JOINT_ARMS = ["sim+joints", "serial+joints", "ur_rtde+joints", "feetech", "dynamixel"]
ARMS = ["sim", "serial", "ur_rtde", *JOINT_ARMS]
#: The serial protocol prints every number with six decimals (docs/serial-protocol.md).
SERIAL_DECIMALS = 6
#: How far each joint turns in the joint tests' positioning move (rad): within every arm's range around its home.
POSITIONING_RAD = 0.1


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


def _panda() -> SceneArm:
    """The shipped Panda, base at the origin, home at test_joint_safety's ready pose (no SO-100 or
    Koch URDF is shipped; the bus arms' tests drive the Panda's chain with servos)."""
    from tests.robot_io.test_joint_safety import PERIOD_S, Q_READY

    return SceneArm(shipped_arm("panda"), np.eye(4), np.eye(4), PERIOD_S, Q_READY.copy())


def _bus_arm(kind: str, request) -> Arm:
    """A servo-bus arm on its twin, one servo per Panda joint at its home position."""
    from robot_io.arms.dynamixel import DynamixelArm
    from robot_io.arms.dynamixel_sim import DynamixelSimulator
    from robot_io.arms.feetech import FeetechArm
    from robot_io.arms.feetech_sim import FeetechSimulator
    from robot_io.arms.servo_bus import SimServo
    from tests.robot_io.test_feetech import centred_joints

    driver, twin = {"feetech": (FeetechArm, FeetechSimulator), "dynamixel": (DynamixelArm, DynamixelSimulator)}[kind]
    scene_arm = _panda()
    joints = centred_joints(scene_arm)
    sim, path = twin.on_pty([SimServo(j.id, position_ticks=j.to_ticks(q)) for j, q in zip(joints, scene_arm.q_home)])
    request.addfinalizer(sim.close)
    # 250 ms per reply: a loaded machine causes no spurious resend (as in test_feetech).
    return driver(path, joints, scene_arm, timeout_ms=250.0)


def make_arm(kind: str, request, monkeypatch) -> Arm:
    """The arm of ``ARMS`` entry ``kind``, not connected."""
    if kind in ("sim", "sim+joints"):
        from robot_io.arms.sim import SimArm

        return SimArm(request.getfixturevalue("fresh_world"), scene_arm=_panda() if kind == "sim+joints" else None)
    if kind in ("serial", "serial+joints"):
        from robot_io.arms.serial_sim import SerialArmSimulator

        ur5 = ur5_scene_arm() if kind == "serial+joints" else None
        sim, path = SerialArmSimulator.on_pty(boot_delay_s=0.02, scene_arm=ur5)
        request.addfinalizer(sim.close)
        return SerialArm(path, timeout_ms=100, kinematics=ur5)
    if kind in ("ur_rtde", "ur_rtde+joints"):
        from robot_io.arms.ur_rtde import URArm
        from tests.robot_io.fakes import FakeURController

        ur5 = ur5_scene_arm() if kind == "ur_rtde+joints" else None
        install_ur(monkeypatch, FakeURController(kinematics=ur5))
        return URArm("10.0.0.2", kinematics=ur5)
    return _bus_arm(kind, request)


@pytest.fixture(params=ARMS)
def arm_kind(request) -> str:
    return request.param


@pytest.fixture
def arm(arm_kind, request, monkeypatch) -> Arm:
    return make_arm(arm_kind, request, monkeypatch)


@pytest.fixture(params=JOINT_ARMS)
def joint_arm(request, monkeypatch) -> Arm:
    return make_arm(request.param, request, monkeypatch)


# ---------------------------------------------------------------------- what an arm reports
def joint_step_rad(arm: Arm) -> np.ndarray:
    """``(n,)`` the step each joint reading comes in: one encoder tick of a servo-bus arm, the
    serial protocol's last decimal, else none (floats)."""
    n = arm.kinematics().n_joints
    if isinstance(arm, BusArm):
        return np.array([2.0 * math.pi / j.ticks_per_rev for j in arm.joints])
    if isinstance(arm, SerialArm):
        return np.full(n, 10.0**-SERIAL_DECIMALS)
    return np.zeros(n)


def pose_rounding(arm: Arm) -> float:
    """How far a reported TCP pose is from the arm's own (m and rad): the serial protocol rounds
    each of its six numbers to its last decimal; the others report floats (a bus arm computes it)."""
    return math.sqrt(3.0) * 0.5 * 10.0**-SERIAL_DECIMALS if isinstance(arm, SerialArm) else 0.0


def fk(scene_arm: SceneArm, q) -> np.ndarray:
    return scene_arm.tcp_pose(torch.as_tensor(np.asarray(q, dtype=np.float64), device=scene_arm.device)).cpu().numpy()


def tcp_spread(scene_arm: SceneArm, q: np.ndarray, dq: np.ndarray) -> tuple[float, float]:
    """``(m, rad)``: how far the TCP can move when each joint ``k`` is off by up to ``dq[k]`` (to first
    order, the sum over joints of the TCP motion that joint alone makes)."""
    T0 = fk(scene_arm, q)
    dm = drad = 0.0
    for k in np.flatnonzero(dq):
        q1 = np.array(q, dtype=np.float64)
        q1[k] += dq[k]
        step_m, step_rad = pose_step(T0, fk(scene_arm, q1))
        dm, drad = dm + step_m, drad + step_rad
    return dm, drad


def tcp_tolerance(arm: Arm) -> tuple[float, float]:
    """``(m, rad)`` within which the arm's measured TCP reaches a reachable TCP target: the IK's
    tolerance (sim.ik; an arm moving its TCP through its joints solves it, the others do better),
    the TCP motion of half a reported step of every joint, and the pose's rounding. For a bus arm
    at the Panda's reach that is about a millimetre; for the others, the IK's tolerance."""
    tol_m, tol_rad = TOL_M, TOL_RAD
    kin = arm.kinematics()
    if kin is not None:
        dm, drad = tcp_spread(kin, arm.joint_positions(), joint_step_rad(arm) / 2.0)
        tol_m, tol_rad = tol_m + dm, tol_rad + drad
    r = pose_rounding(arm)
    return tol_m + r, tol_rad + r


def _wait_near(arm, T, tol=None, timeout_s=2.0):
    """Whether the arm's TCP comes within ``tol`` (default :func:`tcp_tolerance`) of ``T``."""
    tol_m, tol_rad = tcp_tolerance(arm) if tol is None else tol
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        dp, dr = pose_step(arm.tcp_pose(), T)
        if dp <= tol_m and dr <= tol_rad:
            return True
        time.sleep(0.01)
    return False


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
    # Servos report a model number and a firmware version each, and no serial number: a bus arm is
    # identified by its port, its protocol and the servos on it.
    "feetech": {"port": None, "protocol": "feetech-sts", "servo_ids": None, "models": None, "firmwares": None},
    "dynamixel": {"port": None, "protocol": "dynamixel-2.0", "servo_ids": None, "models": None, "firmwares": None},
}
for _kind in JOINT_ARMS:
    ARM_IDENTITY.setdefault(_kind, ARM_IDENTITY.get(_kind.removesuffix("+joints")))


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


def test_arm_identity_is_stable_and_reaches_the_session_record_through_the_safety_layer(arm_kind, arm, limits):
    from trials.real.session import device_identity

    after = _check_identity(arm, ARM_IDENTITY[arm_kind])
    assert _check_identity(arm, ARM_IDENTITY[arm_kind]) == after  # the same on every connection
    if isinstance(arm, BusArm):  # every servo on the bus, by id, with its model
        ids = [j.id for j in arm.servos]
        assert after["servo_ids"] == ",".join(map(str, ids))
        assert [m.split(":")[0] for m in after["models"].split(",")] == [str(i) for i in ids]
    safe = SafeArm(arm, limits)
    assert safe.identity() == after
    assert device_identity(safe) == {"type": arm.name, **after}


def test_the_joint_tests_cover_every_arm_a_urdf_describes(arm_kind, arm):
    assert (arm.kinematics() is not None) == (arm_kind in JOINT_ARMS)


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
        tol = tcp_tolerance(arm)
        assert _wait_near(safe, res.T_cmd, tol)
        assert pose_step(T0, safe.tcp_pose())[0] == pytest.approx(0.005, abs=2 * tol[0])


# ---------------------------------------------------------------------- joint commands
def _assert_tcp_is_fk(arm: Arm) -> None:
    """The arm's TCP is the FK of its joints, within what their readings are rounded to."""
    kin, q = arm.kinematics(), arm.joint_positions()
    T = arm.tcp_pose()
    dm, drad = tcp_spread(kin, q, joint_step_rad(arm) / 2.0)
    r = pose_rounding(arm)
    dp, dr = pose_step(T, fk(kin, q))
    assert dp <= dm + r + 1e-9 and dr <= drad + r + 1e-9, (dp, dr)


def _wait_joints(arm: Arm, q, timeout_s: float = 3.0) -> bool:
    """Whether the arm's joints come to ``q``, each within half its reported step."""
    tol = joint_step_rad(arm) / 2.0 + 1e-9
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if (np.abs(arm.joint_positions() - q) <= tol).all():
            return True
        time.sleep(0.01)
    return False


def test_joint_commands_round_trip_through_the_safety_layer_and_the_tcp_is_their_fk(joint_arm, limits):
    arm = joint_arm
    kin = arm.kinematics()
    n = kin.n_joints
    safe = SafeArm(arm, limits)
    with safe:
        q0 = safe.joint_positions()
        assert q0.shape == (n,) and np.isfinite(q0).all()
        _assert_tcp_is_fk(arm)
        # A positioning move: every joint a little, alternately up and down.
        target = q0 + np.where(np.arange(n) % 2, -1.0, 1.0) * POSITIONING_RAD
        safe.move_joints(target)
        assert _wait_joints(arm, target)
        _assert_tcp_is_fk(arm)
        # One policy step within every cap: sent as commanded.
        q1 = safe.joint_positions()
        step = 0.5 * limits.joints.max_speed_radps * limits.control_period_s
        res = safe.step_joints(q1 - step, time.monotonic())
        assert res.status == "ok"
        np.testing.assert_allclose(res.q_cmd, q1 - step, rtol=0, atol=1e-12)
        assert _wait_joints(arm, res.q_cmd)
        _assert_tcp_is_fk(arm)


def test_a_refused_joint_target_never_reaches_the_driver(joint_arm, limits, monkeypatch):
    arm = joint_arm
    kin = arm.kinematics()
    lo, hi = kin.model.limits.q_min.cpu().numpy(), kin.model.limits.q_max.cpu().numpy()
    sent = []
    for name in ("servo_joints", "move_joints"):
        real = getattr(arm, name)
        monkeypatch.setattr(arm, name, lambda *a, _real=real, _name=name: (sent.append(_name), _real(*a))[1])
    safe = SafeArm(arm, limits)
    with safe:
        q = safe.joint_positions()
        jump = q.copy()  # joint 0 farther than a jump may go, toward the middle of its range
        jump[0] += math.copysign(2 * limits.joints.max_jump_rad, (lo[0] + hi[0]) / 2 - q[0])
        assert lo[0] <= jump[0] <= hi[0]
        for bad in (np.full_like(q, np.nan), np.where(np.arange(q.size) == 1, np.inf, q), q[:-1], jump):
            res = safe.step_joints(bad, time.monotonic())
            assert res.status == "refused" and res.q_cmd is None, res
        for bad in (np.full_like(q, np.nan), q[:-1], np.where(np.arange(q.size) == 0, hi[0] + 0.1, q)):
            with pytest.raises(SafetyRefusal):
                safe.move_joints(bad)
        assert sent == []
        assert _wait_joints(arm, q)  # and nothing moved
        assert safe.step_joints(q, time.monotonic()).status == "ok" and sent == ["servo_joints"]  # the spy sees one
