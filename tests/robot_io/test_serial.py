"""Serial arm driver against the device simulator, real bytes over a pseudo-terminal."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from robot_io.arms.base import check_joint_target, tcp_from_joints
from robot_io.arms.serial import NO_JOINT_COMMANDS, SerialArm, checksum, decode, encode
from robot_io.arms.serial_sim import SerialArmSimulator
from robot_io.errors import ArmFaultError, ArmRefusedError, HardwareConfigError, ProtocolError, RobotIOError
from robot_io.poses import pose_from_vec, pose_step
from robot_io.safety import SafeArm, SafetyLimits
from tests.robot_io.fakes import Q_UR5_READY, ur5_scene_arm


@pytest.fixture
def device():
    sims = []

    def start(**kwargs):
        kwargs.setdefault("boot_delay_s", 0.05)
        sim, path = SerialArmSimulator.on_pty(**kwargs)
        sims.append(sim)
        return sim, path

    yield start
    for s in sims:
        s.close()


@pytest.fixture
def link(device):
    sim, path = device(heartbeat_timeout_ms=2000)
    # 250 ms: long enough that a loaded CI machine never causes a spurious resend.
    arm = SerialArm(path, timeout_ms=250, retries=3, boot_timeout_ms=1000)
    arm.connect()
    yield sim, arm
    arm.disconnect()


def test_frames_carry_an_xor_checksum_and_corruption_is_detected():
    frame = encode(">", 7, ["MOVE", "0.1", "0.2"])
    body = b"7 MOVE 0.1 0.2"
    x = 0
    for b in body:
        x ^= b
    assert frame == b">" + body + b"*" + f"{x:02X}".encode() + b"\n" and checksum(body) == f"{x:02X}"
    assert decode(frame, ">") == (7, ["MOVE", "0.1", "0.2"])
    with pytest.raises(ValueError, match="checksum"):
        decode(frame.replace(b"0.1", b"0.3"), ">")


def test_connect_waits_for_a_late_boot_banner(device):
    sim, path = device(boot_delay_s=0.4)
    arm = SerialArm(path, boot_timeout_ms=2000)
    t0 = time.monotonic()
    with arm:
        assert time.monotonic() - t0 >= 0.35
        assert arm.device_info["proto"] == "1" and arm.device_info["fw"].startswith("advobj-sim")
        assert arm.fault() is None


def test_board_without_banner_is_asked_with_hello(device):
    sim, path = device(send_banner=False)
    with SerialArm(path, boot_timeout_ms=200) as arm:
        assert arm.device_info["proto"] == "1"
    assert "HELLO" in [c for _, c in sim.executed]


def test_device_still_booting_after_the_timeout_is_a_clear_error(device):
    sim, path = device(boot_delay_s=5.0)
    arm = SerialArm(path, boot_timeout_ms=150, timeout_ms=50, retries=1)
    with pytest.raises(ArmFaultError, match="no valid reply to HELLO"):
        arm.connect()
    assert not arm.connected


def test_wrong_protocol_version_is_refused(device):
    sim, path = device(protocol_version=2)
    with pytest.raises(ProtocolError, match="protocol 2"):
        SerialArm(path).connect()


def test_corrupted_reply_is_resent_without_repeating_the_motion(link):
    sim, arm = link
    T = arm.tcp_pose()
    T[0, 3] += 0.01
    sim.corrupt_replies = 1
    arm.servo(T, 0.05)
    assert arm.stats["checksum_errors"] >= 1 and arm.stats["resends"] >= 1
    assert [c for _, c in sim.executed].count("MOVE") == 1


def test_corrupted_request_is_answered_err_chk_and_resent(link):
    sim, arm = link
    sim.corrupt_requests = 1
    arm.status()
    assert arm.stats["checksum_errors"] == 1 and arm.stats["resends"] == 1


def test_lost_ack_times_out_and_the_resend_is_answered_from_the_cache(link):
    sim, arm = link
    T = arm.tcp_pose()
    T[1, 3] += 0.01
    n_moves = [c for _, c in sim.executed].count("MOVE")
    sim.drop_replies = 1
    arm.servo(T, 0.05)
    assert arm.stats["timeouts"] == 1 and arm.stats["resends"] == 1
    assert [c for _, c in sim.executed].count("MOVE") == n_moves + 1


def test_late_reply_is_accepted_once_and_its_duplicate_discarded_later(link):
    sim, arm = link
    before = [c for _, c in sim.executed].count("POSE")
    sim.reply_delay_s = 0.3  # slower than the 250 ms timeout: the host resends
    T = arm.tcp_pose()
    sim.reply_delay_s = 0.0
    for _ in range(3):
        assert arm.status()["state"] == "IDLE"
    assert np.isfinite(T).all() and arm.stats["timeouts"] >= 1
    assert arm.stats["stale_replies"] >= 1  # the cached answer to the resend, seen later
    assert [c for _, c in sim.executed].count("POSE") == before + 1


def test_silent_device_becomes_a_connection_fault_after_the_retries(link):
    sim, arm = link
    sim.drop_replies = 100
    t0 = time.monotonic()
    with pytest.raises(ArmFaultError) as info:
        arm.status()
    elapsed = time.monotonic() - t0
    assert info.value.fault.kind == "connection_lost" and "4 attempts" in str(info.value)
    assert 0.95 <= elapsed < 3.0  # 4 attempts x 250 ms


def test_keepalive_sends_a_heartbeat_only_when_the_link_was_quiet(link):
    sim, arm = link  # the device announced hb_ms=2000: quiet means > 500 ms
    n_hb = lambda: [c for _, c in sim.executed].count("HB")  # noqa: E731
    arm.tcp_pose()
    arm.keepalive()
    assert n_hb() == 0
    arm._last_ok_s -= 1.0  # pretend a second passed without traffic
    arm.keepalive()
    assert n_hb() == 1


def test_a_policy_step_costs_two_round_trips(link, limits):
    from robot_io.safety import SafeArm

    sim, arm = link
    arm.status_interval_s = 60.0  # no periodic STATUS refresh inside this test
    safe = SafeArm(arm, limits)
    safe.step_delta([0.001, 0, 0, 0, 0, 0], time.monotonic())  # may refresh STATUS
    n = len(sim.executed)
    safe.step_delta([0.001, 0, 0, 0, 0, 0], time.monotonic())
    assert [c for _, c in sim.executed[n:]] == ["POSE", "MOVE"]


def test_stop_byte_halts_a_move_immediately(link):
    sim, arm = link
    T = arm.tcp_pose()
    T[2, 3] -= 0.2
    arm._move(T, 0.05)  # a 4 s move
    time.sleep(0.1)
    arm.stop()
    time.sleep(0.05)
    p1 = arm.tcp_pose()[:3, 3]
    time.sleep(0.1)
    assert sim.stops == 1 and sim.target is None
    assert np.allclose(arm.tcp_pose()[:3, 3], p1) and arm.status()["state"] == "IDLE"


def test_device_heartbeat_timeout_stops_and_faults(device):
    sim, path = device(heartbeat_timeout_ms=150)
    with SerialArm(path, timeout_ms=250) as arm:
        T = arm.tcp_pose()
        T[2, 3] -= 0.2
        arm._move(T, 0.05)
        time.sleep(0.35)  # the host "hangs"
        fault = arm.fault()
        assert fault is not None and fault.kind == "heartbeat_timeout" and "reconnect" in fault.recovery
        assert "FAULT HEARTBEAT" in arm._notices


def test_move_to_blocks_until_the_device_is_there(link):
    sim, arm = link
    T = arm.tcp_pose()
    T[0, 3] += 0.02
    arm.move_to(T, 0.2)
    dp, dr = pose_step(arm.tcp_pose(), T)
    assert dp < 1e-5 and dr < 1e-5


def test_emergency_stop_is_an_explained_fault(link):
    sim, arm = link
    sim.raise_fault("ESTOP")
    T = arm.tcp_pose()
    with pytest.raises(ArmFaultError) as info:
        arm.servo(T, 0.05)
    assert info.value.fault.kind == "emergency_stop" and "release the e-stop" in str(info.value)


def test_missing_port_is_a_clear_connection_fault():
    with pytest.raises(ArmFaultError, match="cannot open serial port /nonexistent/ttyX"):
        SerialArm("/nonexistent/ttyX").connect()


def test_banner_sharing_a_line_with_bootloader_noise_is_found(device):
    sim, path = device(boot_delay_s=0.2, boot_noise=b"\xfe\x00garbage")
    with SerialArm(path, boot_timeout_ms=2000) as arm:
        assert arm.device_info["fw"].startswith("advobj-sim")
    assert "HELLO" not in [c for _, c in sim.executed]


def test_unplugged_port_during_a_command_is_a_connection_fault(link):
    sim, arm = link

    def unplugged(data):
        raise OSError(5, "Input/output error")

    arm._ser.write = unplugged
    with pytest.raises(ArmFaultError, match="serial I/O error"):
        arm.tcp_pose()
    assert arm.fault().kind == "connection_lost"


# ---------------------------------------------------------------------------- joint commands


@pytest.fixture(scope="module")
def ur5():
    return ur5_scene_arm()


@pytest.fixture
def joint_link(device, ur5):
    """A connected SerialArm with the UR5's kinematics, on a simulator tracking the UR5's joints."""
    sim, path = device(heartbeat_timeout_ms=2000, scene_arm=ur5)
    arm = SerialArm(path, timeout_ms=250, retries=3, boot_timeout_ms=1000, kinematics=ur5)
    arm.connect()
    yield sim, arm
    arm.disconnect()


def commands(sim) -> list[str]:
    return [c for _, c in sim.executed]


def wait_idle(arm, timeout_s: float = 2.0) -> None:
    deadline = time.monotonic() + timeout_s
    while arm.status()["state"] != "IDLE":
        assert time.monotonic() < deadline, "the device is still moving"
        time.sleep(0.01)


def test_joints_are_asked_on_connect_held_against_the_pose_and_reported_in_the_urdf_order(joint_link, ur5):
    sim, arm = joint_link
    assert arm.kinematics() is ur5 and commands(sim)[-2:] == ["JOINTS", "POSE"]  # the connect check
    np.testing.assert_allclose(arm.joint_positions(), Q_UR5_READY, atol=1e-6)


def test_a_joint_servo_round_trips_and_the_tcp_is_the_fk_of_the_joints(joint_link, ur5):
    sim, arm = joint_link
    q = np.array(Q_UR5_READY) + np.array([0.02, -0.01, 0.015, 0.01, -0.02, 0.03])
    arm.servo_joints(q, 0.05)
    wait_idle(arm)
    q_read = arm.joint_positions()
    np.testing.assert_allclose(q_read, q, atol=1e-6)  # %.6f on the wire
    np.testing.assert_allclose(tcp_from_joints(ur5, q_read), arm.tcp_pose(), atol=1e-6)
    assert commands(sim).count("MOVEJ") == 1


def test_a_joint_servo_moves_the_joints_along_the_joint_space_line_over_its_duration(joint_link):
    sim, arm = joint_link
    q0 = arm.joint_positions()
    q = q0 + np.array([0.2, 0.1, 0.0, 0.0, 0.0, -0.1])
    t0 = time.monotonic()
    arm.servo_joints(q, 0.4)
    time.sleep(0.15)
    part = (arm.joint_positions() - q0) / (q - q0)[0]
    wait_idle(arm)
    assert time.monotonic() - t0 >= 0.35  # the duration was kept, not jumped
    assert 0 < part[0] < 1 and part[1] == pytest.approx(part[0] / 2, abs=1e-4)  # one line in joint space


@pytest.mark.parametrize("bad", [np.zeros(5), np.zeros(7), np.full(6, np.inf), [[0.0] * 6], None])
@pytest.mark.parametrize("method", ["servo_joints", "move_joints"])
def test_a_malformed_joint_target_is_refused_with_one_line_and_nothing_sent(joint_link, bad, method):
    sim, arm = joint_link
    with pytest.raises(RobotIOError) as info:
        getattr(arm, method)(bad, 0.05)
    assert "\n" not in str(info.value) and f"serial arm {arm.port}: a joint target must be" in str(info.value)
    assert "MOVEJ" not in commands(sim)


@given(q=arrays(np.float64, st.integers(0, 8), elements=st.floats(allow_nan=True, allow_infinity=True)))
def test_check_joint_target_returns_n_finite_numbers_or_one_line(ur5, q):
    try:
        out = check_joint_target("serial arm X", ur5, q)
    except RobotIOError as err:
        assert "\n" not in str(err) and (q.shape != (6,) or not np.isfinite(q).all())
        return
    assert out.shape == (6,) and out.dtype == np.float64 and np.isfinite(out).all()


def test_the_device_refuses_a_joint_past_its_limit_but_takes_one_rounded_onto_it(joint_link, ur5):
    sim, arm = joint_link
    hi = ur5.model.limits.q_max.numpy()
    q = np.array(Q_UR5_READY)
    q[2] = hi[2]  # the elbow's limit is pi: "3.141593" on the wire is past it by 3.5e-7
    arm.move_joints(q, 0.3)
    assert sim.q[2] == hi[2] and arm.joint_positions()[2] == pytest.approx(hi[2], abs=1e-6)  # clamped onto it
    q[2] = hi[2] + 1e-3
    with pytest.raises(ArmRefusedError, match="rejected MOVEJ: ERR RANGE joint limit; the arm did not take it"):
        arm.servo_joints(q, 0.05)
    assert arm.fault() is None  # a refusal: the device takes the next command
    q[2] = hi[2] - 1e-3
    arm.move_joints(q, 0.05)
    np.testing.assert_allclose(sim.q, q, atol=1e-6)


def test_firmware_without_joint_commands_is_refused_on_connect_with_one_line(device, ur5):
    sim, path = device()  # no scene arm: the firmware answers JOINTS with ERR UNKNOWN
    arm = SerialArm(path, boot_timeout_ms=1000, kinematics=ur5)
    with pytest.raises(ProtocolError) as info:
        arm.connect()
    assert NO_JOINT_COMMANDS in str(info.value) and "ERR UNKNOWN" in str(info.value) and "\n" not in str(info.value)
    assert not arm.connected and commands(sim)[-1] == "JOINTS"


def test_firmware_without_joint_commands_still_takes_tcp_commands_and_refuses_joint_ones(device, ur5):
    sim, path = device()
    with SerialArm(path, boot_timeout_ms=1000) as arm:  # no URDF: no joint check on connect
        arm._kinematics = ur5  # a URDF named after connecting: the firmware says what it takes
        with pytest.raises(ProtocolError, match=NO_JOINT_COMMANDS):
            arm.servo_joints(np.array(Q_UR5_READY), 0.05)
        assert commands(sim)[-1] == "MOVEJ" and sim.moving is False


def test_a_device_with_other_joints_than_the_urdf_is_refused_on_connect(device, ur5):
    from sim.ik import SceneArm
    from sim.kinematics import shipped_arm

    panda = SceneArm(shipped_arm("panda"), np.eye(4), np.eye(4), 0.05, np.zeros(7))
    sim, path = device(scene_arm=panda)
    arm = SerialArm(path, boot_timeout_ms=1000, kinematics=ur5)
    with pytest.raises(ProtocolError, match="JOINTS replied 7 values .* the arm's URDF has 6 joints") as info:
        arm.connect()
    assert "\n" not in str(info.value) and not arm.connected


def test_a_urdf_placed_otherwise_than_the_device_is_refused_on_connect_and_the_right_one_connects(device, ur5):
    # The device computes its POSE on a UR5 whose base_link is turned by pi about z (as a UR's
    # controller does); the URDF the host is given misses the turn.
    turned = ur5_scene_arm(T_base_link=pose_from_vec([0.0, 0.0, 0.0, 0.0, 0.0, np.pi]))
    sim, path = device(scene_arm=turned)
    arm = SerialArm(path, boot_timeout_ms=1000, kinematics=ur5)
    with pytest.raises(HardwareConfigError) as info:
        arm.connect()
    text = str(info.value)
    assert "\n" not in text and text.startswith(f"serial arm {path}: the arm's URDF kinematics disagree")
    assert "rotvec_base_link" in text and text.endswith("Nothing was moved")
    assert not arm.connected and commands(sim)[-2:] == ["JOINTS", "POSE"]
    assert not {"MOVE", "MOVEJ"} & set(commands(sim)) and not sim.moving
    np.testing.assert_array_equal(sim.q, turned.q_home)
    with SerialArm(path, boot_timeout_ms=1000, expect_banner=False, kinematics=turned) as arm:
        np.testing.assert_allclose(arm.tcp_pose(), tcp_from_joints(turned, arm.joint_positions()), atol=1e-5)


def test_an_arm_without_kinematics_takes_no_joint_commands(link):
    sim, arm = link
    assert arm.kinematics() is None
    for call in (lambda: arm.joint_positions(), lambda: arm.servo_joints(np.zeros(6), 0.05)):
        with pytest.raises(RobotIOError, match="takes no joint commands"):
            call()
    assert not {"JOINTS", "MOVEJ"} & set(commands(sim))


def test_a_fault_refuses_a_joint_servo_and_the_joints_stay(joint_link):
    sim, arm = joint_link
    q0 = arm.joint_positions()
    sim.raise_fault("PSTOP")
    with pytest.raises(ArmFaultError) as info:
        arm.servo_joints(q0 + 0.05, 0.05)
    assert info.value.fault.kind == "protective_stop" and "clear the workspace" in str(info.value)
    np.testing.assert_array_equal(arm.joint_positions(), q0)


def test_a_fault_during_a_joint_move_stops_it_and_is_explained(joint_link):
    sim, arm = joint_link
    q0 = arm.joint_positions()
    q = q0.copy()
    q[0] += 0.5
    threading.Timer(0.15, sim.raise_fault, ["ESTOP"]).start()
    with pytest.raises(ArmFaultError) as info:
        arm.move_joints(q, 1.0)
    assert info.value.fault.kind == "emergency_stop"
    time.sleep(0.05)
    q_stopped = arm.joint_positions()
    assert q0[0] < q_stopped[0] < q[0] and sim.moving is False  # frozen part-way


def test_a_joint_move_that_does_not_end_times_out_and_is_stopped(device, ur5):
    sim, path = device(heartbeat_timeout_ms=2000, scene_arm=ur5, max_joint_speed_radps=0.05)
    with SerialArm(path, timeout_ms=250, kinematics=ur5) as arm:
        q = arm.joint_positions()
        q[0] += 0.5  # 10 s at the device's joint speed cap
        t0 = time.monotonic()
        with pytest.raises(ProtocolError, match="joint move did not finish in 0.3 s") as info:
            arm.move_joints(q, 0.5, timeout_s=0.3)
        assert time.monotonic() - t0 < 1.0 and "\n" not in str(info.value)
        time.sleep(0.05)
        assert sim.stops == 1 and sim.moving is False


def test_move_joints_blocks_until_the_device_is_there(joint_link, ur5):
    sim, arm = joint_link
    q = arm.joint_positions()
    q[[0, 4]] += [0.1, -0.05]
    t0 = time.monotonic()
    arm.move_joints(q, 0.3)
    assert time.monotonic() - t0 >= 0.25 and sim.moving is False
    np.testing.assert_allclose(arm.joint_positions(), q, atol=1e-6)
    np.testing.assert_allclose(arm.tcp_pose(), tcp_from_joints(ur5, arm.joint_positions()), atol=1e-6)


def test_a_tcp_move_on_a_joint_device_goes_through_its_ik_and_keeps_the_fk(joint_link, ur5):
    sim, arm = joint_link
    T = arm.tcp_pose()
    T[0, 3] += 0.02
    arm.move_to(T, 0.2)
    dp, dr = pose_step(arm.tcp_pose(), T)
    assert dp < 1e-4 and dr < 1e-3  # the IK's tolerance
    np.testing.assert_allclose(arm.tcp_pose(), tcp_from_joints(ur5, arm.joint_positions()), atol=1e-6)


@pytest.mark.parametrize("x_m", [2.0, 1e6])
def test_a_tcp_target_out_of_the_devices_reach_is_a_refusal_and_the_next_command_runs(joint_link, x_m):
    """ERR RANGE unreachable: the device did not take the MOVE, no fault stands; the arm moves again."""
    sim, arm = joint_link
    q0, T0 = arm.joint_positions(), arm.tcp_pose()
    far = T0.copy()
    far[:3, 3] = (x_m, 0.0, 0.3)  # a UR5 reaches 0.85 m
    for move in (lambda: arm.servo(far, 0.05), lambda: arm.move_to(far, 0.2)):
        with pytest.raises(ArmRefusedError, match=r"rejected MOVE: ERR RANGE unreachable; the arm did not take it$"):
            move()
    assert arm.fault() is None and sim.moving is False
    np.testing.assert_allclose(arm.joint_positions(), q0, atol=1e-6)
    near = T0.copy()
    near[2, 3] += 0.01
    arm.move_to(near, 0.2)
    assert pose_step(arm.tcp_pose(), near)[0] < 1e-4  # the IK's tolerance


def test_joint_steps_through_the_safety_layer_never_send_the_device_a_target_outside_limits(joint_link, ur5):
    sim, arm = joint_link
    limits = SafetyLimits(workspace_min_m=(-1.0, -1.0, 0.0), workspace_max_m=(1.0, 1.0, 1.0), max_frame_age_ms=1000)
    safe = SafeArm(arm, limits)
    lo, hi = ur5.model.limits.q_min.numpy(), ur5.model.limits.q_max.numpy()
    q0 = np.array(Q_UR5_READY)
    q0[5] = hi[5] - 0.01  # the last wrist joint near its limit: turning it leaves the TCP where it is
    arm.move_joints(q0, 0.1)
    n_before = commands(sim).count("MOVEJ")
    for bad in (np.full(6, np.nan), np.zeros(7), q0 + np.where(np.arange(6) == 0, 2.0, 0.0)):
        assert safe.step_joints(bad, time.monotonic()).status == "refused"
    assert commands(sim).count("MOVEJ") == n_before  # NaN, wrong length, a jump: nothing reached the device
    past = q0.copy()
    past[5] = hi[5] + 0.2
    res = safe.step_joints(past, time.monotonic())
    assert res.status == "clipped" and res.q_cmd[5] == hi[5] and commands(sim).count("MOVEJ") == n_before + 1
    wait_idle(arm)
    assert ((sim.q >= lo) & (sim.q <= hi)).all() and sim.q[5] == pytest.approx(hi[5], abs=1e-6)
