"""``attack run --scene`` with a trained policy whose own pool is for another scene: the attack
builds the task-feasible configurations of that scene (attack and validation parts only)."""

from __future__ import annotations

import pytest
import torch
import trimesh
import yaml

from sim.configs import config_part, load_pool, sample_pool, save_pool, spec_fingerprint
from sim.spec import default_scene, load_scene

TINY_ATTACK = {
    "iterations": 1,
    "num_envs": 1,
    "rollout_steps": 1,
    "texture_size": 8,
    "checkpoint_every": 1,
    "validation_every": 1,
    "validation_episodes": 2,
    "validation_max_steps": 2,
}


def _policy_dir(tmp_path, straight: bool):
    """A small-CNN checkpoint with its own pool for the built-in scene; ``straight``: always moves
    straight ahead (the camera aims between the objects, so it reaches the goal from some starts)."""
    from sim.policies.card import ActionScaling, PolicyCard
    from sim.policies.checkpoint import save_checkpoint
    from sim.policies.policy import VisuomotorPolicy

    torch.manual_seed(0)
    p = VisuomotorPolicy(arch="small_cnn", image_size=32)
    if straight:
        with torch.no_grad():
            p.mlp[-1].weight.zero_()
            p.mlp[-1].bias.zero_()
            p.mlp[-1].bias[2] = 4.0
    d = tmp_path / "policy"
    save_checkpoint(d, p, PolicyCard(arch=p.config, action=ActionScaling(max_step_m=0.02, max_step_rad=0.1)))
    save_pool(d / "feasible_pool.json", default_scene(), sample_pool(default_scene(), 80, seed=0))
    return d


def _own_scene(tmp_path, max_steps: int):
    trimesh.creation.box((50.0, 50.0, 50.0)).export(tmp_path / "cube_mm.stl")  # a 5 cm cube, as a CAD tool exports it
    d = default_scene().model_dump(mode="json")
    next(o for o in d["objects"] if o["role"] == "adversarial").update(mesh=str(tmp_path / "cube_mm.stl"), units="mm")
    d["episode"]["max_steps"] = max_steps
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump(d))
    (tmp_path / "attack.yaml").write_text(yaml.safe_dump(TINY_ATTACK))
    return tmp_path / "scene.yaml"


def test_a_policy_that_cannot_do_the_task_in_the_own_scene_is_told_in_one_line(tmp_path):
    from attack.optimize import AttackError
    from trials.jobs.attack import attack_job

    scene = _own_scene(tmp_path, max_steps=3)  # 3 steps: an untrained policy reaches nothing
    with pytest.raises(
        AttackError, match=r"reached the goal in none of the \d+ configurations of this scene tried for the attack part"
    ):
        attack_job(
            _policy_dir(tmp_path, straight=False),
            "quick",
            tmp_path / "attack.yaml",
            scene,
            None,
            tmp_path / "atk",
            False,
            progress=False,
            log=lambda _t: None,
            min_clean_success=0,  # the top-up's own refusal, behind the competence gate (tests/trials/cli)
        )


def test_an_explicit_pool_for_another_scene_is_refused_saying_how_to_go_on(tmp_path):
    from sim.configs import PoolError
    from trials.jobs.attack import attack_job

    policy = _policy_dir(tmp_path, straight=False)
    with pytest.raises(PoolError, match=r"made for a different scene .*omit --pool to build one"):
        attack_job(
            policy,
            "quick",
            None,
            _own_scene(tmp_path, 3),
            policy / "feasible_pool.json",
            tmp_path / "atk",
            False,
            progress=False,
            log=lambda _t: None,
        )


@pytest.mark.slow
def test_attack_run_on_an_own_scene_builds_its_task_feasible_pool(tmp_path):
    from trials.jobs.attack import attack_job

    said = []
    scene = _own_scene(tmp_path, max_steps=40)
    attack_job(
        _policy_dir(tmp_path, straight=True),
        "quick",
        tmp_path / "attack.yaml",
        scene,
        None,
        tmp_path / "atk",
        False,
        progress=False,
        log=said.append,
        min_clean_success=0,  # straight ahead reaches the goal from some starts only: below the gate's default
    )
    assert any("is for another scene; building a task-feasible pool" in t for t in said)
    pool = load_pool(tmp_path / "atk" / "feasible_pool.json", load_scene(scene))  # for the own scene, by fingerprint
    assert pool and {config_part(c.seed) for c in pool} <= {"attack", "validation"}  # never the evaluation part
    import json

    assert json.loads((tmp_path / "atk" / "run.json").read_text())["config"]["pool"].endswith("atk/feasible_pool.json")
    assert spec_fingerprint(load_scene(scene)) != spec_fingerprint(default_scene())
