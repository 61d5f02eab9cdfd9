"""LeRobot's own ACT (lerobot 0.4.4, random weights) exported to ONNX, white-box through advobj's ONNX path.

The fixture ``tests/data/lerobot_act/`` (``act.onnx``, ``provenance.json``, lerobot's ``LICENSE``) was
written by ``tools/make_lerobot_fixture.py`` in a separate environment that has lerobot: its
``ACTPolicy.predict_action_chunk`` (a ResNet-18 per camera, a transformer encoder and decoder, a chunk
of 10 actions) under LeRobot's input names. The ResNet-18's convolution weights are stored shape-only
and refilled here from the seed (``refill_onnx`` checks their digest), so the refilled graph holds the
tensors LeRobot's module was exported with; the provenance holds that module's own output, which
onnxruntime must reproduce. The card binds LeRobot's names to the wrist and front cameras of
``scenes/two-cameras.yaml`` with LeRobot's image normalisation. Nothing is downloaded.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from attack.optimize import AttackRun, resolve_config
from sim.configs import sample_pool
from sim.env import ReachEnv
from sim.policies.card import ActionScaling, PolicyCard
from sim.policies.checkpoint import load_policy
from sim.policies.contract import ActionContract, ImageInput, InputBinding, PolicyContract, call_policy
from sim.policies.graph_policy import CHECK_FRAMES, GraphPolicy, reference_frames
from sim.policies.interface import PolicyError
from sim.policies.onnx_policy import OnnxPolicy, attach_card
from sim.policies.onnx_torch import ATOL, RTOL, onnx2torch_module
from sim.policies.rollout import rollout
from sim.spec import load_spec
from tools.make_lerobot_fixture import (
    MIN_STRIPPED,
    SIZE_BUDGET_BYTES,
    reference_inputs,
    refill_onnx,
    refill_values,
    stripped_initializers,
)

FIXTURE = Path(__file__).resolve().parents[1] / "data" / "lerobot_act"
TWO_CAMERAS = "scenes/two-cameras.yaml"
WRIST, FRONT, STATE = "observation.images.wrist", "observation.images.front", "observation.state"


@pytest.fixture(scope="module")
def provenance() -> dict:
    return json.loads((FIXTURE / "provenance.json").read_text())


@pytest.fixture(scope="module")
def spec():
    return load_spec(TWO_CAMERAS)


def lerobot_card(provenance: dict) -> PolicyCard:
    """LeRobot's names bound to the scene's wrist and front cameras, each normalised as LeRobot's
    processor does (its image statistics, from the provenance); the state is the TCP pose."""
    cfg, proc = provenance["config"], provenance["processor"]
    size = tuple(cfg["input_features"][WRIST]["shape"][1:])
    image = ImageInput(size=size, mean=tuple(proc["image_mean"]), std=tuple(proc["image_std"]))
    chunk = int(cfg["chunk_size"])
    return PolicyCard(
        contract=PolicyContract(
            state=("tcp_pose",), action=ActionContract(kind="delta_tcp", chunk=chunk, execute=cfg["n_action_steps"])
        ),
        action=ActionScaling(max_step_m=0.02, max_step_rad=0.1),
        inputs={
            WRIST: InputBinding(source="camera", camera="wrist", image=image),
            FRONT: InputBinding(source="camera", camera="front", image=image),
            STATE: InputBinding(source="state"),
        },
        training={"method": "none: lerobot ACTPolicy with random weights (tests/data/lerobot_act/provenance.json)"},
    )


@pytest.fixture(scope="module")
def act_file(tmp_path_factory, provenance) -> Path:
    """The fixture's graph with its stripped weights refilled and the card in its metadata."""
    out = tmp_path_factory.mktemp("lerobot") / "act.onnx"
    refill_onnx(FIXTURE / "act.onnx", out, provenance["seed"], provenance["stripping"]["refilled_weights_sha256"])
    return attach_card(out, lerobot_card(provenance))


@pytest.fixture(scope="module")
def white_box(act_file, spec) -> GraphPolicy:
    return load_policy(act_file, white_box=True, spec=spec)


