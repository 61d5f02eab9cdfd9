"""AprilTag (tag36h11) detection and pose, with the IPPE two-fold ambiguity made explicit.

tag36h11 is detected by AprilTag 3 (the C library, through ``pupil-apriltags``), the field's
reference detector: on small tags (under ~25 px a side) it finds far more than ``cv2.aruco``
(``benchmarks/bench_tags.py`` measures both). ArUco dictionaries, and tag36h11 with
``backend="aruco"``, go through ``cv2.aruco`` with ``CORNER_REFINE_APRILTAG``. Both report
corners in the AprilTag pixel convention (pixel centres at +0.5), half a pixel off OpenCV's
(pixel centres at integers); we shift them back. Corners are off by up to ~0.5 px when tag edges
align with the pixel grid, so by default each corner is re-fit as the intersection of sub-pixel
edge lines (:func:`refine_corners_edges`).

A square tag seen by a pinhole camera has two pose solutions (a reflection of the tag's tilt
about the line of sight). ``solvePnPGeneric(SOLVEPNP_IPPE_SQUARE)`` returns both; each
:class:`TagDetection` keeps them with their reprojection errors. The pose is *ambiguous* when the
two solutions fit almost equally well (error ratio ``best / second`` above a threshold) and yet
differ in orientation by more than a degree. Small tags, near-frontal views and grazing views are
where that happens. A bundle of several tags on one rigid body (:func:`estimate_bundle_pose`) has
no such ambiguity once the tags are spread out: its pose is fit to all corners at once.

Tag frame (OpenCV IPPE_SQUARE): origin at the tag centre, +x right and +y up on the printed tag,
+z out of the printed face. Object points in the detector's corner order (top-left, top-right,
bottom-right, bottom-left): (-s/2, s/2, 0), (s/2, s/2, 0), (s/2, -s/2, 0), (-s/2, -s/2, 0).
"""

from __future__ import annotations

import atexit
from dataclasses import dataclass, field
from typing import Callable, Literal, Mapping, Sequence

import cv2
import numpy as np
import pupil_apriltags

from calibration.errors import CalibrationError
from calibration.intrinsics import ARUCO_DICTS, CameraIntrinsics, to_gray
from calibration.io import Strict
from sim.geometry import invert_T, make_T, rotation_angle, so3_exp, so3_log, transform_points

__all__ = [
    "APRILTAG_PIXEL_OFFSET",
    "TAG_DICTIONARIES",
    "resolve_dictionary",
    "TagDetectorOptions",
    "PoseSolution",
    "TagDetection",
    "BundlePose",
    "tag_object_points",
    "detect_tag_corners",
    "tag_pose_solutions",
    "refine_corners_edges",
    "detect_tags",
    "estimate_bundle_pose",
    "reprojection_rms",
    "pose_std",
]

APRILTAG_PIXEL_OFFSET = 0.5  # px; AprilTag pixel-centre convention minus OpenCV's
TAG36H11 = "tag36h11"
# Names a user may give (``--dictionary``): tag36h11 plus the ArUco dictionaries of the boards.
TAG_DICTIONARIES = (TAG36H11, *ARUCO_DICTS)


class TagDetectorOptions(Strict):
    """Thresholds for flags; they never drop a detection, only mark it."""

    ambiguity_ratio: float = 0.6  # best/second reprojection error above this -> two fits are comparable
    ambiguity_min_angle_deg: float = 1.0  # ... and only if the two solutions differ by more than this
    min_side_px: float = 12.0  # shorter tag edges are flagged "small"
    max_view_angle_deg: float = 65.0  # view angle (tag normal vs line of sight) above this -> "oblique"
    max_reprojection_px: float = 2.0  # best solution worse than this -> "poor_fit"
    # Re-fit each corner as the intersection of sub-pixel edge lines (see refine_corners_edges):
    # OpenCV's AprilTag refinement is off by up to ~0.5 px when tag edges align with the pixel grid.
    edge_refinement: bool = True
    corner_noise_px: float = 0.05  # assumed corner std after edge refinement, for the reported pose uncertainty
    max_orientation_std_deg: float = 1.0  # larger 1-sigma orientation uncertainty -> "uncertain_orientation"
    # tag36h11 detector: AprilTag 3 (the reference; far better recall on small tags) or cv2.aruco.
    backend: Literal["apriltag3", "aruco"] = "apriltag3"


