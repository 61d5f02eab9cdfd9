"""A byte-level twin of a Dynamixel X-series bus (a Koch arm), for tests and for trying the driver.

The servos (:class:`robot_io.arms.servo_bus.SimServo`: ids, positions, position limits, injectable
hardware error bits and silence) run in a thread on the master end of a pseudo-terminal and answer
Protocol 2.0 (:mod:`robot_io.arms.dynamixel`: CRC, byte stuffing) with real bytes, so
:class:`~robot_io.arms.dynamixel.DynamixelArm` opens the slave end like its U2D2. What the twin
does as an X-series servo does: a WRITE of a Goal_Position beyond Min/Max_Position_Limit is refused
with a data limit error (a SYNC_WRITE of one is dropped), Profile_Velocity 0 is no limit, a servo
with a hardware error turns its torque off, sets the Alert bit in its status packets and its bits
in Hardware_Error_Status, and a request failing its CRC is answered with a CRC error by the servo
it was addressed to. Run it standalone with::

    python -m robot_io.arms.dynamixel_sim    # prints the port to put in the hardware config
"""

from __future__ import annotations

from robot_io.arms.dynamixel import (
    ADDR_FIRMWARE_VERSION,
    ADDR_GOAL_POSITION,
    ADDR_HARDWARE_ERROR_STATUS,
    ADDR_MAX_POSITION_LIMIT,
    ADDR_MIN_POSITION_LIMIT,
    ADDR_MODEL_NUMBER,
    ADDR_PRESENT_POSITION,
    ADDR_PROFILE_VELOCITY,
    ADDR_TORQUE_ENABLE,
    ALERT_BIT,
    PROFILE_VELOCITY_RPM,
    XL330_M288_MODEL,
    decode_position,
    encode_position,
    encode_status,
    take_packet,
)
from robot_io.arms.pty_twin import serve_until_interrupted
from robot_io.arms.servo_bus import ServoBusSimulator, SimServo

__all__ = ["DynamixelSimulator", "FIRMWARE", "DATA_LIMIT_ERROR", "CRC_ERROR"]

#: Firmware_Version the twin reports.
FIRMWARE = 52
#: The error numbers the twin answers with.
CRC_ERROR = 3
DATA_LIMIT_ERROR = 6
#: The twin's encoder (ticks per turn), as the X-series'.
TICKS_PER_REV = 4096


class DynamixelSimulator(ServoBusSimulator):
    """X-series servos on a pty (:meth:`~robot_io.arms.servo_bus.ServoBusSimulator.on_pty`)."""

    take_packet = staticmethod(take_packet)
    encode_status = staticmethod(encode_status)

    def _split_addr_len(self, params: bytes) -> tuple[int, int, bytes]:
        return int.from_bytes(params[0:2], "little"), int.from_bytes(params[2:4], "little"), params[4:]

    def _split_addr(self, params: bytes) -> tuple[int, bytes]:
        return int.from_bytes(params[0:2], "little"), params[2:]

    def _init_memory(self, servo: SimServo) -> None:
        m = servo.memory
        m[ADDR_MODEL_NUMBER : ADDR_MODEL_NUMBER + 2] = XL330_M288_MODEL.to_bytes(2, "little")
        m[ADDR_FIRMWARE_VERSION] = FIRMWARE
        m[ADDR_MAX_POSITION_LIMIT : ADDR_MAX_POSITION_LIMIT + 4] = encode_position(servo.max_ticks)
        m[ADDR_MIN_POSITION_LIMIT : ADDR_MIN_POSITION_LIMIT + 4] = encode_position(servo.min_ticks)
        m[ADDR_TORQUE_ENABLE] = 0
        m[ADDR_PROFILE_VELOCITY : ADDR_PROFILE_VELOCITY + 4] = bytes(4)
        m[ADDR_GOAL_POSITION : ADDR_GOAL_POSITION + 4] = encode_position(round(servo.position_ticks))

    def _store_present(self, servo: SimServo) -> None:
        m = servo.memory
        m[ADDR_PRESENT_POSITION : ADDR_PRESENT_POSITION + 4] = encode_position(round(servo.position_ticks))
        m[ADDR_HARDWARE_ERROR_STATUS] = servo.error & 0xFF
        if servo.error:
            m[ADDR_TORQUE_ENABLE] = 0  # the Shutdown register's default: torque off on these errors

    def _goal(self, servo: SimServo) -> tuple[float, float, bool]:
        m = servo.memory
        goal = decode_position(m[ADDR_GOAL_POSITION : ADDR_GOAL_POSITION + 4])
        units = int.from_bytes(m[ADDR_PROFILE_VELOCITY : ADDR_PROFILE_VELOCITY + 4], "little")
        speed = units * PROFILE_VELOCITY_RPM * TICKS_PER_REV / 60.0
        return float(goal), speed, m[ADDR_TORQUE_ENABLE] == 1

    def _check_write(self, servo: SimServo, addr: int, data: bytes) -> tuple[int, bytes]:
        at = ADDR_GOAL_POSITION - addr
        if 0 <= at and at + 4 <= len(data):
            m = servo.memory
            lo = decode_position(m[ADDR_MIN_POSITION_LIMIT : ADDR_MIN_POSITION_LIMIT + 4])
            hi = decode_position(m[ADDR_MAX_POSITION_LIMIT : ADDR_MAX_POSITION_LIMIT + 4])
            if not lo <= decode_position(data[at : at + 4]) <= hi:
                return DATA_LIMIT_ERROR, data
        return 0, data

    def _error_byte(self, servo: SimServo) -> int:
        return ALERT_BIT if servo.error else 0

    def _ping_data(self, servo: SimServo) -> bytes:
        m = servo.memory
        return bytes(m[ADDR_MODEL_NUMBER : ADDR_MODEL_NUMBER + 2]) + bytes([m[ADDR_FIRMWARE_VERSION]])

    def _on_bad_request(self, servo_id: int | None) -> None:
        s = self.servos.get(servo_id) if servo_id is not None else None
        if s is not None and not s.silent:
            self._reply(s, CRC_ERROR | self._error_byte(s))


def main() -> None:
    sim, path = DynamixelSimulator.on_pty([SimServo(i) for i in range(1, 7)])
    serve_until_interrupted(sim, f"Dynamixel X-series bus simulator (servos 1-6) on {path}; Ctrl-C to quit")


if __name__ == "__main__":
    main()
