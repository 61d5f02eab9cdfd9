"""UVC / V4L2 cameras through OpenCV (webcams, the RealSense D435i colour node, capture cards).

The RealSense colour stream is a plain UVC node (usually YUYV), so no vendor SDK is needed. A
grabber thread drains the driver continuously and keeps only the newest frame: with the driver's
own queue at one buffer, ``read()`` returns an image at most one frame period old, never a
backlog the policy would act on late.
"""

from __future__ import annotations

import logging
import os
import stat
import sys
import threading
import time

import numpy as np

from robot_io.cameras.base import Camera, CameraIntrinsics, Frame, scale_intrinsics
from robot_io.errors import CameraLostError, MissingIntrinsicsError

__all__ = ["OpenCVCamera", "resolve_device"]

log = logging.getLogger(__name__)

V4L2_MAJOR = 81  # the Linux device number of video4linux nodes (/dev/videoN)


def resolve_device(device: str | int) -> str | int:
    """An index (int or digit string) stays an index; a path (e.g. ``/dev/v4l/by-id/...``) must exist.

    by-id / by-path symlinks are stable across reboots and USB re-enumeration, unlike
    ``/dev/videoN``; they are resolved here so OpenCV opens the node they point at.
    """
    if isinstance(device, int) or (isinstance(device, str) and device.isdigit()):
        return int(device)
    if not os.path.exists(device):
        raise CameraLostError(f"camera device {device} does not exist (is the camera plugged in?)")
    node = os.path.realpath(device)
    st = os.stat(node)
    mode = st.st_mode
    # Only a video4linux node is a camera: /dev/zero, /dev/null, a FIFO or a socket would be read as
    # one (or block). A regular file is left to OpenCV's V4L2 backend, which refuses it in one line.
    if stat.S_ISCHR(mode) and sys.platform.startswith("linux") and os.major(st.st_rdev) != V4L2_MAJOR:
        raise CameraLostError(f"camera device {device}: {node} is a character device but no video4linux camera")
    if not (stat.S_ISCHR(mode) or stat.S_ISREG(mode)):
        kind = "a directory" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode) else "no device node"
        raise CameraLostError(f"camera device {device}: {node} is {kind}, not a video4linux camera")
    return node


def _fourcc_str(code: float) -> str:
    c = int(code)
    return "".join(chr((c >> (8 * i)) & 0xFF) for i in range(4))


