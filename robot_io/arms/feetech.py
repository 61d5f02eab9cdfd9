"""The SO-100/SO-101 arm: Feetech STS3215 servos on one bus, driven with Feetech's STS/SCS byte protocol.

What :class:`FeetechArm` adds to :class:`robot_io.arms.servo_bus.BusArm` is the protocol, spoken
over pyserial (no vendor SDK, no new dependency). From Feetech's SCS/STS communication protocol
manual, its Python SDK (``scservo_sdk``: ``protocol_packet_handler.py``, ``scservo_def.py``) and
LeRobot's ``lerobot/motors/feetech/tables.py`` (``STS_SMS_SERIES_CONTROL_TABLE``)::

    instruction  FF FF  ID  LEN  INSTR  PARAM...  CHK      LEN = len(PARAM) + 2
    status       FF FF  ID  LEN  ERROR  PARAM...  CHK      CHK = ~(ID + LEN + INSTR|ERROR + PARAM...) & 0xFF

The manual's PING of servo 1 is ``FF FF 01 02 01 FB`` and its answer ``FF FF 01 02 00 FC``.
Instructions: PING 0x01, READ 0x02 (addr, length), WRITE 0x03 (addr, data), SYNC_READ 0x82
(addr, length, ids; each servo answers with its own status packet, in the order of the ids),
SYNC_WRITE 0x83 (addr, length, then id + data per servo; broadcast id 0xFE, no answer).
Multi-byte values are little-endian on the STS series (the SCS series is big-endian and is not
supported here); a signed value carries its sign in a bit of its own (sign-magnitude: bit 15 for
positions and speeds, :func:`to_sign_magnitude`).

The STS3215 control table used here (address, bytes): Firmware_Major_Version (0, 1),
Firmware_Minor_Version (1, 1), Model_Number (3, 2; 777 for the STS3215), Min_Position_Limit
(9, 2), Max_Position_Limit (11, 2), Torque_Enable (40, 1), Acceleration (41, 1), Goal_Position
(42, 2), Goal_Time (44, 2), Goal_Speed (46, 2; steps/s, 0 = full speed), Present_Position (56, 2;
0..4095 per turn), Status (65, 1). The goal block written by :meth:`FeetechArm.servo_joints` is
Goal_Position, Goal_Time (0) and Goal_Speed at 42 in one SYNC_WRITE. The error byte of a status
packet and the Status register share their bits: 0x01 input voltage, 0x02 angle sensor, 0x04
overheating, 0x08 overcurrent, 0x20 overload; a Feetech servo clears a bit when its cause is gone.

The SO-100/SO-101 URDF is the user's (TheRobotStudio's SO-ARM100 repository): see
:mod:`robot_io.arms.servo_bus`. LeRobot sets the bus to 1,000,000 baud, the default here.
The twin is :mod:`robot_io.arms.feetech_sim`.
"""

from __future__ import annotations

import math

from robot_io.arms.servo_bus import BadPacket, BusArm, ServoJoint, Status, error_bits_text

__all__ = [
    "FeetechArm",
    "HEADER",
    "STS3215_MODEL",
    "ERROR_BITS",
    "checksum",
    "encode_packet",
    "take_packet",
    "to_sign_magnitude",
    "from_sign_magnitude",
    "encode_position",
    "decode_position",
    "error_text",
]

HEADER = b"\xff\xff"
#: The STS3215's Model_Number.
STS3215_MODEL = 777
#: The bits of a status packet's error byte and of the Status register.
ERROR_BITS = {
    0x01: "input voltage error",
    0x02: "angle sensor error",
    0x04: "overheating",
    0x08: "overcurrent",
    0x20: "overload",
}
#: Position and speed fields carry their sign in this bit (sign-magnitude).
SIGN_BIT = 15
# The control table (address; module docstring).
ADDR_FIRMWARE_MAJOR = 0
ADDR_MODEL_NUMBER = 3
ADDR_MIN_POSITION_LIMIT = 9
ADDR_MAX_POSITION_LIMIT = 11
ADDR_TORQUE_ENABLE = 40
ADDR_GOAL_POSITION = 42
ADDR_GOAL_SPEED = 46
ADDR_PRESENT_POSITION = 56
ADDR_STATUS = 65


def checksum(body: bytes) -> int:
    """``~sum(body) & 0xFF``: the checksum of a packet's bytes between the header and the checksum."""
    return ~sum(body) & 0xFF


def encode_packet(servo_id: int, code: int, params: bytes = b"") -> bytes:
    """One packet: ``code`` is the instruction (host to servo) or the error byte (servo to host)."""
    if len(params) > 0xFD:
        raise ValueError(f"a Feetech packet holds at most 253 parameter bytes, got {len(params)}")
    body = bytes([servo_id, len(params) + 2, code]) + bytes(params)
    return HEADER + body + bytes([checksum(body)])