def tag_object_points(tag_size_m: float) -> np.ndarray:
    """Corners ``(4, 3)`` m of a tag of side ``tag_size_m`` in its frame, in detector order (IPPE_SQUARE)."""
    h = 0.5 * float(tag_size_m)
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


@dataclass(frozen=True)
class PoseSolution:
    T_cam_tag: np.ndarray  # (4, 4)
    reprojection_rms_px: float


@dataclass(frozen=True)
class TagDetection:
    """One detected tag.

    corners_px: (4, 2) in OpenCV pixel convention, detector order. solutions: best first (empty if
    the tag size is unknown or PnP failed). ambiguity_ratio: best/second reprojection error in
    [0, 1] (NaN with fewer than two solutions). view_angle_deg: angle between the tag normal and
    the line of sight under the best solution. position_std_m / orientation_std_deg: 1-sigma
    uncertainty (largest principal axis) of the best pose for ``corner_noise_px`` corner noise,
    from the PnP Jacobian; a frontal small tag has a well-known position but a poorly known tilt.
    flags: subset of {"ambiguous", "small", "oblique", "poor_fit", "uncertain_orientation",
    "no_pose", "unknown_size"}.
    """

    tag_id: int
    corners_px: np.ndarray
    tag_size_m: float | None
    solutions: tuple[PoseSolution, ...] = ()
    ambiguity_ratio: float = float("nan")
    solution_angle_deg: float = float("nan")
    view_angle_deg: float = float("nan")
    flags: tuple[str, ...] = ()
    position_std_m: float = float("nan")
    orientation_std_deg: float = float("nan")

    @property
    def ambiguous(self) -> bool:
        return "ambiguous" in self.flags

    @property
    def T_cam_tag(self) -> np.ndarray | None:
        """The best-fitting pose, or None if there is none."""
        return self.solutions[0].T_cam_tag if self.solutions else None

    def to_dict(self) -> dict:
        return {
            "id": int(self.tag_id),
            "corners_px": np.round(self.corners_px, 3).tolist(),
            "tag_size_m": self.tag_size_m,
            "solutions": [
                {
                    "translation_m": np.round(s.T_cam_tag[:3, 3], 6).tolist(),
                    "rotvec_rad": np.round(so3_log(s.T_cam_tag[:3, :3]), 6).tolist(),
                    "reprojection_rms_px": round(float(s.reprojection_rms_px), 4),
                }
                for s in self.solutions
            ],
            "ambiguity_ratio": None if np.isnan(self.ambiguity_ratio) else round(float(self.ambiguity_ratio), 4),
            "solution_angle_deg": None
            if np.isnan(self.solution_angle_deg)
            else round(float(self.solution_angle_deg), 3),
            "view_angle_deg": None if np.isnan(self.view_angle_deg) else round(float(self.view_angle_deg), 2),
            "position_std_mm": None if np.isnan(self.position_std_m) else round(1000 * float(self.position_std_m), 3),
            "orientation_std_deg": None
            if np.isnan(self.orientation_std_deg)
            else round(float(self.orientation_std_deg), 3),
            "ambiguous": self.ambiguous,
            "flags": list(self.flags),
        }


def reprojection_rms(
    T_cam_obj: np.ndarray, points_obj: np.ndarray, pixels: np.ndarray, camera: CameraIntrinsics
) -> float:
    """RMS pixel error of ``points_obj: (N, 3)`` seen at ``pixels: (N, 2)`` under ``T_cam_obj``."""
    proj = camera.project(transform_points(T_cam_obj, points_obj))
    return float(np.sqrt(np.mean(np.sum((proj - pixels) ** 2, -1))))


def resolve_dictionary(dictionary: str | int | None) -> str:
    """A dictionary name of :data:`TAG_DICTIONARIES` from a name (case-insensitive, ``DICT_`` prefix
    optional), an OpenCV dictionary id, or None (tag36h11); ValueError names the choices."""
    if dictionary is None:
        return TAG36H11
    if isinstance(dictionary, (int, np.integer)) and not isinstance(dictionary, bool):
        if int(dictionary) == cv2.aruco.DICT_APRILTAG_36h11:
            return TAG36H11
        for name, attr in ARUCO_DICTS.items():
            if getattr(cv2.aruco, attr) == int(dictionary):
                return name
        raise ValueError(
            f"dictionary: OpenCV dictionary id {int(dictionary)} is not supported; choose from "
            f"{', '.join(TAG_DICTIONARIES)}"
        )
    name = str(dictionary).strip().upper().removeprefix("DICT_")
    if name in ("TAG36H11", "APRILTAG_36H11", "36H11"):
        return TAG36H11
    if name in ARUCO_DICTS:
        return name
    raise ValueError(f"dictionary: unknown {dictionary!r}; choose from {', '.join(TAG_DICTIONARIES)}")


