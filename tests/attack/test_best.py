"""Anytime quality: held-out validation, the best/ directory and evaluation-ready checkpoints."""

import json

import numpy as np
import pytest
import torch

from attack.optimize import AttackError, AttackRun, AttackWarning, resolve_config, run_attack
from attack.state import better_score, find_checkpoint
from sim.configs import config_part, sample_pool
from sim.policies.policy import VisuomotorPolicy
from sim.spec import default_scene
from trials.eval.conditions import load_attack_source

CFG = {
    "iterations": 6,
    "num_envs": 2,
    "rollout_steps": 2,
    "texture_size": 16,
    "checkpoint_every": 2,
    "lr": 0.5,
    "validation_every": 1,
    "validation_episodes": 2,
    "validation_max_steps": 3,
}


def _policy():
    torch.manual_seed(0)
    return VisuomotorPolicy(arch="small_cnn", image_size=32)


@pytest.fixture(scope="module")
def spec_pool():
    spec = default_scene()
    # 6 configurations of the attack part and 2 of the validation part (sim.configs.config_part)
    return spec, sample_pool(spec, 6, seed=5, part="attack") + sample_pool(spec, 2, seed=5, part="validation")


def _scripted(run, scores):
    """Replace the rollout by a scripted score per call; remembers the texture each call saw."""
    seen = []

    def validate():
        t_asr, dist = scores[len(seen)]
        seen.append(run.state.texture.detach().clone())
        return {"t_asr": t_asr, "dist_m": dist, "episodes": 2, "seconds": 0.0}

    run.validate = validate
    return seen


def test_a_pool_short_of_validation_configurations_validates_on_what_it_has_and_says_so(spec_pool):
    spec, pool = spec_pool
    with pytest.warns(
        AttackWarning, match="only 2 configurations of the validation part; validating on 2 instead of 16"
    ):
        run = AttackRun(_policy(), spec, resolve_config("quick", {**CFG, "validation_episodes": 16}), pool=pool)
    assert len(run.val_pool) == 2 and len(run.pool) == 6
    run.close()
    with pytest.raises(AttackError, match="no configuration of the validation part"):
        AttackRun(
            _policy(), spec, resolve_config("quick", CFG), pool=[c for c in pool if config_part(c.seed) == "attack"]
        )
    with pytest.raises(AttackError, match="attack part"):
        AttackRun(
            _policy(), spec, resolve_config("quick", CFG), pool=[c for c in pool if config_part(c.seed) == "validation"]
        )


def test_a_pool_of_evaluation_configurations_is_never_attacked_or_validated_on(spec_pool):
    spec, pool = spec_pool
    evaluation = sample_pool(spec, 5, seed=5, part="evaluation")
    run = AttackRun(_policy(), spec, resolve_config("quick", CFG), pool=pool + evaluation)
    try:
        used = {c.seed for c in run.pool} | {c.seed for c in run.val_pool}
        assert used == {c.seed for c in pool} and not used & {c.seed for c in evaluation}
    finally:
        run.close()


def test_run_trains_only_on_configurations_outside_the_validation_pool(spec_pool):
    spec, pool = spec_pool
    run = AttackRun(_policy(), spec, resolve_config("quick", CFG), pool=pool)
    try:
        assert len(run.val_pool) == 2 and len(run.pool) == 6 and len(run.source.pool_r) == 6
        assert not {c.seed for c in run.pool} & {c.seed for c in run.val_pool}
    finally:
        run.close()


def test_score_order():
    assert better_score({"t_asr": 0.5, "dist_m": 0.3}, {"t_asr": 0.25, "dist_m": 0.1})
    assert better_score({"t_asr": 0.5, "dist_m": 0.1}, {"t_asr": 0.5, "dist_m": 0.2})
    assert not better_score({"t_asr": 0.5, "dist_m": 0.2}, {"t_asr": 0.5, "dist_m": 0.2})
    assert not better_score({"t_asr": 0.25, "dist_m": 0.0}, {"t_asr": 0.5, "dist_m": 0.9})


def test_best_is_replaced_only_when_the_validation_score_improves(tmp_path, spec_pool):
    spec, pool = spec_pool
    # call k validates the texture after k iterations; best: call 0, 2 (higher T-ASR), 4 (tie, closer)
    scores = [(0.0, 0.4), (0.0, 0.5), (0.5, 0.3), (0.0, 0.1), (0.5, 0.2), (0.5, 0.2)]
    run = AttackRun(_policy(), spec, resolve_config("quick", {**CFG, "iterations": 5}), pool=pool, out_dir=tmp_path)
    seen = _scripted(run, scores)
    run_attack(run, progress=False)
    run.close()
    info = json.loads((tmp_path / "best" / "best.json").read_text())
    assert info["iteration"] == 4 and info["t_asr"] == 0.5 and info["dist_m"] == 0.2
    best = np.load(tmp_path / "best" / "texture.npy")
    assert np.array_equal(best, seen[4].permute(1, 2, 0).numpy())
    assert not np.array_equal(best, seen[5].permute(1, 2, 0).numpy())  # the final texture moved on
    assert run.state.history.val_iteration == list(range(6)) and run.state.history.val_t_asr == [s[0] for s in scores]
    assert not (tmp_path / "best.tmp").exists() and not (tmp_path / "best.old").exists()


