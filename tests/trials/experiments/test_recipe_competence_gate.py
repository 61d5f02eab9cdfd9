"""A recipe carries its competence threshold (``ExperimentConfig.min_clean_success``) to the jobs it
declares: its attack jobs refuse a policy below it, and 0 turns the check off. The pool and
evaluation jobs get it through the same declarations ``advobj eval --shards`` uses, where
tests/trials/cli/test_competence_cli.py shows each of them applying it."""

import pytest

from sim.spec import default_scene
from tests.trials.cli.test_competence_cli import incompetent_policy
from tests.trials.conftest import MAX_STEPS
from tests.trials.experiments.test_experiments import TINY_ATTACK
from trials.experiments.recipes import resolve_experiment, run_experiment
from trials.jobs.dag import GridError

CARD = "clean success 6.2% (1/16 episodes, from its card)"


def _table1(out, policy, pool_file, **kw):
    cfg = resolve_experiment(
        "quick", attack_overrides=TINY_ATTACK, episodes=2, max_steps=MAX_STEPS, num_envs=2, gifs=0,
        pool=str(pool_file), **kw,
    )  # fmt: skip
    return run_experiment("table1", cfg, out, policy=policy, progress=False, log=lambda _m: None)


def test_a_recipe_refuses_below_its_threshold_and_runs_with_the_check_off(tmp_path, pool_file):
    """The ``ci`` preset's outcome on the built-in scene (its card: 1 success in 16 episodes)."""
    policy = incompetent_policy(tmp_path / "policy", default_scene(), (1, 16))
    # Without its one-configuration pool: with the check off, the attacks draw the scene's
    # configurations (this untrained network reaches nothing, so a pool could not be topped up).
    (policy / "feasible_pool.json").unlink()
    for threshold in (None, 0.1):  # the default 0.5, and a threshold of the recipe's own
        with pytest.raises(GridError) as err:
            _table1(tmp_path / f"t{threshold}", policy, pool_file, min_clean_success=threshold)
        said = str(err.value)
        assert said.startswith("job attack-c2f: ") and CARD in said
        assert f"below --min-clean-success {0.5 if threshold is None else threshold}" in said
        assert not (tmp_path / f"t{threshold}" / "table.md").exists()
    text = _table1(tmp_path / "off", policy, pool_file, min_clean_success=0).read_text()
    assert "| 3D Object | ours |" in text and "| 2D Patch | ours |" in text


def test_the_threshold_is_a_fraction(tmp_path):
    from trials.experiments.recipes import ExperimentError

    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ExperimentError, match="min_clean_success"):
            resolve_experiment("quick", min_clean_success=bad)
