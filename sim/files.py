"""Reading a file that a user or a data file names: a regular file of bounded size, checked on the open file.

A path from the command line or from inside a file may name anything: a FIFO (opening it to read
waits for a writer), a device (``/dev/zero`` never ends; opening a serial port can reset the board
behind it), a socket, a directory, a symlink to any of these, or a file of gigabytes. Every reader
of such a path goes through this module:

* :func:`check_regular`: the question asked before anything opens the path (``os.stat``, or
  ``os.lstat`` with ``follow_symlinks=False``): a regular file of at most ``max_bytes``? For a
  library that opens the path itself (OpenCV, PIL, pyarrow, a video decoder).
* :func:`open_regular`: the same question, then the path opened non-blocking (a FIFO put there
  since is never waited on) and asked again of the open file (``os.fstat``), so what is read is
  what was checked.
* :func:`read_regular`: the bytes of :func:`open_regular`'s file, never more than ``max_bytes``,
  even when the file grows while it is read.

And the one way a small output file is written whole or not at all: :func:`write_atomic`.

Each refusal is one :class:`FileRefusedError`: its ``reason`` (one of :data:`REASONS`) and the
facts behind it (``size``, ``kind``, ``strerror``) let each reader word it in its own error class
(:meth:`FileRefusedError.problem` takes a reader's own wording for some reasons); ``str(err)`` is
``"<path>: <problem>"`` in the standard words of :data:`WORDS`.
"""

from __future__ import annotations

import errno
import os
import stat
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import BinaryIO

from sim.errors import AdvobjError

__all__ = [
    "REASONS",
    "WORDS",
    "FileRefusedError",
    "file_kind",
    "not_a_regular_file",
    "check_regular",
    "open_regular",
    "read_regular",
    "write_atomic",
]

#: Why a path was refused: nothing there, an OS error, a directory, anything else that is not a
#: regular file (a FIFO, device, socket, or a symlink where links are not followed), larger than
#: the limit before reading, or grown past the limit while it was read.
REASONS = ("missing", "unreadable", "directory", "special", "too_large", "grew")

#: The standard words of each reason; fields: ``size`` (bytes, as found), ``max_bytes``,
#: ``kind`` (:func:`file_kind`) and ``strerror`` (the OS's words).
WORDS: dict[str, str] = {
    "missing": "missing",
    "unreadable": "cannot read ({strerror})",
    "directory": "is a directory, expected a file",
    "special": "is {kind}, not a regular file",
    "too_large": "{size} bytes, over the limit of {max_bytes} bytes",
    "grew": "over the limit of {max_bytes} bytes",
}

_CHUNK_BYTES = 1 << 24  # read in pieces: a large limit never allocates the limit for a small file


class FileRefusedError(AdvobjError, ValueError):
    """``path`` is no file to read: ``reason`` (one of :data:`REASONS`) says why, in one line."""

    def __init__(
        self,
        path,
        reason: str,
        max_bytes: int,
        size: int | None = None,
        kind: str = "",
        strerror: str = "",
    ):
        if reason not in REASONS:
            raise ValueError(f"FileRefusedError: reason {reason!r} is none of {REASONS}")
        self.path, self.reason, self.max_bytes = str(path), reason, max_bytes
        self.size, self.kind, self.strerror = size, kind, strerror
        super().__init__(f"{self.path}: {self.problem()}")

    def __reduce__(self):  # pickled whole (a Ray worker hands it back), not from the message alone
        return type(self), (self.path, self.reason, self.max_bytes, self.size, self.kind, self.strerror)

    def problem(self, words: Mapping[str, str] | None = None) -> str:
        """Why, without the path: ``words[reason]`` (a reader's own wording of some reasons) or
        :data:`WORDS`' standard one, filled with the facts."""
        template = (words or {}).get(self.reason, WORDS[self.reason])
        return template.format(size=self.size, max_bytes=self.max_bytes, kind=self.kind, strerror=self.strerror)


def file_kind(mode: int) -> str:
    """What a file of ``st_mode`` ``mode`` is, in words: ``"a regular file"``, ``"a directory"``,
    ``"a FIFO (named pipe)"``, ``"a character device"``, ``"a block device"``, ``"a socket"``,
    ``"a symbolic link"`` or ``"a special file"``."""
    for test, words in (
        (stat.S_ISREG, "a regular file"),
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
        (stat.S_ISLNK, "a symbolic link"),
    ):
        if test(mode):
            return words
    return "a special file"


