"""Cameras (the wrist camera, fixed scene cameras): one interface (:class:`~robot_io.cameras.base.Camera`),
four implementations.

The implementations live in their own modules and are imported by the factory in
:mod:`robot_io.config` only when a config names them.
"""

from robot_io.cameras.base import Camera, CameraIntrinsics, Frame, FrameSizeError

__all__ = ["Camera", "CameraIntrinsics", "Frame", "FrameSizeError"]
