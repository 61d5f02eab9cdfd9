"""The camera interface every camera of a cell implements (the wrist camera and the fixed scene
cameras), and the frame it returns."""

from __future__ import annotations

import abc
import time
from dataclasses import dataclass

import numpy as np

# The calibration package owns the intrinsics type and its YAML file; cameras only carry it.
from calibration.intrinsics import CameraIntrinsics
from robot_io.device import Device
from robot_io.errors import MissingIntrinsicsError, RobotIOError

__all__ = ["Frame", "CameraIntrinsics", "Camera", "FrameSizeError", "scale_intrinsics"]


class FrameSizeError(RobotIOError, ValueError):
    """A camera delivered a frame of another size than the one it is calibrated (or rendered) at."""


@dataclass(frozen=True)
class Frame:
    """One colour image.

    ``timestamp_s`` is on the :func:`time.monotonic` clock (the safety layer's frame-age watchdog
    compares it with ``time.monotonic()``); ``seq`` counts frames delivered by the device, so a gap
    means frames were dropped in favour of newer ones.
    """

    rgb: np.ndarray  # (H, W, 3) uint8
    timestamp_s: float
    seq: int

    def __post_init__(self):
        if self.rgb.dtype != np.uint8 or self.rgb.ndim != 3 or self.rgb.shape[2] != 3:
            raise ValueError(f"Frame.rgb must be (H, W, 3) uint8, got {self.rgb.shape} {self.rgb.dtype}")

    @property
    def age_s(self) -> float:
        return time.monotonic() - self.timestamp_s


def scale_intrinsics(intr: CameraIntrinsics, width: int, height: int, what: str = "camera") -> CameraIntrinsics:
    """The same camera at another resolution of the same aspect ratio (:meth:`CameraIntrinsics.scaled`).

    Frames of another aspect ratio are a crop (or a squashed image) of what was calibrated: no
    rescaling of K describes them, so that is refused in one line naming ``what``.
    """
    if (width, height) == (intr.width, intr.height):
        return intr
    if width * intr.height != height * intr.width:
        raise MissingIntrinsicsError(
            f"{what}: frames are {width}x{height} but the intrinsics are for {intr.width}x{intr.height}, "
            "another aspect ratio (a crop): calibrate the camera at the frames' size"
        )
    return intr.scaled(width, height)


class Camera(Device):
    """A camera: ``connect()``/``disconnect()`` (or ``with camera:``), ``read()``, ``intrinsics``.

    ``label`` is the cell's name for it (``wrist`` or a scene camera's name). After
    :meth:`expect_frame_size`, ``read()`` refuses a frame of any other size in one line naming the
    camera (:class:`FrameSizeError`): a fixed camera's pose and intrinsics hold for one size.
    """

    name: str = "camera"
    label: str = "camera"
    frame_size: tuple[int, int] | None = None  # (W, H) px every frame must have; None: any
    _frame_size_source: str = ""

    def expect_frame_size(self, width: int, height: int, source: str) -> None:
        """Refuse frames other than ``width`` x ``height`` px; ``source`` says where that size comes
        from, for the message (``"its pose file front.yaml holds for"``)."""
        self.frame_size, self._frame_size_source = (int(width), int(height)), str(source)

    def read(self) -> Frame:
        """The newest frame; never one older than the previous ``read()``'s."""
        if not self._connected:
            raise RuntimeError(f"{self.name}: read() before connect()")
        frame = self._read()
        if self.frame_size is not None:
            h, w = frame.rgb.shape[:2]
            if (w, h) != self.frame_size:
                W, H = self.frame_size
                raise FrameSizeError(
                    f"camera {self.label!r}: a {w}x{h} px frame, but {self._frame_size_source} {W}x{H} px: set the "
                    "camera to deliver that size, or calibrate it again at this one"
                )
        return frame

    @property
    @abc.abstractmethod
    def intrinsics(self) -> CameraIntrinsics:
        """Intrinsics at the resolution ``read()`` returns.

        :class:`~robot_io.errors.MissingIntrinsicsError` when there are none (not in the hardware
        config, and the device does not report them).
        """

    @abc.abstractmethod
    def _read(self) -> Frame: ...