class OpenCVCamera(Camera):
    """A V4L2 camera by device path or index.

    Args:
        device: ``/dev/video0``, ``/dev/v4l/by-id/usb-...-video-index0`` or an index.
        width, height, fps: requested mode (``None`` keeps the driver's default).
        fourcc: pixel format, e.g. ``"MJPG"`` or ``"YUYV"``; set before the size because the
            sizes a UVC device offers depend on the format.
        intrinsics: calibration (rescaled if the device delivers another resolution).
        timeout_ms: ``read()`` raises :class:`CameraLostError` when no new frame arrives in time.
    """

    name = "opencv"

    def __init__(
        self,
        device: str | int = 0,
        width: int | None = None,
        height: int | None = None,
        fps: float | None = None,
        fourcc: str | None = None,
        intrinsics: CameraIntrinsics | None = None,
        timeout_ms: float = 1000.0,
        max_consecutive_failures: int = 10,
    ):
        super().__init__()
        if fourcc is not None and len(fourcc) != 4:
            raise ValueError(f"fourcc must be 4 characters, got {fourcc!r}")
        self.device = device
        self.requested = {"width": width, "height": height, "fps": fps, "fourcc": fourcc}
        self._calibration = intrinsics
        self.timeout_ms = float(timeout_ms)
        self.max_consecutive_failures = int(max_consecutive_failures)
        self.size: tuple[int, int] | None = None  # (width, height) actually delivered
        self.actual: dict = {}
        self._cap = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._cond = threading.Condition()
        self._latest: tuple[np.ndarray, float, int] | None = None
        self._last_read_seq = -1
        self._error: Exception | None = None
        self._warned_rescale = False
        self._opened: dict[str, str] = {}  # what connect() found: the resolved node, OpenCV's backend

    # ------------------------------------------------------------------ setup
    def _open(self) -> None:
        import cv2  # lazy: robot_io start-up (cv2)

        src = resolve_device(self.device)
        cap = cv2.VideoCapture(src, cv2.CAP_V4L2)
        if not cap.isOpened():
            cap.release()
            raise CameraLostError(f"cannot open camera {self.device} (busy, or not a V4L2 capture node)")
        self._opened = {"node": str(src)}
        try:
            self._opened["backend"] = str(cap.getBackendName())
        except Exception:  # noqa: BLE001 - informational only; some builds raise for unknown backends
            pass
        req = self.requested
        wanted: list[tuple[str, int, object]] = []
        if req["fourcc"]:
            wanted.append(("fourcc", cv2.CAP_PROP_FOURCC, req["fourcc"]))
        if req["width"]:
            wanted.append(("width", cv2.CAP_PROP_FRAME_WIDTH, req["width"]))
        if req["height"]:
            wanted.append(("height", cv2.CAP_PROP_FRAME_HEIGHT, req["height"]))
        if req["fps"]:
            wanted.append(("fps", cv2.CAP_PROP_FPS, req["fps"]))
        wanted.append(("buffersize", cv2.CAP_PROP_BUFFERSIZE, 1))
        for key, prop, value in wanted:
            raw = cv2.VideoWriter_fourcc(*value) if key == "fourcc" else float(value)
            cap.set(prop, raw)
        # Read back every property: drivers silently substitute the nearest mode they support.
        for key, prop, value in wanted:
            got = cap.get(prop)
            if key == "fourcc":
                got_v, ok = _fourcc_str(got), _fourcc_str(got) == value
            elif key == "fps":
                got_v, ok = float(got), abs(float(got) - float(value)) < 0.5
            else:
                got_v, ok = int(round(got)), int(round(got)) == int(value)
            self.actual[key] = got_v
            if not ok:
                log.warning("camera %s ignored %s=%s (device reports %s)", self.device, key, value, got_v)
        self.size = (int(round(cap.get(cv2.CAP_PROP_FRAME_WIDTH))), int(round(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))))
        self._cap = cap
        self._stop.clear()
        self._error = None
        self._latest = None
        self._last_read_seq = -1
        self._thread = threading.Thread(target=self._grab_loop, name=f"grab-{self.device}", daemon=True)
        self._thread.start()

    def _close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def identity(self) -> dict[str, str]:
        # A /dev/v4l/by-id path names the model and, for most UVC devices, its serial number.
        return {"device": str(self.device), **self._opened}

    # ------------------------------------------------------------------ frames
    def _grab_loop(self) -> None:
        seq, failures = 0, 0
        cap = self._cap
        while not self._stop.is_set():
            ok, img = cap.read()
            ts = time.monotonic()
            if not ok or img is None:
                failures += 1
                if failures >= self.max_consecutive_failures:
                    with self._cond:
                        self._error = CameraLostError(
                            f"camera {self.device} lost: {failures} consecutive failed reads (unplugged?)"
                        )
                        self._cond.notify_all()
                    return
                time.sleep(0.002)
                continue
            failures = 0
            with self._cond:
                self._latest = (img, ts, seq)
                self._cond.notify_all()
            seq += 1

    def _read(self) -> Frame:
        deadline = time.monotonic() + self.timeout_ms / 1000.0
        with self._cond:
            while self._error is None and (self._latest is None or self._latest[2] <= self._last_read_seq):
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise CameraLostError(f"camera {self.device}: no new frame within {self.timeout_ms:.0f} ms")
                self._cond.wait(remaining)
            if self._error is not None:
                raise self._error
            img, ts, seq = self._latest
            self._last_read_seq = seq
        return Frame(_to_rgb(img), ts, seq)

    @property
    def intrinsics(self) -> CameraIntrinsics:
        if self._calibration is None:
            raise MissingIntrinsicsError(
                f"camera {self.device}: no intrinsics; set camera.intrinsics in the hardware config"
            )
        if self.size is None:
            return self._calibration
        if self.size != (self._calibration.width, self._calibration.height) and not self._warned_rescale:
            self._warned_rescale = True
            log.warning(
                "intrinsics calibrated at %dx%d, camera delivers %dx%d: rescaling K",
                self._calibration.width,
                self._calibration.height,
                *self.size,
            )
        return scale_intrinsics(self._calibration, *self.size)


def _to_rgb(img: np.ndarray) -> np.ndarray:
    # OpenCV delivers BGR (YUYV and MJPG are decoded to BGR); grey sensors give 2-D arrays.
    if img.ndim == 2:
        img = img[:, :, None]
    if img.shape[2] == 1:
        return np.ascontiguousarray(np.repeat(img, 3, axis=2))
    return np.ascontiguousarray(img[:, :, 2::-1])
