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

Joint targets (:meth:`SafeArm.step_joints`, an arm a URDF describes: :meth:`Arm.kinematics`)
pass their own ordered list; steps 1 to 3 and 5 are the same, the target's checks are
:func:`limit_joint_command`'s:

1. the arm's watchdog is kicked; 2. the maximum trial duration; 3. the frame-age watchdog (a
   chunk of actions computed from one frame is sent one action per step with that frame: the
   step at which the frame outlives ``max_frame_age_ms`` is refused and stops the arm);
4. a target that is not ``n`` finite numbers (NaN, Inf, wrong length) is refused: stop;
5. the arm's fault state;
6. a jump: a target farther than ``joints.max_jump_rad`` (revolute) or ``joints.max_jump_m``
   (prismatic) from the measured joints, on any joint, is refused: stop (a policy that asks
   for a far configuration is broken, and crawling there one capped step at a time is not what
   it meant);
7. each joint is clipped to its URDF position limits;
8. the step ``q_target - q_now`` is scaled down as a whole (its direction in joint space kept,
   as :meth:`sim.ik.SceneArm.limit_step` does in the sim) until every joint moves at most
   ``min(URDF velocity limit, joints.max_speed_radps or joints.max_speed_mps) * period``, the
   same ``period`` as the TCP path's;
9. the workspace box through FK: the TCP of ``q_now + s (q_cmd - q_now)`` is computed at
   ``s = 0, 1/16, ..., 1`` (one batched FK) and the step is shortened to the largest ``s`` up to
   which no sampled TCP is farther from the box than the TCP is now (inside: outside none). It
   is clipped along the joint-space line, not refused: a policy pushing against the wall then
   stops at the wall and keeps its other motion's direction, as the TCP path's box does, while
   an arm outside the box may only move toward it. The samples also check the motion between
   two commands, not only its end.

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

from robot_io.arms.base import Arm, Fault, tcp_from_joints
from robot_io.errors import ArmFaultError, RobotIOError, SafetyStop
from robot_io.poses import is_valid_pose
from sim.action import next_tcp_pose
from sim.configio import StrictModel
from sim.geometry import make_T, so3_exp, so3_log

__all__ = [
    "JointSafetyLimits",
    "SafetyLimits",
    "SafetyEvent",
    "StepResult",
    "SafeArm",
    "limit_command",
    "limit_joint_command",
    "SafetyRefusal",
    "WORKSPACE_SAMPLES",
]

log = logging.getLogger("robot_io.safety")

Pos = Annotated[float, Field(gt=0, allow_inf_nan=False)]


class SafetyRefusal(RobotIOError, ValueError):
    """A positioning command the safety layer will not execute (the message says why)."""


class JointSafetyLimits(StrictModel):
    """The joint path's own limits (per joint; revolute joints in rad, prismatic ones in m).

    The URDF's position and velocity limits apply too: the speed cap is the smaller of the URDF's
    and these.
    """

    max_speed_radps: Pos = 1.0  # revolute joint speed cap; step cap = min(URDF velocity, this) * period
    max_speed_mps: Pos = 0.25  # prismatic joint speed cap
    max_jump_rad: Pos = 0.5  # a revolute joint target farther than this from its position is refused
    max_jump_m: Pos = 0.1  # a prismatic joint target farther than this from its position is refused


class SafetyLimits(StrictModel):
    """Limits in the arm's base frame (m, rad, s); ``joints``: the joint path's (:class:`JointSafetyLimits`)."""

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
    joints: JointSafetyLimits = JointSafetyLimits()

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
    q_cmd: np.ndarray | None = None  # a joint command's joints as sent (step_joints)


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


#: TCP samples along one joint step (``s = 0, 1/N, ..., 1``) checked against the workspace box.
WORKSPACE_SAMPLES = 16