class _AprilTag3:
    """One AprilTag 3 detector per process (the C detector is costly to build).

    ``pupil-apriltags``' own ``__del__`` frees the tag family before the detector that still
    points at it, which segfaults at interpreter exit; we free them in the library's order
    (detector, then family) at exit and disarm its ``__del__``.
    """

    _det = None

    @classmethod
    def get(cls):
        if cls._det is None:
            # Full resolution (quad_decimate 1): decimation loses the small tags this backend is for.
            # The library's own edge refinement off: on the real photos it lost 2 of 47 tags, and
            # our refine_corners_edges runs after either backend anyway.
            cls._det = pupil_apriltags.Detector(families=TAG36H11, nthreads=1, quad_decimate=1.0, refine_edges=0)
            atexit.register(cls.release)
        return cls._det

    @classmethod
    def release(cls):
        det, cls._det = cls._det, None
        if det is None or getattr(det, "tag_detector_ptr", None) is None:
            return
        det.libc.apriltag_detector_destroy.restype = None
        det.libc.apriltag_detector_destroy(det.tag_detector_ptr)
        for tf in det.tag_families.values():
            det.libc.tag36h11_destroy.restype = None
            det.libc.tag36h11_destroy(tf)
        det.tag_detector_ptr = None  # its __del__ now does nothing


# pupil-apriltags' corner order (counter-clockwise from the tag's bottom-left in its own image
# frame) -> ours (top-left, top-right, bottom-right, bottom-left as printed).
_APRILTAG3_ORDER = [1, 0, 3, 2]
# tag36h11 codes are >= 11 bits apart; correcting up to 2 (the library's default) leaves a
# margin of 9 against reading clutter as a tag. On the real photos, 2 found 46 of 47, 1 found 45.
APRILTAG3_MAX_HAMMING = 2


def detect_tag_corners(gray: np.ndarray, dictionary: str | int | None = None, backend: str = "apriltag3"):
    """Raw detections -> list of ``(tag_id, corners_px (4, 2))``; [] when nothing (or nothing sane) is found.

    ``dictionary``: a name of :data:`TAG_DICTIONARIES` (or an OpenCV id); None is tag36h11.
    ``backend`` picks the tag36h11 detector; ArUco dictionaries always use ``cv2.aruco``.
    """
    name = resolve_dictionary(dictionary)
    gray = np.ascontiguousarray(gray, dtype=np.uint8)
    if gray.ndim != 2 or min(gray.shape) < 8:
        return []  # nothing a detector could decode (and AprilTag 3 asserts on degenerate sizes)
    if name == TAG36H11 and backend == "apriltag3":
        out = []
        for d in _AprilTag3.get().detect(gray):
            c = np.asarray(d.corners, dtype=np.float64)[_APRILTAG3_ORDER] - APRILTAG_PIXEL_OFFSET
            if d.hamming <= APRILTAG3_MAX_HAMMING and np.all(np.isfinite(c)):
                out.append((int(d.tag_id), c))
        return out
    if backend not in ("apriltag3", "aruco"):
        raise ValueError(f"backend: expected 'apriltag3' or 'aruco', got {backend!r}")
    cv_id = cv2.aruco.DICT_APRILTAG_36h11 if name == TAG36H11 else getattr(cv2.aruco, ARUCO_DICTS[name])
    d = cv2.aruco.getPredefinedDictionary(cv_id)
    p = cv2.aruco.DetectorParameters()
    p.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_APRILTAG
    try:
        corners, ids, _ = cv2.aruco.ArucoDetector(d, p).detectMarkers(gray)
    except cv2.error:
        return []  # OpenCV rejects degenerate inputs (e.g. a 1-pixel image) by throwing
    if ids is None:
        return []
    out = []
    for c, i in zip(corners, ids.reshape(-1)):
        # The offset belongs to the refinement method, whatever the dictionary.
        c = c.reshape(4, 2).astype(np.float64) - APRILTAG_PIXEL_OFFSET
        if np.all(np.isfinite(c)):
            out.append((int(i), c))
    return out


