"""Tiny LeRobot datasets built here with pyarrow and PyAV, in the v2.1 and v3.0 layouts, with the
truth they were made from (frames, states, timestamps) and the calibration files an import needs."""

from __future__ import annotations

import json
from pathlib import Path

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import yaml

from calibration.intrinsics import CameraIntrinsics, save_camera_yaml
from calibration.io import save_scene_camera_pose
from sim.geometry import make_T, so3_exp

FPS = 10
CAMERAS = {"wrist": (24, 32), "front": (32, 48)}  # (H, W): even sides for yuv420p
CODEC = "libx264" if "libx264" in av.codecs_available else "mpeg4"
STATE_NAMES = ["x", "y", "z", "rx", "ry", "rz", "gripper"]


def frame(camera: str, episode: int, step: int) -> np.ndarray:
    """A smooth image a video codec keeps well, different for every camera, episode and step: a
    colour gradient and a bright square that moves with the step."""
    h, w = CAMERAS[camera]
    img = np.zeros((h, w, 3), np.uint8)
    img[..., 0] = np.linspace(30, 220, w, dtype=np.uint8)[None]
    img[..., 1] = 60 + 40 * episode + (20 if camera == "front" else 0)
    img[..., 2] = np.linspace(200, 40, h, dtype=np.uint8)[:, None]
    x = 2 + 3 * step
    img[4:12, x % (w - 8) : x % (w - 8) + 8] = (250, 250, 250)
    return img


def encode(path: Path, frames: list[np.ndarray], fps: int = FPS) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    h, w = frames[0].shape[:2]
    with av.open(str(path), "w") as out:
        s = out.add_stream(CODEC, rate=fps)
        s.width, s.height, s.pix_fmt = w, h, "yuv420p"
        if CODEC == "libx264":
            s.options = {"crf": "8", "g": "4"}  # a keyframe every 4 frames: the v3 reader seeks inside a file
        for img in frames:
            for p in s.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                out.mux(p)
        for p in s.encode():
            out.mux(p)


def states(rng, n: int) -> np.ndarray:
    """``(n, 7)`` float32: position (m), rotation vector (rad, angle < pi), gripper."""
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    rotvec = axis * rng.uniform(0.0, 3.1, (n, 1))
    return np.concatenate([rng.uniform(-0.5, 0.5, (n, 3)), rotvec, rng.uniform(0, 1, (n, 1))], 1).astype(np.float32)


def _features() -> dict:
    f = {
        "action": {"dtype": "float32", "shape": [7], "names": STATE_NAMES},
        "observation.state": {"dtype": "float32", "shape": [7], "names": STATE_NAMES},
    }
    for cam, (h, w) in CAMERAS.items():
        f[f"observation.images.{cam}"] = {
            "dtype": "video",
            "shape": [h, w, 3],
            "names": ["height", "width", "channels"],
            "info": {
                "video.fps": float(FPS),
                "video.height": h,
                "video.width": w,
                "video.channels": 3,
                "video.codec": "h264" if CODEC == "libx264" else "mpeg4",
                "video.pix_fmt": "yuv420p",
                "video.is_depth_map": False,
                "has_audio": False,
            },
        }
    for k, dt in (("timestamp", "float32"), ("frame_index", "int64"), ("episode_index", "int64")):
        f[k] = {"dtype": dt, "shape": [1], "names": None}
    f["index"] = {"dtype": "int64", "shape": [1], "names": None}
    f["task_index"] = {"dtype": "int64", "shape": [1], "names": None}
    return f


def _info(version: str, lengths, **extra) -> dict:
    """``meta/info.json`` of a dataset of ``lengths`` episodes, with the version's path templates."""
    v2 = version.startswith("v2")
    return {
        "codebase_version": version,
        "robot_type": "so100",
        "total_episodes": len(lengths),
        "total_frames": int(sum(lengths)),
        "total_tasks": 1,
        "chunks_size": 1000,
        "fps": FPS,
        "splits": {"train": f"0:{len(lengths)}"},
        "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"
        if v2
        else "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
        "video_path": "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4"
        if v2
        else "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4",
        "features": _features(),
        **extra,
    }


