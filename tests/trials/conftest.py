"""Shared fixtures: a tiny untrained policy checkpoint, a short-episode pool and an attack dir."""

import numpy as np
import pytest
import torch

MAX_STEPS = 3


@pytest.fixture(scope="session")
def tiny_policy_dir(tmp_path_factory):
    from sim.policies.card import ActionScaling, PolicyCard
    from sim.policies.checkpoint import save_checkpoint
    from sim.policies.policy import VisuomotorPolicy

    torch.manual_seed(0)
    policy = VisuomotorPolicy(arch="small_cnn", image_size=32)
    d = tmp_path_factory.mktemp("policy")
    save_checkpoint(d, policy, PolicyCard(arch=policy.config, action=ActionScaling(max_step_m=0.02, max_step_rad=0.1)))
    return d


@pytest.fixture(scope="session")
def short_spec():
    from sim.spec import default_scene

    spec = default_scene()
    return spec.with_updates(episode={**spec.episode.model_dump(), "max_steps": MAX_STEPS})


@pytest.fixture(scope="session")
def pool_file(tmp_path_factory, short_spec):
    from sim.configs import sample_pool, save_pool

    path = tmp_path_factory.mktemp("pool") / "pool.json"
    # Configurations of the split's evaluation part, as every evaluation uses (sim.configs.config_part).
    save_pool(path, short_spec, sample_pool(short_spec, 24, seed=0, part="evaluation"))
    return path


@pytest.fixture(scope="session")
def mixed_pool_file(tmp_path_factory, short_spec):
    """Seeds 0..59 of every part (25 attack, 3 validation, 32 evaluation), as a policy's own pool holds."""
    from sim.configs import sample_pool, save_pool

    path = tmp_path_factory.mktemp("mixed_pool") / "pool.json"
    save_pool(path, short_spec, sample_pool(short_spec, 60, seed=0))
    return path


def make_attack_dir(path, mesh=None, seed=0, size=16):
    """An attack run directory in the format 'advobj attack run' writes (texture.npy + run.json)."""
    from attack.artifact import AttackArtifact, write_config_record

    texture = np.random.default_rng(seed).random((size, size, 3)).astype(np.float32)
    AttackArtifact(texture, {"attack": {"adversarial_mesh": mesh}}).save(path)
    from sim.configs import sample_pool
    from sim.spec import default_scene

    spec = default_scene()
    spec = spec.with_updates(episode={**spec.episode.model_dump(), "max_steps": MAX_STEPS})
    write_config_record(path, sample_pool(spec, 4, part="attack"), sample_pool(spec, 2, part="validation"))
    return path


@pytest.fixture(scope="session")
def attack_dir(tmp_path_factory):
    return make_attack_dir(tmp_path_factory.mktemp("attack") / "run")
