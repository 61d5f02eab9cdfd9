"""Joint-space policies in the contract and the card: joints and units stated, checked against the
scene's URDF, joint positions as state, joint_position / joint_delta actions (alone or in chunks),
their motion through the arm's FK, and the rollout of such a policy in the joint-controlled env."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from sim.action import intended_heading, intended_position
from sim.policies.card import ActionScaling, PolicyCard, load_card
from sim.policies.checkpoint import load_policy, save_checkpoint
from sim.policies.contract import (
    ActionContract,
    ActionQueue,
    PolicyContract,
    check_joints,
    check_scene,
    decode_actions,
    from_joint_target,
    joint_mismatch,
    state_vector,
    to_delta,
    to_joint_target,
)
from sim.policies.interface import PolicyError
from sim.policies.policy import PolicyArch, VisuomotorPolicy
from sim.policies.rollout import EnvConfig, make_env, rollout, run_episodes
from sim.spec import default_scene, load_spec

PANDA_SCENE = Path(__file__).resolve().parents[2] / "scenes" / "panda-joint.yaml"
PANDA_JOINTS = tuple(f"panda_joint{k}" for k in range(1, 8))


def joint_contract(kind: str = "joint_delta", chunk: int = 1, execute: int = 1, joints=PANDA_JOINTS, units=None):
    return PolicyContract(
        state=("joint_positions",),
        action=ActionContract(kind=kind, chunk=chunk, execute=execute),
        joints=joints,
        joint_units=units if units is not None else ("rad",) * len(joints),
    )


def tiny_joint_policy(contract: PolicyContract, scale=None, seed: int = 0) -> VisuomotorPolicy:
    torch.manual_seed(seed)
    n = len(contract.joints)
    delta = contract.action.kind == "joint_delta"
    arch = PolicyArch(
        arch="small_cnn",
        image_size=32,
        head_hidden=16,
        head_channels=4,
        state_dim=contract.state_dim,
        chunk=contract.action.chunk,
        action_dim=n,
        output="tanh" if delta else "linear",
        output_scale=tuple(scale) if delta and scale is not None else (),
    )
    return VisuomotorPolicy(arch, contract=contract).eval()


@pytest.fixture(scope="module")
def panda_spec():
    return load_spec(PANDA_SCENE)


@pytest.fixture(scope="module")
def panda_arm(panda_spec):
    return panda_spec.arm.scene_arm()


# ---------------------------------------------------------------------------------- the contract
@pytest.mark.parametrize(
    "fields, match",
    [
        ({"action": {"kind": "joint_delta"}}, r"joints: a joint_delta policy names the arm's joints"),
        (
            {"state": ["joint_positions"], "action": {"kind": "delta_tcp"}},
            r"state: joint_positions is read by joint-space policies",
        ),
        ({"joints": ["a"], "joint_units": ["rad"]}, r"joints: a delta_tcp policy commands no joints"),
        (
            {"action": {"kind": "joint_position"}, "joints": ["a", "b"], "joint_units": ["rad"]},
            r"joint_units: one unit per joint: 2 joints, 1 units",
        ),
        (
            {"action": {"kind": "joint_position"}, "joints": ["a", "b"], "joint_units": ["rad", "deg"]},
            r"joint_units.1\n  Input should be 'rad' or 'm'",
        ),
        (
            {"action": {"kind": "joint_position"}, "joints": ["a", "a"], "joint_units": ["rad", "rad"]},
            r"joints: each joint may appear once",
        ),
    ],
    ids=["no-joints", "joint-state-tcp-action", "joints-on-tcp", "units-length", "unknown-unit", "repeated-joint"],
)
def test_a_joint_contract_states_its_joints_and_units_or_is_refused_naming_the_field(fields, match):
    with pytest.raises(ValidationError, match=match):
        PolicyContract(**fields)


def test_a_tcp_contract_and_network_dump_exactly_as_before_joints_existed():
    assert PolicyContract().model_dump() == {
        "state": (),
        "action": {"kind": "delta_tcp", "chunk": 1, "execute": 1},
    }
    assert "joints" not in PolicyContract(state=("tcp_pose",)).model_dump_json()
    dumped = PolicyArch().model_dump()
    assert "action_dim" not in dumped and "output_scale" not in dumped
    c = joint_contract()
    assert c.state_dim == 7 and c.action_dim == 7 and c.control == "joint" and not c.is_default
    assert PolicyContract.model_validate_json(c.model_dump_json()) == c
    assert PolicyContract().control == "tcp" and PolicyContract().action_dim == 6


def test_the_card_is_checked_against_the_scenes_urdf_in_one_line_naming_the_field(panda_spec):
    check_joints(joint_contract(), panda_spec)  # the arm's chain, in its order: fine
    check_joints(PolicyContract(), default_scene())  # a TCP contract runs anywhere
    cases = [
        (joint_contract(), default_scene(), r"contract: a joint-space policy .* needs a scene with an arm"),
        (
            joint_contract(joints=PANDA_JOINTS[::-1]),
            panda_spec,
            r"contract.joints: position 0 is 'panda_joint7' where the arm's chain .* has 'panda_joint1'",
        ),
        (
            joint_contract(joints=(*PANDA_JOINTS[:6], "panda_finger_joint1")),
            panda_spec,
            r"contract.joints: joint 'panda_finger_joint1' is not in the arm's chain panda_link0 -> panda_grasptarget",
        ),
        (
            joint_contract(joints=PANDA_JOINTS[:6]),
            panda_spec,
            r"contract.joints: 6 joints for the 7 of the arm's chain",
        ),
        (
            joint_contract(units=("rad",) * 6 + ("m",)),
            panda_spec,
            r"contract.joint_units.6: joint 'panda_joint7' is revolute in panda.urdf, so its unit is rad, not m",
        ),
    ]
    for contract, spec, match in cases:
        with pytest.raises(PolicyError, match=match) as err:
            check_joints(contract, spec, "policy.json: ")
        assert "\n" not in str(err.value) and str(err.value).startswith("policy.json: ")


_ARM_NAMES = tuple(f"j{k}" for k in range(6))


@settings(max_examples=200, deadline=None)
@given(
    picks=st.lists(st.sampled_from([*_ARM_NAMES, "gripper"]), min_size=1, max_size=8, unique=True),
    arm_units=st.lists(st.sampled_from(["rad", "m"]), min_size=6, max_size=6),
    card_units=st.lists(st.sampled_from(["rad", "m"]), min_size=8, max_size=8),
)
def test_joint_mismatch_passes_exactly_the_arms_joints_and_units_and_names_the_first_field_at_fault(
    picks, arm_units, card_units
):
    """Any joints (the arm's, in any order and number, or one it lacks) with any units: no mismatch iff
    they are the arm's chain in its order with its units; otherwise one line naming the field."""
    contract = joint_contract(joints=tuple(picks), units=tuple(card_units[: len(picks)]))
    why = joint_mismatch(contract, _ARM_NAMES, arm_units, "the arm's chain b -> t in a.urdf", "a.urdf")
    if tuple(picks) != _ARM_NAMES:
        assert why.startswith("contract.joints: ") and why.endswith(f"; the arm's joints: {', '.join(_ARM_NAMES)}")
        assert ("'gripper' is not in the arm's chain" in why) == ("gripper" in picks)
    elif tuple(card_units[:6]) != tuple(arm_units):
        k = next(i for i, (u, w) in enumerate(zip(card_units, arm_units)) if u != w)
        assert why.startswith(f"contract.joint_units.{k}: joint 'j{k}' is ") and why.endswith(
            f"in a.urdf, so its unit is {arm_units[k]}, not {card_units[k]}"
        )
    else:
        assert why is None
    assert why is None or "\n" not in why
    assert joint_mismatch(PolicyContract(), _ARM_NAMES, arm_units, "x", "y") is None  # a TCP contract: no joints


def test_state_vector_holds_the_joint_positions_in_the_contracts_order():
    c = PolicyContract(
        state=("tcp_pose", "joint_positions", "gripper"),
        action=ActionContract(kind="joint_position"),
        joints=("a", "b"),
        joint_units=("rad", "m"),
    )
    T = np.repeat(np.eye(4)[None], 3, 0)
    q = np.arange(6.0).reshape(3, 2)
    s = state_vector(c, T, 0.05, q)
    assert s.shape == (3, 9) and c.state_dim == 9
    np.testing.assert_array_equal(s[:, 6:8], q.astype(np.float32))
    np.testing.assert_allclose(s[:, 8], 0.05)
    with pytest.raises(PolicyError, match="no joint positions given"):
        state_vector(c, T, 0.05)
    with pytest.raises(PolicyError, match=r"joint_positions must be \(3, 2\)"):
        state_vector(c, T, 0.05, q[:, :1])


def test_joint_actions_decode_alone_or_in_chunks_and_queue_k_of_k():
    c = joint_contract(kind="joint_position", chunk=3, execute=2)
    raw = np.arange(2 * 3 * 7, dtype=float).reshape(2, 21)
    chunks = decode_actions(raw, c, 2)
    assert chunks.shape == (2, 3, 7)
    assert decode_actions(chunks, c, 2) is chunks
    with pytest.raises(PolicyError, match=r"needs outputs of shape \(2, 3, 7\) or \(2, 21\), got \(2, 6\)"):
        decode_actions(np.zeros((2, 6)), c, 2)
    q = ActionQueue(c, 2)
    q.push([0, 1], chunks)
    np.testing.assert_array_equal(q.pop([0, 1]), chunks[:, 0])
    assert q.pop([]).shape == (0, 7)


@settings(max_examples=100, deadline=None)
@given(
    q=st.lists(st.floats(-4, 4), min_size=7, max_size=7),
    a=st.lists(st.floats(-1e3, 1e3), min_size=7, max_size=7),
    kind=st.sampled_from(["joint_position", "joint_delta"]),
)
def test_a_joint_action_and_its_target_convert_both_ways(q, a, kind):
    q, a = np.array([q]), np.array([a])
    target = to_joint_target(q, a, kind)
    np.testing.assert_allclose(from_joint_target(q, target, kind), a, atol=1e-9, rtol=1e-12)
    qt, at = torch.from_numpy(q), torch.from_numpy(a)
    np.testing.assert_array_equal(to_joint_target(qt, at, kind).numpy(), target)


def test_the_motion_of_a_joint_action_is_the_fk_pose_of_its_limited_step(panda_arm):
    g = torch.Generator().manual_seed(0)
    lo, hi = panda_arm.model.limits.q_min, panda_arm.model.limits.q_max
    q = lo + (0.2 + 0.6 * torch.rand(16, 7, generator=g, dtype=torch.float64)) * (hi - lo)
    a = (torch.rand(16, 7, generator=g, dtype=torch.float64) - 0.5) * 2.0  # some beyond one step
    T = panda_arm.tcp_pose(q)
    for kind, act in (("joint_delta", a), ("joint_position", q + a)):
        d = to_delta(T, act, kind, 0.02, 0.1, q=q, arm=panda_arm)
        T_next = panda_arm.tcp_pose(panda_arm.limit_step(q, q + a))
        torch.testing.assert_close(intended_position(T, d, 0.02), T_next[:, :3, 3], atol=1e-12, rtol=0)
        torch.testing.assert_close(intended_heading(T, d, 0.1), T_next[:, :3, 2], atol=1e-9, rtol=0)
        d_np = to_delta(T.numpy(), act.numpy(), kind, 0.02, 0.1, q=q.numpy(), arm=panda_arm)
        np.testing.assert_allclose(d_np, d.numpy(), atol=1e-12)
    assert (d.abs() > 1).any()  # a joint step is bounded by the velocity limits, not the TCP step limits
    with pytest.raises(PolicyError, match="needs the joint positions and the scene's arm"):
        to_delta(T, a, "joint_delta", 0.02, 0.1)


def test_the_joint_motion_is_differentiable_through_the_fk(panda_arm):
    lo, hi = panda_arm.model.limits.q_min, panda_arm.model.limits.q_max
    q = (lo + hi)[None] / 2 + 0.1
    T = panda_arm.tcp_pose(q)
    a = torch.full((1, 7), 0.03, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: to_delta(T, x, "joint_delta", 0.02, 0.1, q=q, arm=panda_arm), (a,))
    d = to_delta(T.float(), a.float(), "joint_delta", 0.02, 0.1, q=q, arm=panda_arm)  # float32, as the attack runs
    (g,) = torch.autograd.grad(d[:, :3].sum(), a)
    assert torch.isfinite(g).all() and g.abs().sum() > 0


# ---------------------------------------------------------------------------------- the network and card
def test_a_joint_delta_network_is_bounded_by_each_joints_step(panda_arm):
    step = (panda_arm.model.limits.qd_max * panda_arm.control_period_s).tolist()
    p = tiny_joint_policy(joint_contract(), scale=step)
    with torch.no_grad():
        p.mlp[-1].bias.fill_(50.0)  # saturate the tanh
    out = p.act(np.zeros((2, 32, 32, 3), np.uint8), np.zeros((2, 7), np.float32))
    assert out.shape == (2, 7)
    np.testing.assert_allclose(out, np.array([step] * 2, np.float32), rtol=1e-6)
    chunked = tiny_joint_policy(joint_contract(kind="joint_position", chunk=4, execute=2))
    assert chunked.act(np.zeros((1, 32, 32, 3), np.uint8), np.zeros((1, 7), np.float32)).shape == (1, 4, 7)
    with pytest.raises(PolicyError, match=r"arch.action_dim is 6 but joint_delta actions have 7 values"):
        VisuomotorPolicy(PolicyArch(arch="small_cnn", image_size=32, state_dim=7), contract=joint_contract())
    with pytest.raises(ValidationError, match="output_scale: one bound per action value"):
        PolicyArch(action_dim=7, output_scale=(0.1,))


def test_a_joint_card_survives_the_checkpoint_and_a_wrong_one_is_refused_in_one_line(tmp_path, panda_spec):
    p = tiny_joint_policy(joint_contract(), scale=[0.2] * 7)
    card = PolicyCard(arch=p.config, contract=p.contract, action=ActionScaling(max_step_m=0.02, max_step_rad=0.1))
    save_checkpoint(tmp_path / "ok", p, card)
    back = load_policy(tmp_path / "ok", spec=panda_spec)
    assert back.contract == p.contract and back.config.output_scale == (0.2,) * 7
    x, s = np.zeros((2, 32, 32, 3), np.uint8), np.ones((2, 7), np.float32)
    np.testing.assert_array_equal(back.act(x, s), p.act(x, s))
    with pytest.raises(PolicyError, match="needs a scene with an arm"):
        load_policy(tmp_path / "ok", spec=default_scene())

    # the joint order on disk differs from the URDF's: refused naming contract.joints
    doc = json.loads((tmp_path / "ok" / "policy.json").read_text())
    doc["contract"]["joints"] = list(PANDA_JOINTS[1:] + PANDA_JOINTS[:1])
    (tmp_path / "ok" / "policy.json").write_text(json.dumps(doc))
    with pytest.raises(PolicyError, match=r"contract.joints: position 0 is 'panda_joint2'") as err:
        load_policy(tmp_path / "ok", spec=panda_spec)
    assert "\n" not in str(err.value)
    # an unknown unit: refused when the card is read, naming the field
    doc["contract"]["joint_units"][3] = "deg"
    (tmp_path / "ok" / "policy.json").write_text(json.dumps(doc))
    with pytest.raises(PolicyError, match=r"contract.joint_units.3: Input should be 'rad' or 'm'") as err:
        load_card(tmp_path / "ok")
    assert "\n" not in str(err.value)


# ---------------------------------------------------------------------------------- the rollout
def test_a_joint_policy_rolls_out_reading_the_arms_joints_and_moving_within_its_limits(panda_spec, panda_arm):
    step = (panda_arm.model.limits.qd_max * panda_arm.control_period_s).tolist()
    policy = tiny_joint_policy(joint_contract(), scale=step, seed=1)
    env = make_env(panda_spec, EnvConfig(image_size=32), 2, control="joint")
    seen, ends = [], []
    lo, hi = panda_arm.model.limits.q_min.numpy(), panda_arm.model.limits.q_max.numpy()

    def query(slots, state):
        q = env.q[slots]
        seen.append(np.abs(state - q).max())  # the state the policy reads is the env's joints
        assert (q >= lo).all() and (q <= hi).all()
        T_fk = panda_arm.tcp_pose(torch.from_numpy(q)).numpy()
        np.testing.assert_allclose(env.T_world_tcp[slots], T_fk, atol=1e-12)  # the TCP follows FK
        return policy.act(env.observe()[slots], state)

    try:
        rollout(env, [0, 1, 2, 3], policy, lambda j, i, r: ends.append(r["steps"]), query=query)
    finally:
        env.close()
    assert len(ends) == 4 and max(seen) < 1e-6


def test_a_policy_and_an_env_of_other_controls_are_refused_naming_the_fix(panda_spec):
    joint = tiny_joint_policy(joint_contract(), scale=[0.2] * 7)
    env = make_env(panda_spec, EnvConfig(image_size=32), 1)
    try:
        with pytest.raises(PolicyError, match=r"moves the joints but the env is made with control='tcp'"):
            run_episodes(env, joint, [0])
    finally:
        env.close()
    check_scene(joint, panda_spec)
    with pytest.raises(PolicyError, match="needs a scene with an arm"):
        check_scene(joint, default_scene())
