"""Path traversal through trial data: ids and session names never choose where files are written or removed.

A plan's ``trial_id`` and the ``--session`` name become ``frames/<session>/<trial_id>/`` beside the
database, which the runner clears and rewrites. Both must be safe names, and every such path must
resolve inside ``frames/``: otherwise ``advobj trial run`` refuses in one line (exit 2), before
anything is written or removed.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from sim.paths import SafeName, UnsafePathError, check_name, name_problem, safe_join
from tests.trials.real.trial_session_helpers import REPO, sim_hardware, small_plan, tiny_onnx
from trials.real.plan import PlanError, load_plan
from trials.real.store import frames_dir, frames_ref, session_frames_dir

ADVOBJ = [sys.executable, "-m", "trials.cli.main"]


# ---------------------------------------------------------------------- helpers
@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("path_safety")
    return {
        "policy": tiny_onnx(d / "p.onnx"),
        "plan": small_plan(d / "plan.yaml", d),
        "hw": sim_hardware(d / "hw.yaml"),
    }


def _advobj(args) -> subprocess.CompletedProcess:
    return subprocess.run(
        ADVOBJ + [str(a) for a in args], cwd=REPO, env=dict(os.environ), capture_output=True, text=True, timeout=300
    )


def _trial_run(files, db, session, plan=None):
    return _advobj(
        [
            "trial",
            "run",
            "--hardware",
            files["hw"],
            "--policy",
            files["policy"],
            "--plan",
            plan or files["plan"],
            "--session",
            session,
            "--db",
            db,
            "--auto-confirm",
            "--no-rate-limit",
            "--max-trials",
            "1",
        ]
    )


def _one_error_line(r: subprocess.CompletedProcess) -> str:
    """Exit 2, no traceback, and stderr is exactly one ``error: ...`` line; returns it."""
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    return lines[0]


def _snapshot(root: Path) -> dict:
    """Every file and directory under ``root``, with file contents and mtimes (to see that nothing changed)."""
    out = {}
    for p in sorted(root.rglob("*")):
        st = p.lstat()
        out[p.relative_to(root).as_posix()] = (p.read_bytes(), st.st_mtime_ns) if p.is_file() else "dir"
    return out


def _victim(path: Path) -> Path:
    path.mkdir(parents=True)
    (path / "precious.txt").write_text("do not delete")
    return path


def _first_trial_id(plan_path) -> str:
    return min(load_plan(plan_path).trials, key=lambda t: t.order).trial_id


# ---------------------------------------------------------------------- (a) the plan's trial_id
@pytest.mark.parametrize("bad_id", ["../../victim", "../../../victim"])
def test_plan_with_a_traversal_trial_id_is_refused_and_the_victim_survives(files, tmp_path, bad_id):
    work = tmp_path / "work"
    db = work / "db" / "t.sqlite"
    # frames/<session>/<bad_id> would be <db dir>/victim or <work>/victim: put a victim at both.
    victims = [_victim(work / "db" / "victim"), _victim(work / "victim")]
    data = yaml.safe_load(Path(files["plan"]).read_text())
    first = min(data["trials"], key=lambda t: t["order"])
    first["trial_id"] = bad_id
    plan = work / "evil_plan.yaml"
    plan.write_text(yaml.safe_dump(data))
    before = _snapshot(tmp_path)

    line = _one_error_line(_trial_run(files, db, "s", plan))
    assert str(plan) in line and ".trial_id" in line and repr(bad_id) in line and "not a safe name" in line
    assert _snapshot(tmp_path) == before  # no database, no frames, victims untouched
    for v in victims:
        assert (v / "precious.txt").read_text() == "do not delete" and not (v / "step_000.png").exists()


def test_load_plan_names_the_trial_id_field(files, tmp_path):
    data = yaml.safe_load(Path(files["plan"]).read_text())
    for bad in ["../x", "/etc", ".hidden", "", "a/b", "x" * 65, "ok\n"]:
        data["trials"][1]["trial_id"] = bad
        path = tmp_path / "bad.yaml"
        path.write_text(yaml.safe_dump(data))
        with pytest.raises(PlanError) as err:
            load_plan(path)
        msg = str(err.value)
        assert "\n" not in msg and "trials.1.trial_id" in msg and "safe name" in msg, msg


def test_plan_names_that_would_make_a_too_long_trial_id_are_refused_at_planning(tmp_path):
    from sim.spec import default_scene
    from trials.real.plan import make_plan

    with pytest.raises(PlanError, match=r"--env/--shape/--tag: trial id .* too long"):
        make_plan(default_scene(), 0, ["E" * 60], ["cube"], ["clean"], {}, n_tcp_poses=1, n_object_layouts=1)


def test_cli_plan_refuses_a_traversal_env_name(tmp_path):
    out = tmp_path / "plan.yaml"
    line = _one_error_line(
        _advobj(
            [
                "trial",
                "plan",
                "--out",
                out,
                "--env",
                "../../x",
                "--shape",
                "cube",
                "--condition",
                "clean",
                "--tcp-poses",
                "1",
                "--object-poses",
                "1",
            ]
        )
    )
    assert "--env" in line and "'../../x'" in line
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------- (b) the session name
def test_session_with_dotdot_is_refused_and_nothing_is_created(files, tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    db = work / "db" / "t.sqlite"
    before = _snapshot(tmp_path)
    line = _one_error_line(_trial_run(files, db, "../../x"))
    assert line.startswith("error: --session: '../../x'") and "not a safe name" in line
    assert _snapshot(tmp_path) == before  # not even the database or its folder
    assert not (work / "x").exists() and not (tmp_path / "x").exists()


def test_absolute_session_is_refused_and_the_folder_keeps_its_subfolders(files, tmp_path):
    target = tmp_path / "abs" / "path"
    # what the runner would have cleared: <session>/<first trial id> (an absolute part replaces the root)
    victim = _victim(target / _first_trial_id(files["plan"]))
    db = tmp_path / "db" / "t.sqlite"
    before = _snapshot(tmp_path)
    line = _one_error_line(_trial_run(files, db, str(target)))
    assert line.startswith(f"error: --session: {str(target)!r}") and "not a safe name" in line
    assert _snapshot(tmp_path) == before
    assert (victim / "precious.txt").read_text() == "do not delete"


def test_session_frames_symlinked_out_of_frames_are_refused(files, tmp_path):
    """A safe name whose frames/<session> is a symlink to elsewhere: refused, the target untouched."""
    from trials.real.operator import AutoOperator
    from trials.real.session import SessionOptions, run_session

    outside = _victim(tmp_path / "outside")
    _victim(outside / _first_trial_id(files["plan"]))
    db = tmp_path / "db" / "t.sqlite"
    (db.parent / "frames").mkdir(parents=True)
    (db.parent / "frames" / "s").symlink_to(outside, target_is_directory=True)
    before = _snapshot(outside)
    with pytest.raises(UnsafePathError, match=r"^--session: 's' leads to .*outside"):
        run_session(
            SessionOptions(
                hardware=files["hw"], policy=files["policy"], plan=files["plan"], session="s", db=db, rate_limit=False
            ),
            operator=AutoOperator(log=None),
        )
    assert _snapshot(outside) == before and not db.exists()


def test_store_paths_refuse_unsafe_names_and_symlinks(tmp_path):
    db = tmp_path / "t.sqlite"
    good = frames_dir(db, "day1", "A-cube-clean-t0-o0")
    assert good == (tmp_path / "frames" / "day1" / "A-cube-clean-t0-o0").resolve()
    assert frames_ref("day1", "A-cube-clean-t0-o0") == "frames/day1/A-cube-clean-t0-o0"
    for session, trial in [("../x", "t"), ("/abs", "t"), ("s", "../../victim"), ("s", "/abs"), (".", "t"), ("s", "..")]:
        with pytest.raises(UnsafePathError):
            frames_dir(db, session, trial)
    with pytest.raises(UnsafePathError, match="^session: "):
        session_frames_dir(db, "../x")
    # a trial directory that is a symlink out of frames/: refused, never cleared through
    _victim(tmp_path / "victim")
    (tmp_path / "frames" / "day1").mkdir(parents=True)
    (tmp_path / "frames" / "day1" / "t0").symlink_to(tmp_path / "victim", target_is_directory=True)
    with pytest.raises(UnsafePathError, match="outside"):
        frames_dir(db, "day1", "t0")
    assert (tmp_path / "victim" / "precious.txt").is_file()


# ---------------------------------------------------------------------- (c) the shared helpers
@pytest.mark.parametrize("name", ["s", "day1", "A-cube-adv3d-t2-o4-dim", "run_2024.06.01", "x" * 64, "-x", "_", "a..b"])
def test_safe_names(name):
    assert check_name(name, "--session") == name and name_problem(name) is None


@pytest.mark.parametrize(
    "name", ["", ".", "..", ".hidden", "../x", "a/b", "/abs", "a\\b", "x" * 65, "ok\n", "a b", "é", "a\0b"]
)
def test_unsafe_names(name):
    with pytest.raises(UnsafePathError, match=r"^--session: .*not a safe name"):
        check_name(name, "--session")
    assert name_problem(name) is not None


def test_unsafe_name_types_and_the_pydantic_field():
    from pydantic import BaseModel, ValidationError

    class M(BaseModel):
        name: SafeName

    assert M(name="ok").name == "ok"
    with pytest.raises(ValidationError, match="not a safe name"):
        M(name="../x")
    with pytest.raises(UnsafePathError, match="must be a string"):
        check_name(None, "name")


def test_safe_join_inside(tmp_path):
    assert safe_join(tmp_path, "a", "b") == (tmp_path / "a" / "b").resolve()  # need not exist
    assert safe_join(tmp_path, "a/b/../c") == (tmp_path / "a" / "c").resolve()
    assert safe_join(str(tmp_path), Path("a")) == (tmp_path / "a").resolve()


@pytest.mark.parametrize("parts", [("..",), ("a", "..", "..", "x"), ("../x",), (".",), ("a", ".."), ()])
def test_safe_join_refuses_paths_leaving_the_root(tmp_path, parts):
    root = tmp_path / "root"
    root.mkdir()
    with pytest.raises(UnsafePathError):
        safe_join(root, *parts)


def test_safe_join_refuses_absolute_parts_and_names_the_input(tmp_path):
    with pytest.raises(UnsafePathError, match=r"^--out: '/etc' is an absolute path"):
        safe_join(tmp_path, "/etc", what="--out")
    with pytest.raises(UnsafePathError, match=r"^trial_id: '\.\./x' leads to"):
        safe_join(tmp_path / "r", "../x", what="trial_id")


def test_safe_join_follows_symlinks(tmp_path):
    root = tmp_path / "root"
    (root / "inner").mkdir(parents=True)
    outside = tmp_path / "outside"
    outside.mkdir()
    (root / "escape").symlink_to(outside, target_is_directory=True)
    (root / "file_escape").symlink_to(tmp_path / "nowhere.txt")  # dangling, pointing out
    (root / "inside_link").symlink_to(root / "inner", target_is_directory=True)
    with pytest.raises(UnsafePathError, match="outside"):
        safe_join(root, "escape")
    with pytest.raises(UnsafePathError, match="outside"):
        safe_join(root, "escape", "deeper", "file.png")
    with pytest.raises(UnsafePathError):
        safe_join(root, "file_escape")
    assert safe_join(root, "inside_link", "x") == (root / "inner" / "x").resolve()  # a link that stays inside is fine
    # the root itself may be a symlink (e.g. frames/ on another disk): paths below its target are inside
    linked_root = tmp_path / "linked_root"
    linked_root.symlink_to(root, target_is_directory=True)
    assert safe_join(linked_root, "inner") == (root / "inner").resolve()
