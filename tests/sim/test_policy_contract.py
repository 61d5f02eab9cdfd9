"""The policy contract: state input, delta and absolute actions, chunks, for torch and ONNX policies."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from sim.action import next_tcp_pose
from sim.geometry import so3_exp
from sim.policies.checkpoint import load_checkpoint, save_checkpoint
from sim.policies.contract import (
    ActionContract,
    ActionQueue,
    PolicyContract,
    decode_actions,
    policy_contract,
    state_vector,
    to_delta,
)
from sim.policies.interface import PolicyError
from sim.policies.onnx_policy import OnnxPolicy, attach_card, export_onnx
from sim.policies.rollout import EnvConfig, make_env, run_episodes
from sim.spec import default_scene
from tests.policy_zoo import COMBOS, IDS, card_of, contract_of, tiny_policy

STEP_M, STEP_RAD = 0.02, 0.1


def _pose(p, rotvec):
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.asarray(rotvec, float))
    T[:3, 3] = p
    return T


def test_contract_refuses_more_executed_actions_than_a_chunk_holds_and_repeated_state():
    with pytest.raises(ValidationError, match="cannot be executed from a chunk of 2"):
        ActionContract(chunk=2, execute=3)
    with pytest.raises(ValidationError, match="each input may appear once"):
        PolicyContract(state=("gripper", "gripper"))
    with pytest.raises(ValidationError):
        PolicyContract(state=("joint_angles",))
    with pytest.raises(ValidationError):
        PolicyContract(actions={"kind": "delta_tcp"})  # unknown key


def test_state_vector_holds_the_base_frame_tcp_pose_then_the_gripper():
    c = PolicyContract(state=("tcp_pose", "gripper"))
    T = np.stack([_pose([0.1, -0.2, 0.3], [0.0, 0.5, 0.0]), _pose([0.0, 0.0, 0.5], [3.0, 0.0, 0.0])])
    s = state_vector(c, T, 0.06)
    assert s.shape == (2, 7) and s.dtype == np.float32
    np.testing.assert_allclose(s[0], [0.1, -0.2, 0.3, 0.0, 0.5, 0.0, 0.06], atol=1e-6)
    np.testing.assert_allclose(s[1, 3:6], [3.0, 0.0, 0.0], atol=1e-6)
    assert state_vector(PolicyContract(), T, 0.06) is None
    assert state_vector(PolicyContract(state=("gripper",)), T, 0.04).tolist() == [[pytest.approx(0.04)]] * 2


def test_an_absolute_target_within_one_step_is_reached_exactly_by_the_env_semantics():
    T = _pose([0.1, 0.0, 0.4], [3.1, 0.0, 0.0])
    target = np.array([0.11, -0.005, 0.39, 3.05, 0.05, 0.0])
    a = to_delta(T[None], target[None], "absolute_tcp", STEP_M, STEP_RAD)
    assert np.abs(a).max() <= 1.0
    T_next = next_tcp_pose(T[None], a, STEP_M, STEP_RAD)[0]
    np.testing.assert_allclose(T_next[:3, 3], target[:3], atol=1e-9)
    np.testing.assert_allclose(T_next[:3, :3], so3_exp(target[3:]), atol=1e-9)


def test_a_far_absolute_target_is_approached_by_one_limited_step_in_its_direction():
    T = _pose([0.0, 0.0, 0.5], [np.pi, 0.0, 0.0])
    target = np.array([[0.3, 0.4, 0.5, np.pi, 0.0, 0.0]])
    a = to_delta(T[None], target, "absolute_tcp", STEP_M, STEP_RAD)
    assert np.abs(a).max() == pytest.approx(1.0)
    p_next = next_tcp_pose(T[None], a, STEP_M, STEP_RAD)[0, :3, 3]
    move = p_next - T[:3, 3]
    np.testing.assert_allclose(move / np.linalg.norm(move), [0.6, 0.8, 0.0], atol=1e-9)
    assert np.abs(move).max() == pytest.approx(STEP_M)


@settings(max_examples=60, deadline=None)
@given(
    p=st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3),
    r=st.lists(st.floats(-3.14, 3.14), min_size=3, max_size=3),
    q=st.lists(st.floats(-1e6, 1e6), min_size=3, max_size=3),
    s=st.lists(st.floats(-20.0, 20.0), min_size=3, max_size=3),
)
def test_absolute_conversion_is_bounded_and_finite_with_finite_gradients_at_the_extremes(p, r, q, s):
    T = _pose(p, r)[None]
    target = np.array([q + s])
    a = to_delta(T, target, "absolute_tcp", STEP_M, STEP_RAD)
    assert np.isfinite(a).all() and np.abs(a).max() <= 1.0 + 1e-12
    at = torch.tensor(target, dtype=torch.float64, requires_grad=True)
    out = to_delta(torch.tensor(T), at, "absolute_tcp", STEP_M, STEP_RAD)
    out.sum().backward()
    assert torch.isfinite(out).all() and torch.isfinite(at.grad).all()


def test_torch_and_numpy_conversions_agree_including_the_target_at_the_current_pose():
    T = np.stack([_pose([0.1, 0.0, 0.4], [3.0, 0.1, 0.0]), _pose([0.0, 0.2, 0.3], [0.0, 0.0, 0.0])])
    targets = np.array([[0.12, 0.01, 0.38, 2.9, 0.2, 0.1], [0.0, 0.2, 0.3, 0.0, 0.0, 0.0]])
    a_np = to_delta(T, targets, "absolute_tcp", STEP_M, STEP_RAD)
    a_t = to_delta(torch.tensor(T), torch.tensor(targets), "absolute_tcp", STEP_M, STEP_RAD).numpy()
    np.testing.assert_allclose(a_t, a_np, atol=1e-6)
    np.testing.assert_allclose(a_np[1], 0.0, atol=1e-6)  # already there: no motion


def test_action_queue_executes_k_of_each_chunk_then_asks_again_and_forgets_on_reset():
    q = ActionQueue(PolicyContract(action=ActionContract(chunk=4, execute=2)), 2)
    assert q.needs([0, 1]) == [0, 1]
    chunks = np.arange(2 * 4 * 6, dtype=float).reshape(2, 4, 6)
    q.push([0, 1], chunks)
    assert q.pop([0, 1]).tolist() == chunks[:, 0].tolist()
    assert q.needs([0, 1]) == []
    assert q.pop([1]).tolist() == [chunks[1, 1].tolist()]
    assert q.needs([0, 1]) == [1]
    q.clear(0)
    assert q.needs([0]) == [0]


def test_outputs_of_the_wrong_shape_for_the_contract_are_one_clear_error():
    c = PolicyContract(action=ActionContract(chunk=3, execute=1))
    assert decode_actions(np.zeros((2, 18)), c, 2).shape == (2, 3, 6)
    with pytest.raises(PolicyError, match=r"needs outputs of shape \(2, 3, 6\) or \(2, 18\), got \(2, 6\)"):
        decode_actions(np.zeros((2, 6)), c, 2)


@pytest.mark.parametrize(("state", "action"), COMBOS, ids=IDS)
def test_every_contract_survives_the_checkpoint_and_onnx_with_identical_actions(state, action, tmp_path):
    c = contract_of(state, action)
    p = tiny_policy(c)
    save_checkpoint(tmp_path / "ck", p, card_of(p))
    q, card = load_checkpoint(tmp_path / "ck")
    assert card.contract == c and policy_contract(q) == c
    onnx = OnnxPolicy(export_onnx(p, tmp_path / "p.onnx", card_of(p)))
    assert policy_contract(onnx) == c
    x = np.random.default_rng(0).integers(0, 256, (3, 32, 32, 3), dtype=np.uint8)
    s = np.random.default_rng(1).normal(size=(3, c.state_dim)).astype(np.float32) if c.state_dim else None
    a, b, o = (pol.act(x) if s is None else pol.act(x, s) for pol in (p, q, onnx))
    K = c.action.chunk
    assert a.shape == ((3, 6) if K == 1 else (3, K, 6))
    assert np.array_equal(a, b)
    np.testing.assert_allclose(o, a, atol=1e-4)


class _Counting:
    """A policy wrapper counting its calls and the rows it was asked for."""

    def __init__(self, policy):
        self.policy, self.calls = policy, 0
        self.image_size, self.contract, self.white_box = policy.image_size, policy.contract, False

    def act(self, images, state=None):
        self.calls += 1
        if self.contract.state_dim:
            assert (
                state is not None and state.shape == (len(images), self.contract.state_dim) and np.isfinite(state).all()
            )
        return self.policy.act(images) if state is None else self.policy.act(images, state)


@pytest.mark.parametrize(("state", "action"), COMBOS, ids=IDS)
def test_every_contract_rolls_out_in_the_env_asking_the_policy_once_per_executed_chunk(state, action):
    c = contract_of(state, action)
    spec = default_scene()
    spec = spec.with_updates(episode={**spec.episode.model_dump(), "max_steps": 6})
    pol = _Counting(tiny_policy(c))
    env = make_env(spec, EnvConfig(image_size=32), num_envs=1)
    try:
        res = run_episodes(env, pol, [0, 1])
    finally:
        env.close()
    k = c.action.execute
    assert res.steps.tolist() == [6, 6] or (res.reached >= 0).any()
    assert pol.calls == sum(-(-int(n) // k) for n in res.steps)


def test_an_onnx_graph_with_a_state_input_but_no_card_is_refused_naming_the_fix(tmp_path):
    import onnx

    from sim.policies.onnx_policy import CARD_METADATA_KEY

    c = contract_of(("tcp_pose",), ("delta_tcp", 1, 1))
    p = tiny_policy(c)
    path = export_onnx(p, tmp_path / "p.onnx", card_of(p))
    model = onnx.load(str(path))  # as a file exported by other code would be: no card
    keep = [(e.key, e.value) for e in model.metadata_props if e.key != CARD_METADATA_KEY]
    del model.metadata_props[:]
    for k, v in keep:
        e = model.metadata_props.add()
        e.key, e.value = k, v
    onnx.save(model, str(path))
    with pytest.raises(PolicyError, match="no card says what it holds.*attach_card"):
        OnnxPolicy(path)
    attach_card(path, card_of(p))
    assert OnnxPolicy(path).contract == c
    # a card whose contract does not fit the graph: one line, not an onnxruntime error at the first step
    other = card_of(tiny_policy(contract_of(("tcp_pose", "gripper"), ("delta_tcp", 1, 1))))
    attach_card(path, other)
    with pytest.raises(PolicyError, match=r"must be \(B, 7\)"):
        OnnxPolicy(path)


def test_an_old_card_without_a_contract_loads_as_the_original_one_image_delta_policy(tmp_path):
    import json

    p = tiny_policy(PolicyContract())
    save_checkpoint(tmp_path, p, card_of(p))
    doc = json.loads((tmp_path / "policy.json").read_text())
    doc.pop("contract")
    for k in ("state_dim", "chunk", "output"):
        doc["arch"].pop(k)
    (tmp_path / "policy.json").write_text(json.dumps(doc))
    q, card = load_checkpoint(tmp_path)
    assert card.contract == PolicyContract() and q.config == p.config


def test_a_checkpoint_card_whose_contract_does_not_fit_its_network_is_refused(tmp_path):
    import json

    p = tiny_policy(contract_of(("tcp_pose",), ("delta_tcp", 1, 1)))
    save_checkpoint(tmp_path, p, card_of(p))
    doc = json.loads((tmp_path / "policy.json").read_text())
    doc["contract"]["state"] = ["gripper"]
    (tmp_path / "policy.json").write_text(json.dumps(doc))
    with pytest.raises(PolicyError, match="arch.state_dim is 6 but the contract's state"):
        load_checkpoint(tmp_path)


def test_the_step_toward_an_absolute_target_is_the_same_in_any_frame_the_pose_and_target_share():
    """The real runner converts the arm's base-frame pose to the table frame the policy speaks; the
    TCP-frame motion toward a target is the same as toward that target mapped to the base frame."""
    T_base_table = _pose([0.4, -0.2, 0.05], [0.0, 0.0, 1.2])
    T_table_tcp = _pose([0.05, 0.1, 0.3], [3.0, 0.2, 0.0])
    target_table = np.array([0.3, 0.0, 0.1, 2.8, 0.1, 0.3])
    T_base_target = T_base_table @ _pose(target_table[:3], target_table[3:])
    from sim.geometry import so3_log

    target_base = np.concatenate([T_base_target[:3, 3], so3_log(T_base_target[:3, :3])])
    a_table = to_delta(T_table_tcp[None], target_table[None], "absolute_tcp", STEP_M, STEP_RAD)
    a_base = to_delta((T_base_table @ T_table_tcp)[None], target_base[None], "absolute_tcp", STEP_M, STEP_RAD)
    np.testing.assert_allclose(a_table, a_base, atol=1e-9)


def test_export_without_a_card_is_refused_for_a_contract_the_file_could_not_state(tmp_path):
    p = tiny_policy(contract_of((), ("delta_tcp", 4, 2)))
    with pytest.raises(PolicyError, match="needs its card in the file"):
        export_onnx(p, tmp_path / "p.onnx")
