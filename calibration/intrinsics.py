"""Camera intrinsics: the boards, calibration from board images, and the camera file.

Two boards: ChArUco (:class:`BoardSpec`, corners found through their markers, so a partly
visible board still counts) and the plain chessboard (:class:`ChessboardSpec`, counted by inner
corners as OpenCV's ``patternSize``; the whole board must be in view). :func:`identify_board`
tells which one a set of photos shows and names it.

Calibration detects the corners (sub-pixel), rejects images that are blurred (edge blur measured
at the corners), too sparse, of another size or near-duplicates of an earlier view (saying which
and why), runs ``calibrateCameraExtended`` and reports the per-image and overall RMS reprojection
error in pixels, the standard deviations of fx, fy, cx, cy, and how much of the image area and of
the tilt range the views cover, with a warning where the set is weak. Images whose error is far
above the rest (a mis-detection, motion blur) are rejected in a second pass.

Camera files in three formats load alike (:func:`load_camera_yaml`): ours, ROS ``camera_info``
YAML, and OpenCV ``FileStorage`` YAML/JSON; :func:`save_camera_yaml` writes ours or ROS's.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal, Sequence

import numpy as np
from pydantic import Field, ValidationInfo, field_validator, model_validator

from calibration.errors import CalibrationError, CalibrationFileError
from calibration.io import Strict, load_model, nesting_depth, read_bytes, read_yaml, write_yaml
from sim.geometry import make_T, so3_exp

__all__ = [
    "BoardSpec",
    "ChessboardSpec",
    "Board",
    "identify_board",
    "detect_board",
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
    "MAX_IMAGE_PX",
    "FOCAL_RANGE",
    "MAX_DISTORTION",
    "CAMERA_FILE_MAX_BYTES",
    "CAMERA_FILE_MAX_DEPTH",
]

# Bounds of a camera file (every format): a real camera's image, focal length and distortion.
MAX_IMAGE_PX = 16384  # per side
FOCAL_RANGE = (0.05, 100.0)  # fx, fy as multiples of the image width: ~175 deg to ~0.6 deg field of view
MAX_DISTORTION = 1e3  # |coefficient|; calibrated lenses stay well below (a strong fisheye: k ~ 10)
CAMERA_FILE_MAX_BYTES = 2**20  # a camera file is a few kB; OpenCV's with per-view data, tens of kB
CAMERA_FILE_MAX_DEPTH = 32  # levels of nesting (a camera file needs 4); parsers recurse per level
CAMERA_FILE_MAX_BRACKETS = 4096  # [ and { in all: bounds flow nesting however brackets hide in strings

ARUCO_DICTS = {
    "4X4_50": "DICT_4X4_50",
    "4X4_100": "DICT_4X4_100",
    "4X4_250": "DICT_4X4_250",
    "5X5_50": "DICT_5X5_50",
    "5X5_100": "DICT_5X5_100",
    "5X5_250": "DICT_5X5_250",
    "6X6_50": "DICT_6X6_50",
    "6X6_100": "DICT_6X6_100",
    "6X6_250": "DICT_6X6_250",
}


class BoardSpec(Strict):
    """A ChArUco board. Defaults fit A4 landscape at true scale (240 x 180 mm)."""

    kind: Literal["charuco"] = "charuco"
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
        import cv2  # lazy: robot_io start-up (cv2)

        n = (self.squares_x * self.squares_y) // 2
        if n > cv2.aruco.getPredefinedDictionary(self.dictionary_id).bytesList.shape[0]:
            raise ValueError(
                f"a {self.squares_x}x{self.squares_y} board needs {n} markers; dictionary {self.dictionary} "
                "is too small"
            )
        return self

    @property
    def dictionary_id(self) -> int:
        import cv2  # lazy: robot_io start-up (cv2)

        return getattr(cv2.aruco, ARUCO_DICTS[self.dictionary])

    def cv_board(self):
        """The ``cv2.aruco.CharucoBoard``."""
        import cv2  # lazy: robot_io start-up (cv2)

        d = cv2.aruco.getPredefinedDictionary(self.dictionary_id)
        board = cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_size_m, self.marker_size_m, d)
        board.setLegacyPattern(self.legacy_pattern)
        return board

    @property
    def n_corners(self) -> int:
        return (self.squares_x - 1) * (self.squares_y - 1)


class ChessboardSpec(Strict):
    """A plain chessboard, counted by its *inner* corners (OpenCV's ``patternSize``): the classic
    OpenCV sample board of 10 x 7 squares is ``inner_cols=9, inner_rows=6``. The square size sets
    the scale of board poses only; intrinsics do not depend on it."""

    kind: Literal["chessboard"] = "chessboard"
    inner_cols: Annotated[int, Field(ge=3, le=60)] = 9
    inner_rows: Annotated[int, Field(ge=3, le=60)] = 6
    square_size_m: Annotated[float, Field(gt=0.0, le=1.0)] = 0.025

    @property
    def n_corners(self) -> int:
        return self.inner_cols * self.inner_rows

    @property
    def pattern_size(self) -> tuple[int, int]:
        return (self.inner_cols, self.inner_rows)

    def object_points(self) -> np.ndarray:
        """Inner corners ``(rows * cols, 3)`` m in OpenCV's order (row-major, x along a row), z = 0."""
        g = np.mgrid[0 : self.inner_cols, 0 : self.inner_rows].T.reshape(-1, 2).astype(np.float64)
        return np.concatenate([g * self.square_size_m, np.zeros((len(g), 1))], 1)


Board = BoardSpec | ChessboardSpec

# Inner-corner counts of boards people print (OpenCV's samples, ROS camera_calibration, calib.io),
# tried in this order when a plain chessboard's size is not given.
COMMON_CHESSBOARDS = (
    (9, 6),
    (8, 6),
    (7, 6),
    (9, 7),
    (7, 5),
    (8, 5),
    (6, 4),
    (10, 7),
    (11, 8),
    (6, 5),
    (5, 4),
    (11, 7),
    (12, 9),
)


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

    def scaled(self, width: int, height: int) -> "CameraIntrinsics":
        """The same camera at another resolution of the same aspect ratio (a resized image).

        Pixel centres sit at integers, so a pixel edge maps as ``x' = (x + 0.5) s - 0.5``.
        Distortion coefficients act on normalised coordinates and are unchanged.
        """
        if not (0 < width <= MAX_IMAGE_PX and 0 < height <= MAX_IMAGE_PX):
            raise ValueError(f"scaled: {width}x{height}: each side must be 1..{MAX_IMAGE_PX} pixels")
        if width * self.height != height * self.width:
            raise ValueError(f"scaled: {width}x{height} does not have the aspect ratio of {self.width}x{self.height}")
        s = width / self.width
        K = self.K.copy()
        K[0, 0] *= s
        K[1, 1] *= s
        K[0, 2] = (K[0, 2] + 0.5) * s - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * s - 0.5
        return CameraIntrinsics(K, self.dist, int(width), int(height), None if self.rms_px is None else self.rms_px * s)

    def project(self, points_cam) -> np.ndarray:
        """Pixels ``(N, 2)`` of camera-frame points ``(N, 3)`` m, with distortion."""
        import cv2  # lazy: robot_io start-up (cv2)

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
    # 1-sigma uncertainty of fx, fy, cx, cy (px), from calibrateCameraExtended.
    std_px: dict = field(default_factory=dict)
    coverage: float = float("nan")  # fraction of an 8x6 grid of image cells that hold a corner
    tilt_deg: tuple[float, float] = (float("nan"), float("nan"))  # least and most board tilt vs the optical axis
    warnings: tuple[str, ...] = ()

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
    # A view whose corners lie within this mean distance of an accepted view's is a duplicate: it
    # adds no constraint, yet weights that pose as if it had been seen twice.
    duplicate_px: Annotated[float, Field(ge=0.0)] = 2.0
    max_focal_std_pct: Annotated[float, Field(gt=0.0)] = 0.5  # warn when std(fx or fy) / f is above this
    min_coverage: Annotated[float, Field(ge=0.0, le=1.0)] = 0.5  # warn below this image-area coverage
    min_tilt_range_deg: Annotated[float, Field(ge=0.0)] = 20.0  # warn when the views' tilts span less
    # Plain chessboards: cornerSubPix half-window (px); None = min(11, 0.4 x the corner spacing)
    # per image. 11 reproduces OpenCV's sample, whose window outgrows a distant board's squares.
    subpix_half_window_px: Annotated[int, Field(ge=1, le=50)] | None = None


def to_gray(image) -> np.ndarray:
    """A 2D uint8 view of ``image``: (H, W), (H, W, 1|3|4) RGB(A), any integer or float dtype.

    Floats are taken as 0..1 (if their max is <= 1) or 0..255; uint16 is scaled down.
    Raises ValueError (naming ``image``) only for arrays that are not images at all.
    """
    import cv2  # lazy: robot_io start-up (cv2)

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
    import cv2  # lazy: robot_io start-up (cv2)

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
    import cv2  # lazy: robot_io start-up (cv2)

    cb = board.cv_board()
    det = cv2.aruco.CharucoDetector(cb)
    try:
        corners, ids, _, _ = det.detectBoard(gray)
    except cv2.error:
        corners, ids = None, None
    if corners is None or ids is None or len(ids) == 0:
        return np.zeros((0, 2)), np.zeros((0,), dtype=np.int64)
    return corners.reshape(-1, 2).astype(np.float64), ids.reshape(-1).astype(np.int64)


def detect_chessboard(gray: np.ndarray, board: ChessboardSpec, half_window_px: int | None = None):
    """Inner corners of a plain chessboard -> (corners_px (N, 2), ids (N,)) with N = all corners,
    refined to sub-pixel; empty arrays unless the whole pattern is found.

    ``half_window_px``: the ``cornerSubPix`` half-window; None adapts it per image (see below)."""
    import cv2  # lazy: robot_io start-up (cv2)

    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    empty = np.zeros((0, 2)), np.zeros((0,), dtype=np.int64)
    try:
        ok, c = cv2.findChessboardCorners(gray, board.pattern_size, flags=flags | cv2.CALIB_CB_FAST_CHECK)
        if ok:
            c = c.reshape(-1, 2).astype(np.float32)
            # Search half-window: OpenCV's calibration sample's 11 px (renders with known K say a
            # wide window is the more accurate), but under 40 % of the corner spacing, so that a
            # small or distant board's window never reaches the next corner.
            grid = c.reshape(board.inner_rows, board.inner_cols, 2)
            spacing = min(
                np.linalg.norm(np.diff(grid, axis=1), axis=-1).min(),
                np.linalg.norm(np.diff(grid, axis=0), axis=-1).min(),
            )
            win = int(max(2, min(11, 0.4 * spacing))) if half_window_px is None else int(half_window_px)
            crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 1e-3)
            c = cv2.cornerSubPix(gray, c.reshape(-1, 1, 2), (win, win), (-1, -1), crit).reshape(-1, 2)
        else:
            # The sector-based detector finds boards the classic one misses (strong blur, low
            # contrast); its corners are sub-pixel already.
            ok, c = cv2.findChessboardCornersSB(
                gray, board.pattern_size, flags=cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY
            )
            if not ok:
                return empty
            c = c.reshape(-1, 2)
    except cv2.error:
        return empty
    c = np.asarray(c, dtype=np.float64)
    if len(c) != board.n_corners or not np.all(np.isfinite(c)):
        return empty
    return c, np.arange(board.n_corners, dtype=np.int64)


