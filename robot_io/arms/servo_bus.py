"""Arms built from smart servos on one serial bus: LeRobot's SO-100/SO-101 and Koch, and their twins.

An SO-100/SO-101 (Feetech STS3215) or a Koch v1.1 (Dynamixel X-series) is a chain of
position-controlled servos with ids on one half-duplex TTL bus behind a USB adapter. The drivers
speak the vendors' documented byte protocols over pyserial (Feetech STS/SCS in
:mod:`robot_io.arms.feetech`, Dynamixel Protocol 2.0 in :mod:`robot_io.arms.dynamixel`); the
vendor SDKs (``feetech-servo-sdk``, ``dynamixel-sdk``) are thin wrappers of the same bytes, so no
new dependency is needed. This module is what both share: :class:`BusArm`, the joint mapping
:class:`ServoJoint`, and :class:`ServoBusSimulator`, the protocol-neutral part of the twins.

Joints. Each servo turns one joint: ``q = sign * (ticks - offset_ticks) * 2 pi / ticks_per_rev``
(:meth:`ServoJoint.to_rad`, :meth:`ServoJoint.to_ticks`; rad). In position mode a servo moves
within one turn, ticks ``[0, ticks_per_rev - 1]``; a joint target outside it is refused in one
line naming the joint (a target the servo cannot reach, or a wrong ``offset_ticks``): an
:class:`~robot_io.errors.ArmRefusedError`, like an unreachable TCP pose (below), since nothing was
sent and the arm takes the next command. No wrap is applied: a joint's range must lie within one
turn of its servo, which calibration ensures.

Kinematics. A :class:`BusArm` requires a :class:`sim.ik.SceneArm` (URDF chain, base placement,
TCP in the tool link) whose joints are exactly the configured servos' joints (any order; the
arm's joint vectors follow the chain's order). No registry package ships a URDF of these arms and
advobj ships none: the user supplies it (the SO-ARM100/SO-101 URDF from TheRobotStudio's SO-ARM100
repository, Koch's from its repository, AlexanderKoch-Koch/low_cost_robot) and the scene config
names it. :meth:`BusArm.tcp_pose` is the FK of the measured joints, in the scene arm's frame:
the servos report ticks only, so there is no independent TCP to hold the URDF against on connect
(the UR and serial arms check their controller's TCP against the FK,
:func:`robot_io.arms.base.check_kinematics_agree`); ``advobj hw check`` prints the joints, each with its
distance to its limits, to check ``sign`` and ``offset_ticks`` by eye;
:meth:`BusArm.servo` and :meth:`BusArm.move_to` solve the IK from the measured joints and refuse
an unreachable pose in one line (an :class:`~robot_io.errors.ArmRefusedError`, nothing sent). An
optional gripper servo is on the bus (pinged, held, watched for faults) but not in the kinematics
(:meth:`BusArm.gripper_position`, :meth:`BusArm.servo_gripper`).

Commands. :meth:`BusArm.servo_joints` is one SYNC_WRITE of every joint's goal block (goal
position and a speed that gets each joint there in ``duration_s``); :meth:`BusArm.move_joints` the
same, then waits until every joint is within ``settle_ticks`` of its goal. :meth:`BusArm.joint_positions`
is one SYNC_READ of the present positions. :meth:`BusArm.stop` holds the present position (goal =
present, at the servos' full speed). Connecting pings every id (a servo that does not answer is
named), writes goal = present, then enables torque, so nothing moves on connect. Disconnecting
holds the present position and, unless ``torque_off_on_close``, leaves torque on: an arm without
torque falls under gravity.

Link. One request is in flight at a time and the input buffer is flushed before each. A reply
that times out or fails its checksum/CRC makes the host resend the same request; PING, READ,
WRITE and SYNC_READ are idempotent, so a resend never doubles a motion. A SYNC_WRITE is broadcast
and answered by no servo, so it is never resent: the next SYNC_READ finds a servo that stopped
answering. After ``retries`` resends the link counts as lost: an :class:`~robot_io.errors.ArmFaultError`
(``connection_lost``) naming the servos that did not answer, and :meth:`BusArm.fault` reports it
until the arm reconnects.

Faults. :meth:`BusArm.fault` reports ``connection_lost`` (not connected, a servo that did not
answer its ping at connect, a missing reply), and ``device_fault`` from the servos' error bits:
the error byte of every status packet, and every ``status_interval_s`` a SYNC_READ of each
servo's error register (Feetech Status, Dynamixel Hardware_Error_Status).

Twins. :class:`ServoBusSimulator` runs servos with ids, register images, position limits and a
speed limit in a thread on a pty master (:class:`robot_io.arms.pty_twin.PtyTwin`), so a
driver under test exchanges real bytes with it; the protocol modules' simulators add the framing
and the control table. Injected faults: :attr:`SimServo.error` (hardware error bits),
:attr:`SimServo.silent` (a servo that answers nothing), :attr:`ServoBusSimulator.corrupt_replies`
and :attr:`ServoBusSimulator.corrupt_requests`.
"""

from __future__ import annotations

import abc
import logging
import math
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Iterable, Mapping, Sequence

import numpy as np

from robot_io.arms.base import Arm, Fault, tcp_from_joints
from robot_io.arms.pty_twin import PtyTwin
from robot_io.errors import ArmFaultError, ArmRefusedError, ProtocolError, RobotIOError
from robot_io.poses import is_valid_pose, pose_step

if TYPE_CHECKING:
    from sim.ik import SceneArm

