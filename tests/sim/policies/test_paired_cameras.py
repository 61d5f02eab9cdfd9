"""The evaluation's rollout core through several cameras: what each camera renders and which shows the attack.

A recording policy reads the wrist camera and the two-camera scene's "front" camera through a plan of
named inputs; it moves the TCP a little toward the table so the views change, and keeps every frame
it is handed. The texture is random noise, so an attacked frame differs from its clean twin wherever
the adversarial object is visible.
"""

from __future__ import annotations

import numpy as np
import pytest

from sim.configs import sample_pool
from sim.policies.contract import BoundImage, BoundState, ImageInput, InputPlan, PolicyContract
from sim.policies.interface import PolicyError
from sim.policies.paired import rollout_paired
from sim.spec import UnknownCameraError, default_scene, load_spec
from sim.variations import Randomization
from trials.eval.conditions import Sources, build_conditions

TWO_CAMERAS = "scenes/two-cameras.yaml"


class _Recording:
    """Reads the cameras named; each call's ``{camera: (B, H, W, 3)}`` is kept in ``calls``."""

    white_box = False
    image_size = 32

    def __init__(self, cameras=("wrist", "front")):
        sizes = {"wrist": (32, 32), "front": (128, 128)}
        self.contract = PolicyContract(state=("tcp_pose", "gripper"))
        self.inputs = InputPlan(
            tuple(BoundImage(f"in_{c}", c, sizes[c], ImageInput()) for c in cameras),
            (BoundState("state", "state", (0, 7)),),
            "action",
        )
        self.calls: list[dict] = []

    def act(self, images, state):
        self.calls.append(images if isinstance(images, dict) else {self.inputs.cameras[0]: images})
        a = np.zeros((len(state), 6), np.float32)
        a[:, 2] = 0.5  # along the wrist camera's view: toward the table
        return a


@pytest.fixture(scope="module")
def scene():
    s = load_spec(TWO_CAMERAS)
    return s.with_updates(episode={**s.episode.model_dump(), "max_steps": 3})


@pytest.fixture(scope="module")
def configs(scene):
    return sample_pool(scene, 2, seed=0, part="evaluation")


TEXTURE = np.random.default_rng(0).integers(0, 256, (64, 64, 3), dtype=np.uint8)


def _run(scene, configs, policy, **kw):
    frames = []

    def keep(slots, T, steps, a_adv, a_clean, views):
        frames.extend(v["cameras"] for v in views)

    rollout_paired(policy, scene, configs, 2, lambda j, i, r: None, on_actions=keep, **kw)
    return frames


def test_every_camera_the_policy_reads_is_rendered_at_its_size_and_handed_over_by_name(scene, configs):
    p = _Recording()
    frames = _run(scene, configs, p)
    assert p.calls and all(set(c) == {"wrist", "front"} for c in p.calls)
    assert all(c["wrist"].shape[1:] == (32, 32, 3) and c["front"].shape[1:] == (128, 128, 3) for c in p.calls)
    assert all(set(f) == {"wrist", "front"} for f in frames)
    assert np.std(frames[0]["front"]["clean"]) > 10  # a rendered scene, not a blank frame


def test_a_one_camera_policy_is_rendered_its_camera_only(scene, configs):
    p = _Recording(cameras=("front",))
    frames = _run(scene, configs, p)
    assert all(set(c) == {"front"} for c in p.calls) and all(set(f) == {"front"} for f in frames)


@pytest.mark.parametrize(
    "attacked, shows",
    [(None, {"wrist", "front"}), (("wrist",), {"wrist"}), (("front",), {"front"})],
    ids=["all", "wrist-only", "front-only"],
)
def test_the_texture_is_shown_to_the_attacked_cameras_only(scene, configs, attacked, shows):
    frames = _run(scene, configs, _Recording(), texture=TEXTURE, attacked_cameras=attacked)
    for cam in ("wrist", "front"):
        differs = any(not np.array_equal(f[cam]["adv"], f[cam]["clean"]) for f in frames)
        assert differs == (cam in shows), cam


def test_each_camera_keeps_its_own_noise_stream_so_the_wrist_frames_do_not_change_beside_a_scene_camera(scene, configs):
    noisy = Randomization(noise_std=0.03)
    both = _run(scene, configs, _Recording(), texture=TEXTURE, randomization=noisy)
    wrist = _run(scene, configs, _Recording(cameras=("wrist",)), texture=TEXTURE, randomization=noisy)
    assert len(both) == len(wrist)
    for a, b in zip(both, wrist):
        np.testing.assert_array_equal(a["wrist"]["adv"], b["wrist"]["adv"])
        np.testing.assert_array_equal(a["wrist"]["clean"], b["wrist"]["clean"])


def test_a_camera_carrying_the_attack_that_the_policy_does_not_read_is_one_line(scene, configs):
    with pytest.raises(PolicyError, match=r"attacked camera 'front': the policy reads wrist;"):
        _run(scene, configs, _Recording(cameras=("wrist",)), texture=TEXTURE, attacked_cameras=("front",))


def test_stereo_with_several_cameras_is_one_line(scene, configs):
    with pytest.raises(PolicyError, match="stereo: the stereo pair is the wrist camera's"):
        _run(scene, configs, _Recording(), texture=TEXTURE, stereo=True)


def test_a_camera_the_scene_lacks_is_one_line(configs):
    with pytest.raises(UnknownCameraError, match="unknown camera 'front'; this scene has: wrist"):
        _run(default_scene(), configs, _Recording())


def test_which_camera_carries_the_attack_is_a_condition_per_camera(tmp_path, monkeypatch):
    import trials.eval.conditions as conditions

    monkeypatch.setattr(conditions, "load_attack_source", lambda path: conditions.AttackSource(path, TEXTURE, None, ""))
    conds = build_conditions(["attack", "attack_wrist_only", "attack_front_only"], Sources(attack="run"))
    got = {c.name: c.attacked_cameras for c in conds}
    assert got == {"clean": None, "attack": None, "attack_wrist_only": ("wrist",), "attack_front_only": ("front",)}
    assert "attacked_cameras" not in conds[1].to_dict()  # the conditions before it dump as they did
    assert conds[3].to_dict()["attacked_cameras"] == ["front"]
    with pytest.raises(conditions.ConditionError, match="unknown condition 'attack_front'"):
        build_conditions(["attack_front"], Sources(attack="run"))