def refine_corners_edges(gray: np.ndarray, corners_px: np.ndarray, cells: int = 8) -> np.ndarray:
    """Corners ``(4, 2)`` re-estimated as intersections of the four outer edges of the black square.

    Each edge is sampled at points along its middle 80 %; at each, the intensity profile across
    the edge (bilinear, 0.25 px steps, half a cell either side: inside is the black border, outside
    the white quiet zone) gives the edge position as the centroid of the dark-to-bright gradient.
    A total-least-squares line through those points per edge, intersected with its neighbours,
    gives the corners. Falls back to ``corners_px`` if the edges cannot be measured.
    """
    c = np.asarray(corners_px, dtype=np.float64)
    centre = c.mean(0)
    lines = []
    for k in range(4):
        a, b = c[k], c[(k + 1) % 4]
        L = np.linalg.norm(b - a)
        if L < 8:
            return c
        u = (b - a) / L
        n = np.array([u[1], -u[0]])
        if n @ (0.5 * (a + b) - centre) < 0:
            n = -n  # outward
        half = max(0.45 * L / cells, 1.0)
        offs = np.arange(-half, half + 1e-9, 0.25)
        ts = np.linspace(0.1, 0.9, max(6, int(L / 2)))
        base = a[None] + ts[:, None] * (b - a)[None]  # (M, 2)
        pts = base[:, None, :] + offs[None, :, None] * n[None, None, :]  # (M, S, 2)
        prof = cv2.remap(
            gray.astype(np.float32),
            pts[..., 0].astype(np.float32),
            pts[..., 1].astype(np.float32),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
        g = np.clip(np.diff(prof, axis=1), 0.0, None)  # dark inside -> bright outside
        w = g.sum(1)
        ok = w > 1e-6 * max(1.0, float(prof.max()))
        if ok.sum() < 3:
            return c
        mid = 0.5 * (offs[1:] + offs[:-1])
        s = (g[ok] * mid[None]).sum(1) / w[ok]
        edge_pts = base[ok] + s[:, None] * n[None]
        m = edge_pts.mean(0)
        _, _, vt = np.linalg.svd(edge_pts - m)
        d = vt[0]
        lines.append((m, d))
    out = np.empty_like(c)
    for k in range(4):
        (p1, d1), (p0, d0) = lines[k], lines[(k - 1) % 4]  # corner k joins edge k-1 and edge k
        A = np.stack([d0, -d1], 1)
        if abs(np.linalg.det(A)) < 1e-6:
            return c
        t = np.linalg.solve(A, p1 - p0)
        out[k] = p0 + t[0] * d0
    # A refinement that moves a corner by more than a cell found something else than the border.
    if not np.all(np.isfinite(out)) or np.abs(out - c).max() > max(1.5, np.linalg.norm(c[1] - c[0]) / cells):
        return c
    return out


def tag_pose_solutions(corners_px: np.ndarray, tag_size_m: float, camera: CameraIntrinsics) -> tuple[PoseSolution, ...]:
    """Both IPPE_SQUARE solutions for one tag, best (lowest reprojection RMS) first; () if PnP fails."""
    obj = tag_object_points(tag_size_m)
    try:
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(
            obj, corners_px.reshape(4, 1, 2), camera.K, camera.dist, flags=cv2.SOLVEPNP_IPPE_SQUARE
        )
    except cv2.error:
        return ()
    sols = []
    for k in range(int(n)):
        T = make_T(so3_exp(np.asarray(rvecs[k]).reshape(3)), np.asarray(tvecs[k]).reshape(3))
        if not np.all(np.isfinite(T)) or T[2, 3] <= 0:
            continue  # a tag behind the camera is not a solution
        sols.append(PoseSolution(T, reprojection_rms(T, obj, corners_px, camera)))
    return tuple(sorted(sols, key=lambda s: s.reprojection_rms_px))


def _view_angle_deg(T_cam_tag: np.ndarray) -> float:
    normal = T_cam_tag[:3, 2]
    ray = T_cam_tag[:3, 3] / np.linalg.norm(T_cam_tag[:3, 3])
    # Printed face toward the camera means normal . ray < 0; abs() so a back-facing fit still reports tilt.
    return float(np.degrees(np.arccos(np.clip(abs(normal @ ray), 0.0, 1.0))))


def pose_std(T_cam_obj: np.ndarray, points_obj: np.ndarray, camera: CameraIntrinsics, corner_noise_px: float):
    """1-sigma ``(position_std_m, orientation_std_deg)`` (largest principal axes) of a PnP pose.

    Linearised: cov = s^2 (J^T J)^-1 with J the Jacobian of the projected ``points_obj: (N, 3)``
    w.r.t. a body-frame twist (translation m, rotation rad), ``T_cam_obj @ exp(twist)``, so the
    translation block is the uncertainty of the body origin itself.
    """
    eps = 1e-6
    base = camera.project(transform_points(T_cam_obj, points_obj)).reshape(-1)
    J = np.zeros((base.size, 6))
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        dT = make_T(so3_exp(d[3:]), d[:3])
        J[:, k] = (camera.project(transform_points(T_cam_obj @ dT, points_obj)).reshape(-1) - base) / eps
    JtJ = J.T @ J
    if not np.all(np.isfinite(JtJ)) or np.linalg.cond(JtJ) > 1e14:
        return float("inf"), float("inf")
    cov = corner_noise_px**2 * np.linalg.inv(JtJ)
    pos = float(np.sqrt(max(np.linalg.eigvalsh(cov[:3, :3]).max(), 0.0)))
    rot = float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:]).max(), 0.0))))
    return pos, rot


