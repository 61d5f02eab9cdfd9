"""``advobj policy train --iterations N``: the number of DAgger iterations, written into the run's
resolved config; an interrupted run resumes with more, not with fewer than it has done.

The runs are the ``ci`` preset on the joint-space Panda scene with 3-step episodes (a few seconds
per iteration) and no final evaluation. Commands run in-process through ``trials.cli.main.main``
(exit code, stderr lines).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import yaml

from sim.spec import load_spec
from tests.trials.conftest import MAX_STEPS

PANDA_SCENE = Path(__file__).resolve().parents[3] / "scenes" / "panda-joint.yaml"


@pytest.fixture(scope="module")
def short_scene(tmp_path_factory):
    """The joint-space Panda scene with 3-step episodes, as a scene YAML."""
    doc = load_spec(PANDA_SCENE).model_dump(mode="json")
    doc["episode"]["max_steps"] = MAX_STEPS
    path = tmp_path_factory.mktemp("scene") / "scene.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def _cli(monkeypatch, capsys, *argv) -> tuple[int, list[str]]:
    from trials.cli.main import main

    monkeypatch.setattr(sys, "argv", ["advobj", *map(str, argv)])
    with pytest.raises(SystemExit) as exc:
        main()
    err = capsys.readouterr().err
    return exc.value.code, [line for line in err.splitlines() if line.startswith("error:")]


def _train(monkeypatch, capsys, scene, out, *extra) -> tuple[int, list[str]]:
    return _cli(
        monkeypatch,
        capsys,
        *("policy", "train", "--preset", "ci", "--scene", scene, "--out", out, "--episodes", "0", "--keep-state"),
        *extra,
    )


def _run_config(out: Path) -> dict:
    return json.loads((out / "run.json").read_text())["config"]


def test_the_iterations_flag_sets_the_runs_length_a_resume_extends_it_and_cannot_shorten_it(
    short_scene, tmp_path, monkeypatch, capsys
):
    out = tmp_path / "run"
    assert _train(monkeypatch, capsys, short_scene, out, "--iterations", 1) == (0, [])
    cfg = _run_config(out)
    assert cfg["dagger"]["iterations"] == 1 and cfg["contract"]["action"]["kind"] == "joint_delta"
    # resumed with more: the run continues from its first iteration, and says so in its config and card
    assert _train(monkeypatch, capsys, short_scene, out, "--iterations", 2) == (0, [])
    assert _run_config(out)["dagger"]["iterations"] == 2
    progress = json.loads((out / "train_state" / "progress.json").read_text())
    assert progress["iterations_done"] == 2 and [h["iteration"] for h in progress["history"]] == [0, 1]
    card = json.loads((out / "policy.json").read_text())
    assert card["training"]["dagger"]["iterations"] == 2
    assert [h["iteration"] for h in card["training"]["history"]] == [0, 1]
    run_json = (out / "run.json").read_bytes()
    # resumed with fewer iterations than it has done: one line, and the run is left as it was
    code, errors = _train(monkeypatch, capsys, short_scene, out, "--iterations", 1)
    assert code == 2 and len(errors) == 1, errors
    assert "dagger.iterations (--iterations): 1" in errors[0] and "has already done 2" in errors[0]
    assert str(out) in errors[0]
    assert (out / "run.json").read_bytes() == run_json


@pytest.mark.parametrize("flag", ["--iterations", "--grad-steps"])
@pytest.mark.parametrize("value", ["0", "-3", "two"])
def test_a_count_below_one_or_not_a_number_is_one_line_naming_the_flag(
    short_scene, tmp_path, monkeypatch, capsys, flag, value
):
    out = tmp_path / "run"
    code, errors = _train(monkeypatch, capsys, short_scene, out, flag, value)
    assert code == 2 and len(errors) == 1 and flag in errors[0], errors
    assert not out.exists()


@pytest.mark.parametrize("flag, ppo_words", [("--iterations", "ppo.total_timesteps"), ("--grad-steps", "ppo.n_epochs")])
def test_a_dagger_setting_with_ppo_is_refused_in_one_line(tmp_path, monkeypatch, capsys, flag, ppo_words):
    out = tmp_path / "run"
    code, errors = _cli(
        monkeypatch, capsys, "policy", "train", "--preset", "ci", "--method", "ppo", flag, 2, "--out", out
    )
    assert code == 2 and len(errors) == 1, errors
    assert flag in errors[0] and ppo_words in errors[0]
    assert not out.exists()


# ----------------------------------------------------------------------------- --grad-steps
def test_grad_steps_sets_the_dagger_steps_per_iteration_and_a_resume_with_others_is_refused(
    short_scene, tmp_path, monkeypatch, capsys
):
    out = tmp_path / "run"
    assert _train(monkeypatch, capsys, short_scene, out, "--iterations", 1, "--grad-steps", 3) == (0, [])
    assert _run_config(out)["dagger"]["grad_steps_per_iter"] == 3
    card = json.loads((out / "policy.json").read_text())
    assert card["training"]["dagger"]["grad_steps_per_iter"] == 3
    run_json = (out / "run.json").read_bytes()
    # the same run resumed with other gradient steps is another run: refused in one line, nothing changed
    code, errors = _train(monkeypatch, capsys, short_scene, out, "--iterations", 2, "--grad-steps", 4)
    assert code == 2 and len(errors) == 1, errors
    assert str(out) in errors[0]
    assert (out / "run.json").read_bytes() == run_json


def test_a_ppo_state_resumed_with_another_config_is_refused_before_run_json_is_rewritten(tmp_path):
    """The fingerprint check runs for every method, and for a DAgger run pointed at PPO state."""
    from sim.errors import AdvobjError
    from sim.policies.presets import resolve_preset
    from sim.policies.train import check_resume_length

    out = tmp_path / "run"
    (out / "train_state").mkdir(parents=True)
    (out / "train_state" / "progress.json").write_text(json.dumps({"fingerprint": "another", "timesteps": 10}))
    for method in ("ppo", "dagger"):
        cfg = resolve_preset("ci", method=method)
        with pytest.raises(AdvobjError, match="holds a run with a different config"):
            check_resume_length(cfg, out)
    same = resolve_preset("ci", method="ppo")
    (out / "train_state" / "progress.json").write_text(json.dumps({"fingerprint": same.fingerprint()}))
    check_resume_length(same, out)  # its own state: resumed
