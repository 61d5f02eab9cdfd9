"""The attack against a joint-space policy: the pose loss reads the TCP its joint action leads to
through the arm's FK, differentiably; the rollouts execute the policy's joint targets in the
joint-controlled env; validation rolls it out as evaluation does."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from attack.losses import safe_cosine
from attack.optimize import AttackError, AttackRun, resolve_config, run_attack
from sim.action import intended_heading, intended_position
from sim.configs import sample_pool
from sim.policies.contract import ActionContract, PolicyContract, first_action, to_joint_target
from sim.policies.policy import PolicyArch, VisuomotorPolicy
from sim.spec import load_spec

PANDA_SCENE = Path(__file__).resolve().parents[2] / "scenes" / "panda-joint.yaml"
CFG = {
    "iterations": 2,
    "num_envs": 2,
    "rollout_steps": 2,
    "texture_size": 16,
    "checkpoint_every": 2,
    "lr": 0.5,
    "validation_every": 2,
    "validation_episodes": 2,
    "validation_max_steps": 4,
}


@pytest.fixture(scope="module")
def spec():
    return load_spec(PANDA_SCENE)


@pytest.fixture(scope="module")
def pool(spec):
    return sample_pool(spec, 6, seed=3, part="attack") + sample_pool(spec, 2, seed=3, part="validation")


def joint_policy(spec) -> VisuomotorPolicy:
    arm = spec.arm.scene_arm()
    contract = PolicyContract(
        state=("joint_positions",),
        action=ActionContract(kind="joint_delta"),
        joints=arm.joint_names,
        joint_units=arm.units,
    )
    step = tuple(float(v) for v in arm.model.limits.qd_max * arm.control_period_s)
    arch = PolicyArch(
        arch="small_cnn", image_size=32, head_hidden=16, head_channels=4, state_dim=7, action_dim=7, output_scale=step
    )
    torch.manual_seed(0)
    return VisuomotorPolicy(arch, contract=contract)


def test_the_pose_loss_is_the_papers_on_the_fk_tcp_of_the_executed_joint_step(spec, pool):
    run = AttackRun(joint_policy(spec), spec, resolve_config("ci", CFG), pool=pool)
    try:
        assert run.env.control == "joint" and run.arm is not None
        run.source.start(0, np.random.default_rng(0))
        frames = run.source.next()
        assert frames.q is not None and frames.q.shape == (2, 7)
        q_before = run.env.q
        out = run.frame_gradients(run.state, frames)
        # the env's command is the policy's joint target on the same images and joint state
        with torch.no_grad():
            raw = run.policy(out["images"], torch.from_numpy(q_before).float())
        want = to_joint_target(q_before, first_action(raw).double().numpy(), "joint_delta")
        np.testing.assert_allclose(out["commands"], want, atol=1e-6)
        # the pose term's motion leads to the FK pose of that step, and the loss is L_ori + lambda L_dist there
        q = torch.from_numpy(q_before)
        T_next = run.arm.tcp_pose(run.arm.limit_step(q, torch.from_numpy(want))).float()
        T = frames.T_world_tcp
        a = out["actions"]
        ep = spec.episode
        torch.testing.assert_close(intended_position(T, a, ep.max_step_m), T_next[:, :3, 3], atol=1e-5, rtol=0)
        torch.testing.assert_close(intended_heading(T, a, ep.max_step_rad), T_next[:, :3, 2], atol=1e-4, rtol=0)
        v = frames.p_adv - T_next[:, :3, 3]
        l_ori = 1 - safe_cosine(T_next[:, :3, 2], v)
        l_dist = v.norm(dim=-1)
        lam = run.cfg.lambda_dist
        assert out["values"]["pose"] == pytest.approx(float((l_ori + lam * l_dist).sum()), rel=1e-4)
        for g in out["grads"].values():
            assert torch.isfinite(g).all()
        # the rollout executes those targets (within the joint limits)
        run.source.advance(out["commands"])
        np.testing.assert_allclose(run.env.q, run.arm.limit_step(q, torch.from_numpy(want)).numpy(), atol=1e-12)
    finally:
        run.close()


def test_the_pose_gradient_reaches_the_policys_joint_output_through_the_fk(spec, pool):
    run = AttackRun(joint_policy(spec), spec, resolve_config("ci", CFG), pool=pool)
    try:
        run.source.start(0, np.random.default_rng(1))
        frames = run.source.next()
        a = torch.full((2, 7), 0.01, requires_grad=True)
        d = run.next_delta(a, frames.T_world_tcp, frames.q)
        p_next = intended_position(frames.T_world_tcp, d, spec.episode.max_step_m)
        (g,) = torch.autograd.grad((frames.p_adv - p_next).norm(dim=-1).sum(), a)
        assert torch.isfinite(g).all() and g.abs().sum() > 0
    finally:
        run.close()


def test_a_joint_policy_attack_runs_validates_and_probes_end_to_end(tmp_path, spec, pool):
    run = AttackRun(joint_policy(spec), spec, resolve_config("ci", CFG), pool=pool, out_dir=tmp_path)
    try:
        run_attack(run, progress=False)
        h = run.state.history
        assert run.state.iteration == 2 and np.isfinite(h.terms["pose"]).all()
        assert len(h.val_t_asr) >= 2 and all(0.0 <= t <= 1.0 for t in h.val_t_asr)
        assert all(np.isfinite(v) for v in h.val_probe_pose)
        assert run._val_env.control == "joint"
        assert (tmp_path / "checkpoint" / "texture.npy").is_file()
    finally:
        run.close()


def test_a_joint_policy_attacks_outputs_are_written_its_rollout_strip_moves_the_arms_joints(tmp_path, spec, pool):
    """write_outputs' figures (Grad-CAM before/after, the rollout strip) ran the joint policy without
    its joint state and stepped the joint env with TCP motions: an experiment's attack job failed at
    its end (state: ... no joint positions given)."""
    from attack.outputs import write_outputs

    cfg = resolve_config("ci", {**CFG, "validation_every": 0})
    run = AttackRun(joint_policy(spec), spec, cfg, pool=pool, out_dir=tmp_path / "ckpt")
    try:
        before = run.state.texture.detach().clone()
        run_attack(run, progress=False)
        run.env.reset_envs([0], configs=[run.pool[0]])
        q_start = run.env.q[0].copy()
        metrics = write_outputs(run, tmp_path / "out", before)
        for name in ("gradcam_before_after.png", "rollout_strip.png", "texture.png", "metrics.json"):
            assert (tmp_path / "out" / name).is_file(), name
        assert np.isfinite(metrics["final_loss_pose"])
        # the strip executed the policy's joint targets: the arm's joints moved from the first configuration's start
        assert not np.allclose(run.env.q[0], q_start)
    finally:
        run.close()


def test_a_joint_policy_on_recordings_is_refused_in_one_line(spec):
    with pytest.raises(
        AttackError, match=r"^recordings: a joint-space policy .* is attacked in the simulator only"
    ) as err:
        AttackRun(joint_policy(spec), spec, resolve_config("ci", {**CFG, "recordings": "anywhere"}))
    assert "\n" not in str(err.value)
