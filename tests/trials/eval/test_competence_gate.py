"""``run_eval``'s competence gate, as a Python caller meets it: the refusal is an exception raised
before anything is written; the policy is measured only when the evaluation would build its pool."""

from __future__ import annotations

import re

import pytest

from sim.configs import sample_pool, save_pool
from sim.policies.competence import IncompetentPolicyError
from sim.spec import default_scene
from tests.trials.cli.test_competence_cli import REFUSED_BY_CARD, incompetent_policy
from tests.trials.conftest import MAX_STEPS
from trials.eval.evaluate import load_eval_config, run_eval


def test_a_card_below_the_threshold_raises_before_the_evaluation_folder_exists(tmp_path):
    spec = default_scene()
    policy = incompetent_policy(tmp_path / "policy", spec, (1, 16))
    pool = tmp_path / "pool.json"
    save_pool(pool, spec, sample_pool(spec, 2, seed=0, part="evaluation"))  # enough: no pool to build
    cfg = load_eval_config(policy=str(policy), conditions=("clean",), episodes=2, pool=str(pool), gifs=0)
    with pytest.raises(IncompetentPolicyError, match=f"^{re.escape(f'{policy}: {REFUSED_BY_CARD}')}"):
        run_eval(cfg, tmp_path / "ev", progress=False, report=False)
    assert not (tmp_path / "ev").exists()
    with pytest.raises(IncompetentPolicyError, match=r"below --min-clean-success 0\.1:"):
        run_eval(cfg, tmp_path / "ev", progress=False, report=False, min_clean_success=0.1)
    summary = run_eval(cfg, tmp_path / "ev", progress=False, report=False, min_clean_success=0.05)  # 6.2% >= 5%
    assert summary["conditions"]["clean"]["n"] == 2


def test_without_a_card_figure_nothing_is_measured_when_the_pool_suffices(tmp_path, short_spec, pool_file):
    """An untrained policy (it reaches nothing) on a pool that holds the episodes asked for: no pool is
    built, so no clean rollout is spent on the check, and the evaluation runs."""
    policy = incompetent_policy(tmp_path / "policy")
    cfg = load_eval_config(
        policy=str(policy), conditions=("clean",), episodes=2, max_steps=MAX_STEPS, pool=str(pool_file), gifs=0
    )
    summary = run_eval(cfg, tmp_path / "ev", progress=False, report=False)
    assert summary["conditions"]["clean"]["n"] == 2
    short = tmp_path / "short.json"
    save_pool(short, short_spec, sample_pool(short_spec, 1, seed=0, part="evaluation"))
    with pytest.raises(IncompetentPolicyError, match=r"\(0/8 clean episodes measured on this scene"):
        run_eval(cfg.model_copy(update={"pool": str(short)}), tmp_path / "built", progress=False, report=False)
    assert not (tmp_path / "built").exists()
