"""The ``recordings`` recipe on a CI-sized budget: the attack on recorded frames against the closed-loop
attack at equal CPU, its growth with the recorded episodes and a shifted cell (issue 29's check).

An untrained 32 px policy is recorded in the simulator (recordings of 2 and 3 episodes of 3 steps, and
3 in the shifted cell), attacked with two attack seeds of two iterations, and every texture is evaluated
on the same evaluation-part configurations. The recordings attacks run with the simulator's env and
rollouts made to fail (:func:`tests.attack.recordings_helpers.no_simulator`). The run takes a few
minutes on 2 shared cores (about 20 jobs, each loading the policy and a renderer): its tests are ``slow``."""

from __future__ import annotations

import json

import pytest
import typer

from attack.artifact import AttackArtifact
from attack.optimize import read_cpu_record
from sim.configs import config_part, sample_pool, save_pool
from sim.recording import read_recording
from tests.attack.recordings_helpers import no_simulator
from tests.trials.conftest import MAX_STEPS
from trials.eval.episodes import read_rows
from trials.experiments import findings as fd
from trials.experiments import recipes
from trials.experiments.recipes import RECIPES, resolve_experiment, run_experiment
from trials.recordings.simulated import recorded_seeds

SIZES = (2, 3)
TINY_ATTACK = {
    "iterations": 2,
    "num_envs": 1,
    "rollout_steps": 1,
    "texture_size": 8,
    "pool_size": 4,
    "checkpoint_every": 1,
    "validation_every": 1,
    "validation_episodes": 2,
}
ARMS = ("closed_loop", "nominal_2", "nominal_3", "shifted_3")


@pytest.fixture(scope="module")
def ran(tmp_path_factory, tiny_policy_dir, short_spec):
    """The recipe run once (module scope): its output folder and the recordings attacks that ran."""
    root = tmp_path_factory.mktemp("recordings")
    pool = root / "pool.json"
    save_pool(pool, short_spec, sample_pool(short_spec, 6, seed=0, part="evaluation"))
    cfg = resolve_experiment(
        "quick",
        attack_overrides=TINY_ATTACK,
        episodes=3,
        max_steps=MAX_STEPS,
        num_envs=2,
        gifs=0,
        pool=str(pool),
        attack_seeds=(0, 1),
    )
    guarded = []
    job_attack = recipes.job_attack

    def without_simulator(out, inputs, preset, fields):
        if "recordings" not in inputs:
            return job_attack(out, inputs, preset, fields)
        guarded.append(out.name)
        with no_simulator():
            return job_attack(out, inputs, preset, fields)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(recipes, "RECORDED_EPISODES", SIZES)
        mp.setattr(recipes, "job_attack", without_simulator)  # the job layer resolves job functions by name
        table = run_experiment(
            "recordings", cfg, root / "recordings", policy=tiny_policy_dir, progress=False, log=lambda m: None
        )
    return {"out": root / "recordings", "table": table, "guarded": guarded}


@pytest.mark.slow
def test_the_recordings_attacks_never_build_the_simulator_and_draw_no_configuration(ran):
    out = ran["out"]
    want = {recipes.seeded(a, s) for a in ARMS[1:] for s in (0, 1)}
    assert set(ran["guarded"]) == want  # every recordings attack ran with the simulator made to fail
    assert {p.name for p in (out / "attacks").iterdir()} == want | {"closed_loop", "closed_loop-seed1"}
    for name in want:
        art = AttackArtifact.load(out / "attacks" / name)
        assert art.trained_on == frozenset()  # no simulator configuration trained or validated on
        assert art.attack_config["recordings"].endswith(f"{name.split('-')[0].replace('_', '-')}/recording")


@pytest.mark.slow
def test_the_recordings_attack_gets_the_closed_loop_attacks_cpu_time_as_its_budget(ran):
    out = ran["out"] / "attacks"
    for s in (0, 1):
        closed = read_cpu_record(out / recipes.seeded("closed_loop", s))
        assert closed["max_cpu_s"] is None and closed["cpu_s"] > 0
        for arm in ARMS[1:]:
            cpu = read_cpu_record(out / recipes.seeded(arm, s))
            assert cpu["max_cpu_s"] == closed["cpu_s"]  # the budget is the closed-loop attack's CPU time
            assert cpu["iterations_planned"] == closed["iterations_planned"] == TINY_ATTACK["iterations"]
            assert cpu["stopped_at_budget"] == (cpu["iterations"] < cpu["iterations_planned"])


