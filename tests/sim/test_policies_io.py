"""Checkpoints (safetensors + policy card), refusal of tampered files, ONNX export parity."""

import json
import pickle

import numpy as np
import pytest
import torch

from sim.policies.card import CARD_NAME, ActionScaling, PolicyCard, load_card
from sim.policies.checkpoint import WEIGHTS_NAME, load_checkpoint, load_policy, save_checkpoint
from sim.policies.interface import PolicyError, WhiteBoxRequired, require_white_box
from sim.policies.onnx_policy import OnnxPolicy, export_onnx
from sim.policies.policy import VisuomotorPolicy


def _policy(arch="small_cnn", size=64, seed=0):
    """A policy with non-trivial BN statistics and actions well inside (-1, 1)."""
    torch.manual_seed(seed)
    p = VisuomotorPolicy(arch=arch, image_size=size)
    p.train()
    with torch.no_grad():
        p(torch.rand(16, 3, size, size))
        p.mlp[-1].weight.mul_(20.0)  # spread the untrained actions over tanh's range
    return p.eval()


def _card(p):
    return PolicyCard(
        arch=p.config, action=ActionScaling(max_step_m=0.02, max_step_rad=0.1), seed=0, training={"method": "test"}
    )


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    p = _policy()
    d = tmp_path_factory.mktemp("ckpt")
    save_checkpoint(d, p, _card(p))
    return p, d


def test_checkpoint_round_trip_restores_identical_actions(ckpt):
    p, d = ckpt
    q, card = load_checkpoint(d)
    x = np.random.default_rng(1).integers(0, 256, (4, 64, 64, 3), dtype=np.uint8)
    assert np.array_equal(p.act(x), q.act(x))
    assert card.arch == p.config and card.training == {"method": "test"} and len(card.weights_sha256) == 64
    assert (d / WEIGHTS_NAME).is_file() and not list(d.glob("*.tmp"))


def test_tampered_weights_are_refused(ckpt, tmp_path):
    _, d = ckpt
    for f in (CARD_NAME, WEIGHTS_NAME):
        (tmp_path / f).write_bytes((d / f).read_bytes())
    raw = bytearray((tmp_path / WEIGHTS_NAME).read_bytes())
    raw[-5] ^= 0xFF  # one flipped byte inside a tensor
    (tmp_path / WEIGHTS_NAME).write_bytes(bytes(raw))
    with pytest.raises(PolicyError, match="weights_sha256"):
        load_checkpoint(tmp_path)


class _Payload:
    def __reduce__(self):
        import pathlib

        return (pathlib.Path.touch, (pathlib.Path(self.marker),))


def test_pickle_carrying_code_is_refused_without_running_it(ckpt, tmp_path):
    _, d = ckpt
    marker = tmp_path / "pwned"
    payload = _Payload()
    payload.marker = str(marker)
    blob = pickle.dumps(payload)
    # 1) a pickle given directly as the policy
    (tmp_path / "policy.pt").write_bytes(blob)
    with pytest.raises(PolicyError, match="not a policy"):
        load_policy(tmp_path / "policy.pt")
    # 2) a pickle swapped in for the weights, even with the card's hash updated to match
    ck = tmp_path / "ck"
    ck.mkdir()
    (ck / WEIGHTS_NAME).write_bytes(blob)
    card = json.loads((d / CARD_NAME).read_text())
    import hashlib

    card["weights_sha256"] = hashlib.sha256(blob).hexdigest()
    (ck / CARD_NAME).write_text(json.dumps(card))
    with pytest.raises(PolicyError, match="safetensors"):
        load_checkpoint(ck)
    assert not marker.exists()


def test_card_with_unknown_key_or_wrong_format_is_refused(ckpt, tmp_path):
    _, d = ckpt
    card = json.loads((d / CARD_NAME).read_text())
    (tmp_path / CARD_NAME).write_text(json.dumps({**card, "optimizer": "adam"}))
    with pytest.raises(PolicyError, match="optimizer"):
        load_card(tmp_path)
    (tmp_path / CARD_NAME).write_text(json.dumps({**card, "format": "something-else"}))
    with pytest.raises(PolicyError, match="format"):
        load_card(tmp_path)
    (tmp_path / CARD_NAME).write_text(json.dumps({**card, "arch": {**card["arch"], "arch": "alexnet"}}))
    with pytest.raises(PolicyError, match="arch.arch"):
        load_card(tmp_path)