__all__ = [
    "BROADCAST_ID",
    "MAX_SERVO_ID",
    "PING",
    "READ",
    "WRITE",
    "SYNC_READ",
    "SYNC_WRITE",
    "ServoBusError",
    "BadPacket",
    "ServoJoint",
    "order_servo_joints",
    "error_bits_text",
    "Request",
    "Status",
    "BusArm",
    "SimServo",
    "ServoBusSimulator",
]

log = logging.getLogger(__name__)

#: The id every servo listens to (both protocols); a broadcast is answered by no servo.
BROADCAST_ID = 0xFE
#: The highest id a servo may have (both protocols).
MAX_SERVO_ID = 0xFC
# Instructions, the same codes in both protocols.
PING = 0x01
READ = 0x02
WRITE = 0x03
SYNC_READ = 0x82
SYNC_WRITE = 0x83

_TWO_PI = 2.0 * math.pi


class ServoBusError(RobotIOError, ValueError):
    """A bus arm's joints or kinematics that do not fit, or a malformed command; one line naming the joint.
    (A well-formed target the arm cannot reach is an :class:`~robot_io.errors.ArmRefusedError`.)"""


class BadPacket(ValueError):
    """A frame whose checksum or CRC does not match; it has been removed from the buffer.

    ``servo_id``: the id in its header (a servo answers a corrupted request with it, in Protocol 2.0).
    """

    def __init__(self, message: str, servo_id: int | None = None):
        super().__init__(message)
        self.servo_id = servo_id


@dataclass(frozen=True)
class ServoJoint:
    """One servo on the bus and the joint it turns.

    ``id``: the servo's bus id (0..252); ``name``: the joint's name in the URDF (or the gripper's);
    ``sign``: +1 when positive ticks turn the joint positively, else -1; ``offset_ticks``: the
    servo's reading at ``q = 0``; ``ticks_per_rev``: the encoder's ticks per turn (4096 for the
    STS3215 and the X-series). The mapping, stated once::

        q_rad = sign * (ticks - offset_ticks) * 2 pi / ticks_per_rev
    """

    id: int
    name: str
    sign: int = 1
    offset_ticks: int = 0
    ticks_per_rev: int = 4096

    def __post_init__(self):
        def integer(x) -> bool:
            return isinstance(x, (int, np.integer)) and not isinstance(x, bool)

        where = f"servo joint {self.name!r}"
        if not isinstance(self.name, str) or not self.name:
            raise ServoBusError(f"servo joint: name must be a non-empty string, got {self.name!r}")
        if not integer(self.id) or not 0 <= self.id <= MAX_SERVO_ID:
            raise ServoBusError(f"{where}: id must be an integer in [0, {MAX_SERVO_ID}], got {self.id!r}")
        if not integer(self.sign) or self.sign not in (1, -1):
            raise ServoBusError(f"{where}: sign must be 1 or -1, got {self.sign!r}")
        if not integer(self.ticks_per_rev) or self.ticks_per_rev < 2:
            raise ServoBusError(f"{where}: ticks_per_rev must be an integer >= 2, got {self.ticks_per_rev!r}")
        if not integer(self.offset_ticks):
            raise ServoBusError(f"{where}: offset_ticks must be an integer, got {self.offset_ticks!r}")

    @property
    def max_ticks(self) -> int:
        """The last tick of the servo's turn in position mode (its first is 0)."""
        return int(self.ticks_per_rev) - 1

    def to_rad(self, ticks: int) -> float:
        """The joint position (rad) of a servo reading ``ticks``."""
        return float(self.sign * (int(ticks) - int(self.offset_ticks)) * (_TWO_PI / int(self.ticks_per_rev)))

    def to_ticks(self, q_rad: float) -> int:
        """The servo position (ticks, nearest) of joint position ``q_rad``; a non-finite one is refused."""
        q = float(q_rad)
        if not math.isfinite(q):
            raise ServoBusError(f"servo joint {self.name!r}: position must be finite, got {q_rad!r}")
        return int(self.offset_ticks) + int(round(self.sign * q * int(self.ticks_per_rev) / _TWO_PI))


def error_bits_text(bits: int, names: Mapping[int, str], unnamed: str, register: str) -> str:
    """The set bits of an 8-bit error byte or register ``bits`` in words, then the register's value:
    ``"overheating, overload (Status 0x24)"``. ``names``: bit -> words; a bit it lacks is
    ``"{unnamed} {k}"``; ``register``: the register's name."""
    words = [names.get(1 << k, f"{unnamed} {k}") for k in range(8) if bits & (1 << k)]
    return ", ".join(words) + f" ({register} 0x{bits:02X})"


@dataclass(frozen=True)
class Request:
    """An instruction packet: the servo id it is for, the instruction, its parameters (unstuffed)."""

    id: int
    instruction: int
    params: bytes = b""


@dataclass(frozen=True)
class Status:
    """A status packet: the servo that sent it, its error byte, its data (unstuffed)."""

    id: int
    error: int
    data: bytes = b""


# ---------------------------------------------------------------------------------------------
# The driver


