"""The safety layer: the only path from a policy (or an operator) to an arm driver.

Every command passes, in this order:

1. the arm's watchdog is kicked (so a hung process stops the arm, not a slow step);
2. the maximum trial duration (exceeded: stop and raise :class:`SafetyStop`);
3. the frame-age watchdog (a camera frame the command was computed from is too old: stop; with
   several cameras the oldest of their frames counts, and the refusal names its camera);
4. NaN / Inf / non-rigid targets (refused: stop);
5. the arm's fault state (protective stop, e-stop, lost link: :class:`ArmFaultError`);
6. :func:`limit_command`: the target is clipped into the workspace box, the per-step translation
   and rotation are capped at ``min(max_step, max_speed * period)``, and the change of
   translation step is capped by ``max_accel_mps2`` (a soft limit: the workspace wins at the wall).

The ``period`` a command may cover is ``min(control_period_s, time since the last motion
command)``, so calling :meth:`SafeArm.step` faster than the loop period cannot add up to more
than the speed caps. The time is measured on the arm's clock: wall-clock time (``clock``) for
every arm that executes commands in real time (UR, serial, a ``realtime`` sim arm), and the
simulated time for a sim arm that runs faster than real time (:meth:`Arm.simulated_time_s`
returns it; each of its commands advances it by one control period), so trial sessions on the
sim can run as fast as the machine allows. After a completed positioning move the arm is at
rest and the next step may cover a full period again.

Refused commands stop the arm; clipped ones are sent clipped. Both are logged with their reason
(logger ``robot_io.safety``) and kept in :attr:`SafeArm.events`. Leaving ``with safe_arm:`` on any
exception, including Ctrl-C, stops the arm before disconnecting.
"""

from __future__ import annotations

import collections
import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Annotated, Callable, Literal

import numpy as np
from pydantic import Field, model_validator

from robot_io.arms.base import Arm, Fault
from robot_io.errors import ArmFaultError, RobotIOError, SafetyStop
from robot_io.poses import is_valid_pose
from sim.action import next_tcp_pose
from sim.configio import StrictModel
from sim.geometry import make_T, so3_exp, so3_log

__all__ = ["SafetyLimits", "SafetyEvent", "StepResult", "SafeArm", "limit_command", "SafetyRefusal"]

log = logging.getLogger("robot_io.safety")

Pos = Annotated[float, Field(gt=0, allow_inf_nan=False)]


class SafetyRefusal(RobotIOError, ValueError):
    """A positioning command the safety layer will not execute (the message says why)."""


class SafetyLimits(StrictModel):
    """Limits in the arm's base frame (m, rad, s)."""

    workspace_min_m: tuple[float, float, float]
    workspace_max_m: tuple[float, float, float]
    max_step_m: Pos = 0.01
    max_step_rad: Pos = 0.05
    max_speed_mps: Pos = 0.25
    max_speed_radps: Pos = 1.0
    max_accel_mps2: Pos = 2.0
    control_period_s: Annotated[float, Field(ge=0.001, le=2.0)] = 1.0 / 30.0
    max_frame_age_ms: Pos = 100.0
    max_trial_s: Pos = 120.0
    positioning_speed_mps: Pos = 0.05

    @model_validator(mode="after")
    def _box(self):
        lo, hi = np.asarray(self.workspace_min_m), np.asarray(self.workspace_max_m)
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
            raise ValueError("workspace bounds must be finite")
        if not (lo < hi).all():
            raise ValueError(
                f"workspace_min_m {list(self.workspace_min_m)} must be below workspace_max_m "
                f"{list(self.workspace_max_m)} "
                "on every axis"
            )
        if self.positioning_speed_mps > self.max_speed_mps:
            raise ValueError("positioning_speed_mps must not exceed max_speed_mps")
        return self

    @property
    def step_cap_m(self) -> float:
        return self.step_caps()[0]

    @property
    def step_cap_rad(self) -> float:
        return self.step_caps()[1]

    def step_caps(self, period_s: float | None = None) -> tuple[float, float]:
        """``(m, rad)`` one command may move when it covers ``period_s`` (default and at most ``control_period_s``)."""
        dt = self.command_period_s(period_s)
        return min(self.max_step_m, self.max_speed_mps * dt), min(self.max_step_rad, self.max_speed_radps * dt)

    def command_period_s(self, period_s: float | None = None) -> float:
        """``period_s`` clamped to ``[0, control_period_s]`` (``None``: the nominal period)."""
        if period_s is None:
            return self.control_period_s
        return max(0.0, min(float(period_s), self.control_period_s))

    def contains(self, p, tol: float = 0.0) -> bool:
        p = np.asarray(p, dtype=np.float64)
        return bool(
            (p >= np.asarray(self.workspace_min_m) - tol).all() and (p <= np.asarray(self.workspace_max_m) + tol).all()
        )


