"""Luxonis OAK cameras through the depthai v3 API (``pip install 'advobj[oak]'``).

Pipeline: ``Camera`` node built on a board socket -> ``requestOutput`` at the wanted size and
fps -> a host queue of one non-blocking slot, so the device overwrites stale frames and ``read()``
always gets the newest. Intrinsics come from the device's factory calibration unless a YAML is
given. The device's USB link failing surfaces as ``RuntimeError('... X_LINK ...')``; it becomes
:class:`CameraLostError`, and so does any depthai error while connecting (no OAK attached).
"""

from __future__ import annotations

import time

import numpy as np

from robot_io.cameras.base import Camera, CameraIntrinsics, Frame, scale_intrinsics
from robot_io.errors import CameraLostError, require_extra

__all__ = ["DepthAICamera"]


def _lost(err: Exception) -> Exception:
    if "X_LINK" in str(err):
        return CameraLostError(f"OAK camera lost (USB link error: {err}); check the cable and power, then reconnect")
    return err


def _not_opened(err: Exception) -> CameraLostError:
    # depthai v3 finds and boots the device when the Pipeline is created: no OAK attached, one
    # without USB permissions or one held by another process fails there ('No available devices').
    return CameraLostError(
        f"cannot open the OAK camera ({err}): check that it is plugged in (lsusb lists Luxonis "
        "devices as 03e7:...), that no other process uses it and, on Linux, that the Luxonis "
        "udev rules are installed"
    )


def _device_info(device, calib) -> dict[str, str]:
    # v3 names the chip id getDeviceId (v2: getMxId); the product name lives in the EEPROM data.
    out: dict[str, str] = {}
    get_id = getattr(device, "getDeviceId", None) or getattr(device, "getMxId", None)
    if get_id is not None:
        out["serial"] = str(get_id())
    try:
        name = calib.getEepromData().productName
        if name:
            out["product"] = str(name)
    except (AttributeError, RuntimeError):
        pass  # old calibration data has no EEPROM block; the id identifies the unit anyway
    return out


class DepthAICamera(Camera):
    """An OAK colour camera.

    Args:
        socket: board socket name, ``CAM_A`` (the RGB sensor on most OAK-D models), ``CAM_B``, ...
        width, height, fps: requested output (the ISP scales to it).
        intrinsics: a calibration to use instead of the device's factory calibration.
        timeout_ms: ``read()`` raises :class:`CameraLostError` when no frame arrives in time.
    """

    name = "depthai"

    def __init__(
        self,
        socket: str = "CAM_A",
        width: int = 640,
        height: int = 480,
        fps: float = 30.0,
        intrinsics: CameraIntrinsics | None = None,
        timeout_ms: float = 1000.0,
    ):
        super().__init__()
        self.socket = socket
        self.width, self.height, self.fps = int(width), int(height), float(fps)
        self.timeout_ms = float(timeout_ms)
        self._calibration = intrinsics
        self._device_intrinsics: CameraIntrinsics | None = None
        self._pipeline = None
        self._queue = None
        self._seq = 0
        self._device_info: dict[str, str] = {}  # device id and product name, read on connect

    def _open(self) -> None:
        dai = require_extra("depthai", "oak", "the OAK (depthai) camera")
        try:
            socket = getattr(dai.CameraBoardSocket, self.socket)
        except AttributeError:
            raise CameraLostError(f"unknown OAK board socket {self.socket!r} (expected CAM_A, CAM_B, ...)") from None
        try:
            pipeline = dai.Pipeline()
            cam = pipeline.create(dai.node.Camera).build(socket)
            out = cam.requestOutput((self.width, self.height), type=dai.ImgFrame.Type.BGR888i, fps=self.fps)
            self._queue = out.createOutputQueue(maxSize=1, blocking=False)
            pipeline.start()
            self._pipeline = pipeline
            device = pipeline.getDefaultDevice()
            calib = device.readCalibration()
            self._device_info = _device_info(device, calib)
            if self._calibration is None:
                K = np.asarray(calib.getCameraIntrinsics(socket, self.width, self.height), dtype=np.float64)
                dist = np.asarray(calib.getDistortionCoefficients(socket), dtype=np.float64)[:5]
                self._device_intrinsics = CameraIntrinsics(K, dist, self.width, self.height)
        except RuntimeError as err:
            self._close()
            raise _not_opened(err) from None
        self._seq = 0

    def identity(self) -> dict[str, str]:
        return {"socket": self.socket, **self._device_info}

    def _close(self) -> None:
        pipeline, self._pipeline, self._queue = self._pipeline, None, None
        if pipeline is not None:
            try:
                pipeline.stop()
            except RuntimeError:
                pass  # the device may already be gone; nothing left to release

    def _read(self) -> Frame:
        deadline = time.monotonic() + self.timeout_ms / 1000.0
        try:
            while True:
                msg = self._queue.tryGet()
                if msg is not None:
                    break
                if time.monotonic() > deadline:
                    raise CameraLostError(f"OAK camera {self.socket}: no frame within {self.timeout_ms:.0f} ms")
                time.sleep(0.001)
            bgr = msg.getCvFrame()
        except RuntimeError as err:
            raise _lost(err) from None
        now = time.monotonic()
        ts = now
        # Device timestamps are synced to the host's steady clock (= time.monotonic on Linux);
        # they include the USB transfer, so prefer them when they are plausible.
        get_ts = getattr(msg, "getTimestamp", None)
        if get_ts is not None:
            t = get_ts()
            t = t.total_seconds() if hasattr(t, "total_seconds") else float(t)
            if 0.0 <= now - t < 5.0:
                ts = t
        seq_fn = getattr(msg, "getSequenceNum", None)
        seq = int(seq_fn()) if seq_fn is not None else self._seq
        self._seq = seq + 1
        return Frame(np.ascontiguousarray(bgr[:, :, 2::-1]), ts, seq)

    @property
    def intrinsics(self) -> CameraIntrinsics:
        if self._calibration is not None:
            return scale_intrinsics(self._calibration, self.width, self.height)
        if self._device_intrinsics is None:
            raise CameraLostError("OAK intrinsics are read from the device: connect() first")
        return self._device_intrinsics
