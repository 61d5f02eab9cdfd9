"""Errors raised by robot_io; all are :class:`sim.errors.AdvobjError`, so the CLI prints them cleanly."""

from __future__ import annotations

import importlib

from sim.errors import AdvobjError

__all__ = [
    "RobotIOError",
    "HardwareConfigError",
    "MissingExtraError",
    "CameraLostError",
    "MissingIntrinsicsError",
    "ArmFaultError",
    "ArmRefusedError",
    "ProtocolError",
    "SafetyStop",
    "require_extra",
]


class RobotIOError(AdvobjError):
    """Base of every camera, arm and safety error."""


class HardwareConfigError(RobotIOError, ValueError):
    """A hardware or calibration YAML that does not validate; the message names file and field."""


class MissingExtraError(RobotIOError, ImportError):
    """A vendor SDK is not installed; the message names the pip extra that provides it."""


class CameraLostError(RobotIOError):
    """The camera cannot be opened or stopped delivering frames (unplugged, X_LINK error, read timeout)."""


class MissingIntrinsicsError(RobotIOError):
    """A camera asked for intrinsics it does not have (they are optional: only tag locating needs them)."""


class ArmFaultError(RobotIOError):
    """The arm reports a protective stop, an emergency stop or a lost connection."""

    def __init__(self, fault):
        self.fault = fault
        super().__init__(str(fault))


class ArmRefusedError(RobotIOError):
    """The arm refused one command it will not execute: nothing moved, no fault is latched, and the
    arm takes the next command. Every driver raises it for such a target (a pose out of reach, a
    joint past its range: the serial arm's ``ERR RANGE``, a servo-bus arm's IK or servo-turn
    refusal, a UR controller rejecting a move without a fault, the sim arm's IK); the message names
    the arm and the target. The trial runner ends that trial with ``refused: ...``, as it does for
    the safety layer's refusal, and the session goes on (an :class:`ArmFaultError` is a fault instead:
    the arm cannot move until it is cleared)."""


class ProtocolError(RobotIOError):
    """The serial arm answered garbage, the wrong protocol version, or not at all."""


class SafetyStop(RobotIOError):
    """The safety layer stopped the arm and ended the trial (e.g. maximum trial duration)."""


def require_extra(module: str, extra: str, what: str):
    """Import a vendor SDK lazily; a missing one becomes an error naming the pip extra."""
    try:
        return importlib.import_module(module)
    except ImportError as err:
        raise MissingExtraError(
            f"{what} needs the '{module}' module, which is not installed: pip install 'advobj[{extra}]' ({err})"
        ) from None
