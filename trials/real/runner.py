"""The trial session runner behind ``advobj trial run``: the plan's remaining trials, one by one.

Per trial, in this order:

1. Stage (sim hardware only: :class:`trials.real.stage.SimStage` sets the scene and object poses).
2. Positioning move to the trial's initial pose (``T_base_tcp = T_base_table @ T_table_tcp``),
   through the safety layer. It comes *before* the placement so the arm never moves while the
   operator's hands are on the table, and so the tag check sees the scene from where the policy
   will start. A joint-space policy (and any start the plan gives as joints) starts in joint space
   (:func:`resolve_starts`): the start's joints, or the IK of its TCP pose
   (:meth:`sim.ik.SceneArm.solve_start`, the simulator's own start joints), reached with
   ``SafeArm.move_joints``. A move that fails (the safety layer or the arm's driver refuses it,
   :class:`~robot_io.errors.ArmRefusedError`, or it ends in an error) while the arm then reports no
   fault ends the trial there: it is committed with stop reason ``positioning_failed: refused|fault|error:
   ...``, outcome ``unknown``, no steps and nothing to confirm, and the session goes on from where
   the arm stands. If the arm reports a fault, the error ends the session, as a fault in the policy
   loop does at the next trial's positioning move; that trial is not committed (it did not run),
   so resuming after the recovery runs it.
3. Placement guide: the locator finds the objects, :func:`placement_issues` compares them with the
   layout within the plan's tolerances, the operator is told what to move, and re-checks until
   the placement is within tolerance (or skips the check: logged in the trial's events).
4. Policy loop at ``plan.control_hz`` (no sleeping with ``rate_limit=False``, for sim arms) for
   at most ``plan.max_steps`` steps: cameras -> policy -> ``SafeArm.step_delta`` (the scene's action
   scaling) -> record. A joint-space policy reads the measured joints (``joint_positions`` state)
   and each of its joint actions becomes a joint target (:func:`sim.policies.contract.to_joint_target`
   at the measured joints, as in the simulator) sent through ``SafeArm.step_joints``; its step
   records hold the target, the joints sent and the joints measured (a joint command refused or
   stopped by the safety layer ends the trial as a TCP one does). Every step reads one frame of
   the wrist camera and of each fixed scene camera the policy reads (and of no other), and hands
   the policy ``{camera: image}``
   (:func:`sim.policies.contract.call_policy`); the safety layer checks the age of every frame the
   command was computed from (the oldest counts), and each camera's frame is written beside the
   wrist camera's in the trial's frame directory. A frame of another size than its camera's
   calibration ends the session in one line naming the camera (:class:`robot_io.cameras.base.FrameSizeError`).
   The objects are tracked in the wrist camera's frames: every step, the locator looks
   at its frame, and an object it sees is taken where it is seen from then on (an
   object moved by more than the placement tolerance is logged as a ``track`` event: the paper's
   dynamic-object scenario). Like the simulator's episodes, the loop ends early when the criterion
   says an object is reached (TCP against the tracked poses; the placement pose of an object not
   seen since). It ends too on a refused command (``refused: ...``: by the safety layer, or by the
   arm's driver, an :class:`~robot_io.errors.ArmRefusedError`: a target out of its reach, nothing
   moved), a safety stop or an arm fault (the reason is stored), and the trial is committed; after
   a fault the next trial's positioning move ends the session (step 2). A non-finite action (NaN/inf)
   is never sent to the arm: the trial stops there with outcome ``policy_error`` (step 6 is
   skipped: there is nothing to confirm), is committed, and the session goes on.
5. Outcome: what the camera sees at the end. The final TCP pose is measured, the objects are
   located from it and :func:`calibration.outcome.measure_reach` applies the paper's criterion
   (roles as names, so the outcome is ``goal``, ``adversarial``, ``none`` or ``unknown``). An
   object not seen from there (the camera is close to the objects at the end of a reach) is looked
   for again from the trial's start pose, where the placement check saw it; the arm moves there
   and back to the final pose through the safety layer, so the operator judges the trial where it
   ended (not after a fault, a safety stop or a policy error: then the arm stays). One still not
   seen (a hand took it, its tags are hidden) makes the outcome ``unknown``, never a guess from
   where it was placed; the reason says where it was last seen.
6. The operator confirms or overrides the outcome, with an optional note (an ``unknown`` outcome
   is put to the operator as a question).
7. The trial is committed in one transaction (:meth:`TrialStore.commit_trial`), frames first.

Pause (during the loop) stops the arm; on resume the trial in progress restarts from step 1 (a
paused rollout is not the experiment). Abort (key ``q``, Ctrl-C, or the operator's input closing)
stops the arm, drops the trial in progress and returns; running the same command again resumes:
committed trials are skipped, and the session refuses a plan, policy or calibration file whose
sha256 differs from the one it started with.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import torch

from calibration.outcome import measure_reach
from robot_io.arms.base import tcp_from_joints
from robot_io.errors import ArmFaultError, ArmRefusedError, RobotIOError, SafetyStop
from robot_io.poses import pose_step
from robot_io.safety import SafetyRefusal
from sim.errors import AdvobjError
from sim.policies.contract import (
    WRIST_CAMERA,
    ActionQueue,
    InputPlan,
    call_policy,
    decode_actions,
    joint_mismatch,
    policy_cameras,
    policy_contract,
    state_vector,
    to_delta,
    to_joint_target,
)
from sim.policyview import policy_view
from trials.real.locate import placement_issues
from trials.real.operator import Decision
from trials.real.store import (
    CameraFrameRecord,
    EventRecord,
    JointStepRecord,
    ObjectPoseRecord,
    SessionInfo,
    StepRecord,
    StoreError,
    TrialRecord,
    camera_frame_name,
    clear_frames,
    frames_dir,
    frames_ref,
    session_frames_dir,
)

__all__ = [
    "TrialRunner",
    "RunSummary",
    "TrialTiming",
    "ROLES",
    "Start",
    "StartError",
    "JointArmError",
    "check_joint_arm",
    "resolve_starts",
    "START_AGREE_TOL_M",
    "START_AGREE_TOL_RAD",
]

ROLES = ("goal", "adversarial")
POLICY_ERROR = "policy_error"  # outcome and stop reason of a trial whose policy gave a non-finite action
POSITIONING_FAILED = "positioning_failed"  # stop reason of a trial whose move to its start failed (it did not run)
_SIM_GUIDANCE_ROUNDS = 5  # the simulated operator follows the guidance this often before asking the real one


def policy_preprocess(policy) -> str:
    """The card's ``preprocess`` (``center_crop`` for a policy without a card)."""
    card = getattr(policy, "card", None)
    return getattr(card, "preprocess", None) or "center_crop"


