"""One rule for non-finite actions in the sim and on the real arm: a policy error, never a motion.

Issue: the sim clipped +-inf to a full step (``to_delta`` clips ``delta_tcp``) while the real runner
recorded ``policy_error``. Now the sim's one rollout ends such an episode with ``policy_error`` too,
and ``policy eval`` / ``advobj eval`` report it.
"""

from __future__ import annotations

import numpy as np
import pytest

from sim.action import POLICY_ERROR, nonfinite_rows
from sim.policies.contract import PolicyContract
from sim.policies.rollout import EnvConfig, make_env, run_episodes
from sim.spec import default_scene


class _Scripted:
    """A one-image delta_tcp policy whose k-th call returns ``script[k]`` for every row."""

    image_size = 32
    white_box = False
    contract = PolicyContract()

    def __init__(self, script):
        self.script = [np.asarray(a, dtype=np.float64) for a in script]
        self.calls = 0

    def act(self, images):
        a = self.script[min(self.calls, len(self.script) - 1)]
        self.calls += 1
        return np.repeat(a[None], len(images), axis=0)


def _run(script, seeds=(0,), steps=4):
    spec = default_scene()
    spec = spec.with_updates(episode={**spec.episode.model_dump(), "max_steps": steps})
    env = make_env(spec, EnvConfig(image_size=32), num_envs=len(seeds))
    try:
        T0 = None
        env.reset_envs(range(len(seeds)), seeds=list(seeds))
        T0 = env.T_world_tcp.copy()
        res = run_episodes(env, _Scripted(script), list(seeds))
        return res, T0, env.T_world_tcp.copy()
    finally:
        env.close()


@pytest.mark.parametrize("bad", [np.inf, -np.inf, np.nan], ids=["+inf", "-inf", "nan"])
def test_a_non_finite_first_action_ends_the_episode_as_a_policy_error_without_moving(bad):
    a = np.zeros(6)
    a[0] = bad
    res, T0, T1 = _run([a])
    assert res.policy_error.tolist() == [True]
    assert res.reached.tolist() == [-1] and not res.success.any()
    assert res.steps.tolist() == [0]  # nothing was executed
    np.testing.assert_array_equal(T0, T1)  # the +-inf was not clipped into a full step
    assert res.summary()["policy_errors"] == 1


def test_a_policy_error_mid_episode_keeps_the_executed_steps_and_stops_there():
    ok = np.array([0.1, 0, 0, 0, 0, 0])
    bad = np.array([0, 0, np.inf, 0, 0, 0])
    res, _, _ = _run([ok, ok, bad], steps=6)
    assert res.policy_error.tolist() == [True]
    assert res.steps.tolist() == [2]


def test_finite_actions_never_count_as_policy_errors_even_at_huge_magnitudes():
    res, _, _ = _run([np.full(6, 1e300)], seeds=(0, 1), steps=2)
    assert not res.policy_error.any()
    assert res.summary()["policy_errors"] == 0


def test_nonfinite_rows_flags_any_nan_or_inf_in_a_row_of_any_rank():
    a = np.zeros((3, 4, 6))
    a[1, 3, 5] = np.nan
    a[2, 0, 0] = -np.inf
    assert nonfinite_rows(a).tolist() == [False, True, True]
    assert POLICY_ERROR == "policy_error"


def test_the_eval_row_of_a_policy_error_episode_says_policy_error():
    from trials.eval.evaluate import _row

    spec = default_scene()

    class _Cfg:
        seed, r_m, theta_rad, phi_rad = 3, 0.3, 0.1, 0.5

    res = {
        "reached": -1,
        "policy_error": True,
        "steps": 0,
        "e_trans": float("nan"),
        "e_rot": float("nan"),
        "min_dist": [0.2] * len(spec.objects),
    }
    row = _row("clean", _Cfg(), res, spec)
    assert row["outcome"] == POLICY_ERROR and not row["success"] and not row["targeted"]
