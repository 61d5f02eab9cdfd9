"""Recordings: camera frames with the arm's poses, from a real cell or a simulator, in one format.

A recording is what a policy saw and where the arm was, episode by episode: each step has a time,
one frame per camera and the TCP pose ``T_base_tcp`` (and the gripper, when recorded). Importers
(``advobj record import``: this project's trial sessions, LeRobot datasets) and the simulator
write it with :func:`write_recording`; everything that reads one goes through
:func:`read_recording`. This module alone spells the files' names.

Layout of a recording folder::

    recording.json                       the manifest (format, version, cameras, table frame, episodes)
    episodes/<episode>/steps.csv         one row per step: times, T_base_tcp, gripper
    episodes/<episode>/<camera>/000000.png ... one frame per step and camera (RGB, 8 bit)

The manifest (JSON, ``format: advobj-recording``, ``version`` :data:`FORMAT_VERSION`) holds:

* ``cameras``: per camera its ``name``, image ``width`` x ``height`` (px), intrinsics ``K`` (3x3,
  px) and OpenCV distortion ``dist`` (0, 4, 5, 8, 12 or 14 coefficients), and its mount: ``tcp`` (a
  wrist camera, with ``T_tcp_cam`` from hand-eye calibration) or ``table`` (a fixed camera, with
  ``T_table_cam``). Poses are ``{translation_m: [x, y, z], rotvec_rad: [rx, ry, rz]}``.
* ``T_table_base``: the robot base in the table frame (the sim's world frame, z up, origin on the
  table top), so every camera's pose in the table frame is known at every step
  (:meth:`Recording.T_table_cam`).
* ``sync_tolerance_s``: how far apart in time a frame and its step's pose may be.
* ``gripper``: what the ``gripper`` column holds (``opening_m``: the finger opening in metres;
  ``state``: the value the source recorded, its own units), or null when none was recorded.
* ``episodes``: ``id`` (a safe name: it is a folder) and ``n_frames`` each; ``source``: where
  the recording came from (strings).

``steps.csv`` has the columns ``step, t_s, x_m, y_m, z_m, rx_rad, ry_rad, rz_rad`` (the pose
``T_base_tcp`` as translation and rotation vector, the project's exchange format), ``gripper``
when recorded, then ``t_<camera>_s`` per camera: when that camera's frame was taken. Times are
seconds from the episode's start, written with Python's shortest exact float text, so they read
back bit for bit. ``t_s`` is the time of the pose.

Frames are PNG files, one per step and camera, not a video per camera: PNG is lossless, so what
a recording hands on (to the attack that composites an object into the frames) is exactly what
was recorded or decoded once from the source, with no second generation of video compression;
every frame is read on its own (an attack samples steps at random); and a frame is a file a person
can open. The price is disk space, a few times a video's.

Poses and times are a CSV file (never a pickle): plain text, read without running anything.

:func:`read_recording` checks everything before it returns: the manifest's fields, every
camera's intrinsics and extrinsics (a camera lacking either is refused), every ``steps.csv``
(finite values, times strictly increasing, every frame within ``sync_tolerance_s`` of its pose),
every frame file (a regular file inside the folder, its size, a PNG of the camera's size). Each
refusal is one :class:`RecordingError` line naming the file and the field. :func:`write_recording`
holds what it is given to the same checks and writes atomically: everything goes to a fresh
staging folder inside the target (files created with ``O_EXCL``), and the manifest is moved into
place last, so a folder with a manifest is a whole recording and a failed write leaves nothing.
"""

from __future__ import annotations

import csv
import io
import json
import os
import re
import shutil
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Iterable, Iterator, Literal, Mapping, NamedTuple, Sequence

import numpy as np
from PIL import Image
from pydantic import Field, ValidationError, field_validator, model_validator

from sim.configio import StrictModel
from sim.errors import AdvobjError, format_validation_error
from sim.files import FileRefusedError, open_regular, read_regular
from sim.geometry import make_T, so3_exp, so3_log
from sim.paths import SafeName, UnsafePathError, name_problem, safe_join
from sim.poses import MAX_ROTVEC_RAD, MAX_TRANSLATION_M, Pose, check_T
from sim.spec import CAMERA_NAME

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "MANIFEST_NAME",
    "STEPS_NAME",
    "MOUNTS",
    "GRIPPER_KINDS",
    "MAX_SIDE_PX",
    "MAX_STEPS",
    "MAX_SYNC_TOLERANCE_S",
    "RecordingError",
    "RecordingCamera",
    "RecordedStep",
    "EpisodeInfo",
    "EpisodePoses",
    "Recording",
    "read_recording",
    "write_recording",
    "is_recording",
    "check_target",
]

