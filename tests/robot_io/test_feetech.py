"""The Feetech STS driver (SO-100/SO-101) against its byte-level twin, real bytes over a pty.

Also home of what both servo-bus drivers share (:mod:`robot_io.arms.servo_bus`): the tick/rad
mapping, the configuration checks, and :class:`BusBehaviour`, the behaviour every bus arm must
show on its twin; ``test_dynamixel.py`` runs the same class on the Dynamixel twin.

The kinematics is the shipped Panda (7 joints; no SO-100/Koch URDF is shipped) with its base at the
world origin; each servo's ``offset_ticks`` puts the middle of its joint's URDF range at the middle
of the servo's turn, and every other joint turns the other way (``sign`` -1).
"""

from __future__ import annotations

import math
import subprocess
import sys
import time
from dataclasses import dataclass

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from robot_io.arms.feetech import (
    ADDR_GOAL_SPEED,
    ERROR_BITS,
    STS3215_MODEL,
    FeetechArm,
    checksum,
    decode_position,
    encode_packet,
    encode_position,
    from_sign_magnitude,
    take_packet,
    to_sign_magnitude,
)
from robot_io.arms.feetech_sim import FeetechSimulator
from robot_io.arms.servo_bus import (
    PING,
    SYNC_WRITE,
    BadPacket,
    ServoBusError,
    ServoJoint,
    SimServo,
)
from robot_io.errors import ArmFaultError, ArmRefusedError, ProtocolError
from robot_io.safety import SafeArm
from sim.ik import SceneArm
from sim.kinematics import shipped_arm
from tests.robot_io.test_joint_safety import PERIOD_S, Q_READY, joint_limits

GRIPPER_ID = 8


def centred_joints(scene_arm: SceneArm, ticks_per_rev: int = 4096) -> list[ServoJoint]:
    """One servo per chain joint (ids from 1), its URDF range centred in the servo's turn."""
    lo = scene_arm.model.limits.q_min.cpu().numpy()
    hi = scene_arm.model.limits.q_max.cpu().numpy()
    out = []
    for k, name in enumerate(scene_arm.joint_names):
        sign = -1 if k % 2 else 1
        offset = ticks_per_rev // 2 - round(sign * 0.5 * (lo[k] + hi[k]) * ticks_per_rev / (2 * math.pi))
        out.append(ServoJoint(k + 1, name, sign, offset, ticks_per_rev))
    return out


def quantized(joints, q) -> np.ndarray:
    """What a servo arm reports after reaching ``q``: each joint on its nearest tick."""
    return np.array([j.to_rad(j.to_ticks(x)) for j, x in zip(joints, q)])


def fk(scene_arm: SceneArm, q) -> np.ndarray:
    return scene_arm.tcp_pose(torch.as_tensor(np.asarray(q, dtype=np.float64))).numpy()


def ik(scene_arm: SceneArm, T, q_seed) -> np.ndarray:
    lim = scene_arm.model.limits
    seed = np.clip(q_seed, lim.q_min.numpy(), lim.q_max.numpy())
    res = scene_arm.ik(torch.as_tensor(T)[None], torch.as_tensor(seed)[None])
    return res.require()[0].numpy()


def wait_for(predicate, timeout_s: float = 3.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.005)
    return predicate()


def bit_named(bits: dict[int, str], words: str) -> int:
    return next(b for b, text in bits.items() if text == words)


@dataclass(frozen=True)
class Protocol:
    """A servo-bus driver, its twin, and its hardware error bits (for :class:`BusBehaviour`)."""

    arm: type
    sim: type
    error_bits: dict[int, str]
    model: int


FEETECH = Protocol(FeetechArm, FeetechSimulator, ERROR_BITS, STS3215_MODEL)


