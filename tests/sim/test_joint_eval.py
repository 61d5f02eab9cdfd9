"""A joint-space policy through the paired evaluation (``advobj eval``'s rollout core): it runs on
the scene's arm, its clean episodes are the plain rollout's, and an attack arm measures its action
errors through the arm's FK."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sim.configs import sample_pool
from sim.policies.graph_policy import reference_frames
from sim.policies.paired import rollout_paired
from sim.policies.rollout import EnvConfig, make_env, rollout
from sim.spec import load_spec
from tests.attack.test_joint_attack import joint_policy
from trials.eval.conditions import AttackSource, Condition
from trials.eval.evaluate import rollout_condition

PANDA_SCENE = Path(__file__).resolve().parents[2] / "scenes" / "panda-joint.yaml"
EPISODES = 3
NUM_ENVS = 2  # the last episode alone in a batch padded to two
TEXTURE = np.random.default_rng(0).integers(0, 256, (32, 32, 3), dtype=np.uint8)


@pytest.fixture(scope="module")
def spec():
    s = load_spec(PANDA_SCENE)
    return s.with_updates(episode={**s.episode.model_dump(), "max_steps": 5})


@pytest.fixture(scope="module")
def policy(spec):
    return joint_policy(spec)


@pytest.fixture(scope="module")
def configs(spec):
    return sample_pool(spec, EPISODES, seed=0, part="evaluation")


def _collect(results: dict):
    return lambda j, _slot, res: results.__setitem__(j, res)


@pytest.fixture(scope="module")
def plain(spec, policy, configs):
    """The non-paired rollout (clean evaluation's) of the same configurations."""
    res = {}
    env = make_env(spec, EnvConfig(image_size=policy.image_size), NUM_ENVS, control="joint")
    try:
        rollout(env, configs, policy, _collect(res))
    finally:
        env.close()
    return res


def test_the_paired_clean_arm_of_a_joint_policy_is_the_plain_rollout(spec, policy, configs, plain):
    res = {}
    rollout_paired(policy, spec, configs, NUM_ENVS, _collect(res))
    assert sorted(res) == sorted(plain) == list(range(EPISODES))
    for j in range(EPISODES):
        assert res[j]["config"] == plain[j]["config"] == configs[j]
        assert res[j]["reached"] == plain[j]["reached"]
        assert res[j]["steps"] == plain[j]["steps"]
        assert res[j]["policy_error"] == plain[j]["policy_error"]
        np.testing.assert_allclose(res[j]["min_dist"], plain[j]["min_dist"], rtol=0, atol=1e-9)
        np.testing.assert_allclose(res[j]["T_world_tcp"], plain[j]["T_world_tcp"], rtol=0, atol=1e-9)
    assert all(res[j]["steps"] > 0 for j in range(EPISODES))


def test_the_paired_core_hands_a_joint_policys_callback_the_joints_and_the_arm(spec, policy, configs):
    seen = []

    def keep(slots, T, steps, a_adv, a_clean, views, q=None, arm=None):
        seen.append((len(slots), a_adv.shape, None if q is None else q.shape, arm))

    rollout_paired(policy, spec, configs, NUM_ENVS, lambda j, i, r: None, on_actions=keep, texture=TEXTURE)
    n = len(policy.contract.joints)
    assert seen
    for k, a_shape, q_shape, arm in seen:
        assert a_shape == (k, 1, n) and q_shape == (k, n)
        assert arm is not None and arm.joint_names == policy.contract.joints


def test_an_attack_arm_of_a_joint_policy_runs_and_measures_its_action_errors(spec, policy, configs, plain):
    clean, attack = {}, {}
    keep = lambda out: lambda j, res: out.__setitem__(j, res)  # noqa: E731
    rollout_condition(policy, spec, Condition("clean"), configs, NUM_ENVS, keep(clean))
    source = AttackSource("texture", TEXTURE, None, "")
    rollout_condition(policy, spec, Condition("attack", source=source), configs, NUM_ENVS, keep(attack))
    assert sorted(clean) == sorted(attack) == list(range(EPISODES))
    for j in range(EPISODES):
        # the clean condition is the plain rollout, and its views are the same on both sides
        assert clean[j]["reached"] == plain[j]["reached"] and clean[j]["steps"] == plain[j]["steps"]
        assert clean[j]["e_trans"] == 0.0 and clean[j]["e_rot"] == 0.0
        assert np.isfinite(attack[j]["e_trans"]) and np.isfinite(attack[j]["e_rot"])
        assert attack[j]["e_trans"] >= 0.0 and attack[j]["e_rot"] >= 0.0
    # the texture is seen: the policy's action on the attacked view differs from the clean one
    assert max(attack[j]["e_trans"] for j in range(EPISODES)) > 0.0


def test_reference_frames_of_a_joint_policy_read_the_arms_joints(spec, policy):
    n = 10
    images, state = reference_frames(policy.image_size, policy.contract, spec, n=n)
    arm = spec.arm.scene_arm()
    assert images.shape == (n, policy.image_size, policy.image_size, 3)
    assert state.shape == (n, arm.n_joints)
    q_min, q_max = (v.numpy().astype(np.float32) for v in (arm.model.limits.q_min, arm.model.limits.q_max))
    assert np.all(state >= q_min - 1e-6) and np.all(state <= q_max + 1e-6)
