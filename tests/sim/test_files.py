"""sim.files: the one check of a file named by a user or a data file (regular, bounded, checked on
the open file), on real FIFOs, devices, directories, symlinks and /proc files."""

from __future__ import annotations

import os
import pickle
import socket
import threading
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sim import files
from sim.files import (
    REASONS,
    WORDS,
    FileRefusedError,
    check_regular,
    file_kind,
    not_a_regular_file,
    open_regular,
    read_regular,
)

READERS = {
    "check": lambda p, n, **kw: check_regular(p, n, **kw),
    "open": lambda p, n, **kw: open_regular(p, n, **kw).close(),
    "read": lambda p, n, **kw: read_regular(p, n, **kw),
}


def _refused(reader, path, max_bytes=1024, **kw) -> FileRefusedError:
    """The refusal of ``path``, asked in a thread: a reader that blocked would fail the test, not hang it."""
    out = {}

    def run():
        try:
            READERS[reader](path, max_bytes, **kw)
        except FileRefusedError as err:
            out["err"] = err

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(10)
    assert not t.is_alive(), f"{reader} blocked on {path}"
    assert "err" in out, f"{reader} accepted {path}"
    err = out["err"]
    assert str(err).startswith(f"{path}: ") and "\n" not in str(err)
    return err


@pytest.fixture
def fifo(tmp_path) -> Path:
    p = tmp_path / "pipe.png"
    os.mkfifo(p)  # no writer: opening it to read without O_NONBLOCK would wait forever
    return p


@pytest.mark.parametrize("reader", READERS)
def test_a_fifo_is_refused_without_blocking(reader, fifo):
    err = _refused(reader, fifo)
    assert (err.reason, err.kind) == ("special", "a FIFO (named pipe)")
    assert str(err) == f"{fifo}: is a FIFO (named pipe), not a regular file"


@pytest.mark.parametrize("reader", READERS)
def test_dev_zero_and_a_symlink_to_it_are_refused_as_a_device_never_read(reader, tmp_path):
    link = tmp_path / "zero.stl"
    link.symlink_to("/dev/zero")
    for path in (Path("/dev/zero"), link):
        err = _refused(reader, path)
        assert (err.reason, err.kind) == ("special", "a character device")


@pytest.mark.parametrize("reader", READERS)
def test_a_directory_is_refused_as_one(reader, tmp_path):
    err = _refused(reader, tmp_path)
    assert err.reason == "directory" and err.problem() == "is a directory, expected a file"


@pytest.mark.parametrize("reader", READERS)
def test_a_unix_socket_is_refused(reader, tmp_path):
    path = tmp_path / "s.sock"
    s = socket.socket(socket.AF_UNIX)
    try:
        s.bind(str(path))
        err = _refused(reader, path)
    finally:
        s.close()
    assert (err.reason, err.kind) == ("special", "a socket")


@pytest.mark.parametrize("reader", READERS)
def test_a_missing_path_and_an_impossible_one_are_missing(reader, tmp_path):
    err = _refused(reader, tmp_path / "none.png")
    assert err.reason == "missing" and err.strerror == "No such file or directory"
    assert err.problem() == "missing" and err.problem({"missing": "cannot read ({strerror})"}) == (
        "cannot read (No such file or directory)"
    )
    assert _refused(reader, str(tmp_path / "a\0b")).reason == "missing"  # a NUL byte: no such file can exist


@pytest.mark.parametrize("reader", READERS)
def test_a_symlink_is_followed_by_default_and_refused_when_links_are_not(reader, tmp_path):
    real = tmp_path / "real.bin"
    real.write_bytes(b"abc")
    link = tmp_path / "link.bin"
    link.symlink_to(real)
    READERS[reader](link, 3)  # followed: the target is a fine file
    err = _refused(reader, link, 3, follow_symlinks=False)
    assert (err.reason, err.kind) == ("special", "a symbolic link")
    dangling = tmp_path / "dangling.bin"
    dangling.symlink_to(tmp_path / "gone")
    assert _refused(reader, dangling).reason == "missing"
    assert _refused(reader, dangling, follow_symlinks=False).kind == "a symbolic link"


