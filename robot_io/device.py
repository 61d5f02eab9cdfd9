"""The lifecycle every device shares: ``connect()`` / ``disconnect()`` and ``with device:``."""

from __future__ import annotations

import abc

__all__ = ["Device"]


class Device(abc.ABC):
    """Idempotent connect/disconnect around the subclass's ``_open`` / ``_close``."""

    name: str = "device"

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

    def __enter__(self):
        self.connect()
        return self

    def __exit__(self, exc_type, exc, tb):
        self.disconnect()
        return False

    @abc.abstractmethod
    def _open(self) -> None: ...

    @abc.abstractmethod
    def _close(self) -> None: ...
