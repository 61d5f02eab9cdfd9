"""Held-out evaluation by construction: attacks never see evaluation configurations, and an
evaluation refuses a texture that was optimised or selected on its own configurations."""

import json
import shutil

import pytest

from attack.artifact import read_config_record, write_config_record
from sim.configs import config_id, config_part, load_pool, sample_pool, save_pool
from sim.spec import default_scene
from tests.trials.conftest import MAX_STEPS, make_attack_dir
from trials.eval.evaluate import EvalError, load_eval_config, run_eval

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


@pytest.fixture()
def policy_with_pool(tmp_path, tiny_policy_dir):
    """A policy directory with a feasible_pool.json over seeds 0..79 of every part, as 'policy train' writes."""
    d = tmp_path / "policy"
    shutil.copytree(tiny_policy_dir, d)
    spec = default_scene()
    save_pool(d / "feasible_pool.json", spec, sample_pool(spec, 80, seed=0))
    return d


def _eval_ids(eval_dir):
    from sim.configs import sample_config

    spec = default_scene()
    seeds = json.loads((eval_dir / "manifest.json").read_text())["config"]["seeds"]
    return {config_id(sample_config(spec, s)) for s in seeds}


def test_an_evaluation_refuses_a_texture_optimised_on_its_configurations_unless_allowed(
    tmp_path, tiny_policy_dir, short_spec, pool_file
):
    evaluation = load_pool(pool_file, short_spec)
    leaky = make_attack_dir(tmp_path / "leaky")
    write_config_record(leaky, evaluation[:3], [])  # trained on three of the evaluation's configurations
    cfg = load_eval_config(
        policy=str(tiny_policy_dir),
        conditions=("attack",),
        episodes=4,
        max_steps=MAX_STEPS,
        num_envs=2,
        pool=str(pool_file),
        attack=str(leaky),
        gifs=0,
    )
    with pytest.raises(
        EvalError, match=r"optimised or selected on 3 of the 4 evaluation configurations.*--allow-overlap"
    ):
        run_eval(cfg, tmp_path / "refused", progress=False, report=False)
    assert not (tmp_path / "refused" / "episodes.csv").exists()

    run_eval(cfg.model_copy(update={"allow_overlap": True}), tmp_path / "allowed", progress=False)
    manifest = json.loads((tmp_path / "allowed" / "manifest.json").read_text())
    assert manifest["config"]["overlap"] == {"attack": 3}
    assert "`attack` 3" in (tmp_path / "allowed" / "report.md").read_text()


def test_the_eval_cli_refuses_an_overlap_in_one_line(
    tmp_path, tiny_policy_dir, short_spec, pool_file, monkeypatch, capsys
):
    from trials.cli.main import main

    leaky = make_attack_dir(tmp_path / "leaky")
    write_config_record(leaky, [], load_pool(pool_file, short_spec)[:1])  # selected on one of them
    monkeypatch.setattr(
        "sys.argv",
        [
            "advobj",
            "eval",
            "--policy",
            str(tiny_policy_dir),
            "--attack",
            str(leaky),
            "--episodes",
            "2",
            "--max-steps",
            str(MAX_STEPS),
            "--num-envs",
            "2",
            "--pool",
            str(pool_file),
            "--gifs",
            "0",
            "--out",
            str(tmp_path / "ev"),
        ],
    )
    with pytest.raises(SystemExit) as exc:
        main()
    err = capsys.readouterr().err
    lines = [l for l in err.splitlines() if l.strip()]
    assert exc.value.code == 2 and len(lines) == 1 and "--allow-overlap" in lines[0] and "Traceback" not in err


def test_an_evaluation_uses_only_the_evaluation_part_of_any_pool(tmp_path, tiny_policy_dir, short_spec):
    mixed = tmp_path / "mixed.json"
    save_pool(mixed, short_spec, sample_pool(short_spec, 40, seed=0))
    cfg = load_eval_config(
        policy=str(tiny_policy_dir),
        conditions=("clean",),
        episodes=5,
        max_steps=MAX_STEPS,
        num_envs=2,
        pool=str(mixed),
        gifs=0,
    )
    run_eval(cfg, tmp_path / "ev", progress=False, report=False)
    seeds = json.loads((tmp_path / "ev" / "manifest.json").read_text())["config"]["seeds"]
    assert len(seeds) == 5 and {config_part(s) for s in seeds} == {"evaluation"}