class BusArm(Arm):
    """A servo-bus arm (module docstring); :class:`~robot_io.arms.feetech.FeetechArm` and
    :class:`~robot_io.arms.dynamixel.DynamixelArm` supply the protocol.

    Args:
        port: the USB adapter (``/dev/serial/by-id/...``, ``/dev/ttyACM0``) or a pyserial URL.
        joints: the arm's servos, one per joint of ``scene_arm`` (any order).
        scene_arm: the :class:`sim.ik.SceneArm` of the user's URDF.
        gripper: the gripper's servo, or ``None``; it is not in the kinematics.
        baudrate: the bus speed the servos are set to.
        timeout_ms: how long to wait for each reply before resending.
        retries: resends before the link counts as lost.
        settle_ticks: :meth:`move_joints` returns once every joint is this close to its goal.
        settle_timeout_s: how much longer than its duration a :meth:`move_joints` may take.
        max_speed_radps: the TCP's rotation speed in :meth:`move_to`.
        torque_off_on_close: release torque on disconnect (the arm then falls under gravity).
    """

    name = "servo_bus"
    #: The protocol's name in :meth:`identity` and messages.
    protocol = "servo bus"
    # The control table (set by each protocol): one byte enabling torque, the first address of
    # the goal block :meth:`_goal_data` writes, the present position and its size in bytes, and
    # the one-byte register of hardware error bits.
    ADDR_TORQUE_ENABLE: int
    ADDR_GOAL: int
    ADDR_PRESENT_POSITION: int
    SIZE_POSITION: int
    ADDR_ERROR_STATUS: int
    #: What the operator does about a servo's hardware error.
    HARDWARE_RECOVERY = "remove the cause (load, heat, supply voltage), then power-cycle the arm and reconnect"
    # The protocol's codec: its module's functions, set by each protocol as staticmethods.
    #: ``(servo_id, instruction, params) -> bytes``: an instruction packet on the wire.
    encode_packet: Callable[[int, int, bytes], bytes]
    #: ``data -> ticks`` of a present-position register.
    decode_position: Callable[[bytes], int]
    #: ``bits -> text``: the error register's set bits in words.
    hardware_error_text: Callable[[int], str]

    def __init__(
        self,
        port: str,
        joints: Sequence[ServoJoint],
        scene_arm: SceneArm,
        gripper: ServoJoint | None = None,
        baudrate: int = 1_000_000,
        timeout_ms: float = 50.0,
        retries: int = 3,
        settle_ticks: int = 2,
        settle_timeout_s: float = 1.0,
        max_speed_radps: float = 1.0,
        torque_off_on_close: bool = False,
    ):
        super().__init__()
        self.port = port
        self.scene_arm = scene_arm
        self.joints = order_servo_joints(self.name, tuple(joints), scene_arm)
        if gripper is not None and not isinstance(gripper, ServoJoint):
            raise ServoBusError(f"{self.name} arm: gripper must be a ServoJoint or None, got {type(gripper).__name__}")
        if gripper is not None and gripper.name in scene_arm.joint_names:
            raise ServoBusError(f"{self.name} arm: the gripper {gripper.name!r} is a joint of the URDF chain")
        self.gripper = gripper
        self.servos: tuple[ServoJoint, ...] = self.joints + ((gripper,) if gripper is not None else ())
        ids = [j.id for j in self.servos]
        if len(set(ids)) != len(ids):
            twice = sorted({i for i in ids if ids.count(i) > 1})
            raise ServoBusError(f"{self.name} arm: servo ids must be unique on the bus; {twice} repeat")
        self._by_id = {j.id: j for j in self.servos}
        self.baudrate = int(baudrate)
        self.timeout_ms = float(timeout_ms)
        self.retries = int(retries)
        self.settle_ticks = int(settle_ticks)
        self.settle_timeout_s = float(settle_timeout_s)
        self.max_speed_radps = float(max_speed_radps)
        self.torque_off_on_close = bool(torque_off_on_close)
        for what, value in (("timeout_ms", self.timeout_ms), ("max_speed_radps", self.max_speed_radps)):
            if not (math.isfinite(value) and value > 0):
                raise ServoBusError(f"{self.name} arm: {what} must be a positive number, got {value}")
        if self.retries < 0 or self.settle_ticks < 0 or not self.settle_timeout_s >= 0:
            raise ServoBusError(f"{self.name} arm: retries, settle_ticks and settle_timeout_s must be >= 0")
        #: Faults are re-read from the servos at most this often (seconds) by :meth:`fault`.
        self.status_interval_s = 0.2
        self.device_info: dict[int, dict[str, str]] = {}
        self.stats = {"resends": 0, "checksum_errors": 0, "timeouts": 0, "stale_replies": 0, "device_crc_errors": 0}
        self._ser = None
        self._buf = bytearray()
        self._lock = threading.RLock()
        self._link_lost: str | None = None
        self._connect_fault: Fault | None = None
        self._servo_faults: dict[int, str] = {}
        self._last_poll_s = -math.inf
        self._poll_due = True
        self._last_ticks: tuple[float, dict[int, int]] | None = None

    # ------------------------------------------------------------------ protocol (per vendor)
    @abc.abstractmethod
    def _take_status(self, buf: bytearray) -> Status | None:
        """The first status packet in ``buf``, removed from it; ``None`` while incomplete.
        Raises :class:`BadPacket` (after removing it) for a frame failing its checksum."""

    @abc.abstractmethod
    def _addr_len(self, addr: int, size: int) -> bytes:
        """An address and a data length as parameters (READ, SYNC_READ, SYNC_WRITE)."""

    @abc.abstractmethod
    def _goal_data(self, joint: ServoJoint, ticks: int, speed_ticks_per_s: float | None) -> bytes:
        """The goal block at :attr:`ADDR_GOAL`: go to ``ticks`` at ``speed_ticks_per_s`` (``None``: full speed)."""

    @abc.abstractmethod
    def _packet_error(self, error: int) -> tuple[str, str] | None:
        """What a status packet's error byte means: ``None`` (no error), ``("hardware", text)``,
        ``("refused", text)`` (the servo refused the instruction) or ``("resend", text)`` (it
        received a corrupted request)."""

    @abc.abstractmethod
    def _identify(self, joint: ServoJoint, ping: Status) -> dict[str, str]:
        """What the servo says about itself after its ping (``model``, ``firmware``)."""

    # ------------------------------------------------------------------ link
    def _open(self) -> None:
        import serial  # lazy: robot_io start-up (serial)

        self._connect_fault = None
        try:
            self._ser = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=0.01)
        except (serial.SerialException, OSError, ValueError) as err:
            self._connect_fault = Fault(
                "connection_lost",
                f"{self.protocol} bus: cannot open serial port {self.port}: {err}",
                "check the USB cable and the port name (ls /dev/serial/by-id/)",
            )
            raise ArmFaultError(self._connect_fault) from None
        self._buf.clear()
        self._link_lost = None
        self._servo_faults = {}
        self._poll_due = True
        self._last_ticks = None
        self.device_info = {}
        try:
            for joint in self.servos:
                self.device_info[joint.id] = self._identify(joint, self._ping(joint))
            self._hold()
            self._sync_write(self.ADDR_TORQUE_ENABLE, {j.id: b"\x01" for j in self.servos})
            self._poll_faults()
        except BaseException as err:
            if isinstance(err, ArmFaultError):
                self._connect_fault = err.fault
            self._ser.close()
            self._ser = None
            raise

    def _close(self) -> None:
        if self._ser is None:
            return
        try:
            self._hold()
            if self.torque_off_on_close:
                self._sync_write(self.ADDR_TORQUE_ENABLE, {j.id: b"\x00" for j in self.servos})
        except Exception as err:  # noqa: BLE001 - the link may already be gone; closing must still happen
            log.warning("%s bus on %s: holding position on disconnect failed (%s)", self.protocol, self.port, err)
        finally:
            ser, self._ser = self._ser, None
            ser.close()

    def identity(self) -> dict[str, str]:
        out = {"port": self.port, "protocol": self.protocol, "servo_ids": ",".join(str(j.id) for j in self.servos)}
        for key in ("model", "firmware"):
            values = [f"{i}:{info[key]}" for i, info in self.device_info.items() if key in info]
            if values:
                out[key + "s"] = ",".join(values)
        return out

    def _label(self, servo_id: int) -> str:
        joint = self._by_id.get(servo_id)
        return f"servo {servo_id}" + (f" (joint {joint.name!r})" if joint is not None else "")

    def _lost_fault(self) -> Fault:
        return Fault(
            "connection_lost",
            f"{self.protocol} bus on {self.port}: {self._link_lost}",
            "check the servo cables, the bus power supply and the ids, then reconnect",
        )

    def _not_connected(self) -> Fault:
        return self._connect_fault or Fault(
            "connection_lost", f"{self.protocol} bus on {self.port} is not connected", "call connect()"
        )

    def _collect(self, expect: tuple[int, ...]) -> dict[int, Status]:
        """The status packets from ``expect`` arriving within the timeout (fewer on a timeout or a corrupt frame)."""
        got: dict[int, Status] = {}
        corrupt = 0
        deadline = time.monotonic() + self.timeout_ms / 1000.0
        while len(got) + corrupt < len(expect):
            try:
                status = self._take_status(self._buf)
            except BadPacket as err:
                corrupt += 1
                self.stats["checksum_errors"] += 1
                log.warning("%s bus on %s: discarding a reply (%s)", self.protocol, self.port, err)
                continue
            if status is not None:
                if status.id in expect and status.id not in got:
                    got[status.id] = status
                else:
                    self.stats["stale_replies"] += 1
                continue
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self.stats["timeouts"] += 1
                break
            self._ser.timeout = min(remaining, 0.01)
            chunk = self._ser.read(max(1, self._ser.in_waiting))
            if chunk:
                self._buf.extend(chunk)
        return got

    def _exchange(self, what: str, servo_id: int, instruction: int, params: bytes, expect: tuple[int, ...]):
        """Send one instruction and return ``{id: Status}`` of every servo in ``expect``.

        Resends on a missing or corrupt reply (module docstring); raises :class:`ArmFaultError`
        (``connection_lost``, naming the servos) when the retries run out, :class:`ProtocolError`
        when a servo refuses the instruction. Hardware error bits are recorded for :meth:`fault`.
        """
        if self._ser is None:
            raise ArmFaultError(self._not_connected())
        frame = self.encode_packet(servo_id, instruction, params)
        with self._lock:
            got: dict[int, Status] = {}
            attempts = self.retries + 1 if expect else 1
            for attempt in range(attempts):
                if attempt:
                    self.stats["resends"] += 1
                try:
                    self._ser.reset_input_buffer()
                    self._buf.clear()
                    self._ser.write(frame)
                    if not expect:
                        return {}
                    got = self._collect(expect)
                except OSError as err:  # pyserial's SerialException is an OSError: unplugged, port gone
                    self._link_lost = f"serial I/O error ({err})"
                    raise ArmFaultError(self._lost_fault()) from None
                resend = [i for i, s in got.items() if (self._packet_error(s.error) or ("",))[0] == "resend"]
                if resend:
                    self.stats["device_crc_errors"] += 1  # a servo received a corrupted request
                    continue
                if len(got) == len(expect):
                    for status in got.values():
                        self._check_status(what, status)
                    return got
            missing = [i for i in expect if i not in got or (self._packet_error(got[i].error) or ("",))[0] == "resend"]
            self._link_lost = (
                f"no valid reply to {what} from {', '.join(self._label(i) for i in missing)} after "
                f"{attempts} attempts of {self.timeout_ms:.0f} ms"
            )
            raise ArmFaultError(self._lost_fault())

    def _check_status(self, what: str, status: Status) -> None:
        meaning = self._packet_error(status.error)
        if meaning is None:
            return
        kind, text = meaning
        if kind == "hardware":
            self._servo_faults.setdefault(status.id, text)
            self._poll_due = True  # the next fault() reads the error registers for the details
            return
        raise ProtocolError(f"{self.protocol} bus on {self.port}: {self._label(status.id)} refused {what}: {text}")

    def _ping(self, joint: ServoJoint) -> Status:
        try:
            return self._exchange("PING", joint.id, PING, b"", (joint.id,))[joint.id]
        except ArmFaultError:
            self._link_lost = f"{self._label(joint.id)} does not answer ping"
            raise ArmFaultError(
                Fault(
                    "connection_lost",
                    f"{self.protocol} bus on {self.port}: {self._link_lost} ({self.retries + 1} attempts of "
                    f"{self.timeout_ms:.0f} ms at {self.baudrate} baud)",
                    f"check that servo's cable and power, and that its id is {joint.id} and its baud rate "
                    f"{self.baudrate} (the vendor's setup tool)",
                )
            ) from None

    def _read(self, joint: ServoJoint, addr: int, size: int) -> bytes:
        """``size`` bytes of one servo's control table from ``addr``."""
        status = self._exchange(f"READ {addr}", joint.id, READ, self._addr_len(addr, size), (joint.id,))[joint.id]
        if len(status.data) != size:
            raise ProtocolError(
                f"{self.protocol} bus on {self.port}: {self._label(joint.id)} answered READ {addr} with "
                f"{len(status.data)} bytes, not {size}"
            )
        return status.data

    def _sync_read(self, joints: Sequence[ServoJoint], addr: int, size: int) -> dict[int, bytes]:
        """``{id: size bytes from addr}`` of every servo in ``joints``, in one SYNC_READ."""
        ids = tuple(j.id for j in joints)
        got = self._exchange(f"SYNC_READ {addr}", BROADCAST_ID, SYNC_READ, self._addr_len(addr, size) + bytes(ids), ids)
        for i, status in got.items():
            if len(status.data) != size:
                raise ProtocolError(
                    f"{self.protocol} bus on {self.port}: {self._label(i)} answered SYNC_READ {addr} with "
                    f"{len(status.data)} bytes, not {size}"
                )
        return {i: got[i].data for i in ids}

    def _sync_write(self, addr: int, data: dict[int, bytes]) -> None:
        """One SYNC_WRITE of ``data[id]`` (all the same length) at ``addr``; no servo answers it."""
        sizes = {len(d) for d in data.values()}
        if len(sizes) != 1:
            raise ValueError(f"a SYNC_WRITE writes the same number of bytes to every servo, got sizes {sorted(sizes)}")
        params = self._addr_len(addr, sizes.pop()) + b"".join(bytes([i]) + d for i, d in data.items())
        self._exchange(f"SYNC_WRITE {addr}", BROADCAST_ID, SYNC_WRITE, params, ())

    # ------------------------------------------------------------------ state
    def _read_ticks(self) -> dict[int, int]:
        """Every servo's present position (ticks), in one SYNC_READ."""
        data = self._sync_read(self.servos, self.ADDR_PRESENT_POSITION, self.SIZE_POSITION)
        ticks = {i: self.decode_position(d) for i, d in data.items()}
        self._last_ticks = (time.monotonic(), ticks)
        return ticks

    def _fresh_ticks(self, max_age_s: float) -> dict[int, int]:
        # The safety layer has usually just read the joints: reuse them rather than ask again.
        if self._last_ticks is not None and time.monotonic() - self._last_ticks[0] < max_age_s:
            return self._last_ticks[1]
        return self._read_ticks()

    def _poll_faults(self) -> None:
        data = self._sync_read(self.servos, self.ADDR_ERROR_STATUS, 1)
        self._servo_faults = {i: self.hardware_error_text(d[0]) for i, d in data.items() if d[0]}
        self._last_poll_s = time.monotonic()
        self._poll_due = False

    def _servo_fault(self) -> Fault | None:
        for joint in self.servos:
            if joint.id in self._servo_faults:
                return Fault(
                    "device_fault",
                    f"{self.protocol} bus on {self.port}: {self._label(joint.id)} reports "
                    f"{self._servo_faults[joint.id]}",
                    self.HARDWARE_RECOVERY,
                )
        return None

    def fault(self) -> Fault | None:
        if self._ser is None:
            return self._not_connected()
        if self._link_lost:
            return self._lost_fault()
        if self._poll_due or time.monotonic() - self._last_poll_s > self.status_interval_s:
            try:
                self._poll_faults()
            except ArmFaultError as err:
                return err.fault
        return self._servo_fault()

    def _require_no_fault(self) -> None:
        if self._ser is None:
            raise ArmFaultError(self._not_connected())
        if self._link_lost:
            raise ArmFaultError(self._lost_fault())
        fault = self._servo_fault()
        if fault is not None:
            raise ArmFaultError(fault)

    # ------------------------------------------------------------------ joints
    def kinematics(self) -> SceneArm:
        return self.scene_arm

    def joint_positions(self) -> np.ndarray:
        ticks = self._read_ticks()
        return np.array([j.to_rad(ticks[j.id]) for j in self.joints], dtype=np.float64)

    def _check_q(self, q) -> np.ndarray:
        n = len(self.joints)
        try:
            q = np.asarray(q, dtype=np.float64)
        except (TypeError, ValueError):
            raise ServoBusError(f"{self.name} arm: a joint target is {n} numbers (rad), got {q!r}") from None
        if q.shape != (n,) or not np.isfinite(q).all():
            got = f"shape {q.shape}" if q.shape != (n,) else f"{q.tolist()}"
            raise ServoBusError(
                f"{self.name} arm: a joint target is {n} finite numbers (rad) for "
                f"{', '.join(j.name for j in self.joints)}; got {got}"
            )
        return q

    def _goal_ticks(self, joint: ServoJoint, q_rad: float) -> int:
        ticks = joint.to_ticks(q_rad)
        if not 0 <= ticks <= joint.max_ticks:
            raise ArmRefusedError(
                f"{self.name} arm: joint {joint.name!r} at {q_rad:.6g} rad is tick {ticks}, outside its servo's turn "
                f"[0, {joint.max_ticks}] (offset_ticks {joint.offset_ticks}, sign {joint.sign}): the servo cannot "
                "reach it, or offset_ticks is wrong; nothing was sent"
            )
        return ticks

    def _write_goals(self, goals: dict[int, int], duration_s: float) -> None:
        if not (math.isfinite(duration_s) and duration_s > 0):
            raise ServoBusError(f"{self.name} arm: duration_s must be a positive number, got {duration_s}")
        now = self._fresh_ticks(duration_s)
        self._sync_write(
            self.ADDR_GOAL,
            {i: self._goal_data(self._by_id[i], t, abs(t - now[i]) / duration_s) for i, t in goals.items()},
        )

    def servo_joints(self, q: np.ndarray, duration_s: float) -> None:
        q = self._check_q(q)
        goals = {j.id: self._goal_ticks(j, x) for j, x in zip(self.joints, q)}
        self._require_no_fault()
        self._write_goals(goals, float(duration_s))

    def move_joints(self, q: np.ndarray, duration_s: float) -> None:
        q = self._check_q(q)
        goals = {j.id: self._goal_ticks(j, x) for j, x in zip(self.joints, q)}
        self._require_no_fault()
        self._write_goals(goals, float(duration_s))
        self._settle(goals, float(duration_s))

    def _settle(self, goals: dict[int, int], duration_s: float) -> None:
        """Wait until every servo in ``goals`` is within :attr:`settle_ticks`; stop and raise if not in time."""
        t0 = time.monotonic()
        deadline = t0 + 1.5 * duration_s + self.settle_timeout_s
        while True:
            ticks = self._read_ticks()
            off = {i: abs(ticks[i] - g) for i, g in goals.items()}
            if max(off.values()) <= self.settle_ticks:
                return
            fault = self._servo_fault()
            if fault is not None:
                self._hold()
                raise ArmFaultError(fault)
            if time.monotonic() > deadline:
                self._hold()
                worst = max(off, key=off.get)
                raise ProtocolError(
                    f"{self.protocol} bus on {self.port}: {self._label(worst)} is {off[worst]} ticks from its goal "
                    f"{time.monotonic() - t0:.2f} s into a {duration_s:.2f} s move (blocked, or its torque is off); "
                    "the arm holds where it is"
                )
            time.sleep(0.005)

    def _hold(self) -> None:
        """Goal = present position for every servo, at full speed (the servos stop where they are)."""
        ticks = self._read_ticks()
        self._sync_write(self.ADDR_GOAL, {j.id: self._goal_data(j, ticks[j.id], None) for j in self.servos})

    def stop(self) -> None:
        self._hold()

    def gripper_position(self) -> float:
        """The gripper servo's position (rad, its :class:`ServoJoint` mapping)."""
        if self.gripper is None:
            raise ServoBusError(f"the {self.name} arm has no gripper servo configured")
        return self.gripper.to_rad(self._read_ticks()[self.gripper.id])

    def servo_gripper(self, q_rad: float, duration_s: float) -> None:
        """Stream one gripper target (rad) to be reached in ``duration_s``; returns immediately."""
        if self.gripper is None:
            raise ServoBusError(f"the {self.name} arm has no gripper servo configured")
        goal = self._goal_ticks(self.gripper, float(q_rad))
        self._require_no_fault()
        self._write_goals({self.gripper.id: goal}, float(duration_s))

    # ------------------------------------------------------------------ TCP
    def _fk(self, q: np.ndarray) -> np.ndarray:
        return tcp_from_joints(self.scene_arm, q)

    def _ik(self, T_base_tcp: np.ndarray, q_seed: np.ndarray) -> np.ndarray:
        import torch  # lazy: robot_io start-up (torch)

        from sim.ik import IkError  # lazy: robot_io start-up (torch)

        limits = self.scene_arm.model.limits
        # A measured joint may read a fraction of a tick beyond its URDF limit; the IK seed may not.
        seed = np.clip(q_seed, limits.q_min.cpu().numpy(), limits.q_max.cpu().numpy())
        like = torch.as_tensor(seed, dtype=torch.float64, device=self.scene_arm.device)[None]
        T = torch.as_tensor(T_base_tcp, dtype=torch.float64, device=like.device)[None]
        try:
            return self.scene_arm.ik(T, like).require("TCP target")[0].cpu().numpy()
        except IkError as err:  # nothing was sent: the arm takes the next command
            raise ArmRefusedError(f"{self.name} arm: {err}; the arm did not move") from None

    def _check_pose(self, T_base_tcp) -> np.ndarray:
        if not is_valid_pose(T_base_tcp):
            raise ServoBusError(f"{self.name} arm: a TCP target is a finite rigid (4, 4) transform")
        return np.asarray(T_base_tcp, dtype=np.float64)

    def tcp_pose(self) -> np.ndarray:
        return self._fk(self.joint_positions())

    def servo(self, T_base_tcp: np.ndarray, duration_s: float) -> None:
        T = self._check_pose(T_base_tcp)
        ticks = self._fresh_ticks(float(duration_s))
        q_now = np.array([j.to_rad(ticks[j.id]) for j in self.joints])
        self.servo_joints(self._ik(T, q_now), duration_s)

    def move_to(self, T_base_tcp: np.ndarray, speed_mps: float) -> None:
        T = self._check_pose(T_base_tcp)
        if not (math.isfinite(speed_mps) and speed_mps > 0):
            raise ServoBusError(f"{self.name} arm: speed_mps must be a positive number, got {speed_mps}")
        q_now = self.joint_positions()
        q = self._ik(T, q_now)
        dp, dr = pose_step(self._fk(q_now), T)
        qd_max = self.scene_arm.model.limits.qd_max.cpu().numpy()
        # As long as the TCP needs at its speeds, and no joint faster than its URDF velocity limit.
        duration_s = max(dp / float(speed_mps), dr / self.max_speed_radps, float(np.max(np.abs(q - q_now) / qd_max)))
        self.move_joints(q, max(duration_s, 1e-3))


