"""``advobj attack run``: the test-sized ``ci`` preset, and the fixed-light warning said before the
attack starts (with ``--light-randomization`` to turn the lights random instead)."""

import json

import pytest
from typer.testing import CliRunner

from trials.cli.main import app, main

WARNING = "attack: warning: light_randomization is off"


def _attack(policy, out, *extra):
    res = CliRunner().invoke(app, ["attack", "run", "--policy", str(policy), "--out", str(out), *extra])
    assert res.exit_code == 0, res.output
    return res.output


def test_the_ci_preset_runs_every_stage_in_seconds_and_warns_about_the_fixed_light_first(tmp_path, tiny_policy_dir):
    out = tmp_path / "ci"
    output = _attack(tiny_policy_dir, out, "--preset", "ci")
    assert output.count(WARNING) == 1 and output.index(WARNING) < output.index("attack done")
    assert "--light-randomization" in output.splitlines()[[WARNING in l for l in output.splitlines()].index(True)]
    run = json.loads((out / "run.json").read_text())
    assert run["config"]["preset"] == "ci" and run["config"]["attack"]["iterations"] == 4
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["iterations"] == 4 and metrics["validation"]["iteration"] == [0, 2, 4]  # validated, best kept
    for name in ("texture.npy", "configs.json", "best/texture.npy", "checkpoint/state.json", "adversarial.glb"):
        assert (out / name).is_file(), name


def test_light_randomization_from_the_command_line_overrides_the_preset_and_silences_the_warning(
    tmp_path, tiny_policy_dir
):
    cfg = tmp_path / "fixed.yaml"
    cfg.write_text("light_randomization: false\n")
    output = _attack(tiny_policy_dir, tmp_path / "lit", "--preset", "ci", "--config", str(cfg), "--light-randomization")
    assert WARNING not in output
    assert json.loads((tmp_path / "lit" / "run.json").read_text())["config"]["attack"]["light_randomization"] is True


def test_an_unknown_preset_is_one_line_naming_the_presets(tmp_path, tiny_policy_dir, monkeypatch, capsys):
    out = tmp_path / "x"
    monkeypatch.setattr(
        "sys.argv", ["advobj", "attack", "run", "--policy", str(tiny_policy_dir), "--preset", "tiny", "--out", str(out)]
    )
    with pytest.raises(SystemExit) as exc:
        main()
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert exc.value.code == 2 and len(err) == 1 and "'ci', 'paper', 'quick'" in err[0], err
    assert not out.exists()