def detect_board(gray: np.ndarray, board: Board, half_window_px: int | None = None):
    """Corners of either board -> (corners_px (N, 2), ids (N,)); empty arrays if none."""
    return (
        detect_chessboard(gray, board, half_window_px)
        if isinstance(board, ChessboardSpec)
        else detect_charuco(gray, board)
    )


def count_aruco_markers(gray: np.ndarray, dictionary: str) -> int:
    """How many markers of an ArUco ``dictionary`` (a key of ``ARUCO_DICTS``) ``gray`` shows."""
    import cv2  # lazy: robot_io start-up (cv2)

    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, ARUCO_DICTS[dictionary]))
    try:
        _, ids, _ = cv2.aruco.ArucoDetector(d, cv2.aruco.DetectorParameters()).detectMarkers(gray)
    except cv2.error:
        return 0
    return 0 if ids is None else len(ids)


def identify_board(
    grays: Sequence[np.ndarray],
    charuco: BoardSpec,
    inner_corners: tuple[int, int] | None = None,
    square_size_m: float | None = None,
    max_images: int = 4,
) -> tuple[Board, str]:
    """Which board the photos show: ``(board, sentence naming it)``, or :class:`CalibrationError`.

    ChArUco markers of ``charuco.dictionary`` -> that board. Markers of another dictionary -> an
    error naming it. Otherwise a plain chessboard of ``inner_corners`` (or of the first common
    size that is found whole) -> a :class:`ChessboardSpec`. Up to ``max_images`` photos are looked at.
    """
    import cv2  # lazy: robot_io start-up (cv2)

    sample = list(grays)[:max_images]
    if any(count_aruco_markers(g, charuco.dictionary) >= 4 for g in sample):
        return (
            charuco,
            f"ChArUco board ({charuco.squares_x}x{charuco.squares_y} squares, dictionary {charuco.dictionary})",
        )
    counts = {
        name: max(count_aruco_markers(g, name) for g in sample) for name in ARUCO_DICTS if name != charuco.dictionary
    }
    best = max(counts.values(), default=0)
    if best >= 4:
        # A smaller dictionary is the start of a larger one (5X5_50 within 5X5_100): name every fit.
        fits = [n for n, c in counts.items() if c == best]
        raise CalibrationError(
            f"board: the photos show ChArUco markers of dictionary {' or '.join(fits)}, not {charuco.dictionary}; "
            f"pass --dictionary {fits[-1] if len(fits) == 1 else fits[0]} or the one printed "
            "(and the board's --squares-x/--squares-y)"
        )
    sizes = [tuple(inner_corners)] if inner_corners else list(COMMON_CHESSBOARDS)
    for cols, rows in sizes:
        for g in sample:
            for pattern in ((cols, rows), (rows, cols)):
                try:
                    ok, _ = cv2.findChessboardCorners(
                        g, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_FAST_CHECK
                    )
                except cv2.error:
                    ok = False
                if ok:
                    spec = ChessboardSpec(
                        inner_cols=pattern[0],
                        inner_rows=pattern[1],
                        **({} if square_size_m is None else {"square_size_m": square_size_m}),
                    )
                    how = "as given" if inner_corners else "found automatically"
                    return spec, f"plain chessboard, {pattern[0]}x{pattern[1]} inner corners ({how})"
    what = f"{inner_corners[0]}x{inner_corners[1]} chessboard" if inner_corners else "chessboard of a common size"
    raise CalibrationError(
        f"board: no ChArUco markers (dictionary {charuco.dictionary}) and no {what} found in "
        f"{len(sample)} photo(s); pass --board chessboard --inner-corners COLSxROWS, or the ChArUco board's options"
    )