def camera_input(policy, camera: str) -> tuple[tuple[int, int], str]:
    """``((H, W), preprocess)`` of the image ``policy`` takes from ``camera``: the wrist camera's is
    ``image_size`` square through the card's ``preprocess``; a scene camera's is its input's own."""
    plan = getattr(policy, "inputs", None)
    if camera == WRIST_CAMERA or not isinstance(plan, InputPlan):
        S = int(policy.image_size)
        return (S, S), policy_preprocess(policy)
    b = plan.image_for(camera)
    return (int(b.size[0]), int(b.size[1])), b.image.preprocess


def camera_view(rgb: np.ndarray, size_hw: tuple[int, int], preprocess: str, camera: str) -> np.ndarray:
    """A camera's ``(H, W, 3)`` frame as the policy takes it: as it is at the input's size, else
    through ``preprocess`` to a square input (:func:`sim.policyview.policy_view`). A frame for a
    non-square input must have its size (a session checks that before any device connects)."""
    h, w = size_hw
    if rgb.shape[:2] == (h, w):
        return rgb
    if h != w:
        raise RobotIOError(
            f"camera {camera!r}: a {rgb.shape[1]}x{rgb.shape[0]} px frame for an input of {h}x{w} px: a non-square "
            "input takes frames of its own size"
        )
    return policy_view(rgb, h, preprocess)


class PlanOutsideWorkspace(AdvobjError, ValueError):
    """A planned initial TCP pose lies outside the safety layer's workspace box."""


class StartError(AdvobjError, ValueError):
    """A planned start the arm cannot take (the message names the start, and a trial using it)."""


class JointArmError(AdvobjError, ValueError):
    """A joint-space policy on an arm that takes no joint commands, or whose joints are not the policy's."""


#: A start given as both a TCP pose and joints: the joints' forward kinematics must put the TCP
#: within this distance (m) and angle (rad) of the TCP pose, or the plan is refused.
START_AGREE_TOL_M = 1e-3
START_AGREE_TOL_RAD = 1e-2


@dataclass(frozen=True)
class Start:
    """Where a trial starts: ``T_base_tcp (4, 4)`` in the arm's base frame and, for a start reached in
    joint space, the joints ``q (n,)`` (``None``: a TCP positioning move, ``SafeArm.move_to``)."""

    T_base_tcp: np.ndarray
    q: np.ndarray | None = None


def check_joint_arm(contract, kinematics, arm_name: str) -> None:
    """Refuse, in one line, a joint-space ``contract`` the arm cannot run: an arm without kinematics
    (``kinematics`` None: no URDF describes it), or whose URDF joints (names, order, units) are not
    the contract's ``joints`` and ``joint_units`` (:func:`sim.policies.contract.joint_mismatch`, the
    comparison a scene's arm gets). A TCP contract passes on any arm."""
    if not contract.is_joint_space:
        return
    if kinematics is None:
        raise JointArmError(
            f"--policy: a joint-space policy ({contract.describe()}) on the {arm_name} arm, which takes no joint "
            "commands (no URDF describes it)"
        )
    model = kinematics.model
    chain = f"the {arm_name} arm's chain {model.base_link} -> {model.tool_link} in {model.urdf.name}"
    why = joint_mismatch(contract, kinematics.joint_names, kinematics.units, chain, model.urdf.name)
    if why is not None:
        raise JointArmError(f"--policy: {why}")


def _vec(v) -> str:
    return "[" + ", ".join(f"{float(x):.3f}" for x in v) + "]"


