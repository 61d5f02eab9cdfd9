"""Synthetic camera images of planar targets (AprilTags, ChArUco boards) rendered with OpenGL.

Each target is a textured quad at a known pose ``T_cam_plane`` seen by an ideal pinhole camera
with known ``K``; rendering is real rasterisation through pyrender (headless EGL), unlit (FLAT)
so the printed contrast survives, with MSAA for realistic edge antialiasing. Lens distortion,
blur and sensor noise are applied afterwards in image space. Used by the tests, the benchmark and
``advobj calibrate selfcheck``.

Plane frames match the targets' own frames: a tag's frame is OpenCV's IPPE_SQUARE frame (origin at
the tag centre, +x right, +y up on the printed tag, +z out of the printed face); a ChArUco board's
frame is OpenCV's board frame (origin at the top-left board corner, +x right, +y down the printed
board, +z into the board).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import cv2
import numpy as np
import pyrender
import trimesh
from PIL import Image

from sim.geometry import compose, invert_T, look_at, make_T, se3_exp, so3_exp, transform_points

__all__ = [
    "TexturedPlane",
    "tag_plane",
    "object_tag_planes",
    "board_plane",
    "render_planes",
    "distort_image",
    "degrade",
    "default_K",
    "camera_facing",
    "random_view_poses",
    "hand_eye_poses",
    "perturb_poses",
]

# OpenCV camera (x right, y down, z forward) -> OpenGL camera (x right, y up, z backward).
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class TexturedPlane:
    """A flat textured quad.

    image: (h, w) or (h, w, 3) uint8 texture; corners_m: (4, 3) plane-frame positions of the
    image's top-left, top-right, bottom-right and bottom-left corners; T_cam_plane: (4, 4).
    """

    image: np.ndarray
    corners_m: np.ndarray
    T_cam_plane: np.ndarray


def default_K(width: int = 640, height: int = 480, fov_x_deg: float = 70.0) -> np.ndarray:
    """A pinhole ``K`` (3, 3) with square pixels, principal point slightly off-centre like a real lens."""
    f = 0.5 * width / np.tan(np.radians(fov_x_deg) / 2.0)
    return np.array([[f, 0.0, 0.5 * width + 3.7], [0.0, f, 0.5 * height - 2.3], [0.0, 0.0, 1.0]])


def camera_facing(
    distance_m: float, tilt_rad: float = 0.0, tilt_axis=(1.0, 0.0, 0.0), roll_rad: float = 0.0, offset_m=(0.0, 0.0)
) -> np.ndarray:
    """``T_cam_target`` (4, 4) of a target at ``distance_m`` along the optical axis.

    The target faces the camera (its +z toward the camera, i.e. printed face visible for tags),
    then is tilted by ``tilt_rad`` about ``tilt_axis`` (target frame) and rolled by ``roll_rad``
    about its normal; ``offset_m`` shifts it across the image (camera x, y).
    """
    # Facing: target +z = camera -z; keep target +x = camera +x, so target +y = camera -y (up).
    R_face = np.diag([1.0, -1.0, -1.0])
    axis = np.asarray(tilt_axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    R = R_face @ so3_exp(axis * tilt_rad) @ so3_exp(np.array([0.0, 0.0, roll_rad]))
    return make_T(R, np.array([offset_m[0], offset_m[1], distance_m]))


def tag_plane(
    tag_id: int,
    tag_size_m: float,
    T_cam_tag: np.ndarray,
    dictionary: int | None = None,
    margin: float = 0.5,
    px_per_cell: int = 24,
) -> TexturedPlane:
    """A printed AprilTag (tag36h11 by default) with a white quiet zone of ``margin`` x the tag size per side.

    ``tag_size_m`` is the side of the black square (OpenCV's marker length).
    """
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11 if dictionary is None else dictionary)
    cells = d.markerSize + 2
    side = cells * px_per_cell
    marker = cv2.aruco.generateImageMarker(d, int(tag_id), side, borderBits=1)
    pad = int(round(margin * side))
    img = np.pad(marker, pad, constant_values=255)
    h = 0.5 * tag_size_m * img.shape[0] / side
    corners = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
    return TexturedPlane(img, corners, np.asarray(T_cam_tag, dtype=np.float64))


def object_tag_planes(registry, T_cam_object: np.ndarray, obj: str = "table", px_per_cell: int = 24) -> list:
    """The printed tags of object ``obj`` of a :class:`calibration.registry.ObjectRegistry` as seen by a
    camera at ``T_cam_object`` (4, 4): each where the registry puts it (``T_tag_object``), its side the
    registry's ``size_m``. For ``table``, the tags lying on the table seen from ``inv(T_table_cam)``."""
    T_cam_object = np.asarray(T_cam_object, dtype=np.float64)
    return [
        tag_plane(
            i,
            registry.tags[i].size_m,
            T_cam_object @ invert_T(registry.tags[i].T_tag_object.T),
            px_per_cell=px_per_cell,
        )
        for i in registry.tag_ids(obj)
    ]


def board_plane(board, T_cam_board: np.ndarray, px_per_square: int = 80, margin_squares: float = 0.5) -> TexturedPlane:
    """A printed ChArUco ``board`` (cv2.aruco.CharucoBoard) with a white margin, in the board frame."""
    sx, sy = board.getChessboardSize()
    sq = board.getSquareLength()
    pad = int(round(margin_squares * px_per_square))
    img = board.generateImage((sx * px_per_square, sy * px_per_square), marginSize=0, borderBits=1)
    img = np.pad(img, pad, constant_values=255)
    m = margin_squares * sq
    w, h = sx * sq, sy * sq
    corners = np.array([[-m, -m, 0.0], [w + m, -m, 0.0], [w + m, h + m, 0.0], [-m, h + m, 0.0]])
    return TexturedPlane(img, corners, np.asarray(T_cam_board, dtype=np.float64))


def chessboard_plane(
    board, T_cam_board: np.ndarray, px_per_square: int = 60, margin_squares: float = 0.5
) -> TexturedPlane:
    """A printed plain chessboard (:class:`~calibration.intrinsics.ChessboardSpec`) with a white
    margin, in the board frame (origin at the first inner corner, +x along a row, +y down)."""
    cols, rows = board.inner_cols + 1, board.inner_rows + 1  # squares
    sq = board.square_size_m
    cells = np.add.outer(np.arange(rows), np.arange(cols)) % 2 == 0
    img = np.where(np.kron(cells, np.ones((px_per_square, px_per_square), dtype=bool)), 0, 255).astype(np.uint8)
    pad = int(round(margin_squares * px_per_square))
    img = np.pad(img, pad, constant_values=255)
    m = margin_squares * sq
    x0, y0, x1, y1 = -sq - m, -sq - m, (cols - 1) * sq + m, (rows - 1) * sq + m
    corners = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])
    return TexturedPlane(img, corners, np.asarray(T_cam_board, dtype=np.float64))