class BusBehaviour:
    """What every servo-bus arm does on its twin; a ``Test...`` subclass names the :class:`Protocol`."""

    protocol: Protocol

    @pytest.fixture(scope="class")
    @classmethod
    def scene_arm(cls):
        return SceneArm(shipped_arm("panda"), np.eye(4), np.eye(4), PERIOD_S, Q_READY.copy())

    @pytest.fixture
    def bus(self, scene_arm):
        """``start(gripper=False, arm_kw=None, headroom=None, **sim_kw) -> (sim, arm)``: a twin at Q_READY
        and an arm on it; ``headroom[id]`` caps that servo's Max_Position_Limit that many ticks above it."""
        started = []

        def start(gripper: bool = False, arm_kw: dict | None = None, headroom: dict | None = None, **sim_kw):
            joints = centred_joints(scene_arm)
            servos = [SimServo(j.id, position_ticks=j.to_ticks(q)) for j, q in zip(joints, Q_READY)]
            for s in servos:
                if s.id in (headroom or {}):
                    s.max_ticks = round(s.position_ticks) + headroom[s.id]
            grip = ServoJoint(GRIPPER_ID, "gripper", 1, 2048) if gripper else None
            if grip is not None:
                servos.append(SimServo(GRIPPER_ID, position_ticks=2048))
            sim, path = self.protocol.sim.on_pty(servos, **sim_kw)
            # 250 ms: long enough that a loaded machine never causes a spurious resend.
            kw = dict(timeout_ms=250.0, settle_ticks=0, gripper=grip) | (arm_kw or {})
            arm = self.protocol.arm(path, joints, scene_arm, **kw)
            started.append((sim, arm))
            return sim, arm

        yield start
        for sim, arm in started:
            arm.disconnect()
            sim.close()

    @pytest.fixture
    def link(self, bus):
        sim, arm = bus()
        arm.connect()
        return sim, arm

    # ------------------------------------------------------------------ connect
    def test_connect_pings_every_servo_and_moves_nothing(self, link, scene_arm):
        sim, arm = link
        assert [i for i, instr in sim.requests if instr == PING] == [j.id for j in arm.joints]
        np.testing.assert_allclose(arm.joint_positions(), quantized(arm.joints, Q_READY), atol=1e-12)
        assert arm.fault() is None
        ident = arm.identity()
        assert ident["models"] == ",".join(f"{j.id}:{self.protocol.model}" for j in arm.joints)

    def test_identity_before_connect_is_kept_and_extended_after(self, bus):
        sim, arm = bus()
        before = arm.identity()
        with arm:
            after = arm.identity()
        assert before.items() <= after.items() and set(after) - set(before) == {"models", "firmwares"}
        assert all(isinstance(v, str) for v in after.values())

    def test_a_servo_silent_at_connect_is_named_by_connect_and_by_fault(self, bus):
        sim, arm = bus(arm_kw=dict(timeout_ms=30.0, retries=1))
        sim.servo(4).silent = True
        with pytest.raises(ArmFaultError, match=r"servo 4 \(joint 'panda_joint4'\) does not answer ping") as err:
            arm.connect()
        assert not arm.connected and "\n" not in str(err.value)
        assert arm.fault().kind == "connection_lost" and "servo 4" in arm.fault().message

    def test_a_port_that_does_not_exist_is_a_connection_fault_naming_it(self, scene_arm, tmp_path):
        arm = self.protocol.arm(str(tmp_path / "ttyNONE"), centred_joints(scene_arm), scene_arm)
        with pytest.raises(ArmFaultError, match="cannot open serial port .*ttyNONE"):
            arm.connect()
        assert arm.fault().kind == "connection_lost"

    def test_after_disconnect_the_fault_is_connection_lost(self, link):
        sim, arm = link
        arm.disconnect()
        assert arm.fault().kind == "connection_lost" and "not connected" in arm.fault().message
        with pytest.raises(ArmFaultError, match="not connected"):
            arm.joint_positions()

    # ------------------------------------------------------------------ joints
    def test_move_joints_reaches_the_target_on_its_ticks(self, link):
        sim, arm = link
        target = Q_READY + np.linspace(-0.2, 0.2, len(Q_READY))
        arm.move_joints(target, 0.3)
        expect = quantized(arm.joints, target)
        np.testing.assert_allclose(arm.joint_positions(), expect, atol=1e-12)
        reading = [round(sim.servo(j.id).position_ticks) for j in arm.joints]  # the twin's present position
        assert reading == [j.to_ticks(x) for j, x in zip(arm.joints, target)]

    def test_servo_joints_returns_at_once_and_the_servos_get_there(self, link):
        sim, arm = link
        target = Q_READY - 0.03
        n_writes = sum(instr == SYNC_WRITE for _, instr in sim.requests)
        arm.servo_joints(target, PERIOD_S)
        expect = quantized(arm.joints, target)
        assert wait_for(lambda: np.allclose(arm.joint_positions(), expect, atol=1e-12, rtol=0))
        assert sum(instr == SYNC_WRITE for _, instr in sim.requests) == n_writes + 1  # one packet for all joints

    def test_tcp_pose_is_the_fk_of_the_measured_joints(self, link, scene_arm):
        sim, arm = link
        arm.move_joints(Q_READY + 0.1, 0.2)
        T, q = arm.tcp_pose(), arm.joint_positions()
        np.testing.assert_allclose(T, fk(scene_arm, q), atol=1e-9, rtol=0)

    @pytest.mark.parametrize(
        "bad, words",
        [
            (Q_READY[:-1], "shape"),
            (np.append(Q_READY, 0.0), "shape"),
            (np.where(np.arange(7) == 2, np.nan, Q_READY), "nan"),
            (np.where(np.arange(7) == 6, np.inf, Q_READY), "inf"),
        ],
    )
    def test_a_wrong_joint_vector_is_refused_in_one_line_and_nothing_is_sent(self, link, bad, words):
        sim, arm = link
        n = len(sim.requests)
        for command in (arm.servo_joints, arm.move_joints):
            with pytest.raises(ServoBusError, match=f"7 finite numbers .*panda_joint1.*{words}") as err:
                command(bad, PERIOD_S)
            assert "\n" not in str(err.value)
        assert len(sim.requests) == n

    def test_a_target_outside_the_servos_turn_is_refused_naming_the_joint_and_the_next_command_runs(self, link):
        sim, arm = link
        j = arm.joints[1]
        beyond = j.to_rad(j.max_ticks + 1)
        target = Q_READY.copy()
        target[1] = beyond
        n = len(sim.requests)
        with pytest.raises(ArmRefusedError, match=rf"'panda_joint2' .* outside its servo's turn \[0, {j.max_ticks}\]"):
            arm.servo_joints(target, PERIOD_S)
        assert len(sim.requests) == n and arm.fault() is None  # nothing sent, no fault latched
        arm.servo_joints(Q_READY + 0.01, PERIOD_S)
        assert wait_for(lambda: SYNC_WRITE in [instr for _, instr in sim.requests[n:]])  # no servo answers it

    @pytest.mark.parametrize("duration_s", [0.0, -1.0, math.nan, math.inf])
    def test_a_duration_that_is_not_positive_and_finite_is_refused(self, link, duration_s):
        sim, arm = link
        with pytest.raises(ServoBusError, match="duration_s must be a positive number"):
            arm.servo_joints(Q_READY, duration_s)

    def test_stop_holds_the_present_position(self, link):
        sim, arm = link
        far = Q_READY + np.where(np.arange(7) % 2, 0.3, -0.3)
        arm.servo_joints(far, 2.0)  # slow: still moving when stopped
        assert wait_for(lambda: not np.allclose(arm.joint_positions(), quantized(arm.joints, Q_READY)))
        arm.stop()
        time.sleep(0.05)  # a servo may pass its stop position by a tick and come back
        held = arm.joint_positions()
        time.sleep(0.1)
        np.testing.assert_array_equal(arm.joint_positions(), held)
        assert not np.allclose(held, quantized(arm.joints, far))

    def test_a_move_a_servo_cannot_finish_stops_the_arm_and_names_the_servo(self, bus):
        sim, arm = bus(arm_kw=dict(settle_timeout_s=0.1), headroom={4: 10})
        arm.connect()
        j = arm.joints[3]
        target = Q_READY.copy()
        target[3] += j.sign * 0.1  # 65 ticks up; its position limit allows 10
        with pytest.raises(ProtocolError, match=r"servo 4 \(joint 'panda_joint4'\) is \d+ ticks from its goal") as err:
            arm.move_joints(target, 0.1)
        assert "\n" not in str(err.value)
        held = arm.joint_positions()
        time.sleep(0.05)
        np.testing.assert_array_equal(arm.joint_positions(), held)

    # ------------------------------------------------------------------ TCP through IK
    def test_move_to_goes_through_ik_from_the_measured_joints(self, link, scene_arm):
        sim, arm = link
        T = fk(scene_arm, Q_READY + 0.05)
        T[:3, 3] += [0.01, -0.01, 0.005]
        q_ik = ik(scene_arm, T, arm.joint_positions())
        arm.move_to(T, 0.1)
        expect = quantized(arm.joints, q_ik)
        np.testing.assert_allclose(arm.joint_positions(), expect, atol=1e-12)
        np.testing.assert_allclose(arm.tcp_pose(), fk(scene_arm, expect), atol=1e-9, rtol=0)

    def test_servo_goes_through_ik_and_the_servos_get_there(self, link, scene_arm):
        sim, arm = link
        T = arm.tcp_pose()
        T[:3, 3] += [0.0, 0.004, -0.003]
        expect = quantized(arm.joints, ik(scene_arm, T, arm.joint_positions()))
        arm.servo(T, PERIOD_S)
        assert wait_for(lambda: np.allclose(arm.joint_positions(), expect, atol=1e-12, rtol=0))

    def test_an_unreachable_pose_is_refused_in_one_line_nothing_moves_and_the_next_command_runs(self, link):
        sim, arm = link
        T = arm.tcp_pose()
        T[:3, 3] = [3.0, 0.0, 0.5]  # the Panda reaches under a metre
        n = len(sim.requests)
        for command, arg in ((arm.servo, PERIOD_S), (arm.move_to, 0.1)):
            with pytest.raises(ArmRefusedError, match="does not reach it.*the arm did not move") as err:
                command(T, arg)
            assert "\n" not in str(err.value)
        assert SYNC_WRITE not in [instr for _, instr in sim.requests[n:]]
        assert arm.fault() is None
        T_near = arm.tcp_pose()
        T_near[2, 3] += 0.003
        arm.servo(T_near, PERIOD_S)
        assert wait_for(lambda: SYNC_WRITE in [instr for _, instr in sim.requests[n:]])  # no servo answers it

    def test_the_safety_layers_joint_path_drives_the_twin(self, link):
        sim, arm = link
        safe = SafeArm(arm, joint_limits())
        with safe:
            target = safe.joint_positions() + 0.02
            res = safe.step_joints(target, time.monotonic())
            assert res.status in ("ok", "clipped")
            expect = quantized(arm.joints, res.q_cmd)
            assert wait_for(lambda: np.allclose(arm.joint_positions(), expect, atol=1e-12, rtol=0))

    # ------------------------------------------------------------------ gripper
    def test_the_gripper_is_on_the_bus_but_not_in_the_kinematics(self, bus):
        sim, arm = bus(gripper=True)
        with arm:
            assert GRIPPER_ID in [i for i, instr in sim.requests if instr == PING]
            assert arm.joint_positions().shape == (7,)
            g = arm.gripper
            goal = g.to_rad(g.offset_ticks + 100)
            arm.servo_gripper(goal, 0.1)
            assert wait_for(lambda: arm.gripper_position() == goal)

    # ------------------------------------------------------------------ faults
    def test_a_servo_error_bit_is_a_device_fault_naming_the_servo(self, link):
        sim, arm = link
        bit = bit_named(self.protocol.error_bits, "overheating")
        sim.servo(3).error = bit
        arm.status_interval_s = 0.0
        f = arm.fault()
        assert f.kind == "device_fault" and "servo 3 (joint 'panda_joint3')" in f.message
        assert "overheating" in f.message and f.recovery
        with pytest.raises(ArmFaultError, match="overheating"):
            arm.servo_joints(Q_READY, PERIOD_S)

    def test_a_servo_that_stops_answering_is_connection_lost_naming_it(self, bus):
        sim, arm = bus(arm_kw=dict(timeout_ms=30.0, retries=2))
        arm.connect()
        resends = arm.stats["resends"]
        sim.servo(5).silent = True
        with pytest.raises(ArmFaultError, match=r"no valid reply .* from servo 5 \(joint 'panda_joint5'\)") as err:
            arm.joint_positions()
        assert err.value.fault.kind == "connection_lost" and f"after {arm.retries + 1} attempts" in str(err.value)
        assert arm.fault() == err.value.fault
        assert arm.stats["resends"] - resends == arm.retries

    def test_a_corrupt_reply_is_resent_and_the_read_succeeds(self, link):
        sim, arm = link
        sim.corrupt_replies = 1
        np.testing.assert_allclose(arm.joint_positions(), quantized(arm.joints, Q_READY), atol=1e-12)
        assert arm.stats["checksum_errors"] == 1 and arm.stats["resends"] == 1
        assert arm.fault() is None

    def test_corrupt_replies_beyond_the_retries_are_connection_lost(self, bus):
        sim, arm = bus(arm_kw=dict(timeout_ms=30.0, retries=2))
        arm.connect()
        sim.corrupt_replies = 10_000
        with pytest.raises(ArmFaultError, match=f"no valid reply .* after {arm.retries + 1} attempts"):
            arm.joint_positions()
        assert arm.stats["checksum_errors"] >= arm.retries + 1 and arm.fault().kind == "connection_lost"

    # ------------------------------------------------------------------ configuration
    def test_joints_that_are_not_the_urdf_chains_are_refused_in_one_line(self, scene_arm):
        joints = centred_joints(scene_arm)
        renamed = joints[:-1] + [ServoJoint(7, "wrist_roll", 1, 2048)]
        with pytest.raises(ServoBusError, match="missing: panda_joint7; not in the URDF chain: wrist_roll") as err:
            self.protocol.arm("/dev/null", renamed, scene_arm)
        assert "\n" not in str(err.value)
        with pytest.raises(ServoBusError, match="missing: panda_joint7"):
            self.protocol.arm("/dev/null", joints[:-1], scene_arm)

    def test_configured_joints_in_any_order_follow_the_chain(self, scene_arm):
        joints = centred_joints(scene_arm)
        arm = self.protocol.arm("/dev/null", joints[::-1], scene_arm)
        assert [j.name for j in arm.joints] == list(scene_arm.joint_names)

    def test_a_repeated_servo_id_or_a_gripper_in_the_chain_is_refused(self, scene_arm):
        joints = centred_joints(scene_arm)
        with pytest.raises(ServoBusError, match=r"ids must be unique on the bus; \[3\] repeat"):
            self.protocol.arm("/dev/null", joints, scene_arm, gripper=ServoJoint(3, "gripper"))
        with pytest.raises(ServoBusError, match="'panda_joint7' is a joint of the URDF chain"):
            self.protocol.arm("/dev/null", joints, scene_arm, gripper=ServoJoint(9, "panda_joint7"))