def _object_points(board: Board, ids: np.ndarray) -> np.ndarray:
    if isinstance(board, ChessboardSpec):
        return board.object_points()[ids]
    return np.asarray(board.cv_board().getChessboardCorners(), dtype=np.float64)[ids]


def _collinear(points: np.ndarray, tol: float = 1e-3) -> bool:
    if len(points) < 3:
        return True
    c = points - points.mean(0)
    s = np.linalg.svd(c, compute_uv=False)
    return s[1] <= tol * max(s[0], 1e-12)


def estimate_board_pose(gray: np.ndarray, board: Board, camera: CameraIntrinsics, min_corners: int = 6):
    """``(T_cam_board (4, 4), rms_px, n_corners)`` from one image, or ``None`` if the board is not usable.

    The board frame is OpenCV's: origin at the top-left board corner, +x right, +y down the printed
    board, +z into the board.
    """
    import cv2  # lazy: robot_io start-up (cv2)

    corners, ids = detect_board(gray, board)
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

    return make_T(so3_exp(rvec.reshape(3)), tvec.reshape(3)), rms, len(ids)


def calibrate_intrinsics(
    images: Sequence, board: Board, names: Sequence[str] | None = None, options: CalibrationOptions | None = None
) -> IntrinsicsResult:
    """Calibrate from board ``images`` (arrays, any layout :func:`to_gray` accepts).

    Raises :class:`CalibrationError` if fewer than ``options.min_images`` images survive; the
    message lists every rejected image with its reason.
    """
    import cv2  # lazy: robot_io start-up (cv2)

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
            reports[i] = ImageReport(
                name, False, f"size {gray.shape[1]}x{gray.shape[0]} differs from the first image's {size[0]}x{size[1]}"
            )
            continue
        corners, ids = detect_board(gray, board, opt.subpix_half_window_px)
        if isinstance(board, ChessboardSpec) and len(ids) == 0:
            reports[i] = ImageReport(name, False, f"no {board.inner_cols}x{board.inner_rows} chessboard found whole")
            continue
        if isinstance(board, BoardSpec) and len(ids) == 0 and count_aruco_markers(gray, board.dictionary) == 0:
            reports[i] = ImageReport(name, False, f"no ChArUco markers (dictionary {board.dictionary}) found")
            continue
        if len(ids) < opt.min_corners:
            reports[i] = ImageReport(name, False, f"too few corners ({len(ids)} < {opt.min_corners})", len(ids))
            continue
        blur = blur_sigma_px(gray, corners)
        if not blur <= opt.max_blur_px:  # NaN (no measurable edge) is rejected too
            reports[i] = ImageReport(
                name, False, f"blurred (edge blur {blur:.2f} px > {opt.max_blur_px:g} px)", len(ids), blur
            )
            continue
        obj = _object_points(board, ids)
        if _collinear(obj[:, :2]):
            reports[i] = ImageReport(name, False, "corners lie on one line", len(ids), blur)
            continue
        dup = _duplicate_of(ids, corners, views, opt.duplicate_px)
        if dup is not None:
            reports[i] = ImageReport(
                name, False, f"near-duplicate of {names[dup]} (corners within {opt.duplicate_px:g} px)", len(ids), blur
            )
            continue
        views.append((i, obj.astype(np.float32), corners.astype(np.float32), ids))
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
        rms, K, dist, rvecs, tvecs, std_intr, _, per_view = cv2.calibrateCameraExtended(
            [v[1] for v in views], [v[2] for v in views], size, None, None, flags=flags
        )
        per_view = np.asarray(per_view).reshape(-1)
        med = float(np.median(per_view))
        bad = [k for k, e in enumerate(per_view) if e > opt.outlier_factor * max(med, 0.05)]
        if not bad:
            break
        for k in bad:
            i = views[k][0]
            r = reports[i]
            reports[i] = ImageReport(
                r.name,
                False,
                f"reprojection error {per_view[k]:.2f} px > {opt.outlier_factor:g} x median {med:.2f} px",
                r.n_corners,
                r.blur_px,
                float(per_view[k]),
            )
        views = [v for k, v in enumerate(views) if k not in bad]
    for k, v in enumerate(views):
        r = reports[v[0]]
        reports[v[0]] = ImageReport(r.name, True, "", r.n_corners, r.blur_px, float(per_view[k]))

    T = make_T(
        so3_exp(np.stack([np.asarray(r).reshape(3) for r in rvecs])),
        np.stack([np.asarray(t).reshape(3) for t in tvecs]),
    )
    cam = CameraIntrinsics(K, np.asarray(dist).reshape(-1)[:5], int(size[0]), int(size[1]), float(rms))
    sd = np.asarray(std_intr, dtype=np.float64).reshape(-1)
    std = {k: float(sd[j]) for j, k in enumerate(("fx", "fy", "cx", "cy"))} if sd.size >= 4 else {}
    coverage = _coverage([v[2] for v in views], size)
    tilts = np.degrees(np.arccos(np.clip(np.abs(T[:, 2, 2]), 0.0, 1.0)))  # board normal vs optical axis
    tilt = (float(tilts.min()), float(tilts.max()))
    warn = []
    for k in ("fx", "fy"):
        if k in std and 100 * std[k] / K[0 if k == "fx" else 1, 0 if k == "fx" else 1] > opt.max_focal_std_pct:
            warn.append(
                f"{k} is uncertain: std {std[k]:.2f} px "
                f"({100 * std[k] / K[0 if k == 'fx' else 1, 0 if k == 'fx' else 1]:.2f} %, "
                f"threshold {opt.max_focal_std_pct:g} %); add views at other tilts and distances"
            )
    if coverage < opt.min_coverage:
        warn.append(
            f"the corners cover {100 * coverage:.0f} % of the image area (threshold {100 * opt.min_coverage:.0f} %); "
            "add views with the board near the edges and corners of the frame, where distortion is strongest"
        )
    if tilt[1] - tilt[0] < opt.min_tilt_range_deg:
        warn.append(
            f"the board's tilt spans only {tilt[0]:.0f}-{tilt[1]:.0f} deg (threshold {opt.min_tilt_range_deg:g} deg); "
            "add views tilted 20-45 deg about both axes: frontal views leave the focal length poorly determined"
        )
    return IntrinsicsResult(
        cam, float(rms), tuple(reports[k] for k in range(len(images))), T, std, coverage, tilt, tuple(warn)
    )