@dataclass(frozen=True)
class SafetyEvent:
    time_s: float
    action: Literal["clipped", "refused", "stopped"]
    reason: str


@dataclass(frozen=True)
class StepResult:
    """What happened to one policy command: ``T_cmd`` is what the arm was sent (``None`` if refused)."""

    status: Literal["ok", "clipped", "refused"]
    T_cmd: np.ndarray | None
    reasons: tuple[str, ...] = field(default_factory=tuple)


def limit_command(
    T_now: np.ndarray,
    T_target: np.ndarray,
    prev_step_m: np.ndarray,
    limits: SafetyLimits,
    period_s: float | None = None,
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Pure math: the command actually sent for ``T_target`` from ``T_now``.

    ``period_s`` is the time this command may cover (the caller measures it since its last
    command; ``None``: ``limits.control_period_s``, which is also its upper bound). Returns
    ``(T_cmd, step_m, reasons)`` where ``step_m`` is the commanded translation (the next call's
    ``prev_step_m``) and ``reasons`` lists every clip applied. Both poses must be valid.
    """
    lo, hi = np.asarray(limits.workspace_min_m), np.asarray(limits.workspace_max_m)
    dt = limits.command_period_s(period_s)
    cap, rcap = limits.step_caps(dt)
    early = "" if dt >= limits.control_period_s else f" ({dt * 1000:.1f} ms since the last command)"
    reasons: list[str] = []
    p_now, R_now = T_now[:3, 3], T_now[:3, :3]
    p_tgt = T_target[:3, 3]
    p_box = np.clip(p_tgt, lo, hi)
    if not np.array_equal(p_box, p_tgt):
        reasons.append(f"target {_vec(p_tgt)} m outside the workspace: clipped to {_vec(p_box)}")
    dp = p_box - p_now
    n = float(np.linalg.norm(dp))
    if n > cap:
        reasons.append(f"translation step {n * 1000:.1f} mm capped to {cap * 1000:.1f} mm{early}")
        dp = dp * (cap / n)
    inside = limits.contains(p_now)
    if inside:
        # A convex mix of two steps within the cap stays within the cap; a shorter period than
        # the previous command's shrinks the cap, so the previous step is shortened to it first.
        prev = np.asarray(prev_step_m, dtype=np.float64)
        pn = float(np.linalg.norm(prev))
        if pn > cap:
            prev = prev * (cap / pn)
        dd = dp - prev
        a_cap = limits.max_accel_mps2 * dt**2
        m = float(np.linalg.norm(dd))
        if m > a_cap:
            reasons.append(
                f"step change {m * 1000:.2f} mm exceeds the acceleration cap {a_cap * 1000:.2f} mm: smoothed"
            )
            dp = prev + dd * (a_cap / m)
        p_cmd = np.clip(p_now + dp, lo, hi)  # the box is hard: it overrides the soft acceleration cap
        if not np.allclose(p_cmd, p_now + dp, atol=0.0, rtol=0.0):
            reasons.append("stopping at the workspace boundary")
        dp = p_cmd - p_now
    else:
        # Started outside the box: only motion toward it (along the capped segment) is allowed.
        reasons.append("arm is outside the workspace: moving toward it only")
        p_cmd = p_now + dp
    r = so3_log(R_now.T @ T_target[:3, :3])
    ang = float(np.linalg.norm(r))
    if ang > rcap:
        reasons.append(f"rotation step {np.degrees(ang):.2f} deg capped to {np.degrees(rcap):.2f} deg{early}")
        r = r * (rcap / ang)
    return make_T(R_now @ so3_exp(r), p_cmd), dp, reasons


def _vec(v) -> str:
    return "[" + ", ".join(f"{x:.4g}" for x in v) + "]"


def _frame_time(frame) -> float | None:
    if frame is None:
        return None
    if isinstance(frame, (int, float)):
        return float(frame)
    return float(getattr(frame, "timestamp_s"))


def _frame_times(frames) -> list[tuple[str, float | None]]:
    """``[(what, timestamp)]`` of one frame (``what`` = "camera frame") or of ``{camera: frame}``."""
    if isinstance(frames, Mapping):
        return [(f"camera {name!r} frame", _frame_time(f)) for name, f in frames.items()] or [("camera frame", None)]
    return [("camera frame", _frame_time(frames))]


class SafeArm:
    """Wraps an :class:`Arm`; the driver itself stays private to this object.

    Args:
        arm: the driver (not connected yet).
        limits: :class:`SafetyLimits`.
        clock: monotonic clock (injectable for tests); frame timestamps must use the same clock.
    """

    def __init__(self, arm: Arm, limits: SafetyLimits, clock: Callable[[], float] = time.monotonic):
        self.__arm = arm
        self.limits = limits
        self.clock = clock
        self.events: collections.deque[SafetyEvent] = collections.deque(maxlen=10_000)
        self._trial_start: float | None = None
        self._prev_step = np.zeros(3)
        self._last_command_s: float | None = None  # on the arm's command clock (see _command_clock)

    # ------------------------------------------------------------------ lifecycle
    @property
    def name(self) -> str:
        return self.__arm.name

    @property
    def connected(self) -> bool:
        return self.__arm.connected

    def connect(self) -> None:
        self.__arm.connect()

    def disconnect(self) -> None:
        self.__arm.disconnect()

    def __enter__(self):
        self.connect()
        return self

    def __exit__(self, exc_type, exc, tb):
        try:
            if exc_type is not None:
                # The error's own text is reported by whoever handles it (the CLI prints it once);
                # the stop record names it only, so one error is not printed twice.
                self._stop_quietly(f"{exc_type.__name__} in the control loop")
        finally:
            self.disconnect()
        return False

    def identity(self) -> dict[str, str]:
        """The driver's :meth:`~robot_io.device.Device.identity` (for the session record)."""
        return self.__arm.identity()

    def keepalive(self) -> None:
        """Kick the driver's watchdog; call it when the arm is connected but no command is due."""
        self.__arm.keepalive()

    # ------------------------------------------------------------------ state
    def tcp_pose(self) -> np.ndarray:
        return self.__arm.tcp_pose()

    def fault(self) -> Fault | None:
        return self.__arm.fault()

    def recover(self) -> None:
        """Clear a recoverable fault through the driver (UR: unlock the protective stop, re-upload the script)."""
        recover = getattr(self.__arm, "recover", None)
        if recover is None:
            raise RobotIOError(f"the {self.name} arm has no remote recovery: follow the fault's instructions")
        self._record("stopped", "recovery requested by the operator")
        recover()
        self._prev_step = np.zeros(3)

    def start_trial(self) -> None:
        """Start the trial clock (the first :meth:`step` does it too) and reset motion history."""
        self._trial_start = self.clock()
        self._prev_step = np.zeros(3)

    @property
    def trial_elapsed_s(self) -> float:
        return 0.0 if self._trial_start is None else self.clock() - self._trial_start

    def _command_clock(self) -> float:
        # Simulated time for a sim arm running faster than real time, else the wall clock.
        t = self.__arm.simulated_time_s()
        return self.clock() if t is None else float(t)

    def _command_period_s(self, now: float) -> float:
        """The time the next command may cover: the loop period, or less when it comes sooner."""
        if self._last_command_s is None:
            return self.limits.control_period_s
        return self.limits.command_period_s(now - self._last_command_s)

    def _record(self, action: str, reason: str) -> None:
        self.events.append(SafetyEvent(self.clock(), action, reason))
        (log.info if action == "clipped" else log.warning)("%s: %s", action, reason)

    def _stop(self, reason: str) -> None:
        self._prev_step = np.zeros(3)
        self._record("stopped", reason)
        if self.__arm.connected:
            self.__arm.stop()

    def stop(self, reason: str = "requested") -> None:
        self._stop(reason)

    def _stop_quietly(self, reason: str) -> None:
        # On the error path: a failing stop (dead link) must not hide the error that got us here.
        try:
            self._stop(reason)
        except Exception as err:  # noqa: BLE001
            log.error(
                "stopping the arm failed (%s: %s); the driver's own watchdog must stop it", type(err).__name__, err
            )

    def _require_no_fault(self) -> None:
        f = self.__arm.fault()
        if f is not None:
            self._stop_quietly(f"arm fault: {f}")
            raise ArmFaultError(f)

    # ------------------------------------------------------------------ commands
    def move_to(self, T_base_tcp: np.ndarray, speed_mps: float | None = None) -> None:
        """Positioning move (not the policy loop): refused, not clipped, if the target is unsafe."""
        if not is_valid_pose(T_base_tcp):
            self._record("refused", "positioning target is not a finite rigid transform")
            raise SafetyRefusal("positioning target is not a finite rigid (4, 4) transform")
        p = np.asarray(T_base_tcp, dtype=np.float64)[:3, 3]
        if not self.limits.contains(p):
            reason = f"positioning target {_vec(p)} m is outside the workspace box"
            self._record("refused", reason)
            raise SafetyRefusal(reason)
        v = self.limits.positioning_speed_mps if speed_mps is None else float(speed_mps)
        if not np.isfinite(v) or v <= 0:
            reason = f"positioning speed must be positive, got {speed_mps}"
            self._record("refused", reason)
            raise SafetyRefusal(reason)
        if v > self.limits.max_speed_mps:
            self._record("clipped", f"positioning speed {v} m/s capped to {self.limits.max_speed_mps} m/s")
            v = self.limits.max_speed_mps
        self.__arm.keepalive()
        self._require_no_fault()
        try:
            self.__arm.move_to(np.asarray(T_base_tcp, dtype=np.float64), v)
        except BaseException as err:
            self._stop_quietly(f"{type(err).__name__} during a positioning move: {err}")
            raise
        # The move ended at rest: the next step starts from zero velocity, with a full period.
        self._prev_step = np.zeros(3)
        self._last_command_s = None

    def step(self, T_base_tcp: np.ndarray, frame) -> StepResult:
        """One policy-loop command toward ``T_base_tcp``, computed from camera ``frame``.

        ``frame`` is the :class:`~robot_io.cameras.base.Frame` (or its ``timestamp_s``) the
        policy saw, or ``{camera: frame}`` of every camera it read; too old a frame (the oldest of
        them) stops the arm instead of moving it.
        """
        return self._guarded(lambda T_now: T_base_tcp, frame)

    def step_delta(self, delta_tcp, frame) -> StepResult:
        """Like :meth:`step`, for a motion ``[dx, dy, dz (m), rx, ry, rz (rad)]`` in the current TCP frame.

        The semantics are :func:`sim.action.next_tcp_pose`'s: translate along the current TCP
        axes, then rotate about the new TCP origin.
        """

        def target(T_now):
            d = np.asarray(delta_tcp, dtype=np.float64)
            if d.shape != (6,):
                raise _Refuse(f"delta must have 6 entries [dx, dy, dz, rx, ry, rz], got shape {d.shape}")
            if not np.isfinite(d).all():
                raise _Refuse("non-finite delta (NaN or Inf)")
            # Huge finite deltas may overflow; the non-finite result is refused below.
            with np.errstate(over="ignore", invalid="ignore"):
                return next_tcp_pose(T_now, d, 1.0, 1.0)

        return self._guarded(target, frame)

    def _guarded(self, target_fn, frame) -> StepResult:
        try:
            return self._step(target_fn, frame)
        except _Refuse as r:
            self._record("refused", r.reason)
            self._stop(f"refused command: {r.reason}")
            return StepResult("refused", None, (r.reason,))
        except BaseException as err:
            if not isinstance(err, (ArmFaultError, SafetyStop)):  # those already stopped the arm
                self._stop_quietly(f"{type(err).__name__} during a control step: {err}")
            raise

    def _step(self, target_fn, frame) -> StepResult:
        lim = self.limits
        self.__arm.keepalive()
        now = self.clock()
        if self._trial_start is None:
            self.start_trial()
        elif now - self._trial_start > lim.max_trial_s:
            reason = f"maximum trial duration {lim.max_trial_s:.1f} s exceeded"
            self._stop(reason)
            raise SafetyStop(reason)
        ages = []
        for what, ts in _frame_times(frame):
            if ts is None or not np.isfinite(ts):
                raise _Refuse(f"no {what} timestamp given")
            age_ms = (now - ts) * 1000.0
            if age_ms < -_FUTURE_TOLERANCE_MS:
                # Usually a wall-clock (time.time) stamp: it would defeat the age check, so refuse.
                raise _Refuse(f"{what} timestamp is {-age_ms:.0f} ms in the future: stamp frames with time.monotonic()")
            ages.append((age_ms, what))
        age_ms, what = max(ages)  # the oldest frame the command was computed from counts
        if age_ms > lim.max_frame_age_ms:
            raise _Refuse(f"{what} is {age_ms:.0f} ms old (limit {lim.max_frame_age_ms:.0f} ms)")
        self._require_no_fault()
        T_now = self.__arm.tcp_pose()
        T_target = target_fn(T_now)
        if not is_valid_pose(T_target):
            raise _Refuse("target is not a finite rigid (4, 4) transform (NaN, Inf or not a rotation)")
        # Read before sending: a sim arm's clock advances while it executes the command.
        t_cmd = self._command_clock()
        T_cmd, dp, reasons = limit_command(
            T_now, np.asarray(T_target, dtype=np.float64), self._prev_step, lim, self._command_period_s(t_cmd)
        )
        for r in reasons:
            self._record("clipped", r)
        self._last_command_s = t_cmd  # before sending: a servo that raises may still have reached the arm
        self.__arm.servo(T_cmd, lim.control_period_s)
        self._prev_step = dp
        return StepResult("clipped" if reasons else "ok", T_cmd, tuple(reasons))


_FUTURE_TOLERANCE_MS = 50.0


class _Refuse(Exception):
    def __init__(self, reason: str):
        self.reason = reason
        super().__init__(reason)
