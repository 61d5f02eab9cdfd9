"""Recipe orchestration on a tiny budget: attacks run via attack_job, evaluations, tables with the paper's numbers."""

import json

import pytest

from tests.trials.conftest import MAX_STEPS
from trials.eval.episodes import read_rows
from trials.experiments.recipes import PAPER, ExperimentError, resolve_experiment, run_experiment

TINY_ATTACK = {
    "iterations": 1,
    "num_envs": 1,
    "rollout_steps": 1,
    "texture_size": 8,
    "pool_size": 4,
    "checkpoint_every": 1,
    "validation_every": 0,
}  # held-out validation is covered in tests/attack/test_best.py


def _cfg(pool_file, **kw):
    return resolve_experiment(
        "quick",
        attack_overrides=TINY_ATTACK,
        episodes=2,
        max_steps=MAX_STEPS,
        num_envs=2,
        gifs=0,
        pool=str(pool_file),
        **kw,
    )


def test_table1_runs_the_3d_and_patch_attacks_then_writes_the_paper_layout(tmp_path, tiny_policy_dir, pool_file):
    log = []
    path = run_experiment("table1", _cfg(pool_file), tmp_path, policy=tiny_policy_dir, progress=False, log=log.append)
    text = path.read_text()
    assert "| 2D Patch | paper | 73.00 | 77.00" in text and "| 3D Object | paper | 78.00 | 79.00" in text
    assert "| 3D Object | ours |" in text and "70-90 T-ASR" in text
    # the overall 3D-vs-patch verdict opens the per-phi and the per-distance section: printed once
    assert text.count("**3D vs patch** (claim: ") == 1 and "## Paired T-ASR test by initial distance r" in text
    assert (
        json.loads((tmp_path / "attacks" / "patch" / "run.json").read_text())["config"]["attack"]["adversarial_mesh"]
        == "patch"
    )
    summary = json.loads((tmp_path / "evals" / "table1" / "summary.json").read_text())
    assert set(summary["conditions"]) == {"clean", "attack", "patch"} and summary["conditions"]["patch"]["n"] == 2
    # a second run reuses every finished piece
    log.clear()
    run_experiment("table1", _cfg(pool_file), tmp_path, policy=tiny_policy_dir, progress=False, log=log.append)
    assert any("attack-c2f: finished earlier, reused" in m for m in log) and any(
        "attack-patch: finished earlier, reused" in m for m in log
    )


@pytest.mark.slow
def test_table2_runs_six_attack_variants_and_reports_errors_by_distance(tmp_path, tiny_policy_dir, pool_file):
    path = run_experiment(
        "table2", _cfg(pool_file), tmp_path, policy=tiny_policy_dir, progress=False, log=lambda m: None
    )
    text = path.read_text()
    for key in PAPER["table2"]:
        assert (tmp_path / "attacks" / key / "texture.npy").is_file()
    run = json.loads((tmp_path / "attacks" / "c2f_untargeted" / "run.json").read_text())["config"]["attack"]
    assert run["loss"] == "untargeted" and run["iterations"] == 1
    assert "| (f) | C2F | x | x | x | ours |" in text and "0.53 | 0.066" in text


@pytest.mark.slow
def test_table3_and_transfer_orchestrate_shapes_conditions_and_targets(tmp_path, tiny_policy_dir, pool_file):
    p3 = run_experiment(
        "table3",
        _cfg(pool_file, shapes=("duck",)),
        tmp_path / "t3",
        policy=tiny_policy_dir,
        progress=False,
        log=lambda m: None,
    )
    t3 = p3.read_text()
    for label in ("Shape: Duck", "Stereo Cam", "Light: Bright", "Light: Dim", "Add Noise", "Bkg Varied"):
        assert f"| {label} |" in t3
    targets = {a: tiny_policy_dir for a in ("resnet34", "vgg16", "inception_v3")}
    pt = run_experiment(
        "transfer",
        _cfg(pool_file),
        tmp_path / "tr",
        policy=tiny_policy_dir,
        targets=targets,
        progress=False,
        log=lambda m: None,
    )
    assert "| vgg16 | black-box target |" in pt.read_text() and "59.68" in pt.read_text()


def test_recipe_inputs_are_validated(tmp_path, tiny_policy_dir):
    with pytest.raises(ExperimentError, match="unknown experiment"):
        run_experiment("table9", resolve_experiment("quick"), tmp_path)
    with pytest.raises(ExperimentError, match="preset"):
        resolve_experiment("huge")
    with pytest.raises(ExperimentError, match="episodes"):
        resolve_experiment("quick", episodes=0)
    with pytest.raises(ExperimentError, match="--target"):
        run_experiment("transfer", resolve_experiment("quick"), tmp_path, targets={"alexnet": tiny_policy_dir})


def test_attack_seeds_are_independent_runs_evaluated_on_the_same_configurations(tmp_path, tiny_policy_dir, pool_file):
    path = run_experiment(
        "table2",
        _cfg(pool_file, attack_seeds=(0, 3), rows=("c2f", "ns")),
        tmp_path,
        policy=tiny_policy_dir,
        progress=False,
        log=lambda m: None,
    )
    # seed 0 keeps the single-seed names (reused by earlier runs); other seeds get their own folders
    assert sorted(p.name for p in (tmp_path / "attacks").iterdir()) == ["c2f", "c2f-seed3", "ns", "ns-seed3"]
    run = json.loads((tmp_path / "attacks" / "ns-seed3" / "run.json").read_text())
    assert run["config"]["attack"]["seed"] == 3 and run["config"]["attack"]["schedule"] == "ns"
    assert json.loads((tmp_path / "attacks" / "ns" / "run.json").read_text())["config"]["attack"]["seed"] == 0
    seeds = {
        d: sorted(r["seed"] for r in read_rows(tmp_path / "evals" / d)) for d in ("table2_c2f", "table2_c2f-seed3")
    }
    assert seeds["table2_c2f"] == seeds["table2_c2f-seed3"] and seeds["table2_c2f"]
    text = path.read_text()
    assert "T-ASR per attack seed (2 independent attack runs per arm" in text
    assert "| c2f |" in text and "| ns |" in text and "f2c" not in text.split("T-ASR per attack seed")[1]


def test_attack_seeds_and_rows_are_validated():
    with pytest.raises(ExperimentError, match="distinct"):
        resolve_experiment("quick", attack_seeds=(1, 1))
    with pytest.raises(ExperimentError, match="unknown Table II row 'nope'"):
        resolve_experiment("quick", rows=("nope",))