# ----------------------------------------------------------------------------- the fixture itself
def test_the_committed_graph_is_small_shape_only_where_stripped_and_the_one_the_provenance_names(provenance):
    data = (FIXTURE / "act.onnx").read_bytes()
    assert len(data) < SIZE_BUDGET_BYTES
    assert hashlib.sha256(data).hexdigest() == provenance["sha256"]["committed_onnx"]
    assert provenance["versions"]["lerobot"] == "0.4.4" and provenance["lerobot_license"] == "Apache-2.0"
    assert (FIXTURE / "LICENSE").read_text().lstrip().splitlines()[2].strip() == "Apache License"
    model = onnx.load(str(FIXTURE / "act.onnx"), load_external_data=False)
    assert [i.name for i in model.graph.input] == [WRIST, FRONT, STATE]
    assert [o.name for o in model.graph.output] == ["action"]
    convs = {n.input[1] for n in model.graph.node if n.op_type == "Conv"}
    stripped = stripped_initializers(model)
    assert len(stripped) == provenance["stripping"]["tensors"] and {t.name for t in stripped} <= convs
    assert sum(int(np.prod(t.dims)) for t in stripped) == provenance["stripping"]["values"]
    assert all(not t.raw_data and len(t.dims) == 4 for t in stripped)
    kept = [t for t in model.graph.initializer if t.data_location != onnx.TensorProto.EXTERNAL]
    assert all(int(np.prod(t.dims)) < MIN_STRIPPED for t in kept if t.data_type == onnx.TensorProto.FLOAT)


def test_the_committed_graph_without_its_weights_is_refused_in_one_line():
    with pytest.raises(PolicyError, match=r"act\.onnx: not a loadable ONNX model") as err:
        OnnxPolicy(FIXTURE / "act.onnx")
    assert "\n" not in str(err.value)


def test_refilling_with_another_seed_is_refused_by_the_recorded_digest(provenance, tmp_path):
    digest = provenance["stripping"]["refilled_weights_sha256"]
    with pytest.raises(ValueError, match="digest"):
        refill_onnx(FIXTURE / "act.onnx", tmp_path / "other.onnx", provenance["seed"] + 1, digest)
    assert not (tmp_path / "other.onnx").exists()


@settings(max_examples=40, deadline=None)
@given(
    o=st.integers(1, 8),
    i=st.integers(1, 600),
    k=st.sampled_from([1, 3, 7]),
    seed=st.integers(0, 2**63 - 1),
)
def test_refill_values_are_he_uniform_float32_and_depend_only_on_name_shape_and_seed(o, i, k, seed):
    a = refill_values("model.backbone.conv1.weight", (o, i, k, k), seed)
    assert a.dtype == np.float32 and a.shape == (o, i, k, k) and np.isfinite(a).all()
    assert np.abs(a).max() <= np.sqrt(6.0 / (i * k * k))
    np.testing.assert_array_equal(a, refill_values("model.backbone.conv1.weight", (o, i, k, k), seed))
    if a.size > 4:
        assert not np.array_equal(a, refill_values("model.backbone.conv2.weight", (o, i, k, k), seed))


def test_refill_values_refuse_a_shape_that_is_no_convolution_weight():
    for shape in [(16, 16), (4, 0, 3, 3), (2, 3, 3, 3, 1)]:
        with pytest.raises(ValueError, match="convolution"):
            refill_values("w", shape, 0)


# ----------------------------------------------------------------------------- LeRobot's computation
def test_the_refilled_graph_reproduces_lerobots_own_output(act_file, provenance):
    ref, proc = provenance["reference"], provenance["processor"]
    feeds = reference_inputs(
        ref["seed"], ref["image_px"], ref["state_dim"], proc["image_mean"], proc["image_std"], ref["batch"]
    )
    got = OnnxPolicy(act_file).session.run(["action"], feeds)[0]
    want = np.asarray(ref["action"])
    assert got.shape == (ref["batch"], provenance["config"]["chunk_size"], 6) and np.abs(want).max() > 0.1
    np.testing.assert_allclose(got, want, atol=ATOL, rtol=RTOL)


