"""SessionOptions: every input of a trial session in one strict model; a bad value is one line naming its flag."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from pydantic import ValidationError

from sim.paths import UnsafePathError
from trials.real.session import SessionOptions, SessionSetupError
from trials.real.store import DEFAULT_DB


def _values(**kw) -> dict:
    return {"hardware": "hw.yaml", "policy": "p.onnx", "plan": "plan.yaml", "session": "s", **kw}


def test_options_take_the_cli_defaults_and_the_stores_default_database():
    import typer

    from trials.cli.trial import app

    opts = SessionOptions(**_values())
    assert opts.db == Path(DEFAULT_DB) and opts.threads == 1 and opts.max_trials is None
    assert opts.rate_limit is None and not opts.auto_confirm and not opts.take_over_stale_lock
    assert isinstance(opts.hardware, Path) and isinstance(opts.plan, Path) and isinstance(opts.policy, Path)
    commands = typer.main.get_command(app).commands
    for name in ("run", "export", "amend", "report"):
        (db,) = [p for p in commands[name].params if p.name == "db"]
        assert Path(db.default) == Path(DEFAULT_DB), name


@pytest.mark.parametrize(
    ("values", "flag"),
    [
        ({"threads": 0}, "--threads"),
        ({"max_trials": -1}, "--max-trials"),
        ({"table_frame": 3}, "--table-frame"),
        ({"rate_limit": "sometimes"}, "--rate-limit"),
        ({"take_over_stale_lock": "maybe"}, "--take-over-stale-lock"),
        ({"session": None}, "--session"),
    ],
)
def test_a_bad_option_is_one_line_naming_its_flag_not_a_field(values, flag):
    with pytest.raises(SessionSetupError) as err:
        SessionOptions(**_values(**values))
    msg = str(err.value)
    assert msg.startswith(f"{flag}: ") and "\n" not in msg, msg


def test_a_missing_option_names_its_flag():
    with pytest.raises(SessionSetupError, match="^--plan: Field required$"):
        SessionOptions(hardware="hw.yaml", policy="p.onnx", session="s")


def test_an_unknown_option_is_refused():
    with pytest.raises(SessionSetupError, match="^speed: not an option of a trial session$"):
        SessionOptions(**_values(speed=2))


@pytest.mark.parametrize("name", ["../x", "/abs", "-x", ""])
def test_an_unsafe_session_name_is_refused_by_the_options_naming_session(name):
    with pytest.raises(UnsafePathError, match=r"^--session: .* is not a safe name for a session"):
        SessionOptions(**_values(session=name))


def test_answers_with_auto_confirm_is_refused_by_the_options():
    with pytest.raises(SessionSetupError, match=r"^--auto-confirm and --answers: give one of them$"):
        SessionOptions(**_values(answers="answers.yaml", auto_confirm=True))


def test_options_are_frozen():
    opts = SessionOptions(**_values())
    with pytest.raises(ValidationError):
        opts.threads = 2


def test_trial_run_refuses_answers_with_auto_confirm_in_one_line_before_reading_any_file(tmp_path, monkeypatch, capsys):
    from trials.cli.main import main

    db = tmp_path / "db" / "t.sqlite"
    argv = ["trial", "run", "--hardware", tmp_path / "hw.yaml", "--policy", tmp_path / "p.onnx"]
    argv += ["--plan", tmp_path / "plan.yaml", "--session", "s", "--db", db]
    argv += ["--answers", tmp_path / "answers.yaml", "--auto-confirm"]
    monkeypatch.setattr(sys, "argv", ["advobj", *map(str, argv)])
    with pytest.raises(SystemExit) as ex:
        main()
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert ex.value.code == 2 and lines == ["error: --auto-confirm and --answers: give one of them"], lines
    assert list(tmp_path.iterdir()) == []  # nothing created, not even the database's folder
