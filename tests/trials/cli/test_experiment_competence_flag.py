"""``advobj experiment <recipe> --min-clean-success`` carries the competence gate's threshold into the
recipe's config (its pool, attack and eval jobs take it from there), and a value outside [0, 1] is
one line naming the flag, before anything runs."""

from __future__ import annotations

import pytest

from sim.policies.competence import DEFAULT_MIN_CLEAN_SUCCESS
from trials.cli import experiment
from trials.cli.main import main


def _run(monkeypatch, argv):
    seen = []

    def fake_run(name, cfg, out, *a, **k):  # the recipe itself is not under test: its config is
        seen.append(cfg)
        raise SystemExit(0)

    monkeypatch.setattr(experiment, "run_experiment", fake_run)
    monkeypatch.setattr("sys.argv", ["advobj", *argv])
    with pytest.raises(SystemExit) as e:
        main()
    return e.value.code, seen


@pytest.mark.parametrize("given,expected", [(None, DEFAULT_MIN_CLEAN_SUCCESS), ("0", 0.0), ("0.8", 0.8)])
def test_the_threshold_reaches_the_recipes_config(monkeypatch, tmp_path, given, expected):
    argv = ["experiment", "table1", "--out", str(tmp_path / "out")]
    if given is not None:
        argv += ["--min-clean-success", given]
    code, (cfg,) = _run(monkeypatch, argv)
    assert code == 0 and cfg.min_clean_success == expected


@pytest.mark.parametrize("bad", ["-0.1", "1.5", "nan"])
def test_a_threshold_outside_0_1_is_one_line_naming_the_flag(monkeypatch, tmp_path, capsys, bad):
    code, seen = _run(monkeypatch, ["experiment", "table1", "--out", str(tmp_path / "out"), "--min-clean-success", bad])
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and not seen and not (tmp_path / "out").exists()
    assert any("--min-clean-success" in line for line in err) and "Traceback" not in "\n".join(err)