def _duplicate_of(ids: np.ndarray, corners: np.ndarray, views: list, tol_px: float) -> int | None:
    """Index (into the images) of an accepted view whose shared corners lie within ``tol_px`` on average."""
    for v in views:
        common, a, b = np.intersect1d(ids, v[3], return_indices=True)
        if len(common) >= 0.8 * max(len(ids), len(v[3])):
            if float(np.linalg.norm(corners[a] - v[2][b], axis=1).mean()) <= tol_px:
                return v[0]
    return None


def _coverage(corner_sets: Sequence[np.ndarray], size: tuple[int, int], cells: tuple[int, int] = (8, 6)) -> float:
    """Fraction of a ``cells`` grid over the image in which some view has a corner."""
    hit = np.zeros(cells[::-1], dtype=bool)
    for c in corner_sets:
        c = np.asarray(c, dtype=np.float64).reshape(-1, 2)
        ix = np.clip((c[:, 0] / size[0] * cells[0]).astype(int), 0, cells[0] - 1)
        iy = np.clip((c[:, 1] / size[1] * cells[1]).astype(int), 0, cells[1] - 1)
        hit[iy, ix] = True
    return float(hit.mean())


# ---- files ---------------------------------------------------------------------------------


_ImagePx = Annotated[int, Field(ge=1, le=MAX_IMAGE_PX)]
_Coefficient = Annotated[float, Field(ge=-MAX_DISTORTION, le=MAX_DISTORTION)]