def take_packet(buf: bytearray) -> tuple[int, int, bytes] | None:
    """``(id, code, params)`` of the first whole packet in ``buf``, removed from it, skipping noise
    before its header; ``None`` while no whole packet has arrived. A packet failing its checksum
    is removed and raises :class:`~robot_io.arms.servo_bus.BadPacket`."""
    while True:
        start = buf.find(HEADER)
        if start < 0:
            del buf[: max(0, len(buf) - 1)]  # a last 0xFF may begin a header
            return None
        del buf[:start]
        if len(buf) < 4:
            return None
        servo_id, length = buf[2], buf[3]
        if servo_id == 0xFF or length < 2:  # FF FF FF: the header starts one byte later
            del buf[0]
            continue
        end = 4 + length
        if len(buf) < end:
            return None
        frame = bytes(buf[:end])
        del buf[:end]
        if frame[-1] != checksum(frame[2:-1]):
            raise BadPacket(f"checksum mismatch in {frame.hex(' ')}", servo_id)
        return servo_id, frame[4], frame[5:-1]


def to_sign_magnitude(value: int, sign_bit: int = SIGN_BIT) -> int:
    """The register value of a signed ``value``: its magnitude, with ``sign_bit`` set when negative."""
    value = int(value)
    if abs(value) >= 1 << sign_bit:
        raise ValueError(f"{value} does not fit a sign-magnitude field with its sign in bit {sign_bit}")
    return (-value) | (1 << sign_bit) if value < 0 else value


def from_sign_magnitude(raw: int, sign_bit: int = SIGN_BIT) -> int:
    """The signed value of a register value with its sign in ``sign_bit``."""
    magnitude = int(raw) & ((1 << sign_bit) - 1)
    return -magnitude if int(raw) & (1 << sign_bit) else magnitude


def encode_position(ticks: int) -> bytes:
    """A position (ticks) as its two register bytes (little-endian, sign in bit 15)."""
    return to_sign_magnitude(ticks).to_bytes(2, "little")


def decode_position(data: bytes) -> int:
    """Ticks from a two-byte position register."""
    return from_sign_magnitude(int.from_bytes(data[:2], "little"))


def error_text(bits: int) -> str:
    """The set bits of an error byte or Status register, in words."""
    return error_bits_text(bits, ERROR_BITS, "error bit", "status")


class FeetechArm(BusArm):
    """An SO-100/SO-101 (or any STS3215 chain) on a Feetech bus adapter.

    ``FeetechArm(port, joints, scene_arm, gripper=None, baudrate=1_000_000, timeout_ms=50.0,
    retries=3, settle_ticks=2, settle_timeout_s=1.0, max_speed_radps=1.0, torque_off_on_close=False)``;
    the arguments are :class:`~robot_io.arms.servo_bus.BusArm`'s.
    """

    name = "feetech"
    protocol = "feetech-sts"
    ADDR_TORQUE_ENABLE = ADDR_TORQUE_ENABLE
    ADDR_GOAL = ADDR_GOAL_POSITION
    ADDR_PRESENT_POSITION = ADDR_PRESENT_POSITION
    SIZE_POSITION = 2
    ADDR_ERROR_STATUS = ADDR_STATUS
    HARDWARE_RECOVERY = (
        "remove the cause (load, heat, supply voltage): a Feetech servo clears the error once it is gone; "
        "then reconnect"
    )
    encode_packet = staticmethod(encode_packet)
    decode_position = staticmethod(decode_position)
    hardware_error_text = staticmethod(error_text)

    def _take_status(self, buf: bytearray) -> Status | None:
        packet = take_packet(buf)
        return None if packet is None else Status(*packet)

    def _addr_len(self, addr: int, size: int) -> bytes:
        return bytes([addr, size])

    def _goal_data(self, joint: ServoJoint, ticks: int, speed_ticks_per_s: float | None) -> bytes:
        # Goal_Speed 0 is the servo's full speed; a commanded speed is at least 1 step/s.
        speed = 0 if speed_ticks_per_s is None else min(max(math.ceil(speed_ticks_per_s), 1), (1 << SIGN_BIT) - 1)
        return encode_position(ticks) + (0).to_bytes(2, "little") + to_sign_magnitude(speed).to_bytes(2, "little")

    def _packet_error(self, error: int) -> tuple[str, str] | None:
        return None if error == 0 else ("hardware", error_text(error))

    def _identify(self, joint: ServoJoint, ping: Status) -> dict[str, str]:
        data = self._read(joint, ADDR_FIRMWARE_MAJOR, ADDR_MODEL_NUMBER + 2)
        model = int.from_bytes(data[ADDR_MODEL_NUMBER : ADDR_MODEL_NUMBER + 2], "little")
        return {"model": str(model), "firmware": f"{data[0]}.{data[1]}"}
