"""Atomic trials: SIGKILL the runner at random points, check the database, resume to completion.

Each kill happens a random delay after the session has committed a given number of trials, so
it lands anywhere in the next trial (placement, policy loop, frame writes, the commit itself).
After every kill: ``PRAGMA integrity_check`` is ``ok``, every committed trial is complete (all its
steps and frames), and after the final resume every planned trial is stored exactly once. At
least one kill must land (a runner that finished before its kill proves nothing). The kill points
come from a seed, printed and named in every failure; ``ADVOBJ_SIGKILL_SEED=N`` replays one.
"""

from __future__ import annotations

import os
import random
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.trials.real.trial_session_helpers import REPO, sim_hardware, small_plan, tiny_onnx


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("sigkill")
    return {
        "policy": tiny_onnx(d / "p.onnx"),
        "plan": small_plan(d / "plan.yaml", d, n_tcp=3, max_steps=8),
        "hw": sim_hardware(d / "hw.yaml"),
    }


def _cmd(files, db):
    return [
        sys.executable,
        "-m",
        "trials.cli.main",
        "trial",
        "run",
        "--hardware",
        str(files["hw"]),
        "--policy",
        str(files["policy"]),
        "--plan",
        str(files["plan"]),
        "--session",
        "k",
        "--db",
        str(db),
        "--auto-confirm",
        "--no-rate-limit",
    ]


def _committed(db: Path) -> int:
    if not db.exists():
        return 0
    try:
        con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5)
        try:
            return con.execute("SELECT COUNT(*) FROM trials").fetchone()[0]
        finally:
            con.close()
    except sqlite3.OperationalError:
        return 0  # schema not created yet


def _seed() -> int:
    seed = int(os.environ.get("ADVOBJ_SIGKILL_SEED", time.time_ns() % 2**32))
    print(f"kill points from seed {seed} (replay: ADVOBJ_SIGKILL_SEED={seed})")
    return seed


def _kill_after(files, db, n_committed: int, delay_s: float, why: str, timeout_s: float = 120.0) -> bool:
    """Start the runner, SIGKILL it ``delay_s`` after ``n_committed`` trials are stored; False if it finished first."""
    env = {**os.environ, "PYOPENGL_PLATFORM": "egl"}
    proc = subprocess.Popen(_cmd(files, db), cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    t_end = time.monotonic() + timeout_s
    try:
        while _committed(db) < n_committed and proc.poll() is None:
            assert time.monotonic() < t_end, f"runner made no progress ({why})"
            time.sleep(0.02)
        time.sleep(delay_s)
        if proc.poll() is not None:
            assert proc.returncode == 0, f"{why}: {proc.stderr.read().decode()}"
            return False
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
        return True
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _check_db(db: Path) -> list[str]:
    """Integrity and completeness of every committed trial; returns the committed trial ids."""
    if not db.exists():
        return []  # killed before the store was created
    con = sqlite3.connect(db)
    try:
        assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        tables = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if not tables:
            return []  # killed while creating the schema (one transaction: nothing of it stays)
        rows = con.execute("SELECT id, trial_id, n_steps, frames_dir FROM trials").fetchall()
        for row_id, trial_id, n_steps, fdir in rows:
            n = con.execute("SELECT COUNT(*) FROM steps WHERE trial_row = ?", (row_id,)).fetchone()[0]
            assert n == n_steps > 0, trial_id
            refs = [r[0] for r in con.execute("SELECT frame_ref FROM steps WHERE trial_row = ?", (row_id,))]
            assert all((db.parent / ref).is_file() for ref in refs), trial_id
            assert con.execute("SELECT COUNT(*) FROM object_poses WHERE trial_row = ?", (row_id,)).fetchone()[0] == 4
        return [r[1] for r in rows]
    finally:
        con.close()


def _kill_and_resume(files, db, kills: list[tuple[int, float]], seed: int) -> None:
    from trials.real.plan import load_plan

    planned = {t.trial_id for t in load_plan(files["plan"]).trials}
    done, killed = [], []
    for k, (after, delay) in enumerate(kills):
        why = f"seed {seed}, kill {k}: {delay:.3f} s after {after} committed trials"
        killed.append(_kill_after(files, db, after, delay, why))
        done = _check_db(db)
        assert len(done) == len(set(done)) and set(done) <= planned, why
    assert any(killed), f"seed {seed}: the runner finished before every kill {kills}; nothing was tested"
    r = subprocess.run(_cmd(files, db), cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, f"seed {seed}: {r.stderr}"
    assert f"{len(done)} of {len(planned)} trials already done" in r.stdout or not done, f"seed {seed}"
    final = _check_db(db)
    assert sorted(final) == sorted(planned), f"seed {seed}"  # every planned trial exactly once


def test_sigkill_mid_session_then_resume(files, tmp_path):
    # One kill keeps the default suite at two runner start-ups (~7 s of CPU each, mostly imports).
    # 9 trials of at most 8 steps: 0.3 s after the 3rd commit, the 6 trials left are far from done.
    seed = _seed()
    rng = random.Random(seed)
    _kill_and_resume(files, tmp_path / "trials.sqlite", [(rng.randint(1, 3), rng.uniform(0.0, 0.3))], seed)


@pytest.mark.slow
def test_sigkill_at_many_random_points(files, tmp_path):
    seed = _seed()
    rng = random.Random(seed)
    kills = sorted((rng.randint(0, 5), rng.uniform(0.0, 1.5)) for _ in range(6))
    _kill_and_resume(files, tmp_path / "trials.sqlite", kills, seed)
