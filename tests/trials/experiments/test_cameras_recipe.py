"""The ``cameras`` recipe on a CI-sized budget: which camera carries the attack against a two-camera policy.

An untrained two-camera policy (wrist 32 px + the two-camera scene's 128 px front camera) is
attacked with two attack seeds of one iteration each; every texture is evaluated with the texture
in both cameras, the wrist camera only and the front camera only, on the same configurations.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
import typer

from sim.configs import sample_pool, save_pool
from sim.spec import load_spec
from tests.trials.conftest import MAX_STEPS
from trials.eval.episodes import read_rows
from trials.experiments.recipes import (
    RECIPES,
    TWO_CAMERA_SCENE,
    Context,
    ExperimentError,
    ensure_policy,
    resolve_experiment,
    run_experiment,
)

TINY_ATTACK = {
    "iterations": 1,
    "num_envs": 1,
    "rollout_steps": 1,
    "texture_size": 8,
    "pool_size": 4,
    "checkpoint_every": 1,
    "validation_every": 0,
}
CONDITIONS = {"clean", "attack", "attack_wrist_only", "attack_front_only"}


@pytest.fixture(scope="module")
def two_camera_dir(tmp_path_factory):
    from sim.policies.card import ActionScaling, PolicyCard
    from sim.policies.checkpoint import save_checkpoint
    from sim.policies.policy import PolicyArch, VisuomotorPolicy

    torch.manual_seed(0)
    arch = PolicyArch(arch="small_cnn", image_size=32, cameras=("wrist", "front"), camera_px={"front": (128, 128)})
    policy = VisuomotorPolicy(arch)
    d = tmp_path_factory.mktemp("two-camera-policy")
    save_checkpoint(d, policy, PolicyCard(arch=arch, action=ActionScaling(max_step_m=0.02, max_step_rad=0.1)))
    return d


@pytest.fixture(scope="module")
def two_camera_pool(tmp_path_factory):
    spec = load_spec(TWO_CAMERA_SCENE)
    spec = spec.with_updates(episode={**spec.episode.model_dump(), "max_steps": MAX_STEPS})
    path = tmp_path_factory.mktemp("pool") / "pool.json"
    save_pool(path, spec, sample_pool(spec, 8, seed=0, part="evaluation"))
    return path


def _cfg(pool, **kw):
    return resolve_experiment(
        "quick",
        attack_overrides=TINY_ATTACK,
        episodes=2,
        max_steps=MAX_STEPS,
        num_envs=2,
        gifs=0,
        pool=None if pool is None else str(pool),
        **kw,
    )


def test_the_cameras_recipe_evaluates_every_seeds_texture_in_both_cameras_and_in_each_alone(
    tmp_path, two_camera_dir, two_camera_pool
):
    path = run_experiment(
        "cameras",
        _cfg(two_camera_pool, attack_seeds=(0, 1)),
        tmp_path,
        policy=two_camera_dir,
        progress=False,
        log=lambda m: None,
    )
    # the recipe's own scene, recorded: the two-camera scene without --scene
    assert json.loads((tmp_path / "run.json").read_text())["config"]["scene"] == TWO_CAMERA_SCENE
    assert sorted(p.name for p in (tmp_path / "attacks").iterdir()) == ["c2f", "c2f-seed1"]
    seeds = {}
    for name in ("cameras", "cameras-seed1"):
        summary = json.loads((tmp_path / "evals" / name / "summary.json").read_text())
        assert set(summary["conditions"]) == CONDITIONS
        rows = read_rows(tmp_path / "evals" / name)
        assert {r["condition"] for r in rows} == CONDITIONS
        by = {c: sorted(r["seed"] for r in rows if r["condition"] == c) for c in CONDITIONS}
        assert len({tuple(v) for v in by.values()}) == 1  # every condition on the same configurations
        seeds[name] = by["attack"]
    assert seeds["cameras"] == seeds["cameras-seed1"] and len(seeds["cameras"]) == 2
    text = path.read_text()
    assert "# Which camera carries the attack: a policy reading wrist, front" in text
    for cond, seen in (("attack", "wrist, front"), ("attack_wrist_only", "wrist"), ("attack_front_only", "front")):
        assert f"| {cond} | {seen} |" in text
    # paired McNemar between every two conditions, for every attack seed
    for seed in (0, 1):
        for a, b in (
            ("attack", "attack_wrist_only"),
            ("attack", "attack_front_only"),
            ("attack_wrist_only", "attack_front_only"),
        ):
            assert f"| {seed} | {a} | {b} | 2 |" in text
    assert "**attack_wrist_only vs attack_front_only** (claim: attack_wrist_only > attack_front_only in T-ASR)" in text
    assert "T-ASR per attack seed (2 independent attack runs per arm" in text and "| attack_front_only |" in text


def test_the_cameras_recipe_refuses_a_scene_or_policy_without_the_cameras_before_writing(
    tmp_path, tiny_policy_dir, two_camera_dir, two_camera_pool
):
    out = tmp_path / "out"
    with pytest.raises(ExperimentError, match="--scene: unknown camera 'front'; this scene has: wrist"):
        run_experiment("cameras", _cfg(None), out, scene="sim/data/default_scene.yaml")
    with pytest.raises(ExperimentError, match="--policy: .* reads the wrist camera only"):
        run_experiment("cameras", _cfg(two_camera_pool), out, policy=tiny_policy_dir)
    with pytest.raises(ExperimentError, match="--policy: .*unknown camera 'front'; this scene has: wrist"):
        run_experiment("cameras", _cfg(None), out, policy=two_camera_dir, scene="sim/data/default_scene.yaml")
    assert not out.exists()


def test_without_a_policy_the_recipe_trains_a_two_camera_policy_on_the_two_camera_scene(tmp_path):
    ctx = Context(_cfg(None), tmp_path, scene=TWO_CAMERA_SCENE, progress=False, log=lambda m: None)
    d = ensure_policy(ctx, cameras=("wrist", "front"))
    (job,) = [j for j in ctx.grid.jobs.values() if j.kind == "train-policy"]
    assert Path(job.out).resolve() == d.resolve()
    assert job.params["cameras"] == ["wrist", "front"] and job.params["preset"] == "quick"
    assert job.inputs["scene"].endswith(TWO_CAMERA_SCENE)
    # a one-camera policy's job keeps the key it had before cameras existed (finished ones are reused)
    other = Context(_cfg(None), tmp_path / "b", progress=False, log=lambda m: None)
    ensure_policy(other)
    (job,) = [j for j in other.grid.jobs.values() if j.kind == "train-policy"]
    assert "cameras" not in job.params


def test_the_evidence_tool_passes_and_records_the_recipes_scene(tmp_path, monkeypatch):
    from tools import evidence
    from trials.cli.experiment import app as experiment_app
    from trials.experiments import record

    monkeypatch.setattr(record, "git_commit", lambda: "0123abc")
    ran = []
    monkeypatch.setattr(record.subprocess, "call", lambda cmd, **k: ran.append(cmd) or 1)  # no run: nothing collected
    extra = ["--attack-seeds", "0,1,2", "--workers", "2"]
    rc = evidence.run("cameras", 300, "runs/policy-two-camera", tmp_path / "work", tmp_path / "results", extra)
    assert rc == 1 and RECIPES["cameras"].scene == TWO_CAMERA_SCENE
    (cmd,) = ran
    assert cmd[1:3] == ["experiment", "cameras"] and cmd[cmd.index("--scene") + 1] == TWO_CAMERA_SCENE
    assert cmd[-4:] == extra and cmd[cmd.index("--episodes") + 1] == "300"
    recorded = json.loads((tmp_path / "results" / "cameras" / "run.json").read_text())["attempts"][0]["command"]
    assert f"--scene {TWO_CAMERA_SCENE}" in recorded
    # every option of the command is one of the recipe command's
    command = typer.main.get_command(experiment_app).commands["cameras"]
    flags = {o for p in command.params for o in p.opts}
    assert {a for a in cmd[3:] if a.startswith("--")} <= flags
    # a --scene given after "--" is the one used
    ran.clear()
    evidence.run("cameras", 10, None, tmp_path / "work", tmp_path / "results", ["--scene", "my.yaml"])
    assert ran[0].count("--scene") == 1 and ran[0][ran[0].index("--scene") + 1] == "my.yaml"


def test_a_sharded_two_camera_evaluation_merges_every_condition_of_every_camera(
    tmp_path, two_camera_dir, two_camera_pool
):
    """The evaluations in shards (as ``--workers`` runs them) and their merge, which has no policy to
    check the cameras with: it once refused every camera but the wrist camera at the merge."""
    run_experiment(
        "cameras",
        _cfg(two_camera_pool, attack_seeds=(0,)),
        tmp_path,
        policy=two_camera_dir,
        progress=False,
        log=lambda m: None,
        shards=2,
    )
    d = tmp_path / "evals" / "cameras"
    assert sorted(p.name for p in (d / "shards").iterdir()) == ["0-of-2", "1-of-2"]
    assert set(json.loads((d / "summary.json").read_text())["conditions"]) == CONDITIONS
    rows = read_rows(d)
    by = {c: sorted(r["seed"] for r in rows if r["condition"] == c) for c in CONDITIONS}
    assert len({tuple(v) for v in by.values()}) == 1 and len(by["attack"]) == 2  # both shards' configurations
