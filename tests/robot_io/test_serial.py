"""Serial arm driver against the device simulator, real bytes over a pseudo-terminal."""

from __future__ import annotations

import time

import numpy as np
import pytest

from robot_io.arms.serial import SerialArm, checksum, decode, encode
from robot_io.arms.serial_sim import SerialArmSimulator
from robot_io.errors import ArmFaultError, ProtocolError
from robot_io.poses import pose_step


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
