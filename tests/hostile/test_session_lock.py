"""Issue 25, "Fail closed II": one runner per session and per arm, safe session names, a checked
``--table-frame`` on sim devices, and trial notes that cannot reach a report or a terminal raw.

The races are run by real processes on a real SQLite store with sim devices: a holder process
stopped in the middle of a session (a trial committed, the next one's frames written but not yet
committed) while a second ``advobj trial run`` of the same session starts; every frame file is
hashed before and after.
"""

from __future__ import annotations

import hashlib
import os
import socket
import sqlite3
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import yaml

from tests.trials.real.trial_session_helpers import REPO, sim_hardware, small_plan, tiny_onnx
from trials.real.locks import LockBusy, LockError, arm_lock, arm_lock_key
from trials.real.operator import AutoOperator
from trials.real.session import SessionOptions, SessionSetupError, run_session
from trials.real.store import TrialStore

SESSION = "same"


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("session_lock")
    return {
        "policy": tiny_onnx(d / "p.onnx"),
        "plan": small_plan(d / "plan.yaml", d, n_tcp=2, max_steps=6),
        "hw": sim_hardware(d / "hw.yaml"),
    }


def _run_args(files, db, session=SESSION, *extra) -> list[str]:
    return [
        "trial",
        "run",
        "--hardware",
        str(files["hw"]),
        "--policy",
        str(files["policy"]),
        "--plan",
        str(files["plan"]),
        "--session",
        session,
        "--db",
        str(db),
        "--auto-confirm",
        "--no-rate-limit",
        *extra,
    ]


def _advobj(args, env=None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "trials.cli.main", *args],
        cwd=REPO,
        env={**os.environ, **(env or {})},
        capture_output=True,
        text=True,
        timeout=300,
    )


def _cli(args, monkeypatch, capsys) -> tuple[int, list[str]]:
    """``advobj ARGS`` in this process: the exit code and stderr's non-empty lines."""
    from trials.cli.main import main

    monkeypatch.setattr(sys, "argv", ["advobj", *[str(a) for a in args]])
    with pytest.raises(SystemExit) as ex:
        main()
    return ex.value.code, [line for line in capsys.readouterr().err.splitlines() if line.strip()]


def _one_error_line(code: int, lines: list[str]) -> str:
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: "), (code, lines)
    assert "Traceback" not in lines[0]
    return lines[0]


def _frame_hashes(db: Path) -> dict[str, str]:
    root = db.parent / "frames" / SESSION
    return {
        p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def _count(db: Path, table: str) -> int:
    con = sqlite3.connect(db)
    try:
        return con.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0]
    finally:
        con.close()