class _CameraFile(Strict):
    width: _ImagePx
    height: _ImagePx
    K: tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]
    dist: tuple[_Coefficient, ...] = ()
    rms_px: Annotated[float, Field(ge=0.0)] | None = None
    model: Literal["opencv_pinhole"] = "opencv_pinhole"
    image_reprojection_rms_px: dict[str, float] | None = None
    intrinsics_std_px: (
        dict[Literal["fx", "fy", "cx", "cy"], Annotated[float, Field(ge=0.0, allow_inf_nan=False)]] | None
    ) = None

    @field_validator("K")
    @classmethod
    def _k(cls, K, info: ValidationInfo):
        k = np.asarray(K, dtype=np.float64)
        if not np.all(np.isfinite(k)):
            raise ValueError("must be finite")
        if k[0, 0] <= 0 or k[1, 1] <= 0:
            raise ValueError("fx (K[0][0]) and fy (K[1][1]) must be positive")
        if k[0, 1] != 0 or k[1, 0] != 0 or tuple(k[2]) != (0.0, 0.0, 1.0):
            raise ValueError("must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]")
        width = info.data.get("width")  # absent when the width itself was refused
        if width is not None:
            lo, hi = FOCAL_RANGE[0] * width, FOCAL_RANGE[1] * width
            for name, f in (("fx (K[0][0])", k[0, 0]), ("fy (K[1][1])", k[1, 1])):
                if not lo <= f <= hi:
                    raise ValueError(
                        f"{name} = {f:g} px is no lens's focal length for a {width} px wide image "
                        f"(expected {FOCAL_RANGE[0]:g}..{FOCAL_RANGE[1]:g} x the width: {lo:g}..{hi:g} px)"
                    )
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


