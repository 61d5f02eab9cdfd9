"""Assembling a trial session from files: hardware YAML, plan, policy, registry -> a running :class:`TrialRunner`.

:class:`SessionOptions` holds every input of a session, one field per flag of ``advobj trial run``
(``table_frame`` is ``--table-frame``); building it checks types, bounds, the session name and the
operator's flags, and a bad value raises one :class:`AdvobjError` naming its flag.

:func:`run_session` is ``advobj trial run`` without the command line: it takes the options, loads
and checks every input before any device connects, records the session's provenance (plan text
and sha256, hardware YAML, policy sha256, software version and git commit, device identities,
sha256 of the calibration files), then runs inside ``with camera, arm:`` so any exception stops
the arm. It is :func:`prepare_session` (no device, nothing written) then :func:`run_prepared`.

With ``sim`` devices the table is staged by :class:`trials.real.stage.SimStage` and located by
:class:`trials.real.locate.SimLocator` (ground truth); the sim camera renders at the policy's
input size unless the hardware YAML sets ``sim.image_size``. Real cells need ``--registry`` (the
tag -> object registry) and a ``T_base_table`` (``--table-frame`` YAML, or estimated from the
registry's ``table`` tags seen from the arm's current pose). The table frame is stored with the
session: a resume without ``--table-frame`` reuses the stored one, never re-estimates it (the arm
may now stand where no table tag is in view, and trials of one session must share one frame).

Cameras: the policy's card says which cameras it reads (:func:`sim.policies.contract.policy_cameras`);
the wrist camera is the hardware YAML's ``camera``, every other one must be one of its
``scene_cameras``, and only those the policy reads are opened. Checked before anything is written
or any device opens, each in one line: a camera the cell does not have; a sim scene camera its
scene lacks, or rendering another size than the policy's input; a real one whose pose file is
missing or bad, or whose frames (the pose file's size) cannot become a non-square input. Once the
cameras are connected, one frame of each fixed camera is read before the session is recorded: a
frame of another size than its calibration ends the session there, in one line naming the camera.

Joint-space policies (a ``joint_position`` / ``joint_delta`` card) run on an arm a URDF describes:
on sim hardware the scene's arm (checked against the card before any device exists,
:func:`sim.policies.contract.check_joints`); on any arm, the runner refuses one whose kinematics
are missing or name other joints before the session is recorded
(:func:`trials.real.runner.check_joint_arm`). The session's config records the card's joints.

Resuming checks the inputs against the stored session before any device connects
(:meth:`trials.real.store.TrialStore.check_resume`): another plan, policy or calibration file is
refused; a changed advobj version, git commit, hardware YAML or device is logged as a warning and
recorded in the session's ``runs``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import importlib.metadata
import math
import time
from pathlib import Path
from typing import Callable, Optional

import numpy as np
from pydantic import Field, ValidationError, field_validator, model_validator

from calibration.errors import CalibrationFileError
from calibration.io import PoseModel, load_model, load_scene_camera_pose, read_yaml
from calibration.registry import load_registry, save_registry
from robot_io.cameras.sim import sim_registry, sim_tags
from robot_io.config import (
    build_arm,
    build_camera,
    build_scene_camera,
    build_world,
    load_hardware_config,
    load_T_tcp_cam,
    scene_camera_pose,
)
from robot_io.errors import MissingIntrinsicsError
from sim.configio import StrictModel, merged
from sim.errors import AdvobjError, flag_error
from sim.geometry import rotation_angle
from sim.policies.checkpoint import is_checkpoint, load_checkpoint, load_policy
from sim.policies.contract import (
    WRIST_CAMERA,
    call_policy,
    check_joints,
    decode_actions,
    policy_cameras,
    policy_contract,
    state_vector,
)
from sim.policies.interface import PolicyError
from sim.policies.onnx_policy import OnnxPolicy
from sim.policyview import policy_view_K, view_mismatch
from sim.runinfo import git_commit, write_run_info
from sim.spec import UnknownCameraError, load_spec
from trials.real.locate import SimLocator, TagLocator
from trials.real.locks import arm_lock
from trials.real.operator import AutoOperator, ScriptedOperator, TerminalOperator
from trials.real.plan import load_plan, plan_sha256
from trials.real.runner import TrialRunner, camera_input, policy_preprocess
from trials.real.stage import SimStage
from trials.real.store import (
    DEFAULT_DB,
    SESSION_NAME_RULE,
    SessionInfo,
    TrialStore,
    check_database,
    check_session_name,
    session_frames_dir,
)
from trials.real.view import DEFAULT_VIEW_PORT, LiveView, PlacementOverlay, view_cameras

__all__ = [
    "SessionSetupError",
    "SessionOptions",
    "PreparedSession",
    "file_sha256",
    "device_identity",
    "load_trial_policy",
    "load_T_base_table",
    "prepare_session",
    "run_prepared",
    "run_session",
]


class SessionSetupError(AdvobjError, ValueError):
    """An input of ``advobj trial run`` is missing or inconsistent; the message names it."""


def _flag(field: str) -> str:
    """The command-line flag of a :class:`SessionOptions` field: ``table_frame`` -> ``--table-frame``."""
    return "--" + field.replace("_", "-")


class SessionOptions(StrictModel):
    """Every input of one trial session: what ``advobj trial run``'s flags say, one field per flag.

    Building it (``SessionOptions(hardware=..., ...)``) checks the values, not the files: types, bounds,
    the session name and that the operator's answers come from one source. A bad value raises one
    :class:`AdvobjError` naming the flag (``--threads: ...``, ``--session: ...``), never a field path.
    The files are read and checked by :func:`prepare_session`. Who confirms outcomes (an explicit
    operator), the log and the callbacks are arguments of the functions, not options.
    """

    hardware: Path = Field(description="hardware YAML (camera, arm, safety limits, calibration files)")
    policy: Path = Field(description="policy: .onnx file (onnxruntime) or checkpoint directory")
    plan: Path = Field(description="trial plan YAML from 'advobj trial plan'")
    session: str = Field(
        description=f"session name ({SESSION_NAME_RULE}); its frames go to frames/<session>/ beside the "
        "database; the same name resumes an interrupted session"
    )
    db: Path = Field(Path(DEFAULT_DB), description="trial database (frames go to frames/ beside it)")
    answers: Optional[Path] = Field(
        None, description="operator answers YAML: {trial_id: {outcome: ..., note: ...}} or a list in run order"
    )
    auto_confirm: bool = Field(False, description="accept every automatic outcome (CI, scripted sessions)")
    registry: Optional[Path] = Field(None, description="tag registry YAML (objects.yaml); needed with a real camera")
    table_frame: Optional[Path] = Field(
        None,
        description="YAML with T_base_table; None: estimated from the registry's table tags at the session's "
        "start, stored, reused on resume (sim devices: only the identity)",
    )
    max_trials: Optional[int] = Field(None, ge=0, description="run at most this many of the remaining trials")
    rate_limit: Optional[bool] = Field(
        None, description="hold the plan's control rate; None: on, off for sim arms without realtime: true"
    )
    threads: int = Field(1, ge=1, description="onnxruntime threads (1: leaves a core to the camera and renderer)")
    take_over_stale_lock: bool = Field(
        False,
        description="take the session over from a runner the database names but that holds no lock (one on "
        "another host, or a live process that is not that run); a dead runner on this host is taken over anyway",
    )
    view: bool = Field(
        False,
        description="serve the cameras' latest frames with the plan's placement overlay on a web page at "
        "127.0.0.1 while the session runs (trials.real.view)",
    )
    view_port: Optional[int] = Field(
        None, ge=0, le=65535, description=f"the live view's port (default {DEFAULT_VIEW_PORT}; 0: any free port)"
    )

    def __init__(self, **values):
        try:
            super().__init__(**values)
        except ValidationError as err:
            raise _options_error(err) from None

    @field_validator("session")
    @classmethod
    def _safe_session_name(cls, value: str) -> str:
        return check_session_name(value, _flag("session"))

    @model_validator(mode="after")
    def _one_answer_source(self):
        if self.answers is not None and self.auto_confirm:
            raise SessionSetupError("--auto-confirm and --answers: give one of them")
        if self.view_port is not None and not self.view:
            raise SessionSetupError("--view-port: only with --view (the live view it is the port of)")
        return self


def _options_error(err: ValidationError) -> AdvobjError:
    """One error naming the flags of a :class:`SessionOptions` validation failure
    (:func:`sim.errors.flag_error`; an unknown field is not an option of a trial session)."""
    return flag_error(err, _flag, "session options", SessionSetupError, extra="not an option of a trial session")


def file_sha256(path: str | Path | None) -> str | None:
    """sha256 of a file's bytes, of a directory's files (sorted relative paths + bytes), or None."""
    if path is None:
        return None
    p = Path(path)
    h = hashlib.sha256()
    if p.is_dir():
        for f in sorted(x for x in p.rglob("*") if x.is_file()):
            h.update(f.relative_to(p).as_posix().encode() + b"\0")
            h.update(f.read_bytes())
        return h.hexdigest()
    if not p.is_file():
        return None
    h.update(p.read_bytes())
    return h.hexdigest()


def device_identity(device) -> dict:
    """What a connected device says about itself: its type, address and, where the hardware reports
    one, its serial number (:meth:`robot_io.device.Device.identity`)."""
    return {"type": device.name, **device.identity()}


def load_trial_policy(path: str | Path, threads: int = 1):
    """An ``.onnx`` file through onnxruntime with ``threads`` threads, else the project's loader (checkpoints)."""
    p = Path(path)
    if p.suffix.lower() == ".onnx" and p.is_file():
        return OnnxPolicy(p, threads=threads)

    if is_checkpoint(p):
        policy, card = load_checkpoint(p)
        policy.card = card  # the runner reads its preprocess
        return policy
    return load_policy(p)


