"""Camera intrinsics: the ChArUco board, calibration from board images, and the camera YAML file.

Calibration detects ChArUco corners (``cv2.aruco.CharucoDetector``), rejects images that are
blurred (edge blur measured at the corners), too sparse or of another size (saying which and why), runs ``calibrateCameraExtended``
and reports the per-image and overall RMS reprojection error in pixels. Images whose error is far
above the rest (a mis-detection, motion blur) are rejected in a second pass.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal, Sequence

import numpy as np
from pydantic import Field, field_validator, model_validator

from calibration.errors import CalibrationError
from calibration.io import Strict, load_model, write_yaml

__all__ = [
    "BoardSpec",
    "CameraIntrinsics",
    "ImageReport",
    "IntrinsicsResult",
    "CalibrationOptions",
    "to_gray",
    "blur_sigma_px",
    "detect_charuco",
    "estimate_board_pose",
    "calibrate_intrinsics",
    "load_camera_yaml",
    "save_camera_yaml",
    "load_board_yaml",
    "save_board_yaml",
]

ARUCO_DICTS = {
    "4X4_50": "DICT_4X4_50", "4X4_100": "DICT_4X4_100", "4X4_250": "DICT_4X4_250",
    "5X5_50": "DICT_5X5_50", "5X5_100": "DICT_5X5_100", "5X5_250": "DICT_5X5_250",
    "6X6_50": "DICT_6X6_50", "6X6_100": "DICT_6X6_100", "6X6_250": "DICT_6X6_250",
}


class BoardSpec(Strict):
    """A ChArUco board. Defaults fit A4 landscape at true scale (240 x 180 mm)."""

    squares_x: Annotated[int, Field(ge=3, le=40)] = 8
    squares_y: Annotated[int, Field(ge=3, le=40)] = 6
    square_size_m: Annotated[float, Field(gt=0.0, le=1.0)] = 0.030
    marker_size_m: Annotated[float, Field(gt=0.0, le=1.0)] = 0.022
    dictionary: Literal[tuple(ARUCO_DICTS)] = "5X5_100"  # type: ignore[valid-type]
    # Boards made by OpenCV < 4.6 with an even number of rows start with a marker in the other
    # colour; set true for those or the detector finds no corners.
    legacy_pattern: bool = False

    @model_validator(mode="after")
    def _marker_fits(self):
        if self.marker_size_m >= self.square_size_m:
            raise ValueError("marker_size_m must be smaller than square_size_m")
        import cv2

        n = (self.squares_x * self.squares_y) // 2
        if n > cv2.aruco.getPredefinedDictionary(self.dictionary_id).bytesList.shape[0]:
            raise ValueError(f"a {self.squares_x}x{self.squares_y} board needs {n} markers; dictionary {self.dictionary} is too small")
        return self

    @property
    def dictionary_id(self) -> int:
        import cv2

        return getattr(cv2.aruco, ARUCO_DICTS[self.dictionary])

    def cv_board(self):
        """The ``cv2.aruco.CharucoBoard``."""
        import cv2

        d = cv2.aruco.getPredefinedDictionary(self.dictionary_id)
        board = cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_size_m, self.marker_size_m, d)
        board.setLegacyPattern(self.legacy_pattern)
        return board

    @property
    def n_corners(self) -> int:
        return (self.squares_x - 1) * (self.squares_y - 1)


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole + OpenCV distortion. K: (3, 3) px; dist: (n,) (k1, k2, p1, p2[, k3, ...]); size in px."""

    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int
    rms_px: float | None = None

    def __post_init__(self):
        K = np.asarray(self.K, dtype=np.float64)
        dist = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise ValueError(f"K: expected a finite 3x3 matrix, got shape {K.shape}")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or K[0, 1] != 0 or np.any(K[2] != [0, 0, 1]) or K[1, 0] != 0:
            raise ValueError("K: expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
        if dist.size not in (0, 4, 5, 8, 12, 14) or not np.all(np.isfinite(dist)):
            raise ValueError(f"dist: expected 0, 4, 5, 8, 12 or 14 finite coefficients, got {dist.size}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError("width/height must be positive")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)

    def project(self, points_cam) -> np.ndarray:
        """Pixels ``(N, 2)`` of camera-frame points ``(N, 3)`` m, with distortion."""
        import cv2

        pts = np.asarray(points_cam, dtype=np.float64).reshape(-1, 1, 3)
        px, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), self.K, self.dist)
        return px.reshape(-1, 2)


