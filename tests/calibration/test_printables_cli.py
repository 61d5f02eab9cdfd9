"""True-scale PDFs (checked in the PDF itself) and the ``advobj calibrate`` commands."""

import json
import re
import zlib

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from calibration import synthetic as S
from calibration.errors import CalibrationError, CalibrationFileError
from calibration.intrinsics import BoardSpec, CameraIntrinsics, save_camera_yaml
from calibration.printables import board_pdf, parse_id_ranges, tag_sheet_pdf
from trials.cli.main import app

from .conftest import H, W

PT_PER_MM = 72.0 / 25.4


def _pdf_pages_and_images(path):
    """MediaBoxes (pt) and, per drawn image, its (width, height) in pt from the 'a b c d e f cm /Ix Do' operator."""
    data = path.read_bytes()
    boxes = [tuple(float(v) for v in m.group(1).split()) for m in re.finditer(rb"/MediaBox \[([^\]]*)\]", data)]
    sizes = []
    for m in re.finditer(rb"stream\r?\n(.*?)\r?\nendstream", data, re.S):
        try:
            text = zlib.decompress(m.group(1))
        except zlib.error:
            continue
        for a, b, c, d in re.findall(
            rb"([-\d.]+)\s+([-\d.]+)\s+([-\d.]+)\s+([-\d.]+)\s+[-\d.]+\s+[-\d.]+\s+cm\s*/I\d+ Do", text
        ):
            sizes.append((abs(float(a)) + abs(float(c)), abs(float(b)) + abs(float(d))))
    return boxes, sizes


def test_tag_sheet_is_true_scale(tmp_path):
    p = tag_sheet_pdf(tmp_path / "tags.pdf", list(range(8)), 40.0)
    boxes, sizes = _pdf_pages_and_images(p)
    assert len(boxes) == 1  # 12 tags of 40 mm per A4 page, in cut boxes 4 mm apart
    assert len(_pdf_pages_and_images(tag_sheet_pdf(tmp_path / "t13.pdf", list(range(13)), 40.0))[0]) == 2
    assert boxes[0][2:] == pytest.approx((210 * PT_PER_MM, 297 * PT_PER_MM), abs=0.01)
    assert len(sizes) == 8
    for w, h in sizes:
        assert w == pytest.approx(40 * PT_PER_MM, abs=0.01) and h == pytest.approx(40 * PT_PER_MM, abs=0.01)


def test_board_pdf_is_true_scale(tmp_path):
    b = BoardSpec(squares_x=8, squares_y=6, square_size_m=0.03)
    boxes, sizes = _pdf_pages_and_images(board_pdf(tmp_path / "b.pdf", b))
    assert boxes[0][2:] == pytest.approx((297 * PT_PER_MM, 210 * PT_PER_MM), abs=0.01)  # A4 landscape
    assert sizes == [pytest.approx((240 * PT_PER_MM, 180 * PT_PER_MM), abs=0.01)]
    big = BoardSpec(squares_x=12, squares_y=9, square_size_m=0.03)
    with pytest.raises(
        CalibrationError, match=r"board: 360 x 270 mm .* does not fit a 210 x 297 mm page \(A4\).*--page A2"
    ) as e:
        board_pdf(tmp_path / "big.pdf", big)
    assert "\n" not in str(e.value) and not (tmp_path / "big.pdf").exists()
    boxes, sizes = _pdf_pages_and_images(board_pdf(tmp_path / "big.pdf", big, page="A2"))
    assert boxes[0][2:] == pytest.approx((420 * PT_PER_MM, 594 * PT_PER_MM), abs=0.01)  # A2 portrait
    assert sizes == [pytest.approx((360 * PT_PER_MM, 270 * PT_PER_MM), abs=0.01)]
    huge = BoardSpec(squares_x=20, squares_y=7, square_size_m=0.0308, marker_size_m=0.02)  # 616 x 216 mm
    with pytest.raises(CalibrationError, match=r"616 x 215.6 mm .*--page 632x244 \(a print service"):
        board_pdf(tmp_path / "huge.pdf", huge)
    boxes, _ = _pdf_pages_and_images(board_pdf(tmp_path / "huge.pdf", huge, page="700x300"))
    assert boxes[0][2:] == pytest.approx((700 * PT_PER_MM, 300 * PT_PER_MM), abs=0.01)
    with pytest.raises(CalibrationError, match="page: expected A4"):
        board_pdf(tmp_path / "x.pdf", b, page="napkin")


