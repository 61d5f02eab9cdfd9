"""The competence gate (``sim.policies.competence``): the card's figure, the measured one, the decision.

Rollouts are real (EGL): an untrained 32 px CNN that reaches nothing in 3-step episodes, and the
task-feasible pool builder's forward-pushed CNN, which reaches the goal from some starts.
"""

from __future__ import annotations

import itertools
import math
import time
from types import SimpleNamespace

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sim.configs import part_seeds, spec_fingerprint
from sim.policies.card import ActionScaling, CleanSuccess, PolicyCard
from sim.policies.competence import (
    CHECK_EPISODES,
    CHECK_ROUND,
    DEFAULT_MIN_CLEAN_SUCCESS,
    CompetenceError,
    IncompetentPolicyError,
    card_clean_success,
    decide,
    require_competence,
)
from sim.policies.pool import build_feasible
from sim.spec import default_scene
from sim.stats import wilson_interval
from tests.policy_zoo import contract_of, tiny_policy
from tests.sim.test_policies_feasible import _forward_policy


def _short_scene(max_steps: int = 3):
    spec = default_scene()
    return spec.with_updates(episode={**spec.episode.model_dump(), "max_steps": max_steps})


def _card(spec, k: int, n: int, fingerprint: str | None = None) -> PolicyCard:
    """A card as ``advobj policy train`` writes it: the clean success of its final evaluation on ``spec``."""
    lo, hi = wilson_interval(k, n)
    return PolicyCard(
        action=ActionScaling(max_step_m=0.02, max_step_rad=0.1),
        training={"scene": {"name": spec.name, "fingerprint": fingerprint or spec_fingerprint(spec)}},
        clean_success=CleanSuccess(
            k=k, n=n, rate=k / n if n else None, lo=lo, hi=hi, confidence=0.95, episodes_seed=0, image_size=32
        ),
    )


def _known_by_its_card(card):
    """A policy the gate may only read the card of: rolling it out would fail (it has no ``act``)."""
    return SimpleNamespace(card=card)


# ----------------------------------------------------------------------------- the decision
@settings(max_examples=400, deadline=None)
@given(
    n=st.integers(0, 64),
    frac=st.floats(0.0, 1.0),
    threshold=st.floats(1e-9, 1.0),
    max_episodes=st.integers(1, 64),
)
def test_a_decision_always_agrees_with_the_rate_and_is_taken_by_the_last_episode(n, frac, threshold, max_episodes):
    k = min(n, int(frac * n))
    d = decide(k, n, threshold, max_episodes)
    if d == "refuse":
        assert k / n < threshold
    if d == "pass":
        assert k / n >= threshold
    if n == 0:
        assert d is None
    elif n >= max_episodes:
        assert d is not None


def test_at_the_default_threshold_the_first_round_settles_the_clear_cases():
    """The module's stated rule: after 8 episodes, 0-1 successes refuse and 7-8 pass; the rest need 8 more."""
    assert CHECK_ROUND == 8 and CHECK_EPISODES == 16 and DEFAULT_MIN_CLEAN_SUCCESS == 0.5
    got = [decide(k, CHECK_ROUND, DEFAULT_MIN_CLEAN_SUCCESS) for k in range(CHECK_ROUND + 1)]
    assert got == ["refuse", "refuse", None, None, None, None, None, "pass", "pass"]
    assert decide(8, 16, 0.5) == "pass" and decide(7, 16, 0.5) == "refuse"


def test_a_threshold_of_one_needs_every_episode_and_the_extremes_decide_consistently():
    assert decide(8, 8, 1.0) is None and decide(16, 16, 1.0) == "pass" and decide(15, 16, 1.0) == "refuse"
    assert decide(0, 16, 1e-12) == "refuse" and decide(1, 1, 1e-12) == "pass"
    with pytest.raises(ValueError, match="max_episodes"):
        decide(0, 0, 0.5, max_episodes=0)


# ----------------------------------------------------------------------------- the card
def test_the_cards_figure_counts_only_for_the_scene_it_was_measured_on():
    spec = default_scene()
    assert card_clean_success(_known_by_its_card(_card(spec, 1, 16)), spec).k == 1
    assert card_clean_success(_known_by_its_card(_card(spec, 1, 16)), _short_scene()) is None  # another episode length
    assert card_clean_success(_known_by_its_card(_card(spec, 1, 16, fingerprint="0" * 16)), spec) is None
    assert card_clean_success(_known_by_its_card(_card(spec, 0, 0)), spec) is None  # no episodes: no figure
    bad = _card(spec, 1, 16)
    bad.clean_success.k = 17  # more successes than episodes: not a figure to go by
    assert card_clean_success(_known_by_its_card(bad), spec) is None
    untrained = PolicyCard(action=ActionScaling(max_step_m=0.02, max_step_rad=0.1))
    assert card_clean_success(_known_by_its_card(untrained), spec) is None
    assert card_clean_success(object(), spec) is None  # a policy without a card