# A runner that stops in the middle of its second trial (trial 1 committed, trial 2's frames on
# disk, not committed) until the test lets it go on.
_HOLDER = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from trials.real.operator import AutoOperator
    from trials.real.session import SessionOptions, run_session

    hw, policy, plan, db, flags = sys.argv[1:6]
    flags, seen = Path(flags), []

    def hold(trial):
        seen.append(trial.trial_id)
        if len(seen) == 2:
            (flags / "ready").write_text(trial.trial_id)
            t_end = time.monotonic() + 120
            while not (flags / "go").exists():
                if time.monotonic() > t_end:
                    sys.exit("never let go")
                time.sleep(0.02)

    opts = SessionOptions(hardware=hw, policy=policy, plan=plan, session="same", db=db, rate_limit=False, max_trials=2)
    s = run_session(opts, operator=AutoOperator(log=None), on_trial_end=hold, log=None)
    print("committed", len(s.committed))
    """
)


def _start_holder(files, db: Path, flags: Path) -> subprocess.Popen:
    flags.mkdir()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-c",
            _HOLDER,
            str(files["hw"]),
            str(files["policy"]),
            str(files["plan"]),
            str(db),
            str(flags),
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    t_end = time.monotonic() + 180
    while not (flags / "ready").exists():
        if proc.poll() is not None:
            raise AssertionError(f"the holder ended early: {proc.communicate()}")
        assert time.monotonic() < t_end, "the holder never reached its second trial"
        time.sleep(0.05)
    return proc


def _finish(proc: subprocess.Popen, flags: Path) -> str:
    (flags / "go").write_text("1")
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    return out


# ---------------------------------------------------------------------- one runner per session
def test_a_second_runner_of_a_session_is_refused_in_one_line_and_changes_no_frame(files, tmp_path):
    db = tmp_path / "trials.sqlite"
    holder = _start_holder(files, db, tmp_path / "flags")
    try:
        in_progress = (tmp_path / "flags" / "ready").read_text()
        (committed_id,) = _committed_ids(db)
        before = _frame_hashes(db)
        # trial 1 committed, trial 2's frames written and not committed: both are the holder's
        assert {k.split("/")[0] for k in before if "/" in k} == {committed_id, in_progress}
        r = _advobj(_run_args(files, db))
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
        assert lines[0].startswith(
            f"error: --session {SESSION}: in use by host {socket.gethostname()} pid {holder.pid}"
        )
        assert "before any device connected" in lines[0]
        assert _frame_hashes(db) == before  # nothing cleared or rewritten, the committed trial's nor the open one's
        assert _count(db, "runs") == 1 and _count(db, "trials") == 1  # the refused run recorded nothing
    finally:
        out = _finish(holder, tmp_path / "flags")
    assert "committed 2" in out
    after = _frame_hashes(db)
    assert {k: v for k, v in after.items() if k in before} == before
    assert _count(db, "trials") == 2 and _count(db, "session_locks") == 0  # released at the end


@pytest.mark.slow
def test_two_cli_runs_of_one_session_the_later_is_refused_while_the_first_commits(files, tmp_path):
    """The issue's scenario with two ``advobj trial run`` processes: the second starts once the
    first has committed a trial, is refused, and no committed trial's frame changes."""
    db = tmp_path / "trials.sqlite"
    # 90 trials of up to 30 steps: the first run must outlive the second's start-up, even on a loaded machine
    plan = small_plan(tmp_path / "long.yaml", tmp_path, n_tcp=5, n_layouts=6, max_steps=30)
    args = _run_args({**files, "plan": plan}, db)
    first = subprocess.Popen(
        [sys.executable, "-m", "trials.cli.main", *args], cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    try:
        t_end = time.monotonic() + 180
        while not db.exists() or _committed(db) < 1:
            assert first.poll() is None and time.monotonic() < t_end, first.stderr.read() if first.poll() else ""
            time.sleep(0.05)
        committed = _committed_frames(db)
        r = _advobj(args)
        assert first.poll() is None, "the first run ended before the second was refused: nothing was raced"
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1, r.stderr
        assert f"in use by host {socket.gethostname()} pid {first.pid}" in lines[0]
        after = _frame_hashes(db)
        assert committed and {k: after.get(k) for k in committed} == committed
    finally:
        first.kill()
        first.wait()


def _committed(db: Path) -> int:
    try:
        con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5)
        try:
            return con.execute("SELECT COUNT(*) FROM trials").fetchone()[0]
        finally:
            con.close()
    except sqlite3.OperationalError:
        return 0


def _committed_ids(db: Path) -> set[str]:
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5)
    try:
        return {r[0] for r in con.execute("SELECT trial_id FROM trials")}
    finally:
        con.close()


def _committed_frames(db: Path) -> dict[str, str]:
    done = _committed_ids(db)
    return {k: v for k, v in _frame_hashes(db).items() if k.split("/")[0] in done}


