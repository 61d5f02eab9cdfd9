"""``advobj record import`` without the command line: one validated job, then :func:`run_import`.

:class:`ImportJob` holds every input, one field per flag (``table_frame`` is ``--table-frame``);
building it checks types, bounds and which options go with which source, and a bad value raises
one :class:`~trials.recordings.calib.RecordImportError` naming its flag. :func:`run_import` reads
the source (:mod:`trials.recordings.session`: this project's trial sessions;
:mod:`trials.recordings.lerobot`: LeRobot datasets), checks what it can before anything is
written (the cameras' calibration, :mod:`trials.recordings.calib`; the tables' columns; every
video's header) and writes the recording with :func:`sim.recording.write_recording`, which
writes only inside ``--out`` and leaves nothing there when the import fails half way.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Literal, Optional

from pydantic import Field, ValidationError, field_validator, model_validator

from sim.configio import StrictModel
from sim.errors import AdvobjError, flag_error
from sim.recording import MAX_SYNC_TOLERANCE_S, Recording, RecordingCamera, check_target, write_recording
from trials.recordings.calib import (
    RecordImportError,
    camera_extrinsics,
    camera_intrinsics,
    check_cameras_named,
    table_frame,
)
from trials.recordings.lerobot import POSE_LAYOUTS, GripperColumn, LeRobotDataset, PoseColumns, video_size
from trials.recordings.session import session_recording

__all__ = ["ImportJob", "SOURCES", "JOINT_LAYOUT", "LEROBOT_TOLERANCE_S", "run_import"]

SOURCES = ("session", "lerobot")
JOINT_LAYOUT = "joints"
#: LeRobot's own tolerance between a row's timestamp and its video frame (LeRobotDataset's tolerance_s).
LEROBOT_TOLERANCE_S = 1e-4


def _flag(field: str) -> str:
    return {"source": "--from", "src": "SRC"}.get(field, "--" + field.replace("_", "-"))


class ImportJob(StrictModel):
    """Every input of one import, one field per flag of ``advobj record import``."""

    source: Literal["session", "lerobot"] = Field(description="session: a trial database; lerobot: a dataset folder")
    src: Path = Field(description="the trial database file, or the LeRobot dataset's folder")
    out: Path = Field(description="the recording's folder (new or empty)")
    session: Optional[str] = Field(None, description="the session to import (--from session; default: the only one)")
    intrinsics: dict[str, Path] = Field({}, description="camera -> camera YAML (overrides the session's file)")
    extrinsics: dict[str, Path] = Field({}, description="camera -> hand-eye result (T_tcp_cam) or T_table_cam YAML")
    table_frame: Optional[Path] = Field(None, description="YAML with T_base_table (LeRobot: needed)")
    cameras: tuple[str, ...] = Field((), description="LeRobot cameras to import (names or video keys); empty: all")
    episodes: Optional[tuple[int, ...]] = Field(None, description="LeRobot episode indices; None: all")
    pose_key: Optional[str] = Field(None, description="LeRobot column holding the end-effector pose")
    pose_layout: Optional[str] = Field(None, description="layout of the pose in that column")
    pose_start: int = Field(0, ge=0, le=10_000, description="index in the column's vector where the pose starts")
    gripper_key: Optional[str] = Field(None, description="LeRobot column holding the gripper's value")
    gripper_index: Optional[int] = Field(None, ge=0, le=10_000, description="element of that column's vector")
    tolerance_s: Optional[float] = Field(
        None,
        gt=0.0,
        le=MAX_SYNC_TOLERANCE_S,
        description="how far a frame may be from its row in time (LeRobot default 1e-4 s; a session's: one control "
        "period)",
    )

    def __init__(self, **values):
        try:
            super().__init__(**values)
        except ValidationError as err:
            raise _job_error(err) from None

    @field_validator("pose_layout")
    @classmethod
    def _layout(cls, v):
        if v == JOINT_LAYOUT:
            raise RecordImportError(
                "--pose-layout joints: camera poses from joint positions through the arm's URDF are the joint-space "
                "issue's and not read yet; name a column holding the end-effector pose ("
                + ", ".join(POSE_LAYOUTS)
                + ")"
            )
        if v is not None and v not in POSE_LAYOUTS:
            raise RecordImportError(
                f"--pose-layout: {v!r} is not one of {', '.join(POSE_LAYOUTS)} (or joints, not read yet)"
            )
        return v

    @field_validator("episodes")
    @classmethod
    def _episodes(cls, v):
        if v is not None and (not v or min(v) < 0 or len(set(v)) != len(v)):
            raise RecordImportError(f"--episodes: expected distinct episode indices >= 0, got {','.join(map(str, v))}")
        return v

    @model_validator(mode="after")
    def _fits_the_source(self):
        lerobot_only = {
            "cameras": self.cameras,
            "episodes": self.episodes,
            "pose_key": self.pose_key,
            "pose_layout": self.pose_layout,
            "pose_start": self.pose_start or None,
            "gripper_key": self.gripper_key,
            "gripper_index": self.gripper_index,
        }
        if self.source == "session":
            given = [f for f, v in lerobot_only.items() if v]
            if given:
                raise RecordImportError(f"{_flag(given[0])}: goes with --from lerobot; a session's poses are its own")
        else:
            if self.session is not None:
                raise RecordImportError("--session: goes with --from session")
            if self.pose_key is None or self.pose_layout is None:
                raise RecordImportError(
                    "--pose-key and --pose-layout: a LeRobot dataset's end-effector pose column is yours to name "
                    "(e.g. --pose-key observation.state --pose-layout xyz_rotvec); joint positions through the arm's "
                    "URDF are the joint-space issue's, not read yet"
                )
            if self.gripper_index is not None and self.gripper_key is None:
                raise RecordImportError("--gripper-index: give --gripper-key too")
            if self.table_frame is None:
                raise RecordImportError(
                    "--table-frame: a LeRobot dataset has no table frame; give the YAML with T_base_table (the "
                    "table's pose in the robot's base frame, as for 'advobj trial run')"
                )
        if self.out.resolve() == self.src.resolve() or self.src.resolve() in self.out.resolve().parents:
            raise RecordImportError(f"--out: {self.out} lies inside SRC; write the recording elsewhere")
        return self


def _job_error(err: ValidationError) -> AdvobjError:
    return flag_error(err, _flag, "record import", RecordImportError)


# ---------------------------------------------------------------------- the LeRobot import
def _lerobot(job: ImportJob, log: Callable[[str], None]):
    ds = LeRobotDataset(job.src)
    cameras = ds.select_cameras(job.cameras)
    check_cameras_named(job.intrinsics, cameras, "--intrinsics")
    check_cameras_named(job.extrinsics, cameras, "--extrinsics")
    for name in cameras:
        for flag, given in (("--intrinsics", job.intrinsics), ("--extrinsics", job.extrinsics)):
            if name not in given:
                what = (
                    "intrinsics (a camera YAML)"
                    if flag == "--intrinsics"
                    else "extrinsics (hand-eye T_tcp_cam or T_table_cam)"
                )
                raise RecordImportError(
                    f"{flag}: camera {name} has no {what}; LeRobot datasets carry no calibration: give "
                    f"{flag} {name}=FILE"
                )
    episodes = list(ds.episode_indices) if job.episodes is None else list(job.episodes)
    pose = PoseColumns(job.pose_key, job.pose_layout, job.pose_start)
    gripper = None if job.gripper_key is None else GripperColumn(job.gripper_key, job.gripper_index)
    sizes: dict[str, tuple[int, int]] = {}
    for index in episodes:  # before anything is written: every table's columns, every video's header
        ds.check_episode(index, pose, gripper)
        for name, key in cameras.items():
            path, _ = ds.video(index, key)
            size = video_size(path)
            if sizes.setdefault(name, size) != size:
                raise RecordImportError(
                    f"{path}: frames of {size[0]}x{size[1]} px, camera {name}'s other videos have "
                    f"{sizes[name][0]}x{sizes[name][1]} px"
                )
    cams = []
    for name in cameras:
        K, dist = camera_intrinsics(job.intrinsics[name], name, sizes[name])
        mount, T = camera_extrinsics(job.extrinsics[name], name)
        cams.append(
            RecordingCamera(
                name, K, dist, *sizes[name], mount, T if mount == "tcp" else None, T if mount == "table" else None
            )
        )
    tolerance = LEROBOT_TOLERANCE_S if job.tolerance_s is None else job.tolerance_s
    log(
        f"LeRobot {ds.version} dataset {job.src}: {len(episodes)} episodes at {ds.fps:g} fps, cameras "
        + ", ".join(f"{n} ({k})" for n, k in cameras.items())
    )
    stream = ((f"episode_{i:06d}", ds.steps(i, cameras, pose, gripper, tolerance)) for i in episodes)
    source = {
        "kind": "lerobot",
        "dataset": str(job.src),
        "codebase_version": ds.version,
        "fps": f"{ds.fps:g}",
        "pose": f"{pose.key}[{pose.start}:] {pose.layout}",
        **({"gripper": f"{gripper.key}" + ("" if gripper.index is None else f"[{gripper.index}]")} if gripper else {}),
        **{f"camera.{n}": k for n, k in cameras.items()},
    }
    return dict(
        cameras=cams,
        episodes=stream,
        T_table_base=table_frame(job.table_frame),
        sync_tolerance_s=tolerance,
        gripper=None if gripper is None else "state",
        source=source,
    )


def run_import(job: ImportJob, log: Callable[[str], None] | None = None) -> Recording:
    """Read ``job.src`` and write it as a recording into ``job.out``; returns the recording."""
    log = log or (lambda _text: None)
    check_target(job.out)  # before any reading: an --out that cannot take a recording
    if job.source == "lerobot":
        return write_recording(job.out, **_lerobot(job, log))
    parts, store = session_recording(
        job.src, job.session, job.intrinsics, job.extrinsics, job.table_frame, job.tolerance_s, log
    )
    try:
        return write_recording(job.out, **parts)
    finally:
        store.close()
