"""A serial-line arm controller speaking the advobj line protocol (``docs/serial-protocol.md``).

Framing (v1), ASCII, one line per message::

    host   -> device   >SEQ CMD ARG...*CS\\n
    device -> host     <SEQ OK FIELD...*CS\\n   or   <SEQ ERR CODE...*CS\\n
    device -> host     #TEXT\\n                (unsolicited: boot banner, fault notices)
    host   -> device   !                       (one byte, outside framing: stop now)

``CS`` is the XOR of the bytes between the start character and ``*``, as two hex digits. One
command is in flight at a time. A reply that times out or fails its checksum, and an ``ERR CHK``,
make the host resend the *same* ``SEQ``; the device answers a repeated ``SEQ`` from its reply
cache without executing it again, so a resend never doubles a motion.

Given ``kinematics`` (the arm's :class:`sim.ik.SceneArm`), the host also sends joint commands:
``JOINTS`` (measured joints) and ``MOVEJ q1 .. qn duration``. It asks ``JOINTS`` on connect, so a
firmware without joint commands (``ERR UNKNOWN``), or with another number of joints than the URDF,
is refused there with one line; so is an arm whose joints put the TCP, through the URDF's FK,
farther from the ``POSE`` it reports than 5 mm or 0.02 rad (:func:`robot_io.arms.base.check_kinematics_agree`:
a wrong URDF, base placement or TCP offset), before anything moves.

A command the device answers ``ERR RANGE`` (a pose it cannot reach, a joint past its limit, a
non-finite value) is an :class:`~robot_io.errors.ArmRefusedError`: the device did not take it and
takes the next command, so the trial runner ends that trial and not the session.
"""

from __future__ import annotations

import logging
import random
import threading
import time
from typing import TYPE_CHECKING

import numpy as np

from robot_io.arms.base import Arm, Fault, check_joint_target, check_kinematics_agree
from robot_io.errors import ArmFaultError, ArmRefusedError, ProtocolError, RobotIOError
from robot_io.poses import pose_from_vec, pose_step, pose_to_vec

if TYPE_CHECKING:
    from sim.ik import SceneArm

__all__ = [
    "SerialArm",
    "PROTOCOL_VERSION",
    "STOP_BYTE",
    "checksum",
    "encode",
    "decode",
    "FAULT_KINDS",
    "NO_JOINT_COMMANDS",
]

log = logging.getLogger(__name__)

PROTOCOL_VERSION = 1
STOP_BYTE = b"!"
SEQ_MODULO = 10000
# Device fault codes -> Fault kinds, with what the operator does about each.
FAULT_KINDS = {
    "HEARTBEAT": (
        "heartbeat_timeout",
        "the device stopped: no command within its heartbeat timeout",
        "find why the host stalled, then reconnect (connect() clears the fault)",
    ),
    "ESTOP": ("emergency_stop", "the emergency stop is pressed", "release the e-stop, then reconnect"),
    "PSTOP": (
        "protective_stop",
        "the controller raised a protective stop (collision or limit)",
        "clear the workspace, then reconnect (connect() sends CLEAR)",
    ),
}


#: What the host says when the firmware answers a joint command ``ERR UNKNOWN``.
NO_JOINT_COMMANDS = "the arm's firmware does not take joint commands"


def checksum(body: bytes) -> str:
    """XOR of ``body``'s bytes as two upper-case hex digits."""
    c = 0
    for b in body:
        c ^= b
    return f"{c:02X}"


def encode(start: str, seq: int, fields: list[str]) -> bytes:
    """One framed line: ``start`` is ``>`` (request) or ``<`` (reply)."""
    body = " ".join([str(seq), *fields]).encode("ascii")
    return start.encode() + body + b"*" + checksum(body).encode() + b"\n"


def decode(line: bytes, start: str) -> tuple[int, list[str]]:
    """``(seq, fields)`` of a framed line; :class:`ValueError` on bad framing or checksum."""
    line = line.rstrip(b"\r\n")
    if not line.startswith(start.encode()) or b"*" not in line:
        raise ValueError(f"bad framing: {line!r}")
    body, _, cs = line[1:].rpartition(b"*")
    if cs.decode("ascii", "replace").upper() != checksum(body):
        raise ValueError(f"checksum mismatch: {line!r}")
    parts = body.decode("ascii").split()
    if not parts or not parts[0].isdigit():
        raise ValueError(f"missing sequence number: {line!r}")
    return int(parts[0]), parts[1:]


