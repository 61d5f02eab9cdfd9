"""The Koch arm: Dynamixel X-series servos on one bus, driven with Robotis' Protocol 2.0.

What :class:`DynamixelArm` adds to :class:`robot_io.arms.servo_bus.BusArm` is the protocol, spoken
over pyserial (no vendor SDK, no new dependency). From the Robotis e-manual's "DYNAMIXEL Protocol
2.0" page, the DynamixelSDK (``python/src/dynamixel_sdk/protocol2_packet_handler.py``: ``updateCRC``,
``addStuffing``, ``removeStuffing``) and LeRobot's ``lerobot/motors/dynamixel/tables.py``
(``X_SERIES_CONTROL_TABLE``)::

    instruction  FF FF FD 00  ID  LEN_L LEN_H  INSTR        PARAM...  CRC_L CRC_H
    status       FF FF FD 00  ID  LEN_L LEN_H  55    ERROR  PARAM...  CRC_L CRC_H

``LEN`` counts the bytes after it (instruction, error, parameters after stuffing, CRC). The CRC is
CRC-16 with polynomial 0x8005, initial value 0, no reflection (the e-manual's ``update_crc`` and
its 256-entry table, which :data:`CRC_TABLE` regenerates: 0x0000, 0x8005, 0x800F, 0x000A, ...),
over every byte from the header to the last parameter, sent little-endian. Byte stuffing: wherever
the instruction and parameters hold ``FF FF FD``, an ``FD`` is inserted after it (``FF FF FD FD``),
so a header never appears inside a packet; ``LEN`` and the CRC are those of the stuffed packet.
The e-manual's PING of servo 1 is ``FF FF FD 00 01 03 00 01 19 4E``. Instructions: PING 0x01
(answer: model number LE16, firmware), READ 0x02 (addr LE16, length LE16), WRITE 0x03 (addr LE16,
data), SYNC_READ 0x82 (addr, length, ids; each servo answers in turn), SYNC_WRITE 0x83 (addr,
length, then id + data per servo; broadcast id 0xFE, no answer). Values are little-endian two's
complement (positions: 4 bytes).

The X-series control table used here (address, bytes): Model_Number (0, 2), Firmware_Version
(6, 1), Max_Position_Limit (48, 4), Min_Position_Limit (52, 4), Torque_Enable (64, 1),
Hardware_Error_Status (70, 1), Profile_Velocity (112, 4; 0.229 rev/min, 0 = no limit, with the
factory velocity-based profile), Goal_Position (116, 4), Present_Position (132, 4; 0..4095 per
turn in position mode). The goal block written by :meth:`DynamixelArm.servo_joints` is
Profile_Velocity and Goal_Position at 112 in one SYNC_WRITE. A status packet's error byte holds an
error number in its low seven bits (1 result fail, 2 instruction, 3 CRC, 4 data range, 5 data
length, 6 data limit, 7 access; a CRC error makes the host resend, the others refuse the
instruction) and the Alert bit 0x80 when Hardware_Error_Status is not zero: 0x01 input voltage,
0x04 overheating, 0x08 motor encoder, 0x10 electrical shock, 0x20 overload. A Dynamixel keeps a
hardware error, with its torque off, until it is rebooted.

Koch's URDF is the user's (its repository): see :mod:`robot_io.arms.servo_bus`. LeRobot sets the
bus to 1,000,000 baud, the default here (a new X-series servo comes at 57,600). The twin is
:mod:`robot_io.arms.dynamixel_sim`.
"""

from __future__ import annotations

import math

from robot_io.arms.servo_bus import BadPacket, BusArm, ServoJoint, Status, error_bits_text

__all__ = [
    "DynamixelArm",
    "HEADER",
    "STATUS_INSTRUCTION",
    "CRC_TABLE",
    "XL330_M288_MODEL",
    "PACKET_ERRORS",
    "HARDWARE_ERROR_BITS",
    "ALERT_BIT",
    "crc16",
    "stuff",
    "unstuff",
    "encode_packet",
    "encode_status",
    "take_packet",
    "encode_position",
    "decode_position",
    "hardware_error_text",
]

