"""Plain chessboards, board identification, degenerate view sets, and camera files from other tools."""

import json

import numpy as np
import pytest

from calibration import synthetic as S
from calibration.errors import CalibrationError, CalibrationFileError
from calibration.intrinsics import (
    BoardSpec,
    CameraIntrinsics,
    ChessboardSpec,
    calibrate_intrinsics,
    camera_file_format,
    detect_chessboard,
    identify_board,
    load_board_yaml,
    load_camera_yaml,
    save_board_yaml,
    save_camera_yaml,
    to_gray,
)
from calibration.selfcheck import _board_views

from .conftest import DIST, H, W

CHESS = ChessboardSpec(inner_cols=9, inner_rows=6, square_size_m=0.025)


@pytest.fixture(scope="module")
def chess_images(K):
    T = _board_views(CHESS, 10, seed=1)
    return [
        S.degrade(S.distort_image(S.render_planes([S.chessboard_plane(CHESS, t)], K, W, H), K, DIST), 0.6, 2.0, seed=i)
        for i, t in enumerate(T)
    ], T


def test_plain_chessboard_intrinsics_within_half_a_percent_of_ground_truth(chess_images, K):
    res = calibrate_intrinsics(chess_images[0], CHESS)
    Kh, f = res.camera.K, K[0, 0]
    assert all(r.accepted and r.n_corners == 54 for r in res.images)
    assert np.abs(Kh[:2, :3] - K[:2, :3]).max() / f < 0.005
    assert abs(res.camera.dist[0] - DIST[0]) < 0.03
    assert res.rms_px < 0.2
    # Sub-pixel corners: the poses' scale comes from the square size.
    assert np.abs(res.T_cam_board[:, :3, 3] - chess_images[1][:, :3, 3]).max() < 0.003


def test_chessboard_corners_are_sub_pixel_accurate(chess_images, K):
    img = S.render_planes([S.chessboard_plane(CHESS, chess_images[1][2])], K, W, H)
    corners, ids = detect_chessboard(to_gray(img), CHESS)
    T = chess_images[1][2]
    truth = CameraIntrinsics(K, np.zeros(5), W, H).project((T[:3, :3] @ CHESS.object_points().T).T + T[:3, 3])
    # OpenCV may start the grid at either end (a 180 deg turn of the board maps the grid onto itself).
    err = min(np.linalg.norm(corners - truth, axis=1).max(), np.linalg.norm(corners[::-1] - truth, axis=1).max())
    assert len(ids) == 54 and err < 0.15


def test_identify_board_names_a_plain_chessboard_and_its_size(chess_images):
    spec, how = identify_board([to_gray(i) for i in chess_images[0]], BoardSpec())
    assert isinstance(spec, ChessboardSpec) and spec.pattern_size == (9, 6)
    assert how == "plain chessboard, 9x6 inner corners (found automatically)"


def test_identify_board_finds_charuco_and_names_a_wrong_dictionary(board_images):
    grays = [to_gray(i) for i in board_images[0][:2]]
    spec, how = identify_board(grays, BoardSpec())
    assert spec == BoardSpec() and how.startswith("ChArUco board")
    with pytest.raises(
        CalibrationError, match=r"dictionary 5X5_50 or 5X5_100 or 5X5_250, not 4X4_50; pass --dictionary"
    ):
        identify_board(grays, BoardSpec(dictionary="4X4_50"))


def test_identify_board_refuses_photos_without_a_board_in_one_line():
    blank = np.full((H, W), 128, np.uint8)
    with pytest.raises(
        CalibrationError,
        match=r"no ChArUco markers \(dictionary 5X5_100\) and no chessboard of a common size found in 1 photo",
    ) as e:
        identify_board([blank], BoardSpec())
    assert "\n" not in str(e.value)


def test_a_chessboard_of_another_size_is_rejected_naming_the_size(chess_images):
    with pytest.raises(CalibrationError, match=r"no 8x6 chessboard found whole"):
        calibrate_intrinsics(chess_images[0][:5], ChessboardSpec(inner_cols=8, inner_rows=6))


