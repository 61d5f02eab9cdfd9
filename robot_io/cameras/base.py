"""The camera interface every wrist camera implements, and the frame it returns."""

from __future__ import annotations

import abc
import time
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Frame", "CameraIntrinsics", "Camera"]


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


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics ``K`` (3, 3) at ``width x height`` px, plus OpenCV distortion coefficients."""

    K: np.ndarray
    width: int
    height: int
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self):
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3) or not np.isfinite(K).all():
            raise ValueError(f"K must be a finite (3, 3) matrix, got shape {K.shape}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", np.asarray(self.dist, dtype=np.float64).ravel())

    def scaled_to(self, width: int, height: int) -> "CameraIntrinsics":
        """The same camera at another resolution (same field of view, pixel-centre convention)."""
        if (width, height) == (self.width, self.height):
            return self
        sx, sy = width / self.width, height / self.height
        fx, fy = self.K[0, 0] * sx, self.K[1, 1] * sy
        cx, cy = (self.K[0, 2] + 0.5) * sx - 0.5, (self.K[1, 2] + 0.5) * sy - 0.5
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        return CameraIntrinsics(K, width, height, self.dist)


class Camera(abc.ABC):
    """A wrist camera: ``connect()``/``disconnect()`` (or ``with camera:``), ``read()``, ``intrinsics``."""

    name: str = "camera"

    def __init__(self):
        self._connected = False

    @property
    def connected(self) -> bool:
        return self._connected

    def connect(self) -> None:
        if not self._connected:
            self._open()
            self._connected = True

    def disconnect(self) -> None:
        if self._connected:
            self._connected = False
            self._close()

    def read(self) -> Frame:
        """The newest frame; never one older than the previous ``read()``'s."""
        if not self._connected:
            raise RuntimeError(f"{self.name}: read() before connect()")
        return self._read()

    @property
    @abc.abstractmethod
    def intrinsics(self) -> CameraIntrinsics:
        """Intrinsics at the resolution ``read()`` returns."""

    @abc.abstractmethod
    def _open(self) -> None: ...

    @abc.abstractmethod
    def _close(self) -> None: ...

    @abc.abstractmethod
    def _read(self) -> Frame: ...

    def __enter__(self):
        self.connect()
        return self

    def __exit__(self, *exc):
        self.disconnect()
        return False
