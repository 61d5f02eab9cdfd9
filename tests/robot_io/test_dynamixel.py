"""The Dynamixel Protocol 2.0 driver (Koch) against its byte-level twin, real bytes over a pty.

The behaviour every bus arm shows is :class:`tests.robot_io.test_feetech.BusBehaviour`, run here on
the Dynamixel twin; this file adds the protocol (CRC, byte stuffing, two's complement positions)
and what only a Dynamixel does (answering a corrupted request with a CRC error, the Alert bit).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robot_io.arms.dynamixel import (
    ADDR_TORQUE_ENABLE,
    CRC_TABLE,
    HARDWARE_ERROR_BITS,
    HEADER,
    STATUS_INSTRUCTION,
    XL330_M288_MODEL,
    DynamixelArm,
    crc16,
    decode_position,
    encode_packet,
    encode_position,
    encode_status,
    stuff,
    take_packet,
    unstuff,
)
from robot_io.arms.dynamixel_sim import DynamixelSimulator
from robot_io.arms.servo_bus import PING, READ, WRITE, BadPacket
from tests.robot_io.test_feetech import BusBehaviour, Protocol, bit_named, quantized
from tests.robot_io.test_joint_safety import Q_READY

DYNAMIXEL = Protocol(DynamixelArm, DynamixelSimulator, HARDWARE_ERROR_BITS, XL330_M288_MODEL)


class TestDynamixelBus(BusBehaviour):
    protocol = DYNAMIXEL

    def test_a_servo_answering_a_crc_error_gets_the_same_request_again(self, bus):
        sim, arm = bus()
        sim.corrupt_requests = 1  # the first PING reaches servo 1 corrupted: it answers a CRC error
        arm.connect()
        assert arm.stats["device_crc_errors"] == 1 and arm.stats["resends"] == 1
        assert [i for i, instr in sim.requests if instr == PING] == [j.id for j in arm.joints]
        assert arm.fault() is None

    def test_the_alert_bit_makes_the_next_fault_check_read_the_hardware_error(self, link):
        sim, arm = link
        arm.fault()
        arm.status_interval_s = math.inf  # no periodic poll: only the Alert bit can bring the details
        sim.servo(6).error = bit_named(HARDWARE_ERROR_BITS, "overload")
        arm.joint_positions()  # its status packets carry the Alert bit
        f = arm.fault()
        assert f.kind == "device_fault" and "servo 6 (joint 'panda_joint6')" in f.message
        assert "overload (Hardware_Error_Status 0x20)" in f.message and "rebooted" in f.recovery

    def test_a_hardware_error_turns_the_servos_torque_off(self, link):
        sim, arm = link
        sim.servo(2).error = bit_named(HARDWARE_ERROR_BITS, "input voltage error")
        arm.joint_positions()
        assert sim.servo(2).memory[ADDR_TORQUE_ENABLE] == 0
        np.testing.assert_allclose(arm.joint_positions(), quantized(arm.joints, Q_READY), atol=1e-12)


# ---------------------------------------------------------------------------- the byte protocol


def test_packets_match_the_e_manuals_examples():
    # Robotis e-manual, Protocol 2.0: PING of servo 1, its status (model 1030, firmware 38),
    # WRITE of Goal_Position (116) = 512, READ of Present_Position (132), 4 bytes.
    assert encode_packet(1, PING) == bytes.fromhex("FF FF FD 00 01 03 00 01 19 4E")
    ping_status = bytes.fromhex("FF FF FD 00 01 07 00 55 00 06 04 26 65 5D")
    assert encode_status(1, 0, (1030).to_bytes(2, "little") + bytes([38])) == ping_status
    write = bytes.fromhex("FF FF FD 00 01 09 00 03 74 00 00 02 00 00 CA 89")
    assert encode_packet(1, WRITE, (116).to_bytes(2, "little") + encode_position(512)) == write
    read = bytes.fromhex("FF FF FD 00 01 07 00 02 84 00 04 00 1D 15")
    assert encode_packet(1, READ, (132).to_bytes(2, "little") + (4).to_bytes(2, "little")) == read
    assert take_packet(bytearray(ping_status)) == (1, STATUS_INSTRUCTION, bytes.fromhex("00 06 04 26"))


def test_the_crc_is_the_e_manuals():
    # The head and tail of the e-manual's (and the DynamixelSDK's updateCRC) crc_table.
    assert CRC_TABLE[:8] == (0x0000, 0x8005, 0x800F, 0x000A, 0x801B, 0x001E, 0x0014, 0x8011)
    assert CRC_TABLE[-5:] == (0x8219, 0x0208, 0x820D, 0x8207, 0x0202)
    assert crc16(bytes.fromhex("FF FF FD 00 01 03 00 01")) == 0x4E19


_STUFFY = st.lists(st.sampled_from([0xFF, 0xFD, 0x00]) | st.integers(0, 255), max_size=64).map(bytes)


@settings(max_examples=300, deadline=None)
@given(body=_STUFFY)
def test_byte_stuffing_round_trips_and_leaves_no_header_in_the_body(body):
    stuffed = stuff(body)
    assert unstuff(stuffed) == body
    assert HEADER not in stuffed
    for k in range(len(stuffed) - 2):
        if stuffed[k : k + 3] == b"\xff\xff\xfd":
            assert stuffed[k + 3 : k + 4] == b"\xfd"  # every FF FF FD carries its stuffing byte


def test_stuffing_the_e_manuals_way():
    assert stuff(bytes.fromhex("FF FF FD")) == bytes.fromhex("FF FF FD FD")
    assert stuff(bytes.fromhex("FF FF FD FD")) == bytes.fromhex("FF FF FD FD FD")
    with pytest.raises(ValueError, match="without its stuffing byte"):
        unstuff(bytes.fromhex("01 FF FF FD 02"))


@settings(max_examples=300, deadline=None)
@given(
    servo_id=st.integers(0, 0xFE),
    instruction=st.integers(0, 0xFF),
    params=_STUFFY,
    noise=st.binary(max_size=8).filter(lambda b: 0xFF not in b),
)
def test_a_packet_after_noise_decodes_to_what_was_encoded(servo_id, instruction, params, noise):
    frame = encode_packet(servo_id, instruction, params)
    stuffed_len = int.from_bytes(frame[5:7], "little")
    assert stuffed_len == len(stuff(bytes([instruction]) + params)) + 2 and len(frame) == 7 + stuffed_len
    buf = bytearray(noise + frame)
    assert take_packet(buf) == (servo_id, instruction, params) and buf == bytearray()


def test_a_partial_packet_waits_and_a_bad_crc_is_dropped_and_reported():
    frame = encode_status(5, 0, encode_position(2048))
    buf = bytearray(frame[:-1])
    assert take_packet(buf) is None and bytes(buf) == frame[:-1]
    bad = bytearray(frame[:-1] + bytes([frame[-1] ^ 0x01]) + encode_status(6, 0))
    with pytest.raises(BadPacket, match="CRC mismatch") as err:
        take_packet(bad)
    assert err.value.servo_id == 5 and take_packet(bad) == (6, STATUS_INSTRUCTION, b"\x00")


@settings(max_examples=300, deadline=None)
@given(value=st.integers(-(2**31), 2**31 - 1))
def test_positions_are_four_byte_twos_complement(value):
    data = encode_position(value)
    assert len(data) == 4 and decode_position(data) == value
    unsigned = int.from_bytes(data, "little")
    assert unsigned == value % 2**32  # a negative position wraps to the top of the unsigned range


def test_position_extremes():
    assert decode_position(b"\xff\xff\xff\xff") == -1
    assert decode_position(b"\x00\x00\x00\x80") == -(2**31)
    assert decode_position(b"\xff\xff\xff\x7f") == 2**31 - 1
    for value in (2**31, -(2**31) - 1):
        with pytest.raises(OverflowError):
            encode_position(value)
