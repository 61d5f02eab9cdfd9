"""Exclusive locks of a trial session and of the arm it drives (issue 25).

Two ``advobj trial run`` on one session would both "resume" it: the second clears the frames of
a trial the first is writing (or has just committed), and on hardware two processes would command
one arm. So a runner holds, for its whole life:

* the **session lock**: ``fcntl.flock`` on ``<db>-session-<name>.lock`` beside the database, and a
  ``session_locks`` row in the store naming the holder (host, pid, process start, since when);
  see :meth:`trials.real.store.TrialStore.lock_session`;
* the **arm lock**: ``fcntl.flock`` on a lock file keyed by the arm's address (a UR controller's
  host, a serial port's real device path) in the user's lock folder (``$XDG_RUNTIME_DIR/advobj-locks``,
  else ``<tmp>/advobj-locks-<uid>``, mode 0700), so two sessions in different databases cannot
  drive one arm. A ``sim`` arm lives in its own process's world and takes no arm lock.

The OS releases a ``flock`` when its process dies, however it dies; the lock files are never
removed (removing one while another process waits on it would let two processes hold "the" lock).
A lock file is opened with ``O_NOFOLLOW`` and must be a plain file with one link: a symlink or a
hard link planted at its path is refused, never written through. The holder writes its identity
into the file it holds (a JSON line), so a refused runner names the holder in its one-line error.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import os
import socket
import stat
import tempfile
import time
from pathlib import Path

from sim.errors import AdvobjError

__all__ = [
    "LockError",
    "LockBusy",
    "FileLock",
    "holder_identity",
    "describe_holder",
    "process_start",
    "pid_running",
    "user_lock_dir",
    "arm_lock_key",
    "arm_lock",
]


class LockError(AdvobjError, RuntimeError):
    """A lock file cannot be used (a symlink, a hard link, no permission); the message names it."""


class LockBusy(AdvobjError, RuntimeError):
    """Another process holds the session or the arm; the message names it (host, pid)."""


def process_start(pid: int) -> str | None:
    """What tells process ``pid`` apart from a later process given the same pid: the boot id and
    the process's start time in clock ticks since boot (``/proc``); None where unknown."""
    try:
        text = Path(f"/proc/{int(pid)}/stat").read_text()
        boot = Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except (OSError, ValueError):
        return None
    fields = text.rsplit(")", 1)[-1].split()  # the command name may hold spaces and parentheses
    return f"{boot}:{fields[19]}" if len(fields) > 19 else None  # field 22 of stat, starttime


def pid_running(pid, start: str | None = None) -> bool:
    """Whether process ``pid`` runs on this host (and, when ``start`` is known, is the same process
    as the one that recorded it, not a later one given the same pid)."""
    try:
        pid = int(pid)
    except (TypeError, ValueError):
        return False
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # it exists, owned by someone else
    if start is not None:
        now = process_start(pid)
        if now is not None and now != start:
            return False
    return True


def holder_identity(**extra) -> dict:
    """This process as a lock holder: host, pid, process start, since when (UTC), plus ``extra``."""
    return {
        "host": socket.gethostname(),
        "pid": os.getpid(),
        "proc_start": process_start(os.getpid()),
        "since": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        **extra,
    }


def describe_holder(h: dict | None) -> str:
    """``host H pid P (since T, session S)`` from a holder record; one line whatever it holds."""
    if not h:
        return "another process (it has not named itself yet)"

    def clean(v) -> str:
        return "".join(c if c.isprintable() else "?" for c in str(v))[:200]

    text = f"host {clean(h.get('host', '?'))} pid {clean(h.get('pid', '?'))}"
    more = [f"since {clean(h['since'])}"] if h.get("since") else []
    more += [f"session {clean(h['session'])}"] if h.get("session") else []
    more += [f"database {clean(h['db'])}"] if h.get("db") else []
    return text + (f" ({', '.join(more)})" if more else "")