def _fault_from_code(code: str) -> Fault | None:
    if code == "NONE":
        return None
    kind, msg, recovery = FAULT_KINDS.get(code, ("device_fault", f"device fault {code}", "see the controller's manual"))
    return Fault(kind, msg, recovery)


def _fmt(x: float) -> str:
    return f"{x:.6f}"


class _Rejected(ProtocolError):
    """The device answered ``ERR CODE ...`` (``code``) to a command."""

    def __init__(self, message: str, code: str):
        self.code = code
        super().__init__(message)


class SerialArm(Arm):
    """Host side of the protocol.

    Args:
        port: a device (``/dev/ttyACM0``, ``/dev/serial/by-id/...``) or any pyserial URL
            (``socket://host:port`` for a serial-over-TCP bridge).
        baudrate: line speed.
        timeout_ms: how long to wait for each reply before resending.
        retries: resends before the link counts as lost.
        boot_timeout_ms: how long to wait for the boot banner after opening the port (opening
            toggles DTR, which resets Arduino-style controllers).
        expect_banner: ``False`` for boards that do not reset on open: go straight to ``HELLO``.
        kinematics: the arm's :class:`sim.ik.SceneArm` (URDF chain, its TCP in the frame of
            ``POSE``): given, the arm takes joint commands (``JOINTS``, ``MOVEJ``); ``None``, TCP
            commands only.
    """

    name = "serial"

    def __init__(
        self,
        port: str,
        baudrate: int = 115200,
        timeout_ms: float = 200.0,
        retries: int = 3,
        boot_timeout_ms: float = 3000.0,
        expect_banner: bool = True,
        *,
        kinematics: SceneArm | None = None,
    ):
        super().__init__()
        self.port = port
        self.baudrate = int(baudrate)
        self.timeout_ms = float(timeout_ms)
        self.retries = int(retries)
        self.boot_timeout_ms = float(boot_timeout_ms)
        self.expect_banner = bool(expect_banner)
        self._kinematics = kinematics
        self.device_info: dict[str, str] = {}
        self.stats = {"resends": 0, "checksum_errors": 0, "timeouts": 0, "stale_replies": 0}
        self._ser = None
        self._buf = bytearray()
        self._seq = 0
        self._lock = threading.RLock()  # re-entered to ask STATUS after an ERR FAULT
        self._notices: list[str] = []
        self._link_lost: str | None = None
        # Round trips cost milliseconds at serial speeds, so per-step checks use what the link
        # already told us: fault notices, the last STATUS (refreshed every status_interval_s) and
        # the last POSE; the device refuses motion while faulted either way.
        self.status_interval_s = 0.2
        self._fault_code = "NONE"
        self._last_status_s = -np.inf
        self._last_ok_s = -np.inf
        self._last_pose: tuple[float, np.ndarray] | None = None

    # ------------------------------------------------------------------ link
    def _open(self) -> None:
        import serial  # lazy: robot_io start-up (serial)

        try:
            self._ser = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=0.05)
        except (serial.SerialException, OSError, ValueError) as err:
            raise ArmFaultError(
                Fault(
                    "connection_lost",
                    f"cannot open serial port {self.port}: {err}",
                    "check the cable and the port name (ls /dev/serial/by-id/)",
                )
            ) from None
        self._buf.clear()
        self._link_lost = None
        # A random first SEQ: a new session must not look like a resend of the previous session's
        # last request, which the device would answer from its cache without executing.
        self._seq = random.randrange(SEQ_MODULO - 1)
        self._fault_code = "NONE"
        self._last_status_s = -np.inf
        self._last_pose = None
        try:
            banner = self._wait_banner() if self.expect_banner else None
            if banner is None:
                # No banner: the board did not reset on open (or it was missed); ask directly.
                _, fields = self._transact(["HELLO"])
                info = dict(f.split("=", 1) for f in fields if "=" in f)
            else:
                info = dict(f.split("=", 1) for f in banner.split()[1:] if "=" in f)
            if info.get("proto") != str(PROTOCOL_VERSION):
                raise ProtocolError(
                    f"serial arm on {self.port} speaks protocol {info.get('proto', '?')}, "
                    f"this host speaks {PROTOCOL_VERSION}: update the firmware or advobj"
                )
            self.device_info = info
            self._transact(["CLEAR"])
            if self._kinematics is not None:
                q = self._read_joints()  # refuses firmware without joint commands, or with other joints
                self._check_kinematics(q)
        except BaseException:
            self._ser.close()
            self._ser = None
            raise

    def _close(self) -> None:
        ser, self._ser = self._ser, None
        if ser is None:
            return
        try:
            ser.write(STOP_BYTE)
            ser.flush()
        except Exception:  # noqa: BLE001 - the link may already be gone; closing must still happen
            pass
        finally:
            ser.close()

    def identity(self) -> dict[str, str]:
        out = {"port": self.port}
        info = self.device_info  # from the boot banner or HELLO; 'id' is optional (docs/serial-protocol.md)
        for key, field in (("serial", "id"), ("firmware", "fw"), ("protocol", "proto")):
            if field in info:
                out[key] = info[field]
        return out

    def _readline(self, deadline: float) -> bytes | None:
        while True:
            nl = self._buf.find(b"\n")
            if nl >= 0:
                line = bytes(self._buf[: nl + 1])
                del self._buf[: nl + 1]
                return line
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            self._ser.timeout = min(remaining, 0.05)
            chunk = self._ser.read(max(1, self._ser.in_waiting))
            if chunk:
                self._buf.extend(chunk)

    def _notice(self, line: bytes) -> None:
        text = line[1:].decode("ascii", "replace").strip()
        if text.startswith("FAULT "):
            self._fault_code = text.split()[1] if len(text.split()) > 1 else "UNKNOWN"
        self._notices.append(text)
        del self._notices[:-50]
        log.info("serial arm %s: %s", self.port, text)

    def _wait_banner(self) -> str | None:
        deadline = time.monotonic() + self.boot_timeout_ms / 1000.0
        while (line := self._readline(deadline)) is not None:
            # Bootloaders print noise before the firmware starts; only a '#BOOT' line counts.
            at = line.find(b"#BOOT")  # noise may share the banner's line
            if at >= 0:
                return line[at + 1 :].decode("ascii", "replace").strip()
        log.warning("serial arm %s: no boot banner within %.0f ms; sending HELLO", self.port, self.boot_timeout_ms)
        return None

    def _transact(self, fields: list[str]) -> tuple[str, list[str]]:
        """Send one command and return ``('OK', fields)``; raises on ``ERR`` or a dead link."""
        if self._ser is None:
            raise ArmFaultError(Fault("connection_lost", f"serial arm {self.port} is not connected", "call connect()"))
        with self._lock:
            self._seq = self._seq % (SEQ_MODULO - 1) + 1
            seq = self._seq
            frame = encode(">", seq, fields)
            for attempt in range(self.retries + 1):
                if attempt:
                    self.stats["resends"] += 1
                try:
                    self._ser.write(frame)
                    reply = self._await_reply(seq)
                except OSError as err:  # pyserial's SerialException is an OSError: unplugged, port gone
                    self._link_lost = f"serial I/O error ({err})"
                    raise ArmFaultError(
                        Fault(
                            "connection_lost",
                            f"serial arm {self.port}: {self._link_lost}",
                            "check the cable and that the controller is powered, then reconnect",
                        )
                    ) from None
                if reply is None:
                    continue
                status, rest = reply[0], reply[1:]
                if status == "OK":
                    self._last_ok_s = time.monotonic()
                    return status, rest
                if status == "ERR" and rest[:1] == ["CHK"]:
                    self.stats["checksum_errors"] += 1  # the device saw a corrupted request
                    continue
                code = rest[0] if rest else "?"
                if code == "FAULT":
                    raise ArmFaultError(self._status_fault() or Fault("device_fault", " ".join(rest), ""))
                if code == "RANGE":  # a target the device will not execute; it takes the next command
                    raise ArmRefusedError(
                        f"serial arm {self.port} rejected {fields[0]}: ERR {' '.join(rest)}; the arm did not take it"
                    )
                raise _Rejected(f"serial arm {self.port} rejected {fields[0]}: ERR {' '.join(rest)}", code)
            self._link_lost = (
                f"no valid reply to {fields[0]} after {self.retries + 1} attempts of {self.timeout_ms:.0f} ms"
            )
            raise ArmFaultError(
                Fault(
                    "connection_lost",
                    f"serial arm {self.port}: {self._link_lost}",
                    "check the cable and that the controller is powered, then reconnect",
                )
            )

    def _await_reply(self, seq: int) -> list[str] | None:
        deadline = time.monotonic() + self.timeout_ms / 1000.0
        while (line := self._readline(deadline)) is not None:
            if line.startswith(b"#"):
                self._notice(line)
                continue
            try:
                got, fields = decode(line, "<")
            except ValueError as err:
                self.stats["checksum_errors"] += 1
                log.warning("serial arm %s: discarding reply (%s)", self.port, err)
                return None  # resend now rather than wait out the timeout
            if got != seq:
                self.stats["stale_replies"] += 1  # a late answer to an earlier, already resent request
                continue
            if fields:
                return fields
        self.stats["timeouts"] += 1
        return None

    # ------------------------------------------------------------------ state
    def _status(self) -> dict[str, str]:
        _, fields = self._transact(["STATUS"])
        st = dict(f.split("=", 1) for f in fields if "=" in f)
        self._fault_code = st.get("fault", "NONE")
        self._last_status_s = time.monotonic()
        return st

    def _drain_notices(self) -> None:
        """Read what the device sent unasked (between commands only stale replies or notices)."""
        with self._lock:
            if self._ser.in_waiting:
                self._buf.extend(self._ser.read(self._ser.in_waiting))
            while (nl := self._buf.find(b"\n")) >= 0:
                line = bytes(self._buf[: nl + 1])
                del self._buf[: nl + 1]
                if line.startswith(b"#"):
                    self._notice(line)

    def _status_fault(self) -> Fault | None:
        return _fault_from_code(self._status().get("fault", "NONE"))

    def fault(self) -> Fault | None:
        if self._ser is None:
            return Fault("connection_lost", f"serial arm {self.port} is not connected", "call connect()")
        if self._link_lost:
            return Fault(
                "connection_lost",
                f"serial arm {self.port}: {self._link_lost}",
                "check the cable and that the controller is powered, then reconnect",
            )
        try:
            self._drain_notices()
            if time.monotonic() - self._last_status_s > self.status_interval_s:
                self._status()
        except ArmFaultError as err:
            return err.fault
        except OSError as err:
            return Fault("connection_lost", f"serial arm {self.port}: {err}", "check the cable, then reconnect")
        return _fault_from_code(self._fault_code)

    def status(self) -> dict[str, str]:
        """The device's ``STATUS`` fields (``state``, ``fault``, ``pose``)."""
        return self._status()

    def tcp_pose(self) -> np.ndarray:
        _, fields = self._transact(["POSE"])
        try:
            T = pose_from_vec([float(x) for x in fields])
        except ValueError:
            raise ProtocolError(f"serial arm {self.port}: malformed POSE reply {fields}") from None
        self._last_pose = (time.monotonic(), T)
        return T.copy()

    # ------------------------------------------------------------------ motion
    def keepalive(self) -> None:
        # Any answered command is a heartbeat; send HB only when the link has been quiet.
        hb_s = float(self.device_info.get("hb_ms", 500)) / 1000.0
        if time.monotonic() - self._last_ok_s > hb_s / 4.0:
            self._transact(["HB"])

    def _move(self, T_base_tcp: np.ndarray, speed_mps: float) -> None:
        self._transact(["MOVE", *(_fmt(x) for x in pose_to_vec(T_base_tcp)), _fmt(speed_mps)])

    def servo(self, T_base_tcp: np.ndarray, duration_s: float) -> None:
        # The safety layer has just read the pose: reuse it rather than ask again.
        fresh = self._last_pose is not None and time.monotonic() - self._last_pose[0] < duration_s
        dp, _ = pose_step(self._last_pose[1] if fresh else self.tcp_pose(), T_base_tcp)
        self._move(T_base_tcp, max(dp / float(duration_s), 1e-4))

    def move_to(self, T_base_tcp: np.ndarray, speed_mps: float, timeout_s: float | None = None) -> None:
        dp, _ = pose_step(self.tcp_pose(), T_base_tcp)
        self._move(T_base_tcp, float(speed_mps))
        self._wait_idle("move", timeout_s if timeout_s is not None else 2.0 * dp / speed_mps + 2.0)

    def _wait_idle(self, what: str, timeout_s: float) -> None:
        """Poll ``STATUS`` until the device is ``IDLE``; a fault raises, and a motion still running
        after ``timeout_s`` is stopped and raised. Polling doubles as the heartbeat while it moves."""
        deadline = time.monotonic() + timeout_s
        while True:
            st = self._status()
            if st.get("fault", "NONE") != "NONE":
                raise ArmFaultError(_fault_from_code(st["fault"]))
            if st.get("state") == "IDLE":
                return
            if time.monotonic() > deadline:
                self.stop()
                raise ProtocolError(
                    f"serial arm {self.port}: {what} did not finish in {timeout_s:.1f} s (state {st.get('state')})"
                )
            time.sleep(0.01)

    # ------------------------------------------------------------------ joints
    def kinematics(self) -> SceneArm | None:
        return self._kinematics

    def _joint_command(self, fields: list[str]) -> list[str]:
        """``_transact`` for a joint command; ``ERR UNKNOWN`` (old firmware) becomes one clear line."""
        try:
            return self._transact(fields)[1]
        except _Rejected as err:
            if err.code != "UNKNOWN":
                raise
            raise ProtocolError(
                f"serial arm {self.port}: {NO_JOINT_COMMANDS} (firmware {self.device_info.get('fw', '?')} answered "
                f"{fields[0]} with ERR UNKNOWN): update the firmware, or configure the arm without a URDF"
            ) from None

    def _check_kinematics(self, q: np.ndarray) -> None:
        """Refuse to connect (:func:`robot_io.arms.base.check_kinematics_agree`, one line) when the FK of
        the device's ``JOINTS`` is not the ``POSE`` it reports: a wrong URDF, base placement or TCP,
        on which the safety layer would check the workspace box. Nothing has moved."""
        check_kinematics_agree(f"serial arm {self.port}", self._kinematics, q, self.tcp_pose())

    def _read_joints(self) -> np.ndarray:
        fields = self._joint_command(["JOINTS"])
        n = self._kinematics.n_joints
        try:
            q = np.array([float(x) for x in fields], dtype=np.float64)
        except ValueError:
            raise ProtocolError(f"serial arm {self.port}: malformed JOINTS reply {fields}") from None
        if q.shape != (n,) or not np.isfinite(q).all():
            raise ProtocolError(
                f"serial arm {self.port}: JOINTS replied {len(fields)} values {fields}, the arm's URDF has {n} joints "
                f"({', '.join(self._kinematics.joint_names)})"
            )
        return q

    def joint_positions(self) -> np.ndarray:
        """``JOINTS``: the measured joints, in the order and units of the kinematics' joints."""
        if self._kinematics is None:
            return super().joint_positions()  # raises: no joint commands
        return self._read_joints()

    def _move_joints(self, q: np.ndarray, duration_s: float) -> None:
        if not (np.isfinite(duration_s) and duration_s >= 0):
            raise RobotIOError(f"serial arm {self.port}: duration_s must be finite and >= 0, got {duration_s}")
        self._joint_command(["MOVEJ", *(_fmt(x) for x in q), _fmt(duration_s)])

    def servo_joints(self, q: np.ndarray, duration_s: float) -> None:
        """``MOVEJ`` to ``q`` over ``duration_s``; returns once the device has taken it."""
        self._move_joints(check_joint_target(f"serial arm {self.port}", self._kinematics, q), float(duration_s))

    def move_joints(self, q: np.ndarray, duration_s: float, timeout_s: float | None = None) -> None:
        """``MOVEJ`` to ``q`` over ``duration_s``, then wait until the device is there (``STATUS``
        ``IDLE``). ``timeout_s`` (default: twice ``duration_s`` plus 2 s): a motion still running
        then is stopped and raised."""
        q = check_joint_target(f"serial arm {self.port}", self._kinematics, q)
        self._move_joints(q, float(duration_s))
        self._wait_idle("joint move", timeout_s if timeout_s is not None else 2.0 * float(duration_s) + 2.0)

    def stop(self) -> None:
        # Written outside the command lock on purpose: the stop byte must not wait for a reply.
        ser = self._ser
        if ser is not None:
            ser.write(STOP_BYTE)
            ser.flush()
