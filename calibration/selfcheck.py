"""End-to-end accuracy checks on synthetic renders with known ground truth.

Each function renders (or simulates) a calibration scenario, runs the real pipeline on it and
returns the errors against ground truth. ``advobj calibrate selfcheck`` runs them small and
``benchmarks/bench_calibration.py`` runs them large; neither hard-codes an expected result.
"""

from __future__ import annotations

import numpy as np

from calibration import synthetic as S
from calibration.apriltag import detect_tags
from calibration.handeye import HandEyeOptions, solve_hand_eye
from calibration.intrinsics import BoardSpec, CameraIntrinsics, calibrate_intrinsics, estimate_board_pose, to_gray
from sim.geometry import make_T, rotation_angle, so3_exp

__all__ = ["intrinsics_check", "tag_check", "handeye_check", "handeye_images_check"]


def _board_views(board, n: int, seed: int, distance_range_m=(0.3, 0.45), max_tilt_deg: float = 40.0):
    """``T_cam_board: (n, 4, 4)`` with the printed face toward the camera, board centre near the
    optical axis; ``board`` is a ChArUco ``BoardSpec`` or a ``ChessboardSpec``."""
    if hasattr(board, "inner_cols"):  # a chessboard's frame starts at its first inner corner
        w, h = (board.inner_cols - 1) * board.square_size_m, (board.inner_rows - 1) * board.square_size_m
    else:
        w, h = board.squares_x * board.square_size_m, board.squares_y * board.square_size_m
    centre = make_T(np.eye(3), [-w / 2, -h / 2, 0.0])
    face = np.diag([1.0, -1.0, -1.0, 1.0])  # camera_facing gives a tag-like frame (+z out); the board's +z is into it
    return np.stack([T @ face @ centre for T in S.random_view_poses(n, distance_range_m, max_tilt_deg, seed)])


def intrinsics_check(
    n_images: int = 12,
    width: int = 640,
    height: int = 480,
    blur_px: float = 0.6,
    noise: float = 2.0,
    dist=(-0.08, 0.03, 0.0, 0.0, 0.0),
    seed: int = 0,
) -> dict:
    """Calibrate from ``n_images`` rendered ChArUco views; relative errors (%) of fx, fy, cx, cy."""
    board = BoardSpec()
    K = S.default_K(width, height)
    cb = board.cv_board()
    imgs = []
    for i, T in enumerate(_board_views(board, n_images, seed)):
        img = S.render_planes([S.board_plane(cb, T)], K, width, height)
        imgs.append(S.degrade(S.distort_image(img, K, np.asarray(dist)), blur_px, noise, seed=seed * 1000 + i))
    res = calibrate_intrinsics(imgs, board)
    Kh = res.camera.K
    f = 0.5 * (K[0, 0] + K[1, 1])
    err = {
        "fx_pct": 100 * abs(Kh[0, 0] - K[0, 0]) / K[0, 0],
        "fy_pct": 100 * abs(Kh[1, 1] - K[1, 1]) / K[1, 1],
        "cx_pct_of_f": 100 * abs(Kh[0, 2] - K[0, 2]) / f,
        "cy_pct_of_f": 100 * abs(Kh[1, 2] - K[1, 2]) / f,
    }
    err["max_pct"] = max(err.values())
    err.update(
        rms_px=res.rms_px, n_used=sum(r.accepted for r in res.images), k1=float(res.camera.dist[0]), k1_true=dist[0]
    )
    return err


def tag_check(
    distance_m: float = 0.5,
    tilt_deg: float = 0.0,
    tag_size_m: float = 0.04,
    n: int = 10,
    width: int = 640,
    height: int = 480,
    blur_px: float = 0.7,
    noise: float = 2.0,
    seed: int = 0,
) -> dict:
    """Single-tag pose errors over ``n`` renders at ``distance_m`` and ``tilt_deg`` (random tilt axis, roll, offset)."""
    K = S.default_K(width, height)
    cam = CameraIntrinsics(K, np.zeros(5), width, height)
    pos, rot, flagged, missed = [], [], 0, 0
    for s in range(n):
        rng = np.random.default_rng(seed * 7919 + s)
        a = rng.uniform(0, np.pi)
        T = S.camera_facing(
            distance_m,
            np.radians(tilt_deg),
            (np.cos(a), np.sin(a), 0.0),
            rng.uniform(-0.5, 0.5),
            rng.uniform(-0.04, 0.04, 2),
        )
        img = S.degrade(S.render_planes([S.tag_plane(7, tag_size_m, T)], K, width, height), blur_px, noise, seed=s)
        det = [d for d in detect_tags(img, cam, tag_size_m) if d.tag_id == 7]
        if not det:
            missed += 1
            continue
        d = det[0]
        flagged += bool(d.flags)
        pos.append(np.linalg.norm(d.T_cam_tag[:3, 3] - T[:3, 3]))
        rot.append(np.degrees(rotation_angle(d.T_cam_tag[:3, :3], T[:3, :3])))
    pos, rot = np.asarray(pos), np.asarray(rot)
    return {
        "n": n,
        "detected": len(pos),
        "flagged": flagged,
        "missed": missed,
        "position_mm_median": float(np.median(pos) * 1000) if len(pos) else float("nan"),
        "position_mm_max": float(pos.max() * 1000) if len(pos) else float("nan"),
        "orientation_deg_median": float(np.median(rot)) if len(rot) else float("nan"),
        "orientation_deg_max": float(rot.max()) if len(rot) else float("nan"),
    }


