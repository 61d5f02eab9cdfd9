"""This project's trial sessions, read as recordings: frames, TCP poses and the cell's calibration.

Everything comes through the session store (:class:`trials.real.store.TrialStore`): the session's
recorded hardware YAML and plan, its table frame, its committed trials in plan order and their
steps. Each trial with at least one step is an episode (its id is the trial id), with one camera,
``wrist`` (the session's camera, on the TCP).

What the runner recorded, step by step (``trials.real.runner``): the frame the policy acted on
(``frames/<session>/<trial>/step_XXX.png`` beside the database, the camera's full image) and when
it was taken, then the pose measured after the step's command. The pose at which frame k was
taken is therefore the one measured after step k-1, which is also the pose the policy was given
with that frame; for frame 0 it is the trial's start pose, the target of the positioning move
before the policy loop (``T_base_table @ T_table_tcp`` of the plan). A pose's time is when its
command was accepted (0 for the start pose), and a frame must lie within one control period of
the plan (``1 / control_hz``) of it, unless ``--tolerance-s`` says otherwise.

The cell's calibration is the session's: the intrinsics file and hand-eye result its hardware
YAML named (paths resolved as ``advobj trial run`` resolved them, beside that YAML), checked
against the sha256 the session recorded, so the recording carries the calibration the trials
were run with. ``--intrinsics wrist=FILE`` / ``--extrinsics wrist=FILE`` name the files when
they have moved (a file other than the recorded one is refused). A sim camera's intrinsics are
its scene camera's at the frames' size, its mount the scene's unless the hardware YAML named a
``T_tcp_cam``. The table frame is the one stored with the session (``--table-frame`` for a
session that has none).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
import yaml
from PIL import Image
from pydantic import ValidationError

from robot_io.config import hardware_config_from_dict
from sim.errors import format_validation_error
from sim.geometry import invert_T, make_T, so3_exp
from sim.paths import UnsafePathError, safe_join
from sim.recording import MAX_SYNC_TOLERANCE_S, RecordedStep, RecordingCamera
from sim.spec import WRIST, load_spec
from trials.real.plan import TrialPlan
from trials.real.session import file_sha256
from trials.real.store import TrialStore, check_database
from trials.recordings.calib import (
    RecordImportError,
    camera_intrinsics,
    check_cameras_named,
    table_frame,
    wrist_T_tcp_cam,
)

__all__ = ["session_recording"]

_MEAS = ("meas_base_x_m", "meas_base_y_m", "meas_base_z_m", "meas_base_rx_rad", "meas_base_ry_rad", "meas_base_rz_rad")


def _pose(row: dict) -> np.ndarray:
    v = np.asarray([row[c] for c in _MEAS], dtype=np.float64)
    return make_T(so3_exp(v[3:]), v[:3])


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


def _recorded_file(flag: str, given: Path | None, configured: Path | None, sha: str | None, what: str) -> Path | None:
    """The calibration file to read: the flag's, else the one the session's hardware YAML named;
    refused when it is not the file the session recorded (sha256), or is gone."""
    path = given if given is not None else configured
    if path is None:
        return None
    if not Path(path).is_file():
        raise RecordImportError(
            f"{flag}: the session's {what} file {path} is not there any more (paths resolve as when the session ran); "
            f"give {flag} {WRIST}=FILE"
        )
    if sha is not None and file_sha256(path) != sha:
        raise RecordImportError(
            f"{flag} {WRIST}={path}: not the {what} file the session was recorded with (sha256 "
            f"{file_sha256(path)[:12]}..., the session's {sha[:12]}...)"
        )
    return Path(path)


def _episode(store: TrialStore, db: Path, session: str, trial: dict, T_base_tcp0, size) -> Iterator[RecordedStep]:
    steps = store.steps(session, trial["trial_id"])
    for k, s in enumerate(steps):
        prev = steps[k - 1] if k else None
        yield RecordedStep(
            0.0 if prev is None else float(prev["t_command_s"]),
            {WRIST: _frame(_frame_path(db, s["frame_ref"], trial["trial_id"]), size)},
            T_base_tcp0 if prev is None else _pose(prev),
            None,
            {WRIST: float(s["t_frame_s"])},
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
    check_cameras_named(intrinsics, [WRIST], "--intrinsics")
    check_cameras_named(extrinsics, [WRIST], "--extrinsics")
    if not db.is_file():
        raise RecordImportError(f"SRC: {db}: no trial database here (--from session reads a trials.sqlite)")
    check_database(db)
    store = TrialStore(db, create=False)
    try:
        return _read(store, db, session, intrinsics, extrinsics, table_frame_path, tolerance_s, log), store
    except BaseException:
        store.close()
        raise


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
    h, w = _frame(_frame_path(db, first["frame_ref"], trials[0]["trial_id"])).shape[:2]
    size = (w, h)
    sim = hw.camera.type == "sim"

    spec = load_spec(plan.scene if plan.scene is not None else hw.sim.scene) if sim else None
    configured = getattr(hw.camera, "intrinsics", None)
    path = _recorded_file("--intrinsics", intrinsics.get(WRIST), configured, recorded.get("intrinsics"), "intrinsics")
    if path is not None:
        K, dist = camera_intrinsics(path, WRIST, size)
    elif sim:
        K, dist = spec.camera.K(*size), np.zeros(5)
    else:
        raise RecordImportError(
            f"--intrinsics: the camera of {where} ({hw.camera.type}) named no intrinsics file (its device's own "
            f"calibration was used and not recorded); give --intrinsics {WRIST}=FILE"
        )
    path = _recorded_file("--extrinsics", extrinsics.get(WRIST), hw.T_tcp_cam, recorded.get("T_tcp_cam"), "hand-eye")
    if path is not None:
        T_tcp_cam = wrist_T_tcp_cam(path, WRIST, "--extrinsics")
    elif sim:
        T_tcp_cam = spec.camera.T_tcp_cam
    else:
        raise RecordImportError(
            f"--extrinsics: the hardware YAML of {where} named no T_tcp_cam (hand-eye result); give --extrinsics "
            f"{WRIST}=FILE"
        )
    if table_frame_path is not None:
        T_table_base = table_frame(table_frame_path)
    else:
        T_base_table = store.stored_T_base_table(session)
        if T_base_table is None:
            raise RecordImportError(f"--table-frame: {where} stored no table frame; give the YAML with T_base_table")
        T_table_base = invert_T(T_base_table)
    T_base_table = invert_T(T_table_base)
    camera = RecordingCamera(WRIST, K, dist, size[0], size[1], "tcp", T_tcp_cam)
    tolerance = 1.0 / float(plan.control_hz) if tolerance_s is None else float(tolerance_s)
    log(f"session {session!r} of {db}: {len(trials)} trials with frames, camera {WRIST} {size[0]}x{size[1]} px")

    episodes = (
        (
            t["trial_id"],
            _episode(store, db, session, t, T_base_table @ plan.tcp_pose(t["tcp_pose"]).T_table_tcp.T(), size),
        )
        for t in trials
    )
    return dict(
        cameras=[camera],
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