class _RosMatrix(Strict):
    rows: Annotated[int, Field(ge=1)]
    cols: Annotated[int, Field(ge=1)]
    data: tuple[Annotated[float, Field(allow_inf_nan=False)], ...]

    @model_validator(mode="after")
    def _count(self):
        if len(self.data) != self.rows * self.cols:
            raise ValueError(f"data: {len(self.data)} values for a {self.rows}x{self.cols} matrix")
        return self


class _RosCameraInfo(Strict):
    """ROS ``camera_info`` YAML (``camera_calibration_parsers``; what ROS 1 and 2 calibrators write)."""

    image_width: _ImagePx
    image_height: _ImagePx
    camera_name: str | None = None
    camera_matrix: _RosMatrix
    distortion_model: Literal["plumb_bob", "rational_polynomial", "equidistant", "fisheye"] = "plumb_bob"
    distortion_coefficients: _RosMatrix
    rectification_matrix: _RosMatrix | None = None
    projection_matrix: _RosMatrix | None = None

    @field_validator("distortion_model")
    @classmethod
    def _pinhole(cls, v):
        if v in ("equidistant", "fisheye"):
            raise ValueError(
                "the fisheye (equidistant) model is not supported; calibrate with plumb_bob or rational_polynomial"
            )
        return v


CAMERA_FORMATS = ("advobj", "ros")


def save_camera_yaml(
    path,
    camera: CameraIntrinsics,
    images: Sequence[ImageReport] = (),
    fmt: str = "advobj",
    std_px: dict | None = None,
    camera_name: str = "camera",
) -> Path:
    """Write ``camera`` to ``path``: ``fmt="advobj"`` (ours, with the per-image reprojection RMS
    of accepted images and the intrinsics' standard deviations) or ``"ros"`` (``camera_info``)."""
    if fmt == "ros":
        K = camera.K
        dist = [float(x) for x in camera.dist] or [0.0] * 5
        model = "plumb_bob" if len(dist) <= 5 else "rational_polynomial"
        dist = (dist + [0.0] * 5)[:5] if model == "plumb_bob" else (dist + [0.0] * 8)[:8]
        # Monocular, unrectified: R = I, P = [K | 0] (ROS's calibrator would put an optimal new K there).
        P = [float(K[0, 0]), 0.0, float(K[0, 2]), 0.0, 0.0, float(K[1, 1]), float(K[1, 2]), 0.0, 0.0, 0.0, 1.0, 0.0]
        data = {
            "image_width": int(camera.width),
            "image_height": int(camera.height),
            "camera_name": camera_name,
            "camera_matrix": {"rows": 3, "cols": 3, "data": [float(x) for x in K.reshape(-1)]},
            "distortion_model": model,
            "distortion_coefficients": {"rows": 1, "cols": len(dist), "data": dist},
            "rectification_matrix": {"rows": 3, "cols": 3, "data": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]},
            "projection_matrix": {"rows": 3, "cols": 4, "data": P},
        }
        return write_yaml(path, data)
    if fmt != "advobj":
        raise ValueError(f"format: expected one of {', '.join(CAMERA_FORMATS)}, got {fmt!r}")
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
    if std_px:
        data["intrinsics_std_px"] = {k: float(v) for k, v in std_px.items()}
    return write_yaml(path, data, header="Camera intrinsics (OpenCV pinhole; K in px, dist = k1 k2 p1 p2 k3)")


def _camera_text(path) -> str:
    """The text of camera file ``path`` once it has passed the checks no parser is trusted with: a
    regular file (not a device or FIFO, which would block), at most :data:`CAMERA_FILE_MAX_BYTES`,
    nested at most :data:`CAMERA_FILE_MAX_DEPTH` levels (OpenCV's parser recurses per level and
    crashes the process on a deep enough file; Python's parsers raise RecursionError)."""
    text = read_bytes(path, "<file>", CAMERA_FILE_MAX_BYTES).decode("utf-8", errors="replace")
    brackets = text.count("[") + text.count("{")
    if brackets > CAMERA_FILE_MAX_BRACKETS:
        raise CalibrationFileError(
            path, "<file>", f"{brackets} brackets, over the {CAMERA_FILE_MAX_BRACKETS} a camera file can hold"
        )
    depth = nesting_depth(text)
    if depth > CAMERA_FILE_MAX_DEPTH:
        raise CalibrationFileError(
            path,
            "<file>",
            f"nested {depth} levels deep, over the limit of {CAMERA_FILE_MAX_DEPTH} (a camera file needs 4)",
        )
    return text


