"""What every byte-level device twin shares: a pseudo-terminal, a thread serving its master end, and
the command-line loop that runs one until Ctrl-C.

A twin (:class:`robot_io.arms.serial_sim.SerialArmSimulator`,
:class:`robot_io.arms.servo_bus.ServoBusSimulator` and the protocol twins on it) is a
:class:`PtyTwin`: :meth:`PtyTwin.on_pty` opens a pty pair (:func:`open_pty_pair`), starts the
twin's thread on the master end and returns the slave's path, which a driver opens like any serial
port, so the real bytes, framing and timing are exercised. The thread reads what has arrived (at
most :data:`POLL_S` apart) and hands it, with the time since the previous call, to the twin's
:meth:`PtyTwin._serve`; the twin answers with :meth:`PtyTwin._send`.
"""

from __future__ import annotations

import abc
import os
import select
import threading
import time
import tty
from typing import Callable

__all__ = ["open_pty_pair", "PtyTwin", "POLL_S", "serve_until_interrupted"]

#: The twin's thread looks for bytes at least this often (s); its devices' motion advances as often.
POLL_S = 0.002


def open_pty_pair() -> tuple[int, int, str]:
    """``(master_fd, slave_fd, slave_path)``; the slave is raw so nothing is echoed back.

    Keep ``slave_fd`` open while the simulator runs: once the last slave fd closes (the driver
    disconnecting), reads on the master fail with EIO and bytes written are lost.
    """
    master, slave = os.openpty()
    tty.setraw(slave)
    return master, slave, os.ttyname(slave)


class PtyTwin(abc.ABC):
    """A device twin served by a thread on a pty master.

    Args:
        fd: the pty master (:func:`open_pty_pair`).
        keep_fd: the slave fd to keep open while the twin runs (see :func:`open_pty_pair`); closed
            with the master by :meth:`close`.
    """

    def __init__(self, fd: int, keep_fd: int | None = None):
        self.fd = fd
        self._keep_fd = keep_fd
        self._stop_evt = threading.Event()
        self._thread: threading.Thread | None = None

    @classmethod
    def on_pty(cls, *args, **kwargs):
        """A started twin on a fresh pty, and the port path for the driver: ``(twin, path)``. ``args``
        and ``kwargs`` are the twin's own, after its ``fd`` (``keep_fd`` is set here)."""
        master, slave, path = open_pty_pair()
        twin = cls(master, *args, keep_fd=slave, **kwargs)
        twin.start()
        return twin, path

    @abc.abstractmethod
    def _serve(self, data: bytes, dt_s: float, now_s: float) -> None:
        """Take ``data`` (possibly empty), the bytes that arrived, and advance the device by ``dt_s``
        to ``now_s`` (``time.monotonic()``)."""

    # ------------------------------------------------------------------ lifecycle
    def start(self):
        """Start serving the pty in a daemon thread; returns the twin."""
        self._thread = threading.Thread(target=self._run, name=type(self).__name__, daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop the thread and close both ends of the pty."""
        self._stop_evt.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        for fd in (self.fd, self._keep_fd):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ------------------------------------------------------------------ I/O
    def _send(self, data: bytes) -> None:
        try:
            os.write(self.fd, data)
        except OSError:
            pass  # nobody listening (port closed); a real line drops the bytes too

    def _run(self) -> None:
        t_prev = time.monotonic()
        while not self._stop_evt.is_set():
            try:
                ready, _, _ = select.select([self.fd], [], [], POLL_S)
                data = os.read(self.fd, 4096) if ready else b""
            except OSError:  # no slave open yet, or the driver just closed it
                data = b""
                time.sleep(POLL_S)
            now = time.monotonic()
            self._serve(data, now - t_prev, now)
            t_prev = now


def _print(text: str) -> None:
    print(text, flush=True)


def serve_until_interrupted(twin: PtyTwin, message: str, say: Callable[[str], None] = _print) -> None:
    """Run a started ``twin`` until Ctrl-C, after telling the user ``message`` (its port: ``say``
    prints it at once), then close it (the ``python -m robot_io.arms.<twin>`` entry points)."""
    try:
        say(message)
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        twin.close()
