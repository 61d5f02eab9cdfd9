"""ChArUco intrinsics: accuracy against rendered ground truth, image rejection, the camera YAML."""

import numpy as np
import pytest

from calibration import synthetic as S
from calibration.errors import CalibrationError, CalibrationFileError
from calibration.intrinsics import (
    BoardSpec,
    CalibrationOptions,
    CameraIntrinsics,
    blur_sigma_px,
    calibrate_intrinsics,
    detect_charuco,
    estimate_board_pose,
    load_board_yaml,
    load_camera_yaml,
    save_board_yaml,
    save_camera_yaml,
    to_gray,
)
from sim.geometry import rotation_angle

from .conftest import DIST, H, W


@pytest.fixture(scope="module")
def result(board_images, board):
    imgs, _ = board_images
    return calibrate_intrinsics(imgs, board)


def test_intrinsics_within_one_percent_of_ground_truth(result, K):
    Kh = result.camera.K
    f = K[0, 0]
    assert abs(Kh[0, 0] - K[0, 0]) / f < 0.01
    assert abs(Kh[1, 1] - K[1, 1]) / f < 0.01
    assert abs(Kh[0, 2] - K[0, 2]) / f < 0.01
    assert abs(Kh[1, 2] - K[1, 2]) / f < 0.01
    assert abs(result.camera.dist[0] - DIST[0]) < 0.03  # k1 recovered, not just absorbed


def test_per_image_and_overall_reprojection_errors_are_reported(result):
    per = np.array([r.reprojection_rms_px for r in result.images])
    assert all(r.accepted for r in result.images) and np.all(per > 0) and np.all(per < 0.5)
    assert 0 < result.rms_px < 0.5
    # The overall RMS is the corner-weighted RMS of the per-image RMS values.
    n = np.array([r.n_corners for r in result.images])
    assert result.rms_px == pytest.approx(np.sqrt((per**2 * n).sum() / n.sum()), rel=1e-3)


def test_board_poses_recovered_per_image(result, board_images):
    _, T = board_images
    assert np.abs(result.T_cam_board[:, :3, 3] - T[:, :3, 3]).max() < 0.003