def test_copies_of_one_photo_are_refused_as_near_duplicates(chess_images):
    img = chess_images[0][0]
    with pytest.raises(CalibrationError, match=r"only 1 usable.*c1\.png: near-duplicate of c0\.png"):
        calibrate_intrinsics([img] * 5, CHESS, [f"c{i}.png" for i in range(5)])


def test_std_coverage_and_tilt_are_reported_and_weak_sets_warned(chess_images, K):
    res = calibrate_intrinsics(chess_images[0], CHESS)
    assert set(res.std_px) == {"fx", "fy", "cx", "cy"} and all(0 < v < 2 for v in res.std_px.values())
    assert 0 < res.coverage <= 1 and 0 <= res.tilt_deg[0] < res.tilt_deg[1] <= 90
    # Frontal views only, all near the centre: the focal length is weakly determined and the
    # edges of the frame are never seen; both are said.
    T = _board_views(CHESS, 6, seed=5, distance_range_m=(0.4, 0.42), max_tilt_deg=4.0)
    frontal = [
        S.degrade(S.render_planes([S.chessboard_plane(CHESS, t)], K, W, H), 0.6, 2.0, seed=i) for i, t in enumerate(T)
    ]
    weak = calibrate_intrinsics(frontal, CHESS)
    text = " ".join(weak.warnings)
    assert "tilt spans only" in text and "of the image area" in text
    assert weak.std_px["fx"] > 3 * res.std_px["fx"]


def test_board_yaml_round_trips_both_kinds(tmp_path):
    assert load_board_yaml(save_board_yaml(tmp_path / "c.yaml", CHESS)) == CHESS
    assert load_board_yaml(save_board_yaml(tmp_path / "b.yaml", BoardSpec())) == BoardSpec()


# ---- camera files from other tools ------------------------------------------------------------


def _cam():
    K = np.array([[536.07, 0.0, 342.37], [0.0, 536.02, 235.54], [0.0, 0.0, 1.0]])
    return CameraIntrinsics(K, np.array([-0.265, -0.0467, 0.00183, -0.00031, 0.252]), 640, 480, 0.4)


def test_ros_camera_info_round_trips(tmp_path):
    p = save_camera_yaml(tmp_path / "ost.yaml", _cam(), fmt="ros")
    assert camera_file_format(p) == "ros"
    back = load_camera_yaml(p)
    assert (
        np.allclose(back.K, _cam().K)
        and np.allclose(back.dist, _cam().dist)
        and (back.width, back.height) == (640, 480)
    )


def test_a_ros_camera_info_file_as_the_calibrator_writes_it_loads(tmp_path):
    # The layout of camera_calibration_parsers' output (ROS 1 and 2).
    (tmp_path / "head_camera.yaml").write_text("""image_width: 640
image_height: 480
camera_name: head_camera
camera_matrix:
  rows: 3
  cols: 3
  data: [536.07, 0, 342.37, 0, 536.02, 235.54, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.265, -0.0467, 0.00183, -0.00031, 0.252]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [536.07, 0, 342.37, 0, 0, 536.02, 235.54, 0, 0, 0, 1, 0]
""")
    cam = load_camera_yaml(tmp_path / "head_camera.yaml")
    assert cam.K[0, 0] == 536.07 and cam.dist[4] == 0.252


def test_ros_fisheye_and_malformed_matrices_are_refused_naming_the_field(tmp_path):
    good = save_camera_yaml(tmp_path / "a.yaml", _cam(), fmt="ros").read_text()
    (tmp_path / "fish.yaml").write_text(good.replace("plumb_bob", "equidistant"))
    with pytest.raises(CalibrationFileError, match=r"fish\.yaml: distortion_model: .*fisheye"):
        load_camera_yaml(tmp_path / "fish.yaml")
    (tmp_path / "short.yaml").write_text(
        good.replace("rows: 3\n  cols: 3\n  data: [536", "rows: 3\n  cols: 3\n  data: [0.0, 536", 1)
    )
    with pytest.raises(CalibrationFileError, match=r"short\.yaml: camera_matrix"):
        load_camera_yaml(tmp_path / "short.yaml")