def load_T_base_table(path: str | Path) -> np.ndarray:
    """``T_base_table`` from ``{T_base_table: {translation_m: [..], rotvec_rad: [..]}}`` (or the pose at top level)."""
    data = read_yaml(path)
    if isinstance(data, dict) and set(data) == {"T_base_table"}:
        data = data["T_base_table"]
    return load_model(path, PoseModel, data=data).T


def _scene_spec(plan, hw):
    if plan.scene is not None:
        return load_spec(Path(plan.scene))
    return load_spec(hw.sim.scene)


@dataclasses.dataclass(frozen=True)
class PreparedSession:
    """A session with every input loaded and validated, before any device exists
    (:func:`prepare_session`); :func:`run_prepared` connects the devices and runs it."""

    opts: SessionOptions  # what was asked for
    hw: object  # robot_io.config.HardwareConfig, the safety layer at the plan's rate
    plan: object  # trials.real.plan.TrialPlan
    policy: object
    spec: object  # the scene the trials use
    session_dir: Path
    operator: object
    rate_limit: bool  # opts.rate_limit, or its default for these devices
    info: object  # trials.real.store.SessionInfo (devices filled in when they connect)
    action_scale: tuple
    scene_cameras: tuple[str, ...] = ()  # the fixed cameras the policy reads (the wrist camera aside)

    @property
    def sim(self) -> bool:
        return self.hw.camera.type == "sim"