def handeye_check(
    n_samples: int = 15,
    tcp_noise=(1e-4, 0.02),
    board_noise=(5e-4, 0.1),
    seed: int = 0,
    options: HandEyeOptions | None = None,
) -> dict:
    """Hand-eye error against a known ``T_tcp_cam`` with noisy arm poses (m, deg) and board poses (m, deg)."""
    rng = np.random.default_rng(seed)
    X = make_T(so3_exp(rng.normal(0, 0.2, 3) + [0.0, 0.0, np.pi / 2]), rng.uniform(-0.06, 0.06, 3) + [0.0, 0.0, 0.05])
    T_base_board = make_T(so3_exp([np.pi, 0.0, rng.uniform(-np.pi, np.pi)]), [0.5, rng.uniform(-0.2, 0.2), 0.0])
    A, B = S.hand_eye_poses(n_samples, X, T_base_board, (0.12, 0.09, 0.0), seed=seed)
    A = S.perturb_poses(A, tcp_noise[0], np.radians(tcp_noise[1]), seed=seed + 1)
    B = S.perturb_poses(B, board_noise[0], np.radians(board_noise[1]), seed=seed + 2)
    r = solve_hand_eye(A, B, options)
    return {
        "position_mm": float(np.linalg.norm(r.T_tcp_cam[:3, 3] - X[:3, 3]) * 1000),
        "rotation_deg": float(np.degrees(rotation_angle(r.T_tcp_cam[:3, :3], X[:3, :3]))),
        "check_position_mm": float(np.linalg.norm(r.T_tcp_cam_check[:3, 3] - X[:3, 3]) * 1000),
        "check_rotation_deg": float(np.degrees(rotation_angle(r.T_tcp_cam_check[:3, :3], X[:3, :3]))),
        "methods_disagreement_mm": r.disagreement_m * 1000,
        "methods_disagreement_deg": r.disagreement_deg,
        "residual_rms_mm": r.rms_position_m * 1000,
        "residual_rms_deg": r.rms_rotation_deg,
    }


def handeye_images_check(
    n_samples: int = 12,
    tcp_noise=(1e-4, 0.02),
    width: int = 640,
    height: int = 480,
    seed: int = 0,
    options: HandEyeOptions | None = None,
) -> dict:
    """Hand-eye error when the board poses come from rendered, blurred, noisy board images (not assumed noise)."""
    rng = np.random.default_rng(seed)
    board = BoardSpec()
    K = S.default_K(width, height)
    cam = CameraIntrinsics(K, np.zeros(5), width, height)
    X = make_T(so3_exp(rng.normal(0, 0.2, 3) + [0.0, 0.0, np.pi / 2]), rng.uniform(-0.06, 0.06, 3) + [0.0, 0.0, 0.05])
    T_base_board = make_T(so3_exp([np.pi, 0.0, rng.uniform(-np.pi, np.pi)]), [0.5, rng.uniform(-0.2, 0.2), 0.0])
    centre = (board.squares_x * board.square_size_m / 2, board.squares_y * board.square_size_m / 2, 0.0)
    A, B_true = S.hand_eye_poses(
        n_samples, X, T_base_board, centre, distance_range_m=(0.35, 0.45), lateral_m=0.12, roll_rad=0.5, seed=seed
    )
    A = S.perturb_poses(A, tcp_noise[0], np.radians(tcp_noise[1]), seed=seed + 1)
    cb = board.cv_board()
    keep_A, B = [], []
    for i, (a, b) in enumerate(zip(A, B_true)):
        img = S.degrade(S.render_planes([S.board_plane(cb, b)], K, width, height), 0.7, 2.0, seed=seed * 1000 + i)
        pose = estimate_board_pose(to_gray(img), board, cam)
        if pose is not None:
            keep_A.append(a)
            B.append(pose[0])
    r = solve_hand_eye(np.stack(keep_A), np.stack(B), options)
    return {
        "n_used": len(B),
        "position_mm": float(np.linalg.norm(r.T_tcp_cam[:3, 3] - X[:3, 3]) * 1000),
        "rotation_deg": float(np.degrees(rotation_angle(r.T_tcp_cam[:3, :3], X[:3, :3]))),
        "methods_disagreement_mm": r.disagreement_m * 1000,
        "methods_disagreement_deg": r.disagreement_deg,
    }
