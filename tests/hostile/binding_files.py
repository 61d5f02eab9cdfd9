"""Inputs whose parts are each valid but do not fit together: a policy file's card and its model, a
policy and the scene's cameras, a scene camera and the table. Built here from real exporters and
the zoo's tiny policies (tests/policy_zoo.py), never downloaded; each builder writes one file and
returns its path. Used by the CLI's one-line tests (test_policy_file_formats.py) and the hostile
campaign (test_cli_campaign.py).
"""

from __future__ import annotations

from pathlib import Path

import yaml

from sim.policies.card import PolicyCard
from sim.policies.checkpoint import save_checkpoint
from sim.policies.onnx_policy import export_onnx
from sim.policies.pt2 import export_pt2
from sim.spec import default_scene
from tests.policy_files import two_camera_onnx
from tests.policy_zoo import TwoCameraPolicy, card_of, contract_of, tiny_policy, two_camera_card

__all__ = [
    "TWO_CAMERAS",
    "card_missing_input_onnx",
    "card_unknown_camera_onnx",
    "card_unknown_camera_pt2",
    "card_image_size_onnx",
    "front_64px_onnx",
    "scene_camera_without_pose",
    "tiny_checkpoint",
]

ROOT = Path(__file__).resolve().parents[2]
TWO_CAMERAS = ROOT / "scenes" / "two-cameras.yaml"  # front renders 128 x 128 px


def _card(policy, inputs: dict) -> PolicyCard:
    """``policy``'s card with ``inputs`` as its named-input bindings."""
    return PolicyCard.model_validate({**card_of(policy).model_dump(mode="json"), "inputs": inputs})


def _image_only():
    return tiny_policy(contract_of((), ("delta_tcp", 1, 1)))  # 32 px, one input "images"


def card_missing_input_onnx(path) -> Path:
    """A one-camera .onnx whose card binds an input ``observation.images.side`` the model lacks."""
    p = _image_only()
    inputs = {
        "images": {"source": "camera", "camera": "wrist"},
        "observation.images.side": {"source": "camera", "camera": "wrist"},
    }
    return export_onnx(p, path, card=_card(p, inputs))


def card_unknown_camera_onnx(path) -> Path:
    """A one-camera .onnx whose card binds its image to camera ``side``, which no scene has."""
    p = _image_only()
    return export_onnx(p, path, card=_card(p, {"images": {"source": "camera", "camera": "side"}}))


def card_unknown_camera_pt2(path) -> Path:
    """The same card inside a .pt2 (torch.export names the image input after forward's argument, x)."""
    p = _image_only()
    return export_pt2(p, path, _card(p, {"x": {"source": "camera", "camera": "side"}}))


def card_image_size_onnx(path) -> Path:
    """A 32 px .onnx whose card says its wrist image is 64 x 64 px."""
    p = _image_only()
    inputs = {"images": {"source": "camera", "camera": "wrist", "image": {"size": [64, 64]}}}
    return export_onnx(p, path, card=_card(p, inputs))


def front_64px_onnx(path) -> Path:
    """A LeRobot-named two-camera .onnx whose front input takes 64 px images: on scenes/two-cameras.yaml
    the front camera renders 128 px."""
    return two_camera_onnx(path, TwoCameraPolicy(front_px=64), two_camera_card())


def scene_camera_without_pose(path) -> Path:
    """The built-in scene with a ``scene_cameras`` entry that has no pose (no extrinsics)."""
    doc = default_scene().model_dump(mode="json")
    doc["scene_cameras"] = [{"name": "front", "width": 128, "height": 128, "fov_deg": 60}]
    Path(path).write_text(yaml.safe_dump(doc, sort_keys=False))
    return Path(path)


def tiny_checkpoint(path) -> Path:
    """A valid checkpoint directory of the zoo's 32 px image-only policy (what a command needs beside
    the input under test)."""
    p = _image_only()
    save_checkpoint(path, p, card_of(p))
    return Path(path)
