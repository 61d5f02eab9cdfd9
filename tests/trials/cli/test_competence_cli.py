"""The competence gate on ``advobj attack run`` and ``advobj eval`` (issue 30): a policy that cannot
do the task is refused in one line, before a task-feasible pool is topped up and before anything
is written in ``--out``.

The policies are deliberately incompetent: untrained 32 px CNNs (they reach nothing). One carries
the card ``advobj policy train --preset ci`` left on the built-in scene (1 success in 16 final
episodes) and that run's pool (the one configuration it solved): the path that used to spend
minutes topping the pool up. The other has no clean-success figure, so the gate measures it.
Commands run in-process through ``trials.cli.main.main`` (exit code, stderr lines).
"""

from __future__ import annotations

import re
import sys
import time

import pytest
import torch
import yaml

from sim.configs import sample_pool, save_pool, spec_fingerprint
from sim.policies.card import ActionScaling, CleanSuccess, PolicyCard
from sim.policies.checkpoint import save_checkpoint
from sim.policies.policy import VisuomotorPolicy
from sim.spec import default_scene, load_spec
from sim.stats import wilson_interval
from tests.trials.conftest import MAX_STEPS

REFUSED_BY_CARD = "clean success 6.2% (1/16 episodes, from its card) is below --min-clean-success 0.5"
ADVICE = ("train it longer", "check that the scene is the one it was trained for", "0 turns the check off")


def incompetent_policy(d, spec=None, card_k_of_n: tuple[int, int] | None = None):
    """An untrained small-CNN checkpoint in ``d``; with ``card_k_of_n``, its card records that clean
    success on ``spec`` (as ``advobj policy train`` writes it) and ``d/feasible_pool.json`` holds as
    many configurations as it claims successes."""
    torch.manual_seed(0)
    p = VisuomotorPolicy(arch="small_cnn", image_size=32)
    card = PolicyCard(arch=p.config, action=ActionScaling(max_step_m=0.02, max_step_rad=0.1))
    if card_k_of_n is not None:
        k, n = card_k_of_n
        lo, hi = wilson_interval(k, n)
        card.training = {"preset": "ci", "scene": {"name": spec.name, "fingerprint": spec_fingerprint(spec)}}
        card.clean_success = CleanSuccess(
            k=k, n=n, rate=k / n, lo=lo, hi=hi, confidence=0.95, episodes_seed=0, image_size=32
        )
    save_checkpoint(d, p, card)
    if card_k_of_n is not None:
        save_pool(d / "feasible_pool.json", spec, sample_pool(spec, card_k_of_n[0], seed=0))
    return d


@pytest.fixture(scope="module")
def ci_policy(tmp_path_factory):
    """The ``ci`` preset's outcome: 1/16 clean success on the built-in scene, a one-configuration pool."""
    return incompetent_policy(tmp_path_factory.mktemp("ci") / "policy", default_scene(), (1, 16))


@pytest.fixture(scope="module")
def short_scene(tmp_path_factory):
    """The built-in scene with 3-step episodes, as a scene YAML."""
    doc = default_scene().model_dump(mode="json")
    doc["episode"]["max_steps"] = MAX_STEPS
    path = tmp_path_factory.mktemp("scene") / "scene.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def _cli(monkeypatch, capsys, *argv) -> tuple[int, list[str], str]:
    from trials.cli.main import main

    monkeypatch.setattr(sys, "argv", ["advobj", *map(str, argv)])
    with pytest.raises(SystemExit) as exc:
        main()
    out = capsys.readouterr()
    return exc.value.code, [line for line in out.err.splitlines() if line.strip()], out.out


def _refused(monkeypatch, capsys, *argv) -> str:
    """The one error line of a refused command (exit 2); a measurement's progress bar may precede it."""
    code, err, _ = _cli(monkeypatch, capsys, *argv)
    errors = [line for line in err if line.startswith("error:")]
    assert code == 2 and len(errors) == 1 and err[-1] == errors[0], err
    assert all(line.startswith("clean-success check:") for line in err[:-1]), err
    return errors[0]


def test_the_ci_preset_policy_is_refused_from_its_card_in_seconds_before_the_pool_top_up(
    ci_policy, tmp_path, monkeypatch, capsys
):
    """Before the gate, this attack topped its one-configuration pool up to 32 attack configurations
    (up to 124 clean candidates of 60 steps): minutes. Now its card refuses it, with no rollout."""
    out = tmp_path / "atk"
    t0 = time.perf_counter()
    line = _refused(monkeypatch, capsys, "attack", "run", "--policy", ci_policy, "--preset", "ci", "--out", out)
    assert time.perf_counter() - t0 < 30
    assert line == f"error: {ci_policy}: {REFUSED_BY_CARD}" + line.split(REFUSED_BY_CARD, 1)[1]
    assert all(a in line for a in ADVICE)
    assert not out.exists()


def test_eval_refuses_the_ci_preset_policy_from_its_card_and_writes_nothing(
    ci_policy, attack_dir, tmp_path, monkeypatch, capsys
):
    out = tmp_path / "ev"
    argv = ["eval", "--policy", ci_policy, "--attack", attack_dir, "--episodes", "4", "--out", out]
    line = _refused(monkeypatch, capsys, *argv)
    assert line.startswith(f"error: {ci_policy}: {REFUSED_BY_CARD}") and all(a in line for a in ADVICE)
    assert not out.exists()


