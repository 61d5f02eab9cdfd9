"""The attack's CPU budget (AttackConfig.max_cpu_s): the run ends at the first iteration whose CPU time
reaches it, validated and checkpointed as a finished run, and the checkpoint records the CPU time, the
budget and the iterations done; a resumed run counts the CPU of its earlier sessions."""

from __future__ import annotations

import math

import pytest
import torch

from attack.optimize import AttackError, AttackRun, read_cpu_record, resolve_config, run_attack
from attack.state import find_checkpoint
from sim.policies.policy import VisuomotorPolicy
from sim.spec import default_scene
from tests.attack.recordings_helpers import sim_recording

S = 32
TINY = {
    "num_envs": 1,
    "rollout_steps": 1,
    "texture_size": 8,
    "checkpoint_every": 1000,
    "validation_every": 0,
}


@pytest.fixture(scope="module")
def spec():
    return default_scene()


@pytest.fixture(scope="module")
def rec(spec, tmp_path_factory):
    return sim_recording(tmp_path_factory.mktemp("rec") / "rec", spec, size=S, episodes=3, steps=2)


def _run(spec, rec, out, **fields) -> AttackRun:
    torch.manual_seed(0)
    cfg = resolve_config("quick", {**TINY, "recordings": str(rec.path), **fields})
    return AttackRun(VisuomotorPolicy(arch="small_cnn", image_size=S), spec, cfg, out_dir=out)


def test_without_a_budget_every_iteration_runs_and_the_cpu_time_is_recorded(spec, rec, tmp_path):
    run = _run(spec, rec, tmp_path, iterations=3)
    try:
        run_attack(run, progress=False)
    finally:
        run.close()
    cpu = read_cpu_record(tmp_path)
    assert cpu["iterations"] == cpu["iterations_planned"] == 3 and cpu["max_cpu_s"] is None
    assert cpu["stopped_at_budget"] is False and cpu["cpu_s"] > 0


def test_the_budget_ends_the_run_at_the_first_iteration_that_reaches_it(spec, rec, tmp_path):
    budget = 1.0
    run = _run(spec, rec, tmp_path, iterations=100_000, max_cpu_s=budget, validation_every=1000)
    try:
        run_attack(run, progress=False)
    finally:
        run.close()
    cpu = read_cpu_record(tmp_path)
    done = cpu["iterations"]
    assert cpu["stopped_at_budget"] is True and cpu["max_cpu_s"] == budget
    assert 1 <= done < 100_000 and run.state.iteration == done
    assert cpu["cpu_s"] >= budget
    # Ended at the first iteration past the budget: what it spent beyond is at most about one iteration
    # and the final validation (the run's own cost per iteration, measured, with room for a slow one).
    per_iteration = cpu["cpu_s"] / done
    assert cpu["cpu_s"] - budget <= 3 * per_iteration + 2.0, (cpu, per_iteration)
    # ... and the final iteration was validated and checkpointed as a finished run's
    assert run.state.history.val_iteration[-1] == done
    assert find_checkpoint(tmp_path) is not None


def test_a_resumed_run_counts_the_cpu_time_of_its_earlier_sessions(spec, rec, tmp_path):
    run = _run(spec, rec, tmp_path, iterations=50, max_cpu_s=1000.0)
    run.step()
    run.cpu_s = 1000.0  # as if the first session had spent the budget (and then crashed)
    run.save_checkpoint()
    run.close()
    resumed = _run(spec, rec, tmp_path, iterations=50, max_cpu_s=1000.0)
    try:
        resumed.load_checkpoint(find_checkpoint(tmp_path))
        assert resumed.cpu_s == 1000.0  # read back from the checkpoint
        run_attack(resumed, progress=False)
        assert resumed.state.iteration == 1  # the budget is spent: no further iteration
    finally:
        resumed.close()
    fresh = _run(spec, rec, tmp_path / "fresh", iterations=2, max_cpu_s=1000.0)
    try:
        run_attack(fresh, progress=False)  # the same budget, nothing spent before: every iteration runs
        assert fresh.state.iteration == 2 and 0 < fresh.cpu_s < 1000.0
    finally:
        fresh.close()


@pytest.mark.parametrize("bad", [0.0, -1.0, math.nan, math.inf, 1e9])
def test_a_budget_that_is_not_a_positive_finite_number_is_refused(bad):
    with pytest.raises(AttackError, match="max_cpu_s"):
        resolve_config("quick", {"max_cpu_s": bad})
