"""Wrist cameras and arm drivers behind one safety layer.

Layout: ``cameras/`` (OpenCV V4L2, depthai OAK, sim, replay), ``arms/`` (UR via ur-rtde, a serial
line-protocol arm, the sim's floating gripper), ``safety.py`` (the only way commands reach an arm)
and ``config.py`` (the validated hardware YAML plus the ``build_camera``/``build_arm`` factories).

Importing this package loads no vendor SDK and neither cv2 nor depthai: drivers import them on
``connect()`` so ``advobj --help`` and the sim-only paths stay fast.
"""

from robot_io.errors import (
    ArmFaultError,
    CameraLostError,
    HardwareConfigError,
    MissingExtraError,
    MissingIntrinsicsError,
    ProtocolError,
    RobotIOError,
    SafetyStop,
)

__all__ = [
    "RobotIOError",
    "HardwareConfigError",
    "MissingExtraError",
    "CameraLostError",
    "MissingIntrinsicsError",
    "ArmFaultError",
    "ProtocolError",
    "SafetyStop",
]