# ----------------------------------------------------------------------------- white-box through advobj
def test_what_onnx2torch_converts_wrongly_in_lerobots_export_is_converted_right(act_file, white_box, provenance):
    """torch.onnx leaves CumSum's default reverse=0 out (ACT's 2-D position embedding) and onnx2torch
    1.5.15 reads it as 1; ACT's decoder input is a ConstantOfShape of the batch size, whose shape only
    data propagation infers, so onnx2torch would size the decoder's LayerNorms from an unknown axis;
    the batch size is read off the wrist image, which is no data path around the feature map."""
    model = onnx.load(str(act_file))
    cumsums = [n for n in model.graph.node if n.op_type == "CumSum"]
    assert cumsums and not any(a.name == "reverse" for n in cumsums for a in n.attribute)
    onnx2torch_module()  # imports onnx2torch as advobj does (without torchvision)
    from onnx2torch.node_converters.cumsum import OnnxCumSum  # lazy: optional dependency (onnx2torch)

    modules = list(white_box.modules())
    assert any(isinstance(m, OnnxCumSum) for m in modules)
    assert not any(m.reverse for m in modules if isinstance(m, OnnxCumSum))
    norms = [m for m in modules if isinstance(m, torch.nn.LayerNorm)]
    assert len(norms) >= 6 and all(m.normalized_shape == (provenance["config"]["dim_model"],) for m in norms)
    # the wrist image's batch size (ACT's latent, its decoder's queries) reaches the head as a size, not as data
    assert any("sym_size" in str(n.target) for n in white_box.head_graph.graph.nodes)


def test_the_conversion_matches_onnxruntime_on_rendered_frames_of_both_cameras(act_file, white_box, spec, provenance):
    assert white_box.cameras == ("wrist", "front") and white_box.format == "onnx"
    assert white_box.check["frames"] >= CHECK_FRAMES and white_box.check["max_abs_diff"] <= ATOL
    black = OnnxPolicy(act_file)
    images, state = reference_frames(white_box.image_size, black.contract, spec, cameras=("wrist", "front"))
    assert images["front"].std() > 10 and images["wrist"].std() > 10  # rendered scenes, not blank frames
    want = call_policy(black, images, state)
    assert want.shape == (CHECK_FRAMES, provenance["config"]["chunk_size"], 6) and want.std() > 0.01
    np.testing.assert_allclose(call_policy(white_box, images, state), want, atol=ATOL, rtol=RTOL)


def test_each_camera_is_cut_at_acts_projection_of_its_resnet_map(white_box, provenance):
    assert white_box.feature_map == {
        "wrist": "/model/encoder_img_feat_input_proj/Conv_output_0",
        "front": "/model/encoder_img_feat_input_proj_1/Conv_output_0",
    }
    S, d = white_box.image_size, provenance["config"]["dim_model"]
    A = white_box.features({"wrist": torch.rand(2, 3, S, S), "front": torch.rand(2, 3, S, S)})
    cells = S // 32  # ResNet-18's stride
    assert {k: tuple(v.shape) for k, v in A.items()} == {"wrist": (2, d, cells, cells), "front": (2, d, cells, cells)}


def test_texture_gradients_through_the_converted_module_are_finite_and_non_zero(white_box, spec):
    pool = sample_pool(spec, 8, seed=5, part="attack")
    cfg = resolve_config("quick", {"num_envs": 4, "rollout_steps": 1, "texture_size": 16, "validation_every": 0})
    run = AttackRun(white_box, spec, cfg, pool=pool)
    try:
        run.source.start(run.state.iteration, run.state.rng)
        out = run.frame_gradients(run.state, run.source.next())
    finally:
        run.close()
    assert set(out["images"]) == {"wrist", "front"} and set(out["grads"]) == {"pose", "saliency"}
    for term, g in out["grads"].items():
        assert g.shape == (3, 16, 16) and torch.isfinite(g).all(), term
        assert float(g.abs().max()) > 0, f"{term}: no gradient reaches the texture"


def test_a_rollout_step_in_the_two_camera_scene_moves_the_arm_as_onnxruntime_does(act_file, white_box, spec):
    scene = spec.with_updates(episode={**spec.episode.model_dump(), "max_steps": 2})
    ends, starts = {}, None
    for name, policy in (("white", white_box), ("black", OnnxPolicy(act_file))):
        env = ReachEnv(scene, num_envs=2, image_size=white_box.image_size, cameras=("wrist", "front"))
        try:
            env.reset_envs([0, 1], seeds=[0, 1])
            starts = env.T_world_tcp.copy()
            out: dict = {}
            rollout(env, [0, 1], policy, lambda j, slot, res, out=out: out.__setitem__(j, res))
        finally:
            env.close()
        ends[name] = out
    for j in (0, 1):
        w, b = ends["white"][j], ends["black"][j]
        assert w["steps"] == 2 and not w["policy_error"], w
        assert np.abs(w["T_world_tcp"][:3, 3] - starts[j][:3, 3]).max() > 1e-3  # the arm moved
        np.testing.assert_allclose(w["T_world_tcp"], b["T_world_tcp"], atol=1e-6)
