"""Well-formed inputs a recording is refused from, for the hostile CLI campaign
(tests/hostile/test_cli_campaign.py, ``BUILT_KINDS``): LeRobot datasets that ``advobj record import``
cannot read (a truncated mp4, a table without the pose column, a codebase version advobj does not
read) and a recording whose frames show no table (``advobj attack run --recordings``).

Each builder writes its input at ``path`` and returns it; a LeRobot dataset's calibration files go
into ``path.parent / "cal"``, where :data:`LEROBOT_ARGS` (relative to ``path.parent.parent``, the
campaign's working folder) names them."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from sim.geometry import make_T, so3_exp
from sim.spec import default_scene
from tests.attack.recordings_helpers import sim_recording
from tests.trials.recordings.lerobot_datasets import build_v21, calibration_files

#: The rest of an ``advobj record import`` command line for these datasets (the campaign's cwd holds ``inputs/``).
LEROBOT_ARGS = (
    "--from",
    "lerobot",
    "--pose-key",
    "observation.state",
    "--pose-layout",
    "xyz_rotvec",
    "--intrinsics",
    "wrist=inputs/cal/wrist_cam.yaml",
    "--intrinsics",
    "front=inputs/cal/front_cam.yaml",
    "--extrinsics",
    "wrist=inputs/cal/T_tcp_cam.yaml",
    "--extrinsics",
    "front=inputs/cal/T_table_cam.yaml",
    "--table-frame",
    "inputs/cal/T_base_table.yaml",
)


def _dataset(path: Path) -> Path:
    path = Path(path)
    build_v21(path)
    calibration_files(path.parent / "cal")
    return path


def lerobot_truncated_mp4(path) -> Path:
    """A v2.1 dataset whose second episode's front video lost its second half."""
    root = _dataset(path)
    video = root / "videos" / "chunk-000" / "observation.images.front" / "episode_000001.mp4"
    video.write_bytes(video.read_bytes()[: video.stat().st_size // 2])
    return root


def lerobot_no_pose_column(path) -> Path:
    """A v2.1 dataset whose second episode's table has no ``observation.state`` (the pose column named)."""
    root = _dataset(path)
    table = root / "data" / "chunk-000" / "episode_000001.parquet"
    pq.write_table(pq.read_table(table).drop_columns(["observation.state"]), table)
    return root


def lerobot_unknown_version(path) -> Path:
    """A dataset whose ``meta/info.json`` says ``codebase_version`` v1.6 (a layout advobj does not read)."""
    root = _dataset(path)
    info = root / "meta" / "info.json"
    data = json.loads(info.read_text())
    data["codebase_version"] = "v1.6"
    info.write_text(json.dumps(data))
    return root


def recording_no_table(path) -> Path:
    """A recording of the built-in scene at 32 px whose base frame turns every camera away from the table."""
    upside_down = make_T(so3_exp(np.array([math.pi, 0.0, 0.0])), np.array([0.0, 0.0, 1.0]))
    return sim_recording(Path(path), default_scene(), size=32, episodes=3, steps=1, T_table_base=upside_down).path