class TestFeetechBus(BusBehaviour):
    protocol = FEETECH

    def test_each_joint_gets_the_speed_that_brings_it_there_in_the_duration(self, link):
        sim, arm = link
        target = Q_READY + np.linspace(0.0, 0.3, 7)
        duration_s = 0.5
        now = {j.id: j.to_ticks(q) for j, q in zip(arm.joints, Q_READY)}
        arm.servo_joints(target, duration_s)
        arm.joint_positions()  # a round trip: the twin has applied the write before it answers
        for j, q in zip(arm.joints, target):
            speed = int.from_bytes(sim.servo(j.id).memory[ADDR_GOAL_SPEED : ADDR_GOAL_SPEED + 2], "little")
            assert speed == max(1, math.ceil(abs(j.to_ticks(q) - now[j.id]) / duration_s)), j.name

    def test_a_feetech_error_clears_when_its_cause_is_gone(self, link):
        sim, arm = link
        arm.status_interval_s = 0.0
        sim.servo(2).error = bit_named(ERROR_BITS, "overload")
        assert "overload" in arm.fault().message
        sim.servo(2).error = 0
        assert arm.fault() is None


# ---------------------------------------------------------------------------- the byte protocol


def test_packets_match_the_feetech_manuals_examples():
    # The manual's PING of servo 1, its answer, and a READ of Present_Position (0x38, 2 bytes).
    assert encode_packet(1, PING) == bytes.fromhex("FF FF 01 02 01 FB")
    assert encode_packet(1, 0) == bytes.fromhex("FF FF 01 02 00 FC")
    assert encode_packet(1, 0x02, bytes([0x38, 2])) == bytes.fromhex("FF FF 01 04 02 38 02 BE")


