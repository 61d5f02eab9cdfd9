"""A damaged trial database is refused at open, in one line naming the file, and never written to."""

from __future__ import annotations

import hashlib
import sys

import pytest

from trials.real.store import StoreError, TrialStore, check_database


def _damaged_store(path):
    """A real trial store with ~90 pages of sessions, then 4 KiB of its middle overwritten."""
    with TrialStore(path) as store:
        store.con.execute("BEGIN")
        for i in range(150):
            store.con.execute(
                "INSERT INTO sessions (name, created_at, plan_sha256, plan_text, hardware_text, policy_path, "
                "policy_sha256, "
                "software_version, git_commit, devices_json, calibration_json, config_json) VALUES "
                "(?,?,?,?,?,?,?,?,?,?,?,?)",
                (f"s{i}", "t", "p", "x" * 1500, "h", "pol", "", "v", "g", "{}", "{}", "{}"),
            )
        store.con.execute("COMMIT")
    data = bytearray(path.read_bytes())
    assert len(data) > 60 * 4096 and data[:16] == b"SQLite format 3\x00"
    mid = (len(data) // 2) // 4096 * 4096
    data[mid : mid + 4096] = bytes(range(256)) * 16
    path.write_bytes(bytes(data))
    return path


def _state(folder):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir()) if p.is_file()}


@pytest.fixture
def damaged(tmp_path):
    d = tmp_path / "db"
    d.mkdir()
    return _damaged_store(d / "trials.sqlite")


def test_open_refuses_a_damaged_database_without_writing(damaged):
    before = _state(damaged.parent)
    for opener in (
        lambda: TrialStore(damaged),
        lambda: TrialStore(damaged, create=False),
        lambda: check_database(damaged),
    ):
        with pytest.raises(StoreError) as info:
            opener()
        msg = str(info.value)
        assert msg.startswith(f"{damaged}: ") and "\n" not in msg
        assert "damaged" in msg or "malformed" in msg
    assert _state(damaged.parent) == before  # same bytes, no -wal/-shm left behind


def test_a_healthy_database_passes(tmp_path):
    with TrialStore(tmp_path / "ok.sqlite") as store:
        assert store.integrity_check() == "ok"
    check_database(tmp_path / "ok.sqlite")
    check_database(tmp_path / "absent.sqlite")  # a new database: nothing to check


@pytest.mark.parametrize(
    "command",
    [
        ["trial", "report", "--out", "{out}/report"],
        ["trial", "export", "--out", "{out}/export"],
        [
            "trial",
            "run",
            "--hardware",
            "{hw}",
            "--policy",
            "{policy}",
            "--plan",
            "{plan}",
            "--session",
            "s",
            "--auto-confirm",
        ],
    ],
    ids=["report", "export", "run"],
)
def test_cli_refuses_a_damaged_database_in_one_line(damaged, tmp_path, monkeypatch, capsys, command):
    from trials.cli.main import main

    out = tmp_path / "out"
    hw, policy, plan = tmp_path / "hw.yaml", tmp_path / "p.onnx", tmp_path / "plan.yaml"
    for f in (hw, policy, plan):
        f.write_text("placeholder: 1\n")  # never read: the database is checked first
    argv = [a.format(out=out, hw=hw, policy=policy, plan=plan) for a in command] + ["--db", str(damaged)]
    before = _state(damaged.parent)
    monkeypatch.setattr(sys, "argv", ["advobj", *argv])
    with pytest.raises(SystemExit) as info:
        main()
    err = capsys.readouterr().err.strip().splitlines()
    assert info.value.code == 2 and len(err) == 1 and str(damaged) in err[0] and "Traceback" not in err[0]
    assert _state(damaged.parent) == before and not out.exists()