HEADER = b"\xff\xff\xfd\x00"
#: The instruction byte of a status packet.
STATUS_INSTRUCTION = 0x55
#: The Model_Number of an XL330-M288 (Koch v1.1's follower; an XL430-W250 is 1060).
XL330_M288_MODEL = 1200
#: A packet longer than this is taken as noise (the SDK's RXPACKET_MAX_LEN).
MAX_PACKET_BYTES = 1024
#: Error numbers in the low seven bits of a status packet's error byte.
PACKET_ERRORS = {
    1: "result fail (the servo failed to process the instruction)",
    2: "instruction error (undefined instruction, or an ACTION without REG_WRITE)",
    3: "CRC error (the request arrived corrupted)",
    4: "data range error (the value is out of range)",
    5: "data length error",
    6: "data limit error (the value exceeds a limit, e.g. Goal_Position beyond Min/Max_Position_Limit)",
    7: "access error (a read-only address, or EEPROM while torque is on)",
}
#: Set in a status packet's error byte while Hardware_Error_Status is not zero.
ALERT_BIT = 0x80
#: The bits of Hardware_Error_Status.
HARDWARE_ERROR_BITS = {
    0x01: "input voltage error",
    0x04: "overheating",
    0x08: "motor encoder error",
    0x10: "electrical shock error",
    0x20: "overload",
}
#: The unit of Profile_Velocity (rev/min).
PROFILE_VELOCITY_RPM = 0.229
# The control table (address; module docstring).
ADDR_MODEL_NUMBER = 0
ADDR_FIRMWARE_VERSION = 6
ADDR_MAX_POSITION_LIMIT = 48
ADDR_MIN_POSITION_LIMIT = 52
ADDR_TORQUE_ENABLE = 64
ADDR_HARDWARE_ERROR_STATUS = 70
ADDR_PROFILE_VELOCITY = 112
ADDR_GOAL_POSITION = 116
ADDR_PRESENT_POSITION = 132


def _crc_table(poly: int = 0x8005) -> tuple[int, ...]:
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ poly) if crc & 0x8000 else crc << 1
        table.append(crc & 0xFFFF)
    return tuple(table)


#: The CRC-16 table of polynomial 0x8005 (the e-manual's ``crc_table``).
CRC_TABLE = _crc_table()


def crc16(data: bytes, crc: int = 0) -> int:
    """Protocol 2.0's CRC-16 of ``data`` (the e-manual's ``update_crc`` from ``crc``)."""
    for b in data:
        crc = ((crc << 8) ^ CRC_TABLE[((crc >> 8) ^ b) & 0xFF]) & 0xFFFF
    return crc


def stuff(body: bytes) -> bytes:
    """``body`` with an ``FD`` inserted after every ``FF FF FD`` (instruction and parameters)."""
    out = bytearray()
    for k, b in enumerate(body):
        out.append(b)
        if b == 0xFD and k >= 2 and body[k - 2] == 0xFF and body[k - 1] == 0xFF:
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes) -> bytes:
    """The inverse of :func:`stuff`; a ``FF FF FD`` not followed by its stuffed ``FD`` is a :class:`ValueError`."""
    out = bytearray()
    k = 0
    while k < len(body):
        out.append(body[k])
        k += 1
        if out[-3:] == b"\xff\xff\xfd":
            if k >= len(body) or body[k] != 0xFD:
                raise ValueError(f"FF FF FD without its stuffing byte at offset {k} of {body.hex(' ')}")
            k += 1
    return bytes(out)


def encode_packet(servo_id: int, instruction: int, params: bytes = b"") -> bytes:
    """One packet: header, id, length, the stuffed instruction and parameters, CRC."""
    body = stuff(bytes([instruction]) + bytes(params))
    frame = HEADER + bytes([servo_id]) + (len(body) + 2).to_bytes(2, "little") + body
    return frame + crc16(frame).to_bytes(2, "little")


def encode_status(servo_id: int, error: int, data: bytes = b"") -> bytes:
    """A status packet (what a servo sends): instruction 0x55, the error byte, then ``data``."""
    return encode_packet(servo_id, STATUS_INSTRUCTION, bytes([error]) + bytes(data))


