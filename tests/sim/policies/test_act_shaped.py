"""An ACT-shaped policy white-box through .onnx and .pt2: a transformer over two cameras' feature maps and the state.

tests.policy_zoo.TinyACT (LeRobot's ACT in miniature: a conv backbone per camera, a 1x1 projection,
tokens with position embeddings, an encoder, a decoder of K queries, a chunk of K = 4 actions) is
exported here with LeRobot's names by torch.onnx (the TorchScript exporter writes attention as
MatMul / Softmax / Transpose / LayerNormalization, all of which onnx2torch converts) and by
torch.export; each file is loaded white-box, checked against onnxruntime, and attacked for one
iteration on scenes/two-cameras.yaml. Nothing is downloaded.
"""

from __future__ import annotations

import collections

import numpy as np
import onnx
import pytest
import torch
from onnx import TensorProto, helper, numpy_helper

from attack.optimize import AttackRun, resolve_config
from sim.configs import sample_pool
from sim.policies.checkpoint import load_policy
from sim.policies.contract import call_policy
from sim.policies.graph_policy import GraphPolicy, reference_frames
from sim.policies.interface import PolicyError
from sim.policies.onnx_policy import OnnxPolicy
from sim.policies.onnx_torch import ATOL, RTOL, unsupported_operators
from sim.spec import load_spec
from tests.policy_files import two_camera_onnx, two_camera_pt2
from tests.policy_zoo import TinyACT, two_camera_card

TWO_CAMERAS = "scenes/two-cameras.yaml"
K = 4


@pytest.fixture(scope="module")
def act_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("act")
    p = TinyACT(chunk=K).eval()
    card = two_camera_card(chunk=K)
    return p, two_camera_onnx(d / "act.onnx", p, card), two_camera_pt2(d / "act.pt2", p, card)


@pytest.fixture(scope="module")
def spec():
    return load_spec(TWO_CAMERAS)


def test_the_exported_attention_is_operators_onnx2torch_converts(act_files):
    _, onnx_path, _ = act_files
    model = onnx.load(str(onnx_path))
    ops = collections.Counter(n.op_type for n in model.graph.node)
    assert {"MatMul", "Softmax", "LayerNormalization"} <= set(ops) and ops["Conv"] >= 4
    assert unsupported_operators(model) == []


def test_both_files_load_white_box_and_match_onnxruntime_on_rendered_frames_of_both_cameras(act_files, spec):
    p, onnx_path, pt2_path = act_files
    ref = OnnxPolicy(onnx_path)
    g_onnx = load_policy(onnx_path, white_box=True, spec=spec)
    g_pt2 = load_policy(pt2_path, spec=spec)
    assert g_onnx.check["max_abs_diff"] <= ATOL and g_onnx.check["frames"] >= 32
    images, state = reference_frames(32, ref.contract, spec, cameras=("wrist", "front"))
    want = call_policy(ref, images, state)
    assert want.shape == (32, K, 6) and np.abs(want).max() > 0.01
    for g in (g_onnx, g_pt2):
        assert isinstance(g, GraphPolicy) and g.cameras == ("wrist", "front")
        got = call_policy(g, images, state)
        np.testing.assert_allclose(got, want, atol=ATOL, rtol=RTOL)
    x = {k: torch.from_numpy(v).permute(0, 3, 1, 2).float() / 255.0 for k, v in images.items()}
    with torch.no_grad():
        np.testing.assert_allclose(p(x["wrist"], x["front"], torch.from_numpy(state)).numpy(), want, atol=ATOL)


def test_each_camera_is_cut_at_its_projected_feature_map(act_files, spec):
    _, onnx_path, pt2_path = act_files
    for g in (load_policy(onnx_path, white_box=True, spec=spec), load_policy(pt2_path)):
        A = g.features({"wrist": torch.rand(2, 3, 32, 32), "front": torch.rand(2, 3, 128, 128)})
        assert tuple(A["wrist"].shape) == (2, 16, 8, 8) and tuple(A["front"].shape) == (2, 16, 8, 8)


