"""The reach task as a gymnasium env: gymnasium's own checker, registration, vectorisation, SB3."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import sim.gym_env  # noqa: F401  (registers the id)
from sim.gym_env import ENV_ID, ReachGymEnv


@pytest.fixture
def env():
    e = ReachGymEnv(image_size=32, render_mode="rgb_array")
    yield e
    e.close()


def test_gymnasiums_env_checker_passes():
    import warnings

    e = gym.make(
        ENV_ID, image_size=32, render_mode="rgb_array"
    ).unwrapped  # made: the checker also tries its render modes
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # any complaint of the checker fails the test
        check_env(e, skip_render_check=False)
    e.close()


def test_the_same_seed_gives_the_same_episode_and_spaces_hold(env):
    a, _ = env.reset(seed=7)
    b, info = env.reset(seed=7)
    assert np.array_equal(a, b) and env.observation_space.contains(a) and info["seeds"] == 7
    c, _ = env.reset(seed=8)
    assert not np.array_equal(a, c)
    obs, r, term, trunc, info = env.step(np.array([0, 0, 1, 0, 0, 0], np.float32))
    assert env.observation_space.contains(obs) and isinstance(r, float) and isinstance(term, bool) and info["step"] == 1


def test_an_episode_ends_by_reaching_or_by_max_steps(env):
    env.reset(seed=3)
    for _ in range(env.unwrapped._env.max_steps):
        _, _, term, trunc, info = env.step(env.action_space.sample())
        if term or trunc:
            break
    assert term or trunc
    assert trunc == (not term) and (info["step"] == env.unwrapped._env.max_steps or term)


def test_registered_and_vectorised():
    e = gym.make(ENV_ID, image_size=32)
    assert e.spec.id == ENV_ID and e.observation_space.shape == (32, 32, 3)
    e.close()
    envs = gym.make_vec(ENV_ID, num_envs=2, vectorization_mode="sync", image_size=32)
    obs, _ = envs.reset(seed=[1, 2])
    assert obs.shape == (2, 32, 32, 3)
    obs, r, term, trunc, _ = envs.step(np.zeros((2, 6), np.float32))
    assert r.shape == (2,)
    envs.close()


def test_stable_baselines3_takes_it_without_a_wrapper():
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    e = ReachGymEnv(image_size=32)
    sb3_check_env(e, warn=False)
    e.close()


def test_registering_twice_changes_nothing_and_the_entry_point_names_the_class():
    import warnings

    from gymnasium.envs.registration import load_env_creator

    from sim.gym_env import register_envs

    spec = gym.spec(ENV_ID)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # gymnasium warns when an id is registered over
        register_envs()
    assert gym.spec(ENV_ID) is spec
    assert spec.entry_point == "sim.gym_env:ReachGymEnv" and load_env_creator(spec.entry_point) is ReachGymEnv


def test_a_fresh_interpreter_makes_the_env_by_its_module_prefixed_id_without_importing_it():
    """gymnasium 1.x reads no plugin entry points; ``"sim.gym_env:advobj/Reach-v0"`` makes gymnasium
    import the module that registers the id, and the bare id works from then on."""
    import subprocess
    import sys
    from pathlib import Path

    code = (
        "import sys, gymnasium as gym\n"
        "assert 'sim.gym_env' not in sys.modules and 'advobj/Reach-v0' not in gym.registry\n"
        "e = gym.make('sim.gym_env:advobj/Reach-v0', image_size=32)\n"
        "obs, _ = e.reset(seed=0)\n"
        "e.close()\n"
        "v = gym.make_vec('advobj/Reach-v0', num_envs=1, vectorization_mode='sync', image_size=32)\n"
        "v.close()\n"
        "print(obs.shape)\n"
    )
    root = Path(__file__).resolve().parents[2]
    r = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "(32, 32, 3)"
