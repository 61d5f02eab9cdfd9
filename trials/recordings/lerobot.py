"""LeRobot datasets on disk, read as recordings: ``meta/info.json``, parquet tables (pyarrow), mp4 videos (PyAV).

Layouts read (``info.json``'s ``codebase_version``):

* **v2.0, v2.1**: one table and one video per camera per episode,
  ``data/chunk-XXX/episode_XXXXXX.parquet`` and ``videos/chunk-XXX/<video_key>/episode_XXXXXX.mp4``
  (chunk = episode index // ``chunks_size``); the episodes and their lengths in ``meta/episodes.jsonl``.
* **v3.0**: several episodes per file, ``data/chunk-XXX/file-XXX.parquet`` and
  ``videos/<video_key>/chunk-XXX/file-XXX.mp4``; ``meta/episodes/chunk-XXX/file-XXX.parquet`` says
  where each episode is: its data file, and per camera its video file and the span
  ``[from_timestamp, to_timestamp)`` it occupies there.

Paths follow LeRobot's fixed templates for the version: ``info.json``'s ``data_path`` and
``video_path`` must be those (a template is data: it is compared, never formatted), video keys
must be plain names, and every path is joined below the dataset's folder and refused if it leaves
it (a symlink out included).

Each row of an episode's table is a step: its ``timestamp`` (s from the episode's start) and the
end-effector pose ``T_base_tcp`` from a column the user names (:class:`PoseColumns`: the column, a
layout, where in the vector the pose starts). A camera is a ``video`` feature, named after
``observation.images.<camera>``; the decoded frame whose presentation time is nearest the row's
time is the step's frame, and it must lie within the tolerance (LeRobot's own default is 1e-4 s).
A row with no frame that close (a truncated or shifted video) is refused in one line naming the
file. Frames are decoded one at a time, never an episode at once.
"""

from __future__ import annotations

import collections
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from sim.errors import AdvobjError
from sim.files import FileRefusedError, check_regular, read_regular
from sim.geometry import make_T, so3_exp
from sim.paths import UnsafePathError, name_problem, safe_join
from sim.policies.contract import LEROBOT_IMAGE_PREFIX
from sim.recording import MAX_SIDE_PX, MAX_STEPS, RecordedStep
from sim.spec import CAMERA_NAME

__all__ = [
    "CODEBASE_VERSIONS",
    "POSE_LAYOUTS",
    "LeRobotError",
    "PoseColumns",
    "GripperColumn",
    "LeRobotDataset",
    "poses_from_vectors",
]

CODEBASE_VERSIONS = ("v2.0", "v2.1", "v3.0")
#: End-effector pose layouts: how many values each takes from the pose column's vector.
POSE_LAYOUTS = {"xyz_rotvec": 6, "xyz_quat_xyzw": 7, "xyz_quat_wxyz": 7}
_TEMPLATES = {
    "v2": {
        "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
        "video_path": "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4",
    },
    "v3": {
        "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
        "video_path": "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4",
    },
}
_V3_EPISODES = re.compile(r"chunk-\d{3,}/file-\d{3,}\.parquet")
MAX_INFO_BYTES = 16 * 2**20
MAX_EPISODES_BYTES = 1024 * 2**20
MAX_TABLE_BYTES = 16 * 2**30
MAX_VIDEO_BYTES = 64 * 2**30
_QUATERNION_NORM_TOL = 1e-3  # float32 quaternions are unit to ~1e-7; further off is not a rotation


class LeRobotError(AdvobjError, ValueError):
    """A LeRobot dataset cannot be read as a recording; the one-line message names the file and field."""


@dataclass(frozen=True)
class PoseColumns:
    """Where the end-effector pose ``T_base_tcp`` is in each row: the column ``key`` (a vector of
    numbers), its ``layout`` (one of :data:`POSE_LAYOUTS`: metres, then a rotation vector in rad or a
    quaternion), starting at index ``start`` of the vector."""

    key: str
    layout: str
    start: int = 0


@dataclass(frozen=True)
class GripperColumn:
    """The gripper's value in each row: column ``key``, element ``index`` of a vector (None: a scalar column)."""

    key: str
    index: int | None = None


@dataclass(frozen=True)
class _Episode:
    index: int
    length: int
    data: Path  # its table
    videos: dict  # video key -> (file, from_timestamp_s)