_RENDERER = None  # one offscreen context per process, resized on demand (see render_planes)


def _renderer(width: int, height: int):
    # One long-lived context: pyrender's delete() eglTerminate()s the shared display, which would
    # kill every other live context (e.g. the sim's renderer) if we created and freed our own.
    global _RENDERER

    if _RENDERER is None:
        _RENDERER = pyrender.OffscreenRenderer(width, height)
    else:
        _RENDERER.viewport_width, _RENDERER.viewport_height = width, height
    return _RENDERER


def _quad_mesh(plane: TexturedPlane):
    img = plane.image if plane.image.ndim == 3 else np.repeat(plane.image[..., None], 3, -1)
    # UV origin is the texture's bottom-left (OpenGL): TL=(0,1), TR=(1,1), BR=(1,0), BL=(0,0).
    uv = np.array([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]])
    faces = np.array([[0, 2, 1], [0, 3, 2]])
    tm = trimesh.Trimesh(plane.corners_m, faces, process=False)
    tex = pyrender.Texture(source=Image.fromarray(np.ascontiguousarray(img, dtype=np.uint8)), source_channels="RGB")
    mat = pyrender.MetallicRoughnessMaterial(baseColorTexture=tex, doubleSided=True)
    prim = pyrender.Primitive(
        positions=tm.vertices.astype(np.float32), indices=faces, texcoord_0=uv.astype(np.float32), material=mat
    )
    return pyrender.Mesh([prim])


def render_planes(
    planes,
    K: np.ndarray,
    width: int,
    height: int,
    background: float = 0.45,
    znear_m: float = 0.01,
    zfar_m: float = 20.0,
) -> np.ndarray:
    """Render ``planes`` with pinhole ``K: (3, 3)`` into an ``(height, width, 3)`` uint8 RGB image.

    ``background`` is the grey level (0..1) where nothing is drawn.
    """
    K = np.asarray(K, dtype=np.float64)
    scene = pyrender.Scene(bg_color=(background, background, background, 1.0), ambient_light=(1.0, 1.0, 1.0))
    # pyrender measures the principal point from the image edge, OpenCV from the first pixel
    # centre: shift by half a pixel (checked against detected corners in the tests).
    cam = pyrender.IntrinsicsCamera(K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5, znear=znear_m, zfar=zfar_m)
    scene.add(cam, pose=_CV_TO_GL)  # the world is the OpenCV camera frame
    for p in planes:
        scene.add(_quad_mesh(p), pose=np.asarray(p.T_cam_plane, dtype=np.float64))
    r = _renderer(int(width), int(height))
    rgb, _ = r.render(scene, flags=pyrender.RenderFlags.FLAT)
    return np.ascontiguousarray(rgb[..., :3])


