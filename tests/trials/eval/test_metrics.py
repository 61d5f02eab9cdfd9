"""Metric functions on hand-made episode tables: bins, rates, action errors, bootstrap, McNemar."""

import math

import numpy as np
import pytest

from trials.eval.metrics import (
    DISTANCE_BINS_CM,
    PHI_BINS_DEG,
    action_errors,
    attack_rates,
    bin_index,
    bin_labels,
    bootstrap_mean_ci,
    mcnemar_exact,
    mcnemar_from_outcomes,
)


def test_distance_bins_follow_the_paper_edges_including_boundaries():
    r_cm = [25.0, 35.99, 36.0, 47.0, 57.9, 58.0, 69.0, 79.99, 80.0, 24.99, 80.01, float("nan")]
    assert bin_index(r_cm, DISTANCE_BINS_CM).tolist() == [0, 0, 1, 2, 2, 3, 4, 4, 4, -1, -1, -1]
    assert bin_labels(DISTANCE_BINS_CM) == ["25-36", "36-47", "47-58", "58-69", "69-80"]


def test_phi_bins_have_a_wide_last_bin_closed_at_90_degrees():
    phi = [0.0, 9.99, 10.0, 65.0, 70.0, 89.0, 90.0, -0.1]
    assert bin_index(phi, PHI_BINS_DEG).tolist() == [0, 0, 1, 6, 7, 7, 7, -1]
    assert bin_labels(PHI_BINS_DEG)[-1] == "70-90"
    with pytest.raises(ValueError, match="increasing"):
        bin_index([1.0], [0.0, 0.0, 1.0])


def test_attack_rates_count_failures_and_adversarial_reaches_with_wilson_intervals():
    # goal = 0, adversarial = 1; outcomes: goal, adversarial, none, adversarial
    rates = attack_rates([0, 1, -1, 1], goal_index=0, adv_index=1)
    assert (rates["asr"].k, rates["asr"].n) == (3, 4)
    assert (rates["tasr"].k, rates["tasr"].n) == (2, 4)
    assert rates["asr"].lo < 0.75 < rates["asr"].hi
    empty = attack_rates([], 0, 1)
    assert empty["asr"].n == 0 and math.isnan(empty["asr"].rate) and (empty["asr"].lo, empty["asr"].hi) == (0.0, 1.0)
    all_goal = attack_rates([0] * 10, 0, 1)
    assert all_goal["asr"].lo == 0.0 and all_goal["asr"].rate == 0.0 and 0.0 < all_goal["asr"].hi < 0.35