@settings(max_examples=300, deadline=None)
@given(body=st.binary(min_size=1, max_size=64))
def test_the_checksum_makes_the_byte_sum_0xff(body):
    assert (sum(body) + checksum(body)) & 0xFF == 0xFF


@settings(max_examples=300, deadline=None)
@given(
    servo_id=st.integers(0, 0xFE),
    code=st.integers(0, 0xFF),
    params=st.binary(max_size=32),
    noise=st.binary(max_size=8).filter(lambda b: 0xFF not in b),
)
def test_a_packet_after_noise_decodes_to_what_was_encoded(servo_id, code, params, noise):
    buf = bytearray(noise + encode_packet(servo_id, code, params) + b"\xff")
    assert take_packet(buf) == (servo_id, code, params)
    assert take_packet(buf) is None and buf == bytearray(b"\xff")  # a trailing 0xFF may begin a header


def test_a_partial_packet_waits_and_a_bad_checksum_is_dropped_and_reported():
    frame = encode_packet(3, 0x03, bytes([42, 1, 2]))
    buf = bytearray(frame[:-1])
    assert take_packet(buf) is None and bytes(buf) == frame[:-1]
    bad = bytearray(frame[:-1] + bytes([frame[-1] ^ 0x01]) + encode_packet(4, 0))
    with pytest.raises(BadPacket, match="checksum mismatch") as err:
        take_packet(bad)
    assert err.value.servo_id == 3 and take_packet(bad) == (4, 0, b"")


