"""DAgger and PPO training, resuming, clean evaluation, the task-feasible pool, the policy CLI."""

import json

import numpy as np
import pytest
import torch

from sim.configs import load_pool, sample_pool
from sim.policies.card import ActionScaling, PolicyCard
from sim.policies.checkpoint import save_checkpoint
from sim.policies.dagger import DaggerConfig, train_dagger
from sim.policies.interface import PolicyError
from sim.policies.policy import PolicyArch, VisuomotorPolicy
from sim.policies.pool import feasible_configs, write_feasible_pool
from sim.policies.presets import PRESETS, resolve_preset
from sim.policies.rollout import EnvConfig, EpisodeResults, make_env, run_episodes, set_randomization
from sim.spec import default_scene

SIZE = 64
CLEAN = EnvConfig(image_size=SIZE)
DR = EnvConfig(image_size=SIZE, light="random", background="varied", noise_std=0.02)


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    # The renderer shares the CPU; OpenMP spin-waiting on an oversubscribed CPU makes small
    # convolutions ~10x slower with 2 threads than with 1 (see benchmarks/bench_policy.py --threads).
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def spec():
    # Starts nearer the scene and shorter episodes: the same task at a test-sized cost.
    s = default_scene()
    return s.model_copy(
        update={
            "init": s.init.model_copy(update={"r_range_m": (0.25, 0.45)}),
            "episode": s.episode.model_copy(update={"max_steps": 40}),
        }
    )


@pytest.fixture(scope="module")
def env(spec):
    e = make_env(spec, DR, num_envs=8)
    yield e
    e.close()


def test_dagger_on_a_tiny_budget_beats_the_untrained_policy(env, tmp_path):
    torch.manual_seed(0)
    policy = VisuomotorPolicy(arch="small_cnn", image_size=SIZE)
    cfg = DaggerConfig(iterations=1, episodes_per_iter=16, num_envs=8, grad_steps_per_iter=100, batch_size=32, lr=2e-3)
    set_randomization(env, CLEAN)
    before = run_episodes(env, policy, range(8))
    prog = train_dagger(policy, env, cfg, DR, tmp_path, seed=0, progress=False, log=lambda *_: None)
    set_randomization(env, CLEAN)
    after = run_episodes(env, policy, range(8))
    assert prog["history"][0]["frames"] > 100
    # Closest approach to the goal, averaged over the same 8 configurations.
    assert after.min_goal_dist.mean() < 0.6 * before.min_goal_dist.mean()
    assert after.success.sum() >= before.success.sum()


def test_interrupted_dagger_resumes_and_a_different_config_is_refused(env, tmp_path):
    torch.manual_seed(0)
    cfg = DaggerConfig(iterations=1, episodes_per_iter=8, num_envs=8, grad_steps_per_iter=3, batch_size=8)
    quiet = dict(progress=False, log=lambda *_: None)
    train_dagger(VisuomotorPolicy(arch="small_cnn", image_size=SIZE), env, cfg, DR, tmp_path, fingerprint="a", **quiet)
    frames_1 = json.loads((tmp_path / "train_state" / "progress.json").read_text())["history"][0]["frames"]
    resumed = VisuomotorPolicy(arch="small_cnn", image_size=SIZE)
    prog = train_dagger(resumed, env, cfg.model_copy(update={"iterations": 2}), DR, tmp_path, fingerprint="a", **quiet)
    assert [h["iteration"] for h in prog["history"]] == [0, 1]
    assert prog["history"][1]["frames"] > frames_1  # the aggregate kept iteration 0's data
    with pytest.raises(PolicyError, match="different config"):
        train_dagger(resumed, env, cfg, DR, tmp_path, fingerprint="b", **quiet)


def test_ppo_deterministic_action_is_the_exported_policy_action(env, tmp_path):
    from sim.policies.ppo import PPOConfig, ReachVecEnv, _make_model, to_visuomotor, train_ppo

    arch = PolicyArch(arch="small_cnn", image_size=SIZE)
    cfg = PPOConfig(total_timesteps=64, num_envs=8, n_steps=8, batch_size=32, n_epochs=1, chunk_timesteps=64)
    set_randomization(env, DR)
    model = _make_model(ReachVecEnv(env, 10**7), arch, cfg, seed=0, device="cpu")
    model.learn(64)
    obs = np.ascontiguousarray(env.observe().transpose(0, 3, 1, 2))
    mean, _ = model.predict(obs, deterministic=True)
    policy = to_visuomotor(model)
    assert isinstance(policy, VisuomotorPolicy)
    assert np.allclose(np.tanh(mean), policy.act(obs.astype(np.float32) / 255), atol=1e-4)
    # The training entry point runs, checkpoints its state and resumes.
    _, prog = train_ppo(arch, env, cfg, DR, tmp_path, progress=False, log=lambda *_: None)
    _, prog = train_ppo(
        arch, env, cfg.model_copy(update={"total_timesteps": 128}), DR, tmp_path, progress=False, log=lambda *_: None
    )
    assert [h["timesteps"] for h in prog["history"]] == [64, 128]


