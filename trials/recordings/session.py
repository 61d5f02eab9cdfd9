"""This project's trial sessions, read as recordings: frames, TCP poses and the cell's calibration.

Everything comes through the session store (:class:`trials.real.store.TrialStore`): the session's
recorded hardware YAML and plan, its table frame, its committed trials in plan order and their
steps. Each trial with at least one step is an episode (its id is the trial id). Its cameras are
the ones the session's policy read: ``wrist`` (the session's camera, on the TCP) and each fixed
scene camera whose frames the steps reference (``step_XXX_<camera>.png``).

What the runner recorded, step by step (``trials.real.runner``): the frames the policy acted on
(``frames/<session>/<trial>/`` beside the database, each camera's full image) and when each was
taken, then the pose measured after the step's command. The pose at which the frames of step k
were taken is therefore the one measured after step k-1, which is also the pose the policy was
given with them; for step 0 it is the trial's start pose, the target of the positioning move
before the policy loop (``T_base_table @ T_table_tcp`` of the plan; a start given as joints: their
TCP by the session arm's forward kinematics, as the runner took it, :func:`start_poses`). A pose's time is when its
command was accepted (0 for the start pose), and a frame must lie within one control period of
the plan (``1 / control_hz``) of it, unless ``--tolerance-s`` says otherwise.

The cell's calibration is the session's: the intrinsics files, the hand-eye result and the fixed
cameras' pose files its hardware YAML named (paths resolved as ``advobj trial run`` resolved
them, beside that YAML), checked against the sha256 the session recorded, so the recording
carries the calibration the trials were run with. ``--intrinsics CAMERA=FILE`` /
``--extrinsics CAMERA=FILE`` name the files when they have moved (a file other than the recorded
one is refused). A sim camera's intrinsics are its scene camera's at the frames' size, and it
stands where the scene puts it (the wrist camera: unless the hardware YAML named a ``T_tcp_cam``;
a fixed one: unless it named a pose file). The table frame is the one stored with the session
(``--table-frame`` for a session that has none).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
import yaml
from PIL import Image
from pydantic import ValidationError

from robot_io.config import build_scene_arm, hardware_config_from_dict
from sim.errors import format_validation_error
from sim.geometry import invert_T, make_T, so3_exp
from sim.paths import UnsafePathError, safe_join
from sim.recording import MAX_SYNC_TOLERANCE_S, RecordedStep, RecordingCamera
from sim.spec import WRIST, load_spec
from trials.real.plan import TrialPlan
from trials.real.runner import StartError, resolve_starts
from trials.real.session import file_sha256
from trials.real.store import TrialStore, check_database
from trials.recordings.calib import (
    RecordImportError,
    camera_extrinsics,
    camera_intrinsics,
    check_cameras_named,
    table_frame,
    wrist_T_tcp_cam,
)

__all__ = ["session_recording", "start_poses"]

_MEAS = ("meas_base_x_m", "meas_base_y_m", "meas_base_z_m", "meas_base_rx_rad", "meas_base_ry_rad", "meas_base_rz_rad")


def _pose(row: dict) -> np.ndarray:
    v = np.asarray([row[c] for c in _MEAS], dtype=np.float64)
    return make_T(so3_exp(v[3:]), v[:3])


@dataclass(frozen=True)
class _Started:
    """A stored trial as :func:`trials.real.runner.resolve_starts` reads one."""

    trial_id: str
    tcp_pose: int


def start_poses(plan, trials, T_base_table, kinematics, arm: str) -> dict[str, np.ndarray]:
    """``{trial id: T_base_tcp (4, 4)}``: where each of ``trials`` (stored rows: ``trial_id``,
    ``tcp_pose``) started, as the runner took it (:func:`trials.real.runner.resolve_starts`): a TCP
    start is ``T_base_table @ T_table_tcp``; a start given as joints is their forward kinematics on
    ``kinematics`` (the session arm's :class:`sim.ik.SceneArm`, TCP in its base frame).

    Without ``kinematics`` a start given both ways is taken at its TCP pose (the runner held its
    joints' TCP within ``START_AGREE_TOL_M`` of it), and a joints-only start is a
    :class:`RecordImportError` in one line naming the trial and ``arm`` (what the session's arm is).
    """
    rows = [_Started(t["trial_id"], int(t["tcp_pose"])) for t in trials]
    if kinematics is None:
        for r in rows:
            tp = plan.tcp_pose(r.tcp_pose)
            if tp.T_table_tcp is None:
                raise RecordImportError(
                    f"trial {r.trial_id}: its start (tcp_poses.{r.tcp_pose}) is given as joint_positions only, and "
                    f"{arm} has no kinematics to place their TCP"
                )
        return {r.trial_id: np.asarray(T_base_table) @ plan.tcp_pose(r.tcp_pose).T_table_tcp.T() for r in rows}
    try:
        starts = resolve_starts(plan, rows, T_base_table, kinematics, joint_space=False)
    except StartError as err:
        raise RecordImportError(str(err)) from None
    return {r.trial_id: starts[r.tcp_pose].T_base_tcp for r in rows}


def _frame_path(db: Path, ref: str, trial: str) -> Path:
    try:
        return safe_join(db.resolve().parent, *ref.split("/"), what=f"trial {trial}'s frame")
    except UnsafePathError as err:
        raise RecordImportError(str(err)) from None


def _frame(path: Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """A stored frame as (H, W, 3) uint8 (``size``: the (width, height) it must have)."""
    if not path.is_file():
        raise RecordImportError(f"{path}: a frame of the session is missing")
    try:
        with Image.open(path) as im:
            if size is not None and im.size != size:
                w, h = im.size
                raise RecordImportError(f"{path}: {w}x{h} px, the session's frames are {size[0]}x{size[1]}")
            return np.asarray(im.convert("RGB"), dtype=np.uint8)
    except (OSError, ValueError, Image.DecompressionBombError) as err:
        raise RecordImportError(f"{path}: not a readable frame ({' '.join(str(err).split())})") from None


def _recorded_file(flag: str, camera: str, given, configured, sha: str | None, what: str) -> Path | None:
    """The calibration file of ``camera`` to read: the flag's, else the one the session's hardware
    YAML named; refused when it is gone or is not the file the session recorded (sha256)."""
    path = given if given is not None else configured
    if path is None:
        return None
    if not Path(path).is_file():
        raise RecordImportError(
            f"{flag}: the session's {what} file {path} is not there any more (paths resolve as when the session ran); "
            f"give {flag} {camera}=FILE"
        )
    if sha is not None and file_sha256(path) != sha:
        raise RecordImportError(
            f"{flag} {camera}={path}: not the {what} file the session was recorded with (sha256 "
            f"{file_sha256(path)[:12]}..., the session's {sha[:12]}...)"
        )
    return Path(path)


def _frames_of(step: dict, camera: str) -> tuple[str, float]:
    """``(frame_ref, t_frame_s)`` of ``camera``'s frame in a stored step."""
    if camera == WRIST:
        return step["frame_ref"], float(step["t_frame_s"])
    f = step["camera_frames"][camera]
    return f["frame_ref"], float(f["t_frame_s"])


def _episode(
    store: TrialStore, db: Path, session: str, trial: dict, T_base_tcp0, sizes: dict
) -> Iterator[RecordedStep]:
    steps = store.steps(session, trial["trial_id"])
    for k, s in enumerate(steps):
        prev = steps[k - 1] if k else None
        missing = [c for c in sizes if c != WRIST and c not in s["camera_frames"]]
        if missing:
            raise RecordImportError(
                f"session {session!r}: trial {trial['trial_id']} step {k}: no frame of {missing[0]}"
            )
        images, times = {}, {}
        for cam, size in sizes.items():
            ref, times[cam] = _frames_of(s, cam)
            images[cam] = _frame(_frame_path(db, ref, trial["trial_id"]), size)
        yield RecordedStep(
            0.0 if prev is None else float(prev["t_command_s"]),
            images,
            T_base_tcp0 if prev is None else _pose(prev),
            None,
            times,
        )


def session_recording(
    db: Path,
    session: str | None,
    intrinsics: dict,
    extrinsics: dict,
    table_frame_path: Path | None,
    tolerance_s: float | None,
    log: Callable[[str], None],
) -> tuple[dict, TrialStore]:
    """The :func:`sim.recording.write_recording` arguments for session ``session`` of the trial
    database ``db`` (None: its only session), and the open store its episodes read from (the
    caller closes it). Every input is checked before this returns; the frames are read as the
    episodes are written."""
    if not db.is_file():
        raise RecordImportError(f"SRC: {db}: no trial database here (--from session reads a trials.sqlite)")
    check_database(db)
    store = TrialStore(db, create=False)
    try:
        return _read(store, db, session, intrinsics, extrinsics, table_frame_path, tolerance_s, log), store
    except BaseException:
        store.close()
        raise


def _camera(name, hw, spec, recorded, size, intrinsics, extrinsics, where) -> RecordingCamera:
    """Camera ``name`` of the session's cell, calibrated as the session ran it (see the module's docstring)."""
    c = hw.camera if name == WRIST else hw.scene_cameras.get(name)
    if c is None:
        raise RecordImportError(f"{where}: its frames of camera {name!r} come from no camera of its hardware YAML")
    key = "" if name == WRIST else f".{name}"
    sim = c.type == "sim"
    path = _recorded_file(
        "--intrinsics", name, intrinsics.get(name), getattr(c, "intrinsics", None), recorded.get(f"intrinsics{key}"),
        "intrinsics",
    )  # fmt: skip
    if path is not None:
        K, dist = camera_intrinsics(path, name, size)
    elif sim:
        K, dist = (spec.camera if name == WRIST else spec.camera_spec(name)).K(*size), np.zeros(5)
    else:
        raise RecordImportError(
            f"--intrinsics: camera {name} of {where} ({c.type}) named no intrinsics file (its device's own "
            f"calibration was used and not recorded); give --intrinsics {name}=FILE"
        )
    if name == WRIST:
        path = _recorded_file(
            "--extrinsics", name, extrinsics.get(name), hw.T_tcp_cam, recorded.get("T_tcp_cam"), "hand-eye"
        )
        if path is not None:
            T = wrist_T_tcp_cam(path, name, "--extrinsics")
        elif sim:
            T = spec.camera.T_tcp_cam
        else:
            raise RecordImportError(
                f"--extrinsics: the hardware YAML of {where} named no T_tcp_cam (hand-eye result); give --extrinsics "
                f"{name}=FILE"
            )
        return RecordingCamera(name, K, dist, size[0], size[1], "tcp", T)
    path = _recorded_file(
        "--extrinsics", name, extrinsics.get(name), c.T_table_cam, recorded.get(f"T_table_cam.{name}"), "pose"
    )
    if path is not None:
        mount, T = camera_extrinsics(path, name)
        if mount != "table":
            raise RecordImportError(
                f"--extrinsics {name}={path}: camera {name} of the session is fixed; expected T_table_cam"
            )
    elif sim:
        T = spec.camera_spec(name).T_table_cam
    else:
        raise RecordImportError(
            f"--extrinsics: camera {name} of {where} has no pose file; give --extrinsics {name}=FILE"
        )
    return RecordingCamera(name, K, dist, size[0], size[1], "table", None, T)


def _read(store, db, session, intrinsics, extrinsics, table_frame_path, tolerance_s, log) -> dict:
    names = store.session_names()
    if session is None:
        if len(names) != 1:
            raise RecordImportError(
                f"--session: {db} holds {len(names)} sessions ({', '.join(names[:8]) or 'none'}); name one"
            )
        session = names[0]
    row = store.session(session)
    if row is None:
        raise RecordImportError(f"--session: no session {session!r} in {db} (it has {', '.join(names) or 'none'})")
    config = json.loads(row["config_json"])
    recorded = json.loads(row["calibration_json"])
    where = f"session {session!r} in {db}"
    try:
        plan = TrialPlan.model_validate(yaml.safe_load(row["plan_text"]))
        hardware_yaml = Path(config.get("hardware") or ".")
        hw = hardware_config_from_dict(
            yaml.safe_load(row["hardware_text"]), source=f"{where}: hardware YAML", base=hardware_yaml.resolve().parent
        )
    except ValidationError as err:
        raise RecordImportError(format_validation_error(err, "trial plan", f"{where}: plan")) from None
    except yaml.YAMLError as err:
        raise RecordImportError(f"{where}: its stored plan or hardware YAML does not parse ({err})") from None
    trials = [t for t in store.trial_rows([session]) if t["n_steps"] > 0]
    if not trials:
        raise RecordImportError(f"--session: {where} has no committed trial with a frame")
    first = store.steps(session, trials[0]["trial_id"])[0]
    cameras = [WRIST, *sorted(first["camera_frames"])]  # the cameras the session's policy read
    check_cameras_named(intrinsics, cameras, "--intrinsics")
    check_cameras_named(extrinsics, cameras, "--extrinsics")
    sizes = {}
    for cam in cameras:
        h, w = _frame(_frame_path(db, _frames_of(first, cam)[0], trials[0]["trial_id"])).shape[:2]
        sizes[cam] = (w, h)
    sim = hw.camera.type == "sim" or any(c.type == "sim" for c in hw.scene_cameras.values())
    sim_arm = hw.arm.type == "sim"
    spec = load_spec(plan.scene if plan.scene is not None else hw.sim.scene) if sim or sim_arm else None
    cams = [_camera(c, hw, spec, recorded, sizes[c], intrinsics, extrinsics, where) for c in cameras]
    if table_frame_path is not None:
        T_table_base = table_frame(table_frame_path)
    else:
        T_base_table = store.stored_T_base_table(session)
        if T_base_table is None:
            raise RecordImportError(f"--table-frame: {where} stored no table frame; give the YAML with T_base_table")
        T_table_base = invert_T(T_base_table)
    T_base_table = invert_T(T_table_base)
    tolerance = 1.0 / float(plan.control_hz) if tolerance_s is None else float(tolerance_s)
    log(
        f"session {session!r} of {db}: {len(trials)} trials with frames, cameras "
        + ", ".join(f"{c} {w}x{h} px" for c, (w, h) in sizes.items())
    )
    if sim_arm:  # the scene's arm, where the scene places it (robot_io.config builds the sim arm so)
        kinematics = None if spec.arm is None else spec.arm.scene_arm()
        arm = f"the session's sim arm (its scene {spec.name!r} has no arm)"
    else:
        kinematics = build_scene_arm(hw)
        arm = f"the session's {hw.arm.type} arm (its hardware YAML gives no arm kinematics)"
    try:
        starts = start_poses(plan, trials, T_base_table, kinematics, arm)
    except RecordImportError as err:
        raise RecordImportError(f"{where}: {err}") from None
    episodes = ((t["trial_id"], _episode(store, db, session, t, starts[t["trial_id"]], sizes)) for t in trials)
    return dict(
        cameras=cams,
        episodes=episodes,
        T_table_base=T_table_base,
        sync_tolerance_s=min(tolerance, MAX_SYNC_TOLERANCE_S),
        gripper=None,
        source={
            "kind": "session",
            "database": str(db),
            "session": session,
            "plan_sha256": row["plan_sha256"],
            "policy_sha256": row["policy_sha256"],
            "camera": hw.camera.type,
        },
    )