def distort_image(image: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Apply lens distortion ``dist`` (OpenCV model) to an ideal pinhole ``image`` taken with ``K``.

    Each output (distorted) pixel samples the ideal image at its undistorted location.
    """
    h, w = image.shape[:2]
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pts = np.stack([u, v], -1).reshape(-1, 1, 2)
    ideal = cv2.undistortPointsIter(
        pts, K, np.asarray(dist, np.float64), None, K, (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-9)
    )
    ideal = ideal.reshape(h, w, 2).astype(np.float32)
    return cv2.remap(image, ideal[..., 0], ideal[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def degrade(image: np.ndarray, blur_sigma_px: float = 0.0, noise_sigma: float = 0.0, seed: int = 0) -> np.ndarray:
    """Gaussian blur (sigma in px) then additive Gaussian noise (sigma in grey levels), clipped to uint8."""
    out = image.astype(np.float32)
    if blur_sigma_px > 0:
        out = cv2.GaussianBlur(out, (0, 0), blur_sigma_px)
    if noise_sigma > 0:
        out = out + np.random.default_rng(seed).normal(0.0, noise_sigma, out.shape).astype(np.float32)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def random_view_poses(n: int, distance_range_m=(0.35, 0.6), max_tilt_deg: float = 40.0, seed: int = 0) -> np.ndarray:
    """``n`` camera-from-target poses ``T_cam_target: (n, 4, 4)`` spread over tilts and rolls (for boards/tags)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        d = rng.uniform(*distance_range_m)
        ang = np.radians(rng.uniform(-max_tilt_deg, max_tilt_deg))
        axis_ang = rng.uniform(0, np.pi)
        out.append(
            camera_facing(
                d, ang, (np.cos(axis_ang), np.sin(axis_ang), 0.0), rng.uniform(-0.4, 0.4), rng.uniform(-0.03, 0.03, 2)
            )
        )
    return np.stack(out)


def hand_eye_poses(
    n: int,
    T_tcp_cam: np.ndarray,
    T_base_board: np.ndarray,
    board_center_board=(0.0, 0.0, 0.0),
    distance_range_m=(0.3, 0.45),
    lateral_m: float = 0.15,
    roll_rad: float = 0.6,
    seed: int = 0,
):
    """``n`` eye-in-hand samples looking at a board: ``(T_base_tcp (n, 4, 4), T_cam_board (n, 4, 4))``, noise-free.

    Camera positions scatter above the board (base +z side of the board's face) within
    ``lateral_m``, at ``distance_range_m``, aimed near ``board_center_board`` (board frame) with a
    random roll about the optical axis, so motions rotate about diverse axes.
    """
    rng = np.random.default_rng(seed)
    T_base_board = np.asarray(T_base_board, dtype=np.float64)
    center = transform_points(T_base_board, np.asarray(board_center_board, dtype=np.float64)[None])[0]
    normal = -T_base_board[:3, 2]  # board +z points into the board; the camera stays on the printed side
    A, B = [], []
    for _ in range(n):
        lat = rng.uniform(-lateral_m, lateral_m, 3)
        lat -= normal * (lat @ normal)
        eye = center + normal * rng.uniform(*distance_range_m) + lat
        T_base_cam = look_at(eye, center + rng.normal(0.0, 0.02, 3)) @ make_T(
            so3_exp([0.0, 0.0, rng.uniform(-roll_rad, roll_rad)]), np.zeros(3)
        )
        A.append(compose(T_base_cam, invert_T(T_tcp_cam)))
        B.append(compose(invert_T(T_base_cam), T_base_board))
    return np.stack(A), np.stack(B)


def perturb_poses(T, position_sigma_m: float, rotation_sigma_rad: float, seed: int = 0) -> np.ndarray:
    """``T: (n, 4, 4)`` with Gaussian noise applied in each pose's own frame (per-axis sigmas)."""
    rng = np.random.default_rng(seed)
    T = np.asarray(T, dtype=np.float64)
    xi = np.concatenate(
        [
            rng.normal(0.0, position_sigma_m, T.shape[:-2] + (3,)),
            rng.normal(0.0, rotation_sigma_rad, T.shape[:-2] + (3,)),
        ],
        -1,
    )
    return T @ se3_exp(xi)