def _one_line(text) -> str:
    return " ".join(str(text).split())


def _inside(root: Path, rel: str, what: str) -> Path:
    try:
        return safe_join(root, *rel.split("/"), what=what)
    except UnsafePathError as err:
        raise LeRobotError(str(err)) from None


def _regular(path: Path, what: str, max_bytes: int) -> None:
    """Refuse a missing file, a directory, FIFO or device, or one over ``max_bytes``, before anything
    opens it (for the readers that open the path themselves: parquet, video)."""
    try:
        check_regular(path, max_bytes)
    except FileRefusedError as err:
        raise LeRobotError(f"{path}: {what}: {err.problem()}") from None


def _read_json_text(path: Path, what: str, max_bytes: int) -> str:
    try:
        data = read_regular(path, max_bytes)
    except FileRefusedError as err:
        raise LeRobotError(f"{path}: {what}: {err.problem()}") from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise LeRobotError(f"{path}: {what}: not UTF-8 text (byte {err.start})") from None


def _json(text: str, where: str):
    try:
        return json.loads(text)
    except (json.JSONDecodeError, RecursionError) as err:
        raise LeRobotError(f"{where}: not valid JSON ({_one_line(err)})") from None


def _int(value, where: str, low: int = 0) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise LeRobotError(f"{where}: expected an integer >= {low}, got {value!r}"[:300])
    return int(value)


def _camera_name(key: str) -> str:
    return key[len(LEROBOT_IMAGE_PREFIX) :] if key.startswith(LEROBOT_IMAGE_PREFIX) else key.rsplit(".", 1)[-1]