class FileLock:
    """An exclusive, non-blocking ``flock`` on ``path``, holding the holder's identity as a JSON line.

    :meth:`acquire` returns None when the lock is taken, else the holder's record as read from the
    file (``{}``: the holder has not written it yet). :meth:`release` empties the file and unlocks it.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.fd: int | None = None

    @property
    def held(self) -> bool:
        return self.fd is not None

    def _open(self) -> int:
        flags = os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0)
        try:
            fd = os.open(self.path, flags, 0o600)
        except OSError as err:
            why = "a symlink; refused, never followed" if err.errno == errno.ELOOP else err.strerror
            raise LockError(f"{self.path}: cannot open the lock file ({why})") from None
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_nlink != 1:
            os.close(fd)
            raise LockError(
                f"{self.path}: the lock file is not a plain file with one link; refused (remove it if no run is active)"
            )
        return fd

    def _read(self, fd: int) -> dict:
        try:
            data = json.loads(os.pread(fd, 4096, 0).decode("utf-8", "replace") or "{}")
        except ValueError:
            return {}
        return data if isinstance(data, dict) else {}

    def peek(self) -> dict:
        """The holder's record as the file says now (``{}``: none, or unreadable)."""
        try:
            fd = os.open(self.path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
        except OSError:
            return {}
        try:
            return self._read(fd) if stat.S_ISREG(os.fstat(fd).st_mode) else {}
        finally:
            os.close(fd)

    def acquire(self, holder: dict, wait_for_name_s: float = 2.0) -> dict | None:
        if self.fd is not None:
            raise LockError(f"{self.path}: already held by this process")
        fd = self._open()
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            # held: name the holder. It writes its record right after it takes the lock; an empty or
            # stale record (a dead pid on this host) is the moment in between, so look again briefly.
            t_end = time.monotonic() + wait_for_name_s
            while True:
                other = self._read(fd)
                named = other and not (
                    other.get("host") == socket.gethostname() and not pid_running(other.get("pid"), None)
                )
                if named or time.monotonic() >= t_end:
                    os.close(fd)
                    return other
                time.sleep(0.05)
        except OSError as err:
            os.close(fd)
            raise LockError(f"{self.path}: cannot lock the file ({err.strerror})") from None
        data = (json.dumps(holder, default=str) + "\n").encode()
        os.ftruncate(fd, 0)
        os.pwrite(fd, data, 0)
        self.fd = fd
        return None

    def release(self) -> None:
        fd, self.fd = self.fd, None
        if fd is None:
            return
        try:
            os.ftruncate(fd, 0)  # no holder named any more
        except OSError:
            pass
        finally:
            os.close(fd)  # closing the descriptor drops the flock

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.release()


# ---------------------------------------------------------------------- the arm
def user_lock_dir() -> Path:
    """The folder of this user's device locks: ``$XDG_RUNTIME_DIR/advobj-locks``, else
    ``<tmp>/advobj-locks-<uid>``; created with mode 0700 and refused unless it is this user's own
    private directory (not a symlink, not writable by others)."""
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    if runtime and os.path.isabs(runtime) and os.path.isdir(runtime):
        d = Path(runtime) / "advobj-locks"
    else:
        d = Path(tempfile.gettempdir()) / f"advobj-locks-{os.getuid()}"
    try:
        d.mkdir(mode=0o700)
    except FileExistsError:
        pass
    except OSError as err:
        raise LockError(f"{d}: cannot create the device lock folder ({err.strerror})") from None
    st = os.lstat(d)
    if stat.S_ISLNK(st.st_mode) or not stat.S_ISDIR(st.st_mode) or st.st_uid != os.getuid() or st.st_mode & 0o077:
        raise LockError(
            f"{d}: the device lock folder must be a directory of this user's, mode 0700 (not a symlink); "
            "refused, remove or fix it"
        )
    return d


def arm_lock_key(arm_config) -> str | None:
    """The arm's identity for its lock: ``ur_rtde:<host>`` (lower case) or ``serial:<real device
    path>`` (a ``/dev/serial/by-id`` link and the ``/dev/ttyACM0`` it names are one arm; a pyserial
    URL as given). None for a ``sim`` arm: it exists only in its own process."""
    kind = arm_config.type
    if kind == "sim":
        return None
    if kind == "ur_rtde":
        return f"ur_rtde:{arm_config.host.strip().lower()}"
    if kind == "serial":
        port = arm_config.port.strip()
        return f"serial:{port if '://' in port else os.path.realpath(port)}"
    return f"{kind}:{json.dumps(arm_config.model_dump(mode='json'), sort_keys=True)}"


def arm_lock(arm_config, **holder) -> FileLock | None:
    """Take the arm's lock (None for a sim arm); :class:`LockBusy` naming the holder when another
    process holds it. ``holder``: what the lock file says besides host and pid (session, db)."""
    key = arm_lock_key(arm_config)
    if key is None:
        return None
    lock = FileLock(user_lock_dir() / f"arm-{hashlib.sha256(key.encode()).hexdigest()[:32]}.lock")
    other = lock.acquire(holder_identity(arm=key, **holder))
    if other is not None:
        raise LockBusy(
            f"arm {key}: in use by {describe_holder(other)}; one arm takes one session at a time: wait for that "
            "run to end or stop it (refused before any device connected)"
        )
    return lock