@pytest.mark.slow
def test_the_recordings_are_prefixes_and_a_shifted_cell_of_attack_part_configurations(ran):
    recs = {
        n: read_recording(ran["out"] / "recordings" / n / recipes.RECORDING_DIR) for n in ("nominal-2", "nominal-3")
    }
    shifted = read_recording(ran["out"] / "recordings" / "shifted-3" / recipes.RECORDING_DIR)
    assert [e.id for e in recs["nominal-2"].episodes] == [e.id for e in recs["nominal-3"].episodes[:2]]
    assert recorded_seeds(shifted) == recorded_seeds(recs["nominal-3"])  # the same starts, another cell
    assert shifted.source["cell"] == "shifted" and recs["nominal-3"].source["cell"] == "nominal"
    seen = set(recorded_seeds(recs["nominal-3"]))
    assert seen and all(config_part(s) == "attack" for s in seen)
    for ev in (ran["out"] / "evals").iterdir():
        assert not seen & {r["seed"] for r in read_rows(ev)}  # held out: no evaluation episode starts there


@pytest.mark.slow
def test_every_texture_is_evaluated_with_its_clean_arm_on_the_same_configurations(ran):
    configs = set()
    names = {recipes.seeded(f"recordings_{a}", s) for a in ARMS for s in (0, 1)}
    assert {p.name for p in (ran["out"] / "evals").iterdir()} == names
    for name in names:
        rows = read_rows(ran["out"] / "evals" / name)
        by = {c: sorted(r["seed"] for r in rows if r["condition"] == c) for c in ("clean", "attack")}
        assert by["clean"] == by["attack"] and len(by["attack"]) == 3
        configs.add(tuple(by["attack"]))
    assert len(configs) == 1
    text = ran["table"].read_text()
    assert "# Attacking recorded frames" in text and "| nominal_3 | nominal | 3 | " in text
    assert "| shifted_3 | shifted | 3 | " in text and "0 of 3 |" in text
    for arm in ARMS:
        assert f"| 1 | {arm} | " in text  # its CPU row for attack seed 1
    assert "| 0 | nominal_3 | closed_loop | 3 |" in text and "| 1 | shifted_3 | nominal_3 | 3 |" in text


@pytest.mark.slow
def test_the_run_is_collected_unchanged_and_its_finding_computed_over_seeds(ran, tmp_path):
    from tools import evidence

    work = ran["out"].parent
    dst = evidence.collect("recordings", work, tmp_path / "results")
    attacks = json.loads((dst / "attacks.json").read_text())
    assert set(attacks) == {recipes.seeded(a, s) for a in ARMS for s in (0, 1)}
    finding = fd.recordings_finding(SIZES)
    assert {(a.eval, a.condition) for a in finding.arms} <= {(r["eval"], r["condition"]) for r in read_rows(dst)}
    e = fd.findings(tmp_path / "results", registry=(finding,))["F7"]
    (part,) = e.parts
    assert part.ratio.n == part.ratio.n_ref == 3 and part.ratio.vs_control.n == 3
    (over,) = e.seeds
    assert over.seeds == (0, 1) and over.n == 3 and over.part.claim == "ratio"
    assert [p.names for p, _ in e.extras] == [("3 episodes", "2 episodes"), ("shifted cell", "same cell")]
    assert all(pr.n == 3 for _, pr in e.extras)
    details = fd.render_details({"F7": e})
    assert "## F7 recordings vs closed loop" in details and "- shifted cell vs same cell:" in details


def test_the_evidence_tool_runs_the_recipe_with_options_the_command_has(tmp_path, monkeypatch):
    from tools import evidence
    from trials.cli.experiment import app as experiment_app
    from trials.experiments import record

    monkeypatch.setattr(record, "git_commit", lambda: "0123abc")
    ran = []
    monkeypatch.setattr(record.subprocess, "call", lambda cmd, **k: ran.append(cmd) or 1)  # no run: nothing collected
    extra = ["--attack-seeds", "0,1,2", "--workers", "2"]
    rc = evidence.run("recordings", 300, "runs/evidence/policy-quick-seeds", tmp_path / "w", tmp_path / "r", extra)
    assert rc == 1 and "recordings" in evidence.RECIPES and RECIPES["recordings"].scene is None
    (cmd,) = ran
    assert cmd[1:3] == ["experiment", "recordings"] and "--scene" not in cmd and cmd[-4:] == extra
    command = typer.main.get_command(experiment_app).commands["recordings"]
    flags = {o for p in command.params for o in p.opts}
    assert {a for a in cmd[3:] if a.startswith("--")} <= flags