@dataclass(frozen=True)
class ImageReport:
    """What happened to one calibration image."""

    name: str
    accepted: bool
    reason: str = ""
    n_corners: int = 0
    blur_px: float = float("nan")
    reprojection_rms_px: float = float("nan")


@dataclass(frozen=True)
class IntrinsicsResult:
    camera: CameraIntrinsics
    rms_px: float
    images: tuple[ImageReport, ...]
    T_cam_board: np.ndarray = field(repr=False)  # (n_accepted, 4, 4), in the order of accepted images

    @property
    def rejected(self) -> tuple[ImageReport, ...]:
        return tuple(r for r in self.images if not r.accepted)


class CalibrationOptions(Strict):
    min_corners: Annotated[int, Field(ge=6)] = 12
    max_blur_px: Annotated[float, Field(gt=0.0)] = 1.5  # edge blur std at the board corners (see blur_sigma_px)
    min_images: Annotated[int, Field(ge=3)] = 5
    outlier_factor: Annotated[float, Field(gt=1.0)] = 3.0  # per-image RMS > factor * median -> rejected
    fix_k3: bool = True  # k3 is poorly determined without strong distortion and wide coverage
    zero_tangential: bool = False


def to_gray(image) -> np.ndarray:
    """A 2D uint8 view of ``image``: (H, W), (H, W, 1|3|4) RGB(A), any integer or float dtype.

    Floats are taken as 0..1 (if their max is <= 1) or 0..255; uint16 is scaled down.
    Raises ValueError (naming ``image``) only for arrays that are not images at all.
    """
    import cv2

    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (3, 4)) or min(a.shape[:2]) < 1:
        raise ValueError(f"image: expected (H, W) or (H, W, 3|4), got shape {a.shape}")
    if a.dtype != np.uint8:
        f = a.astype(np.float64)
        f = np.nan_to_num(f, nan=0.0, posinf=0.0, neginf=0.0)
        if a.dtype == np.uint16:
            f = f / 257.0
        elif a.dtype.kind == "f" and f.size and f.max() <= 1.0:
            f = f * 255.0
        a = np.clip(np.rint(f), 0, 255).astype(np.uint8)
    if a.ndim == 3:
        a = cv2.cvtColor(a, cv2.COLOR_RGBA2GRAY if a.shape[2] == 4 else cv2.COLOR_RGB2GRAY)
    return np.ascontiguousarray(a)


def blur_sigma_px(gray: np.ndarray, corners_px: np.ndarray, half_px: int = 6) -> float:
    """Estimated Gaussian blur (px) of the edges around ``corners_px: (N, 2)``; NaN if none is measurable.

    For a step edge of contrast C blurred by a Gaussian of std s, the peak gradient is
    C / (s sqrt(2 pi)); so s = C / (sqrt(2 pi) max|grad I|) per corner patch, median over corners.
    It measures focus and motion blur independently of contrast, exposure and noise level (a sharp
    render gives about 0.8 px: the pixel footprint itself).
    """
    import cv2

    g = gray.astype(np.float32)
    # 3x3 Sobel responds 8x to a unit-slope ramp.
    mag = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)) / 8.0
    r = half_px
    out = []
    for x, y in np.asarray(corners_px, dtype=np.float64).reshape(-1, 2):
        x0, y0 = int(round(x)) - r, int(round(y)) - r
        if x0 < 0 or y0 < 0 or x0 + 2 * r + 1 > g.shape[1] or y0 + 2 * r + 1 > g.shape[0]:
            continue
        patch = g[y0 : y0 + 2 * r + 1, x0 : x0 + 2 * r + 1]
        contrast = float(np.percentile(patch, 95) - np.percentile(patch, 5))
        peak = float(mag[y0 : y0 + 2 * r + 1, x0 : x0 + 2 * r + 1].max())
        if contrast >= 20.0 and peak > 0:
            out.append(contrast / (peak * np.sqrt(2.0 * np.pi)))
    return float(np.median(out)) if out else float("nan")


def detect_charuco(gray: np.ndarray, board: BoardSpec):
    """ChArUco corners of ``board`` in ``gray`` -> (corners_px (N, 2), ids (N,)); empty arrays if none."""
    import cv2

    cb = board.cv_board()
    det = cv2.aruco.CharucoDetector(cb)
    try:
        corners, ids, _, _ = det.detectBoard(gray)
    except cv2.error:
        corners, ids = None, None
    if corners is None or ids is None or len(ids) == 0:
        return np.zeros((0, 2)), np.zeros((0,), dtype=np.int64)
    return corners.reshape(-1, 2).astype(np.float64), ids.reshape(-1).astype(np.int64)