def _flags(sols, corners_px, opt: TagDetectorOptions):
    flags = []
    side = float(np.min(np.linalg.norm(corners_px - np.roll(corners_px, -1, 0), axis=-1)))
    ratio = angle = view = float("nan")
    if side < opt.min_side_px:
        flags.append("small")
    if not sols:
        flags.append("no_pose")
        return ratio, angle, view, tuple(flags)
    view = _view_angle_deg(sols[0].T_cam_tag)
    if len(sols) >= 2:
        e0, e1 = sols[0].reprojection_rms_px, sols[1].reprojection_rms_px
        ratio = e0 / e1 if e1 > 0 else 1.0
        angle = float(np.degrees(rotation_angle(sols[0].T_cam_tag[:3, :3], sols[1].T_cam_tag[:3, :3])))
        if ratio > opt.ambiguity_ratio and angle > opt.ambiguity_min_angle_deg:
            flags.append("ambiguous")
    if view > opt.max_view_angle_deg:
        flags.append("oblique")
    if sols[0].reprojection_rms_px > opt.max_reprojection_px:
        flags.append("poor_fit")
    return ratio, angle, view, tuple(flags)


def detect_tags(
    image,
    camera: CameraIntrinsics,
    tag_size_m: float | Mapping[int, float] | Callable[[int], float | None] | None = None,
    options: TagDetectorOptions | None = None,
    dictionary: str | int | None = None,
) -> list[TagDetection]:
    """Every tag in ``image`` with both pose solutions (if its size is known), sorted by id.

    ``tag_size_m``: one size for all tags, a mapping id -> size, a function id -> size or None, or
    None (corners only). Never raises on image *content* (blank, saturated, no tags, wrong family):
    those give ``[]``.
    """
    opt = options or TagDetectorOptions()
    gray = to_gray(image)
    if gray.shape != (camera.height, camera.width):
        # Intrinsics belong to one resolution; poses from another would be silently wrong.
        aspect = (
            ""
            if gray.shape[1] * camera.height != gray.shape[0] * camera.width
            else (
                " (same aspect ratio: pass --rescale to rescale the intrinsics, or calibrate the camera at this size)"
            )
        )
        raise CalibrationError(
            f"image: size {gray.shape[1]}x{gray.shape[0]} does not match the camera file's "
            f"{camera.width}x{camera.height}; intrinsics hold for one resolution{aspect}"
        )
    if callable(tag_size_m):
        size_of = tag_size_m
    elif isinstance(tag_size_m, Mapping):
        size_of = lambda i: tag_size_m.get(i)  # noqa: E731
    else:
        size_of = lambda i: tag_size_m  # noqa: E731
    out = []
    for tag_id, corners in detect_tag_corners(gray, dictionary, opt.backend):
        if opt.edge_refinement:
            corners = refine_corners_edges(gray, corners)
        size = size_of(tag_id)
        sols = tag_pose_solutions(corners, size, camera) if size else ()
        ratio, angle, view, flags = _flags(sols, corners, opt)
        pos_std = rot_std = float("nan")
        if sols:
            pos_std, rot_std = pose_std(sols[0].T_cam_tag, tag_object_points(size), camera, opt.corner_noise_px)
            if rot_std > opt.max_orientation_std_deg:
                flags = flags + ("uncertain_orientation",)
        if not size:
            flags = tuple(f for f in flags if f != "no_pose") + ("unknown_size",)
        out.append(TagDetection(tag_id, corners, size, sols, ratio, angle, view, flags, pos_std, rot_std))
    return sorted(out, key=lambda d: d.tag_id)