@settings(max_examples=300, deadline=None)
@given(value=st.integers(-(2**15 - 1), 2**15 - 1))
def test_sign_magnitude_round_trips_with_the_sign_in_bit_15(value):
    raw = to_sign_magnitude(value)
    assert from_sign_magnitude(raw) == value and 0 <= raw < 2**16
    assert bool(raw & 0x8000) == (value < 0) and raw & 0x7FFF == abs(value)
    assert decode_position(encode_position(value)) == value


def test_sign_magnitude_extremes():
    assert encode_position(-1) == bytes([0x01, 0x80])
    assert from_sign_magnitude(0x8000) == 0  # "minus zero" reads as zero
    assert from_sign_magnitude(0xFFFF) == -(2**15 - 1)
    for value in (2**15, -(2**15)):
        with pytest.raises(ValueError, match="does not fit"):
            to_sign_magnitude(value)


# ---------------------------------------------------------------------------- ticks <-> rad (servo_bus)


@settings(max_examples=200, deadline=None)
@given(
    ticks=st.integers(-(2**31), 2**31 - 1),
    offset=st.integers(-(2**20), 2**20),
    sign=st.sampled_from([1, -1]),
    ticks_per_rev=st.integers(2, 2**20),
)
def test_every_tick_maps_to_rad_and_back_to_itself(ticks, offset, sign, ticks_per_rev):
    j = ServoJoint(1, "j", sign, offset, ticks_per_rev)
    assert j.to_ticks(j.to_rad(ticks)) == ticks