def test_action_errors_units_translation_l2_and_rotation_angle_in_rad():
    clean = np.zeros((3, 6))
    adv = np.array([[1.0, 0, 0, 0, 0, 0], [0, 0.6, 0.8, 0, 0, 0], [0, 0, 0, 0, 0, 1.0]])
    e_t, e_r = action_errors(adv, clean, max_step_rad=0.1)
    np.testing.assert_allclose(e_t, [1.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(e_r, [0.0, 0.0, 0.1], atol=1e-9)
    # opposite rotations about the same axis: angle adds up
    _, e_r2 = action_errors(np.array([[0, 0, 0, 1.0, 0, 0]]), np.array([[0, 0, 0, -1.0, 0, 0]]), 0.1)
    np.testing.assert_allclose(e_r2, [0.2], atol=1e-9)
    with pytest.raises(ValueError, match="6"):
        action_errors(np.zeros((2, 3)), np.zeros((2, 3)), 0.1)


def test_bootstrap_interval_contains_the_mean_and_handles_degenerate_samples():
    x = np.random.default_rng(0).normal(1.0, 0.5, 400)
    ci = bootstrap_mean_ci(x, seed=1)
    assert ci.lo < ci.mean < ci.hi and ci.n == 400
    # the bootstrap width is close to the normal-theory one for a mean of 400 draws
    assert abs((ci.hi - ci.lo) - 2 * 1.96 * x.std() / 20) < 0.02
    assert bootstrap_mean_ci(x, seed=1) == ci  # deterministic
    empty = bootstrap_mean_ci([])
    assert empty.n == 0 and math.isnan(empty.mean) and math.isnan(empty.lo)
    one = bootstrap_mean_ci([0.3])
    assert (one.mean, one.lo, one.hi, one.n) == (0.3, 0.3, 0.3, 1)
    const = bootstrap_mean_ci([0.0] * 50)
    assert (const.lo, const.hi) == (0.0, 0.0)
    assert bootstrap_mean_ci([1.0, float("nan"), 3.0]).n == 2


def test_mcnemar_exact_matches_hand_computed_binomial_tails():
    # b=0, c=5: p = 2 * C(5,0)/2^5 = 1/16
    assert mcnemar_exact(0, 5).p_value == pytest.approx(1 / 16)
    # b=1, c=9: p = 2 * (1 + 10) / 1024
    assert mcnemar_exact(1, 9).p_value == pytest.approx(22 / 1024)
    # symmetric, and balanced discordance gives p = 1
    assert mcnemar_exact(9, 1).p_value == mcnemar_exact(1, 9).p_value
    assert mcnemar_exact(4, 4).p_value == 1.0
    # no discordant pairs: no evidence
    assert mcnemar_exact(0, 0).p_value == 1.0
    # large counts stay exact and tiny
    assert 0.0 < mcnemar_exact(0, 200).p_value < 1e-59
    with pytest.raises(ValueError):
        mcnemar_exact(-1, 2)


def test_mcnemar_from_outcomes_pairs_edge_cases():
    assert mcnemar_from_outcomes([], []).to_dict() == {"b": 0, "c": 0, "n_pairs": 0, "p_value": 1.0}
    same = mcnemar_from_outcomes([True, False, True], [True, False, True])
    assert (same.b, same.c, same.p_value) == (0, 0, 1.0)
    all_disc = mcnemar_from_outcomes([True] * 6, [False] * 6)
    assert (all_disc.b, all_disc.c, all_disc.n_pairs) == (6, 0, 6)
    assert all_disc.p_value == pytest.approx(2 / 64)
    mixed = mcnemar_from_outcomes([1, 1, 0, 0, 1], [0, 1, 1, 0, 0])
    assert (mixed.b, mixed.c) == (2, 1)
    with pytest.raises(ValueError, match="same length"):
        mcnemar_from_outcomes([True], [True, False])


def test_summary_pairs_conditions_by_seed_for_mcnemar():
    from sim.spec import default_scene
    from trials.eval.report import summarize

    spec = default_scene()
    goal, adv = spec.object_index("goal"), spec.object_index("adversarial")

    def row(cond, seed, reached):
        return {
            "condition": cond,
            "seed": seed,
            "r_m": 0.5,
            "phi_rad": 0.3,
            "reached": reached,
            "success": reached == goal,
            "targeted": reached == adv,
            "steps": 10,
            "e_trans": 0.0,
            "e_rot": 0.0,
        }

    rows = [row("clean", s, goal) for s in range(6)]
    rows += [row("attack", s, adv) for s in range(5)] + [row("attack", 5, goal)]
    rows += [row("patch", s, adv if s < 2 else goal) for s in (5, 4, 3, 2, 1, 0)]  # order must not matter
    s = summarize(rows, spec, ["clean", "attack", "patch"])
    vs = s["conditions"]["attack"]["vs_clean"]["tasr"]
    assert (vs["b"], vs["c"], vs["n_pairs"]) == (5, 0, 6) and vs["p_value"] == pytest.approx(2 / 32)
    pair = s["paired"]["attack vs patch"]["tasr"]
    assert (pair["b"], pair["c"]) == (3, 0) and pair["p_value"] == pytest.approx(2 / 8)
    assert s["conditions"]["attack"]["by_distance"]["47-58"]["n"] == 6
