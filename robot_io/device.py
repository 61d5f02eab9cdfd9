"""What every device shares: ``connect()`` / ``disconnect()``, ``with device:``, and ``identity()``."""

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
    def identity(self) -> dict[str, str]:
        """What identifies this unit, for the session record (``trials.real.session.device_identity``).

        Always the configured address (device path, host, port, socket); once connected also what
        the device reported when it connected, with its hardware serial number, when it has one,
        under ``serial``. Cheap and side-effect free (no I/O): callable before ``connect()``.
        """

    @abc.abstractmethod
    def _open(self) -> None: ...

    @abc.abstractmethod
    def _close(self) -> None: ...