FORMAT = "advobj-recording"
FORMAT_VERSION = 1
MANIFEST_NAME = "recording.json"
STEPS_NAME = "steps.csv"
EPISODES_DIR = "episodes"
MOUNTS = ("tcp", "table")
#: What a recording's gripper column holds: the finger opening in metres, or the source's own value.
GRIPPER_KINDS = ("opening_m", "state")

MAX_SIDE_PX = 8192  # a frame's width and height
MAX_STEPS = 1_000_000  # steps of one episode
MAX_EPISODES = 100_000
MAX_SYNC_TOLERANCE_S = 2.0  # one period of the slowest trial loop a plan accepts (0.5 Hz)
MAX_MANIFEST_BYTES = 16 * 2**20
MAX_STEPS_BYTES = 256 * 2**20
MAX_FRAME_BYTES = 256 * 2**20
_PNG_COMPRESSION = 3  # zlib level: lossless whatever the level; 3 writes several times faster than 9

_POSE_COLUMNS = ("x_m", "y_m", "z_m", "rx_rad", "ry_rad", "rz_rad")


class RecordingError(AdvobjError, ValueError):
    """A recording (or what is to be written as one) is invalid; the one-line message names the file and field."""


# ---------------------------------------------------------------------- the manifest's schema
Vec3 = tuple[float, float, float]


