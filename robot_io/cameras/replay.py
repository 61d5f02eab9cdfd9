"""Replays recorded frames (a folder of images or a video file) as if they came from a camera.

Useful to run a policy on a recorded real session, and for tests. Frames are timestamped when
they are read, so the safety layer's frame-age watchdog sees them as fresh; with ``fps`` set,
``read()`` paces playback to that rate.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from PIL import Image

from robot_io.cameras.base import Camera, CameraIntrinsics, Frame, scale_intrinsics
from robot_io.errors import CameraLostError, MissingIntrinsicsError, RobotIOError

__all__ = ["ReplayCamera", "IMAGE_SUFFIXES"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


class ReplayCamera(Camera):
    """Plays ``path``: a directory of images (sorted by name) or a video file.

    Args:
        loop: start over at the end instead of raising :class:`CameraLostError`.
        fps: pace ``read()`` to this rate (``None``: as fast as called).
        intrinsics: calibration of the camera that recorded the frames.
    """

    name = "replay"

    def __init__(
        self, path: str | Path, loop: bool = False, fps: float | None = None, intrinsics: CameraIntrinsics | None = None
    ):
        super().__init__()
        self.path = Path(path)
        self.loop = bool(loop)
        self.fps = fps
        self._calibration = intrinsics
        self._files: list[Path] = []
        self._cap = None
        self._index = 0
        self._seq = 0
        self._next_due = 0.0
        self.size: tuple[int, int] | None = None

    def _open(self) -> None:
        if self.path.is_dir():
            self._files = sorted(p for p in self.path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
            if not self._files:
                raise RobotIOError(f"replay folder {self.path} holds no images ({', '.join(IMAGE_SUFFIXES)})")
        elif self.path.is_file():
            import cv2  # lazy: robot_io start-up (cv2)

            self._cap = cv2.VideoCapture(str(self.path))
            if not self._cap.isOpened():
                raise RobotIOError(f"replay file {self.path} is not a readable video")
        elif self.path.exists():  # a FIFO or a device would block or never end
            raise RobotIOError(f"replay path {self.path} is neither a folder of images nor a regular (video) file")
        else:
            raise RobotIOError(f"replay path {self.path} does not exist")
        self._index = 0
        self._seq = 0
        self._next_due = time.monotonic()

    def _close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def _next_image(self) -> np.ndarray | None:
        if self._files:
            if self._index >= len(self._files):
                return None

            with Image.open(self._files[self._index]) as im:
                rgb = np.asarray(im.convert("RGB"))
            self._index += 1
            return rgb
        ok, bgr = self._cap.read()
        if not ok:
            return None
        return np.ascontiguousarray(bgr[:, :, 2::-1])

    def identity(self) -> dict[str, str]:
        return {"path": str(self.path)}

    def _rewind(self) -> None:
        self._index = 0
        if self._cap is not None:
            import cv2  # lazy: robot_io start-up (cv2)

            self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)

    def _read(self) -> Frame:
        if self.fps:
            delay = self._next_due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            self._next_due = max(self._next_due, time.monotonic()) + 1.0 / self.fps
        rgb = self._next_image()
        if rgb is None and self.loop:
            self._rewind()
            rgb = self._next_image()
        if rgb is None:
            raise CameraLostError(f"replay {self.path} ended after {self._seq} frames")
        self.size = (rgb.shape[1], rgb.shape[0])
        frame = Frame(rgb, time.monotonic(), self._seq)
        self._seq += 1
        return frame

    @property
    def intrinsics(self) -> CameraIntrinsics:
        if self._calibration is None:
            raise MissingIntrinsicsError(
                f"replay {self.path}: no intrinsics; set camera.intrinsics in the hardware config"
            )
        return (
            self._calibration
            if self.size is None
            else scale_intrinsics(self._calibration, *self.size, f"replay {self.path}")
        )