def prepare_session(opts: SessionOptions, *, operator=None, log=print) -> PreparedSession:
    """Load and check everything a session needs, touching no device: the session's frames folder,
    the database's integrity, the hardware config, the plan, the operator's answers, the policy and
    its contract against the safety limits, the scene, the calibration files' hashes.

    ``operator``: an explicit :class:`Operator`; else ``opts.auto_confirm`` / ``opts.answers`` pick
    the scripted ones and the default is the terminal UI. ``log``: where notes and warnings go (None: nowhere).
    """
    # First of all, before anything is read or written: the session name becomes the directory
    # frames/<session> beside the database, which must stay inside frames/ (no symlink out of it);
    # and an existing database must pass SQLite's quick_check (a damaged one is never written to).
    # (SessionOptions already refused a bad name and --answers with --auto-confirm.)
    db, session = opts.db, opts.session
    session_dir = session_frames_dir(db, session, "--session")
    check_database(db)
    hardware, plan_path, policy_path = opts.hardware, opts.plan, opts.policy
    answers, registry, table_frame, threads = opts.answers, opts.registry, opts.table_frame, opts.threads
    log = log or (lambda _text: None)
    hw = load_hardware_config(hardware)
    plan = load_plan(plan_path)
    sim = hw.camera.type == "sim"
    if operator is None:
        if answers is not None:
            operator = ScriptedOperator.from_file(answers, log)
        elif opts.auto_confirm:
            operator = AutoOperator(log)
        else:
            operator = TerminalOperator()
    if hasattr(operator, "check_plan"):
        operator.check_plan(plan)
    if table_frame is not None:
        # Loaded and checked whatever the devices (a NaN, inf or absurd value: one line naming the
        # file and the field), never silently ignored.

        try:
            T_file = load_T_base_table(table_frame)
        except CalibrationFileError as err:
            raise SessionSetupError(f"--table-frame: {err}") from None
        if sim and not np.allclose(T_file, np.eye(4), rtol=0.0, atol=1e-9):
            raise SessionSetupError(
                f"--table-frame: {table_frame}: sim devices work in the sim world's frame, which is the table frame; "
                "a T_base_table other than the identity cannot apply to them: drop --table-frame"
            )
    if not sim and registry is None:
        raise SessionSetupError(
            "--registry: a real camera needs the tag registry (objects.yaml) for the placement check and the outcome"
        )
    policy = load_trial_policy(policy_path, threads)
    S = int(policy.image_size)
    if sim and hw.sim.image_size is None:
        sim_cfg = merged(
            hw.sim, {"image_size": (S, S)}, what="hardware config sim", source=str(policy_path), error=SessionSetupError
        )
        hw = merged(hw, {"sim": sim_cfg}, what="hardware config", error=SessionSetupError)
    spec = _scene_spec(plan, hw)
    scene_cameras = _check_cameras(policy, policy_path, hw, hardware, spec)
    if hw.arm.type == "sim":
        try:  # the sim arm is the scene's (robot_io.config): its joints are known before it exists
            check_joints(policy_contract(policy), spec, f"--policy: {policy_path}: ")
        except PolicyError as err:
            raise SessionSetupError(str(err)) from None
    ep = spec.episode
    action_scale = (ep.max_step_m,) * 3 + (ep.max_step_rad,) * 3
    hw = _safety_at_plan_rate(hw, plan, ep, log)
    inference_s = _check_policy_outputs(policy, spec, policy_path)
    _check_chunk_frame_age(policy, plan, hw, inference_s)
    rate_limit = opts.rate_limit
    if rate_limit is None:
        rate_limit = not (hw.arm.type == "sim" and not hw.arm.realtime)
    calibration_files = {
        "T_tcp_cam": hw.T_tcp_cam,
        "intrinsics": getattr(hw.camera, "intrinsics", None),
        "registry": registry,
        "table_frame": table_frame,
    }
    for name in scene_cameras:  # keys only for the fixed cameras read: a wrist-only session's stay as they were
        c = hw.scene_cameras[name]
        calibration_files[f"T_table_cam.{name}"] = c.T_table_cam
        calibration_files[f"intrinsics.{name}"] = getattr(c, "intrinsics", None)
    info = SessionInfo(
        name=session,
        plan_sha256=plan_sha256(plan_path),
        plan_text=plan_path.read_text(),
        hardware_text=hardware.read_text(),
        policy_path=str(policy_path),
        policy_sha256=file_sha256(policy_path) or "",
        software_version=importlib.metadata.version("advobj"),
        git_commit=git_commit(),
        devices=None,
        calibration={k: file_sha256(v) for k, v in calibration_files.items()},
        config={
            "hardware": str(hardware),
            "plan": str(plan_path),
            "policy": str(policy_path),
            "db": str(db),
            "registry": registry,
            "table_frame": table_frame,
            "rate_limit": rate_limit,
            "threads": threads,
            "image_size": S,
            "action_scale": list(action_scale),
            "seed": plan.seed,
            "calibration_files": {k: None if v is None else str(v) for k, v in calibration_files.items()},
            **({"cameras": list(policy_cameras(policy))} if scene_cameras else {}),
            **_joint_config(policy_contract(policy)),
        },
    )
    return PreparedSession(
        opts, hw, plan, policy, spec, session_dir, operator, rate_limit, info, action_scale, scene_cameras
    )