def test_id_ranges_parse_and_errors():
    assert parse_id_ranges("0-3, 7") == [0, 1, 2, 3, 7]
    for bad in ("a", "5-2", ""):
        with pytest.raises(ValueError, match="ids"):
            parse_id_ranges(bad)


runner = CliRunner()


def test_cli_board_and_tags_write_pdfs(tmp_path):
    r = runner.invoke(app, ["calibrate", "board", "--out", str(tmp_path / "board.pdf")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "board.pdf").exists() and (tmp_path / "board.yaml").exists()
    r = runner.invoke(
        app, ["calibrate", "tags", "--ids", "0-7", "--size-mm", "40", "--out", str(tmp_path / "tags.pdf")]
    )
    assert r.exit_code == 0, r.output
    assert _pdf_pages_and_images(tmp_path / "tags.pdf")[1][0][0] == pytest.approx(40 * PT_PER_MM, abs=0.01)
    r = runner.invoke(app, ["calibrate", "tags", "--ids", "x", "--out", str(tmp_path / "t.pdf")])
    assert r.exit_code != 0 and "ids" in r.output


def test_cli_intrinsics_writes_camera_yaml_and_reports_errors(tmp_path, board_images, K):
    imgs, _ = board_images
    paths = []
    for i, img in enumerate(imgs[:8]):
        paths.append(tmp_path / f"b{i}.png")
        cv2.imwrite(str(paths[-1]), img[..., ::-1])
    cv2.imwrite(str(tmp_path / "blank.png"), np.full((H, W), 128, np.uint8))
    out = tmp_path / "cam.yaml"
    r = runner.invoke(
        app, ["calibrate", "intrinsics", *map(str, paths), str(tmp_path / "blank.png"), "--out", str(out)]
    )
    assert r.exit_code == 0, r.output
    assert r.output.startswith("board: ChArUco board (8x6 squares, dictionary 5X5_100)")
    assert "blank.png: 0 corners" in r.output and "REJECTED: no ChArUco markers" in r.output and "RMS" in r.output
    assert "1-sigma: fx" in r.output
    from calibration.intrinsics import load_camera_yaml

    assert abs(load_camera_yaml(out).K[0, 0] - K[0, 0]) / K[0, 0] < 0.01


def test_cli_intrinsics_on_plain_chessboard_photos_finds_the_board_and_writes_ros(tmp_path, K):
    from calibration.intrinsics import ChessboardSpec, load_camera_yaml
    from calibration.selfcheck import _board_views

    b = ChessboardSpec()
    paths = []
    for i, t in enumerate(_board_views(b, 6, seed=2)):
        paths.append(tmp_path / f"left{i:02d}.jpg")
        cv2.imwrite(
            str(paths[-1]), S.degrade(S.render_planes([S.chessboard_plane(b, t)], K, W, H), 0.6, 2.0, seed=i)[..., ::-1]
        )
    out = tmp_path / "ost.yaml"
    r = runner.invoke(app, ["calibrate", "intrinsics", *map(str, paths), "--out", str(out), "--format", "ros"])
    assert r.exit_code == 0, r.output
    assert r.output.startswith("board: plain chessboard, 9x6 inner corners (found automatically)")
    assert "camera_matrix:" in out.read_text() and abs(load_camera_yaml(out).K[0, 0] - K[0, 0]) / K[0, 0] < 0.01
    r = runner.invoke(
        app,
        [
            "calibrate",
            "intrinsics",
            *map(str, paths),
            "--board",
            "chessboard",
            "--inner-corners",
            "9x",
            "--out",
            str(out),
        ],
    )
    assert r.exit_code == 2 and "--inner-corners" in r.output and "COLSxROWS" in r.output
    r = runner.invoke(app, ["calibrate", "intrinsics", *map(str, paths), "--board", "charuco", "--out", str(out)])
    assert isinstance(r.exception, CalibrationError) and "no ChArUco markers (dictionary 5X5_100) found" in str(
        r.exception
    )


def test_cli_wrong_image_size_is_one_line_and_rescale_fixes_it(tmp_path, K, monkeypatch, capsys):
    from trials.cli.main import main

    img = S.render_planes([S.tag_plane(3, 0.04, S.camera_facing(0.5))], K, W, H)
    cv2.imwrite(str(tmp_path / "half.png"), cv2.resize(img, (W // 2, H // 2), interpolation=cv2.INTER_AREA)[..., ::-1])
    save_camera_yaml(tmp_path / "cam.yaml", CameraIntrinsics(K, np.zeros(5), W, H))
    argv = [
        "advobj",
        "calibrate",
        "detect",
        str(tmp_path / "half.png"),
        "--camera",
        str(tmp_path / "cam.yaml"),
        "--size-mm",
        "40",
    ]
    monkeypatch.setattr("sys.argv", argv)
    with pytest.raises(SystemExit) as exc:
        main()
    err = [l for l in capsys.readouterr().err.splitlines() if l.strip()]
    assert (
        exc.value.code == 2 and len(err) == 1 and "half.png" in err[0] and "320x240" in err[0] and "--rescale" in err[0]
    )
    r = runner.invoke(app, argv[1:] + ["--rescale", "--json"])
    assert r.exit_code == 0, r.output
    t = json.loads(r.output[r.output.index("{") :])["tags"][0]["solutions"][0]["translation_m"]
    assert abs(t[2] - 0.5) < 0.015  # the true distance (unrescaled intrinsics would say 1 m); an 18 px tag


def test_cli_detect_json_lists_tags_and_objects(tmp_path, K):
    from pathlib import Path

    reg = Path(__file__).resolve().parents[2] / "examples" / "calibration" / "objects.yaml"
    T = S.camera_facing(0.35, np.radians(25), (1.0, 0.0, 0.0))
    img = S.render_planes(
        [S.tag_plane(2, 0.04, T), S.tag_plane(42, 0.04, S.camera_facing(0.35, 0.3, offset_m=(0.1, 0.05)))], K, W, H
    )
    cv2.imwrite(str(tmp_path / "photo.png"), img[..., ::-1])
    save_camera_yaml(tmp_path / "cam.yaml", CameraIntrinsics(K, np.zeros(5), W, H))
    r = runner.invoke(
        app,
        [
            "calibrate",
            "detect",
            str(tmp_path / "photo.png"),
            "--camera",
            str(tmp_path / "cam.yaml"),
            "--registry",
            str(reg),
            "--json",
        ],
    )
    assert r.exit_code == 0, r.output
    out = json.loads(r.output)
    tags = {t["id"]: t for t in out["tags"]}
    assert set(tags) == {2, 42}
    assert len(tags[2]["solutions"]) == 2 and "ambiguous" in tags[2] and len(tags[2]["corners_px"]) == 4
    assert tags[42]["solutions"] == [] and "unknown_size" in tags[42]["flags"]  # not registered, no --size-mm
    centre = (T @ np.array([0, 0, -0.05, 1.0]))[:3]  # goal centre 5 cm behind its tag
    assert np.linalg.norm(np.array(out["objects"]["goal"]["position_cam_m"]) - centre) < 0.003
    assert set(out["not_detected"]) == {"table", "adversarial", "distractor"}


def test_cli_detect_on_a_corrupt_camera_file_names_file_and_field(tmp_path):
    (tmp_path / "cam.yaml").write_text("width: 640\nheight: 480\nK: [[1, 0, 1], [0, 1, 1]]\n")
    cv2.imwrite(str(tmp_path / "p.png"), np.zeros((H, W), np.uint8))
    r = runner.invoke(app, ["calibrate", "detect", str(tmp_path / "p.png"), "--camera", str(tmp_path / "cam.yaml")])
    assert isinstance(r.exception, CalibrationFileError)
    assert "cam.yaml" in str(r.exception) and r.exception.field.startswith("K")


def test_cli_handeye_on_the_example_samples(tmp_path):
    from pathlib import Path

    samples = Path(__file__).resolve().parents[2] / "examples" / "calibration" / "handeye_samples.yaml"
    out = tmp_path / "T_tcp_cam.yaml"
    r = runner.invoke(app, ["calibrate", "handeye", str(samples), "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "park vs tsai" in r.output and "residuals over 15 samples" in r.output
    from calibration.handeye import load_hand_eye_yaml

    X = load_hand_eye_yaml(out)  # the example's true T_tcp_cam: t = (0, -0.06, 0.04), yaw 90 deg
    assert np.linalg.norm(X[:3, 3] - [0.0, -0.06, 0.04]) < 0.002