# ---------------------------------------------------------------------- stale locks
def _plant_lock_row(db: Path, host: str, pid: int, proc_start: str | None) -> None:
    with TrialStore(db) as store:
        store.con.execute(
            "INSERT INTO session_locks (session, host, pid, proc_start, since) VALUES (?,?,?,?,?)",
            (SESSION, host, pid, proc_start, "2024-01-01T00:00:00Z"),
        )


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def _run(files, db, *, log=print, **options):
    opts = SessionOptions(
        hardware=files["hw"],
        policy=files["policy"],
        plan=files["plan"],
        session=SESSION,
        db=db,
        rate_limit=False,
        max_trials=1,
        **options,
    )
    return run_session(opts, operator=AutoOperator(log=None), log=log)


@pytest.mark.parametrize("how", ["dead pid", "pid reused by another process"])
def test_a_lock_row_left_by_a_process_gone_from_this_host_is_taken_over_and_said_so(files, tmp_path, how):
    db = tmp_path / "trials.sqlite"
    # a pid reused: this process is alive, but it is not the process that recorded that start
    pid, start = (_dead_pid(), None) if how == "dead pid" else (os.getpid(), "another-boot:1")
    _plant_lock_row(db, socket.gethostname(), pid, start)
    said: list[str] = []
    summary = _run(files, db, log=said.append)
    assert len(summary.committed) == 1
    assert any(f"taking over the lock of host {socket.gethostname()} pid {pid}" in s for s in said), said
    assert any("no longer running" in s for s in said)
    assert _count(db, "session_locks") == 0


def test_a_lock_row_naming_a_live_or_remote_holder_is_refused_unless_taken_over_explicitly(files, tmp_path):
    db = tmp_path / "trials.sqlite"
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        from trials.real.locks import process_start

        for host, pid, start, why in [
            ("cell-pc-2", 4242, None, "ran on another host"),
            (socket.gethostname(), sleeper.pid, process_start(sleeper.pid), "still runs on this host"),
        ]:
            with TrialStore(db) as store:
                store.con.execute("DELETE FROM session_locks")
            _plant_lock_row(db, host, pid, start)
            with pytest.raises(LockBusy) as err:
                _run(files, db, log=None)
            msg = str(err.value)
            assert len(msg.splitlines()) == 1 and f"host {host} pid {pid}" in msg and why in msg
            assert "--take-over-stale-lock" in msg
            assert not (db.parent / "frames").exists() and _count(db, "sessions") == 0  # nothing written
        said: list[str] = []
        assert len(_run(files, db, log=said.append, take_over_stale_lock=True).committed) == 1
        assert any("--take-over-stale-lock given" in s for s in said)
        assert _count(db, "session_locks") == 0
    finally:
        sleeper.kill()
        sleeper.wait()


def test_a_symlink_or_hard_link_at_the_lock_file_is_refused_and_never_written_through(files, tmp_path):
    db = tmp_path / "trials.sqlite"
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    lock_path = tmp_path / f"{db.name}-session-{SESSION}.lock"
    for plant in (lambda: lock_path.symlink_to(victim), lambda: os.link(victim, lock_path)):
        plant()
        with pytest.raises(LockError, match=str(lock_path)):
            _run(files, db, log=None)
        assert victim.read_text() == "precious"
        lock_path.unlink()


# ---------------------------------------------------------------------- one session per arm
def _ur_hardware(path: Path, host: str = "192.0.2.10") -> Path:
    data = yaml.safe_load((REPO / "examples" / "hardware" / "ur_v4l2.yaml").read_text())
    data["camera"] = {"type": "opencv", "device": "/dev/no-such-camera"}
    data["arm"]["host"] = host
    data.pop("T_tcp_cam")
    path.write_text(yaml.safe_dump(data))
    return path


_ARM_HOLDER = textwrap.dedent(
    """
    import sys
    from robot_io.config import load_hardware_config
    from trials.real.locks import arm_lock

    lock = arm_lock(load_hardware_config(sys.argv[1]).arm, session="day1", db=sys.argv[2])
    print("held", flush=True)
    sys.stdin.read()
    """
)