def resolve_starts(plan, trials, T_base_table, kinematics, joint_space: bool) -> dict[int, Start]:
    """The :class:`Start` of every start (``plan.tcp_poses`` index) ``trials`` use, before anything moves.

    A start given as joints (``joint_positions``) is taken in joint space: it needs an arm with
    ``kinematics`` (:class:`sim.ik.SceneArm`, its TCP in the base frame), one value per joint,
    within the joints' position limits, and with a TCP pose given too, forward kinematics within
    :data:`START_AGREE_TOL_M` / :data:`START_AGREE_TOL_RAD` of it; its pose is the FK one. A TCP start
    of a ``joint_space`` policy is solved by IK (:meth:`sim.ik.SceneArm.solve_start`: from the arm's
    home joints, then fixed restarts, as the simulator's starts). Any other start is a TCP pose,
    ``T_base_table @ T_table_tcp``. A start the arm cannot take raises :class:`StartError` in one
    line naming it and a trial using it.
    """
    users: dict[int, list[str]] = {}
    for t in trials:
        users.setdefault(t.tcp_pose, []).append(t.trial_id)
    starts: dict[int, Start] = {}
    solve: list[int] = []
    for k in sorted(users):
        tp = plan.tcp_pose(k)
        where = f"trial plan: tcp_poses.{k} (trial {users[k][0]}"
        where += f" and {len(users[k]) - 1} more)" if len(users[k]) > 1 else ")"
        T_plan = None if tp.T_table_tcp is None else np.asarray(T_base_table) @ tp.T_table_tcp.T()
        if tp.joint_positions is None:
            if joint_space and kinematics is not None:
                solve.append(k)
            starts[k] = Start(T_plan)
            continue
        if kinematics is None:
            raise StartError(f"{where}: joint_positions: the arm takes no joint commands (no URDF describes it)")
        q = np.asarray(tp.joint_positions, dtype=np.float64)
        names = kinematics.joint_names
        if q.shape != (kinematics.n_joints,):
            raise StartError(
                f"{where}: joint_positions: {len(q)} values for the arm's {kinematics.n_joints} joints "
                f"({', '.join(names)})"
            )
        lo = kinematics.model.limits.q_min.cpu().numpy()
        hi = kinematics.model.limits.q_max.cpu().numpy()
        out = np.flatnonzero((q < lo) | (q > hi))
        if len(out):
            j = int(out[0])
            raise StartError(
                f"{where}: joint_positions.{j}: {names[j]!r} at {q[j]:.4g} is outside its limits "
                f"[{lo[j]:.4g}, {hi[j]:.4g}]"
            )
        T_fk = tcp_from_joints(kinematics, q)
        if T_plan is not None:
            dp, dr = pose_step(T_plan, T_fk)
            if dp > START_AGREE_TOL_M or dr > START_AGREE_TOL_RAD:
                raise StartError(
                    f"{where}: joint_positions put the TCP {dp * 1000:.1f} mm and {math.degrees(dr):.2f} deg from "
                    f"its T_table_tcp (tolerance {START_AGREE_TOL_M * 1000:g} mm, "
                    f"{math.degrees(START_AGREE_TOL_RAD):.2f} deg): give one of them, or both of the same start"
                )
        starts[k] = Start(T_fk, q)
    if solve:
        T = torch.as_tensor(np.stack([starts[k].T_base_tcp for k in solve]), device=kinematics.device)
        res = kinematics.solve_start(T)
        reached = res.start_reached()  # the simulator's rule (sim.ik.START_TOL_M): a few mm short is a start
        for i, k in enumerate(solve):
            if not bool(reached[i]):
                n_more = len(users[k]) - 1
                raise StartError(
                    f"trial {users[k][0]}" + (f" (and {n_more} more)" if n_more else "") + f": start TCP pose {k} at "
                    f"{_vec(starts[k].T_base_tcp[:3, 3])} m (base frame) is out of the arm's reach (IK: "
                    f"{float(res.pos_err_m[i]):.3g} m, {float(res.rot_err_rad[i]):.3g} rad off after "
                    f"{res.iterations} iterations, from its home joints and the restarts)"
                )
            q = res.q[i].detach().cpu().numpy().astype(np.float64)
            # where the arm will be: the pose asked for, or FK of the joints a few mm short of it
            starts[k] = Start(starts[k].T_base_tcp if bool(res.converged[i]) else tcp_from_joints(kinematics, q), q)
    return starts


class _Abort(Exception):
    pass


class _Restart(Exception):
    pass


@dataclass(frozen=True)
class TrialTiming:
    """Wall-clock split of one trial (s); ``loop_hz`` = steps per second of the policy loop."""

    trial_id: str
    stage_s: float
    move_s: float
    placement_s: float
    loop_s: float
    outcome_s: float
    commit_s: float
    n_steps: int

    @property
    def overhead_s(self) -> float:
        return self.stage_s + self.move_s + self.placement_s + self.outcome_s + self.commit_s

    @property
    def loop_hz(self) -> float:
        return self.n_steps / self.loop_s if self.loop_s > 0 else float("nan")


@dataclass
class RunSummary:
    session: str
    planned: int
    already_done: int
    committed: list[str] = field(default_factory=list)
    aborted: bool = False
    abort_reason: str = ""
    timings: list[TrialTiming] = field(default_factory=list)

    @property
    def remaining(self) -> int:
        return self.planned - self.already_done - len(self.committed)


def _iso_utc(t: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(t))