class _Camera(StrictModel):
    name: str
    width: int = Field(ge=1, le=MAX_SIDE_PX)
    height: int = Field(ge=1, le=MAX_SIDE_PX)
    K: tuple[Vec3, Vec3, Vec3] | None = None
    dist: tuple[float, ...] = ()
    mount: Literal["tcp", "table"]
    T_tcp_cam: Pose | None = None
    T_table_cam: Pose | None = None

    @field_validator("name")
    @classmethod
    def _name(cls, v):
        if not re.fullmatch(CAMERA_NAME, v):
            raise ValueError(
                f"{v!r}: a camera name is a lower case letter, then lower case letters, digits or _ (<= 32)"
            )
        return v

    @field_validator("dist")
    @classmethod
    def _dist(cls, v):
        if len(v) not in (0, 4, 5, 8, 12, 14):
            raise ValueError(f"expected 0, 4, 5, 8, 12 or 14 distortion coefficients (OpenCV's), got {len(v)}")
        return v

    @model_validator(mode="after")
    def _calibrated(self):
        if self.K is None:
            raise ValueError(f"camera {self.name!r} has no intrinsics (K): a frame cannot be related to the scene")
        (fx, s, cx), (zero, fy, cy), last = self.K
        if not (fx > 0 and fy > 0 and s == 0 and zero == 0 and tuple(last) == (0.0, 0.0, 1.0)):
            raise ValueError(f"camera {self.name!r}: K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
        if not (-0.5 <= cx <= self.width - 0.5 and -0.5 <= cy <= self.height - 0.5):
            raise ValueError(f"camera {self.name!r}: the principal point ({cx:g}, {cy:g}) px lies outside the image")
        need, other = ("T_tcp_cam", "T_table_cam") if self.mount == "tcp" else ("T_table_cam", "T_tcp_cam")
        if getattr(self, need) is None:
            raise ValueError(
                f"camera {self.name!r} (mount {self.mount}) has no extrinsics: {need} missing "
                f"({'the hand-eye result' if self.mount == 'tcp' else 'its pose in the table frame'})"
            )
        if getattr(self, other) is not None:
            raise ValueError(f"camera {self.name!r} (mount {self.mount}) takes {need}, not {other}")
        return self


class _Episode(StrictModel):
    id: SafeName
    n_frames: int = Field(ge=1, le=MAX_STEPS)


class _Manifest(StrictModel):
    format: Literal["advobj-recording"]
    version: Literal[1]
    source: dict[str, str] = {}
    sync_tolerance_s: float = Field(ge=0.0, le=MAX_SYNC_TOLERANCE_S)
    gripper: Literal["opening_m", "state"] | None = None
    T_table_base: Pose
    cameras: list[_Camera] = Field(min_length=1, max_length=64)
    episodes: list[_Episode] = Field(min_length=1, max_length=MAX_EPISODES)

    @model_validator(mode="after")
    def _unique(self):
        for what, names in (("camera", [c.name for c in self.cameras]), ("episode", [e.id for e in self.episodes])):
            dup = sorted({n for n in names if names.count(n) > 1})
            if dup:
                raise ValueError(f"{what} names must be unique, repeated: {dup}")
        return self


# ---------------------------------------------------------------------- the API's types
@dataclass(frozen=True)
class RecordingCamera:
    """One camera of a recording: intrinsics, image size and mount.

    ``K``: (3, 3) px; ``dist``: (n,) OpenCV distortion (k1, k2, p1, p2[, k3, ...]); ``width`` x
    ``height`` px. ``mount``: ``tcp`` (wrist camera, ``T_tcp_cam`` (4, 4) from hand-eye) or
    ``table`` (fixed camera, ``T_table_cam`` (4, 4)); the other pose is None. Built from the
    same checks as a manifest's camera: a camera without intrinsics or extrinsics is refused.
    """

    name: str
    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int
    mount: str
    T_tcp_cam: np.ndarray | None = None
    T_table_cam: np.ndarray | None = None

    def __post_init__(self):
        entry = _camera_entry(self)
        object.__setattr__(self, "K", np.asarray(entry.K, dtype=np.float64))
        object.__setattr__(self, "dist", np.asarray(entry.dist, dtype=np.float64))
        for name in ("T_tcp_cam", "T_table_cam"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, _check_T(getattr(self, name), f"camera {self.name!r}: {name}"))


class RecordedStep(NamedTuple):
    """One step of an episode: ``t_s`` (s from the episode's start, the pose's time), ``images``
    ``{camera: (H, W, 3) uint8}``, ``T_base_tcp`` (4, 4), ``gripper`` (None when not recorded) and
    ``frame_t_s`` ``{camera: s}``, when each frame was taken (None or a missing camera: at ``t_s``)."""

    t_s: float
    images: dict
    T_base_tcp: np.ndarray
    gripper: float | None = None
    frame_t_s: dict | None = None


@dataclass(frozen=True)
class EpisodeInfo:
    id: str
    n_frames: int
    duration_s: float  # from the first step's t_s to the last's


@dataclass(frozen=True)
class EpisodePoses:
    """An episode's timeline without its images: ``t_s`` (N,), ``T_base_tcp`` (N, 4, 4), ``gripper``
    (N,) or None, ``frame_t_s`` ``{camera: (N,)}``."""

    t_s: np.ndarray
    T_base_tcp: np.ndarray
    gripper: np.ndarray | None
    frame_t_s: dict


# ---------------------------------------------------------------------- shared checks
def _one_line(text) -> str:
    return " ".join(str(text).split())


def _camera_entry(cam: RecordingCamera) -> _Camera:
    """The manifest entry of ``cam``, validated (the one set of checks of a camera)."""

    def plain(a):
        return None if a is None else np.asarray(a, dtype=np.float64).tolist()

    poses = {}
    for name in ("T_tcp_cam", "T_table_cam"):
        T = getattr(cam, name)
        if T is not None:
            poses[name] = Pose.of(_check_T(T, f"camera {cam.name!r}: {name}")).model_dump()
    try:
        dist = np.asarray(cam.dist, dtype=np.float64).reshape(-1).tolist()
        return _Camera.model_validate(
            {"name": cam.name, "width": cam.width, "height": cam.height, "K": plain(cam.K), "dist": dist}
            | {"mount": cam.mount}
            | poses
        )
    except ValidationError as err:
        raise RecordingError(format_validation_error(err, "recording camera", f"camera {cam.name!r}")) from None
    except (TypeError, ValueError) as err:
        raise RecordingError(f"camera {cam.name!r}: {_one_line(err)}") from None


def _check_T(T, what: str) -> np.ndarray:
    """``T`` as a float64 (4, 4) rigid transform within :data:`~sim.poses.MAX_TRANSLATION_M`
    (:func:`sim.poses.check_T`), or :class:`RecordingError` naming ``what``."""
    try:
        return check_T(T, what, single=True, max_translation_m=MAX_TRANSLATION_M)
    except ValueError as err:
        raise RecordingError(str(err)) from None


def _check_timeline(
    where: str,
    t_s: np.ndarray,
    pose6: np.ndarray,
    gripper: np.ndarray | None,
    frame_t_s: Mapping[str, np.ndarray],
    tolerance_s: float,
) -> None:
    """One episode's values, as written or read: finite, poses in bounds, times strictly
    increasing, every frame within ``tolerance_s`` of its step's pose. ``where`` names the file
    or episode in the :class:`RecordingError`."""
    columns = {"t_s": t_s, **{c: pose6[:, i] for i, c in enumerate(_POSE_COLUMNS)}}
    columns |= {} if gripper is None else {"gripper": gripper}
    columns |= {f"t_{cam}_s": t for cam, t in frame_t_s.items()}
    for name, values in columns.items():
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raise RecordingError(f"{where}: {name}: step {bad[0]} is {float(values[bad[0]])!r}, not a finite number")
    far = np.flatnonzero(np.abs(pose6[:, :3]).max(axis=1) > MAX_TRANSLATION_M)
    if far.size:
        raise RecordingError(
            f"{where}: step {far[0]}: T_base_tcp's translation lies beyond +-{MAX_TRANSLATION_M:g} m "
            "(millimetres given as metres?)"
        )
    wound = np.flatnonzero(np.linalg.norm(pose6[:, 3:], axis=1) > MAX_ROTVEC_RAD)
    if wound.size:
        raise RecordingError(
            f"{where}: step {wound[0]}: T_base_tcp's rotation vector is longer than {MAX_ROTVEC_RAD:g} rad"
        )
    for name in ["t_s"] + [f"t_{cam}_s" for cam in frame_t_s]:
        values = columns[name]
        back = np.flatnonzero(np.diff(values) <= 0)
        if back.size:
            k = int(back[0]) + 1
            now, before = float(values[k]), float(values[k - 1])
            raise RecordingError(
                f"{where}: {name} does not increase at step {k} ({now!r} s after {before!r} s); "
                "times must increase strictly"
            )
    for cam, t in frame_t_s.items():
        gap = np.abs(t - t_s)
        off = np.flatnonzero(gap > tolerance_s)
        if off.size:
            k = int(off[0])
            t_frame, t_pose = float(t[k]), float(t_s[k])
            raise RecordingError(
                f"{where}: step {k}: camera {cam}'s frame was taken at {t_frame!r} s and the pose at {t_pose!r} s, "
                f"{gap[k] * 1000:.6g} ms apart, over the sync tolerance of {tolerance_s * 1000:.6g} ms: frames and "
                "poses do not line up in time"
            )


_FILE_WORDS = {"directory": "not a regular file", "special": "not a regular file"}


def _open_file(path: Path, what: str, max_bytes: int) -> BinaryIO:
    """``path`` open for reading: a regular file of at most ``max_bytes``, checked before it is
    opened and on the open file (:func:`sim.files.open_regular`: a FIFO would block, a device never
    end), or :class:`RecordingError` naming ``what``."""
    try:
        return open_regular(path, max_bytes)
    except FileRefusedError as err:
        raise RecordingError(f"{path}: {what}: {err.problem(_FILE_WORDS)}") from None


def _read_text(path: Path, what: str, max_bytes: int) -> str:
    try:
        data = read_regular(path, max_bytes)
    except FileRefusedError as err:
        raise RecordingError(f"{path}: {what}: {err.problem(_FILE_WORDS)}") from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise RecordingError(f"{path}: {what}: not UTF-8 text (byte {err.start})") from None


def _frame_name(step: int) -> str:
    return f"{step:06d}.png"


def _inside(root: Path, *parts: str, what: str) -> Path:
    try:
        return safe_join(root, *parts, what=what)
    except UnsafePathError as err:
        raise RecordingError(str(err)) from None


# ---------------------------------------------------------------------- reading
class Recording:
    """A validated recording folder (:func:`read_recording`): its cameras, episodes and table frame.

    ``cameras``: ``{name: RecordingCamera}`` in the manifest's order; ``episodes``: a tuple of
    :class:`EpisodeInfo`; ``T_table_base`` (4, 4); ``sync_tolerance_s``; ``gripper`` (one of
    :data:`GRIPPER_KINDS` or None); ``source`` (strings). Frames are read from disk when asked for.
    """

    def __init__(self, path: Path, manifest: _Manifest, timelines: dict[str, EpisodePoses]):
        self.path = path
        self.cameras: dict[str, RecordingCamera] = {
            c.name: RecordingCamera(
                c.name,
                np.asarray(c.K),
                np.asarray(c.dist),
                c.width,
                c.height,
                c.mount,
                None if c.T_tcp_cam is None else c.T_tcp_cam.T,
                None if c.T_table_cam is None else c.T_table_cam.T,
            )
            for c in manifest.cameras
        }
        self.T_table_base = manifest.T_table_base.T
        self.sync_tolerance_s = float(manifest.sync_tolerance_s)
        self.gripper = manifest.gripper
        self.source = dict(manifest.source)
        self._timelines = timelines
        self.episodes: tuple[EpisodeInfo, ...] = tuple(
            EpisodeInfo(e.id, e.n_frames, float(timelines[e.id].t_s[-1] - timelines[e.id].t_s[0]))
            for e in manifest.episodes
        )

    def __repr__(self) -> str:
        return f"Recording({str(self.path)!r}, cameras={list(self.cameras)}, episodes={len(self.episodes)})"

    def episode(self, episode: str) -> EpisodeInfo:
        for e in self.episodes:
            if e.id == episode:
                return e
        shown = ", ".join(e.id for e in self.episodes[:5]) + (", ..." if len(self.episodes) > 5 else "")
        raise RecordingError(f"{self.path}: no episode {episode!r} (it has {shown})")

    def camera(self, camera: str) -> RecordingCamera:
        if camera not in self.cameras:
            raise RecordingError(f"{self.path}: no camera {camera!r} (it has {', '.join(self.cameras)})")
        return self.cameras[camera]

    def poses(self, episode: str) -> EpisodePoses:
        """The episode's times, poses and gripper values (no images)."""
        self.episode(episode)
        return self._timelines[episode]

    def image(self, episode: str, step: int, camera: str) -> np.ndarray:
        """The frame of ``camera`` at ``step`` of ``episode``: (H, W, 3) uint8."""
        info, cam = self.episode(episode), self.camera(camera)
        if not 0 <= int(step) < info.n_frames:
            raise RecordingError(f"{self.path}: episode {episode!r} has steps 0..{info.n_frames - 1}, not {step}")
        return _read_png(self.path, episode, cam, int(step))

    def frames(self, episode: str, cameras: Sequence[str] | None = None) -> Iterator[RecordedStep]:
        """The episode's steps in order, each a :class:`RecordedStep`: ``(t_s, {camera: (H, W, 3)
        uint8}, T_base_tcp (4, 4), gripper, frame_t_s)``; ``cameras`` (default all) chooses the
        frames read."""
        tl = self.poses(episode)
        names = list(self.cameras) if cameras is None else [self.camera(c).name for c in cameras]
        for k in range(len(tl.t_s)):
            yield RecordedStep(
                float(tl.t_s[k]),
                {c: _read_png(self.path, episode, self.cameras[c], k) for c in names},
                tl.T_base_tcp[k].copy(),
                None if tl.gripper is None else float(tl.gripper[k]),
                {c: float(tl.frame_t_s[c][k]) for c in names},
            )

    def T_table_cam(self, camera: str, T_base_tcp) -> np.ndarray:
        """The camera's pose in the table frame at the TCP pose ``T_base_tcp`` (..., 4, 4) -> (..., 4, 4).

        A wrist camera (mount ``tcp``) moves with the arm: ``T_table_base @ T_base_tcp @ T_tcp_cam``;
        a fixed camera (mount ``table``) stands at ``T_table_cam`` whatever the arm does.
        """
        cam = self.camera(camera)
        T_base_tcp = np.asarray(T_base_tcp, dtype=np.float64)
        if T_base_tcp.shape[-2:] != (4, 4):
            raise ValueError(f"T_base_tcp: expected shape (..., 4, 4), got {T_base_tcp.shape}")
        if cam.mount == "table":
            return np.broadcast_to(cam.T_table_cam, T_base_tcp.shape).copy()
        return self.T_table_base @ T_base_tcp @ cam.T_tcp_cam


def is_recording(path: str | Path) -> bool:
    """Whether ``path`` is a folder holding a recording's manifest (not whether it is valid)."""
    return (Path(path) / MANIFEST_NAME).is_file()


def read_recording(path: str | Path) -> Recording:
    """The recording in folder ``path``, checked whole before it is returned (see the module's
    docstring); any problem is one :class:`RecordingError` naming the file and field."""
    root = Path(path)
    if not root.is_dir():
        raise RecordingError(f"{root}: not a recording (no such folder)")
    manifest = _read_manifest(root)
    timelines = {}
    for e in manifest.episodes:
        timelines[e.id] = _read_steps(root, manifest, e)
        for cam in manifest.cameras:
            for k in range(e.n_frames):
                _check_png_header(_frame_path(root, e.id, cam.name, k), cam)
    return Recording(root.resolve(), manifest, timelines)


def _read_manifest(root: Path) -> _Manifest:
    path = root / MANIFEST_NAME
    if not path.exists() and not path.is_symlink():
        raise RecordingError(f"{root}: not a recording ({MANIFEST_NAME} missing; an interrupted write leaves none)")
    text = _read_text(path, "recording manifest", MAX_MANIFEST_BYTES)
    try:
        data = json.loads(text)
    except (json.JSONDecodeError, RecursionError) as err:
        raise RecordingError(f"{path}: not valid JSON ({_one_line(err)})") from None
    if not isinstance(data, dict):
        raise RecordingError(f"{path}: a recording manifest is a JSON object, got {type(data).__name__}")
    if data.get("format") != FORMAT:
        raise RecordingError(f"{path}: format: {data.get('format')!r}, expected {FORMAT!r}")
    if data.get("version") != FORMAT_VERSION:
        raise RecordingError(
            f"{path}: version: a recording of format version {data.get('version')!r}; this advobj reads version "
            f"{FORMAT_VERSION}"
        )
    try:
        return _Manifest.model_validate(data)
    except ValidationError as err:
        raise RecordingError(format_validation_error(err, "recording manifest", str(path))) from None


def _header(manifest_or_cameras, gripper) -> list[str]:
    cams = [c if isinstance(c, str) else c.name for c in manifest_or_cameras]
    return ["step", "t_s", *_POSE_COLUMNS] + (["gripper"] if gripper else []) + [f"t_{c}_s" for c in cams]


def _read_steps(root: Path, manifest: _Manifest, episode: _Episode) -> EpisodePoses:
    path = _inside(root, EPISODES_DIR, episode.id, STEPS_NAME, what=f"episode {episode.id!r}")
    text = _read_text(path, "steps", MAX_STEPS_BYTES)
    rows = list(csv.reader(io.StringIO(text)))
    want = _header(manifest.cameras, manifest.gripper)
    if not rows or rows[0] != want:
        got = "nothing" if not rows else ",".join(rows[0])[:200]
        raise RecordingError(f"{path}: header: expected {','.join(want)}, got {got}")
    body = rows[1:]
    if len(body) != episode.n_frames:
        raise RecordingError(f"{path}: {len(body)} steps, the manifest says {episode.n_frames} (n_frames)")
    values = np.empty((len(body), len(want) - 1), dtype=np.float64)
    for k, row in enumerate(body):
        if len(row) != len(want):
            raise RecordingError(f"{path}: step {k}: {len(row)} columns, expected {len(want)}")
        if row[0] != str(k):
            raise RecordingError(f"{path}: step: row {k + 1} holds step {row[0][:20]!r}, expected {k}")
        for i, cell in enumerate(row[1:]):
            try:
                values[k, i] = float(cell)
            except ValueError:
                raise RecordingError(f"{path}: {want[i + 1]}: step {k}: {cell[:40]!r} is not a number") from None
    n_cam = len(manifest.cameras)
    t_s, pose6 = values[:, 0], values[:, 1:7]
    gripper = values[:, 7] if manifest.gripper else None
    frame_t = {c.name: values[:, len(want) - 1 - n_cam + i] for i, c in enumerate(manifest.cameras)}
    _check_timeline(str(path), t_s, pose6, gripper, frame_t, manifest.sync_tolerance_s)
    T = make_T(so3_exp(pose6[:, 3:]), pose6[:, :3])
    return EpisodePoses(
        t_s.copy(), T, None if gripper is None else gripper.copy(), {c: t.copy() for c, t in frame_t.items()}
    )


def _frame_path(root: Path, episode: str, camera: str, step: int) -> Path:
    return _inside(root, EPISODES_DIR, episode, camera, _frame_name(step), what=f"episode {episode!r}")


@contextmanager
def _frame(path: Path, cam) -> Iterator[Image.Image]:
    """The frame file ``path`` open as an image, once it is a regular file of at most
    :data:`MAX_FRAME_BYTES` (checked on the open file) and an 8-bit RGB PNG of the camera's size
    (only its header is read here)."""
    what = f"frame of camera {cam.name}"
    with _open_file(path, what, MAX_FRAME_BYTES) as f:
        try:
            im = Image.open(f)
        except (OSError, ValueError, Image.DecompressionBombError) as err:
            raise RecordingError(f"{path}: {what}: not a readable image ({_one_line(err)})") from None
        with im:
            if im.format != "PNG" or im.mode != "RGB":
                raise RecordingError(f"{path}: {what}: a {im.format} image in mode {im.mode}, expected an RGB PNG")
            if im.size != (cam.width, cam.height):
                raise RecordingError(
                    f"{path}: {what}: {im.size[0]}x{im.size[1]} px, the camera's is {cam.width}x{cam.height}"
                )
            yield im


def _check_png_header(path: Path, cam) -> None:
    with _frame(path, cam):
        pass


def _read_png(root: Path, episode: str, cam, step: int) -> np.ndarray:
    path = _frame_path(root, episode, cam.name, step)
    with _frame(path, cam) as im:  # checked again: the file may have changed since the recording was read
        try:
            return np.asarray(im, dtype=np.uint8)
        except (OSError, ValueError) as err:
            raise RecordingError(f"{path}: frame of camera {cam.name}: cannot decode ({_one_line(err)})") from None


# ---------------------------------------------------------------------- writing
def _create(path: Path):
    """A new file at ``path`` opened for binary writing; refused (``FileExistsError``) if anything,
    a planted link included, is already there."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o644)
    return os.fdopen(fd, "wb")


def _as_step(step, where: str) -> RecordedStep:
    if isinstance(step, RecordedStep):
        return step
    try:
        return RecordedStep(*step)
    except TypeError:
        raise RecordingError(f"{where}: a step is (t_s, images, T_base_tcp[, gripper[, frame_t_s]])") from None


def _write_episode(
    staging: Path,
    episode: str,
    steps: Iterable,
    cameras: Sequence[RecordingCamera],
    tolerance_s: float,
    gripper_kind: str | None,
) -> int:
    """Write one episode's frames and ``steps.csv`` below ``staging``; returns its step count."""
    problem = name_problem(episode)
    if problem is not None:
        raise RecordingError(f"episode id: {problem}")
    where = f"episode {episode!r}"
    folder = staging / EPISODES_DIR / episode
    folder.mkdir(parents=True)
    for cam in cameras:
        (folder / cam.name).mkdir()
    names = [c.name for c in cameras]
    t_s, pose6, grip, frame_t = [], [], [], {c: [] for c in names}
    for k, raw in enumerate(steps):
        at = f"{where} step {k}"
        if k >= MAX_STEPS:
            raise RecordingError(f"{where}: more than {MAX_STEPS} steps")
        step = _as_step(raw, at)
        images = dict(step.images)
        if sorted(images) != sorted(names):
            raise RecordingError(f"{at}: images of cameras {sorted(images)}, the recording has {sorted(names)}")
        try:
            t = float(step.t_s)
        except (TypeError, ValueError):
            raise RecordingError(f"{at}: t_s: not a number") from None
        T = _check_T(step.T_base_tcp, f"{at}: T_base_tcp")
        if (step.gripper is None) != (gripper_kind is None):
            raise RecordingError(
                f"{at}: gripper: "
                + ("none given, the recording has one" if step.gripper is None else "given, the recording has none")
            )
        times = dict(step.frame_t_s or {})
        unknown = sorted(set(times) - set(names))
        if unknown:
            raise RecordingError(f"{at}: frame_t_s: no camera {unknown[0]!r} in the recording")
        for cam in cameras:
            img = np.asarray(images[cam.name])
            if img.dtype != np.uint8 or img.shape != (cam.height, cam.width, 3):
                raise RecordingError(
                    f"{at}: camera {cam.name}: a {img.dtype} image of shape {img.shape}, expected uint8 "
                    f"({cam.height}, {cam.width}, 3)"
                )
            with _create(folder / cam.name / _frame_name(k)) as f:
                Image.fromarray(np.ascontiguousarray(img)).save(f, format="PNG", compress_level=_PNG_COMPRESSION)
            frame_t[cam.name].append(float(times.get(cam.name, t)))
        t_s.append(t)
        pose6.append(np.concatenate([T[:3, 3], so3_log(T[:3, :3])]))
        grip.append(None if step.gripper is None else float(step.gripper))
    if not t_s:
        raise RecordingError(f"{where}: no steps")
    arrays = np.asarray(t_s), np.asarray(pose6), None if gripper_kind is None else np.asarray(grip, dtype=np.float64)
    frame_arrays = {c: np.asarray(v) for c, v in frame_t.items()}
    _check_timeline(where, *arrays, frame_arrays, tolerance_s)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(_header(names, gripper_kind))
    for k in range(len(t_s)):
        w.writerow(
            [k, repr(t_s[k]), *(repr(float(v)) for v in pose6[k])]
            + ([repr(grip[k])] if gripper_kind else [])
            + [repr(frame_arrays[c][k].item()) for c in names]
        )
    with _create(folder / STEPS_NAME) as f:
        f.write(buf.getvalue().encode())
    return len(t_s)


def check_target(path: str | Path) -> bool:
    """Whether ``path`` must be created (True) or is an empty folder to write a recording into (False);
    anything else (a file, a symlink, a folder with something in it) is one :class:`RecordingError`.
    :func:`write_recording` asks first; an importer may ask before its reading starts."""
    root = Path(path)
    if root.is_symlink():
        raise RecordingError(f"{root}: a symlink; a recording is written into a new or empty folder")
    if not root.exists():
        return True
    if not root.is_dir():
        raise RecordingError(f"{root}: exists and is not a folder; a recording is written into a new or empty folder")
    if any(root.iterdir()):
        raise RecordingError(f"{root}: not empty; a recording is written into a new or empty folder")
    return False


def write_recording(
    path: str | Path,
    cameras: Sequence[RecordingCamera],
    episodes: Iterable[tuple[str, Iterable]],
    *,
    T_table_base,
    sync_tolerance_s: float,
    gripper: str | None = None,
    source: Mapping[str, str] | None = None,
) -> Recording:
    """Write a recording into the new or empty folder ``path`` and return it read back.

    ``cameras``: :class:`RecordingCamera` each; ``episodes``: ``(id, steps)`` pairs, ``steps`` an
    iterable of :class:`RecordedStep` (or tuples of its fields), consumed once, so importers stream
    frames without holding an episode in memory. ``T_table_base`` (4, 4): the robot base in the
    table frame. ``sync_tolerance_s``: how far a frame may be from its pose in time. ``gripper``:
    one of :data:`GRIPPER_KINDS` when every step has a gripper value, else None. ``source``: where
    the recording came from (strings, kept in the manifest).

    Everything is checked as :func:`read_recording` checks it; a problem raises one
    :class:`RecordingError` and leaves nothing behind (``path`` is removed again if this call made
    it). Files are created with ``O_EXCL`` in a staging folder inside ``path``, and the manifest
    is moved into place last.
    """
    root = Path(path)
    cams = list(cameras)
    for cam in cams:
        if not isinstance(cam, RecordingCamera):
            raise RecordingError(f"cameras: expected RecordingCamera, got {type(cam).__name__}")
    head = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "source": {str(k): str(v) for k, v in (source or {}).items()},
        "sync_tolerance_s": sync_tolerance_s,
        "gripper": gripper,
        "T_table_base": Pose.of(_check_T(T_table_base, "T_table_base")).model_dump(),
        "cameras": [_camera_entry(c).model_dump() for c in cams],
    }
    _validate_manifest({**head, "episodes": [{"id": "episode", "n_frames": 1}]}, "recording")  # before any write
    created = check_target(root)
    root.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".staging-", dir=root))
    published: list[Path] = []
    try:
        entries, seen = [], set()
        for item in episodes:
            episode, steps = item
            if episode in seen:
                raise RecordingError(f"episode id: {episode!r} given twice")
            seen.add(episode)
            if len(seen) > MAX_EPISODES:
                raise RecordingError(f"more than {MAX_EPISODES} episodes")
            n = _write_episode(staging, episode, steps, cams, float(sync_tolerance_s), gripper)
            entries.append({"id": episode, "n_frames": n})
        if not entries:
            raise RecordingError("a recording needs at least one episode, none given")
        manifest = _validate_manifest({**head, "episodes": entries}, "recording")
        with _create(staging / MANIFEST_NAME) as f:
            f.write(json.dumps(manifest.model_dump(mode="json"), indent=1).encode())
        for name in (EPISODES_DIR, MANIFEST_NAME):  # the manifest last: a folder with one is whole
            os.rename(staging / name, root / name)
            published.append(root / name)
        staging.rmdir()
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        for p in published:
            if p.is_dir():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)
        if created:
            try:
                root.rmdir()
            except OSError:
                pass
        raise
    return read_recording(root)


def _validate_manifest(data: dict, what: str) -> _Manifest:
    try:
        return _Manifest.model_validate(data)
    except ValidationError as err:
        raise RecordingError(format_validation_error(err, what)) from None