def _format_of(path, text: str) -> str:
    head = text[:4096]
    if head.lstrip().startswith("%YAML") or "opencv-matrix" in head:
        return "opencv"
    if Path(path).suffix.lower() == ".json" and any(
        f'"{k}"' in head for k in ("camera_matrix", "cameraMatrix", "intrinsic", "mtx")
    ):
        return "opencv"  # FileStorage JSON with plain lists
    if "camera_matrix" in head and "image_width" in head and "opencv-matrix" not in head:
        return "ros"
    return "advobj"


def camera_file_format(path) -> str:
    """``"opencv"`` (FileStorage YAML/JSON), ``"ros"`` (camera_info) or ``"advobj"``, from the file's content."""
    return _format_of(path, _camera_text(path))


def _cam(path, names: dict, K, dist, width, height, rms=None) -> CameraIntrinsics:
    """Validate through our own schema, so every format gets the same checks and messages; an
    error names the field as the file's format calls it (``names``: our field -> theirs)."""
    data = {"width": width, "height": height, "K": K, "dist": dist, "rms_px": rms}
    try:
        m = load_model(path, _CameraFile, data)
    except CalibrationFileError as err:
        ours, _, rest = err.field.partition(".")
        message = str(err)[len(f"{err.path}: {err.field}: ") :]
        field = names.get(ours, ours) + (f".{rest}" if rest and ours == "dist" else "")
        raise CalibrationFileError(path, field, message) from None
    return CameraIntrinsics(np.asarray(m.K), np.asarray(m.dist), m.width, m.height, m.rms_px)


# Names OpenCV programs use for the same things (samples, calibration tools, ROS's converter).
_CV_K = ("camera_matrix", "cameraMatrix", "K", "intrinsic", "intrinsics", "M", "mtx")
_CV_D = ("distortion_coefficients", "dist_coeffs", "distCoeffs", "D", "distortion", "dist")
_CV_W = ("image_width", "width", "imageWidth")
_CV_H = ("image_height", "height", "imageHeight")


def _node_number(node, path, name: str) -> float:
    if not (node.isInt() or node.isReal()):
        raise CalibrationFileError(path, name, "expected a number")
    return float(node.real())


def _node_matrix(node, path, name: str) -> tuple[np.ndarray, bool]:
    """A FileStorage node as a 2D float array, and whether the file gave its shape: an
    ``!!opencv-matrix`` (``rows`` x ``cols``, whose ``data`` must hold exactly rows * cols numbers)
    or a plain list of numbers (one row) or of equally long lists of numbers. Nothing deeper."""

    def numbers(seq, where: str) -> list[float]:
        if not seq.isSeq():
            raise CalibrationFileError(path, where, "not a matrix or a list of numbers")
        return [_node_number(seq.at(i), path, where) for i in range(seq.size())]

    if node.isMap():
        rows, cols, data = node.getNode("rows"), node.getNode("cols"), node.getNode("data")
        if rows.empty() or cols.empty() or data.empty():
            raise CalibrationFileError(path, name, "not a matrix (an opencv-matrix needs rows, cols and data)")
        r, c = _node_number(rows, path, f"{name}.rows"), _node_number(cols, path, f"{name}.cols")
        if not (r.is_integer() and c.is_integer() and r >= 1 and c >= 1):
            raise CalibrationFileError(path, name, f"rows and cols must be whole numbers >= 1, got {r:g} x {c:g}")
        n = data.size() if data.isSeq() else 1
        if n != r * c:
            raise CalibrationFileError(path, f"{name}.data", f"{n} values for a {r:g}x{c:g} matrix")
        return np.asarray(numbers(data, f"{name}.data"), dtype=np.float64).reshape(int(r), int(c)), True
    if not node.isSeq():
        raise CalibrationFileError(path, name, "not a matrix or a list of numbers")
    if node.size() and node.at(0).isSeq():
        rows = [numbers(node.at(i), name) for i in range(node.size())]
        if len({len(r) for r in rows}) != 1:
            raise CalibrationFileError(
                path, name, f"rows of different lengths ({', '.join(str(len(r)) for r in rows)})"
            )
        return np.asarray(rows, dtype=np.float64), True
    return np.asarray(numbers(node, name), dtype=np.float64).reshape(1, -1), False