def test_blurred_sparse_and_odd_sized_images_are_rejected_with_reasons(board_images, board, K):
    imgs, T = board_images
    blurred = S.degrade(imgs[0], 1.3, 0.0)
    assert len(detect_charuco(to_gray(blurred), board)[1]) >= 12  # still detected: rejected for blur, not corners
    blank = np.full((H, W, 3), 128, np.uint8)
    small = imgs[1][: H // 2, : W // 2]
    res = calibrate_intrinsics(
        list(imgs[2:8]) + [blurred, blank, small],
        board,
        [f"ok{i}" for i in range(6)] + ["blurred.png", "blank.png", "small.png"],
        CalibrationOptions(max_blur_px=1.25),
    )
    by = {r.name: r for r in res.images}
    assert not by["blurred.png"].accepted and by["blurred.png"].reason.startswith("blurred")
    assert not by["blank.png"].accepted and by["blank.png"].reason == "no ChArUco markers (dictionary 5X5_100) found"
    assert not by["small.png"].accepted and "differs" in by["small.png"].reason
    assert all(by[f"ok{i}"].accepted for i in range(6))


def test_blur_estimate_tracks_applied_blur(board_images, board):
    img = board_images[0][4]
    corners, _ = detect_charuco(to_gray(img), board)
    b = [blur_sigma_px(to_gray(S.degrade(img, s, 0.0)), corners) for s in (0.0, 1.0, 2.0)]
    assert b[0] < b[1] < b[2]
    assert b[2] == pytest.approx(np.hypot(2.0, b[0]), rel=0.25)  # Gaussian blurs add in quadrature


def test_too_few_usable_images_is_an_error_listing_every_rejection(board):
    blank = np.zeros((H, W), np.uint8)
    with pytest.raises(CalibrationError, match=r"only 0 usable.*dark\.png: no ChArUco markers"):
        calibrate_intrinsics([blank, blank], board, ["dark.png", "dark2.png"])


def test_board_pose_from_one_image(board_images, board, K):
    imgs, T = board_images
    cam = CameraIntrinsics(K, DIST, W, H)
    T_est, rms, n = estimate_board_pose(to_gray(imgs[5]), board, cam)
    assert n >= 20 and rms < 0.5
    assert np.linalg.norm(T_est[:3, 3] - T[5][:3, 3]) < 0.002
    assert np.degrees(rotation_angle(T_est[:3, :3], T[5][:3, :3])) < 0.3
    assert estimate_board_pose(np.zeros((H, W), np.uint8), board, cam) is None


def test_camera_yaml_round_trip(tmp_path, result):
    p = save_camera_yaml(tmp_path / "cam.yaml", result.camera, result.images)
    cam = load_camera_yaml(p)
    assert np.allclose(cam.K, result.camera.K) and np.allclose(cam.dist, result.camera.dist)
    assert (cam.width, cam.height) == (W, H) and cam.rms_px == pytest.approx(result.rms_px)


GOOD = "width: 640\nheight: 480\nK: [[500, 0, 320], [0, 500, 240], [0, 0, 1]]\ndist: [0, 0, 0, 0, 0]\n"


@pytest.mark.parametrize(
    "text, field",
    [
        (GOOD.replace("K: [[500, 0, 320], [0, 500, 240], [0, 0, 1]]", "K: [[500, 0, 320], [0, 500, 240]]"), "K"),
        (GOOD.replace("[[500, 0, 320]", "[[-500, 0, 320]"), "K"),
        (GOOD.replace("[0, 0, 1]]", "[0, 1, 1]]"), "K"),
        (GOOD.replace("dist: [0, 0, 0, 0, 0]", "dist: [0, 0, 0]"), "dist"),
        (GOOD.replace("dist: [0, 0, 0, 0, 0]", "dist: [0, .nan, 0, 0, 0]"), "dist"),
        (GOOD.replace("width: 640", "width: -1"), "width"),
        (GOOD.replace("height: 480\n", ""), "height"),
        (GOOD + "focal: 3\n", "focal"),
        (GOOD.replace("width: 640", "width: 100"), "<root>"),  # principal point outside the image
        ("K: [[1, 2\n", "<yaml>"),
        ("- 1\n- 2\n", "<root>"),
    ],
)
def test_corrupt_camera_yaml_error_names_file_and_field(tmp_path, text, field):
    p = tmp_path / "cam.yaml"
    p.write_text(text)
    with pytest.raises(CalibrationFileError) as e:
        load_camera_yaml(p)
    assert e.value.field.split(".")[0] == field  # e.g. "K.2" for the missing third row
    assert str(p) in str(e.value) and field in str(e.value)


def test_missing_camera_yaml_names_the_file(tmp_path):
    with pytest.raises(CalibrationFileError, match="nope.yaml"):
        load_camera_yaml(tmp_path / "nope.yaml")


def test_board_yaml_round_trip_and_validation(tmp_path):
    b = BoardSpec(squares_x=5, squares_y=4, legacy_pattern=True)
    assert load_board_yaml(save_board_yaml(tmp_path / "b.yaml", b)) == b
    (tmp_path / "bad.yaml").write_text("squares_x: 5\nmarker_size_m: 0.05\n")
    with pytest.raises(CalibrationFileError, match="marker_size_m must be smaller"):
        load_board_yaml(tmp_path / "bad.yaml")


def test_legacy_board_is_only_detected_with_the_legacy_flag(K):
    from calibration.selfcheck import _board_views

    legacy = BoardSpec(squares_x=6, squares_y=6, legacy_pattern=True)
    T = _board_views(legacy, 1, seed=2)[0]
    gray = to_gray(S.render_planes([S.board_plane(legacy.cv_board(), T)], K, W, H))
    modern = legacy.model_copy(update={"legacy_pattern": False})
    assert len(detect_charuco(gray, legacy)[1]) >= 20
    assert len(detect_charuco(gray, modern)[1]) < len(detect_charuco(gray, legacy)[1])


@pytest.mark.parametrize(
    "img",
    [
        np.zeros((H, W), np.float32),
        np.ones((H, W, 4), np.float64),
        np.full((H, W, 1), 65535, np.uint16),
    ],
)
def test_to_gray_accepts_common_layouts(img):
    g = to_gray(img)
    assert g.shape == (H, W) and g.dtype == np.uint8


def test_to_gray_rejects_non_images():
    with pytest.raises(ValueError, match="image"):
        to_gray(np.zeros(5))
