"""A device-side simulator of the serial arm protocol, for tests and for trying the driver.

It runs in a thread on the master end of a pseudo-terminal; the driver opens the slave end like
any serial port, so the real bytes, framing and timing are exercised. Run it standalone with::

    python -m robot_io.arms.serial_sim        # prints the port to put in the hardware config

Fault injection (counters count down per affected message): ``corrupt_replies``,
``drop_replies``, ``corrupt_requests`` (treat the next requests as having a bad checksum),
``reply_delay_s``, ``boot_delay_s``, ``send_banner``, :meth:`raise_fault`.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty

import numpy as np

from robot_io.arms.serial import PROTOCOL_VERSION, STOP_BYTE, checksum, encode
from robot_io.poses import interpolate_pose, pose_from_vec, pose_step, pose_to_vec

__all__ = ["SerialArmSimulator", "open_pty_pair"]

FIRMWARE = "advobj-sim-1.0"


def open_pty_pair() -> tuple[int, int, str]:
    """``(master_fd, slave_fd, slave_path)``; the slave is raw so nothing is echoed back.

    Keep ``slave_fd`` open while the simulator runs: once the last slave fd closes (the driver
    disconnecting), reads on the master fail with EIO and bytes written are lost.
    """
    master, slave = os.openpty()
    tty.setraw(slave)
    return master, slave, os.ttyname(slave)


class SerialArmSimulator:
    """The firmware: parses requests, moves a kinematic TCP, enforces the heartbeat timeout.

    Args:
        fd: the pty master (see :func:`open_pty_pair`).
        heartbeat_timeout_ms: stop and fault when no valid request arrives for this long while moving.
        boot_delay_s: time from start to the boot banner (requests before it are ignored, as a
            real bootloader would).
        max_speed_mps, max_speed_radps: the device's own motion limits.
    """

    def __init__(
        self,
        fd: int,
        heartbeat_timeout_ms: float = 500.0,
        boot_delay_s: float = 0.05,
        send_banner: bool = True,
        boot_noise: bytes = b"\x00\xfe boot v0.1\r\n",
        max_speed_mps: float = 0.5,
        max_speed_radps: float = 2.0,
        T_base_tcp: np.ndarray | None = None,
        keep_fd: int | None = None,
        protocol_version: int = PROTOCOL_VERSION,
        device_id: str = "SIM-0001",
    ):
        self.fd = fd
        self.protocol_version = int(protocol_version)
        self.device_id = device_id
        self._keep_fd = keep_fd
        self.heartbeat_timeout_ms = float(heartbeat_timeout_ms)
        self.boot_delay_s = float(boot_delay_s)
        self.send_banner = send_banner
        self.boot_noise = boot_noise
        self.max_speed_mps = float(max_speed_mps)
        self.max_speed_radps = float(max_speed_radps)
        self.T_base_tcp = (
            pose_from_vec([0.4, 0.0, 0.3, np.pi, 0.0, 0.0]) if T_base_tcp is None else np.array(T_base_tcp, float)
        )
        # Fault injection knobs (see the module docstring).
        self.corrupt_replies = 0
        self.drop_replies = 0
        self.corrupt_requests = 0
        self.reply_delay_s = 0.0
        # Observable state for tests.
        self.fault_code = "NONE"
        self.target: tuple[np.ndarray, float] | None = None
        self.executed: list[tuple[int, str]] = []  # (seq, command) actually executed, not replayed
        self.stops = 0
        self.booted = threading.Event()
        self._last: tuple[int, bytes] | None = None
        self._last_rx = time.monotonic()
        self._buf = bytearray()
        self._stop_evt = threading.Event()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    @classmethod
    def on_pty(cls, **kwargs) -> tuple["SerialArmSimulator", str]:
        """A started simulator on a fresh pty, and the port path for the driver."""
        master, slave, path = open_pty_pair()
        sim = cls(master, keep_fd=slave, **kwargs)
        sim.start()
        return sim, path

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> "SerialArmSimulator":
        self._thread = threading.Thread(target=self._run, name="serial-arm-sim", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop_evt.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        for fd in (self.fd, self._keep_fd):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def raise_fault(self, code: str) -> None:
        """Simulate ``ESTOP``, ``PSTOP``, ...: motion stops and commands answer ``ERR FAULT``."""
        with self._lock:
            self.fault_code = code
            self.target = None
        self._send(f"#FAULT {code}\n".encode())

    # ------------------------------------------------------------------ I/O
    def _send(self, data: bytes) -> None:
        try:
            os.write(self.fd, data)
        except OSError:
            pass  # nobody listening (port closed); a real UART would drop the bytes too

    def _run(self) -> None:
        t_boot = time.monotonic() + self.boot_delay_s
        booted = False
        t_prev = time.monotonic()
        while not self._stop_evt.is_set():
            try:
                ready, _, _ = select.select([self.fd], [], [], 0.002)
                data = os.read(self.fd, 4096) if ready else b""
            except OSError:
                data = b""
                time.sleep(0.002)
            now = time.monotonic()
            if not booted:
                if now >= t_boot:
                    booted = True
                    self._last_rx = now
                    if self.send_banner:
                        self._send(
                            self.boot_noise
                            + f"#BOOT advobj-arm fw={FIRMWARE} proto={self.protocol_version} "
                            f"hb_ms={self.heartbeat_timeout_ms:.0f} id={self.device_id}\n".encode()
                        )
                    self.booted.set()
                t_prev = now
                continue  # input during boot is lost, as on a real board
            for b in data:
                if bytes([b]) == STOP_BYTE:
                    self._stop_motion()
                    self._buf.clear()  # a partial request is abandoned
                elif b == 0x0A:
                    line, self._buf = bytes(self._buf), bytearray()
                    self._handle(line.rstrip(b"\r"))
                else:
                    self._buf.append(b)
            self._tick(now - t_prev, now)
            t_prev = now

    def _stop_motion(self) -> None:
        with self._lock:
            self.target = None
            self.stops += 1
        self._send(b"#STOPPED\n")

    def _tick(self, dt: float, now: float) -> None:
        with self._lock:
            if self.target is None:
                return
            if (now - self._last_rx) * 1000.0 > self.heartbeat_timeout_ms:
                self.target = None
                self.fault_code = "HEARTBEAT"
                notice = b"#FAULT HEARTBEAT\n"
            else:
                T_goal, speed = self.target
                dp, dr = pose_step(self.T_base_tcp, T_goal)
                need = max(dp / speed if speed > 0 else np.inf, dr / self.max_speed_radps)
                s = 1.0 if need <= dt else dt / need
                self.T_base_tcp = interpolate_pose(self.T_base_tcp, T_goal, s)
                if s >= 1.0:
                    self.target = None
                return
        self._send(notice)

    # ------------------------------------------------------------------ requests
    def _reply(self, seq: int, fields: list[str]) -> None:
        frame = encode("<", seq, fields)
        self._last = (seq, frame)
        self._transmit(frame)

    def _transmit(self, frame: bytes) -> None:
        if self.drop_replies > 0:
            self.drop_replies -= 1
            return
        if self.corrupt_replies > 0:
            self.corrupt_replies -= 1
            frame = frame[:-3] + (b"00" if frame[-3:-1] != b"00" else b"FF") + b"\n"
        if self.reply_delay_s:
            time.sleep(self.reply_delay_s)
        self._send(frame)

    def _handle(self, line: bytes) -> None:
        if not line.startswith(b">"):
            return  # noise between frames
        body, star, cs = line[1:].rpartition(b"*")
        parts = body.decode("ascii", "replace").split()
        seq = int(parts[0]) if parts and parts[0].isdigit() else 0
        if not star or cs.decode("ascii", "replace").upper() != checksum(body) or self.corrupt_requests > 0:
            if self.corrupt_requests > 0:
                self.corrupt_requests -= 1
            self._transmit(encode("<", seq, ["ERR", "CHK"]))
            return
        self._last_rx = time.monotonic()  # any valid request is a heartbeat
        if self._last is not None and self._last[0] == seq:
            self._transmit(self._last[1])  # a resend: answer from the cache, do not execute twice
            return
        if len(parts) < 2:
            self._reply(seq, ["ERR", "SYNTAX"])
            return
        cmd, args = parts[1], parts[2:]
        self.executed.append((seq, cmd))
        self._reply(seq, self._execute(cmd, args))

    def _execute(self, cmd: str, args: list[str]) -> list[str]:
        with self._lock:
            if cmd == "HELLO":
                return [
                    "OK",
                    f"proto={self.protocol_version}",
                    f"fw={FIRMWARE}",
                    f"hb_ms={self.heartbeat_timeout_ms:.0f}",
                    f"id={self.device_id}",
                ]
            if cmd == "HB":
                return ["OK"]
            if cmd == "STATUS":
                state = "FAULT" if self.fault_code != "NONE" else ("MOVING" if self.target is not None else "IDLE")
                pose = ",".join(f"{x:.6f}" for x in pose_to_vec(self.T_base_tcp))
                return ["OK", f"state={state}", f"fault={self.fault_code}", f"pose={pose}"]
            if cmd == "POSE":
                return ["OK", *(f"{x:.6f}" for x in pose_to_vec(self.T_base_tcp))]
            if cmd == "CLEAR":
                if self.fault_code == "ESTOP":
                    return ["ERR", "FAULT", "ESTOP"]  # only releasing the button clears an e-stop
                self.fault_code = "NONE"
                return ["OK"]
            if cmd == "MOVE":
                if self.fault_code != "NONE":
                    return ["ERR", "FAULT", self.fault_code]
                if len(args) != 7:
                    return ["ERR", "ARGS", "MOVE takes x y z rx ry rz speed"]
                try:
                    v = np.array([float(a) for a in args])
                except ValueError:
                    return ["ERR", "ARGS", "not a number"]
                if not np.isfinite(v).all() or v[6] <= 0:
                    return ["ERR", "RANGE"]
                self.target = (pose_from_vec(v[:6]), min(float(v[6]), self.max_speed_mps))
                return ["OK"]
            return ["ERR", "UNKNOWN", cmd]


def main() -> None:
    sim, path = SerialArmSimulator.on_pty(boot_delay_s=1.0)
    print(f"serial arm simulator on {path} (protocol {PROTOCOL_VERSION}); Ctrl-C to quit", flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        sim.close()


if __name__ == "__main__":
    main()