@pytest.mark.parametrize("suffix", [".yml", ".json"])
def test_opencv_filestorage_intrinsics_load(tmp_path, suffix):
    import cv2

    p = tmp_path / f"out_camera_data{suffix}"
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)  # what OpenCV's calibration sample writes
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", _cam().K)
    fs.write("distortion_coefficients", _cam().dist.reshape(5, 1))
    fs.write("avg_reprojection_error", 0.4)
    fs.release()
    assert camera_file_format(p) == "opencv"
    cam = load_camera_yaml(p)
    assert np.allclose(cam.K, _cam().K) and np.allclose(cam.dist, _cam().dist) and cam.rms_px == pytest.approx(0.4)


def test_opencv_file_without_an_image_size_is_refused_in_one_line(tmp_path):
    import cv2

    p = tmp_path / "k.yml"
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
    fs.write("K", _cam().K)
    fs.release()
    with pytest.raises(CalibrationFileError, match=r"k\.yml: image_width: no image size"):
        load_camera_yaml(p)


def test_scaled_intrinsics_project_where_the_resized_image_shows_a_point():
    cam = _cam()
    half = cam.scaled(320, 240)
    p = np.array([[0.05, -0.02, 0.6]])
    # Pixel edges scale by s: x' + 0.5 = s (x + 0.5).
    assert np.allclose(half.project(p) + 0.5, 0.5 * (cam.project(p) + 0.5))
    with pytest.raises(ValueError, match="aspect ratio"):
        cam.scaled(320, 320)


def test_std_is_written_to_our_camera_file(tmp_path):
    p = save_camera_yaml(tmp_path / "c.yaml", _cam(), std_px={"fx": 0.5, "fy": 0.4, "cx": 0.3, "cy": 0.2})
    assert "intrinsics_std_px" in p.read_text() and load_camera_yaml(p).K[0, 0] == 536.07
    json.dumps(load_camera_yaml(p).K.tolist())


def test_opencv_files_with_plain_lists_load_and_broken_ones_are_one_line(tmp_path):
    (tmp_path / "plain.yml").write_text(
        "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\n"
        "camera_matrix: [[536.07, 0, 342.37], [0, 536.02, 235.54], [0, 0, 1]]\n"
        "distortion_coefficients: [-0.265, -0.0467, 0.00183, -0.00031, 0.252]\n"
    )
    cam = load_camera_yaml(tmp_path / "plain.yml")
    assert cam.K[0, 0] == pytest.approx(536.07) and cam.dist[4] == pytest.approx(0.252)
    (tmp_path / "plain.json").write_text(
        json.dumps(
            {
                "image_width": 640,
                "image_height": 480,
                "camera_matrix": _cam().K.tolist(),
                "distortion_coefficients": _cam().dist.tolist(),
            }
        )
    )
    assert load_camera_yaml(tmp_path / "plain.json").K[1, 1] == pytest.approx(536.02)
    (tmp_path / "ours.json").write_text(json.dumps({"width": 640, "height": 480, "K": _cam().K.tolist(), "dist": []}))
    assert load_camera_yaml(tmp_path / "ours.json").K[0, 2] == pytest.approx(342.37)  # our schema, written as JSON
    for name, text in (
        ("broken.yml", "%YAML:1.0\n---\ncamera_matrix: !!opencv-matrix\n   rows: 3\n  cols: [\n"),
        ("words.yml", "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: hello\n"),
    ):
        (tmp_path / name).write_text(text)
        with pytest.raises(CalibrationFileError) as e:
            load_camera_yaml(tmp_path / name)
        assert str(e.value).startswith(str(tmp_path / name)) and "\n" not in str(e.value)