def _object_points(board: BoardSpec, ids: np.ndarray) -> np.ndarray:
    return np.asarray(board.cv_board().getChessboardCorners(), dtype=np.float64)[ids]


def _collinear(points: np.ndarray, tol: float = 1e-3) -> bool:
    if len(points) < 3:
        return True
    c = points - points.mean(0)
    s = np.linalg.svd(c, compute_uv=False)
    return s[1] <= tol * max(s[0], 1e-12)


def estimate_board_pose(gray: np.ndarray, board: BoardSpec, camera: CameraIntrinsics, min_corners: int = 6):
    """``(T_cam_board (4, 4), rms_px, n_corners)`` from one image, or ``None`` if the board is not usable.

    The board frame is OpenCV's: origin at the top-left board corner, +x right, +y down the printed
    board, +z into the board.
    """
    import cv2

    corners, ids = detect_charuco(gray, board)
    if len(ids) < min_corners:
        return None
    obj = _object_points(board, ids)
    if _collinear(obj[:, :2]):
        return None
    ok, rvec, tvec = cv2.solvePnP(obj, corners, camera.K, camera.dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj, corners, camera.K, camera.dist, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, camera.K, camera.dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - corners) ** 2, -1))))
    from sim.geometry import make_T, so3_exp

    return make_T(so3_exp(rvec.reshape(3)), tvec.reshape(3)), rms, len(ids)


def calibrate_intrinsics(images: Sequence, board: BoardSpec, names: Sequence[str] | None = None,
                         options: CalibrationOptions | None = None) -> IntrinsicsResult:
    """Calibrate from ChArUco ``images`` (arrays, any layout :func:`to_gray` accepts).

    Raises :class:`CalibrationError` if fewer than ``options.min_images`` images survive; the
    message lists every rejected image with its reason.
    """
    import cv2

    opt = options or CalibrationOptions()
    names = list(names) if names is not None else [f"image {i}" for i in range(len(images))]
    if len(names) != len(images):
        raise ValueError("names: must have one entry per image")
    reports: dict[int, ImageReport] = {}
    views = []  # (index, obj (N, 3), img (N, 2))
    size = None
    for i, (img, name) in enumerate(zip(images, names)):
        gray = to_gray(img)
        if size is None:
            size = gray.shape[::-1]
        if gray.shape[::-1] != size:
            reports[i] = ImageReport(name, False, f"size {gray.shape[1]}x{gray.shape[0]} differs from the first image's {size[0]}x{size[1]}")
            continue
        corners, ids = detect_charuco(gray, board)
        if len(ids) < opt.min_corners:
            reports[i] = ImageReport(name, False, f"too few corners ({len(ids)} < {opt.min_corners})", len(ids))
            continue
        blur = blur_sigma_px(gray, corners)
        if not blur <= opt.max_blur_px:  # NaN (no measurable edge) is rejected too
            reports[i] = ImageReport(name, False, f"blurred (edge blur {blur:.2f} px > {opt.max_blur_px:g} px)", len(ids), blur)
            continue
        obj = _object_points(board, ids)
        if _collinear(obj[:, :2]):
            reports[i] = ImageReport(name, False, "corners lie on one line", len(ids), blur)
            continue
        views.append((i, obj.astype(np.float32), corners.astype(np.float32)))
        reports[i] = ImageReport(name, True, "", len(ids), blur)

    flags = (cv2.CALIB_FIX_K3 if opt.fix_k3 else 0) | (cv2.CALIB_ZERO_TANGENT_DIST if opt.zero_tangential else 0)

    def _fail(n_ok: int):
        listing = "; ".join(f"{r.name}: {r.reason}" for r in (reports[k] for k in sorted(reports)) if not r.accepted)
        raise CalibrationError(
            f"intrinsics: only {n_ok} usable image(s), need at least {opt.min_images}. "
            f"Rejected: {listing or 'none'}. Take more sharp photos with the whole board in view, at varied tilts."
        )

    for _ in range(2):  # second pass only if outliers were dropped
        if len(views) < opt.min_images:
            _fail(len(views))
        rms, K, dist, rvecs, tvecs, _, _, per_view = cv2.calibrateCameraExtended(
            [v[1] for v in views], [v[2] for v in views], size, None, None, flags=flags)
        per_view = np.asarray(per_view).reshape(-1)
        med = float(np.median(per_view))
        bad = [k for k, e in enumerate(per_view) if e > opt.outlier_factor * max(med, 0.05)]
        if not bad:
            break
        for k in bad:
            i = views[k][0]
            r = reports[i]
            reports[i] = ImageReport(r.name, False, f"reprojection error {per_view[k]:.2f} px > {opt.outlier_factor:g} x median {med:.2f} px",
                                     r.n_corners, r.blur_px, float(per_view[k]))
        views = [v for k, v in enumerate(views) if k not in bad]
    for k, v in enumerate(views):
        r = reports[v[0]]
        reports[v[0]] = ImageReport(r.name, True, "", r.n_corners, r.blur_px, float(per_view[k]))

    from sim.geometry import make_T, so3_exp

    T = make_T(so3_exp(np.stack([np.asarray(r).reshape(3) for r in rvecs])), np.stack([np.asarray(t).reshape(3) for t in tvecs]))
    cam = CameraIntrinsics(K, np.asarray(dist).reshape(-1)[:5], int(size[0]), int(size[1]), float(rms))
    return IntrinsicsResult(cam, float(rms), tuple(reports[k] for k in range(len(images))), T)


