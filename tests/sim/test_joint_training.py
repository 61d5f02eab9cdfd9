"""DAgger trains a joint-space policy on the Panda scene: the expert's IK joint targets become the
labels of the joint action that executes them, the policy reads the joint positions, and a tiny run
(one iteration, a few episodes) goes end to end and learns its labels measurably."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from pydantic import ValidationError

from sim.env import ReachEnv
from sim.policies.checkpoint import load_checkpoint
from sim.policies.dagger import collect
from sim.policies.policy import VisuomotorPolicy
from sim.policies.presets import TrainConfig, resolve_preset
from sim.policies.train import train_policy
from sim.spec import default_scene, load_spec

PANDA_SCENE = Path(__file__).resolve().parents[2] / "scenes" / "panda-joint.yaml"
TINY = dict(
    dagger=dict(iterations=1, episodes_per_iter=4, num_envs=4, grad_steps_per_iter=40, batch_size=32),
    final_eval_episodes=4,
)


@pytest.fixture(scope="module")
def spec():
    return load_spec(PANDA_SCENE)


def test_the_preset_on_a_scene_with_an_arm_makes_a_joint_space_contract_from_its_urdf(spec):
    cfg = resolve_preset("quick", spec=spec, action="joint_delta")
    arm = spec.arm.scene_arm()
    assert cfg.contract.joints == arm.joint_names and cfg.contract.joint_units == arm.units
    assert cfg.contract.state == ("joint_positions",) and cfg.contract.action.kind == "joint_delta"
    p = cfg.policy
    assert (p.state_dim, p.action_dim, p.output) == (7, 7, "tanh")
    np.testing.assert_allclose(p.output_scale, arm.model.limits.qd_max.numpy() * arm.control_period_s)
    pos = resolve_preset("quick", spec=spec, action="joint_position")
    assert pos.policy.output == "linear" and pos.policy.output_scale == ()
    # a delta_tcp run's record and resume hash are those of before joint-space training existed
    tcp = resolve_preset("quick")
    assert (
        "contract" not in tcp.model_dump()
        and tcp.fingerprint() == resolve_preset("quick", action="delta_tcp").fingerprint()
    )


def test_a_joint_preset_without_an_arm_or_with_ppo_is_refused_naming_the_field(spec):
    with pytest.raises(
        ValueError, match=r"^action: a joint_delta policy moves the scene's arm; scene 'paper-reach' has none"
    ):
        resolve_preset("ci", spec=default_scene(), action="joint_delta")
    with pytest.raises(ValidationError, match="method: PPO trains delta_tcp policies"):
        resolve_preset("ci", spec=spec, action="joint_delta", method="ppo")
    doc = resolve_preset("ci", spec=spec, action="joint_delta").model_dump()
    doc["policy"].update(output="linear", output_scale=())
    with pytest.raises(ValidationError, match="a joint_delta policy on 7 joints is 7, 1, tanh and 7"):
        TrainConfig.model_validate(doc)


def test_expert_labels_are_the_joint_deltas_the_env_executes(spec):
    cfg = resolve_preset("ci", spec=spec, action="joint_delta")
    policy = VisuomotorPolicy(cfg.policy, cfg.contract)
    with ReachEnv(spec, num_envs=1, image_size=64, control="joint") as env:
        frames, labels, success, driven = collect(env, policy, np.array([True]), [12])
    states = frames["_state"]
    assert success.all() and not driven.any()
    assert labels.shape == (len(states), 7) and states.shape == (len(states), 7)
    # each state's joints plus its label are the next state's joints
    np.testing.assert_allclose(states[:-1] + labels[:-1], states[1:], atol=1e-5)
    assert (np.abs(labels) <= np.asarray(cfg.policy.output_scale) + 1e-6).all()


def test_a_tiny_joint_dagger_run_goes_end_to_end_and_learns_its_labels(tmp_path, spec):
    cfg = resolve_preset("ci", spec=spec, action="joint_delta", **TINY)
    card = train_policy(cfg, tmp_path / "p", spec, progress=False, log=lambda *_: None, keep_state=True)
    assert card.contract == cfg.contract and card.clean_success.n == 4
    record = card.training["history"][0]
    assert record["expert_ik_misses"] >= 0 and record["frames"] > 0
    policy, _ = load_checkpoint(tmp_path / "p")
    with np.load(tmp_path / "p" / "train_state" / "data.npz", allow_pickle=False) as d:
        images, states, labels = d["images"], d["states"], d["actions"]

    def mse(p):
        return float(np.mean((p.act(images, states) - labels) ** 2))

    torch.manual_seed(cfg.seed)
    fresh = VisuomotorPolicy(cfg.policy, cfg.contract)
    assert mse(policy) < 0.5 * mse(fresh)
