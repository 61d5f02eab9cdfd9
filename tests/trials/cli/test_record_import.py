"""``advobj record import`` from the command line (``trials.cli.main.main`` in-process): a LeRobot
dataset imported, and each bad input refused in one line with exit code 2, writing nothing: not in
``--out`` (left absent) and not anywhere else."""

from __future__ import annotations

import hashlib
import json
import os
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from sim.recording import read_recording
from tests.trials.recordings.lerobot_datasets import build_v21, build_v30, calibration_files, encode, frame, import_args
from trials.cli.main import main


def _run(monkeypatch, capsys, argv) -> tuple[int, str, list[str]]:
    monkeypatch.setattr(sys, "argv", ["advobj", *argv])
    with pytest.raises(SystemExit) as exit_:
        main()
    out = capsys.readouterr()
    return exit_.value.code, out.out, [line for line in out.err.splitlines() if line.strip()]


def _tree(root: Path) -> dict:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir"
        for p in sorted(root.rglob("*"))
    }


@pytest.fixture(scope="module")
def sources(tmp_path_factory):
    d = tmp_path_factory.mktemp("lerobot")
    build_v21(d / "v21")
    build_v30(d / "v30")
    return {"dir": d, "files": calibration_files(d / "cal")}


@pytest.fixture()
def work(sources, tmp_path):
    """Fresh copies of both datasets (the cases damage them) and the calibration files."""
    import shutil

    for name in ("v21", "v30"):
        shutil.copytree(sources["dir"] / name, tmp_path / name)
    return tmp_path


def test_a_lerobot_dataset_imports_from_the_command_line(monkeypatch, capsys, sources, tmp_path):
    code, out, err = _run(monkeypatch, capsys, import_args(sources["dir"] / "v30", tmp_path / "rec", sources["files"]))
    assert code == 0, err
    assert "recording: 3 episodes, 15 steps, cameras wrist, front" in out
    rec = read_recording(tmp_path / "rec")
    assert [e.n_frames for e in rec.episodes] == [5, 4, 6]


def _truncate(work, files):
    video = work / "v21" / "videos" / "chunk-000" / "observation.images.front" / "episode_000001.mp4"
    video.write_bytes(video.read_bytes()[: video.stat().st_size // 2])
    return import_args(work / "v21", work / "out", files), "episode_000001.mp4: not a readable video"


def _short_video(work, files):
    """The episode's video lost its last two frames (re-encoded): the table's last rows have none."""
    video = work / "v21" / "videos" / "chunk-000" / "observation.images.wrist" / "episode_000000.mp4"
    video.unlink()
    encode(video, [frame("wrist", 0, k) for k in range(3)])
    return import_args(work / "v21", work / "out", files), "the video ends (its last frame at 0.2 s) before"


def _shifted_table(work, files):
    """The table's times run 30 ms late against the video: no frame within LeRobot's 0.1 ms."""
    path = work / "v30" / "data" / "chunk-000" / "file-001.parquet"
    table = pq.read_table(path)
    t = table.column("timestamp").to_numpy() + np.float32(0.03)
    i = table.schema.get_field_index("timestamp")
    pq.write_table(table.set_column(i, "timestamp", [t]), path)
    return import_args(work / "v30", work / "out", files), "no frame within 0.1 ms of the table's row 0 at 0.03 s"


def _no_pose_column(work, files):
    path = work / "v21" / "data" / "chunk-000" / "episode_000001.parquet"
    pq.write_table(pq.read_table(path).drop_columns(["observation.state"]), path)
    return import_args(work / "v21", work / "out", files), "no column 'observation.state' (--pose-key)"


def _other_pose_key(work, files):
    argv = import_args(work / "v30", work / "out", files)
    argv[argv.index("--pose-key") + 1] = "observation.ee_pose"
    return argv, "file-000.parquet: no column 'observation.ee_pose' (--pose-key)"


def _version(work, files):
    info = work / "v21" / "meta" / "info.json"
    data = json.loads(info.read_text())
    data["codebase_version"] = "v1.6"
    info.write_text(json.dumps(data))
    return import_args(work / "v21", work / "out", files), "codebase_version 'v1.6' is a LeRobot layout"


def _no_intrinsics(work, files):
    argv = import_args(work / "v21", work / "out", files)
    i = argv.index(f"front={files['front_intrinsics']}")
    del argv[i - 1 : i + 1]
    return argv, "--intrinsics: camera front has no intrinsics"


def _no_extrinsics(work, files):
    argv = import_args(work / "v30", work / "out", files)
    i = argv.index(f"wrist={files['T_tcp_cam']}")
    del argv[i - 1 : i + 1]
    return argv, "--extrinsics: camera wrist has no extrinsics"


def _no_table_frame(work, files):
    argv = import_args(work / "v21", work / "out", files)
    i = argv.index("--table-frame")
    del argv[i : i + 2]
    return argv, "--table-frame: a LeRobot dataset has no table frame"


def _joints(work, files):
    argv = import_args(work / "v21", work / "out", files)
    argv[argv.index("--pose-layout") + 1] = "joints"
    return argv, "--pose-layout joints: camera poses from joint positions through the arm's URDF"


def _intrinsics_of_another_camera_mode(work, files):
    argv = import_args(work / "v21", work / "out", files)
    argv[argv.index(f"front={files['front_intrinsics']}")] = f"front={files['wrist_intrinsics']}"
    return argv, "calibrated at 32x24 px, the frames of camera front are 48x32 px"


def _not_empty_out(work, files):
    (work / "out").mkdir()
    (work / "out" / "mine.txt").write_text("keep")
    return import_args(work / "v21", work / "out", files), "not empty; a recording is written into a new or empty"


@pytest.mark.parametrize(
    "damage",
    [
        _truncate,
        _short_video,
        _shifted_table,
        _no_pose_column,
        _other_pose_key,
        _version,
        _no_intrinsics,
        _no_extrinsics,
        _no_table_frame,
        _joints,
        _intrinsics_of_another_camera_mode,
        _not_empty_out,
    ],
)
def test_a_bad_input_is_one_line_exit_2_and_writes_nothing(monkeypatch, capsys, sources, work, damage):
    argv, expect = damage(work, sources["files"])
    before = _tree(work), _tree(sources["dir"] / "cal")
    out_before = _tree(work / "out") if (work / "out").exists() else None
    monkeypatch.chdir(work)
    code, _, err = _run(monkeypatch, capsys, argv)
    assert code == 2
    assert len(err) == 1 and err[0].startswith("error: ") and "Traceback" not in err[0], err
    assert expect in err[0], err[0]
    assert (_tree(work), _tree(sources["dir"] / "cal")) == before  # nothing written, in --out or anywhere
    assert (_tree(work / "out") if (work / "out").exists() else None) == out_before
    assert not any(p.name.startswith(".staging-") for p in work.rglob("*"))
    assert os.listdir(work)  # (the tree compared above is not empty)
