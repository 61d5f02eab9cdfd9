"""The cameras' calibration for an import: the calibration package's files, read into what a
recording holds (``K``, distortion, a mount and its pose), each problem one line naming the flag.

* ``--intrinsics CAMERA=FILE``: a camera YAML (ours, ROS ``camera_info`` or OpenCV's), read by
  :func:`calibration.intrinsics.load_camera_yaml`. Calibrated at another resolution of the same
  aspect ratio, it is scaled to the frames' (:meth:`CameraIntrinsics.scaled`); another aspect is refused.
* ``--extrinsics CAMERA=FILE``: the hand-eye result (``T_tcp_cam``, ``advobj calibrate handeye``'s
  file): a wrist camera; or the pose file of ``advobj calibrate scene-camera`` (``T_table_cam``): a
  fixed camera's pose in the table frame.
* ``--table-frame FILE``: ``T_base_table``, as ``advobj trial run`` takes it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calibration.errors import CalibrationFileError
from calibration.handeye import load_hand_eye_yaml
from calibration.intrinsics import CameraIntrinsics, load_camera_yaml
from calibration.io import load_scene_camera_pose, read_yaml
from robot_io.config import load_T_tcp_cam
from sim.errors import AdvobjError
from sim.geometry import invert_T
from trials.real.session import load_T_base_table

__all__ = [
    "RecordImportError",
    "camera_intrinsics",
    "intrinsics_at_size",
    "camera_extrinsics",
    "wrist_T_tcp_cam",
    "table_frame",
    "check_cameras_named",
]


class RecordImportError(AdvobjError, ValueError):
    """An input of ``advobj record import`` is missing or inconsistent; the one-line message names the flag."""


def camera_intrinsics(path: Path, camera: str, size: tuple[int, int], flag: str = "--intrinsics"):
    """``(K (3, 3), dist (n,))`` of the camera YAML ``path`` at the frames' ``size`` (width, height) px."""
    try:
        intr = load_camera_yaml(path)
    except CalibrationFileError as err:
        raise RecordImportError(f"{flag} {camera}={path}: {err}") from None
    return intrinsics_at_size(intr, camera, size, f"{flag} {camera}={path}")


def intrinsics_at_size(intr: CameraIntrinsics, camera: str, size: tuple[int, int], where: str):
    """``(K, dist)`` of ``intr`` at ``size`` (width, height) px: scaled from another resolution of the same
    aspect ratio, refused (naming ``where``) for another aspect."""
    w, h = size
    if (intr.width, intr.height) != (w, h):
        if intr.width * h != intr.height * w:
            raise RecordImportError(
                f"{where}: calibrated at {intr.width}x{intr.height} px, the frames of camera {camera} are {w}x{h} px "
                "(another aspect ratio: another camera mode)"
            )
        intr = intr.scaled(w, h)
    return intr.K, intr.dist


def camera_extrinsics(path: Path, camera: str, flag: str = "--extrinsics") -> tuple[str, np.ndarray]:
    """``(mount, T)`` from ``path``: the hand-eye result (``tcp``, ``T_tcp_cam``) or a fixed camera's pose
    file (``table``, ``T_table_cam``: :func:`calibration.io.load_scene_camera_pose`)."""
    where = f"{flag} {camera}={path}"
    try:
        data = read_yaml(path)
        if isinstance(data, dict) and "T_table_cam" in data:
            return "table", load_scene_camera_pose(path).T
        if isinstance(data, dict) and "T_tcp_cam" in data:
            return "tcp", load_hand_eye_yaml(path)
    except CalibrationFileError as err:
        raise RecordImportError(f"{where}: {err}") from None
    raise RecordImportError(
        f"{where}: expected T_tcp_cam (a wrist camera: the hand-eye result of 'advobj calibrate handeye') or "
        "T_table_cam (a fixed camera's pose in the table frame, from 'advobj calibrate scene-camera')"
    )


def wrist_T_tcp_cam(path: Path, camera: str, flag: str) -> np.ndarray:
    """``T_tcp_cam`` of a wrist camera's file: the format a session's hardware YAML names
    (:func:`robot_io.config.load_T_tcp_cam`) or the hand-eye result; a fixed camera's pose is refused."""
    try:
        data = read_yaml(path)
        if isinstance(data, dict) and "T_table_cam" in data:
            raise RecordImportError(f"{flag} {camera}={path}: a session's camera is on the wrist; expected T_tcp_cam")
        if isinstance(data, dict) and "T_tcp_cam" in data and len(data) > 1:
            return load_hand_eye_yaml(path)
        return load_T_tcp_cam(path)
    except CalibrationFileError as err:
        raise RecordImportError(f"{flag} {camera}={path}: {err}") from None


def table_frame(path: Path) -> np.ndarray:
    """``T_table_base`` from ``--table-frame`` (a YAML holding ``T_base_table``)."""
    try:
        return invert_T(load_T_base_table(path))
    except CalibrationFileError as err:
        raise RecordImportError(f"--table-frame: {err}") from None


def check_cameras_named(given: dict, cameras, flag: str) -> None:
    """Refuse a ``flag CAMERA=FILE`` naming a camera that is not imported."""
    extra = sorted(set(given) - set(cameras))
    if extra:
        raise RecordImportError(
            f"{flag} {extra[0]}=...: no camera {extra[0]!r} is imported (cameras: {', '.join(cameras)})"
        )