def test_a_card_below_the_threshold_refuses_in_one_line_without_a_rollout():
    spec = default_scene()
    t0 = time.perf_counter()
    with pytest.raises(IncompetentPolicyError) as err:
        require_competence(_known_by_its_card(_card(spec, 1, 16)), spec, name="runs/policy-ci")
    msg = str(err.value)
    assert time.perf_counter() - t0 < 1.0
    assert msg.startswith(
        "runs/policy-ci: clean success 6.2% (1/16 episodes, from its card) is below --min-clean-success 0.5"
    )
    assert "\n" not in msg
    for what in ("train it longer", "check that the scene", "lower --min-clean-success", "0 turns the check off"):
        assert what in msg
    assert err.value.figure.source == "card" and (err.value.figure.success.k, err.value.figure.success.n) == (1, 16)


def test_a_card_at_or_above_the_threshold_passes_and_zero_turns_the_gate_off():
    spec = default_scene()
    fig = require_competence(_known_by_its_card(_card(spec, 8, 16)), spec)
    assert fig.source == "card" and fig.success.rate == 0.5
    assert require_competence(_known_by_its_card(_card(spec, 1, 16)), spec, 0.0) is None
    assert require_competence(_known_by_its_card(_card(spec, 1, 16)), spec, 0.05).success.k == 1
    # no card figure and not asked to measure: nothing to go by, nothing rolled out
    assert require_competence(_known_by_its_card(None), spec, measure=False) is None


@pytest.mark.parametrize("value", [1.5, -0.1, math.nan, math.inf, "half", None])
def test_a_threshold_that_is_not_a_fraction_is_one_line_naming_the_flag(value):
    with pytest.raises(CompetenceError) as err:
        require_competence(_known_by_its_card(None), default_scene(), value, flag="--min-clean-success")
    assert str(err.value).startswith("--min-clean-success: expected a fraction of episodes in [0, 1]")
    assert not isinstance(err.value, IncompetentPolicyError)


# ----------------------------------------------------------------------------- measured
def test_an_incompetent_policy_without_a_card_figure_is_measured_and_refused_after_one_round():
    policy = tiny_policy(contract_of((), ("delta_tcp", 1, 1)))  # untrained: reaches nothing in 3 steps
    with pytest.raises(IncompetentPolicyError) as err:
        require_competence(policy, _short_scene(), progress=False, name="tiny")
    fig = err.value.figure
    assert fig.source == "measured" and (fig.success.k, fig.success.n) == (0, CHECK_ROUND)
    assert str(err.value).startswith(
        f"tiny: clean success 0.0% (0/{CHECK_ROUND} clean episodes measured on this scene, 95% CI 0.0-"
    )


@pytest.fixture(scope="module")
def fast_scene():
    """The pool builder's test scene: long steps, at most 12 of them."""
    base = default_scene()
    return base.with_updates(episode={**base.episode.model_dump(), "max_steps": 12, "max_step_m": 0.07})


def test_the_measured_figure_counts_what_the_pool_builder_keeps_of_the_same_candidates(fast_scene):
    """Undecided after the first round, the check runs all 16 episodes: its successes are exactly the
    configurations the task-feasible pool builder keeps of the first 16 candidates of the part."""
    policy = _forward_policy((), ("delta_tcp", 1, 1))
    kept, tried = build_feasible(policy, fast_scene, "evaluation", 16, 0, 4, max_candidates=16, progress=False)
    assert tried == 16 and 0 < len(kept) < 16
    first_round = set(itertools.islice(part_seeds("evaluation", 0), CHECK_ROUND))
    threshold = len(kept) / 16  # a pass, by the rate, that the first round alone must not settle
    assert decide(sum(c.seed in first_round for c in kept), CHECK_ROUND, threshold) is None
    fig = require_competence(policy, fast_scene, threshold, num_envs=4, progress=False)
    assert fig.source == "measured" and (fig.success.k, fig.success.n) == (len(kept), 16)
    assert decide(len(kept), 16, (len(kept) + 1) / 16) == "refuse"  # one more success needed: refused at 16