def run_prepared(
    prep: PreparedSession,
    *,
    on_trial_end: Callable | None = None,
    on_ready: Callable | None = None,
    log=print,
):
    """Connect the devices of a :func:`prepare_session` result and run (or resume) at most
    ``prep.opts.max_trials`` of its trials; returns the :class:`RunSummary`. A refused resume is
    found before any device connects.

    The session's lock and the arm's lock (:mod:`trials.real.locks`) are taken first and held
    until the devices are closed; ``opts.take_over_stale_lock``: take the session over from a holder
    the store names but that holds no OS lock, on another host too (``--take-over-stale-lock``).
    ``on_trial_end(trial)`` is called after each committed trial, ``on_ready(runner, world)`` before
    the first one (tests use it to reach the sim world and stage).
    """
    log = log or (lambda _text: None)
    hw, plan, sim, info, opts = prep.hw, prep.plan, prep.sim, prep.info, prep.opts
    with contextlib.ExitStack() as stack:  # closed in reverse: devices, world, stage, the locks, store, view
        view = None
        if opts.view:  # first: a port in use is one line naming --view-port, before anything is written
            view = stack.enter_context(LiveView((WRIST_CAMERA, *prep.scene_cameras), opts.view_port, info.name))
            log(f"live view: {view.url} (the cameras' latest frames with the plan's placement)")
        store = TrialStore(opts.db)
        stack.callback(store.close)
        # First of all: this process becomes the session's only runner and the arm's only driver
        # (issue 25). A second runner is refused here, in one line naming the holder, before any
        # device exists and before anything of the session is read, written or deleted.
        store.lock_session(info.name, opts.take_over_stale_lock, log)
        stack.callback(store.release_session, info.name)
        arm_held = arm_lock(hw.arm, session=info.name, db=str(opts.db.resolve()))
        if arm_held is not None:
            stack.callback(arm_held.release)
        world = build_world(hw) if hw.camera.type == "sim" or hw.arm.type == "sim" else None
        if world is not None:
            stack.callback(world.close)
        stages: list = []  # closed after the devices, before the world
        stack.callback(lambda: [st.close() for st in stages])
        if world is not None and plan.scene is not None:
            world.set_scene(prep.spec)
        camera, arm = build_camera(hw, world), build_arm(hw, world)
        fixed = {name: build_scene_camera(hw, name, world) for name in prep.scene_cameras}
        for warning in store.check_resume(info):  # a refused resume raises here, before any device connects
            log(warning)
        stored_T_base_table = store.stored_T_base_table(info.name)
        stack.enter_context(camera)
        stack.enter_context(arm)
        for cam in fixed.values():
            stack.enter_context(cam)
            cam.read()  # a frame of another size than its calibration: one line naming it, nothing recorded
        write_run_info(prep.session_dir, info.config, plan.seed)
        # Identities after connecting: drivers read serial numbers from the devices.
        devices = {"camera": device_identity(camera), "arm": device_identity(arm)}
        if fixed:  # only then: a wrist-only session's device record stays as it was
            devices["scene_cameras"] = {name: device_identity(cam) for name, cam in fixed.items()}
        info = dataclasses.replace(info, devices=devices)
        if not sim:
            for warning in camera_view_warnings(camera, prep.policy, prep.spec, hw):
                log(f"warning: {warning}")
        for name, cam in fixed.items():
            if hw.scene_cameras[name].type != "sim":
                for warning in scene_camera_warnings(name, cam, prep.policy, prep.spec, hw):
                    log(f"warning: {warning}")
        for warning in store.device_changes(info):
            log(warning)
        T_base_table, stage = np.eye(4), None
        if sim:
            locator = SimLocator(world)
            sim_fixed = [name for name in fixed if hw.scene_cameras[name].type == "sim"]
            stage = SimStage(world, plan, opts.plan.parent, cameras=sim_fixed)
            stages.append(stage)
            if hw.camera.tags:
                locator = _sim_tag_locator(camera, world, opts.registry, prep.session_dir, log)
        else:
            locator, T_base_table = _tag_locator(
                hw, camera, arm, opts.registry, opts.table_frame, stored_T_base_table, log
            )
        info = dataclasses.replace(info, T_base_table=T_base_table)
        if view is not None:
            view.set_overlay(PlacementOverlay(plan, prep.spec, view_cameras(hw, prep.spec, camera, fixed)))
        runner = TrialRunner(
            plan,
            camera,
            arm,
            prep.policy,
            store,
            prep.operator,
            locator,
            info,
            list(prep.action_scale),
            stage=stage,
            T_base_table=T_base_table,
            rate_limit=prep.rate_limit,
            on_trial_end=on_trial_end,
            gripper_m=prep.spec.gripper.opening_m,
            scene_cameras=fixed,
            view=view,
        )
        if on_ready is not None:
            on_ready(runner, world)
        return runner.run(opts.max_trials)


