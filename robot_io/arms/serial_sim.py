"""A device-side simulator of the serial arm protocol, for tests and for trying the driver.

It runs in a thread on the master end of a pseudo-terminal (:class:`robot_io.arms.pty_twin.PtyTwin`);
the driver opens the slave end like any serial port, so the real bytes, framing and timing are
exercised. Run it standalone with::

    python -m robot_io.arms.serial_sim        # prints the port to put in the hardware config

Fault injection (counters count down per affected message): ``corrupt_replies``,
``drop_replies``, ``corrupt_requests`` (treat the next requests as having a bad checksum),
``reply_delay_s``, ``boot_delay_s``, ``send_banner``, :meth:`raise_fault`.

Joints: given a ``scene_arm`` (:class:`sim.ik.SceneArm`), the simulated arm holds joint positions
``q`` and its TCP is their FK (:func:`robot_io.arms.base.tcp_from_joints`): ``JOINTS`` reports ``q``,
``MOVEJ`` moves the joints along the straight line in joint space, the leading joint at ``max |dq| / duration``
(capped at ``max_joint_speed_radps``), and ``MOVE`` solves the IK of its pose from the current
joints and then moves the same way (so a ``MOVE``'s TCP path is not exactly straight here). Without
a ``scene_arm`` it is firmware without joint commands: ``JOINTS`` and ``MOVEJ`` answer ``ERR UNKNOWN``.
"""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING

import numpy as np

from robot_io.arms.base import tcp_from_joints
from robot_io.arms.pty_twin import PtyTwin, serve_until_interrupted
from robot_io.arms.serial import PROTOCOL_VERSION, STOP_BYTE, checksum, encode
from robot_io.poses import interpolate_pose, pose_from_vec, pose_step, pose_to_vec

if TYPE_CHECKING:
    from sim.ik import SceneArm

__all__ = ["SerialArmSimulator", "JOINT_LIMIT_TOL"]

FIRMWARE = "advobj-sim-1.0"
#: A ``MOVEJ`` joint this far (rad or m) beyond a position limit is clamped to it (the wire's
#: ``%.6f`` rounds a target at a limit up to 5e-7 past it); farther, the command is ``ERR RANGE``.
JOINT_LIMIT_TOL = 1e-6