def not_a_regular_file(path) -> str | None:
    """Why ``path`` is no file to read (``"is a FIFO (named pipe), not a regular file"``: a device
    such as ``/dev/zero``, a FIFO, a socket), or None. Asked without opening the path. A missing
    path, one that cannot be asked about, or a directory gives None (the reader reports those in its
    own words)."""
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return None
    if stat.S_ISREG(mode) or stat.S_ISDIR(mode):
        return None
    return WORDS["special"].format(kind=file_kind(mode))


def _refusal(path, st: os.stat_result, max_bytes: int) -> FileRefusedError | None:
    """The refusal of a file of ``st`` as a file of at most ``max_bytes``, or None when it is one."""
    if stat.S_ISDIR(st.st_mode):
        return FileRefusedError(path, "directory", max_bytes, kind="a directory")
    if not stat.S_ISREG(st.st_mode):
        return FileRefusedError(path, "special", max_bytes, kind=file_kind(st.st_mode))
    if st.st_size > max_bytes:
        return FileRefusedError(path, "too_large", max_bytes, size=st.st_size)
    return None


def _os_refusal(path, err: OSError, max_bytes: int) -> FileRefusedError:
    reason = "missing" if err.errno == errno.ENOENT else "unreadable"
    return FileRefusedError(path, reason, max_bytes, strerror=err.strerror or str(err))


def _check_max_bytes(max_bytes: int) -> None:
    if isinstance(max_bytes, bool) or not isinstance(max_bytes, int) or max_bytes < 0:
        raise ValueError(f"max_bytes must be a whole number of bytes >= 0, got {max_bytes!r}")


def check_regular(path: str | Path, max_bytes: int, *, follow_symlinks: bool = True) -> int:
    """The size (bytes) of ``path`` when it is a regular file of at most ``max_bytes``; else
    :class:`FileRefusedError`. Nothing opens the path: it is only asked about (with
    ``follow_symlinks=False`` a symlink is refused as ``special``, whatever it points at)."""
    _check_max_bytes(max_bytes)
    try:
        st = os.stat(path, follow_symlinks=follow_symlinks)
    except OSError as err:
        raise _os_refusal(path, err, max_bytes) from None
    except ValueError as err:  # an embedded NUL byte: no such file can exist
        raise FileRefusedError(path, "missing", max_bytes, strerror=str(err)) from None
    refusal = _refusal(path, st, max_bytes)
    if refusal is not None:
        raise refusal
    return st.st_size


def open_regular(path: str | Path, max_bytes: int, *, follow_symlinks: bool = True) -> BinaryIO:
    """``path`` open for binary reading (the caller closes it; use it as a context manager) when it
    is a regular file of at most ``max_bytes``: checked by :func:`check_regular` before it is
    opened, then on the open file. The open never blocks (``O_NONBLOCK``: a FIFO put at the path
    after the first check is refused, not waited on); with ``follow_symlinks=False`` it never
    follows a link (``O_NOFOLLOW``). Refusals raise :class:`FileRefusedError`."""
    check_regular(path, max_bytes, follow_symlinks=follow_symlinks)
    flags = os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0) | (0 if follow_symlinks else os.O_NOFOLLOW)
    try:
        fd = os.open(path, flags)
    except OSError as err:
        if err.errno == errno.ELOOP and not follow_symlinks:  # a link put at the path since the check
            raise FileRefusedError(path, "special", max_bytes, kind="a symbolic link") from None
        raise _os_refusal(path, err, max_bytes) from None
    try:
        refusal = _refusal(path, os.fstat(fd), max_bytes)
    except OSError as err:
        os.close(fd)
        raise _os_refusal(path, err, max_bytes) from None
    if refusal is not None:
        os.close(fd)
        raise refusal
    return os.fdopen(fd, "rb")


def read_regular(path: str | Path, max_bytes: int, *, follow_symlinks: bool = True) -> bytes:
    """The bytes of ``path``, a regular file of at most ``max_bytes`` (:func:`open_regular`'s
    checks). Memory stays within ``max_bytes``: a file that grows past it while it is read is
    refused (reason ``grew``). Refusals, and an OS error while reading, raise :class:`FileRefusedError`."""
    with open_regular(path, max_bytes, follow_symlinks=follow_symlinks) as f:
        chunks, left = [], max_bytes + 1
        try:
            while left > 0:
                chunk = f.read(min(left, _CHUNK_BYTES))
                if not chunk:
                    break
                chunks.append(chunk)
                left -= len(chunk)
        except OSError as err:
            raise _os_refusal(path, err, max_bytes) from None
    if left <= 0:
        raise FileRefusedError(path, "grew", max_bytes)
    return b"".join(chunks)


def write_atomic(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` whole or not at all: a fresh temporary file beside it (``O_EXCL``,
    a random name starting ``.<name>.``), readable by all (0644), renamed over ``path``. A failure
    leaves neither a half-written file nor the temporary. Returns ``path``."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return path