def test_two_sessions_in_different_databases_cannot_drive_one_arm(files, tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    run_dir.mkdir(mode=0o700)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(run_dir))
    hw = _ur_hardware(tmp_path / "ur.yaml", host="192.0.2.10")
    holder = subprocess.Popen(
        [sys.executable, "-c", _ARM_HOLDER, str(hw), str(tmp_path / "one" / "trials.sqlite")],
        cwd=REPO,
        env={**os.environ, "XDG_RUNTIME_DIR": str(run_dir)},
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        db = tmp_path / "two" / "trials.sqlite"
        # the same arm under another spelling of its address, another database and session
        opts = SessionOptions(
            hardware=_ur_hardware(tmp_path / "ur2.yaml", host=" 192.0.2.10 "),
            policy=files["policy"],
            plan=files["plan"],
            session="day2",
            db=db,
            registry=tmp_path / "objects.yaml",
        )
        with pytest.raises(LockBusy) as err:
            run_session(opts, operator=AutoOperator(log=None), log=None)
        msg = str(err.value)
        assert msg.startswith(f"arm ur_rtde:192.0.2.10: in use by host {socket.gethostname()} pid {holder.pid}")
        assert "session day1" in msg and str(tmp_path / "one" / "trials.sqlite") in msg
        assert len(msg.splitlines()) == 1 and "before any device connected" in msg
        # the session's own lock was let go with the refusal
        assert _count(db, "session_locks") == 0 and _count(db, "sessions") == 0
    finally:
        holder.communicate("", timeout=30)
    lock = arm_lock(_ur_hardware_config(hw))  # the holder is gone: the arm is free again
    assert lock is not None
    lock.release()


def _ur_hardware_config(path: Path):
    from robot_io.config import load_hardware_config

    return load_hardware_config(path).arm


def test_arm_lock_keys_name_the_physical_arm(tmp_path):
    from robot_io.config import hardware_config_from_dict

    base = yaml.safe_load((REPO / "examples" / "hardware" / "ur_v4l2.yaml").read_text())
    base.pop("T_tcp_cam")
    base["camera"] = {"type": "opencv", "device": 0}
    tty = tmp_path / "ttyACM0"
    tty.write_text("")
    by_id = tmp_path / "usb-arm-if00"
    by_id.symlink_to(tty)

    def key(arm):
        return arm_lock_key(hardware_config_from_dict({**base, "arm": arm}).arm)

    assert key({"type": "ur_rtde", "host": "UR5.local"}) == key({"type": "ur_rtde", "host": "ur5.local"})
    assert key({"type": "serial", "port": str(by_id)}) == key({"type": "serial", "port": str(tty)})
    assert key({"type": "serial", "port": "socket://10.0.0.2:9000"}) == "serial:socket://10.0.0.2:9000"
    assert key({"type": "sim"}) is None  # a sim arm lives in its own process: no arm lock


# ---------------------------------------------------------------------- session names
@pytest.mark.parametrize(
    "name", ["--", "-x", "", "_", ".hidden", "!!!", "a/b", "..", "a b", "a\nb", "a\x1b[31m", "é", "x" * 65]
)
def test_a_session_name_that_is_no_plain_token_is_refused_in_one_line(files, tmp_path, name, monkeypatch, capsys):
    db = tmp_path / "trials.sqlite"
    code, lines = _cli(_run_args(files, db, name), monkeypatch, capsys)
    line = _one_error_line(code, lines)
    assert line.startswith("error: --session: ") and "starting with a letter or digit" in line
    assert "\x1b" not in line and not db.exists() and not (tmp_path / "frames").exists()


# ---------------------------------------------------------------------- --table-frame with sim devices
@pytest.mark.parametrize(
    "pose, field",
    [
        ({"translation_m": [float("nan"), 0, 0]}, "translation_m"),
        ({"translation_m": [0, float("inf"), 0]}, "translation_m"),
        ({"translation_m": [1e6, 0, 0]}, "translation_m"),
        ({"rotvec_rad": [0, 0, 1e200]}, "rotvec_rad"),
        ({"translation_m": [0.1, 0, 0]}, None),  # valid, but a sim cell cannot apply it
    ],
)
def test_table_frame_is_loaded_and_checked_with_sim_devices(files, tmp_path, pose, field, monkeypatch, capsys):
    path = tmp_path / "table.yaml"
    path.write_text(yaml.safe_dump({"T_base_table": pose}))
    db = tmp_path / "trials.sqlite"
    code, lines = _cli([*_run_args(files, db), "--table-frame", path], monkeypatch, capsys)
    line = _one_error_line(code, lines)
    assert line.startswith(f"error: --table-frame: {path}")
    assert (field or "cannot apply") in line
    assert not db.exists()


def test_an_identity_table_frame_is_accepted_with_sim_devices(files, tmp_path):
    path = tmp_path / "table.yaml"
    path.write_text(yaml.safe_dump({"T_base_table": {"translation_m": [0, 0, 0], "rotvec_rad": [0, 0, 0]}}))
    with pytest.raises(SessionSetupError, match="cannot apply"):
        path2 = tmp_path / "moved.yaml"
        path2.write_text(yaml.safe_dump({"translation_m": [0, 0, 0.5]}))
        _run(files, tmp_path / "a.sqlite", table_frame=path2, log=None)
    assert len(_run(files, tmp_path / "b.sqlite", table_frame=path, log=None).committed) == 1


# ---------------------------------------------------------------------- hostile notes
HOSTILE = (
    "done\n\x1b[31mRED\x1b[0m <script>alert(1)</script> | `rm -rf` [x](javascript:alert(1)) \x1b]0;pwned\x07\u202e"
)


def test_a_hostile_note_reaches_report_md_escaped_and_no_terminal_raw(files, tmp_path, monkeypatch, capsys):
    db = tmp_path / "trials.sqlite"
    assert len(_run(files, db, log=None).committed) == 1
    with TrialStore(db) as store:
        trial = store.trial_rows()[0]["trial_id"]
        store.amend_trial(SESSION, trial, None, HOSTILE, reason=HOSTILE)
    out = tmp_path / "report"
    monkeypatch.setattr(sys, "argv", ["advobj", "trial", "report", "--db", str(db), "--out", str(out)])
    from trials.cli.main import main

    with pytest.raises(SystemExit) as ex:
        main()
    code = ex.value.code
    shown = capsys.readouterr()
    assert code == 0
    assert "\x1b" not in shown.out and "\x1b" not in shown.err and "<script>" not in shown.out
    md = (out / "report.md").read_text()
    for raw in ("\x1b", "\u202e", "\x07", "<script>", " `rm", "[x]"):
        assert raw not in md, raw
    note_lines = [line for line in md.splitlines() if "RED" in line]
    # the note, the amendment's new note and its reason: each on one line of its list, never a new line
    assert note_lines and all(line.startswith("- ") for line in note_lines)
    assert "&lt;script&gt;alert(1)&lt;/script&gt; \\| \\`rm -rf\\` \\[x\\](javascript:alert(1))" in md
    # the data exports keep the note as the operator typed it
    with TrialStore(db) as store:
        assert store.trial_rows()[0]["note"] == HOSTILE


def test_md_text_leaves_no_markup_and_no_control_character():
    from hypothesis import given
    from hypothesis import strategies as st

    from trials.real.report import md_text, plain_text

    @given(st.text(max_size=200))
    def check(text):
        md = md_text(text)
        assert all(c.isprintable() for c in md) and "\n" not in md
        assert "<" not in md and ">" not in md
        escaped = False
        for c in md:  # every backslash escapes the next character; no special one stands alone
            if escaped:
                escaped = False
            elif c == "\\":
                escaped = True
            else:
                assert c not in "|`[]", md
        assert not escaped
        assert "\x1b" not in plain_text(text)

    check()