def _box_distance_m(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``(...,)`` m from points ``p (..., 3)`` to the box ``[lo, hi]`` (0 inside)."""
    return np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0.0), axis=-1)


def joint_step_caps(scene_arm, limits: SafetyLimits, period_s: float | None = None) -> np.ndarray:
    """``(n,)`` the most each joint may move in one command covering ``period_s`` (rad or m):
    ``min(URDF velocity limit, the configured joint speed of its unit) * period``."""
    dt = limits.command_period_s(period_s)
    j = limits.joints
    own = np.array([j.max_speed_radps if u == "rad" else j.max_speed_mps for u in scene_arm.units])
    return np.minimum(scene_arm.model.limits.qd_max.cpu().numpy(), own) * dt


def limit_joint_command(
    q_now: np.ndarray,
    q_target,
    scene_arm,
    limits: SafetyLimits,
    period_s: float | None = None,
) -> tuple[np.ndarray, list[str]]:
    """Pure math: the joints actually sent for ``q_target (n,)`` from the measured ``q_now (n,)``.

    Steps 4 and 6 to 9 of the joint path (module docstring) for the arm ``scene_arm``
    (:class:`sim.ik.SceneArm`, whose TCP frame is the workspace box's); ``period_s`` as in
    :func:`limit_command`. Returns ``(q_cmd, reasons)``, every clip in ``reasons``; raises
    :class:`SafetyRefusal` for a target that is not ``n`` finite numbers or is a jump.
    """
    import torch  # lazy: robot_io start-up (torch)

    n = scene_arm.n_joints
    names, units = scene_arm.joint_names, scene_arm.units
    try:
        q_t = np.asarray(q_target, dtype=np.float64)
    except (TypeError, ValueError):
        raise SafetyRefusal(f"joint target is not numbers (type {type(q_target).__name__})") from None
    if q_t.shape != (n,):
        raise SafetyRefusal(f"joint target has shape {q_t.shape}; the arm has {n} joints ({', '.join(names)})")
    if not np.isfinite(q_t).all():
        k = int(np.flatnonzero(~np.isfinite(q_t))[0])
        raise SafetyRefusal(f"non-finite joint target: joint {names[k]!r} is {q_t[k]}")
    q_now = np.asarray(q_now, dtype=np.float64)
    j = limits.joints
    jump = np.array([j.max_jump_rad if u == "rad" else j.max_jump_m for u in units])
    far = np.abs(q_t - q_now) > jump
    if far.any():
        k = int(np.flatnonzero(far)[0])
        raise SafetyRefusal(
            f"joint jump: {names[k]!r} target {q_t[k]:.4g} {units[k]} is {abs(q_t[k] - q_now[k]):.4g} {units[k]} "
            f"from its position {q_now[k]:.4g} (limit {jump[k]:.4g})"
        )
    reasons: list[str] = []
    lo = scene_arm.model.limits.q_min.cpu().numpy()
    hi = scene_arm.model.limits.q_max.cpu().numpy()
    q_c = np.clip(q_t, lo, hi)
    out = np.flatnonzero(q_c != q_t)
    if len(out):
        clipped = ", ".join(f"{names[k]!r} clipped to {q_c[k]:.4g}" for k in out)
        reasons.append(f"joint target outside the position limits: {clipped}")
    dt = limits.command_period_s(period_s)
    cap = joint_step_caps(scene_arm, limits, dt)
    dq = q_c - q_now
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # a zero period: no joint may move
        ratio = np.where(dq == 0.0, 0.0, np.abs(dq) / cap)
    scale = float(np.max(ratio))
    if scale > 1.0:
        k = int(np.argmax(ratio))
        early = "" if dt >= limits.control_period_s else f" ({dt * 1000:.1f} ms since the last command)"
        reasons.append(
            f"joint step of {names[k]!r} {abs(dq[k]):.4g} {units[k]} capped to {cap[k]:.4g}{early}: step scaled by "
            f"{1.0 / scale:.3g}"
        )
        dq = dq / scale if np.isfinite(scale) else np.zeros_like(dq)
    inside_now = bool(((q_now >= lo) & (q_now <= hi)).all())
    q_cmd = q_now + dq
    if inside_now:
        q_cmd = np.clip(q_cmd, lo, hi)  # q + (limit - q) can round one ulp past the limit
    s = np.linspace(0.0, 1.0, WORKSPACE_SAMPLES + 1)
    q_line = q_now[None, :] + s[:, None] * (q_cmd - q_now)[None, :]
    q_line[-1] = q_cmd
    T = scene_arm.tcp_pose(torch.as_tensor(q_line, dtype=torch.float64, device=scene_arm.device))
    p = T[:, :3, 3].detach().cpu().numpy()
    box_lo, box_hi = np.asarray(limits.workspace_min_m), np.asarray(limits.workspace_max_m)
    d = _box_distance_m(p, box_lo, box_hi)
    ok = d <= d[0]
    if not ok.all():
        last = int(np.argmin(ok)) - 1  # the last sample of the leading run within the rule
        reasons.append(
            f"TCP {_vec(p[int(np.argmin(ok))])} m leaves the workspace box along the joint step: "
            f"shortened to {s[last]:.3g} of it" + ("" if d[0] == 0 else " (arm outside the box: toward it only)")
        )
        q_cmd = q_line[last]
    return q_cmd, reasons


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
        return self._guarded(self._step, lambda T_now: T_base_tcp, frame)

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

        return self._guarded(self._step, target, frame)

    # ------------------------------------------------------------------ joint commands
    def kinematics(self):
        """The driver's :class:`sim.ik.SceneArm`, or ``None`` for an arm without joint commands."""
        return self.__arm.kinematics()

    def joint_positions(self) -> np.ndarray:
        return self.__arm.joint_positions()

    def _scene_arm(self):
        arm = self.__arm.kinematics()
        if arm is None:
            raise _Refuse(f"the {self.name} arm takes no joint commands (no URDF describes it)")
        return arm

    def step_joints(self, q_target, frame) -> StepResult:
        """One policy-loop joint command toward ``q_target (n,)``, computed from camera ``frame``.

        The joint path of the module docstring. A chunk of actions computed from one frame is sent
        as one call per action, each with that frame: the first action the frame's age outlives is
        refused (and stops the arm), so the rest of the chunk must be dropped by the caller.
        """
        return self._guarded(self._step_joints, q_target, frame)

    def _step_joints(self, q_target, frame) -> StepResult:
        lim = self.limits
        scene_arm = self._scene_arm()
        self._check_time_and_frame(frame)
        q_now = np.asarray(self.__arm.joint_positions(), dtype=np.float64)
        t_cmd = self._command_clock()
        try:
            q_cmd, reasons = limit_joint_command(q_now, q_target, scene_arm, lim, self._command_period_s(t_cmd))
        except SafetyRefusal as err:
            raise _Refuse(str(err)) from None
        for r in reasons:
            self._record("clipped", r)
        self._last_command_s = t_cmd  # before sending: a servo that raises may still have reached the arm
        self.__arm.servo_joints(q_cmd, lim.control_period_s)
        self._prev_step = np.zeros(3)  # the TCP path's acceleration history does not carry over
        return StepResult("clipped" if reasons else "ok", None, tuple(reasons), q_cmd)

    def move_joints(self, q_target) -> None:
        """Positioning move to joints ``q_target (n,)`` (not the policy loop): refused, not clipped,
        if the target is not ``n`` finite numbers, outside the position limits, or puts the TCP
        outside the workspace box. It takes as long as the slowest joint needs at its speed cap."""
        try:
            scene_arm = self._scene_arm()
            q = np.asarray(q_target, dtype=np.float64)
            if q.shape != (scene_arm.n_joints,) or not np.isfinite(q).all():
                raise _Refuse(f"positioning joint target must be {scene_arm.n_joints} finite numbers, got {q}")
            lo = scene_arm.model.limits.q_min.cpu().numpy()
            hi = scene_arm.model.limits.q_max.cpu().numpy()
            if ((q < lo) | (q > hi)).any():
                k = int(np.flatnonzero((q < lo) | (q > hi))[0])
                raise _Refuse(
                    f"positioning joint target: {scene_arm.joint_names[k]!r} at {q[k]:.4g} is outside its limits "
                    f"[{lo[k]:.4g}, {hi[k]:.4g}]"
                )
            p = tcp_from_joints(scene_arm, q)[:3, 3]
            if not self.limits.contains(p):
                raise _Refuse(f"positioning joint target puts the TCP at {_vec(p)} m, outside the workspace box")
        except _Refuse as r:
            self._record("refused", r.reason)
            raise SafetyRefusal(r.reason) from None
        cap_per_s = joint_step_caps(scene_arm, self.limits, self.limits.control_period_s) / self.limits.control_period_s
        duration_s = float(np.max(np.abs(q - self.__arm.joint_positions()) / cap_per_s))
        self.__arm.keepalive()
        self._require_no_fault()
        try:
            self.__arm.move_joints(q, duration_s)
        except BaseException as err:
            self._stop_quietly(f"{type(err).__name__} during a positioning move: {err}")
            raise
        self._prev_step = np.zeros(3)
        self._last_command_s = None

    def _guarded(self, step, *args) -> StepResult:
        """``step(*args)`` with a refusal turned into a stop and a refused result, and any other
        error stopping the arm before it propagates."""
        try:
            return step(*args)
        except _Refuse as r:
            self._record("refused", r.reason)
            self._stop(f"refused command: {r.reason}")
            return StepResult("refused", None, (r.reason,))
        except BaseException as err:
            if not isinstance(err, (ArmFaultError, SafetyStop)):  # those already stopped the arm
                self._stop_quietly(f"{type(err).__name__} during a control step: {err}")
            raise

    def _check_time_and_frame(self, frame) -> None:
        """Steps 1, 2, 3 and 5 of both paths: watchdog, trial duration, frame age, fault."""
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

    def _step(self, target_fn, frame) -> StepResult:
        lim = self.limits
        self._check_time_and_frame(frame)
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