@dataclass(frozen=True)
class BundlePose:
    """Pose of a rigid body from all corners of its visible tags.

    T_cam_frame: best fit; alternatives: other local minima that fit comparably (only when
    ``ambiguous``); reprojection_rms_px over all corners; tag_ids used.
    """

    T_cam_frame: np.ndarray
    reprojection_rms_px: float
    tag_ids: tuple[int, ...]
    ambiguous: bool
    alternatives: tuple[np.ndarray, ...] = field(default=())


def estimate_bundle_pose(
    detections: Sequence[TagDetection],
    corners_in_frame: Mapping[int, np.ndarray],
    camera: CameraIntrinsics,
    options: TagDetectorOptions | None = None,
) -> BundlePose | None:
    """Fit one pose ``T_cam_frame`` to every detected tag listed in ``corners_in_frame``.

    ``corners_in_frame[id]: (4, 3)`` m are the tag's corners (detector order) in the body frame.
    Every single-tag solution seeds a Levenberg-Marquardt refinement on all corners; the best
    refined fit wins. The result is ambiguous only if a clearly different seed (> the angle
    threshold) converges to a fit within the error ratio threshold: with one tag that reproduces
    the IPPE ambiguity; with spread-out tags the wrong reflection no longer fits and it vanishes.
    Returns None if none of the tags has a pose.
    """
    opt = options or TagDetectorOptions()
    used = [d for d in detections if d.tag_id in corners_in_frame and d.solutions]
    if not used:
        return None
    obj = np.concatenate([np.asarray(corners_in_frame[d.tag_id], dtype=np.float64) for d in used])
    img = np.concatenate([d.corners_px for d in used])
    fits = []
    for d in used:
        T_frame_tag = _fit_frame_tag(np.asarray(corners_in_frame[d.tag_id], dtype=np.float64), d.tag_size_m)
        for s in d.solutions:
            T0 = s.T_cam_tag @ invert_T(T_frame_tag)
            rvec, tvec = so3_log(T0[:3, :3]).reshape(3, 1), T0[:3, 3].reshape(3, 1).copy()
            if len(used) > 1:
                try:
                    rvec, tvec = cv2.solvePnPRefineLM(obj, img, camera.K, camera.dist, rvec, tvec)
                except cv2.error:
                    continue
            T = make_T(so3_exp(rvec.reshape(3)), tvec.reshape(3))
            if T[2, 3] > 0:
                fits.append((reprojection_rms(T, obj, img, camera), T))
    if not fits:
        return None
    fits.sort(key=lambda f: f[0])
    best_err, best_T = fits[0]
    alts = []
    for err, T in fits[1:]:
        different = np.degrees(rotation_angle(T[:3, :3], best_T[:3, :3])) > opt.ambiguity_min_angle_deg
        if different and (best_err / err if err > 0 else 1.0) > opt.ambiguity_ratio:
            if all(np.degrees(rotation_angle(T[:3, :3], a[:3, :3])) > opt.ambiguity_min_angle_deg for a in alts):
                alts.append(T)
    return BundlePose(best_T, best_err, tuple(d.tag_id for d in used), bool(alts), tuple(alts))


def _fit_frame_tag(corners_frame: np.ndarray, tag_size_m: float) -> np.ndarray:
    """``T_frame_tag`` mapping the tag's canonical corners onto ``corners_frame`` (Kabsch, rigid)."""
    src = tag_object_points(tag_size_m)
    cs, cd = src.mean(0), corners_frame.mean(0)
    H = (src - cs).T @ (corners_frame - cd)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return make_T(R, cd - R @ cs)