def test_missing_paths_and_plain_files_get_clear_errors(tmp_path):
    with pytest.raises(PolicyError, match="no such"):
        load_policy(tmp_path / "nope")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(PolicyError, match="not a policy"):
        load_policy(tmp_path / "notes.txt")
    (tmp_path / "bad.onnx").write_bytes(b"not onnx")
    with pytest.raises(PolicyError, match="ONNX"):
        load_policy(tmp_path / "bad.onnx")


def _synthetic_scenes(n, size, seed=0):
    """Scene-like images: a table-coloured field with two coloured blobs at random places."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size]
    imgs = np.empty((n, size, size, 3), np.uint8)
    for i in range(n):
        img = np.ones((size, size, 3)) * rng.uniform(0.3, 0.8, 3)
        for _ in range(2):
            cx, cy, r = rng.uniform(0, size, 2).tolist() + [rng.uniform(3, size / 4)]
            img[(xx - cx) ** 2 + (yy - cy) ** 2 < r * r] = rng.uniform(0, 1, 3)
        imgs[i] = np.clip(img * 255 + rng.normal(0, 3, img.shape), 0, 255)
    return imgs


@pytest.fixture(scope="module")
def onnx_pair(tmp_path_factory):
    p = _policy("resnet18", 64)
    path = export_onnx(p, tmp_path_factory.mktemp("onnx") / "policy.onnx", card=_card(p))
    return p, OnnxPolicy(path)


def test_onnx_matches_torch_on_32_random_images(onnx_pair):
    p, o = onnx_pair
    x = np.random.default_rng(0).random((32, 3, 64, 64), dtype=np.float32)
    ref = p.act(x)
    assert ref.std() > 0.1  # actions are spread out, so the comparison means something
    assert np.abs(o.act(x) - ref).max() <= 1e-4


def test_onnx_matches_torch_on_32_synthetic_scene_images(onnx_pair):
    p, o = onnx_pair
    imgs = _synthetic_scenes(32, 64)
    assert np.abs(o.act(imgs) - p.act(imgs)).max() <= 1e-4


def test_onnx_matches_torch_on_32_rendered_wrist_camera_images(onnx_pair):
    from sim.spec import default_scene
    from sim.variations import Randomization
    from sim.world import SimWorld

    p, o = onnx_pair
    with SimWorld(
        default_scene(), image_size=64, randomization=Randomization(light="random", background="varied")
    ) as world:
        frames = []
        for seed in range(32):
            world.reset(seed)
            frames.append(world.render(with_ids=False).rgb)
    imgs = np.stack(frames)
    assert imgs.std() > 10  # real scenes, not blank frames
    assert np.abs(o.act(imgs) - p.act(imgs)).max() <= 1e-4


def test_onnx_policy_carries_its_card_and_is_refused_by_the_attack(onnx_pair):
    p, o = onnx_pair
    assert o.image_size == 64 and o.card is not None and o.card.arch == p.config
    with pytest.raises(WhiteBoxRequired, match="white-box"):
        require_white_box(o)
    assert isinstance(load_policy(o.path), OnnxPolicy)


def test_onnx_export_rejects_old_opsets(tmp_path):
    with pytest.raises(PolicyError, match="opset"):
        export_onnx(_policy(), tmp_path / "p.onnx", opset=13)


def test_onnx_thread_and_spin_settings_change_speed_not_actions(onnx_pair):
    from sim.policies.onnx_policy import OnnxPolicy

    _, default = onnx_pair
    x = np.random.default_rng(5).integers(0, 256, (4, default.image_size, default.image_size, 3), dtype=np.uint8)
    ref = default.act(x)
    for threads, spin in ((1, False), (2, False), (2, True)):
        np.testing.assert_allclose(OnnxPolicy(default.path, threads=threads, spin=spin).act(x), ref, atol=1e-5)
