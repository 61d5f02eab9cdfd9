"""Calibration errors: every one is a user-fixable :class:`~sim.errors.AdvobjError` with a clear message."""

from __future__ import annotations

from sim.errors import AdvobjError

__all__ = ["CalibrationError", "CalibrationFileError", "DegenerateDataError"]


class CalibrationError(AdvobjError, ValueError):
    """Calibration cannot proceed with the given input; the message says what to change."""


class CalibrationFileError(CalibrationError):
    """A calibration file is missing, unreadable or invalid; the message names the file and field."""

    def __init__(self, path, field: str, message: str):
        self.path = str(path)
        self.field = field
        super().__init__(f"{self.path}: {field}: {message}")


class DegenerateDataError(CalibrationError):
    """The data cannot determine the quantity asked for (e.g. a hand-eye set without diverse rotations)."""