def test_without_a_card_figure_the_policy_is_measured_before_the_top_up_and_refused(
    tmp_path, short_scene, monkeypatch, capsys
):
    spec = load_spec(short_scene)
    policy = incompetent_policy(tmp_path / "policy")
    save_pool(policy / "feasible_pool.json", spec, sample_pool(spec, 1, seed=0, part="attack"))  # short: a top-up
    out = tmp_path / "atk"
    line = _refused(
        monkeypatch, capsys, "attack", "run", "--policy", policy, "--scene", short_scene, "--preset", "ci", "--out", out
    )
    assert line.startswith(f"error: {policy}: clean success 0.0% (0/8 clean episodes measured on this scene, 95% CI ")
    assert "below --min-clean-success 0.5" in line and not out.exists()
    out = tmp_path / "ev"
    argv = ["eval", "--policy", policy, "-c", "clean", "--scene", short_scene, "--max-steps", MAX_STEPS]
    line = _refused(monkeypatch, capsys, *argv, "--episodes", "2", "--out", out)  # its pool has no evaluation part
    assert "(0/8 clean episodes measured on this scene" in line and not out.exists()


def test_min_clean_success_0_turns_the_gate_off(ci_policy, tmp_path, monkeypatch, capsys):
    """The card-refused policy evaluated on configurations given to it (2 clean episodes)."""
    spec = default_scene()
    pool = tmp_path / "pool.json"
    save_pool(pool, spec, sample_pool(spec, 2, seed=0, part="evaluation"))
    out = tmp_path / "ev"
    argv = ["eval", "--policy", ci_policy, "-c", "clean", "--pool", pool, "--episodes", "2", "--gifs", "0"]
    assert _refused(monkeypatch, capsys, *argv, "--out", out).startswith(f"error: {ci_policy}: {REFUSED_BY_CARD}")
    code, err, said = _cli(monkeypatch, capsys, *argv, "--out", out, "--min-clean-success", "0")
    assert code == 0, err
    assert "clean: T-ASR" in said and "(n=2, 95% CI)" in said and (out / "summary.json").is_file()


@pytest.mark.parametrize("value", ["1.5", "-0.2", "nan"])
def test_a_threshold_outside_0_1_is_one_line_naming_the_flag(ci_policy, tmp_path, monkeypatch, capsys, value):
    for argv in (["attack", "run", "--policy", ci_policy], ["eval", "--policy", ci_policy]):
        line = _refused(monkeypatch, capsys, *argv, "--out", tmp_path / "o", "--min-clean-success", value)
        assert "--min-clean-success" in line
    assert not (tmp_path / "o").exists()


def test_the_job_layer_carries_the_threshold_to_its_pool_and_eval_jobs(ci_policy, tmp_path, monkeypatch, capsys):
    """``--shards 2`` runs a pool job and two eval-shard jobs; each applies the threshold given."""
    # The pool job, about to top the card-refused policy's one-configuration pool up: refused at 0.3
    # (not at the default 0.5 it used to check at), from the card, with nothing evaluated.
    out = tmp_path / "ev-pool"
    line = _refused(
        monkeypatch, capsys, "eval", "--policy", ci_policy, "--shards", "2", "--min-clean-success", "0.3", "--out", out
    )
    assert line.startswith(f"error: job pool: {ci_policy}: clean success 6.2% (1/16 episodes, from its card) ")
    assert "below --min-clean-success 0.3" in line and not (out / "summary.json").exists()
    # Configurations given (the pool job builds none): the eval-shard jobs check the card, refuse at
    # the default and evaluate at 0.
    pool = tmp_path / "pool.json"
    save_pool(pool, default_scene(), sample_pool(default_scene(), 2, seed=0, part="evaluation"))
    argv = ["eval", "--policy", ci_policy, "-c", "clean", "--pool", pool, "--episodes", "2", "--gifs", "0"]
    line = _refused(monkeypatch, capsys, *argv, "--shards", "2", "--out", tmp_path / "ev-default")
    assert line.startswith("error: job eval-shard0of2: ") and REFUSED_BY_CARD in line
    code, err, said = _cli(
        monkeypatch, capsys, *argv, "--shards", "2", "--min-clean-success", "0", "--out", tmp_path / "ev"
    )
    assert code == 0, err
    assert "clean: T-ASR" in said and "(n=2, 95% CI)" in said and (tmp_path / "ev" / "summary.json").is_file()


def test_the_python_attack_job_raises_the_same_refusal(ci_policy, tmp_path):
    from sim.policies.competence import IncompetentPolicyError
    from trials.jobs.attack import AttackJob, attack_job

    with pytest.raises(IncompetentPolicyError, match=f"^{re.escape(f'{ci_policy}: {REFUSED_BY_CARD}')}") as err:
        attack_job(ci_policy, "ci", None, None, None, tmp_path / "atk", False, progress=False, log=lambda _t: None)
    assert (err.value.figure.success.k, err.value.figure.success.n) == (1, 16)
    with pytest.raises(IncompetentPolicyError, match=re.escape(REFUSED_BY_CARD)):
        AttackJob(policy=ci_policy, preset="ci", out=tmp_path / "atk").run(progress=False, log=lambda _t: None)
    assert not (tmp_path / "atk").exists()


def test_policy_eval_says_when_the_clean_success_is_below_the_gates_default(tmp_path, monkeypatch, capsys):
    policy = incompetent_policy(tmp_path / "policy")
    code, err, said = _cli(monkeypatch, capsys, "policy", "eval", policy, "--episodes", "2", "--out", tmp_path / "ev")
    assert code == 0, err
    assert "clean success: 0.0% (0/2;" in said
    assert "below the 50% that 'advobj attack run' and 'advobj eval' ask for by default (--min-clean-success)" in said