def _table(episode: int, state: np.ndarray, first_index: int, fixed: bool) -> pa.Table:
    n = len(state)
    vec = pa.list_(pa.float32(), 7) if fixed else pa.list_(pa.float32())
    return pa.table(
        {
            "action": pa.array(state.tolist(), type=vec),
            "observation.state": pa.array(state.tolist(), type=vec),
            "timestamp": pa.array((np.arange(n) / FPS).astype(np.float32)),
            "frame_index": pa.array(np.arange(n), pa.int64()),
            "episode_index": pa.array(np.full(n, episode), pa.int64()),
            "index": pa.array(first_index + np.arange(n), pa.int64()),
            "task_index": pa.array(np.zeros(n, np.int64)),
        }
    )


def build_v21(root: Path, lengths=(5, 4), seed: int = 0) -> dict:
    """A v2.1 dataset: one table and one video per camera per episode. Returns the truth: per
    episode ``{"state": (n, 7) float32, "frames": {camera: [(H, W, 3)]}}``."""
    rng = np.random.default_rng(seed)
    truth, index = {}, 0
    meta = root / "meta"
    meta.mkdir(parents=True)
    for ep, n in enumerate(lengths):
        st = states(rng, n)
        frames = {cam: [frame(cam, ep, k) for k in range(n)] for cam in CAMERAS}
        path = root / "data" / "chunk-000" / f"episode_{ep:06d}.parquet"
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(_table(ep, st, index, fixed=True), path)
        for cam, imgs in frames.items():
            encode(root / "videos" / "chunk-000" / f"observation.images.{cam}" / f"episode_{ep:06d}.mp4", imgs)
        truth[ep] = {"state": st, "frames": frames}
        index += n
    info = _info("v2.1", lengths, total_videos=len(lengths) * len(CAMERAS), total_chunks=1)
    (meta / "info.json").write_text(json.dumps(info, indent=4))
    (meta / "episodes.jsonl").write_text(
        "".join(json.dumps({"episode_index": e, "tasks": ["reach"], "length": n}) + "\n" for e, n in enumerate(lengths))
    )
    (meta / "tasks.jsonl").write_text(json.dumps({"task_index": 0, "task": "reach"}) + "\n")
    return truth


def build_v30(root: Path, lengths=(5, 4, 6), seed: int = 1) -> dict:
    """A v3.0 dataset: episodes 0 and 1 share data file 000, the last has file 001; every camera's
    episodes are concatenated in one video file, located by from/to timestamps."""
    rng = np.random.default_rng(seed)
    truth, rows, index = {}, [], 0
    videos = {cam: [] for cam in CAMERAS}
    tables: dict[int, list] = {}
    for ep, n in enumerate(lengths):
        st = states(rng, n)
        frames = {cam: [frame(cam, ep, k) for k in range(n)] for cam in CAMERAS}
        file_index = 0 if ep < 2 else 1
        tables.setdefault(file_index, []).append(_table(ep, st, index, fixed=False))
        row = {
            "episode_index": ep,
            "tasks": ["reach"],
            "length": n,
            "data/chunk_index": 0,
            "data/file_index": file_index,
            "dataset_from_index": index,
            "dataset_to_index": index + n,
        }
        for cam, imgs in frames.items():
            start = len(videos[cam]) / FPS
            row |= {
                f"videos/observation.images.{cam}/chunk_index": 0,
                f"videos/observation.images.{cam}/file_index": 0,
                f"videos/observation.images.{cam}/from_timestamp": start,
                f"videos/observation.images.{cam}/to_timestamp": start + n / FPS,
            }
            videos[cam] += imgs
        row |= {"meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0}
        rows.append(row)
        truth[ep] = {"state": st, "frames": frames}
        index += n
    for file_index, parts in tables.items():
        path = root / "data" / "chunk-000" / f"file-{file_index:03d}.parquet"
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.concat_tables(parts), path)
    for cam, imgs in videos.items():
        encode(root / "videos" / f"observation.images.{cam}" / "chunk-000" / "file-000.mp4", imgs)
    meta = root / "meta"
    (meta / "episodes" / "chunk-000").mkdir(parents=True)
    pq.write_table(pa.Table.from_pylist(rows), meta / "episodes" / "chunk-000" / "file-000.parquet")
    pq.write_table(pa.table({"task_index": [0], "task": ["reach"]}), meta / "tasks.parquet")
    info = _info("v3.0", lengths, data_files_size_in_mb=100, video_files_size_in_mb=500)
    (meta / "info.json").write_text(json.dumps(info, indent=4))
    return truth