def run_session(
    opts: SessionOptions,
    *,
    operator=None,
    on_trial_end: Callable | None = None,
    on_ready: Callable | None = None,
    log=print,
):
    """Run (or resume) the session ``opts`` describes: :func:`prepare_session`, then
    :func:`run_prepared`; returns the :class:`RunSummary`.

    ``operator``: an explicit :class:`Operator`; else ``opts.auto_confirm`` / ``opts.answers`` pick
    the scripted ones and the default is the terminal UI. ``opts.rate_limit`` None: on for real arms
    and for sim arms with ``realtime: true``, off for other sim arms. ``on_trial_end`` and
    ``on_ready``: see :func:`run_prepared`.
    """
    prep = prepare_session(opts, operator=operator, log=log)
    return run_prepared(prep, on_trial_end=on_trial_end, on_ready=on_ready, log=log)


def camera_view_warnings(camera, policy, spec, hw) -> list[str]:
    """How the real camera, as the policy sees it through its card's ``preprocess``, differs from
    the camera the policy was trained with (the scene's): field of view, pixel aspect, mount."""
    try:
        intr = camera.intrinsics
    except MissingIntrinsicsError:
        return ["camera: no intrinsics, so its field of view cannot be compared with the policy's training camera"]
    S = int(policy.image_size)
    mode = policy_preprocess(policy)
    K_view = policy_view_K(intr.K, intr.width, intr.height, S, mode)
    T_mount = spec.camera.T_tcp_cam if hw.T_tcp_cam is None else load_T_tcp_cam(hw.T_tcp_cam)
    return [
        f"camera ({intr.width}x{intr.height}, preprocess {mode} to {S}x{S}): {m}"
        for m in view_mismatch(K_view, spec.camera.K(S, S), S, T_mount, spec.camera.T_tcp_cam)
    ]