def _fmt_eta(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "--:--"
    m, s = divmod(int(round(seconds)), 60)
    return f"{m // 60}:{m % 60:02d}:{s:02d}" if m >= 60 else f"{m:02d}:{s:02d}"


class TrialRunner:
    """Runs the remaining trials of one session (see the module docstring).

    Args:
        plan: :class:`trials.real.plan.TrialPlan`.
        camera: the connected wrist camera (``read() -> Frame``); the locator reads it.
        arm: a connected :class:`robot_io.safety.SafeArm`.
        policy: behind the policy interface, with ``image_size`` S; its contract
            (:mod:`sim.policies.contract`) says whether it reads the TCP pose, gripper or joints, and
            whether its actions are TCP motions (sent with ``step_delta``) or joint targets (sent with
            ``step_joints``; the arm's joints must be the contract's), in chunks of which the first
            ``k`` are executed per frame.
        store: :class:`trials.real.store.TrialStore`.
        operator: an :class:`trials.real.operator.Operator`.
        locator: a :class:`trials.real.locate.Locator`.
        session: the :class:`SessionInfo` recorded (or matched on resume).
        action_scale: (6,) per-component scale of ``delta_tcp`` actions (``[max_step_m]*3 + [max_step_rad]*3``).
        gripper_m: the finger opening a policy reading ``gripper`` state is given (the scene's).
        stage: :class:`trials.real.stage.SimStage` for sim hardware, else None (a person stages).
        T_base_table: table frame in the arm's base frame (identity for sim arms).
        rate_limit: sleep to the control period (off: as fast as possible, sim arms only).
        on_trial_end: called with the planned trial right after its policy loop (tests record the
            sim's ground truth there).
        on_step: called with the planned trial and the step index before each step's frame is
            read (a sim scenario moves or hides an object there).
        scene_cameras: ``{name: connected camera}`` of the fixed cameras; each one the policy reads
            (:func:`sim.policies.contract.policy_cameras`) must be here.
        view: a :class:`trials.real.view.LiveView` (``--view``), or None: each frame read (the wrist
            camera's at the placement check, the outcome and every step; each fixed camera's at
            every step) is published to it with the TCP pose it was taken at and the trial.
    """

    def __init__(
        self,
        plan,
        camera,
        arm,
        policy,
        store,
        operator,
        locator,
        session: SessionInfo,
        action_scale,
        stage=None,
        T_base_table=None,
        rate_limit: bool = True,
        on_trial_end: Callable | None = None,
        on_step: Callable | None = None,
        gripper_m: float = 0.06,
        stop_on_reach: bool = True,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable = time.sleep,
        scene_cameras=None,
        view=None,
    ):
        self.plan = plan
        self.camera = camera
        self.scene_cameras = dict(scene_cameras or {})
        self.cameras = policy_cameras(policy)  # what the policy reads, in its input order
        missing = [c for c in self.cameras if c != WRIST_CAMERA and c not in self.scene_cameras]
        if missing:
            have = ", ".join([WRIST_CAMERA, *self.scene_cameras])
            raise RobotIOError(f"the policy reads camera {missing[0]!r}; the cell has {have}")
        self._inputs = {c: camera_input(policy, c) for c in self.cameras}
        self.arm = arm
        self.policy = policy
        self.store = store
        self.operator = operator
        self.locator = locator
        self.session = session
        self.action_scale = np.asarray(action_scale, dtype=np.float64).reshape(6)
        self.gripper_m = float(gripper_m)
        self.stage = stage
        self.T_base_table = np.eye(4) if T_base_table is None else np.asarray(T_base_table, dtype=np.float64)
        self.T_table_base = np.linalg.inv(self.T_base_table)
        self.rate_limit = rate_limit
        self.on_trial_end = on_trial_end
        self.on_step = on_step
        self.stop_on_reach = stop_on_reach
        self.clock = clock
        self.sleep = sleep
        self._sid: int | None = None  # the session's row id, once run() opened it
        self._kinematics = None  # the arm's (sim.ik.SceneArm), once run() checked it against the policy
        self._starts: dict[int, Start] = {}  # plan.tcp_poses index -> where its trials start (run())
        self.view = view
        self._trial = None  # the trial in progress, for the live view

    # ------------------------------------------------------------------ session
    def run(self, max_trials: int | None = None) -> RunSummary:
        """Run the remaining trials, holding the session's lock (taken here unless the caller holds it)."""
        ordered = sorted(self.plan.trials, key=lambda t: t.order)
        # Before the session is opened: a refused policy or plan records nothing.
        contract = policy_contract(self.policy)
        kinematics = self.arm.kinematics()
        check_joint_arm(contract, kinematics, self.arm.name)
        self._kinematics = kinematics
        self._starts = resolve_starts(self.plan, ordered, self.T_base_table, kinematics, contract.is_joint_space)
        self._check_initial_poses(ordered)
        session_frames_dir(
            self.store.path, self.session.name
        )  # a name that is no safe directory: refused, nothing recorded
        # Only the session's one runner reads which trials are done and clears frames (issue 25).
        with self.store.session_locked(self.session.name):
            return self._run(ordered, max_trials)

    def _run(self, ordered, max_trials: int | None) -> RunSummary:
        sid = self._sid = self.store.open_session(self.session)
        done = self.store.committed_trial_ids(sid)
        todo = [t for t in ordered if t.trial_id not in done]
        summary = RunSummary(self.session.name, len(ordered), len(ordered) - len(todo))
        if max_trials is not None:
            todo = todo[: max(0, int(max_trials))]
        if summary.already_done:
            self.operator.show(
                f"session {self.session.name}: {summary.already_done} of {len(ordered)} trials already done, resuming"
            )
        current = None
        try:
            for i, trial in enumerate(todo):
                current = trial
                self.operator.show(
                    self._header(trial, summary.already_done + i + 1, len(ordered), summary.timings, len(todo) - i)
                )
                while True:
                    try:
                        rec, timing = self._run_trial(trial)
                        break
                    except _Restart:
                        self.operator.show(f"  restarting {trial.trial_id}")
                t = self.clock()
                self.store.commit_trial(sid, rec)
                timing = TrialTiming(**{**timing.__dict__, "commit_s": self.clock() - t})
                summary.committed.append(trial.trial_id)
                summary.timings.append(timing)
                current = None
                self.operator.show(
                    f"  committed: {rec.final_outcome}"
                    + (f" (auto: {rec.auto_outcome})" if rec.operator_outcome else "")
                    + f", {len(rec.steps)} steps at {timing.loop_hz:.1f} Hz, {rec.stop_reason}"
                )
        except (_Abort, KeyboardInterrupt, EOFError) as err:
            # EOF: the operator's input closed (terminal gone, answers piped in ran out). Nobody can
            # confirm outcomes any more, so it is an abort like 'q', not a crash with a traceback.
            summary.aborted = True
            summary.abort_reason = (
                "Ctrl-C"
                if isinstance(err, KeyboardInterrupt)
                else "operator input closed"
                if isinstance(err, EOFError)
                else "operator abort"
            )
            self._stop_quietly(f"session aborted ({summary.abort_reason})")
            if current is not None and current.trial_id not in self.store.committed_trial_ids(sid):
                self._clear_uncommitted(current.trial_id)
        return summary

    def _clear_uncommitted(self, trial_id: str) -> Path:
        """Clear the frame directory of ``trial_id``, a leftover of an interrupted attempt, and return it.

        Only by the session's lock holder, and only for a trial the store has not committed: a
        committed trial's frames are its record and are never removed (issue 25).
        """
        self.store.check_session_owner(self.session.name)
        if trial_id in self.store.committed_trial_ids(self._sid):
            raise StoreError(
                f"session {self.session.name}: trial {trial_id} is already committed; its frames are kept "
                "(is another runner working on this session?)"
            )
        fdir = frames_dir(self.store.path, self.session.name, trial_id)
        clear_frames(fdir)
        return fdir

    def _check_initial_poses(self, trials) -> None:
        """Refuse the plan if an initial TCP pose (:func:`resolve_starts`) lies outside the workspace box.

        The safety layer would refuse that positioning move in the middle of the session; checking
        every pose up front turns it into one error, before anything moves, naming the poses.
        """
        limits = self.arm.limits
        bad = {}
        for t in trials:
            if t.tcp_pose in bad:
                bad[t.tcp_pose][1].append(t.trial_id)
                continue
            p = self._starts[t.tcp_pose].T_base_tcp[:3, 3]
            if not limits.contains(p):
                bad[t.tcp_pose] = (p, [t.trial_id])
        if bad:
            lines = [
                f"TCP pose {k} at [{', '.join(f'{v:.3f}' for v in p)}] m in the base frame ({len(ids)} trials, "
                f"e.g. {ids[0]})"
                for k, (p, ids) in sorted(bad.items())
            ]
            raise PlanOutsideWorkspace(
                "trial plan: initial TCP poses outside the safety workspace box "
                f"{list(limits.workspace_min_m)} .. {list(limits.workspace_max_m)} m:\n  "
                + "\n  ".join(lines)
                + "\nwiden workspace_min_m / workspace_max_m in the hardware YAML (if the cell allows it) or make "
                "a new plan"
            )

    def _header(self, trial, k: int, n: int, timings, left: int) -> str:
        per = np.mean([t.overhead_s + t.loop_s + t.commit_s for t in timings]) if timings else float("nan")
        return (
            f"[{k}/{n}] {trial.trial_id}: env {trial.env}, shape {trial.shape}, {trial.condition}, TCP pose "
            f"{trial.tcp_pose}, "
            f"layout {trial.object_layout}"
            + (f", tags {','.join(trial.tags)}" if trial.tags else "")
            + f"   ETA {_fmt_eta(per * left)}"
        )

    def _stop_quietly(self, reason: str) -> None:
        try:
            self.arm.stop(reason)
        except Exception:  # noqa: BLE001 - the driver's own watchdog stops a dead link; keep the first error
            pass

    # ------------------------------------------------------------------ one trial
    def _run_trial(self, trial):
        plan = self.plan
        self._trial = trial
        t_wall = time.time()
        t0 = self.clock()
        events: list[EventRecord] = []
        fdir = self._clear_uncommitted(trial.trial_id)  # a leftover of an interrupted attempt at this trial
        fdir.mkdir(parents=True)
        rel_dir = frames_ref(self.session.name, trial.trial_id)

        if self.stage is not None:
            self.stage.prepare(trial)
        if hasattr(self.locator, "for_trial"):  # a tag locator looks for this trial's object by its name
            self.locator.for_trial(plan, trial)
        t1 = self.clock()
        start = self._starts[trial.tcp_pose]
        n_ev = len(self.arm.events)
        try:
            self._move_to_start(start)
        except RobotIOError as err:
            if self.arm.fault() is not None:
                raise  # the arm must be recovered: the session stops here, and this trial (not run) stays to do
            return self._not_started(trial, err, n_ev, events, rel_dir, t_wall, t0, t1)
        t2 = self.clock()
        layout = plan.object_layout(trial.object_layout).objects
        placed, checks, skipped = self._placement(trial, layout, events, t0)
        t3 = self.clock()

        n_ev = len(self.arm.events)
        tracked = {
            r: (obj, -1) for r, obj in placed.items()
        }  # role -> (last seen pose, step; -1 = the placement check)

        with getattr(self.operator, "running", contextlib.nullcontext)():
            steps, stop_reason, t_loop, light = self._loop(trial, placed, tracked, fdir, rel_dir, events, t0)
        policy_error = stop_reason.startswith(POLICY_ERROR)
        t4 = self.clock()
        self.arm.stop("trial ended")
        if self.on_trial_end is not None:
            self.on_trial_end(trial)
        events += self._safety_events(n_ev, t0)

        result, final, T_table_tcp = self._outcome(start, stop_reason, events, t0)
        reason = result.reason + "".join(f"; {self._last_seen(role, tracked)}" for role in result.missing)
        info = f"  outcome: {result.reached} ({reason}); distances " + ", ".join(
            f"{k} {'?' if v is None else f'{v * 100:.1f} cm'}" for k, v in result.distances_m.items()
        )
        t5 = self.clock()
        if policy_error:
            # the policy broke, the arm was stopped before that action: no outcome to confirm
            self.operator.show(f"  {stop_reason}; trial stopped, recorded as {POLICY_ERROR}")
            result = dataclasses.replace(result, reached=POLICY_ERROR, reason=stop_reason)
            reason = stop_reason
            decision = Decision()
        else:
            decision: Decision = self.operator.confirm(trial, result, info)
        if decision.abort:
            raise _Abort()
        if decision.outcome is not None and decision.outcome != result.reached:
            events.append(
                EventRecord(self.clock() - t0, "operator", "override", f"{result.reached} -> {decision.outcome}")
            )
        operator_outcome = decision.outcome if decision.outcome != result.reached else None

        poses = [self._pose_record(role, "placement", placed.get(role)) for role in ROLES]
        poses += [self._pose_record(role, "final", final.get(role)) for role in ROLES]
        rec = self._trial_record(
            trial,
            t_wall,
            t0,
            rel_dir,
            stop_reason=stop_reason,
            auto_outcome=result.reached,
            auto_reason=reason,
            distances_m=result.distances_m,
            operator_outcome=operator_outcome,
            note=decision.note,
            placement_checks=checks,
            placement_skipped=skipped,
            T_table_tcp_final=T_table_tcp,
            steps=steps,
            object_poses=poses,
            events=events,
            light_level=light,
        )
        timing = TrialTiming(trial.trial_id, t1 - t0, t2 - t1, t3 - t2, t_loop, t5 - t4, 0.0, len(steps))
        return rec, timing

    def _safety_events(self, since: int, t0: float) -> list[EventRecord]:
        """The safety layer's events from its ``since``-th on, as the trial's (times from ``t0``)."""
        return [EventRecord(ev.time_s - t0, "safety", ev.action, ev.reason) for ev in list(self.arm.events)[since:]]

    def _trial_record(self, trial, t_wall: float, t0: float, rel_dir: str, **fields) -> TrialRecord:
        """The :class:`TrialRecord` of ``trial``, begun at ``t_wall`` (``t0`` on :attr:`clock`): the plan's
        fields, when it started and how long it took, its frame directory, and ``fields`` (what it did)."""
        ref = self.plan.texture_for(trial)
        return TrialRecord(
            trial_id=trial.trial_id,
            plan_order=trial.order,
            env=trial.env,
            shape=trial.shape,
            condition=trial.condition,
            tcp_pose=trial.tcp_pose,
            object_layout=trial.object_layout,
            tags=list(trial.tags),
            texture_sha256=None if ref is None else ref.sha256,
            started_at=_iso_utc(t_wall),
            duration_s=self.clock() - t0,
            frames_dir=rel_dir,
            **fields,
        )

    def _not_started(self, trial, err: RobotIOError, n_ev: int, events, rel_dir: str, t_wall: float, t0, t1):
        """The record of a trial whose positioning move failed with ``err`` while the arm reports no
        fault (step 2 of the module docstring): ``positioning_failed: refused|fault|error: <err>``, no
        placement, steps or outcome (``unknown``, nothing to confirm), the safety layer's events since
        ``n_ev``; the arm stays where the move left it and the next trial starts from there."""
        kind = (
            "refused"
            if isinstance(err, (ArmRefusedError, SafetyRefusal))
            else "fault"
            if isinstance(err, ArmFaultError)
            else "error"
        )
        stop_reason = f"{POSITIONING_FAILED}: {kind}: {err}"
        t2 = self.clock()
        events += [*self._safety_events(n_ev, t0), EventRecord(t2 - t0, "positioning", "failed", stop_reason)]
        self.operator.show(f"  {stop_reason}; the trial did not run, recorded as unknown")
        rec = self._trial_record(
            trial,
            t_wall,
            t0,
            rel_dir,
            stop_reason=stop_reason,
            auto_outcome="unknown",
            auto_reason=stop_reason,
            distances_m={role: None for role in ROLES},
            operator_outcome=None,
            note="",
            placement_checks=0,
            placement_skipped=False,
            T_table_tcp_final=self.T_table_base @ self.arm.tcp_pose(),
            object_poses=[self._pose_record(role, phase, None) for phase in ("placement", "final") for role in ROLES],
            events=events,
        )
        return rec, TrialTiming(trial.trial_id, t1 - t0, t2 - t1, 0.0, 0.0, 0.0, 0.0, 0)

    def _move_to_start(self, start: Start) -> None:
        """The positioning move to ``start``: in joint space when it has joints, else to its TCP pose."""
        if start.q is None:
            self.arm.move_to(start.T_base_tcp)
        else:
            self.arm.move_joints(start.q)

    def _locate(self):
        frame = self.camera.read()
        T_base_tcp = self.arm.tcp_pose()
        self._publish({WRIST_CAMERA: frame}, T_base_tcp)
        return self.locator.locate(frame, T_base_tcp)

    def _publish(self, frames, T_base_tcp) -> None:
        """Hand ``{camera: frame}``, just read with the TCP at ``T_base_tcp``, to the live view (if
        any): a reference each, under its lock; no camera is read for it and nothing waits on a client."""
        if self.view is not None:
            T_table_tcp = self.T_table_base @ T_base_tcp
            for camera, frame in frames.items():
                self.view.publish(camera, frame, T_table_tcp, self._trial)

    def _placement(self, trial, layout, events, t0):
        """Check (and guide) the placement until it is within tolerance or skipped."""
        plan = self.plan
        attempt = 0
        while True:
            attempt += 1
            located = self._locate()
            issues = placement_issues(layout, located, plan.placement_tolerance_m, plan.placement_tolerance_rad)
            if not issues:
                if attempt > 1:
                    self.operator.show("  placement OK")
                return located, attempt, False
            text = "; ".join(i.message for i in issues)
            events.append(EventRecord(self.clock() - t0, "placement", "out_of_tolerance", text))
            if self.stage is not None and attempt <= _SIM_GUIDANCE_ROUNDS:
                self.operator.show(f"  placement check {attempt}: {text} (simulated operator corrects)")
                self.stage.follow_guidance(issues)
                continue
            answer = self.operator.placement(trial, issues, attempt)
            if answer == "abort":
                raise _Abort()
            if answer == "skip":
                events.append(EventRecord(self.clock() - t0, "operator", "skip_placement", text))
                return located, attempt, True

    def _read_frames(self):
        """The wrist camera's frame (the locator's, read first) and ``{camera: frame}`` of each camera
        the policy reads, in its input order: one frame of each, and of no other camera."""
        wrist = self.camera.read()
        return wrist, {c: wrist if c == WRIST_CAMERA else self.scene_cameras[c].read() for c in self.cameras}

    def _policy_images(self, frames) -> dict:
        """``{camera: (1, H, W, 3)}`` of the policy's frames, each as its input takes it."""
        return {c: camera_view(frames[c].rgb, *self._inputs[c], c)[None] for c in self.cameras}

    def _reached_now(self, T_base_tcp, tracked) -> bool:
        if not self.stop_on_reach or any(r not in tracked for r in ROLES):
            return False
        p = (self.T_table_base @ T_base_tcp)[:3, 3]
        res = measure_reach(p, {r: tracked[r][0].center_table_m for r in ROLES}, ROLES, self.plan.radius_m)
        return res.reached in ROLES

    def _track(self, frame, T_base_tcp, k: int, placed, tracked, moved: set, events, t0) -> None:
        """Take every object the locator sees in ``frame`` where it is seen; log the first time one
        has moved beyond the placement tolerance."""
        for role, obj in self.locator.locate(frame, T_base_tcp).items():
            if role not in ROLES:
                continue
            tracked[role] = (obj, k)
            ref = placed.get(role)
            if ref is not None and role not in moved:
                d = float(np.linalg.norm(obj.xy_m - ref.xy_m))
                if d > self.plan.placement_tolerance_m:
                    moved.add(role)
                    events.append(
                        EventRecord(
                            self.clock() - t0,
                            "track",
                            "moved",
                            f"{role} moved {d * 100:.1f} cm from its placement by step {k}",
                        )
                    )

    @staticmethod
    def _last_seen(role: str, tracked) -> str:
        if role not in tracked:
            return f"{role} never seen"
        obj, k = tracked[role]
        where = "at the placement check" if k < 0 else f"at step {k}"
        return f"{role} last seen {where}, at [{', '.join(f'{v:.3f}' for v in obj.center_table_m)}] m"

    def _loop(self, trial, placed, tracked, fdir: Path, rel_dir: str, events, t0):
        period = 1.0 / float(self.plan.control_hz)
        steps: list[StepRecord] = []
        stop_reason = "max_steps"
        light = None
        moved: set[str] = set()

        contract = policy_contract(self.policy)
        queue = ActionQueue(contract, 1)
        joint = contract.is_joint_space
        self.arm.start_trial()
        t_start = self.clock()
        T_frame = self.arm.tcp_pose()  # the arm's pose when the next frame is taken
        q_frame = self.arm.joint_positions() if joint else None  # and its joints (a joint-space policy's state)
        for k in range(int(self.plan.max_steps)):
            t_tick = self.clock()
            cmd = self.operator.poll()
            if cmd == "abort":
                raise _Abort()
            if cmd == "pause":
                self.arm.stop("paused by the operator")
                if self.operator.paused() == "abort":
                    raise _Abort()
                raise _Restart()
            if self.on_step is not None:
                self.on_step(trial, k)
            frame, frames = self._read_frames()
            self._publish({**frames, WRIST_CAMERA: frame}, T_frame)
            if light is None:  # what the camera saw at the start: the lighting scenarios' measure
                light = float(np.asarray(frame.rgb, dtype=np.float32).mean() / 255.0)
            if queue.needs([0]):
                # A new chunk from these frames; its later actions keep them as the ones the policy
                # saw (the safety layer's frame-age check is on every one of them: the oldest counts).
                # Poses in the contract are in the task's frame: the table frame, the sim's world frame.
                q_state = None if q_frame is None else q_frame[None]
                state = state_vector(contract, self.T_table_base @ T_frame, self.gripper_m, q_state)
                raw = np.asarray(call_policy(self.policy, self._policy_images(frames), state), dtype=np.float64)
                queue.push([0], decode_actions(raw, contract, 1))
                seen = frames
            action = queue.pop([0])[0]
            if not np.isfinite(action).all():
                # never sent to the arm (the safety layer would refuse it too) and not a step record:
                # the action columns hold numbers only
                stop_reason = (
                    f"{POLICY_ERROR}: the policy output a non-finite action at step {k} "
                    f"([{', '.join(f'{a:g}' for a in action)}])"
                )
                events.append(EventRecord(self.clock() - t0, "policy", "error", stop_reason))
                break
            try:
                if joint:
                    # The joint target at the measured joints, as the sim makes it; the safety layer
                    # enforces the limits (the sim's limit_step is the same rule) and refuses a jump.
                    q_target = np.asarray(to_joint_target(q_frame, action, contract.action.kind), dtype=np.float64)
                    res = self.arm.step_joints(q_target, seen)
                else:
                    # The sim's own step toward the action (an absolute target: the limited motion toward
                    # it from the measured pose, direction kept); the safety layer stays the backstop.
                    delta = to_delta(
                        (self.T_table_base @ T_frame)[None],
                        action[None],
                        contract.action.kind,
                        float(self.action_scale[0]),
                        float(self.action_scale[3]),
                    )[0]
                    res = self.arm.step_delta(delta * self.action_scale, seen)
            except SafetyStop as err:
                stop_reason = f"safety_stop: {err}"
                break
            except ArmRefusedError as err:  # the driver refused the target: the arm is fine, the trial ends
                stop_reason = f"refused: {err}"
                break
            except ArmFaultError as err:
                stop_reason = f"fault: {err}"
                break
            t_cmd = self.clock()
            # Tracking looks at the frame the policy acted on, after its command is sent: a tag
            # detection must not age the frame the safety layer checks.
            self._track(frame, T_frame, k, placed, tracked, moved, events, t0)
            T_meas = T_frame = self.arm.tcp_pose()
            T_cmd, joints = res.T_cmd, None
            if joint:
                q_frame = self.arm.joint_positions()
                q_cmd = None if res.q_cmd is None else np.asarray(res.q_cmd, dtype=np.float64)
                # the TCP the joints sent put it at
                T_cmd = None if q_cmd is None else tcp_from_joints(self._kinematics, q_cmd)
                joints = JointStepRecord(q_target.tolist(), None if q_cmd is None else q_cmd.tolist(), q_frame.tolist())
            name = camera_frame_name(k)
            cv2.imwrite(str(fdir / name), cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR))
            extra = {}
            for cam, f in frames.items():
                if cam != WRIST_CAMERA:  # each fixed camera's frame beside the wrist camera's
                    cam_name = camera_frame_name(k, cam)
                    cv2.imwrite(str(fdir / cam_name), cv2.cvtColor(f.rgb, cv2.COLOR_RGB2BGR))
                    extra[cam] = CameraFrameRecord(f"{rel_dir}/{cam_name}", int(f.seq), f.timestamp_s - t_start)
            steps.append(
                StepRecord(
                    k,
                    frame.timestamp_s - t_start,
                    t_cmd - t_start,
                    int(frame.seq),
                    action.tolist(),
                    T_cmd,
                    T_meas,
                    res.status,
                    "; ".join(res.reasons),
                    f"{rel_dir}/{name}",
                    extra,
                    joints,
                )
            )
            if res.status == "refused":
                stop_reason = f"refused: {'; '.join(res.reasons)}"
                break
            if self._reached_now(T_meas, tracked):
                stop_reason = "reached"
                break
            if self.rate_limit:
                wait = t_tick + period - self.clock()
                if wait > 0:
                    self.sleep(wait)
        return steps, stop_reason, self.clock() - t_start, light

    def _outcome(self, start: Start, stop_reason: str, events, t0):
        """The criterion at the final TCP position on what the camera sees (an unseen object: unknown).

        At the end of a reach the wrist camera is close to the objects and often sees neither
        whole; an object not seen from the final pose is looked for again from the trial's start
        pose (the placement check's view), after the final TCP pose is measured, and the arm then
        returns to the final pose, so the operator judges the trial where it ended. After a fault,
        a safety stop or a policy error the arm does not move again: the object stays unseen.
        """
        T_base_final = self.arm.tcp_pose()
        # a start reached in joint space is looked from and left in joint space: the same joints
        final_at = Start(T_base_final, None if start.q is None else self.arm.joint_positions())
        T_table_tcp = self.T_table_base @ T_base_final
        final = self._locate()
        unseen = [r for r in ROLES if r not in final]
        if unseen:
            stopped = stop_reason.startswith(("fault", "safety_stop", POLICY_ERROR)) or self.arm.fault() is not None
            if stopped:
                events.append(
                    EventRecord(
                        self.clock() - t0,
                        "outcome",
                        "no_look_again",
                        f"not seen from the final pose: {', '.join(unseen)}; the arm stays where the trial "
                        f"stopped ({stop_reason.split(':')[0]})",
                    )
                )
            else:
                try:
                    self._move_to_start(start)
                    again = self._locate()
                    self._move_to_start(final_at)
                except RobotIOError as err:  # a fault or refusal on the way: the outcome stays unseen
                    events.append(EventRecord(self.clock() - t0, "outcome", "look_again_failed", str(err)))
                else:
                    found = [r for r in unseen if r in again]
                    final = {**final, **{r: again[r] for r in found}}
                    events.append(
                        EventRecord(
                            self.clock() - t0,
                            "outcome",
                            "look_again",
                            f"not seen from the final pose: {', '.join(unseen)}; from the start pose: "
                            f"{', '.join(found) or 'none of them'}; back at the final pose",
                        )
                    )
        positions = {role: final[role].centers_for_outcome() for role in ROLES if role in final}
        return measure_reach(T_table_tcp[:3, 3], positions, ROLES, self.plan.radius_m), final, T_table_tcp

    def _pose_record(self, role: str, phase: str, obj) -> ObjectPoseRecord:
        if obj is None:
            return ObjectPoseRecord(role, phase, None, None, (), False, 0, getattr(self.locator, "source", "tags"))
        n_alt = 0 if obj.alternatives_center_m is None else len(obj.alternatives_center_m)
        return ObjectPoseRecord(
            role,
            phase,
            obj.T_table_object,
            obj.center_table_m,
            obj.tag_ids,
            obj.ambiguous,
            n_alt,
            obj.source,
            obj.visible_fraction,
        )