def test_feasible_pool_holds_exactly_the_successful_configurations(spec, tmp_path):
    configs = sample_pool(spec, 5, seed=3)
    ok = np.array([True, False, True, True, False])
    res = EpisodeResults(np.arange(3, 8), ok, np.where(ok, 0, -1), np.full(5, 10), np.zeros(5), configs)
    path = write_feasible_pool(tmp_path / "pool.json", spec, res, meta={"policy": "p"})
    assert load_pool(path, spec) == feasible_configs(res) == [configs[0], configs[2], configs[3]]
    meta = json.loads(path.read_text())["meta"]
    assert meta["feasible"] == 3 and meta["episodes"] == 5 and meta["policy"] == "p"


def test_presets_resolve_and_reject_unknown_names_and_keys():
    quick = resolve_preset("quick")
    assert quick.policy.image_size == quick.env.image_size == 64 and quick.final_eval_episodes == 200
    paper = resolve_preset("paper")
    assert paper.policy.arch == "resnet18" and paper.policy.image_size == 128 and paper.target_success == 0.95
    assert resolve_preset("quick", arch="resnet34").policy.arch == "resnet34"
    assert set(PRESETS) == {"ci", "quick", "paper"}
    with pytest.raises(ValueError, match="preset"):
        resolve_preset("huge")
    with pytest.raises(ValueError, match="epochs"):
        resolve_preset("quick", dagger={"epochs": 3})
    # Run length is not part of the resume fingerprint; everything else is.
    assert resolve_preset("quick").fingerprint() == resolve_preset("quick", dagger={"iterations": 20}).fingerprint()
    assert resolve_preset("quick").fingerprint() != resolve_preset("quick", dagger={"lr": 0.1}).fingerprint()


def test_policy_cli_evaluates_and_exports_a_checkpoint(spec, tmp_path):
    from typer.testing import CliRunner

    from trials.cli.main import app

    torch.manual_seed(0)
    p = VisuomotorPolicy(arch="small_cnn", image_size=SIZE)
    ck = tmp_path / "ck"
    save_checkpoint(ck, p, PolicyCard(arch=p.config, action=ActionScaling(max_step_m=0.02, max_step_rad=0.1)))
    runner = CliRunner()
    r = runner.invoke(app, ["policy", "eval", str(ck), "--episodes", "4", "--num-envs", "4"])
    assert r.exit_code == 0, r.output
    assert "95% CI" in r.output
    doc = json.loads((ck / "eval" / "eval.json").read_text())
    assert doc["success"]["n"] == 4 and len(doc["episodes"]) == 4
    assert (ck / "eval" / "feasible_pool.json").is_file() and (ck / "eval" / "run.json").is_file()
    r = runner.invoke(app, ["policy", "export", str(ck), "--onnx", str(tmp_path / "p.onnx")])
    assert r.exit_code == 0, r.output
    assert "max |onnx - torch|" in r.output
    r = runner.invoke(app, ["policy", "eval", str(tmp_path / "p.onnx"), "--episodes", "4", "--num-envs", "4"])
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "p-eval" / "eval.json").read_text())["success"]["n"] == 4


@pytest.mark.parametrize("keep", [False, True])
def test_a_finished_training_drops_its_resume_data_unless_kept(spec, tmp_path, keep):
    from sim.policies.checkpoint import load_checkpoint
    from sim.policies.train import train_policy

    cfg = resolve_preset(
        "ci",
        dagger={"iterations": 1, "episodes_per_iter": 8, "num_envs": 8, "grad_steps_per_iter": 2},
        final_eval_episodes=2,
        policy={"arch": "small_cnn", "image_size": SIZE},
        env={"image_size": SIZE},
    )
    said = []
    train_policy(cfg, tmp_path, spec, progress=False, log=said.append, keep_state=keep)
    assert (tmp_path / "train_state").is_dir() == keep
    assert any("deleted" in t and "train_state" in t for t in said) != keep
    load_checkpoint(tmp_path)  # the final weights and card stay either way


def test_the_contract_fields_leave_existing_training_runs_resumable_and_other_contracts_are_refused():
    # pinned before PolicyArch had state_dim/chunk/output: a run started then still resumes
    assert resolve_preset("quick").fingerprint() == "c7daca81a8f8215c"
    assert resolve_preset("paper").fingerprint() == "621206d1b93d6cda"
    with pytest.raises(ValueError, match="one-image delta_tcp contract only"):
        resolve_preset("quick", policy={"chunk": 4})
