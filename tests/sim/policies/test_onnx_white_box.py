"""An .onnx file attacked white-box: onnx2torch's conversion, checked against onnxruntime, cut for Grad-CAM.

Real files: each is exported here by torch.onnx from a tiny policy of the zoo (or built node by node
with onnx.helper) and run by the real onnxruntime; nothing is downloaded.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch
from onnx import helper, numpy_helper

from attack.optimize import AttackRun, resolve_config
from sim.configs import sample_pool
from sim.policies.checkpoint import load_policy
from sim.policies.graph_policy import CHECK_FRAMES, GraphPolicy, reference_frames
from sim.policies.interface import PolicyError, prepare_images
from sim.policies.onnx_policy import OnnxPolicy, export_onnx
from sim.policies.onnx_torch import ATOL, convert_onnx, onnx2torch_module
from sim.policies.pt2 import export_pt2
from sim.spec import default_scene
from tests.policy_files import linear_head, mismatched_onnx, onnx_graph, unsupported_op_onnx
from tests.policy_zoo import card_of, contract_of, tiny_policy

CONTRACTS = {
    "image-delta": contract_of((), ("delta_tcp", 1, 1)),
    "state-absolute-K3": contract_of(("tcp_pose", "gripper"), ("absolute_tcp", 3, 3)),
}


@pytest.fixture(scope="module", params=sorted(CONTRACTS))
def exported(request, tmp_path_factory):
    """(native policy, its .onnx converted white-box, the OnnxPolicy) for one contract."""
    d = tmp_path_factory.mktemp("onnx")
    p = tiny_policy(CONTRACTS[request.param])
    path = export_onnx(p, d / "p.onnx", card_of(p))
    return p, load_policy(path, white_box=True), OnnxPolicy(path)


def test_converted_outputs_match_onnxruntime_on_rendered_frames(exported):
    p, g, o = exported
    assert isinstance(g, GraphPolicy) and g.white_box and g.format == "onnx"
    assert g.check["frames"] >= CHECK_FRAMES and g.check["max_abs_diff"] <= ATOL
    images, state = reference_frames(g.image_size, g.contract)
    assert images.std() > 10  # rendered scenes, not blank frames
    np.testing.assert_allclose(g.act(images, state), o.act(images, state), atol=ATOL, rtol=1e-4)
    np.testing.assert_allclose(g.act(images, state), p.act(images, state), atol=ATOL, rtol=1e-4)


def test_the_card_cuts_the_graph_where_the_checkpoint_does(exported):
    p, g, _ = exported
    assert g.card.feature_map and "backbone" in g.card.feature_map
    x = torch.rand(3, 3, g.image_size, g.image_size)
    torch.testing.assert_close(g.features(x), p.features(x), atol=1e-5, rtol=1e-5)
    A = p.features(x)
    st = torch.rand(3, p.contract.state_dim) if p.contract.state_dim else None
    torch.testing.assert_close(g.head(A, st), p.head(A, st), atol=1e-5, rtol=1e-5)


def _iteration_grads(run) -> dict:
    """Each objective term's texture gradient summed over one iteration's frames (as attack_step)."""
    st = run.state
    run.source.start(st.iteration, st.rng)
    total: dict = {}
    while (frames := run.source.next()) is not None:
        out = run.frame_gradients(st, frames)
        for k, g in out["grads"].items():
            total[k] = total.get(k, 0) + g
        run.source.advance(out["actions"].cpu().numpy())
    return total


def test_texture_gradients_agree_between_onnx_pt2_and_the_native_module(tmp_path):
    """The attack's texture gradients (pose and saliency terms) through the three paths."""
    p = tiny_policy(CONTRACTS["state-absolute-K3"])
    onnx_path = export_onnx(p, tmp_path / "p.onnx", card_of(p))
    pt2_path = export_pt2(p, tmp_path / "p.pt2", card_of(p))
    spec = default_scene()
    pool = sample_pool(spec, 8, seed=5, part="attack")
    cfg = resolve_config("quick", {"num_envs": 4, "rollout_steps": 1, "texture_size": 16, "validation_every": 0})
    grads = {}
    for name, policy in (("native", p), ("onnx", OnnxPolicy(onnx_path)), ("pt2", load_policy(pt2_path))):
        run = AttackRun(policy, spec, cfg, pool=pool)
        try:
            if name == "onnx":  # the run converted the file itself, checked on this scene's frames
                assert isinstance(run.policy, GraphPolicy) and run.policy.check["max_abs_diff"] <= ATOL
            grads[name] = _iteration_grads(run)
        finally:
            run.close()
    ref = grads["native"]
    assert set(ref) == {"pose", "saliency"}
    for term, g in ref.items():
        assert torch.isfinite(g).all() and float(g.abs().max()) > 0, term
        scale = float(g.abs().max())
        for name in ("onnx", "pt2"):
            other = grads[name][term]
            assert torch.isfinite(other).all()
            diff = float((other - g).abs().max())
            assert diff <= 1e-3 * scale, f"{term}: {name} differs by {diff:.3g} (scale {scale:.3g})"