def order_servo_joints(arm: str, joints: Sequence[ServoJoint], chain) -> tuple[ServoJoint, ...]:
    """The servos ``joints`` in the order of ``chain``'s joints (a bus arm's joint vectors follow it).

    ``chain``: anything with ``joint_names`` and ``units`` in the chain's order (a
    :class:`sim.ik.SceneArm` or a :class:`sim.kinematics.ArmChain`). ``joints`` must be exactly the
    chain's joints, each once, in any order, and every chain joint revolute (a servo turns it);
    otherwise one :class:`ServoBusError` line, prefixed ``"{arm} arm: "`` (``arm``: the arm type,
    ``"feetech"``), naming the joints missing, not in the URDF chain, repeated or prismatic.
    :class:`BusArm` and the hardware config's check (:func:`robot_io.config.hardware_config_from_dict`)
    both call it, so a config and a driver refuse the same joints with the same line.
    """
    for j in joints:
        if not isinstance(j, ServoJoint):
            raise ServoBusError(f"{arm} arm: joints must be ServoJoint entries, got {type(j).__name__}")
    names = list(chain.joint_names)
    given = [j.name for j in joints]
    if sorted(given) != sorted(names) or len(set(given)) != len(given):
        missing = [n for n in names if n not in given]
        unknown = [n for n in given if n not in names]
        twice = sorted({n for n in given if given.count(n) > 1})
        detail = "; ".join(
            f"{what}: {', '.join(items)}"
            for what, items in (("missing", missing), ("not in the URDF chain", unknown), ("twice", twice))
            if items
        )
        raise ServoBusError(
            f"{arm} arm: the configured joints must be the URDF chain's joints ({', '.join(names)}); {detail}"
        )
    bad_units = [n for n, u in zip(names, chain.units) if u != "rad"]
    if bad_units:
        raise ServoBusError(f"{arm} arm: a servo turns a revolute joint; {', '.join(bad_units)} is prismatic")
    by_name = {j.name: j for j in joints}
    return tuple(by_name[n] for n in names)