class SerialArmSimulator(PtyTwin):
    """The firmware: parses requests, moves a kinematic TCP, enforces the heartbeat timeout.

    Args:
        fd: the pty master (:func:`robot_io.arms.pty_twin.open_pty_pair`; :meth:`on_pty` opens one).
        heartbeat_timeout_ms: stop and fault when no valid request arrives for this long while moving.
        boot_delay_s: time from start to the boot banner (requests before it are ignored, as a
            real bootloader would).
        max_speed_mps, max_speed_radps: the device's own motion limits.
        scene_arm: the arm's :class:`sim.ik.SceneArm`: the device then takes joint commands and
            its TCP is the FK of its joints (``T_base_tcp`` is then ignored); ``None``: firmware
            without joint commands.
        q: the joints at start (default: ``scene_arm.q_home``).
        max_joint_speed_radps: the device's cap on the leading joint's speed.
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
        scene_arm: SceneArm | None = None,
        q=None,
        max_joint_speed_radps: float = 3.0,
    ):
        super().__init__(fd, keep_fd)
        self.protocol_version = int(protocol_version)
        self.device_id = device_id
        self.heartbeat_timeout_ms = float(heartbeat_timeout_ms)
        self.boot_delay_s = float(boot_delay_s)
        self.send_banner = send_banner
        self.boot_noise = boot_noise
        self.max_speed_mps = float(max_speed_mps)
        self.max_speed_radps = float(max_speed_radps)
        self.T_base_tcp = (
            pose_from_vec([0.4, 0.0, 0.3, np.pi, 0.0, 0.0]) if T_base_tcp is None else np.array(T_base_tcp, float)
        )
        self.scene_arm = scene_arm
        self.max_joint_speed_radps = float(max_joint_speed_radps)
        self.q: np.ndarray | None = None
        self.joint_target: tuple[np.ndarray, float] | None = None  # (q_goal, leading joint speed)
        if scene_arm is not None:
            self._q_lo = scene_arm.model.limits.q_min.cpu().numpy()
            self._q_hi = scene_arm.model.limits.q_max.cpu().numpy()
            self._set_q(np.asarray(scene_arm.q_home if q is None else q, dtype=np.float64))
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
        self._lock = threading.Lock()
        self._t_boot_s = 0.0  # when the banner is due (time.monotonic()), set by start()

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> "SerialArmSimulator":
        self._t_boot_s = time.monotonic() + self.boot_delay_s
        return super().start()

    def raise_fault(self, code: str) -> None:
        """Simulate ``ESTOP``, ``PSTOP``, ...: motion stops and commands answer ``ERR FAULT``."""
        with self._lock:
            self.fault_code = code
            self.target = self.joint_target = None
        self._send(f"#FAULT {code}\n".encode())

    @property
    def moving(self) -> bool:
        """A TCP or joint target is being followed."""
        return self.target is not None or self.joint_target is not None

    def _set_q(self, q: np.ndarray) -> None:
        self.q = np.array(q, dtype=np.float64)
        self.T_base_tcp = tcp_from_joints(self.scene_arm, self.q)

    # ------------------------------------------------------------------ I/O
    def _serve(self, data: bytes, dt_s: float, now_s: float) -> None:
        if not self.booted.is_set():
            if now_s >= self._t_boot_s:
                self._last_rx = now_s
                if self.send_banner:
                    self._send(
                        self.boot_noise
                        + f"#BOOT advobj-arm fw={FIRMWARE} proto={self.protocol_version} "
                        f"hb_ms={self.heartbeat_timeout_ms:.0f} id={self.device_id}\n".encode()
                    )
                self.booted.set()
            return  # input during boot is lost, as on a real board
        for b in data:
            if bytes([b]) == STOP_BYTE:
                self._stop_motion()
                self._buf.clear()  # a partial request is abandoned
            elif b == 0x0A:
                line, self._buf = bytes(self._buf), bytearray()
                self._handle(line.rstrip(b"\r"))
            else:
                self._buf.append(b)
        self._tick(dt_s, now_s)

    def _stop_motion(self) -> None:
        with self._lock:
            self.target = self.joint_target = None
            self.stops += 1
        self._send(b"#STOPPED\n")

    def _tick(self, dt: float, now: float) -> None:
        with self._lock:
            if not self.moving:
                return
            if (now - self._last_rx) * 1000.0 > self.heartbeat_timeout_ms:
                self.target = self.joint_target = None
                self.fault_code = "HEARTBEAT"
                notice = b"#FAULT HEARTBEAT\n"
            elif self.joint_target is not None:
                q_goal, rate = self.joint_target
                need = float(np.max(np.abs(q_goal - self.q))) / rate
                if need <= dt:
                    self._set_q(q_goal)  # exactly the target: no rounding drift
                    self.joint_target = None
                else:
                    self._set_q(self.q + (q_goal - self.q) * (dt / need))
                return
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
                state = "FAULT" if self.fault_code != "NONE" else ("MOVING" if self.moving else "IDLE")
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
                speed = min(float(v[6]), self.max_speed_mps)
                if self.scene_arm is not None:
                    return self._move_through_ik(pose_from_vec(v[:6]), speed)
                self.target = (pose_from_vec(v[:6]), speed)
                return ["OK"]
            if self.scene_arm is not None and cmd == "JOINTS":
                return ["OK", *(f"{x:.6f}" for x in self.q)]
            if self.scene_arm is not None and cmd == "MOVEJ":
                return self._movej(args)
            return ["ERR", "UNKNOWN", cmd]

    def _start_joint_move(self, q_goal: np.ndarray, duration_s: float) -> None:
        """Move the joints to ``q_goal`` along the joint-space line in ``duration_s`` (or slower)."""
        dq = float(np.max(np.abs(q_goal - self.q)))
        rate = dq / duration_s if duration_s > 0 else np.inf
        self.target = None
        self.joint_target = (q_goal, min(rate, self.max_joint_speed_radps)) if dq > 0 else None

    def _movej(self, args: list[str]) -> list[str]:
        n = self.scene_arm.n_joints
        if self.fault_code != "NONE":
            return ["ERR", "FAULT", self.fault_code]
        if len(args) != n + 1:
            return ["ERR", "ARGS", f"MOVEJ takes {n} joints and a duration"]
        try:
            v = np.array([float(a) for a in args])
        except ValueError:
            return ["ERR", "ARGS", "not a number"]
        q, duration_s = v[:n], float(v[n])
        if not np.isfinite(v).all() or duration_s < 0:
            return ["ERR", "RANGE"]
        if ((q < self._q_lo - JOINT_LIMIT_TOL) | (q > self._q_hi + JOINT_LIMIT_TOL)).any():
            return ["ERR", "RANGE", "joint limit"]
        self._start_joint_move(np.clip(q, self._q_lo, self._q_hi), duration_s)
        return ["OK"]

    def _move_through_ik(self, T_goal: np.ndarray, speed_mps: float) -> list[str]:
        import torch  # lazy: robot_io start-up (torch)

        arm = self.scene_arm
        q0 = torch.as_tensor(self.q, dtype=torch.float64, device=arm.device)[None]
        res = arm.ik(torch.as_tensor(T_goal, dtype=torch.float64, device=arm.device)[None], q0)
        if not bool(res.converged[0]):
            return ["ERR", "RANGE", "unreachable"]
        dp, dr = pose_step(self.T_base_tcp, T_goal)
        self._start_joint_move(res.q[0].cpu().numpy(), max(dp / speed_mps, dr / self.max_speed_radps))
        return ["OK"]


def main() -> None:
    sim, path = SerialArmSimulator.on_pty(boot_delay_s=1.0)
    serve_until_interrupted(sim, f"serial arm simulator on {path} (protocol {PROTOCOL_VERSION}); Ctrl-C to quit")


if __name__ == "__main__":
    main()