def test_best_and_checkpoint_are_evaluation_sources(tmp_path, spec_pool):
    spec, pool = spec_pool
    run = AttackRun(_policy(), spec, resolve_config("quick", {**CFG, "iterations": 2}), pool=pool, out_dir=tmp_path)
    _scripted(run, [(0.0, 0.3), (0.5, 0.3), (0.0, 0.3)])
    run_attack(run, progress=False)
    run.close()
    for d in ("best", "checkpoint"):
        src = load_attack_source(tmp_path / d)
        assert src.mesh is None and src.texture.shape == (16, 16, 3) and src.texture.dtype == np.uint8
    ck = np.load(tmp_path / "checkpoint" / "texture.npy")
    assert ck.dtype == np.float32 and np.array_equal(ck, run.state.texture.permute(1, 2, 0).numpy())


def test_resume_keeps_best(tmp_path, spec_pool):
    spec, pool = spec_pool
    cfg = resolve_config("quick", {**CFG, "checkpoint_every": 3, "iterations": 5})
    part = AttackRun(_policy(), spec, cfg, pool=pool, out_dir=tmp_path)
    _scripted(part, [(0.0, 0.3), (0.5, 0.3), (0.0, 0.3), (0.0, 0.3), (1.0, 0.1)])
    real_step = part.step

    def step_or_crash():
        if part.state.iteration == 4:  # best/ was written at iteration 4, the checkpoint at 3: crash
            raise RuntimeError("power cut")
        return real_step()

    part.step = step_or_crash
    with pytest.raises(RuntimeError):
        run_attack(part, progress=False)
    part.close()
    assert json.loads((tmp_path / "checkpoint" / "state.json").read_text())["best"]["iteration"] == 1
    assert json.loads((tmp_path / "best" / "best.json").read_text())["iteration"] == 4

    resumed = AttackRun(_policy(), spec, cfg, pool=pool, out_dir=tmp_path)
    resumed.load_checkpoint(find_checkpoint(tmp_path))
    assert resumed.state.iteration == 3 and resumed.state.best["iteration"] == 4 and resumed.state.best["t_asr"] == 1.0
    on_disk = torch.from_numpy(np.load(tmp_path / "best" / "texture.npy")).permute(2, 0, 1)
    assert torch.equal(resumed.state.best_texture, on_disk)
    # Replay: iteration 4 scores the same again (not better), 5 is worse.
    _scripted(resumed, [(1.0, 0.1), (0.5, 0.0)])
    run_attack(resumed, progress=False)
    resumed.close()
    assert json.loads((tmp_path / "best" / "best.json").read_text())["iteration"] == 4
    assert torch.equal(torch.from_numpy(np.load(tmp_path / "best" / "texture.npy")).permute(2, 0, 1), on_disk)
    assert resumed.state.history.val_iteration == [0, 1, 2, 3, 4, 5]

    # best/ deleted by hand: the checkpoint still carries the best texture it knew of.
    import shutil

    shutil.rmtree(tmp_path / "best")
    again = AttackRun(_policy(), spec, cfg, pool=pool, out_dir=tmp_path)
    again.load_checkpoint(find_checkpoint(tmp_path))
    assert again.state.best["iteration"] == 4 and torch.equal(again.state.best_texture, on_disk)
    again.close()


def test_real_validation_is_deterministic_and_leaves_the_training_rng_alone(spec_pool):
    spec, pool = spec_pool
    run = AttackRun(_policy(), spec, resolve_config("quick", CFG), pool=pool)
    try:
        state = run.state.rng.bit_generator.state
        a, b = run.validate(), run.validate()
        assert run.state.rng.bit_generator.state == state
        assert a["episodes"] == 2 and 0.0 <= a["t_asr"] <= 1.0 and np.isfinite(a["dist_m"]) and a["dist_m"] >= 0
        assert (a["t_asr"], a["dist_m"]) == (b["t_asr"], b["dist_m"])
    finally:
        run.close()


def test_validation_off_keeps_the_whole_pool_and_writes_no_best(tmp_path, spec_pool):
    spec, pool = spec_pool
    run = AttackRun(
        _policy(),
        spec,
        resolve_config("quick", {**CFG, "validation_every": 0, "iterations": 2}),
        pool=pool,
        out_dir=tmp_path,
    )
    assert resolve_config("quick").validation_every > 0 and resolve_config("paper").validation_every > 0
    run_attack(run, progress=False)
    run.close()
    assert len(run.pool) == 6 and not run.state.history.val_iteration and not (tmp_path / "best").exists()
    assert (tmp_path / "checkpoint" / "texture.npy").is_file()


def test_attack_and_validation_render_at_the_policy_size(spec_pool):
    spec, pool = spec_pool
    run = AttackRun(_policy(), spec, resolve_config("quick", CFG), pool=pool)
    try:
        assert spec.camera.width == 128 and run.image_size == 32
        cap = run.hybrid.capture(run.env.worlds[0])
        assert cap.i_sim.shape == (32, 32, 3) and (cap.fragments.height, cap.fragments.width) == (32, 32)
        run.validate()
        assert (run._val_env.height, run._val_env.width) == (32, 32)
    finally:
        run.close()


def test_the_probe_pose_loss_is_logged_at_each_validation_and_repeats_for_the_same_texture(spec_pool):
    spec, pool = spec_pool
    run = AttackRun(_policy(), spec, resolve_config("quick", {**CFG, "iterations": 2}), pool=pool)
    try:
        a, b = run.probe_pose_loss(), run.probe_pose_loss()
        assert np.isfinite(a) and a == b
        run_attack(run, progress=False)
        assert len(run.state.history.val_probe_pose) == len(run.state.history.val_iteration) == 3
        assert run.state.history.val_probe_pose[0] == a
    finally:
        run.close()
    off = AttackRun(_policy(), spec, resolve_config("quick", {**CFG, "use_pose": False}), pool=pool)
    assert np.isnan(off.probe_pose_loss())
    off.close()