# ---------------------------------------------------------------------------------------------
# The twins' shared part


@dataclass
class SimServo:
    """One simulated servo: its control table, its motion, and what a test injects.

    ``position_ticks``: where it is; ``min_ticks``/``max_ticks``: its position limits (a goal is
    clamped, or refused, as the protocol's servos do); ``error``: hardware error bits in the
    protocol's layout (set: the servo stops and reports them); ``silent``: it answers nothing and
    ignores every write (a cut cable, a wrong id).
    """

    id: int
    position_ticks: float = 2048.0
    min_ticks: int = 0
    max_ticks: int = 4095
    error: int = 0
    silent: bool = False
    memory: bytearray = field(default_factory=lambda: bytearray(256))


class ServoBusSimulator(PtyTwin):
    """The servos on a simulated bus, in a thread on a pty master; the protocol modules add the bytes.

    Args:
        fd: the pty master (:func:`robot_io.arms.pty_twin.open_pty_pair`; :meth:`on_pty` opens one and
            takes the other arguments).
        servos: the servos on the bus.
        keep_fd: the slave fd to keep open while the simulator runs (see ``open_pty_pair``).
        max_speed_ticks_per_s: the servos' top speed (a goal speed of 0, or above it, runs at it).

    Fault injection: :attr:`SimServo.error`, :attr:`SimServo.silent`, ``corrupt_replies`` (the next
    replies go out with a wrong checksum), ``corrupt_requests`` (the next requests are taken as
    received corrupted), ``reply_delay_s``.
    """

    def __init__(
        self,
        fd: int,
        servos: Iterable[SimServo],
        keep_fd: int | None = None,
        max_speed_ticks_per_s: float = 3000.0,
    ):
        super().__init__(fd, keep_fd)
        self.servos: dict[int, SimServo] = {}
        for s in servos:
            if s.id in self.servos:
                raise ValueError(f"servo id {s.id} appears twice on the simulated bus")
            self.servos[s.id] = s
            self._init_memory(s)
            self._store_present(s)
        self.max_speed_ticks_per_s = float(max_speed_ticks_per_s)
        self.corrupt_replies = 0
        self.corrupt_requests = 0
        self.reply_delay_s = 0.0
        #: ``(id, instruction)`` of every request received intact, in order (tests read it).
        self.requests: list[tuple[int, int]] = []
        self._buf = bytearray()
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ protocol (per vendor)
    # The protocol's codec: its module's functions, set by each protocol as staticmethods.
    #: ``buf -> (id, instruction, params) | None``: the first whole packet in ``buf``, removed from
    #: it (``None`` while incomplete); raises :class:`BadPacket` for one failing its checksum.
    take_packet: Callable[[bytearray], tuple[int, int, bytes] | None]
    #: ``(servo_id, error, data) -> bytes``: a status packet on the wire.
    encode_status: Callable[[int, int, bytes], bytes]

    def _take_request(self, buf: bytearray) -> Request | None:
        """The first instruction packet in ``buf``, removed from it; raises :class:`BadPacket`."""
        packet = self.take_packet(buf)
        return None if packet is None else Request(*packet)

    @abc.abstractmethod
    def _split_addr_len(self, params: bytes) -> tuple[int, int, bytes]:
        """``(addr, size, rest)`` of READ, SYNC_READ and SYNC_WRITE parameters."""

    @abc.abstractmethod
    def _split_addr(self, params: bytes) -> tuple[int, bytes]:
        """``(addr, data)`` of WRITE parameters."""

    @abc.abstractmethod
    def _init_memory(self, servo: SimServo) -> None:
        """Fill the control table at power-on (model, limits, goal = present, torque off)."""

    @abc.abstractmethod
    def _store_present(self, servo: SimServo) -> None:
        """Write the present position and the error register into the control table."""

    @abc.abstractmethod
    def _goal(self, servo: SimServo) -> tuple[float, float, bool]:
        """``(goal_ticks, speed_ticks_per_s, torque_on)`` from the control table (speed 0: full speed)."""

    @abc.abstractmethod
    def _check_write(self, servo: SimServo, addr: int, data: bytes) -> tuple[int, bytes]:
        """``(packet_error, data_to_store)`` of a write: the protocol's refusal or clamping."""

    @abc.abstractmethod
    def _error_byte(self, servo: SimServo) -> int:
        """The error byte of the servo's status packets."""

    @abc.abstractmethod
    def _ping_data(self, servo: SimServo) -> bytes:
        """The parameters of the servo's reply to PING."""

    def _on_bad_request(self, servo_id: int | None) -> None:
        """A request arrived corrupted; a servo ignores it unless the protocol answers it."""

    # ------------------------------------------------------------------ state
    def servo(self, servo_id: int) -> SimServo:
        return self.servos[servo_id]

    def place(self, servo_id: int, ticks: float) -> None:
        """Put a servo at ``ticks`` (an arm moved by hand while its torque is off)."""
        with self._lock:
            s = self.servos[servo_id]
            s.position_ticks = float(ticks)
            self._store_present(s)

    # ------------------------------------------------------------------ I/O
    def _reply(self, servo: SimServo, error: int, data: bytes = b"") -> None:
        frame = self.encode_status(servo.id, error, data)
        if self.corrupt_replies > 0:
            self.corrupt_replies -= 1
            frame = frame[:-1] + bytes([frame[-1] ^ 0xFF])
        if self.reply_delay_s:
            time.sleep(self.reply_delay_s)
        self._send(frame)

    def _serve(self, data: bytes, dt_s: float, now_s: float) -> None:
        with self._lock:
            self._tick(dt_s)  # first: a request reads the state as of its arrival
            self._buf.extend(data)
            while True:
                try:
                    req = self._take_request(self._buf)
                except BadPacket as err:
                    self._on_bad_request(err.servo_id)
                    continue
                if req is None:
                    break
                if self.corrupt_requests > 0:
                    self.corrupt_requests -= 1
                    self._on_bad_request(req.id)
                    continue
                self.requests.append((req.id, req.instruction))
                self._handle(req)

    def _tick(self, dt: float) -> None:
        for s in self.servos.values():
            goal, speed, torque = self._goal(s)
            if torque and not s.error:
                v = self.max_speed_ticks_per_s if speed <= 0 else min(speed, self.max_speed_ticks_per_s)
                step = goal - s.position_ticks
                s.position_ticks = goal if abs(step) <= v * dt else s.position_ticks + math.copysign(v * dt, step)
            self._store_present(s)

    def _write(self, servo: SimServo, addr: int, data: bytes) -> int:
        error, data = self._check_write(servo, addr, data)
        if not error:
            servo.memory[addr : addr + len(data)] = data
        return error

    def _handle(self, req: Request) -> None:
        if req.instruction == SYNC_WRITE:
            addr, size, rest = self._split_addr_len(req.params)
            for k in range(0, len(rest) - size, size + 1) if size else ():
                s = self.servos.get(rest[k])
                if s is not None and not s.silent:
                    self._write(s, addr, rest[k + 1 : k + 1 + size])
            return
        if req.instruction == SYNC_READ:
            addr, size, ids = self._split_addr_len(req.params)
            for i in ids:
                s = self.servos.get(i)
                if s is not None and not s.silent:
                    self._reply(s, self._error_byte(s), bytes(s.memory[addr : addr + size]))
            return
        s = self.servos.get(req.id)
        if s is None or s.silent:
            return
        if req.instruction == PING:
            self._reply(s, self._error_byte(s), self._ping_data(s))
        elif req.instruction == READ:
            addr, size, _ = self._split_addr_len(req.params)
            self._reply(s, self._error_byte(s), bytes(s.memory[addr : addr + size]))
        elif req.instruction == WRITE:
            addr, data = self._split_addr(req.params)
            self._reply(s, self._write(s, addr, data) or self._error_byte(s))
