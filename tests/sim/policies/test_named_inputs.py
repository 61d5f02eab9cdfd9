"""Named inputs: the card binds each model input to a camera or the state; LeRobot's names bind as they come.

Real files: a tiny two-camera policy (tests.policy_zoo.TwoCameraPolicy) exported here by torch.onnx and
torch.export, run by the real onnxruntime and loaded white-box; nothing is downloaded.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from sim.policies.card import PolicyCard
from sim.policies.checkpoint import load_policy
from sim.policies.contract import (
    ImageInput,
    InputBinding,
    bind_inputs,
    call_policy,
    check_scene,
    policy_cameras,
    to_model_image,
)
from sim.policies.graph_policy import GraphPolicy
from sim.policies.interface import PolicyError
from sim.policies.onnx_policy import OnnxPolicy, attach_card
from sim.policies.onnx_torch import ATOL
from sim.policies.policy import IMAGENET_MEAN, IMAGENET_STD
from sim.spec import UnknownCameraError, default_scene, load_spec
from tests.policy_files import legacy_onnx_export, two_camera_onnx, two_camera_pt2
from tests.policy_zoo import TwoCameraPolicy, card_of, contract_of, tiny_policy, two_camera_card, two_camera_contract

TWO_CAMERAS = "scenes/two-cameras.yaml"
LW = "observation.images.wrist"


def _batch(n=3, seed=0):
    rng = np.random.default_rng(seed)
    return (
        {
            "wrist": rng.integers(0, 256, (n, 32, 32, 3), dtype=np.uint8),
            "front": rng.integers(0, 256, (n, 128, 128, 3), dtype=np.uint8),
        },
        rng.standard_normal((n, 7)).astype(np.float32),
    )


def _torch_actions(policy, images, state):
    x = {k: torch.from_numpy(v).permute(0, 3, 1, 2).float() / 255.0 for k, v in images.items()}
    with torch.no_grad():
        return policy(x["wrist"], x["front"], torch.from_numpy(state)).numpy()


@pytest.fixture(scope="module")
def lerobot_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("named")
    p = TwoCameraPolicy()
    card = two_camera_card()
    return p, two_camera_onnx(d / "p.onnx", p, card), two_camera_pt2(d / "p.pt2", p, card)


def test_lerobot_names_bind_as_they_come_in_an_onnx_file(lerobot_files):
    p, onnx_path, _ = lerobot_files
    o = OnnxPolicy(onnx_path)
    assert policy_cameras(o) == ("wrist", "front")
    assert [(s.name, s.source) for s in o.inputs.states] == [("observation.state", "state")]
    assert o.inputs.output == "action" and o.image_size == 32
    images, state = _batch()
    np.testing.assert_allclose(call_policy(o, images, state), _torch_actions(p, images, state), atol=1e-5)


def test_lerobot_dict_inputs_of_a_pt2_bind_by_their_keys_and_compute_the_module(lerobot_files):
    p, _, pt2_path = lerobot_files
    g = load_policy(pt2_path)
    assert isinstance(g, GraphPolicy) and g.cameras == ("wrist", "front")
    assert set(g.feature_map) == {"wrist", "front"}
    images, state = _batch()
    np.testing.assert_allclose(call_policy(g, images, state), _torch_actions(p, images, state), atol=1e-5)


def test_a_two_camera_onnx_converts_white_box_on_the_two_camera_scene_and_matches_onnxruntime(lerobot_files):
    p, onnx_path, _ = lerobot_files
    g = load_policy(onnx_path, white_box=True, spec=load_spec(TWO_CAMERAS))
    assert g.check["frames"] >= 32 and g.check["max_abs_diff"] <= ATOL
    images, state = _batch(seed=1)
    np.testing.assert_allclose(g.act(images, state), OnnxPolicy(onnx_path).act(images, state), atol=ATOL)
    x = {c: torch.rand(2, 3, *(32, 32) if c == "wrist" else (128, 128), requires_grad=True) for c in g.cameras}
    A = g.features(x)
    assert set(A) == {"wrist", "front"} and all(a.ndim == 4 for a in A.values())
    g.head(A, torch.zeros(2, 7)).sum().backward()
    assert all(torch.isfinite(v.grad).all() and v.grad.abs().sum() > 0 for v in x.values())


def test_a_camera_the_scene_lacks_is_one_line_listing_the_scene_cameras(lerobot_files):
    _, onnx_path, _ = lerobot_files
    with pytest.raises(UnknownCameraError, match=r"unknown camera 'front'; this scene has: wrist$"):
        load_policy(onnx_path, white_box=True)  # the built-in scene has the wrist camera only
    with pytest.raises(UnknownCameraError, match="unknown camera 'front'"):
        check_scene(OnnxPolicy(onnx_path), default_scene())
    check_scene(OnnxPolicy(onnx_path), load_spec(TWO_CAMERAS))


def test_a_scene_camera_of_another_size_than_its_input_is_one_line(tmp_path):
    p = TwoCameraPolicy(front_px=64)
    path = two_camera_onnx(tmp_path / "p64.onnx", p, two_camera_card())
    with pytest.raises(PolicyError, match=r"camera 'front' renders 128x128 px but the model takes 64x64 px"):
        check_scene(OnnxPolicy(path), load_spec(TWO_CAMERAS))


def test_an_image_of_the_wrong_size_is_one_line_naming_the_camera(lerobot_files):
    _, onnx_path, pt2_path = lerobot_files
    images, state = _batch()
    images["front"] = images["front"][:, :64, :64]
    with pytest.raises(PolicyError, match=r"camera 'front': images: policy expects 128x128 px, got 64x64"):
        OnnxPolicy(onnx_path).act(images, state)
    with pytest.raises(PolicyError, match="policy expects 128x128 px, got 64x64"):
        load_policy(pt2_path).act(images, state)


def test_a_several_camera_policy_given_one_array_is_one_line(lerobot_files):
    _, onnx_path, _ = lerobot_files
    images, state = _batch()
    with pytest.raises(PolicyError, match=r"reads cameras wrist, front; pass \{camera: images\}"):
        call_policy(OnnxPolicy(onnx_path), images["wrist"], state)
    with pytest.raises(PolicyError, match="no images of 'front'"):
        call_policy(OnnxPolicy(onnx_path), {"wrist": images["wrist"]}, state)


def test_a_one_camera_policy_takes_its_array_or_a_dict_holding_it_with_the_same_actions(tmp_path):
    p = tiny_policy(contract_of((), ("delta_tcp", 1, 1)))
    images, _ = _batch()
    a = call_policy(p, images["wrist"], None)
    np.testing.assert_array_equal(call_policy(p, {"wrist": images["wrist"], "front": images["front"]}, None), a)


def test_an_old_card_dumps_and_binds_as_before_named_inputs(tmp_path):
    p = tiny_policy(contract_of(("tcp_pose", "gripper"), ("delta_tcp", 1, 1)))
    card = card_of(p)
    doc = json.loads(card.model_dump_json())
    assert "inputs" not in doc and "action_output" not in doc
    assert PolicyCard.model_validate(doc) == card
    plan = bind_inputs(None, [("x", (None, 3, 32, 32)), ("s", (None, 7))], ["y"], p.contract)
    assert [(b.name, b.camera, b.size) for b in plan.images] == [("x", "wrist", (32, 32))]
    assert [(s.name, s.source, s.slice) for s in plan.states] == [("s", "state", (0, 7))] and plan.output == "y"


def _card_with(inputs, **kw):
    return two_camera_card(inputs={k: InputBinding.model_validate(v) for k, v in inputs.items()}, **kw)


class _Convention(torch.nn.Module):
    """The two-camera policy behind other conventions: the front camera as BGR NHWC in 0..255 with
    per-channel normalisation, the state split into tcp_pose and gripper inputs of their own."""

    example_sizes = (32, 128)

    def __init__(self, inner, mean, std):
        super().__init__()
        self.inner = inner
        self.register_buffer("mean", torch.tensor(mean).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(std).view(1, 3, 1, 1))

    def forward(self, cam_a, cam_b, pose, grip):
        rgb01 = (cam_b.permute(0, 3, 1, 2) * self.std + self.mean)[:, [2, 1, 0]] / 255.0
        return self.inner(cam_a, rgb01, torch.cat([pose, grip], 1))


def test_a_card_binds_any_names_and_converts_each_image_to_the_model_convention(tmp_path):
    inner = TwoCameraPolicy()
    mean, std = (100.0, 110.0, 120.0), (50.0, 60.0, 70.0)
    wrapped = _Convention(inner, mean, std)
    front = {"layout": "nhwc", "channel_order": "bgr", "value_range": "0..255", "mean": mean, "std": std}
    card = _card_with(
        {
            "cam_a": {"source": "camera", "camera": "wrist"},
            "cam_b": {"source": "camera", "camera": "front", "image": front},
            "pose": {"source": "tcp_pose"},
            "grip": {"source": "gripper"},
        },
        action_output="out",
    )
    path = tmp_path / "conv.onnx"
    args = (torch.rand(2, 3, 32, 32), torch.rand(2, 128, 128, 3) * 255, torch.rand(2, 6), torch.rand(2, 1))
    legacy_onnx_export(
        wrapped.eval(),
        args,
        str(path),
        input_names=["cam_a", "cam_b", "pose", "grip"],
        output_names=["out"],
        dynamic_axes={n: {0: "b"} for n in ["cam_a", "cam_b", "pose", "grip", "out"]},
        opset_version=17,
    )
    attach_card(path, card)
    o = OnnxPolicy(path)
    assert o.inputs.image_for("front").size == (128, 128) and o.inputs.output == "out"
    images, state = _batch()
    want = _torch_actions(inner, images, state)
    np.testing.assert_allclose(call_policy(o, images, state), want, atol=1e-4)
    g = load_policy(path, white_box=True, spec=load_spec(TWO_CAMERAS))
    np.testing.assert_allclose(call_policy(g, images, state), want, atol=1e-4)


def test_to_model_image_is_the_same_in_numpy_and_torch():
    x = np.random.default_rng(0).random((2, 3, 4, 5)).astype(np.float32)
    im = ImageInput(value_range="-1..1", channel_order="bgr", layout="nhwc", mean=(0.1, 0.2, 0.3), std=(2, 3, 4))
    got = to_model_image(torch.from_numpy(x), im).numpy()
    np.testing.assert_allclose(got, to_model_image(x, im), atol=1e-6)
    assert got.shape == (2, 4, 5, 3)
    np.testing.assert_allclose(got[..., 0], ((x[:, 2] * 2 - 1) - 0.1) / 2, atol=1e-6)


@pytest.mark.parametrize(
    "inputs, match",
    [
        ({"nope": {"source": "camera", "camera": "wrist"}}, r"card inputs: 'nope' is not an input of the model"),
        (
            {LW: {"source": "camera", "camera": "wrist"}},
            r"input 'observation.images.front' of the model is not bound by the card's inputs",
        ),
        (
            {
                LW: {"source": "camera", "camera": "wrist"},
                "observation.images.front": {"source": "camera", "camera": "front"},
                "observation.state": {"source": "joint_positions"},
            },
            # a TCP card's state lists no joint positions: binding them is refused, naming the input
            r"input 'observation.state' reads joint_positions but the card's contract.state .* does not list it",
        ),
        (
            {
                LW: {"source": "camera", "camera": "wrist"},
                "observation.images.front": {"source": "camera", "camera": "wrist"},
                "observation.state": {"source": "state"},
            },
            r"camera 'wrist' is bound to two inputs",
        ),
    ],
    ids=["missing-input", "unbound-input", "joint-positions", "camera-twice"],
)
def test_a_card_that_does_not_fit_the_model_is_one_line(lerobot_files, tmp_path, inputs, match):
    _, onnx_path, _ = lerobot_files
    path = tmp_path / "p.onnx"
    path.write_bytes(onnx_path.read_bytes())
    attach_card(path, _card_with(inputs))
    with pytest.raises(PolicyError, match=match) as err:
        OnnxPolicy(path)
    assert "\n" not in str(err.value) and str(path) in str(err.value)


def test_a_binding_that_mixes_camera_and_state_fields_is_refused_naming_the_field():
    with pytest.raises(ValueError, match="a state input reads no camera"):
        InputBinding(source="state", camera="wrist")
    with pytest.raises(ValueError, match="a camera input names its camera"):
        InputBinding(source="camera")
    with pytest.raises(ValueError, match="std"):
        ImageInput(std=(1.0, 0.0, 1.0))


def test_the_contract_state_must_be_bound_field_by_field_once():
    c = two_camera_contract()
    shapes = [("w", (None, 3, 32, 32)), ("p", (None, 6))]
    b = {"w": InputBinding(source="camera", camera="wrist"), "p": InputBinding(source="tcp_pose")}
    with pytest.raises(PolicyError, match=r"reads state \['tcp_pose', 'gripper'\] but the model's inputs read"):
        bind_inputs(b, shapes, ["a"], c)


def test_the_workflow_docs_lerobot_act_card_validates_and_binds_a_lerobot_named_model():
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[3] / "docs" / "workflow.md").read_text()
    blocks = [b for b in re.findall(r"```json\n(.*?)```", text, re.S) if "observation.images.front" in b]
    assert len(blocks) == 1
    card = PolicyCard.model_validate(json.loads(blocks[0]))
    assert "arch" not in json.loads(card.model_dump_json())
    plan = bind_inputs(
        card.inputs,
        [
            ("observation.images.wrist", ("B", 3, 128, 128)),
            ("observation.images.front", ("B", 3, 128, 128)),
            ("observation.state", ("B", 7)),
        ],
        ["action"],
        card.contract,
        card.action_output,
    )
    assert plan.cameras == ("wrist", "front") and plan.output == "action"
    same = bind_inputs(
        None,
        [(b.name, ("B", 3, 128, 128)) for b in plan.images] + [("observation.state", ("B", 7))],
        ["action"],
        card.contract,
    )
    # LeRobot's names bind to the same cameras, state and output without the card's inputs, but then
    # feed unnormalised frames: LeRobot 0.4 normalises in its processor, so the card states it.
    assert (same.cameras, same.states, same.output) == (plan.cameras, plan.states, plan.output)
    assert all(b.image.is_identity for b in same.images)
    assert all(b.image.mean == IMAGENET_MEAN and b.image.std == IMAGENET_STD for b in plan.images)
    check_scene(type("P", (), {"inputs": plan})(), load_spec(TWO_CAMERAS))
