"""Eye-in-hand calibration: accuracy on noisy synthetic sets, method cross-check, refusals, files."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration import synthetic as S
from calibration.errors import CalibrationError, CalibrationFileError, DegenerateDataError
from calibration.handeye import (
    HandEyeOptions,
    check_motion_diversity,
    load_hand_eye_yaml,
    load_samples_yaml,
    save_hand_eye_yaml,
    solve_hand_eye,
)
from calibration.io import T_to_pose, write_yaml
from sim.geometry import make_T, rotation_angle, so3_exp

X_TRUE = make_T(so3_exp([0.05, -0.1, np.pi / 2]), [0.03, -0.05, 0.06])
T_BASE_BOARD = make_T(so3_exp([np.pi, 0.0, 0.3]), [0.55, 0.05, 0.0])


def _noisy_set(n=15, seed=0, board_noise=(5e-4, 0.1), tcp_noise=(1e-4, 0.02)):
    A, B = S.hand_eye_poses(n, X_TRUE, T_BASE_BOARD, (0.12, 0.09, 0.0), seed=seed)
    A = S.perturb_poses(A, tcp_noise[0], np.radians(tcp_noise[1]), seed=seed + 1)
    B = S.perturb_poses(B, board_noise[0], np.radians(board_noise[1]), seed=seed + 2)
    return A, B


def _err(T):
    return np.linalg.norm(T[:3, 3] - X_TRUE[:3, 3]), np.degrees(rotation_angle(T[:3, :3], X_TRUE[:3, :3]))


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_recovers_T_tcp_cam_within_2mm_and_half_degree_on_noisy_sets(seed):
    A, B = _noisy_set(seed=seed * 10)
    res = solve_hand_eye(A, B)
    dt, dr = _err(res.T_tcp_cam)
    assert dt < 0.002 and dr < 0.5


def test_noise_free_set_is_recovered_exactly():
    A, B = S.hand_eye_poses(8, X_TRUE, T_BASE_BOARD, seed=4)
    res = solve_hand_eye(A, B)
    dt, dr = _err(res.T_tcp_cam)
    assert dt < 1e-6 and dr < 1e-4
    assert res.rms_position_m < 1e-6 and res.disagreement_m < 1e-6


def test_two_methods_are_cross_checked_and_residuals_reported():
    A, B = _noisy_set(seed=5)
    res = solve_hand_eye(A, B, HandEyeOptions(method="park", check_method="tsai"))
    assert res.check_method == "tsai" and res.method.startswith("park")
    assert 0 < res.disagreement_m < 0.005 and 0 < res.disagreement_deg < 1.0
    assert res.residual_position_m.shape == (15,) and res.residual_rotation_deg.shape == (15,)
    # Residuals reflect the injected board noise (0.5 mm, 0.1 deg per axis), not zero, not huge.
    assert 0.0003 < res.rms_position_m < 0.003 and 0.05 < res.rms_rotation_deg < 0.5
    assert "park vs tsai" in res.summary()


def test_refinement_does_not_make_the_solution_worse_on_average():
    e_raw, e_ref = [], []
    for seed in range(4):
        A, B = _noisy_set(seed=100 + seed)
        e_raw.append(_err(solve_hand_eye(A, B, HandEyeOptions(refine=False)).T_tcp_cam)[0])
        e_ref.append(_err(solve_hand_eye(A, B).T_tcp_cam)[0])
    assert np.mean(e_ref) <= np.mean(e_raw) * 1.1


def test_too_few_samples_are_refused_with_advice():
    A, B = _noisy_set(n=3)
    with pytest.raises(DegenerateDataError, match=r"3 sample\(s\), need at least 5.*rotating the gripper"):
        solve_hand_eye(A, B)


def test_translation_only_motion_is_refused():
    A = np.stack([make_T(np.eye(3), [0.1 * i, 0.02 * i, 0.3]) for i in range(8)])
    with pytest.raises(DegenerateDataError, match="barely rotates"):
        check_motion_diversity(A)


@settings(max_examples=30, deadline=None)
@given(
    axis=st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)).filter(lambda a: np.linalg.norm(a) > 0.2),
    seed=st.integers(0, 10_000),
)
def test_rotation_about_a_single_axis_is_refused_with_a_perpendicular_axis_to_add(axis, seed):
    rng = np.random.default_rng(seed)
    a = np.asarray(axis) / np.linalg.norm(axis)
    A = np.stack([make_T(so3_exp(a * rng.uniform(-1.2, 1.2)), rng.uniform(-0.2, 0.2, 3)) for _ in range(10)])
    A[0, :3, :3] = so3_exp(a * 1.3)  # guarantee rotating pairs exist
    with pytest.raises(DegenerateDataError, match="same axis") as e:
        check_motion_diversity(A)
    msg = str(e.value)
    suggested = np.array([float(x) for x in msg.rsplit("e.g. [", 1)[1].split("]")[0].split(",")])
    assert abs(suggested @ a) < 0.05  # the advice names a perpendicular axis


def test_diverse_set_passes_the_check():
    A, _ = _noisy_set()
    rep = check_motion_diversity(A)
    assert rep.axis_spread_deg > 20 and rep.n_rotating_pairs >= 2


def test_mismatched_inputs_are_value_errors():
    A, B = _noisy_set()
    with pytest.raises(ValueError, match="T_cam_board"):
        solve_hand_eye(A, B[:-1])
    B2 = B.copy()
    B2[0, :3, :3] *= 2
    with pytest.raises(ValueError, match="T_cam_board"):
        solve_hand_eye(A, B2)


def test_hand_eye_yaml_round_trip_and_corrupt_file(tmp_path):
    A, B = _noisy_set()
    res = solve_hand_eye(A, B)
    p = save_hand_eye_yaml(tmp_path / "T_tcp_cam.yaml", res)
    assert np.allclose(load_hand_eye_yaml(p), res.T_tcp_cam, atol=1e-9)
    bad = tmp_path / "bad.yaml"
    bad.write_text("T_tcp_cam:\n  translation_m: [0.1, 0.2]\n")
    with pytest.raises(CalibrationFileError) as e:
        load_hand_eye_yaml(bad)
    assert e.value.field.startswith("T_tcp_cam.translation_m") and str(bad) in str(e.value)


def _pose(T):
    p = T_to_pose(T)
    return {"translation_m": list(p.translation_m), "rotvec_rad": list(p.rotvec_rad)}


def test_samples_file_with_board_poses(tmp_path):
    A, B = _noisy_set()
    p = write_yaml(
        tmp_path / "samples.yaml",
        {"samples": [{"T_base_tcp": _pose(a), "T_cam_board": _pose(b)} for a, b in zip(A, B)]},
    )
    A2, B2, notes = load_samples_yaml(p)
    assert np.allclose(A2, A, atol=1e-9) and np.allclose(B2, B, atol=1e-9) and notes == []


def test_samples_file_with_images_needs_board_and_camera(tmp_path):
    p = write_yaml(tmp_path / "s.yaml", {"samples": [{"T_base_tcp": _pose(np.eye(4)), "image": "a.png"}]})
    with pytest.raises(CalibrationFileError, match="need both 'board' and 'camera'"):
        load_samples_yaml(p)
    p = write_yaml(tmp_path / "s2.yaml", {"samples": [{"T_base_tcp": _pose(np.eye(4))}]})
    with pytest.raises(CalibrationFileError) as e:
        load_samples_yaml(p)
    assert e.value.field == "samples.0"


def test_hand_eye_from_rendered_board_images(tmp_path, K, board):
    """The full path: photos of a board from arm poses -> board poses -> T_tcp_cam."""
    import cv2

    from calibration.intrinsics import CameraIntrinsics, save_board_yaml, save_camera_yaml

    from .conftest import H, W

    w, h = board.squares_x * board.square_size_m, board.squares_y * board.square_size_m
    A, B = S.hand_eye_poses(
        10,
        X_TRUE,
        T_BASE_BOARD,
        (w / 2, h / 2, 0.0),
        distance_range_m=(0.35, 0.45),
        lateral_m=0.1,
        roll_rad=0.4,
        seed=7,
    )
    A = S.perturb_poses(A, 1e-4, np.radians(0.02), seed=8)
    save_board_yaml(tmp_path / "board.yaml", board)
    save_camera_yaml(tmp_path / "cam.yaml", CameraIntrinsics(K, np.zeros(5), W, H))
    samples = []
    for i, (a, b) in enumerate(zip(A, B)):
        img = S.degrade(S.render_planes([S.board_plane(board.cv_board(), b)], K, W, H), 0.6, 2.0, seed=i)
        cv2.imwrite(str(tmp_path / f"v{i}.png"), img[..., ::-1])
        samples.append({"T_base_tcp": _pose(a), "image": f"v{i}.png"})
    p = write_yaml(tmp_path / "samples.yaml", {"board": "board.yaml", "camera": "cam.yaml", "samples": samples})
    A2, B2, notes = load_samples_yaml(p)
    assert len(A2) == 10 and all("board at" in n for n in notes)
    dt, dr = _err(solve_hand_eye(A2, B2).T_tcp_cam)
    assert dt < 0.002 and dr < 0.5


def test_samples_file_with_a_missing_or_wrong_size_image_names_the_sample(tmp_path, K, board):
    import cv2

    from calibration.intrinsics import CameraIntrinsics, save_board_yaml, save_camera_yaml

    save_board_yaml(tmp_path / "board.yaml", board)
    save_camera_yaml(tmp_path / "cam.yaml", CameraIntrinsics(K, np.zeros(5), 640, 480))
    cv2.imwrite(str(tmp_path / "small.png"), np.zeros((100, 120), np.uint8))
    for image, msg in (("gone.png", "samples.0.image: no such file"), ("small.png", "samples.0.image: .*120x100")):
        p = write_yaml(
            tmp_path / "s.yaml",
            {
                "board": "board.yaml",
                "camera": "cam.yaml",
                "samples": [{"T_base_tcp": _pose(np.eye(4)), "image": image}],
            },
        )
        with pytest.raises(CalibrationError, match=msg):
            load_samples_yaml(p)
