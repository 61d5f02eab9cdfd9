"""Arm drivers: one interface (:class:`~robot_io.arms.base.Arm`) and its implementations.

* :mod:`robot_io.arms.sim`: the sim world's arm (a floating TCP, or joint-driven by a scene's URDF arm).
* :mod:`robot_io.arms.ur_rtde`: Universal Robots through ur-rtde (``servoL``/``speedL``/``moveL``;
  with a URDF also ``servoJ``/``moveJ``).
* :mod:`robot_io.arms.serial`: a controller speaking the advobj line protocol (``MOVE``;
  with a URDF also ``MOVEJ``); its device simulator is :mod:`robot_io.arms.serial_sim`.
* :mod:`robot_io.arms.feetech` (SO-100/SO-101, Feetech STS servos) and :mod:`robot_io.arms.dynamixel`
  (Koch, Dynamixel Protocol 2.0): servo-bus arms (:mod:`robot_io.arms.servo_bus`), always with a
  URDF; their byte-level twins are :mod:`robot_io.arms.feetech_sim` and :mod:`robot_io.arms.dynamixel_sim`.
* :mod:`robot_io.arms.pty_twin`: what the byte-level twins share (a pty, the thread serving it).

The hardware config (:mod:`robot_io.config`) builds them, and they reach trial code only wrapped in
:class:`robot_io.safety.SafeArm`. A target a driver will not execute is an
:class:`~robot_io.errors.ArmRefusedError` (nothing moved, the arm takes the next command), a fault an
:class:`~robot_io.errors.ArmFaultError`. No module here imports a vendor SDK or pyserial at import time.
"""

from robot_io.arms.base import Arm, Fault

__all__ = ["Arm", "Fault"]
