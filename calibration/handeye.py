"""Eye-in-hand calibration: ``T_tcp_cam`` from arm poses and camera-seen board poses.

Each sample pairs the arm's ``T_base_tcp`` with the board pose ``T_cam_board`` seen at that
moment (AX = XB with A = relative TCP motion, B = relative board motion, X = ``T_tcp_cam``).
``cv2.calibrateHandEye`` solves it; a second method cross-checks the first and their disagreement
is reported. Sets that cannot determine X are refused before solving, with the motion to add:
rotation about one axis alone leaves the translation along that axis free.

Residuals: the board is fixed in the base frame, so ``T_base_board_i = T_base_tcp_i X
T_cam_board_i`` should be one pose; per-sample deviations from their mean are the residuals.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np
from pydantic import Field, model_validator

from calibration.errors import CalibrationError, DegenerateDataError
from calibration.intrinsics import ChessboardSpec, estimate_board_pose, load_board_yaml, load_camera_yaml, to_gray
from calibration.io import PoseModel, Strict, T_to_pose, check_T, load_model, read_image, write_yaml
from sim.geometry import compose, invert_T, make_T, rotation_angle, se3_exp, so3_log

__all__ = [
    "METHODS",
    "HandEyeOptions",
    "DiversityReport",
    "HandEyeResult",
    "check_motion_diversity",
    "solve_hand_eye",
    "refine_hand_eye",
    "mean_pose",
    "save_hand_eye_yaml",
    "load_hand_eye_yaml",
    "HandEyeSample",
    "HandEyeSamplesFile",
    "load_samples_yaml",
]

Method = Literal["tsai", "park", "horaud", "andreff", "daniilidis"]
METHODS = ("tsai", "park", "horaud", "andreff", "daniilidis")


class HandEyeOptions(Strict):
    method: Method = "park"
    check_method: Method = "tsai"
    min_samples: Annotated[int, Field(ge=3)] = 5
    min_rotation_deg: Annotated[float, Field(gt=0.0)] = 10.0  # a relative motion counts if it rotates this much
    min_axis_spread_deg: Annotated[float, Field(gt=0.0, le=90.0)] = 20.0  # between two counted motion axes
    # Refine the primary solution jointly with the board pose over all samples (AX = YB, least
    # squares on absolute poses): pairwise AX = XB solvers amplify noise; this uses each sample once.
    refine: bool = True
    position_sigma_m: Annotated[float, Field(gt=0.0)] = 1e-3  # residual weights for the refinement
    rotation_sigma_deg: Annotated[float, Field(gt=0.0)] = 0.1


@dataclass(frozen=True)
class DiversityReport:
    n_samples: int
    n_rotating_pairs: int
    max_rotation_deg: float
    axis_spread_deg: float  # largest angle between rotation axes of counted motions (sign-free)
    dominant_axis_tcp: np.ndarray  # (3,) unit


def _cv_method(name: str) -> int:
    return {
        "tsai": cv2.CALIB_HAND_EYE_TSAI,
        "park": cv2.CALIB_HAND_EYE_PARK,
        "horaud": cv2.CALIB_HAND_EYE_HORAUD,
        "andreff": cv2.CALIB_HAND_EYE_ANDREFF,
        "daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS,
    }[name]


def check_motion_diversity(T_base_tcp, options: HandEyeOptions | None = None) -> DiversityReport:
    """Refuse (``DegenerateDataError``) sample sets that cannot determine ``T_tcp_cam``.

    T_base_tcp: (N, 4, 4). Counts every pair of samples whose relative rotation is at least
    ``min_rotation_deg``; their rotation axes (in the TCP frame) must span at least
    ``min_axis_spread_deg``.
    """
    opt = options or HandEyeOptions()
    T = check_T(T_base_tcp, "T_base_tcp")
    if T.ndim != 3:
        raise ValueError(f"T_base_tcp: expected (N, 4, 4), got {T.shape}")
    n = len(T)
    if n < opt.min_samples:
        raise DegenerateDataError(
            f"hand-eye: {n} sample(s), need at least {opt.min_samples} (10-20 recommended): "
            "add arm poses that each see the whole board, rotating the gripper between them"
        )
    i, j = np.triu_indices(n, 1)
    R_rel = np.swapaxes(T[i, :3, :3], -1, -2) @ T[j, :3, :3]  # A's rotation, in tcp_i axes
    w = so3_log(R_rel)
    ang = np.linalg.norm(w, axis=-1)
    keep = ang >= np.radians(opt.min_rotation_deg)
    max_rot = float(np.degrees(ang.max())) if len(ang) else 0.0
    if keep.sum() < 2:
        raise DegenerateDataError(
            f"hand-eye: the gripper barely rotates between samples (largest relative rotation {max_rot:.1f} deg; "
            f"need pairs rotating >= {opt.min_rotation_deg:g} deg): add poses that rotate the gripper by "
            "20-40 deg about different axes (tilt about TCP x and y, turn about TCP z)"
        )
    axes = w[keep] / ang[keep, None]
    cos = np.clip(np.abs(axes @ axes.T), 0.0, 1.0)
    spread = float(np.degrees(np.arccos(cos.min())))
    # Dominant axis: principal direction of the sign-free axis scatter.
    evals, evecs = np.linalg.eigh((axes[:, :, None] * axes[:, None, :]).mean(0))
    dom = evecs[:, -1]
    if spread < opt.min_axis_spread_deg:
        perp = np.cross(dom, [1.0, 0.0, 0.0] if abs(dom[0]) < 0.9 else [0.0, 1.0, 0.0])
        perp /= np.linalg.norm(perp)
        raise DegenerateDataError(
            f"hand-eye: all rotations are about nearly the same axis (TCP frame {np.round(dom, 2).tolist()}, "
            f"spread {spread:.1f} deg < {opt.min_axis_spread_deg:g} deg), which leaves T_tcp_cam undetermined: "
            f"add poses that rotate the gripper about a perpendicular axis, e.g. {np.round(perp, 2).tolist()} in "
            "the TCP frame"
        )
    return DiversityReport(n, int(keep.sum()), max_rot, spread, dom)


def mean_pose(T) -> np.ndarray:
    """Chordal mean ``(4, 4)`` of poses ``T: (N, 4, 4)`` (mean translation, SVD-projected mean rotation)."""
    T = np.asarray(T, dtype=np.float64)
    U, _, Vt = np.linalg.svd(T[:, :3, :3].mean(0))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return make_T(U @ D @ Vt, T[:, :3, 3].mean(0))


def _solve(T_base_tcp, T_cam_board, method: str) -> np.ndarray:
    R, t = cv2.calibrateHandEye(
        [x[:3, :3] for x in T_base_tcp],
        [x[:3, 3] for x in T_base_tcp],
        [x[:3, :3] for x in T_cam_board],
        [x[:3, 3] for x in T_cam_board],
        method=_cv_method(method),  # keyword: positionally the 5th argument is an output
    )
    X = make_T(np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64).reshape(3))
    if not np.all(np.isfinite(X)):
        raise DegenerateDataError(f"hand-eye: method {method} returned no finite solution; add more diverse poses")
    return X


def _pose_residuals(A, B, X, Y, w_t: float, w_r: float) -> np.ndarray:
    E = compose(invert_T(Y), A, X, B)  # identity when consistent
    return np.concatenate([E[:, :3, 3] * w_t, so3_log(E[:, :3, :3]) * w_r], -1).reshape(-1)


def refine_hand_eye(
    T_base_tcp,
    T_cam_board,
    T_tcp_cam,
    position_sigma_m: float = 1e-3,
    rotation_sigma_rad: float = np.radians(0.1),
    iterations: int = 20,
):
    """Levenberg-Marquardt on ``T_base_board^-1 T_base_tcp_i X T_cam_board_i = I`` over X and the board pose.

    Residuals are weighted by ``1/position_sigma_m`` and ``1/rotation_sigma_rad``. Returns
    ``(T_tcp_cam, T_base_board)``.
    """
    A = np.asarray(T_base_tcp, dtype=np.float64)
    B = np.asarray(T_cam_board, dtype=np.float64)
    X = np.asarray(T_tcp_cam, dtype=np.float64)
    Y = mean_pose(compose(A, X, B))
    w_t, w_r = 1.0 / position_sigma_m, 1.0 / rotation_sigma_rad
    r = _pose_residuals(A, B, X, Y, w_t, w_r)
    lam, eps = 1e-3, 1e-7
    for _ in range(iterations):
        J = np.zeros((r.size, 12))
        for k in range(12):
            d = np.zeros(12)
            d[k] = eps
            J[:, k] = (_pose_residuals(A, B, X @ se3_exp(d[:6]), Y @ se3_exp(d[6:]), w_t, w_r) - r) / eps
        H, g = J.T @ J, J.T @ r
        while True:
            step = -np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), g)
            Xn, Yn = X @ se3_exp(step[:6]), Y @ se3_exp(step[6:])
            rn = _pose_residuals(A, B, Xn, Yn, w_t, w_r)
            if rn @ rn < r @ r:
                X, Y, r, lam = Xn, Yn, rn, lam * 0.3
                break
            lam *= 10.0
            if lam > 1e8:
                return X, Y
        if np.abs(step).max() < 1e-10:
            break
    return X, Y


def _residuals(T_base_tcp, T_cam_board, X):
    T_base_board = compose(T_base_tcp, X, T_cam_board)
    M = mean_pose(T_base_board)
    pos = np.linalg.norm(T_base_board[:, :3, 3] - M[:3, 3], axis=-1)
    rot = np.degrees(rotation_angle(T_base_board[:, :3, :3], M[:3, :3]))
    return M, pos, rot


@dataclass(frozen=True)
class HandEyeResult:
    """``T_tcp_cam`` by ``method``; the cross-check by ``check_method`` and how far apart the two
    OpenCV solvers land (before any refinement).

    residual_position_m / residual_rotation_deg: (N,) per-sample deviation of the implied board
    pose in the base frame from its mean. T_base_board: that mean.
    """

    T_tcp_cam: np.ndarray
    method: str
    T_tcp_cam_check: np.ndarray
    check_method: str
    disagreement_m: float
    disagreement_deg: float
    residual_position_m: np.ndarray
    residual_rotation_deg: np.ndarray
    T_base_board: np.ndarray
    diversity: DiversityReport

    @property
    def rms_position_m(self) -> float:
        return float(np.sqrt(np.mean(self.residual_position_m**2)))

    @property
    def rms_rotation_deg(self) -> float:
        return float(np.sqrt(np.mean(self.residual_rotation_deg**2)))

    def summary(self) -> str:
        return (
            f"T_tcp_cam ({self.method}): t = {np.round(self.T_tcp_cam[:3, 3] * 1000, 2).tolist()} mm, "
            f"rotvec = {np.round(so3_log(self.T_tcp_cam[:3, :3]), 4).tolist()} rad\n"
            f"{self.method.split('+')[0]} vs {self.check_method}: {self.disagreement_m * 1000:.2f} mm, "
            f"{self.disagreement_deg:.3f} deg\n"
            f"residuals over {len(self.residual_position_m)} samples: RMS {self.rms_position_m * 1000:.2f} mm, "
            f"{self.rms_rotation_deg:.3f} deg (max {self.residual_position_m.max() * 1000:.2f} mm, "
            f"{self.residual_rotation_deg.max():.3f} deg)"
        )


def solve_hand_eye(T_base_tcp, T_cam_board, options: HandEyeOptions | None = None) -> HandEyeResult:
    """Eye-in-hand ``T_tcp_cam`` from ``T_base_tcp: (N, 4, 4)`` and ``T_cam_board: (N, 4, 4)``."""
    opt = options or HandEyeOptions()
    A = check_T(T_base_tcp, "T_base_tcp")
    B = check_T(T_cam_board, "T_cam_board")
    if A.ndim != 3 or B.shape != A.shape:
        raise ValueError(f"T_base_tcp {A.shape} and T_cam_board {B.shape}: expected two (N, 4, 4) arrays of equal N")
    div = check_motion_diversity(A, opt)
    X = _solve(A, B, opt.method)
    Xc = _solve(A, B, opt.check_method)
    dis_m = float(np.linalg.norm(X[:3, 3] - Xc[:3, 3]))
    dis_deg = float(np.degrees(rotation_angle(X[:3, :3], Xc[:3, :3])))
    method = opt.method
    if opt.refine:
        X, _ = refine_hand_eye(A, B, X, opt.position_sigma_m, np.radians(opt.rotation_sigma_deg))
        method = f"{opt.method}+refine"
    M, pos, rot = _residuals(A, B, X)
    return HandEyeResult(X, method, Xc, opt.check_method, dis_m, dis_deg, pos, rot, M, div)


# ---- files ---------------------------------------------------------------------------------


class _HandEyeFile(Strict):
    T_tcp_cam: PoseModel
    method: str | None = None
    check_method: Method | None = None
    disagreement_mm: float | None = None
    disagreement_deg: float | None = None
    residual_rms_mm: float | None = None
    residual_rms_deg: float | None = None
    n_samples: int | None = None


def save_hand_eye_yaml(path, result: HandEyeResult) -> Path:
    p = T_to_pose(result.T_tcp_cam)
    data = {
        "T_tcp_cam": {"translation_m": list(p.translation_m), "rotvec_rad": list(p.rotvec_rad)},
        "method": result.method,
        "check_method": result.check_method,
        "disagreement_mm": round(result.disagreement_m * 1000, 4),
        "disagreement_deg": round(result.disagreement_deg, 5),
        "residual_rms_mm": round(result.rms_position_m * 1000, 4),
        "residual_rms_deg": round(result.rms_rotation_deg, 5),
        "n_samples": int(len(result.residual_position_m)),
    }
    return write_yaml(path, data, header="Eye-in-hand calibration: camera (OpenCV frame) in the TCP frame")


def load_hand_eye_yaml(path) -> np.ndarray:
    """``T_tcp_cam`` (4, 4) from ``path``; a :class:`CalibrationFileError` names the file and field."""
    return load_model(path, _HandEyeFile).T_tcp_cam.T


class HandEyeSample(Strict):
    """One arm pose plus either a photo of the board or the board pose seen in it."""

    T_base_tcp: PoseModel
    image: str | None = None
    T_cam_board: PoseModel | None = None

    @model_validator(mode="after")
    def _one_source(self):
        if (self.image is None) == (self.T_cam_board is None):
            raise ValueError("give exactly one of image or T_cam_board")
        return self


class HandEyeSamplesFile(Strict):
    """``samples.yaml``: board and camera files (needed when samples carry images), then samples.

    Relative paths are relative to the samples file.
    """

    board: str | None = None
    camera: str | None = None
    samples: list[HandEyeSample]

    @model_validator(mode="after")
    def _files_for_images(self):
        if any(s.image for s in self.samples) and (self.board is None or self.camera is None):
            raise ValueError("samples with images need both 'board' and 'camera' files")
        return self


def load_samples_yaml(path, min_board_corners: int = 8):
    """``(T_base_tcp (N, 4, 4), T_cam_board (N, 4, 4), notes)`` from a samples file.

    Image samples are posed with the board and camera files; an image where the board is not found
    is skipped and listed in ``notes`` (it is not an error unless too few samples remain).
    """
    path = Path(path)
    f = load_model(path, HandEyeSamplesFile)
    root = path.parent
    board = load_board_yaml(root / f.board) if f.board else None

    if isinstance(board, ChessboardSpec) and board.inner_cols % 2 == board.inner_rows % 2:
        # Turned by 180 deg such a board looks the same, so its detected origin can jump between
        # samples and T_cam_board with it; hand-eye needs a pose that is the board's own.
        raise CalibrationError(
            f"{path}: board: a {board.inner_cols}x{board.inner_rows} chessboard looks the same turned by 180 deg, "
            "so its pose is ambiguous; use a ChArUco board, or a chessboard with one odd and one even count "
            "of inner corners (e.g. 9x6)"
        )
    camera = load_camera_yaml(root / f.camera) if f.camera else None
    A, B, notes = [], [], []
    for k, s in enumerate(f.samples):
        if s.T_cam_board is not None:
            A.append(s.T_base_tcp.T)
            B.append(s.T_cam_board.T)
            continue
        img_path = root / s.image
        if not img_path.is_file():
            raise CalibrationError(f"{path}: samples.{k}.image: no such file {img_path}")
        gray = to_gray(read_image(img_path))
        if gray.shape != (camera.height, camera.width):
            raise CalibrationError(
                f"{path}: samples.{k}.image: {img_path} is {gray.shape[1]}x{gray.shape[0]}, "
                f"the camera file is for {camera.width}x{camera.height}"
            )
        pose = estimate_board_pose(gray, board, camera, min_board_corners)
        if pose is None:
            notes.append(f"samples.{k} ({s.image}): board not found (fewer than {min_board_corners} corners); skipped")
            continue
        A.append(s.T_base_tcp.T)
        B.append(pose[0])
        notes.append(f"samples.{k} ({s.image}): board at {pose[1]:.2f} px RMS from {pose[2]} corners")
    return np.asarray(A).reshape(-1, 4, 4), np.asarray(B).reshape(-1, 4, 4), notes
