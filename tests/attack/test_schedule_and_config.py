"""C2F schedule direction, strategies, and attack config validation."""

import numpy as np
import pytest

from attack.optimize import AttackError, resolve_config
from attack.schedule import PAPER_STAGES, config_weights, sample_configs, stage_index, stage_params


def _mean_r(params, r, rng_range=(0.25, 0.8)):
    return float((config_weights(r, params, rng_range) * r).sum())


def test_c2f_stage_means_move_from_far_to_near():
    r = np.linspace(0.25, 0.8, 500)
    means = [_mean_r(stage_params("c2f", it, 100), r) for it in (0, 20, 40, 60, 80)]
    assert all(a > b for a, b in zip(means, means[1:])), means
    assert means[0] > 0.65 and means[-1] < 0.4


def test_f2c_is_c2f_reversed_and_ns_is_uniform():
    for it in range(0, 100, 7):
        assert stage_params("f2c", it, 100) == PAPER_STAGES[4 - stage_index(it, 100)]
    assert stage_params("ns", 3, 100) is None
    w = config_weights(np.array([0.3, 0.5, 0.7]), None, (0.25, 0.8))
    assert np.allclose(w, 1 / 3)
    assert stage_params("coarse", 99, 100) == PAPER_STAGES[0] and stage_params("fine", 0, 100) == PAPER_STAGES[-1]


def test_five_equal_stages():
    stages = [stage_index(i, 1000) for i in range(1000)]
    assert [stages.count(k) for k in range(5)] == [200] * 5


def test_weights_are_finite_at_range_ends_and_sampling_is_reproducible():
    r = np.array([0.25, 0.25, 0.8, 0.8, 0.5])
    for params in PAPER_STAGES:
        w = config_weights(r, params, (0.25, 0.8))
        assert np.isfinite(w).all() and np.isclose(w.sum(), 1)
    a = sample_configs(r, PAPER_STAGES[0], (0.25, 0.8), 8, np.random.default_rng(1))
    b = sample_configs(r, PAPER_STAGES[0], (0.25, 0.8), 8, np.random.default_rng(1))
    assert np.array_equal(a, b)


def test_unknown_strategy_and_config_keys_are_errors():
    with pytest.raises(ValueError, match="strategy"):
        stage_params("zigzag", 0, 10)
    with pytest.raises(AttackError, match="lamda_sal"):
        resolve_config("quick", {"lamda_sal": 0.1}, source="attack.yaml")
    with pytest.raises(AttackError, match="iterations"):
        resolve_config("quick", {"iterations": 0})
    with pytest.raises(AttackError, match="preset"):
        resolve_config("medium")


def test_paper_preset_matches_the_paper():
    cfg = resolve_config("paper")
    assert (cfg.iterations, cfg.num_envs, cfg.rollout_steps) == (10_000, 4, 10)
    assert (cfg.lr, cfg.lambda_dist, cfg.lambda_sal) == (0.1, 0.1, 0.01)
    assert cfg.schedule == "c2f" and cfg.pcgrad and cfg.use_saliency
