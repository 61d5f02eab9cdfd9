"""``advobj calibrate intrinsics DIR``: a folder of board photos, as ROS and camera tools export them.

The photos are rendered ChArUco views with a known K (``calibration.synthetic``); refusals go
through ``trials.cli.main.main`` in-process: exit code 2 and one line on stderr.
"""

from __future__ import annotations

import sys

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from calibration import synthetic as S
from calibration.intrinsics import BoardSpec, load_camera_yaml
from calibration.selfcheck import _board_views
from trials.cli.main import app

W, H = 640, 480
N_VIEWS = 8


@pytest.fixture(scope="module")
def photos(tmp_path_factory):
    """A folder of 8 board photos named out of order on disk, a note, a sub-folder and an uppercase suffix."""
    board = BoardSpec()
    K = S.default_K(W, H)
    d = tmp_path_factory.mktemp("photos") / "frames"
    (d / "rejected").mkdir(parents=True)
    names = [f"frame{i:04d}.png" for i in range(N_VIEWS - 1)] + ["frame0007.PNG"]
    for i, T in reversed(list(enumerate(_board_views(board, N_VIEWS, seed=3)))):  # written last to first
        img = S.degrade(S.render_planes([S.board_plane(board.cv_board(), T)], K, W, H), 0.6, 2.0, seed=i)
        cv2.imwrite(str(d / names[i]), img[..., ::-1])
    cv2.imwrite(str(d / "rejected" / "blank.png"), np.full((H, W), 128, np.uint8))  # not read: sub-folders are not
    (d / "notes.txt").write_text("camera 1, 2024-05-01\n")
    return d, names, K


def _refused(monkeypatch, capsys, *argv) -> str:
    from trials.cli.main import main

    monkeypatch.setattr(sys, "argv", ["advobj", *argv])
    with pytest.raises(SystemExit) as exc:
        main()
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert exc.value.code == 2 and len(err) == 1, err
    return err[0]


def test_a_folder_is_read_as_its_photos_sorted_by_name(photos, tmp_path):
    d, names, K = photos
    out = tmp_path / "cam.yaml"
    r = CliRunner().invoke(app, ["calibrate", "intrinsics", str(d), "--out", str(out)])
    assert r.exit_code == 0, r.output
    listed = [line.strip().split(":")[0] for line in r.output.splitlines() if line.startswith("  ")]
    assert listed == [str(d / n) for n in sorted(names)]  # the photos only, by name; no note, no sub-folder
    assert "REJECTED" not in r.output
    assert abs(load_camera_yaml(out).K[0, 0] - K[0, 0]) / K[0, 0] < 0.01


def test_folders_and_files_mix_and_a_folder_without_photos_is_one_line(photos, tmp_path, monkeypatch, capsys):
    d, names, _ = photos
    r = CliRunner().invoke(
        app, ["calibrate", "intrinsics", str(d / names[0]), str(d), "--out", str(tmp_path / "c.yaml")]
    )
    assert r.exit_code == 0, r.output
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("x")
    line = _refused(monkeypatch, capsys, "calibrate", "intrinsics", str(empty), "--out", str(tmp_path / "e.yaml"))
    assert line.startswith(f"error: {empty}: <images>: a folder with no photos (.png .jpg")
    assert not (tmp_path / "e.yaml").exists()


def test_more_photos_than_the_stated_maximum_are_refused_before_any_is_read(photos, tmp_path, monkeypatch, capsys):
    import trials.cli.calibrate as cli_calibrate

    d, names, _ = photos
    monkeypatch.setattr(cli_calibrate, "MAX_INTRINSICS_PHOTOS", N_VIEWS - 1)
    read = []
    monkeypatch.setattr(cli_calibrate, "_read_image", lambda p: read.append(p))
    line = _refused(monkeypatch, capsys, "calibrate", "intrinsics", str(d), "--out", str(tmp_path / "c.yaml"))
    assert line == (
        f"error: <images>: {N_VIEWS} photos, over the maximum of {N_VIEWS - 1} for one calibration; pick a subset "
        "that shows the board across the image and tilted (e.g. every 10th frame of a recording)"
    )
    assert read == [] and not (tmp_path / "c.yaml").exists()


def test_a_photo_over_the_size_limit_or_a_link_out_of_the_folder_is_one_line(photos, tmp_path, monkeypatch, capsys):
    import calibration.io as cio

    d, names, _ = photos
    monkeypatch.setattr(cio, "MAX_IMAGE_BYTES", 1000)
    line = _refused(monkeypatch, capsys, "calibrate", "intrinsics", str(d), "--out", str(tmp_path / "c.yaml"))
    assert line.startswith(f"error: {d / sorted(names)[0]}: <image>:") and "over the limit of 1000 bytes" in line
    monkeypatch.undo()
    linked = tmp_path / "linked"
    linked.mkdir()
    (linked / "a.png").symlink_to(d / names[0])
    line = _refused(monkeypatch, capsys, "calibrate", "intrinsics", str(linked), "--out", str(tmp_path / "c.yaml"))
    assert line == f"error: {linked / 'a.png'}: <images>: a link to {d / names[0]}, outside the folder {linked}"
