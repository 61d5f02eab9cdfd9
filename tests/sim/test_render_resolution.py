"""Envs render at the policy's input size, never larger (a larger render would only be downsampled)."""

import pytest

from sim.env import EnvError, ReachEnv
from sim.spec import default_scene


def test_env_renders_at_the_policy_size_and_refuses_others():
    spec = default_scene()
    assert (spec.camera.height, spec.camera.width) == (128, 128)
    with ReachEnv(spec, num_envs=1, policy_image_size=32) as env:
        obs, _ = env.reset(seed=0)
        assert obs.shape == (1, 32, 32, 3) and (env.renderer.height, env.renderer.width) == (32, 32)
        # The intrinsics are the spec camera's rescaled: same field of view, not a crop.
        assert env.renderer.K[0, 0] == pytest.approx(spec.camera.K()[0, 0] * 32 / 128)
    for wrong in (64, (32, 48), None):
        with pytest.raises(EnvError, match="image_size.*policy reads 32x32"):
            ReachEnv(spec, num_envs=1, image_size=wrong if wrong is not None else (128, 128), policy_image_size=32)