def _check_cameras(policy, policy_path, hw, hardware, spec) -> tuple[str, ...]:
    """The fixed cameras ``policy`` reads (the wrist camera aside), each checked against the cell
    (``hw``, read from ``hardware``) and the scene, before anything is written or any device opens:
    one :class:`SessionSetupError` line for a camera the cell lacks, a sim camera its scene lacks
    or rendering another size than the policy's input, a real camera's missing or bad pose file,
    or frames of a size that cannot become a non-square input."""
    fixed = tuple(c for c in policy_cameras(policy) if c != WRIST_CAMERA)
    for name in fixed:
        if name not in hw.scene_cameras:
            have = ", ".join([WRIST_CAMERA, *hw.scene_cameras])
            raise SessionSetupError(
                f"--policy: {policy_path} reads camera {name!r}, which the hardware config {hardware} does not have "
                f"(its cameras: {have}); add it under scene_cameras"
            )
        c = hw.scene_cameras[name]
        (h, w), _ = camera_input(policy, name)
        if c.type == "sim":
            try:
                cam = spec.camera_spec(name)
            except UnknownCameraError as err:
                raise SessionSetupError(
                    f"--hardware: {hardware}: scene_cameras.{name} renders the sim scene's camera {name!r}: {err}"
                ) from None
            size, source = (cam.width, cam.height), f"the sim scene renders camera {name!r} at"
        else:
            try:
                pose = load_scene_camera_pose(c.T_table_cam)
            except CalibrationFileError as err:
                raise SessionSetupError(f"--hardware: scene_cameras.{name}.T_table_cam: {err}") from None
            size, source = (pose.width, pose.height), f"camera {name!r} delivers (its pose file's size)"
        if size != (w, h) and (c.type == "sim" or h != w):
            fix = (
                "give the scene camera that size"
                if c.type == "sim"
                else "set the camera to that size and calibrate it there"
            )
            raise SessionSetupError(
                f"--policy: {policy_path} takes {h}x{w} px images of camera {name!r}, but {source} "
                f"{size[1]}x{size[0]} px: {fix}"
            )
    return fixed


def scene_camera_warnings(name: str, camera, policy, spec, hw) -> list[str]:
    """How fixed camera ``name`` of the cell, as the policy sees it, differs from the scene's camera of
    that name the policy was trained with: field of view, pixel aspect, principal point (at the
    input's size) and where it stands (its calibrated ``T_table_cam`` against the scene's pose)."""
    try:
        trained = spec.camera_spec(name)
    except UnknownCameraError:
        return [f"camera {name!r}: the scene has no camera of that name, so its view cannot be compared"]
    (h, w), mode = camera_input(policy, name)
    out = []
    try:
        intr = camera.intrinsics
    except MissingIntrinsicsError:
        out.append(f"camera {name!r}: no intrinsics, so its field of view cannot be compared with the scene's")
    else:
        if h == w:
            K_view = policy_view_K(intr.K, intr.width, intr.height, h, mode)
            same = np.eye(4)  # where it stands is compared below, in the table frame
            out += [
                f"camera {name!r} ({intr.width}x{intr.height}, preprocess {mode} to {h}x{w}): {m}"
                for m in view_mismatch(K_view, trained.K(w, h), h, same, same)
            ]
    T, U = scene_camera_pose(hw, name), trained.T_table_cam
    dt = float(np.linalg.norm(T[:3, 3] - U[:3, 3]))
    da = float(np.degrees(rotation_angle(T[:3, :3], U[:3, :3])))
    if dt > SCENE_CAMERA_TOL_M or da > SCENE_CAMERA_TOL_DEG:
        out.append(
            f"camera {name!r} stands {100 * dt:.1f} cm and {da:.1f} deg from the scene's camera of that name "
            f"(tolerance {100 * SCENE_CAMERA_TOL_M:g} cm, {SCENE_CAMERA_TOL_DEG:g} deg): the policy sees the table "
            "from elsewhere than in training"
        )
    return out