def test_default_attack_then_eval_gives_overlap_0_and_records_what_the_attack_saw(tmp_path, policy_with_pool):
    import yaml

    from trials.jobs.attack import attack_job

    cfg_path = tmp_path / "attack.yaml"
    cfg_path.write_text(yaml.safe_dump(TINY_ATTACK))
    attack_job(policy_with_pool, "quick", cfg_path, None, None, tmp_path / "atk", False, progress=False)
    record = json.loads((tmp_path / "atk" / "configs.json").read_text())
    assert {config_part(e["seed"]) for e in record["attack"]} == {"attack"}
    assert {config_part(e["seed"]) for e in record["validation"]} == {"validation"} and len(record["validation"]) == 2
    cfg = load_eval_config(
        policy=str(policy_with_pool),
        conditions=("attack",),
        episodes=3,
        num_envs=3,
        attack=str(tmp_path / "atk"),
        gifs=0,
    )
    run_eval(cfg, tmp_path / "ev", progress=False, report=False)
    manifest = json.loads((tmp_path / "ev" / "manifest.json").read_text())["config"]
    assert manifest["overlap"] == {"attack": 0}
    assert not _eval_ids(tmp_path / "ev") & read_config_record(tmp_path / "atk")
    assert read_config_record(tmp_path / "atk" / "best") == read_config_record(
        tmp_path / "atk"
    )  # best/ uses its run's record


@pytest.mark.parametrize("recipe", ["table1", "table2", "table3", "transfer", "lighting"])
def test_every_recipe_on_its_default_paths_gives_overlap_0(tmp_path, policy_with_pool, recipe, monkeypatch):
    import trials.experiments.recipes as ex

    # One attack and one short evaluation per recipe keeps this fast; the orchestration is the real one.
    monkeypatch.setattr(ex, "TABLE2_ROWS", ex.TABLE2_ROWS[:1])
    # The policy's pool is made for the scene's own episode length, so the evaluations use it too.
    cfg = ex.resolve_experiment(
        "quick",
        attack_overrides=TINY_ATTACK,
        episodes=2,
        num_envs=2,
        gifs=0,
        shapes=("duck",),
        transfer_targets=("vgg16",),
    )
    targets = {"vgg16": policy_with_pool} if recipe == "transfer" else None
    ex.run_experiment(
        recipe, cfg, tmp_path / "out", policy=policy_with_pool, targets=targets, progress=False, log=lambda m: None
    )
    manifests = list((tmp_path / "out" / "evals").glob("*/manifest.json"))
    assert manifests
    for m in manifests:
        overlap = json.loads(m.read_text())["config"]["overlap"]
        assert overlap and set(overlap.values()) == {0}, (m, overlap)


def test_the_demo_gives_overlap_0(tmp_path, policy_with_pool, monkeypatch):
    import trials.experiments.demo as demo
    import trials.experiments.recipes as ex

    monkeypatch.setattr(demo, "DEMO_BUDGET", dict(attack_overrides=TINY_ATTACK, episodes=2, num_envs=2, gifs=0))
    for mod in (ex, demo):  # demo binds ensure_policy at import
        monkeypatch.setattr(mod, "ensure_policy", lambda ctx, name="reference", **kw: policy_with_pool)
    demo.run_demo(tmp_path / "demo", log=lambda m: None)
    overlap = json.loads((tmp_path / "demo" / "evals" / "demo" / "manifest.json").read_text())["config"]["overlap"]
    assert overlap == {"attack": 0, "patch": 0}


def test_an_evaluation_finds_a_leak_by_pose_when_the_seeds_differ(tmp_path, tiny_policy_dir, short_spec, pool_file):
    """The check compares configuration content: the evaluation's poses recorded under other seeds
    (other content ids) are still an overlap."""
    import dataclasses

    evaluation = load_pool(pool_file, short_spec)
    twins = [dataclasses.replace(c, seed=10**7 + i) for i, c in enumerate(evaluation[:2])]
    leaky = make_attack_dir(tmp_path / "leaky")
    write_config_record(leaky, twins, [])
    cfg = load_eval_config(
        policy=str(tiny_policy_dir),
        conditions=("attack",),
        episodes=4,
        max_steps=MAX_STEPS,
        num_envs=2,
        pool=str(pool_file),
        attack=str(leaky),
        gifs=0,
    )
    with pytest.raises(EvalError, match=r"optimised or selected on 2 of the 4 evaluation configurations"):
        run_eval(cfg, tmp_path / "refused", progress=False, report=False)