def _load_opencv(path) -> CameraIntrinsics:
    import cv2  # lazy: robot_io start-up (cv2)

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as err:
        raise CalibrationFileError(
            path, "<file>", f"not a readable OpenCV FileStorage file ({str(err).splitlines()[-1][:80]})"
        ) from None
    try:
        if not fs.isOpened():
            raise CalibrationFileError(path, "<file>", "not a readable OpenCV FileStorage file")

        def first(names):
            for n in names:
                node = fs.getNode(n)
                if not node.empty():
                    return n, node
            return None, None

        kname, knode = first(_CV_K)
        if knode is None:
            raise CalibrationFileError(path, "camera_matrix", f"no 3x3 camera matrix under any of {', '.join(_CV_K)}")
        K, shaped = _node_matrix(knode, path, kname)
        if K.shape != (3, 3) and not (not shaped and K.size == 9):  # a flat list of 9 is row-major 3x3
            raise CalibrationFileError(path, kname, f"expected a 3x3 camera matrix, got {K.shape[0]}x{K.shape[1]}")
        dname, dnode = first(_CV_D)
        dist = np.zeros((1, 0)) if dnode is None else _node_matrix(dnode, path, dname)[0]
        if min(dist.shape) > 1:
            raise CalibrationFileError(path, dname, f"expected one row or column, got {dist.shape[0]}x{dist.shape[1]}")
        wname, w = first(_CV_W)
        hname, h = first(_CV_H)
        if w is None or h is None:
            wname = hname = "image_size"
            size = fs.getNode("image_size")
            if size.empty() or not size.isSeq() or size.size() != 2:
                raise CalibrationFileError(
                    path, "image_width", "no image size (image_width/image_height, width/height or image_size)"
                )
            width, height = (_node_number(size.at(i), path, "image_size") for i in (0, 1))
        else:
            width, height = _node_number(w, path, wname), _node_number(h, path, hname)
        for name, v in ((wname, width), (hname, height)):
            if not (v.is_integer() and 1 <= v <= MAX_IMAGE_PX):
                raise CalibrationFileError(path, name, f"expected whole pixels 1..{MAX_IMAGE_PX}, got {v:g}")
        rnode = fs.getNode("avg_reprojection_error")
        rms = None if rnode.empty() else _node_number(rnode, path, "avg_reprojection_error")
        names = {
            "width": wname,
            "height": hname,
            "K": kname,
            "dist": dname or _CV_D[0],
            "rms_px": "avg_reprojection_error",
        }
        return _cam(path, names, K.reshape(3, 3).tolist(), dist.reshape(-1).tolist(), int(width), int(height), rms)
    finally:
        fs.release()


def _ros_shape(path, name: str, m: _RosMatrix, shapes) -> None:
    if (m.rows, m.cols) not in shapes:
        want = " or ".join(f"{r}x{c}" for r, c in shapes)
        raise CalibrationFileError(path, name, f"expected {want}, got {m.rows}x{m.cols}")


def load_camera_yaml(path) -> CameraIntrinsics:
    """The :class:`CameraIntrinsics` in ``path``: our camera YAML, a ROS ``camera_info`` YAML, or
    an OpenCV ``FileStorage`` YAML/JSON (told apart by content). A :class:`CalibrationFileError`
    names the file and field.

    Before any parser sees it, the file must be a regular file of at most
    :data:`CAMERA_FILE_MAX_BYTES`, nested at most :data:`CAMERA_FILE_MAX_DEPTH` levels. Every
    format is held to the same bounds: 1..:data:`MAX_IMAGE_PX` pixels a side, fx and fy within
    :data:`FOCAL_RANGE` x the width, the principal point inside the image, distortion coefficients
    finite and at most :data:`MAX_DISTORTION` in size.
    """
    fmt = _format_of(path, _camera_text(path))
    if fmt == "opencv" or (str(path).lower().endswith(".json") and fmt != "advobj"):
        return _load_opencv(path)
    if fmt == "ros":
        m = load_model(path, _RosCameraInfo)
        _ros_shape(path, "camera_matrix", m.camera_matrix, [(3, 3)])
        n = len(m.distortion_coefficients.data)
        _ros_shape(path, "distortion_coefficients", m.distortion_coefficients, [(1, n), (n, 1)])
        if m.rectification_matrix is not None:
            _ros_shape(path, "rectification_matrix", m.rectification_matrix, [(3, 3)])
        if m.projection_matrix is not None:
            _ros_shape(path, "projection_matrix", m.projection_matrix, [(3, 4)])
        names = {
            "width": "image_width",
            "height": "image_height",
            "K": "camera_matrix",
            "dist": "distortion_coefficients.data",
        }
        K = np.asarray(m.camera_matrix.data, dtype=np.float64).reshape(3, 3).tolist()
        return _cam(path, names, K, list(m.distortion_coefficients.data), m.image_width, m.image_height)
    m = load_model(path, _CameraFile)
    return CameraIntrinsics(np.asarray(m.K), np.asarray(m.dist), m.width, m.height, m.rms_px)


def load_board_yaml(path) -> Board:
    """A board YAML: ChArUco (``kind: charuco``, the default) or plain chessboard (``kind: chessboard``)."""
    data = read_yaml(path)
    if isinstance(data, dict) and data.get("kind") == "chessboard":
        return load_model(path, ChessboardSpec, data)
    return load_model(path, BoardSpec, data)


def save_board_yaml(path, board: Board) -> Path:
    what = "Plain chessboard (counted by inner corners" if isinstance(board, ChessboardSpec) else "ChArUco board ("
    return write_yaml(
        path,
        board.model_dump(),
        header=f"{what}{'; ' if isinstance(board, ChessboardSpec) else ''}sizes in metres as printed)",
    )