# ---------------------------------------------------------------------- poses
def _quaternion_R(q_xyzw: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(N, 3, 3)`` of unit quaternions ``(N, 4)`` ordered x, y, z, w."""
    x, y, z, w = q_xyzw.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def poses_from_vectors(vectors: np.ndarray, pose: PoseColumns, where: str) -> np.ndarray:
    """``T_base_tcp`` ``(N, 4, 4)`` from the pose column's vectors ``(N, D)`` (see :class:`PoseColumns`)."""
    n = POSE_LAYOUTS[pose.layout]
    if vectors.shape[1] < pose.start + n:
        raise LeRobotError(
            f"{where}: {pose.key}: {vectors.shape[1]} values per row; --pose-layout {pose.layout} from --pose-start "
            f"{pose.start} needs {pose.start + n}"
        )
    v = vectors[:, pose.start : pose.start + n]
    bad = np.flatnonzero(~np.isfinite(v).all(axis=1))
    if bad.size:
        raise LeRobotError(f"{where}: {pose.key}: row {bad[0]} holds NaN or inf")
    if pose.layout == "xyz_rotvec":
        R = so3_exp(v[:, 3:6])
    else:
        q = v[:, 3:7] if pose.layout == "xyz_quat_xyzw" else v[:, [4, 5, 6, 3]]
        norm = np.linalg.norm(q, axis=1)
        off = np.flatnonzero(np.abs(norm - 1.0) > _QUATERNION_NORM_TOL)
        if off.size:
            raise LeRobotError(
                f"{where}: {pose.key}: row {off[0]}: a quaternion of norm {norm[off[0]]:.6g}, not a unit quaternion "
                f"(is --pose-layout {pose.layout} the column's layout?)"
            )
        R = _quaternion_R(q / norm[:, None])
    return make_T(R, v[:, :3])


# ---------------------------------------------------------------------- video
def _open_video(path: Path):
    _regular(path, "video", MAX_VIDEO_BYTES)
    try:
        container = av.open(str(path), mode="r")
    except (av.error.FFmpegError, OSError, ValueError) as err:
        why = getattr(err, "strerror", None) or err  # FFmpeg's own text, without the path repeated
        raise LeRobotError(f"{path}: not a readable video ({_one_line(why)}); is it truncated?") from None
    if not container.streams.video:
        container.close()
        raise LeRobotError(f"{path}: no video stream (truncated, or not a video)")
    stream = container.streams.video[0]
    w, h = stream.codec_context.width, stream.codec_context.height
    if not (0 < w <= MAX_SIDE_PX and 0 < h <= MAX_SIDE_PX):
        container.close()
        raise LeRobotError(f"{path}: frames of {w}x{h} px; each side must be 1..{MAX_SIDE_PX}")
    return container, stream


def video_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` px of the first video stream of ``path``, from its header."""
    container, stream = _open_video(path)
    try:
        return stream.codec_context.width, stream.codec_context.height
    finally:
        container.close()


def _decoded(container, stream, path: Path, offset_s: float) -> Iterator[tuple[float, object]]:
    """``(t, frame)`` of every frame from the current position on, ``t`` in s after ``offset_s``."""
    try:
        for frame in container.decode(stream):
            if frame.time is None:
                raise LeRobotError(f"{path}: a frame without a presentation time; cannot line it up with the table")
            yield float(frame.time) - offset_s, frame
    except av.error.FFmpegError as err:
        why = getattr(err, "strerror", None) or err
        raise LeRobotError(f"{path}: cannot decode the video ({_one_line(why)}); is it truncated?") from None


def _frames_at(
    path: Path, times_s: np.ndarray, offset_s: float, tolerance_s: float, where: str
) -> Iterator[tuple[float, np.ndarray]]:
    """For each time of ``times_s`` (s, increasing, relative to ``offset_s`` in the file), the decoded
    frame nearest to it: ``(its time relative to offset_s, (H, W, 3) uint8)``. A time with no frame
    within ``tolerance_s`` raises :class:`LeRobotError` naming the file. Frames are decoded in
    order, keeping only those within the tolerance of the current time."""
    container, stream = _open_video(path)
    try:
        size = (stream.codec_context.height, stream.codec_context.width, 3)
        if offset_s > 0:  # v3: the episode starts inside the file; seek to the keyframe before it
            container.seek(max(0, int((offset_s - 1.0) / stream.time_base)), stream=stream, backward=True)
        frames = _decoded(container, stream, path, offset_s)
        window: collections.deque = collections.deque()
        ended, last_t = False, None
        for k, q in enumerate(times_s):
            while not ended and (not window or window[-1][0] <= q + tolerance_s):
                nxt = next(frames, None)
                if nxt is None:
                    ended = True
                    break
                last_t = nxt[0]
                window.append(nxt)
                while len(window) > 1 and window[0][0] < q - tolerance_s:
                    window.popleft()
            while window and window[0][0] < q - tolerance_s:
                window.popleft()
            near = [f for f in window if abs(f[0] - q) <= tolerance_s]
            if not near:
                if ended and (last_t is None or last_t < q - tolerance_s):
                    end = "no frame at all" if last_t is None else f"its last frame at {last_t:.6g} s"
                    raise LeRobotError(
                        f"{path}: {where}: the video ends ({end}) before the table's row {k} at {q:.6g} s: truncated, "
                        "or the table and the video do not line up in time"
                    )
                raise LeRobotError(
                    f"{path}: {where}: no frame within {tolerance_s * 1000:g} ms of the table's row {k} at {q:.6g} s: "
                    "frames and poses do not line up in time"
                )
            t, frame = min(near, key=lambda f: abs(f[0] - q))
            rgb = frame.to_ndarray(format="rgb24")
            if rgb.shape != size:
                raise LeRobotError(f"{path}: {where}: a frame of shape {rgb.shape}, the stream's is {size}")
            yield t, rgb
    finally:
        container.close()


# ---------------------------------------------------------------------- the dataset
class LeRobotDataset:
    """A LeRobot dataset folder: its version, fps, cameras and episodes (read and checked on open)."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        if not self.root.is_dir():
            raise LeRobotError(f"{self.root}: not a LeRobot dataset (no such folder)")
        info_path = self.root / "meta" / "info.json"
        if not info_path.exists():
            raise LeRobotError(f"{self.root}: not a LeRobot dataset (no meta/info.json)")
        info = _json(_read_json_text(info_path, "dataset info", MAX_INFO_BYTES), str(info_path))
        if not isinstance(info, dict):
            raise LeRobotError(f"{info_path}: a JSON object expected, got {type(info).__name__}")
        self.info_path = info_path
        version = info.get("codebase_version")
        if version not in CODEBASE_VERSIONS:
            raise LeRobotError(
                f"{info_path}: codebase_version {str(version)[:40]!r} is a LeRobot layout this advobj does not read "
                f"(it reads {', '.join(CODEBASE_VERSIONS)})"
            )
        self.version: str = version
        self._layout = version[:2]
        fps = info.get("fps")
        if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not (0 < fps <= 10_000):
            raise LeRobotError(f"{info_path}: fps: expected a positive number, got {fps!r}"[:300])
        self.fps = float(fps)
        for field in ("data_path", "video_path"):
            want = _TEMPLATES[self._layout][field]
            if info.get(field) != want:
                raise LeRobotError(
                    f"{info_path}: {field}: {str(info.get(field))[:120]!r} is not LeRobot's {self._layout}.x layout "
                    f"({want!r}); this advobj reads that layout only"
                )
        self.chunks_size = _int(info.get("chunks_size"), f"{info_path}: chunks_size", 1)
        features = info.get("features")
        if not isinstance(features, dict):
            raise LeRobotError(f"{info_path}: features: expected a mapping of feature names")
        self.features = features
        #: camera name -> video key, in the features' order (None: the key names no usable camera)
        self.cameras: dict[str, str] = {}
        self._unnamed: list[str] = []
        for key, feat in features.items():
            if isinstance(feat, dict) and feat.get("dtype") == "video":
                problem = name_problem(key)
                if problem is not None:
                    raise LeRobotError(f"{info_path}: features: video key {problem}")
                name = _camera_name(key)
                if re.fullmatch(CAMERA_NAME, name) and name not in self.cameras:
                    self.cameras[name] = key
                else:
                    self._unnamed.append(key)
        self.image_keys = [k for k, f in features.items() if isinstance(f, dict) and f.get("dtype") == "image"]
        self._episodes = self._read_episodes()

    # -------------------------------------------------------------- metadata
    @property
    def episode_indices(self) -> tuple[int, ...]:
        return tuple(self._episodes)

    def select_cameras(self, wanted: Sequence[str]) -> dict[str, str]:
        """``{camera: video key}`` of ``wanted`` (camera names or video keys; empty: every camera)."""
        if not wanted:
            if self._unnamed:
                raise LeRobotError(
                    f"{self.info_path}: video key {self._unnamed[0]!r} names no camera advobj takes (a lower case "
                    "letter, then lower case letters, digits or _, unique); leave it out by naming the cameras to "
                    "import with --camera"
                )
            if not self.cameras:
                kinds = f" (its image features, {', '.join(self.image_keys)}, are stored in the tables)"
                raise LeRobotError(
                    f"{self.info_path}: no video features: no camera to import"
                    + (kinds + ": not read yet" if self.image_keys else "")
                )
            return dict(self.cameras)
        out = {}
        by_key = {v: k for k, v in self.cameras.items()}
        for w in wanted:
            name = w if w in self.cameras else by_key.get(w)
            if name is None:
                extra = " (stored as images in the tables: not read yet)" if w in self.image_keys else ""
                raise LeRobotError(
                    f"--camera: {w!r} is not a camera of {self.root}{extra}; its cameras: "
                    + (", ".join(f"{k} ({v})" for k, v in self.cameras.items()) or "none")
                )
            out[name] = self.cameras[name]
        return out

    def _read_episodes(self) -> dict[int, dict]:
        return self._episodes_v2() if self._layout == "v2" else self._episodes_v3()

    def _episodes_v2(self) -> dict[int, dict]:
        path = self.root / "meta" / "episodes.jsonl"
        text = _read_json_text(path, "episode list", MAX_EPISODES_BYTES)
        out = {}
        for no, line in enumerate(text.splitlines(), 1):
            if not line.strip():
                continue
            row = _json(line, f"{path}: line {no}")
            if not isinstance(row, dict):
                raise LeRobotError(f"{path}: line {no}: a JSON object expected")
            idx = _int(row.get("episode_index"), f"{path}: line {no}: episode_index")
            out[idx] = {"length": _int(row.get("length"), f"{path}: line {no}: length", 1)}
        if not out:
            raise LeRobotError(f"{path}: no episodes")
        return dict(sorted(out.items()))

    def _episodes_v3(self) -> dict[int, dict]:
        folder = self.root / "meta" / "episodes"
        files = sorted(
            p for p in folder.glob("chunk-*/file-*.parquet") if _V3_EPISODES.fullmatch(p.relative_to(folder).as_posix())
        )
        if not files:
            raise LeRobotError(f"{folder}: no episode tables (chunk-XXX/file-XXX.parquet)")
        need = ["episode_index", "length", "data/chunk_index", "data/file_index"]
        for key in self.cameras.values():
            need += [f"videos/{key}/chunk_index", f"videos/{key}/file_index", f"videos/{key}/from_timestamp"]
        out = {}
        for f in files:
            f = _inside(self.root, f.relative_to(self.root).as_posix(), "episode table")
            table = _read_table(f, need, {}, "episode table", optional=[c for c in need if c.startswith("videos/")])
            for row in table.to_pylist():
                idx = _int(row["episode_index"], f"{f}: episode_index")
                out[idx] = row
        return dict(sorted(out.items()))

    def episode(self, index: int) -> _Episode:
        """Where episode ``index``'s table and videos are (paths checked to stay inside the dataset)."""
        if index not in self._episodes:
            known = list(self._episodes)
            shown = ", ".join(map(str, known[:8])) + (", ..." if len(known) > 8 else "")
            raise LeRobotError(f"--episodes: {self.root} has no episode {index} (it has {shown})")
        meta = self._episodes[index]
        where = f"episode {index}"
        if self._layout == "v2":
            chunk = index // self.chunks_size
            data = _TEMPLATES["v2"]["data_path"].format(episode_chunk=chunk, episode_index=index)
            videos = {
                key: (
                    _TEMPLATES["v2"]["video_path"].format(episode_chunk=chunk, video_key=key, episode_index=index),
                    0.0,
                )
                for key in self.cameras.values()
            }
        else:
            src = f"{self.root}/meta/episodes: {where}"
            data = _TEMPLATES["v3"]["data_path"].format(
                chunk_index=_int(meta["data/chunk_index"], f"{src}: data/chunk_index"),
                file_index=_int(meta["data/file_index"], f"{src}: data/file_index"),
            )
            videos = {}
            for key in self.cameras.values():
                if meta.get(f"videos/{key}/chunk_index") is None:
                    continue  # reported when the camera is read
                offset = meta[f"videos/{key}/from_timestamp"]
                if not isinstance(offset, (int, float)) or not math.isfinite(offset) or offset < 0:
                    raise LeRobotError(f"{src}: videos/{key}/from_timestamp: {offset!r} is no time in s")
                rel = _TEMPLATES["v3"]["video_path"].format(
                    video_key=key,
                    chunk_index=_int(meta[f"videos/{key}/chunk_index"], f"{src}: videos/{key}/chunk_index"),
                    file_index=_int(meta[f"videos/{key}/file_index"], f"{src}: videos/{key}/file_index"),
                )
                videos[key] = (rel, float(offset))
        return _Episode(
            index,
            _int(meta["length"], f"{where}: length", 1),
            _inside(self.root, data, f"{where}'s table"),
            {k: (_inside(self.root, rel, f"{where}'s video"), off) for k, (rel, off) in videos.items()},
        )

    def video(self, index: int, camera_key: str) -> tuple[Path, float]:
        ep = self.episode(index)
        if camera_key not in ep.videos:
            raise LeRobotError(f"{self.root}/meta/episodes: episode {index}: no video of {camera_key}")
        return ep.videos[camera_key]

    # -------------------------------------------------------------- reading an episode
    def check_episode(self, index: int, pose: PoseColumns, gripper: GripperColumn | None) -> None:
        """Refuse an episode whose table lacks a column the import needs (read from its schema only)."""
        ep = self.episode(index)
        _schema_has(ep.data, self._columns(pose, gripper), _flags(pose, gripper))

    @staticmethod
    def _columns(pose: PoseColumns, gripper: GripperColumn | None) -> list[str]:
        cols = ["timestamp", "episode_index", pose.key]
        return cols + ([gripper.key] if gripper is not None and gripper.key not in cols else [])

    def steps(
        self,
        index: int,
        cameras: dict[str, str],
        pose: PoseColumns,
        gripper: GripperColumn | None,
        tolerance_s: float,
    ) -> Iterator[RecordedStep]:
        """Episode ``index`` step by step: the table's rows with each camera's nearest frame."""
        ep = self.episode(index)
        where = f"episode {index}"
        cols = self._columns(pose, gripper)
        table = _read_table(ep.data, cols, _flags(pose, gripper), "table", episode=index)
        if table.num_rows != ep.length:
            raise LeRobotError(
                f"{ep.data}: {where} has {table.num_rows} rows, the episode list says {ep.length} (length)"
            )
        t_s = _vectors(table, "timestamp", ep.data)[:, 0]
        T = poses_from_vectors(_vectors(table, pose.key, ep.data), pose, f"{ep.data}: {where}")
        grip = None if gripper is None else _gripper(table, gripper, ep.data)
        streams = {}
        for name, key in cameras.items():
            path, offset = self.video(index, key)
            streams[name] = _frames_at(path, t_s, offset, tolerance_s, f"{where}, camera {name}")
        try:
            for k in range(len(t_s)):
                images, times = {}, {}
                for name, frames in streams.items():
                    times[name], images[name] = next(frames)
                yield RecordedStep(float(t_s[k]), images, T[k], None if grip is None else float(grip[k]), times)
        finally:
            for frames in streams.values():
                frames.close()


def _flags(pose: PoseColumns, gripper: GripperColumn | None) -> dict[str, str]:
    out = {pose.key: "--pose-key"}
    if gripper is not None:
        out.setdefault(gripper.key, "--gripper-key")
    return out


def _schema_has(path: Path, columns: list[str], flags: dict[str, str]) -> pa.Schema:
    _regular(path, "table", MAX_TABLE_BYTES)
    try:
        schema = pq.read_schema(path)
    except (pa.ArrowException, OSError) as err:
        raise LeRobotError(f"{path}: not a readable parquet table ({_one_line(err)})") from None
    for c in columns:
        if c not in schema.names:
            flag = f" ({flags[c]})" if c in flags else ""
            shown = ", ".join(schema.names[:20]) + (", ..." if len(schema.names) > 20 else "")
            raise LeRobotError(f"{path}: no column {c!r}{flag}; its columns: {shown}")
    return schema


def _read_table(
    path: Path,
    columns: list[str],
    flags: dict[str, str],
    what: str,
    episode: int | None = None,
    optional: Sequence[str] = (),
) -> pa.Table:
    """The ``columns`` of the parquet file ``path`` (rows of ``episode`` only, when given); a missing
    column (unless ``optional``) or an unreadable file is one :class:`LeRobotError` naming it."""
    schema = _schema_has(path, [c for c in columns if c not in optional], flags)
    cols = [c for c in columns if c in schema.names]
    try:
        filters = None if episode is None else [("episode_index", "==", episode)]
        table = pq.read_table(path, columns=cols, filters=filters)
    except (pa.ArrowException, OSError) as err:
        raise LeRobotError(f"{path}: cannot read the {what} ({_one_line(err)})") from None
    if episode is not None and table.num_rows > MAX_STEPS:
        raise LeRobotError(f"{path}: episode {episode} has {table.num_rows} rows, over the limit of {MAX_STEPS}")
    return table


def _vectors(table: pa.Table, key: str, path: Path) -> np.ndarray:
    """Column ``key`` as a float64 ``(N, D)`` array (a scalar column: D = 1)."""
    try:
        arr = np.asarray(table.column(key).to_pylist(), dtype=np.float64)
    except (TypeError, ValueError):
        raise LeRobotError(f"{path}: {key}: not a column of numbers (or of vectors of one length)") from None
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise LeRobotError(f"{path}: {key}: values of shape {arr.shape[1:]}, expected numbers or vectors")
    return arr


def _gripper(table: pa.Table, gripper: GripperColumn, path: Path) -> np.ndarray:
    v = _vectors(table, gripper.key, path)
    if gripper.index is None:
        if v.shape[1] != 1:
            raise LeRobotError(
                f"{path}: {gripper.key}: vectors of {v.shape[1]} values; say which is the gripper's (--gripper-index)"
            )
        return v[:, 0]
    if gripper.index >= v.shape[1]:
        raise LeRobotError(f"{path}: {gripper.key}: {v.shape[1]} values per row, no --gripper-index {gripper.index}")
    return v[:, gripper.index]