K_WRIST = np.array([[30.0, 0.0, 15.5], [0.0, 30.0, 11.5], [0.0, 0.0, 1.0]])
K_FRONT = np.array([[90.0, 0.0, 47.5], [0.0, 90.0, 31.5], [0.0, 0.0, 1.0]])  # calibrated at 96x64: scaled to 48x32
T_TCP_CAM = {"translation_m": [0.0, -0.04, -0.06], "rotvec_rad": [0.0, 0.0, 0.1]}
T_TABLE_CAM = {"translation_m": [0.6, 0.0, 0.5], "rotvec_rad": [2.0, 0.0, 0.0]}
T_BASE_TABLE = {"translation_m": [0.1, -0.2, 0.0], "rotvec_rad": [0.0, 0.0, 0.3]}


def _T(pose: dict) -> np.ndarray:
    return make_T(so3_exp(np.asarray(pose["rotvec_rad"], dtype=np.float64)), np.asarray(pose["translation_m"]))


def calibration_files(folder: Path) -> dict[str, Path]:
    """The files an import of these datasets needs: intrinsics of both cameras (the front camera's
    at twice the video's resolution), the wrist camera's hand-eye result, the front camera's pose
    in the table frame (``advobj calibrate scene-camera``'s file) and the table frame."""
    folder.mkdir(parents=True, exist_ok=True)
    files = {
        "wrist_intrinsics": save_camera_yaml(
            folder / "wrist_cam.yaml", CameraIntrinsics(K_WRIST, np.array([0.05, -0.01, 0.0, 0.0, 0.0]), 32, 24)
        ),
        "front_intrinsics": save_camera_yaml(folder / "front_cam.yaml", CameraIntrinsics(K_FRONT, np.zeros(5), 96, 64)),
    }
    files["T_table_cam"] = save_scene_camera_pose(folder / "T_table_cam.yaml", _T(T_TABLE_CAM), 96, 64, 0.4, [0, 1])
    for name, data in (
        ("T_tcp_cam", {"T_tcp_cam": T_TCP_CAM, "method": "park", "n_samples": 12}),
        ("T_base_table", {"T_base_table": T_BASE_TABLE}),
    ):
        files[name] = folder / f"{name}.yaml"
        files[name].write_text(yaml.safe_dump(data))
    return files


def import_args(src: Path, out: Path, files: dict[str, Path], *extra: str) -> list[str]:
    """``advobj`` arguments importing ``src`` with both cameras calibrated."""
    return [
        "record",
        "import",
        "--from",
        "lerobot",
        str(src),
        "--out",
        str(out),
        "--pose-key",
        "observation.state",
        "--pose-layout",
        "xyz_rotvec",
        "--gripper-key",
        "observation.state",
        "--gripper-index",
        "6",
        "--intrinsics",
        f"wrist={files['wrist_intrinsics']}",
        "--intrinsics",
        f"front={files['front_intrinsics']}",
        "--extrinsics",
        f"wrist={files['T_tcp_cam']}",
        "--extrinsics",
        f"front={files['T_table_cam']}",
        "--table-frame",
        str(files["T_base_table"]),
        *extra,
    ]