@settings(max_examples=200, deadline=None)
@given(
    q=st.floats(-100.0, 100.0, allow_nan=False),
    offset=st.integers(-4096, 8192),
    sign=st.sampled_from([1, -1]),
    ticks_per_rev=st.sampled_from([1024, 4096, 2**20]),
)
def test_rad_to_the_nearest_tick_is_within_half_a_tick(q, offset, sign, ticks_per_rev):
    j = ServoJoint(1, "j", sign, offset, ticks_per_rev)
    half_tick = math.pi / ticks_per_rev
    assert abs(j.to_rad(j.to_ticks(q)) - q) <= half_tick * (1 + 1e-9)


def test_the_mapping_turns_the_offset_into_zero_and_one_turn_into_two_pi():
    for sign in (1, -1):
        j = ServoJoint(1, "j", sign, 1000, 4096)
        assert j.to_rad(1000) == 0.0
        assert j.to_rad(1000 + 4096) == pytest.approx(sign * 2 * math.pi, abs=0, rel=1e-15)
        assert j.max_ticks == 4095


@pytest.mark.parametrize("q", [math.nan, math.inf, -math.inf])
def test_a_non_finite_joint_position_has_no_tick(q):
    with pytest.raises(ServoBusError, match="'j': position must be finite"):
        ServoJoint(1, "j").to_ticks(q)


@pytest.mark.parametrize(
    "kw, words",
    [
        (dict(id=253), "id must be an integer in"),
        (dict(id=-1), "id must be an integer in"),
        (dict(id=True), "id must be an integer in"),
        (dict(id=1.0), "id must be an integer in"),
        (dict(name=""), "name must be a non-empty string"),
        (dict(sign=0), "sign must be 1 or -1"),
        (dict(sign=2), "sign must be 1 or -1"),
        (dict(ticks_per_rev=1), "ticks_per_rev must be an integer >= 2"),
        (dict(offset_ticks=0.5), "offset_ticks must be an integer"),
    ],
)
def test_a_bad_servo_joint_is_refused_naming_the_field(kw, words):
    args = dict(id=1, name="elbow") | kw
    with pytest.raises(ServoBusError, match=words):
        ServoJoint(**args)


def test_importing_the_bus_drivers_and_twins_loads_neither_serial_nor_torch():
    code = (
        "import sys\n"
        "import robot_io.arms.servo_bus, robot_io.arms.feetech, robot_io.arms.feetech_sim\n"
        "import robot_io.arms.dynamixel, robot_io.arms.dynamixel_sim\n"
        "print(','.join(m for m in ('serial', 'torch', 'sim.ik') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", f"imported eagerly: {out.stdout.strip()}"
