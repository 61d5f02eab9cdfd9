"""Arm drivers: one interface (:class:`~robot_io.arms.base.Arm`), three implementations plus the serial
device simulator.

The drivers are imported by the factory in :mod:`robot_io.config` only when a config names them,
and reach trial code only wrapped in :class:`robot_io.safety.SafeArm`.
"""

from robot_io.arms.base import Arm, Fault

__all__ = ["Arm", "Fault"]