def _iteration_grads(run) -> dict:
    st = run.state
    run.source.start(st.iteration, st.rng)
    total: dict = {}
    while (frames := run.source.next()) is not None:
        out = run.frame_gradients(st, frames)
        for k, g in out["grads"].items():
            total[k] = total.get(k, 0) + g
        run.source.advance(out["actions"].cpu().numpy())
    return total


def test_texture_gradients_are_finite_and_agree_between_the_onnx_and_pt2_paths(act_files, spec):
    _, onnx_path, pt2_path = act_files
    pool = sample_pool(spec, 8, seed=5, part="attack")
    cfg = resolve_config("quick", {"num_envs": 4, "rollout_steps": 1, "texture_size": 16, "validation_every": 0})
    grads = {}
    for name, policy in (("onnx", OnnxPolicy(onnx_path)), ("pt2", load_policy(pt2_path))):
        run = AttackRun(policy, spec, cfg, pool=pool)
        try:
            grads[name] = _iteration_grads(run)
        finally:
            run.close()
    assert set(grads["onnx"]) == {"pose", "saliency"}
    assert all(float(g.abs().max()) > 0 for g in grads["onnx"].values())  # both terms reach the texture
    for term, g in grads["onnx"].items():
        other = grads["pt2"][term]
        assert torch.isfinite(g).all() and torch.isfinite(other).all(), term
        scale = float(g.abs().max())
        diff = float((other - g).abs().max())
        assert diff <= 1e-3 * max(scale, 1e-12), f"{term}: pt2 differs by {diff:.3g} (scale {scale:.3g})"


def test_an_attention_operator_onnx2torch_lacks_is_refused_by_name_and_runs_black_box(tmp_path):
    """onnxruntime's fused com.microsoft MultiHeadAttention (what its transformer optimiser writes
    into an ACT export) has no onnx2torch converter: one line naming it; black-box still works."""
    S, D = 32, 8  # 32 px images -> 4 x 4 patches of 8 x 8 x 3 -> 16 tokens of 8 channels
    image = helper.make_tensor_value_info("observation.images.wrist", TensorProto.FLOAT, ["B", 3, S, S])
    action = helper.make_tensor_value_info("action", TensorProto.FLOAT, ["B", 6])
    rng = np.random.default_rng(0)
    nodes = [
        helper.make_node("Conv", ["observation.images.wrist", "wp"], ["patches"], strides=[8, 8]),
        helper.make_node("Reshape", ["patches", "tok_shape"], ["t"]),
        helper.make_node("Transpose", ["t"], ["tokens"], perm=[0, 2, 1]),
        helper.make_node(
            "MultiHeadAttention", ["tokens", "tokens", "tokens"], ["att"], domain="com.microsoft", num_heads=2
        ),
        helper.make_node("ReduceMean", ["att"], ["pooled"], axes=[1], keepdims=0),
        helper.make_node("MatMul", ["pooled", "w"], ["mm"]),
        helper.make_node("Tanh", ["mm"], ["action"]),
    ]
    inits = [
        numpy_helper.from_array((rng.standard_normal((D, 3, 8, 8)) * 0.05).astype(np.float32), "wp"),
        numpy_helper.from_array(np.array([0, D, -1], np.int64), "tok_shape"),
        numpy_helper.from_array((rng.standard_normal((D, 6)) * 0.5).astype(np.float32), "w"),
    ]
    model = helper.make_model(
        helper.make_graph(nodes, "g", [image], [action], inits),
        opset_imports=[helper.make_opsetid("", 17), helper.make_opsetid("com.microsoft", 1)],
    )
    path = tmp_path / "fused.onnx"
    onnx.save(model, str(path))
    black = OnnxPolicy(path)
    a = black.act(np.random.default_rng(1).integers(0, 256, (2, S, S, 3), dtype=np.uint8))
    assert a.shape == (2, 6) and np.isfinite(a).all()
    with pytest.raises(
        PolicyError, match=r"operator 'com.microsoft::MultiHeadAttention' .* has no torch conversion"
    ) as err:
        load_policy(path, white_box=True)
    assert "\n" not in str(err.value) and "black-box" in str(err.value)
