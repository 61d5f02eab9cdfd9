"""A byte-level twin of an STS3215 bus (an SO-100/SO-101), for tests and for trying the driver.

The servos (:class:`robot_io.arms.servo_bus.SimServo`: ids, positions, position limits, injectable
error bits and silence) run in a thread on the master end of a pseudo-terminal and answer the
Feetech STS protocol of :mod:`robot_io.arms.feetech` with real bytes, so
:class:`~robot_io.arms.feetech.FeetechArm` opens the slave end like its USB adapter. What the twin
does as an STS3215 does: a goal beyond Min/Max_Position_Limit is clamped to it, Goal_Speed 0 is
full speed, a servo with an error bit set holds still and reports the bits in its status packets
and its Status register, a request with a bad checksum is ignored. Run it standalone with::

    python -m robot_io.arms.feetech_sim      # prints the port to put in the hardware config
"""

from __future__ import annotations

from robot_io.arms.feetech import (
    ADDR_FIRMWARE_MAJOR,
    ADDR_GOAL_POSITION,
    ADDR_GOAL_SPEED,
    ADDR_MAX_POSITION_LIMIT,
    ADDR_MIN_POSITION_LIMIT,
    ADDR_MODEL_NUMBER,
    ADDR_PRESENT_POSITION,
    ADDR_STATUS,
    ADDR_TORQUE_ENABLE,
    STS3215_MODEL,
    decode_position,
    encode_packet,
    encode_position,
    from_sign_magnitude,
    take_packet,
)
from robot_io.arms.pty_twin import serve_until_interrupted
from robot_io.arms.servo_bus import ServoBusSimulator, SimServo

__all__ = ["FeetechSimulator", "FIRMWARE"]

#: Firmware_Major_Version and Firmware_Minor_Version the twin reports.
FIRMWARE = (3, 10)


def _u16(data) -> int:
    return int.from_bytes(bytes(data[:2]), "little")


class FeetechSimulator(ServoBusSimulator):
    """STS3215 servos on a pty (:meth:`~robot_io.arms.servo_bus.ServoBusSimulator.on_pty`)."""

    take_packet = staticmethod(take_packet)
    encode_status = staticmethod(encode_packet)  # a status packet has the instruction's framing, the error as code

    def _split_addr_len(self, params: bytes) -> tuple[int, int, bytes]:
        return params[0], params[1], params[2:]

    def _split_addr(self, params: bytes) -> tuple[int, bytes]:
        return params[0], params[1:]

    def _init_memory(self, servo: SimServo) -> None:
        m = servo.memory
        m[ADDR_FIRMWARE_MAJOR : ADDR_FIRMWARE_MAJOR + 2] = bytes(FIRMWARE)
        m[ADDR_MODEL_NUMBER : ADDR_MODEL_NUMBER + 2] = STS3215_MODEL.to_bytes(2, "little")
        m[ADDR_MIN_POSITION_LIMIT : ADDR_MIN_POSITION_LIMIT + 2] = servo.min_ticks.to_bytes(2, "little")
        m[ADDR_MAX_POSITION_LIMIT : ADDR_MAX_POSITION_LIMIT + 2] = servo.max_ticks.to_bytes(2, "little")
        m[ADDR_TORQUE_ENABLE] = 0
        m[ADDR_GOAL_POSITION : ADDR_GOAL_POSITION + 2] = encode_position(round(servo.position_ticks))

    def _store_present(self, servo: SimServo) -> None:
        m = servo.memory
        m[ADDR_PRESENT_POSITION : ADDR_PRESENT_POSITION + 2] = encode_position(round(servo.position_ticks))
        m[ADDR_STATUS] = servo.error & 0xFF

    def _goal(self, servo: SimServo) -> tuple[float, float, bool]:
        m = servo.memory
        lo, hi = _u16(m[ADDR_MIN_POSITION_LIMIT:]), _u16(m[ADDR_MAX_POSITION_LIMIT:])
        goal = min(max(decode_position(m[ADDR_GOAL_POSITION : ADDR_GOAL_POSITION + 2]), lo), hi)
        speed = abs(from_sign_magnitude(_u16(m[ADDR_GOAL_SPEED:])))
        return float(goal), float(speed), m[ADDR_TORQUE_ENABLE] == 1

    def _check_write(self, servo: SimServo, addr: int, data: bytes) -> tuple[int, bytes]:
        return 0, data  # an STS3215 clamps a goal to its limits rather than refusing it (see _goal)

    def _error_byte(self, servo: SimServo) -> int:
        return servo.error & 0xFF

    def _ping_data(self, servo: SimServo) -> bytes:
        return b""


def main() -> None:
    sim, path = FeetechSimulator.on_pty([SimServo(i) for i in range(1, 7)])
    serve_until_interrupted(sim, f"Feetech STS3215 bus simulator (servos 1-6) on {path}; Ctrl-C to quit")


if __name__ == "__main__":
    main()