SCENE_CAMERA_TOL_M, SCENE_CAMERA_TOL_DEG = 0.02, 5.0  # as the wrist camera's mount (sim.policyview.view_mismatch)


def _check_policy_outputs(policy, spec, policy_path) -> float:
    """Ask the policy twice, on a grey frame from the start of a reach, before any device exists: an
    output its contract cannot read (shape, a missing state input) or a runtime error of the model
    fails the session here, in one line, instead of in the middle of the first trial. Returns the
    second (warm) call's time in seconds, the inference latency a chunk's frame age includes."""
    c = policy_contract(policy)
    T = np.eye(4)
    T[2, 3] = 0.3
    image = {cam: np.full((1, *camera_input(policy, cam)[0], 3), 128, np.uint8) for cam in policy_cameras(policy)}
    q = np.zeros((1, len(c.joints))) if "joint_positions" in c.state else None  # joints at 0: a test input
    state = state_vector(c, T[None], spec.gripper.opening_m, q)
    elapsed = 0.0
    for _ in range(2):
        t0 = time.perf_counter()
        try:
            raw = call_policy(policy, image, state)
            decode_actions(np.asarray(raw, dtype=np.float64), c, 1)
        except Exception as err:  # any model: onnxruntime and torch raise their own types
            raise SessionSetupError(
                f"{policy_path}: the policy fails on a test frame: {' '.join(str(err).split())}"
            ) from None
        elapsed = time.perf_counter() - t0
    return elapsed


def _joint_config(contract) -> dict:
    """The session config's record of a joint-space policy's joints (names and units, the order of
    its actions and of every step's joints); empty for a TCP policy, whose config stays as it was."""
    if not contract.is_joint_space:
        return {}
    return {"joints": list(contract.joints), "joint_units": list(contract.joint_units)}


def _check_chunk_frame_age(policy, plan, hw, inference_s: float = 0.0) -> None:
    """Refuse a policy whose chunks outlive the safety layer's frame-age limit: the k-th action of
    a chunk is sent (k - 1) control periods, plus the policy's inference time, after the frame it
    was computed from."""
    c = policy_contract(policy)
    k = c.action.execute
    age_ms = (k - 1) * 1000.0 / float(plan.control_hz) + 1000.0 * float(inference_s)
    limit = float(hw.safety.max_frame_age_ms)
    if k > 1 and age_ms >= limit:
        raise SessionSetupError(
            f"safety.max_frame_age_ms: the policy executes {k} actions per frame at {plan.control_hz:g} Hz, so its "
            f"last action is sent {age_ms:.0f} ms after its frame (inference {1000 * inference_s:.0f} ms included), "
            f"beyond the {limit:.0f} ms limit; raise max_frame_age_ms above {age_ms:.0f} ms in the hardware config or "
            "export the policy with a smaller execute"
        )


def _safety_at_plan_rate(hw, plan, episode, log):
    """``hw`` with the safety layer's ``control_period_s`` set to the plan's loop period.

    The speed caps assume the period the loop really runs at (``1 / plan.control_hz``), not the
    hardware YAML's nominal one. Logs when the caps at that rate are smaller than the policy's own
    step (the scene's ``max_step_m`` / ``max_step_rad``): every step is then clipped, the arm moves
    slower than the policy did in simulation, and trials may end at ``max_steps`` short of any object.
    """
    period_s = 1.0 / float(plan.control_hz)
    lim = hw.safety
    if not math.isclose(lim.control_period_s, period_s, rel_tol=1e-6):
        log(
            f"safety: control_period_s {lim.control_period_s * 1000:.1f} ms (hardware YAML) -> "
            f"{period_s * 1000:.1f} ms, "
            f"the plan's control_hz {plan.control_hz:g}: the speed caps assume the loop's real period"
        )
        # validated again: the plan's rate must give a period the safety limits accept
        lim = merged(
            lim, {"control_period_s": period_s}, what="safety limits at the plan's control_hz", error=SessionSetupError
        )
        hw = merged(hw, {"safety": lim}, what="hardware config", error=SessionSetupError)
    cap_m, cap_rad = lim.step_caps()
    if cap_m < episode.max_step_m * (1 - 1e-9) or cap_rad < episode.max_step_rad * (1 - 1e-9):
        log(
            f"warning: at {plan.control_hz:g} Hz the safety layer caps a step at {cap_m * 1000:.1f} mm / "
            f"{math.degrees(cap_rad):.1f} deg, below the policy's {episode.max_step_m * 1000:.1f} mm / "
            f"{math.degrees(episode.max_step_rad):.1f} deg: steps are clipped, the arm moves slower than in "
            "simulation and "
            "trials may end at max_steps; lower the plan's control_hz or raise max_speed_mps / max_speed_radps / "
            "max_step_m / max_step_rad in the hardware YAML"
        )
    return hw


