"""A real camera as the policy sees it: frames cropped (not squashed) to the policy's input, and a
warning when its field of view or mount differs from the policy's training camera."""

import numpy as np
import pytest
import yaml

from calibration.intrinsics import CameraIntrinsics
from robot_io.cameras.replay import ReplayCamera
from robot_io.config import hardware_config_from_dict
from sim.spec import default_scene
from tests.trials.real.trial_session_helpers import SIM_HW, tiny_onnx
from trials.real.session import camera_view_warnings, load_trial_policy


def _frames(tmp_path, n=2):
    from PIL import Image

    for i in range(n):
        img = np.zeros((480, 640, 3), np.uint8)
        img[:, :80] = 255  # a white band that a center crop drops and a squash keeps
        Image.fromarray(img).save(tmp_path / f"f{i}.png")
    return tmp_path


def _hw():
    return hardware_config_from_dict(yaml.safe_load(SIM_HW.read_text()))


@pytest.mark.parametrize("fx,warned", [(None, False), (200.0, True)])
def test_a_camera_whose_view_differs_from_training_is_warned_about(tmp_path, fx, warned):
    spec = default_scene()
    policy = load_trial_policy(tiny_onnx(tmp_path / "p.onnx"))
    S = int(policy.image_size)
    # The training camera's field of view, as a 640x480 camera seen through the center crop.
    f = spec.camera.K(S, S)[0, 0] * 480 / S if fx is None else fx
    intr = CameraIntrinsics(np.array([[f, 0, 319.5], [0, f, 239.5], [0, 0, 1]]), np.zeros(5), 640, 480)
    with ReplayCamera(_frames(tmp_path), intrinsics=intr) as cam:
        cam.read()
        w = camera_view_warnings(cam, policy, spec, _hw())
    assert bool(w) == warned
    if warned:
        assert "camera (640x480, preprocess center_crop to 32x32): field of view" in w[0]


def test_the_runner_crops_a_wide_frame_instead_of_squashing_it(tmp_path):
    from trials.real.runner import camera_input, camera_view

    policy = load_trial_policy(tiny_onnx(tmp_path / "p.onnx"))
    img = np.zeros((480, 640, 3), np.uint8)
    img[:, :80] = 255
    assert camera_input(policy, "wrist") == ((32, 32), "center_crop")
    view = camera_view(img, *camera_input(policy, "wrist"), "wrist")
    assert view.shape == (32, 32, 3) and view.max() == 0  # the band outside the centred square is gone


def test_a_scene_camera_frame_becomes_its_own_input_and_a_non_square_input_takes_only_its_size():
    from robot_io.errors import RobotIOError
    from trials.real.runner import camera_view

    img = np.zeros((480, 640, 3), np.uint8)
    img[:, :80] = 255
    assert camera_view(img, (480, 640), "center_crop", "front") is img  # its own size: as it is
    view = camera_view(img, (96, 96), "letterbox", "front")
    assert view.shape == (96, 96, 3) and view[48, 8].tolist() == [255, 255, 255]  # letterboxed: the band stays
    with pytest.raises(RobotIOError, match=r"camera 'front': a 640x480 px frame for an input of 96x128 px"):
        camera_view(img, (96, 128), "center_crop", "front")


def test_a_checkpoint_policy_carries_its_card_into_the_session(tmp_path):
    import torch

    from sim.policies.card import PolicyCard
    from sim.policies.checkpoint import save_checkpoint
    from sim.policies.policy import VisuomotorPolicy
    from trials.real.runner import policy_preprocess

    torch.manual_seed(0)
    pol = VisuomotorPolicy(arch="small_cnn", image_size=32)
    card = PolicyCard.model_validate(
        {
            "arch": pol.config.model_dump(),
            "action": {"max_step_m": 0.02, "max_step_rad": 0.1},
            "preprocess": "letterbox",
        }
    )
    save_checkpoint(tmp_path / "ck", pol, card)
    assert policy_preprocess(load_trial_policy(tmp_path / "ck")) == "letterbox"
