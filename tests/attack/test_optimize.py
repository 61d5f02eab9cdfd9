"""The attack loop: resume reaches the same texture, black-box policies are refused, outputs exist."""

import json

import pytest
import torch

from attack.optimize import AttackRun, resolve_config, run_attack
from attack.state import find_checkpoint
from sim.configs import sample_pool
from sim.policies.interface import WhiteBoxRequired
from sim.policies.policy import VisuomotorPolicy
from sim.spec import default_scene

CFG = {
    "iterations": 4,
    "num_envs": 2,
    "rollout_steps": 2,
    "texture_size": 16,
    "checkpoint_every": 2,
    "pool_size": 8,
    "lr": 0.5,
    "validation_every": 0,
}  # validation: tests/attack/test_best.py


def _policy():
    torch.manual_seed(0)
    return VisuomotorPolicy(arch="small_cnn", image_size=32)


@pytest.fixture(scope="module")
def spec_pool():
    spec = default_scene()
    return spec, sample_pool(spec, 8, seed=5, part="attack")


def test_resume_reaches_the_same_final_texture(tmp_path, spec_pool):
    spec, pool = spec_pool
    cfg = resolve_config("quick", CFG)
    full = AttackRun(_policy(), spec, cfg, pool=pool, out_dir=tmp_path / "full")
    run_attack(full, progress=False)
    full.close()

    part = AttackRun(_policy(), spec, cfg, pool=pool, out_dir=tmp_path / "part")
    part.step()
    part.step()
    part.save_checkpoint()
    part.close()  # "crash" after iteration 2

    resumed = AttackRun(_policy(), spec, cfg, pool=pool, out_dir=tmp_path / "part")
    resumed.load_checkpoint(find_checkpoint(tmp_path / "part"))
    assert resumed.state.iteration == 2
    run_attack(resumed, progress=False)
    resumed.close()
    assert torch.equal(full.state.texture, resumed.state.texture)
    assert full.state.history.loss_pose == resumed.state.history.loss_pose
    state = json.loads((tmp_path / "part" / "checkpoint" / "state.json").read_text())
    assert state["iteration"] == 4 and (tmp_path / "part" / "checkpoint" / "texture.png").is_file()


def test_checkpoint_with_other_config_is_refused(tmp_path, spec_pool):
    spec, pool = spec_pool
    run = AttackRun(_policy(), spec, resolve_config("quick", CFG), pool=pool, out_dir=tmp_path)
    run.step()
    run.save_checkpoint()
    run.close()
    other = AttackRun(_policy(), spec, resolve_config("quick", {**CFG, "lr": 0.25}), pool=pool, out_dir=tmp_path)
    with pytest.raises(ValueError, match="lr"):
        other.load_checkpoint(find_checkpoint(tmp_path))
    other.close()


def test_black_box_policy_is_refused(spec_pool):
    spec, pool = spec_pool

    class Blackbox:
        image_size = 32

        def act(self, images):
            return images

    with pytest.raises(WhiteBoxRequired, match="white-box"):
        AttackRun(Blackbox(), spec, resolve_config("quick", CFG), pool=pool)


def test_texture_moves_and_stays_in_range_for_every_loss_variant(spec_pool):
    spec, pool = spec_pool
    for extra in (
        {},
        {"loss": "untargeted"},
        {"use_saliency": False},
        {"use_pose": False},
        {"pcgrad": False, "print_aware": True, "light_randomization": True},
    ):
        run = AttackRun(_policy(), spec, resolve_config("quick", {**CFG, "iterations": 2, **extra}), pool=pool)
        before = run.state.texture.clone()
        run_attack(run, progress=False)
        run.close()
        assert torch.isfinite(run.state.texture).all()
        assert run.state.texture.min() >= 0 and run.state.texture.max() <= 1
        assert not torch.equal(before, run.state.texture) or run.state.history.skipped == 2, extra


def test_ctrl_c_leaves_a_usable_checkpoint(tmp_path, spec_pool):
    spec, pool = spec_pool
    cfg = resolve_config("quick", {**CFG, "checkpoint_every": 100})
    run = AttackRun(_policy(), spec, cfg, pool=pool, out_dir=tmp_path)
    real_step, calls = run.step, []

    def step_then_interrupt():
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real_step()

    run.step = step_then_interrupt
    with pytest.raises(KeyboardInterrupt):
        run_attack(run, progress=False)
    run.close()
    again = AttackRun(_policy(), spec, cfg, pool=pool, out_dir=tmp_path)
    again.load_checkpoint(find_checkpoint(tmp_path))
    assert again.state.iteration == 1 and torch.equal(again.state.texture, run.state.texture)
    again.close()


def test_attack_step_advances_only_the_state_and_the_hook_sees_every_iteration(spec_pool):
    from attack.optimize import attack_step
    from attack.state import AttackState

    spec, pool = spec_pool
    run = AttackRun(_policy(), spec, resolve_config("quick", CFG), pool=pool)
    try:
        s = run.state
        before = s.texture.clone()
        info = attack_step(run, s)
        assert s.iteration == 1 and len(s.history.loss_pose) == 1 and info["pairs"] > 0
        assert not torch.equal(before, s.texture) and run.state.texture is s.texture
        # any state: the run is machinery only, so a second state advances without touching the first
        other = AttackState.start(before.clone(), 0)
        kept = s.texture.clone()
        attack_step(run, other)
        assert other.iteration == 1 and not torch.equal(other.texture, before)
        assert s.iteration == 1 and torch.equal(s.texture, kept) and run.state is s
        seen = []
        run_attack(run, progress=False, on_iteration=lambda r, i: seen.append((r.state.iteration, i["pairs"])))
        assert [k for k, _ in seen] == [2, 3, 4]
    finally:
        run.close()