@pytest.mark.parametrize("reader", READERS)
def test_a_file_over_the_limit_is_refused_with_its_size_before_it_is_read(reader, tmp_path):
    big = tmp_path / "big.gif"
    big.write_bytes(b"x" * 1001)
    err = _refused(reader, big, 1000)
    assert (err.reason, err.size, err.max_bytes) == ("too_large", 1001, 1000)
    assert err.problem() == "1001 bytes, over the limit of 1000 bytes"
    words = {"too_large": "{size:,} bytes, more than the {max_bytes:,} advobj reads"}
    assert err.problem(words) == "1,001 bytes, more than the 1,000 advobj reads"


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads a file whatever its mode")
@pytest.mark.parametrize("reader", ["open", "read"])
def test_a_file_without_read_permission_cannot_be_read(reader, tmp_path):
    p = tmp_path / "secret.png"
    p.write_bytes(b"x")
    p.chmod(0)
    err = _refused(reader, p)
    assert err.reason == "unreadable" and err.problem() == "cannot read (Permission denied)"


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.binary(max_size=300), max_bytes=st.integers(0, 300))
def test_a_regular_file_is_read_whole_exactly_when_it_fits(tmp_path, data, max_bytes):
    p = tmp_path / "f.bin"
    p.write_bytes(data)
    if len(data) <= max_bytes:
        assert read_regular(p, max_bytes) == data and check_regular(p, max_bytes) == len(data)
        with open_regular(p, max_bytes) as f:
            assert f.read() == data
    else:
        with pytest.raises(FileRefusedError) as err:
            read_regular(p, max_bytes)
        assert (err.value.reason, err.value.size) == ("too_large", len(data))


def test_a_file_larger_than_it_says_is_cut_off_at_the_limit():
    """/proc files say 0 bytes and hold more: what is read never passes the limit."""
    path = Path("/proc/self/status")
    if not path.is_file():
        pytest.skip("no /proc")
    assert check_regular(path, 8) == 0  # asked, it is an empty regular file
    with pytest.raises(FileRefusedError) as err:
        read_regular(path, 8)
    assert err.value.reason == "grew" and err.value.problem() == "over the limit of 8 bytes"
    assert read_regular(path, 1 << 20).startswith(b"Name:")


def test_the_open_file_is_checked_too(fifo, monkeypatch):
    """A FIFO put at the path after the path was asked about: the open never waits on it and the
    open file's own check refuses it (the path check is skipped here to stand for that race)."""
    monkeypatch.setattr(files, "check_regular", lambda *a, **k: 0)
    err = _refused("open", fifo)
    assert (err.reason, err.kind) == ("special", "a FIFO (named pipe)")


def test_a_refusal_survives_pickling_whole(tmp_path):
    """A refusal raised in a Ray worker comes back with its reason and facts, not only its text."""
    err = FileRefusedError(tmp_path / "x", "too_large", 10, 20)
    back = pickle.loads(pickle.dumps(err))
    assert (back.path, back.reason, back.size, back.max_bytes, str(back)) == (
        str(tmp_path / "x"),
        "too_large",
        20,
        10,
        str(err),
    )


def test_every_reason_has_standard_words_and_an_unknown_reason_is_a_bug():
    assert set(WORDS) == set(REASONS)
    with pytest.raises(ValueError, match="reason 'big'"):
        FileRefusedError("x", "big", 1)


@pytest.mark.parametrize("max_bytes", [-1, True, 1.5, None])
def test_a_limit_that_is_no_byte_count_is_a_bug(tmp_path, max_bytes):
    p = tmp_path / "f"
    p.write_bytes(b"")
    with pytest.raises(ValueError, match="max_bytes"):
        read_regular(p, max_bytes)


def test_an_empty_file_fits_a_zero_limit(tmp_path):
    p = tmp_path / "empty"
    p.write_bytes(b"")
    assert read_regular(p, 0) == b"" and check_regular(p, 0) == 0


def test_not_a_regular_file_names_specials_and_leaves_files_folders_and_missing_paths_to_their_reader(tmp_path, fifo):
    (tmp_path / "a.yaml").write_text("a: 1\n")
    assert not_a_regular_file(fifo) == "is a FIFO (named pipe), not a regular file"
    assert not_a_regular_file("/dev/zero") == "is a character device, not a regular file"
    for quiet in (tmp_path / "a.yaml", tmp_path, tmp_path / "none", "a\0b"):
        assert not_a_regular_file(quiet) is None


def test_file_kind_names_each_kind_of_file(tmp_path, fifo):
    assert file_kind(os.stat(tmp_path).st_mode) == "a directory"
    assert file_kind(os.stat(fifo).st_mode) == "a FIFO (named pipe)"
    assert file_kind(os.stat("/dev/null").st_mode) == "a character device"
    link = tmp_path / "l"
    link.symlink_to(fifo)
    assert file_kind(os.lstat(link).st_mode) == "a symbolic link"


def test_write_atomic_replaces_the_file_whole_and_a_failed_write_leaves_the_old_one_and_no_temporary(tmp_path):
    import stat as st

    from sim.files import write_atomic

    p = tmp_path / "out.json"
    p.write_bytes(b"old")
    assert write_atomic(p, b"new contents") == p and p.read_bytes() == b"new contents"
    assert st.S_IMODE(p.stat().st_mode) == 0o644
    with pytest.raises(TypeError):
        write_atomic(p, "not bytes")  # fails inside the write
    assert p.read_bytes() == b"new contents" and sorted(x.name for x in tmp_path.iterdir()) == ["out.json"]