def take_packet(buf: bytearray) -> tuple[int, int, bytes] | None:
    """``(id, instruction, params)`` (unstuffed) of the first whole packet in ``buf``, removed from
    it, skipping noise before its header; ``None`` while no whole packet has arrived. A packet
    failing its CRC or its stuffing is removed and raises :class:`~robot_io.arms.servo_bus.BadPacket`."""
    while True:
        start = buf.find(HEADER[:3])
        if start < 0:
            del buf[: max(0, len(buf) - 2)]  # the last two bytes may begin a header
            return None
        del buf[:start]
        if len(buf) < 7:
            return None
        length = int.from_bytes(buf[5:7], "little")
        if buf[3] != 0x00 or not 3 <= length <= MAX_PACKET_BYTES:  # not a header (e.g. stuffed FF FF FD FD)
            del buf[0]
            continue
        servo_id, end = buf[4], 7 + length
        if len(buf) < end:
            return None
        frame = bytes(buf[:end])
        del buf[:end]
        if crc16(frame[:-2]) != int.from_bytes(frame[-2:], "little"):
            raise BadPacket(f"CRC mismatch in {frame.hex(' ')}", servo_id)
        try:
            body = unstuff(frame[7:-2])
        except ValueError as err:
            raise BadPacket(str(err), servo_id) from None
        return servo_id, body[0], body[1:]


def encode_position(ticks: int) -> bytes:
    """A position (ticks) as its four register bytes (little-endian two's complement)."""
    return int(ticks).to_bytes(4, "little", signed=True)


def decode_position(data: bytes) -> int:
    """Ticks from a four-byte position register."""
    return int.from_bytes(data[:4], "little", signed=True)


def hardware_error_text(bits: int) -> str:
    """The set bits of Hardware_Error_Status, in words."""
    return error_bits_text(bits, HARDWARE_ERROR_BITS, "hardware error bit", "Hardware_Error_Status")


class DynamixelArm(BusArm):
    """A Koch arm (or any X-series chain) on a Dynamixel bus adapter (U2D2 and alike).

    ``DynamixelArm(port, joints, scene_arm, gripper=None, baudrate=1_000_000, timeout_ms=50.0,
    retries=3, settle_ticks=2, settle_timeout_s=1.0, max_speed_radps=1.0, torque_off_on_close=False)``;
    the arguments are :class:`~robot_io.arms.servo_bus.BusArm`'s.
    """

    name = "dynamixel"
    protocol = "dynamixel-2.0"
    ADDR_TORQUE_ENABLE = ADDR_TORQUE_ENABLE
    ADDR_GOAL = ADDR_PROFILE_VELOCITY
    ADDR_PRESENT_POSITION = ADDR_PRESENT_POSITION
    SIZE_POSITION = 4
    ADDR_ERROR_STATUS = ADDR_HARDWARE_ERROR_STATUS
    HARDWARE_RECOVERY = (
        "remove the cause (load, heat, supply voltage), then power-cycle the arm (a Dynamixel keeps a hardware "
        "error, with its torque off, until it is rebooted) and reconnect"
    )
    encode_packet = staticmethod(encode_packet)
    decode_position = staticmethod(decode_position)
    hardware_error_text = staticmethod(hardware_error_text)

    def _take_status(self, buf: bytearray) -> Status | None:
        while (packet := take_packet(buf)) is not None:
            servo_id, instruction, params = packet
            if instruction != STATUS_INSTRUCTION:
                self.stats["stale_replies"] += 1  # an instruction packet (another host's, or an echo)
                continue
            if not params:
                raise BadPacket(f"status packet of servo {servo_id} without its error byte", servo_id)
            return Status(servo_id, params[0], params[1:])
        return None

    def _addr_len(self, addr: int, size: int) -> bytes:
        return addr.to_bytes(2, "little") + size.to_bytes(2, "little")

    def _goal_data(self, joint: ServoJoint, ticks: int, speed_ticks_per_s: float | None) -> bytes:
        # Profile_Velocity 0 is no limit; a commanded speed is at least one unit (0.229 rev/min).
        if speed_ticks_per_s is None:
            velocity = 0
        else:
            rpm = speed_ticks_per_s * 60.0 / joint.ticks_per_rev
            velocity = min(max(math.ceil(rpm / PROFILE_VELOCITY_RPM), 1), 32767)
        return velocity.to_bytes(4, "little") + encode_position(ticks)

    def _packet_error(self, error: int) -> tuple[str, str] | None:
        number = error & 0x7F
        if number == 3:
            return "resend", PACKET_ERRORS[3]
        if number:
            return "refused", PACKET_ERRORS.get(number, f"error number {number}")
        if error & ALERT_BIT:
            return "hardware", "a hardware error (Alert bit; Hardware_Error_Status not read yet)"
        return None

    def _identify(self, joint: ServoJoint, ping: Status) -> dict[str, str]:
        if len(ping.data) < 3:
            return {}
        return {"model": str(int.from_bytes(ping.data[:2], "little")), "firmware": str(ping.data[2])}