def test_an_operator_onnx2torch_lacks_is_refused_by_name_and_the_file_still_runs_black_box(tmp_path):
    path = unsupported_op_onnx(tmp_path / "shrink.onnx")
    with pytest.raises(PolicyError) as err:
        load_policy(path, white_box=True)
    msg = str(err.value)
    assert "'Shrink'" in msg and str(path) in msg and "\n" not in msg and "black-box" in msg
    o = load_policy(path)  # onnxruntime runs it: evaluation is unaffected
    assert isinstance(o, OnnxPolicy) and o.act(np.zeros((2, 32, 32, 3), np.uint8)).shape == (2, 6)


def test_a_conversion_that_differs_from_onnxruntime_is_refused_naming_the_output_and_the_difference(tmp_path):
    path = mismatched_onnx(tmp_path / "resize.onnx")
    with pytest.raises(PolicyError) as err:
        load_policy(path, white_box=True)
    msg = str(err.value)
    assert "output 'actions'" in msg and "differs from onnxruntime by up to" in msg and "\n" not in msg
    diff = float(msg.split("by up to ")[1].split()[0])
    assert diff > 0.01


def test_a_tampered_conversion_is_refused(tmp_path, monkeypatch):
    """The check compares what the attack will run: a weight changed after conversion is caught."""
    p = tiny_policy(CONTRACTS["image-delta"])
    path = export_onnx(p, tmp_path / "p.onnx", card_of(p))
    o2t = onnx2torch_module()
    convert = o2t.convert

    def tampered(*args, **kwargs):
        gm = convert(*args, **kwargs)
        with torch.no_grad():
            next(w for w in gm.parameters() if w.ndim == 4).mul_(1.05)  # the first convolution's weights, 5% off
        return gm

    monkeypatch.setattr(o2t, "convert", tampered)
    with pytest.raises(PolicyError, match="differs from onnxruntime by up to"):
        convert_onnx(OnnxPolicy(path))


def test_without_a_card_the_last_spatial_map_on_every_path_is_the_feature_map(tmp_path):
    """A user's file with no card: Grad-CAM reads the last 4-D map through which everything passes."""
    w = np.random.default_rng(1).standard_normal((8, 3, 3, 3)).astype(np.float32) * 0.2
    nodes = [
        helper.make_node("Conv", ["images", "k"], ["c1"], pads=[1, 1, 1, 1], strides=[2, 2]),
        helper.make_node("Relu", ["c1"], ["r1"]),
        helper.make_node("GlobalAveragePool", ["r1"], ["pooled"]),  # (B, 8, 1, 1): one cell, not a map
    ]
    head, inits = linear_head("pooled", 8)
    path = onnx_graph(tmp_path / "user.onnx", nodes + head, inits + [numpy_helper.from_array(w, "k")])
    g = load_policy(path, white_box=True)
    assert g.feature_map == "r1" and g.features(torch.rand(2, 3, 32, 32)).shape == (2, 8, 16, 16)


def test_a_card_feature_map_that_is_not_in_the_graph_is_one_line(tmp_path):
    from sim.policies.onnx_policy import attach_card

    p = tiny_policy(CONTRACTS["image-delta"])
    path = export_onnx(p, tmp_path / "p.onnx", card_of(p))
    attach_card(path, card_of(p).model_copy(update={"feature_map": "no/such/tensor"}))
    with pytest.raises(PolicyError, match="feature_map: 'no/such/tensor' is not a tensor") as err:
        load_policy(path, white_box=True)
    assert "\n" not in str(err.value)


def test_onnx2torch_is_imported_without_leaving_a_stand_in_for_torchvision():
    o2t = onnx2torch_module()
    if o2t.torchvision_stubbed:
        assert "torchvision" not in sys.modules and "torchvision.ops" not in sys.modules


def test_the_check_frames_are_the_scene_at_the_policy_size_with_its_state():
    c = CONTRACTS["state-absolute-K3"]
    images, state = reference_frames(32, c)
    assert images.shape == (CHECK_FRAMES, 32, 32, 3) and images.dtype == np.uint8
    assert state.shape == (CHECK_FRAMES, 7) and np.isfinite(state).all()
    x = prepare_images(images, 32)
    assert len({x[i].tobytes() for i in range(len(x))}) > CHECK_FRAMES // 2  # distinct views