# ---- files ---------------------------------------------------------------------------------

class _CameraFile(Strict):
    width: Annotated[int, Field(gt=0)]
    height: Annotated[int, Field(gt=0)]
    K: tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]
    dist: tuple[float, ...] = ()
    rms_px: Annotated[float, Field(ge=0.0)] | None = None
    model: Literal["opencv_pinhole"] = "opencv_pinhole"
    image_reprojection_rms_px: dict[str, float] | None = None

    @field_validator("K")
    @classmethod
    def _k(cls, K):
        k = np.asarray(K, dtype=np.float64)
        if not np.all(np.isfinite(k)):
            raise ValueError("must be finite")
        if k[0, 0] <= 0 or k[1, 1] <= 0:
            raise ValueError("fx (K[0][0]) and fy (K[1][1]) must be positive")
        if k[0, 1] != 0 or k[1, 0] != 0 or tuple(k[2]) != (0.0, 0.0, 1.0):
            raise ValueError("must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]")
        return K

    @field_validator("dist")
    @classmethod
    def _dist(cls, d):
        if len(d) not in (0, 4, 5, 8, 12, 14):
            raise ValueError(f"expected 0, 4, 5, 8, 12 or 14 coefficients, got {len(d)}")
        if not all(np.isfinite(d)):
            raise ValueError("must be finite")
        return d

    @model_validator(mode="after")
    def _pp_inside(self):
        cx, cy = self.K[0][2], self.K[1][2]
        if not (0 <= cx <= self.width and 0 <= cy <= self.height):
            raise ValueError(f"principal point ({cx:g}, {cy:g}) lies outside the {self.width}x{self.height} image")
        return self


def save_camera_yaml(path, camera: CameraIntrinsics, images: Sequence[ImageReport] = ()) -> Path:
    """Write ``camera`` (and per-image reprojection RMS of accepted images) to ``path``."""
    data = {
        "model": "opencv_pinhole",
        "width": int(camera.width),
        "height": int(camera.height),
        "K": [[float(x) for x in row] for row in camera.K],
        "dist": [float(x) for x in camera.dist],
        "rms_px": None if camera.rms_px is None else float(camera.rms_px),
    }
    per = {r.name: float(r.reprojection_rms_px) for r in images if r.accepted}
    if per:
        data["image_reprojection_rms_px"] = per
    return write_yaml(path, data, header="Camera intrinsics (OpenCV pinhole; K in px, dist = k1 k2 p1 p2 k3)")


def load_camera_yaml(path) -> CameraIntrinsics:
    """The :class:`CameraIntrinsics` in ``path``; a :class:`CalibrationFileError` names the file and field."""
    m = load_model(path, _CameraFile)
    return CameraIntrinsics(np.asarray(m.K), np.asarray(m.dist), m.width, m.height, m.rms_px)


def save_board_yaml(path, board: BoardSpec) -> Path:
    return write_yaml(path, board.model_dump(), header="ChArUco board (sizes in metres as printed)")


def load_board_yaml(path) -> BoardSpec:
    return load_model(path, BoardSpec)