def _sim_tag_locator(camera, world, registry, session_dir, log):
    """Tags drawn by the sim camera, located by the real pipeline (detector, bundles, the chain).

    The registry is ``--registry`` or, without one, :func:`robot_io.cameras.sim.sim_registry`
    (written into the session folder). The sim world frame is the table frame, so ``T_base_table``
    is the identity and the chain uses the sim camera's own mount.
    """
    if registry is not None:
        reg = load_registry(registry)
        camera.tags = sim_tags(reg)
        return TagLocator(reg, camera.intrinsics, camera.T_tcp_cam, np.eye(4))
    log(f"sim tags: no --registry; each staged object is tagged on its faces (sim_registry), saved under {session_dir}")
    return _SimTaggedLocator(
        camera, world, Path(session_dir), TagLocator(None, camera.intrinsics, camera.T_tcp_cam, np.eye(4))
    )


class _SimTaggedLocator:
    """A :class:`TagLocator` whose registry follows the staged scene: each condition's adversarial
    object (a cube, a patch...) is a physical object of its own, tagged on its own faces, as a
    person would tag each object of a real cell."""

    source = "tags"

    def __init__(self, camera, world, folder: Path, locator):
        self.camera, self.world, self.folder, self.inner = camera, world, folder, locator
        self._spec = None

    def locate(self, frame, T_base_tcp):
        if self._spec is not self.world.spec:  # staged a new scene: tag its objects (the frame shows the old tags)
            self._spec = self.world.spec
            reg = sim_registry(self.world)

            adv = self.world.spec.adversarial
            # A file name from the mesh's name and a digest of its source and scale: never a path.
            tag = hashlib.sha256(f"{adv.mesh}|{adv.scale}".encode()).hexdigest()[:8]
            stem = "".join(c if c.isalnum() or c in "-_" else "_" for c in Path(str(adv.mesh)).stem)[:40] or "mesh"
            save_registry(self.folder / f"sim_registry_{stem}_{tag}.yaml", reg)
            self.camera.tags = sim_tags(reg)
            self.inner.registry = reg
            frame = self.camera.read()
        return self.inner.locate(frame, T_base_tcp)

    @property
    def registry(self):
        return self.inner.registry


def _tag_locator(hw, camera, arm, registry, table_frame, stored_T_base_table=None, log=print):
    """The tag locator and ``T_base_table``: from ``table_frame``, else the session's stored one, else estimated."""
    if hw.T_tcp_cam is None:
        raise SessionSetupError("T_tcp_cam: the hardware config must name the hand-eye result for tag-based locating")
    reg = load_registry(registry)
    T_tcp_cam = load_T_tcp_cam(hw.T_tcp_cam)
    if table_frame is not None:
        T_base_table = load_T_base_table(table_frame)
    elif stored_T_base_table is not None:
        # the resume check guarantees the session had no --table-frame either: this is its estimate
        T_base_table = np.asarray(stored_T_base_table, dtype=np.float64)
        log("table frame: the one estimated at the session's start (stored with the session), not re-estimated")
    else:
        probe = TagLocator(reg, camera.intrinsics, T_tcp_cam, np.eye(4))
        T_base_table = TagLocator.estimate_T_base_table(probe.observe(camera.read()), arm.tcp_pose(), T_tcp_cam)
        if T_base_table is None:
            raise SessionSetupError(
                "--table-frame: not given, and no 'table' tag of the registry is visible from the arm's "
                "current pose; give the table frame YAML or move the arm so a table tag is in view"
            )
        log("table frame: estimated from the registry's table tags; stored with the session and reused on resume")
    return TagLocator(reg, camera.intrinsics, T_tcp_cam, T_base_table), T_base_table
