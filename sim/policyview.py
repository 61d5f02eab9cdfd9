"""What a policy sees of a camera frame: the image preprocessing of its card, and the camera it implies.

A policy is trained on square ``S x S`` renders of the scene camera. A real camera delivers
``W x H`` frames with its own intrinsics, so the frame must be brought to ``S x S`` the way the
policy's card says (``preprocess``):

* ``center_crop`` (the default): the largest centred square, then resized; the aspect ratio (and
  square pixels) stay, the sides outside the square are dropped.
* ``letterbox``: the whole frame, resized to fit, padded with mid-grey bars; nothing is dropped,
  but the picture fills only part of the input.
* ``resize``: squashed to ``S x S``; only for frames that are square already or for a policy
  trained on squashed frames (a 4:3 frame's pixels become 1.33 times wider than tall).

:func:`policy_view` applies it to an image (batch-free, ``(H, W, 3)``), :func:`policy_view_K`
gives the intrinsics of the camera the policy effectively looks through, and
:func:`view_mismatch` compares that with the training camera, so a session can say when a
real camera's field of view or mount differs from what the policy learned on.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from sim.geometry import rotation_angle

__all__ = ["PREPROCESS_MODES", "policy_view", "policy_view_K", "fov_deg", "view_mismatch"]

PREPROCESS_MODES = ("center_crop", "letterbox", "resize")
LETTERBOX_GREY = 128


def _check(mode: str) -> None:
    if mode not in PREPROCESS_MODES:
        raise ValueError(f"preprocess: expected one of {', '.join(PREPROCESS_MODES)}, got {mode!r}")


def _geometry(width: int, height: int, size: int, mode: str):
    """``(crop x0, y0, w, h), (scale x, y), (pad x, y), (resized w, h)`` of the preprocessing."""
    _check(mode)
    if mode == "center_crop":
        side = min(width, height)
        x0, y0 = (width - side) // 2, (height - side) // 2
        s = size / side
        return (x0, y0, side, side), (s, s), (0, 0), (size, size)
    if mode == "letterbox":
        s = size / max(width, height)
        w, h = max(1, round(width * s)), max(1, round(height * s))
        return (0, 0, width, height), (w / width, h / height), ((size - w) // 2, (size - h) // 2), (w, h)
    return (0, 0, width, height), (size / width, size / height), (0, 0), (size, size)


def policy_view(rgb: np.ndarray, size: int, mode: str = "center_crop") -> np.ndarray:
    """``rgb (H, W, 3)`` uint8 as the policy takes it: ``(size, size, 3)`` uint8."""
    rgb = np.asarray(rgb)
    H, W = rgb.shape[:2]
    if (H, W) == (size, size):
        _check(mode)
        return rgb
    (x0, y0, cw, ch), _, (px, py), (w, h) = _geometry(W, H, int(size), mode)
    crop = rgb[y0 : y0 + ch, x0 : x0 + cw]
    interp = cv2.INTER_AREA if w < cw else cv2.INTER_LINEAR  # area averaging when shrinking: no aliasing
    out = cv2.resize(crop, (w, h), interpolation=interp)
    if (w, h) != (size, size):
        canvas = np.full((size, size) + rgb.shape[2:], LETTERBOX_GREY, dtype=rgb.dtype)
        canvas[py : py + h, px : px + w] = out
        out = canvas
    return np.ascontiguousarray(out)


def policy_view_K(K: np.ndarray, width: int, height: int, size: int, mode: str = "center_crop") -> np.ndarray:
    """Intrinsics ``(3, 3)`` of the ``size x size`` view :func:`policy_view` makes of a ``width x height``
    frame with intrinsics ``K`` (pixel centres at integers: ``x' + 0.5 = s (x - x0 + 0.5) + pad``)."""
    (x0, y0, _, _), (sx, sy), (px, py), _ = _geometry(int(width), int(height), int(size), mode)
    K = np.asarray(K, dtype=np.float64)
    out = np.eye(3)
    out[0, 0], out[1, 1] = K[0, 0] * sx, K[1, 1] * sy
    out[0, 2] = (K[0, 2] - x0 + 0.5) * sx - 0.5 + px
    out[1, 2] = (K[1, 2] - y0 + 0.5) * sy - 0.5 + py
    return out


def fov_deg(K: np.ndarray, width: int, height: int) -> tuple[float, float]:
    """Horizontal and vertical field of view (deg) of a pinhole ``K`` at ``width x height``."""
    return (math.degrees(2 * math.atan(0.5 * width / K[0, 0])), math.degrees(2 * math.atan(0.5 * height / K[1, 1])))


def view_mismatch(
    K_view: np.ndarray,
    K_train: np.ndarray,
    size: int,
    T_tcp_cam: np.ndarray,
    T_tcp_cam_train: np.ndarray,
    fov_tol_deg: float = 5.0,
    mount_tol_m: float = 0.02,
    mount_tol_deg: float = 5.0,
) -> list[str]:
    """Sentences for every way the camera the policy looks through differs from its training camera
    beyond the tolerances: field of view, pixel aspect, principal point, mount position and angle."""
    out = []
    fx, fy = fov_deg(K_view, size, size)
    tx, ty = fov_deg(K_train, size, size)
    if abs(fx - tx) > fov_tol_deg or abs(fy - ty) > fov_tol_deg:
        out.append(
            f"field of view {fx:.1f} x {fy:.1f} deg as the policy sees it, trained at {tx:.1f} x {ty:.1f} deg "
            f"(tolerance {fov_tol_deg:g} deg): objects appear {'smaller' if fx > tx else 'larger'} than in training"
        )
    if abs(K_view[0, 0] / K_view[1, 1] - 1.0) > 0.02:
        out.append(
            f"pixels are {K_view[0, 0] / K_view[1, 1]:.2f} times as wide as tall in the policy's view (a "
            "squashed frame); "
            "use preprocess center_crop or letterbox"
        )
    off = np.hypot(K_view[0, 2] - K_train[0, 2], K_view[1, 2] - K_train[1, 2])
    if off > 0.05 * size:
        out.append(
            f"the principal point is {off:.1f} px ({100 * off / size:.0f} % of the image) from the training camera's"
        )
    T, U = np.asarray(T_tcp_cam, dtype=np.float64), np.asarray(T_tcp_cam_train, dtype=np.float64)
    dt = float(np.linalg.norm(T[:3, 3] - U[:3, 3]))
    da = math.degrees(rotation_angle(T[:3, :3], U[:3, :3]))
    if dt > mount_tol_m or da > mount_tol_deg:
        out.append(
            f"the camera mount T_tcp_cam differs from the training camera's by {100 * dt:.1f} cm and {da:.1f} deg "
            f"(tolerance {100 * mount_tol_m:g} cm, {mount_tol_deg:g} deg)"
        )
    return out
