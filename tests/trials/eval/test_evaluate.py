"""The harness: paired frames across conditions, shared noise draws, resume, reports."""

import json

import numpy as np
import pytest

import trials.eval.evaluate as ev
from sim.configs import load_pool
from sim.policies.checkpoint import load_policy
from tests.trials.conftest import MAX_STEPS
from trials.eval.conditions import Sources, build_conditions
from trials.eval.evaluate import load_eval_config, rollout_condition, run_eval


def _first_frames(policy, spec, cond, configs):
    frames = {}

    def on_frame(j, step, adv, clean):
        if step == 0:
            frames[configs[j].seed] = (adv.copy(), clean.copy())

    rollout_condition(policy, spec, cond, configs, 3, lambda j, r: None, on_frame)
    return frames


def test_same_seeds_give_the_same_initial_frames_across_conditions(tiny_policy_dir, short_spec, pool_file, attack_dir):
    policy = load_policy(tiny_policy_dir)
    configs = load_pool(pool_file, short_spec)[:3]
    clean, attack, noise = build_conditions(["attack", "noise"], Sources(attack=str(attack_dir)))
    f_clean = _first_frames(policy, short_spec, clean, configs)
    f_attack = _first_frames(policy, short_spec, attack, configs)
    assert sorted(f_clean) == sorted(f_attack) == [c.seed for c in configs]
    for s in f_clean:
        adv0, clean0 = f_clean[s]
        assert np.array_equal(adv0, clean0)  # the clean arm acts on the clean view
        # the attack arm's clean view of the same state is pixel-identical to the clean arm's
        assert np.array_equal(f_attack[s][1], clean0)
    # and the attack texture is visible in at least one start
    assert any(not np.array_equal(f_attack[s][0], f_attack[s][1]) for s in f_attack)

    # Sensor noise: one draw per frame shared by the attacked and the clean view, so they
    # differ only on the adversarial object, while both differ from the noise-free frame.
    f_noise = _first_frames(policy, short_spec, noise, configs)
    for s, (adv, cl) in f_noise.items():
        assert not np.array_equal(cl, f_clean[s][1])
        assert (adv == cl).all(-1).mean() > 0.5


def test_noise_draws_repeat_for_the_same_seed(tiny_policy_dir, short_spec, pool_file, attack_dir):
    policy = load_policy(tiny_policy_dir)
    configs = load_pool(pool_file, short_spec)[:1]
    noise = build_conditions(["noise"], Sources(attack=str(attack_dir)))[1]
    a = _first_frames(policy, short_spec, noise, configs)[configs[0].seed]
    b = _first_frames(policy, short_spec, noise, configs)[configs[0].seed]
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


def test_interrupted_eval_resumes_without_redoing_finished_episodes(
    tmp_path, monkeypatch, tiny_policy_dir, pool_file, attack_dir
):
    cfg = load_eval_config(
        policy=str(tiny_policy_dir),
        conditions=("attack",),
        episodes=4,
        max_steps=MAX_STEPS,
        num_envs=2,
        pool=str(pool_file),
        attack=str(attack_dir),
        gifs=0,
    )
    real_row = ev._row
    calls = []

    def crashing_row(*a, **k):
        calls.append(a[1].seed)
        if len(calls) == 5:
            raise KeyboardInterrupt  # killed after 4 finished episodes
        return real_row(*a, **k)

    monkeypatch.setattr(ev, "_row", crashing_row)
    with pytest.raises(KeyboardInterrupt):
        run_eval(cfg, tmp_path, progress=False)
    assert len((tmp_path / "episodes.csv").read_text().splitlines()) == 1 + 4
    calls.clear()
    monkeypatch.setattr(ev, "_row", lambda *a, **k: (calls.append(a[1].seed), real_row(*a, **k))[1])
    summary = run_eval(cfg, tmp_path, resume=True, progress=False)
    assert len(calls) == 4  # only the 4 unfinished episodes ran
    rows = [l.split(",")[:2] for l in (tmp_path / "episodes.csv").read_text().splitlines()[1:]]
    assert len(rows) == 8 and len({tuple(r) for r in rows}) == 8
    assert summary["conditions"]["clean"]["n"] == 4 and summary["conditions"]["attack"]["n"] == 4
    with pytest.raises(Exception, match="different config"):
        run_eval(cfg.model_copy(update={"episodes": 3}), tmp_path, resume=True, progress=False)


def test_eval_writes_rows_summary_report_and_provenance(tmp_path, tiny_policy_dir, pool_file, attack_dir):
    cfg = load_eval_config(
        policy=str(tiny_policy_dir),
        conditions=("attack",),
        episodes=3,
        max_steps=MAX_STEPS,
        num_envs=3,
        pool=str(pool_file),
        attack=str(attack_dir),
        gifs=1,
    )
    summary = run_eval(cfg, tmp_path, progress=False)
    for name in (
        "episodes.csv",
        "manifest.json",
        "summary.json",
        "run.json",
        "report.md",
        "bars_by_phi.png",
        "bars_by_distance.png",
        "textures/attack.png",
    ):
        assert (tmp_path / name).is_file(), name
    gifs = sorted(p.name for p in (tmp_path / "gifs").iterdir())
    assert any(g.startswith("compare_clean_vs_attack_seed") for g in gifs)
    header = (tmp_path / "episodes.csv").read_text().splitlines()[0].split(",")
    assert (
        header[:12]
        == [
            "condition",
            "seed",
            "r_m",
            "theta_rad",
            "phi_rad",
            "outcome",
            "reached",
            "success",
            "targeted",
            "steps",
            "e_trans",
            "e_rot",
        ]
        and "min_dist_mustard_bottle" in header
    )
    att = summary["conditions"]["attack"]
    assert att["n"] == 3 and 0 <= att["asr"]["lo"] <= att["asr"]["hi"] <= 1
    assert summary["conditions"]["clean"]["e_trans"]["mean"] == 0.0
    assert att["e_trans"]["mean"] >= 0 and "vs_clean" in att
    run = json.loads((tmp_path / "run.json").read_text())
    assert run["git_commit"] and run["config"]["eval"]["episodes"] == 3
    report = (tmp_path / "report.md").read_text()
    assert "McNemar" in report and "E_trans" in report and "70-90" in report and "69-80" in report


@pytest.mark.slow
def test_end_to_end_cli_short_attack_then_20_paired_episodes(tmp_path, tiny_policy_dir, pool_file):
    """CI-sized main job through the CLI: a short attack on a tiny policy, then 20 episodes per arm."""
    import yaml
    from typer.testing import CliRunner

    from trials.cli.main import app

    cfg = tmp_path / "attack.yaml"
    cfg.write_text(
        yaml.safe_dump({"iterations": 3, "num_envs": 2, "rollout_steps": 2, "texture_size": 16, "pool_size": 8})
    )
    runner = CliRunner()
    res = runner.invoke(
        app, ["attack", "run", "--policy", str(tiny_policy_dir), "--config", str(cfg), "--out", str(tmp_path / "atk")]
    )
    assert res.exit_code == 0, res.output
    res = runner.invoke(
        app,
        [
            "eval",
            "--policy",
            str(tiny_policy_dir),
            "--attack",
            str(tmp_path / "atk"),
            "--episodes",
            "20",
            "--max-steps",
            str(MAX_STEPS),
            "--num-envs",
            "10",
            "--pool",
            str(pool_file),
            "--out",
            str(tmp_path / "ev"),
        ],
    )
    assert res.exit_code == 0, res.output
    assert "T-ASR" in res.output and "95% CI" in res.output
    summary = json.loads((tmp_path / "ev" / "summary.json").read_text())
    assert summary["conditions"]["clean"]["n"] == summary["conditions"]["attack"]["n"] == 20
    clean_seeds = [
        l.split(",")[1]
        for l in (tmp_path / "ev" / "episodes.csv").read_text().splitlines()[1:]
        if l.startswith("clean,")
    ]
    attack_seeds = [
        l.split(",")[1]
        for l in (tmp_path / "ev" / "episodes.csv").read_text().splitlines()[1:]
        if l.startswith("attack,")
    ]
    assert sorted(clean_seeds) == sorted(attack_seeds)  # paired: the same 20 configurations


def test_feasible_pool_keeps_only_configs_the_clean_policy_solves(tmp_path, monkeypatch, tiny_policy_dir, short_spec):
    """Building the pool: candidates (seeds of the evaluation part only) are rolled out clean and only
    goal-reaching ones are kept, in seed order."""
    from sim.configs import part_seeds
    from sim.policies import pool as feasible_pool

    goal = short_spec.object_index("goal")
    seeds = part_seeds("evaluation", 100)
    cands = [next(seeds) for _ in range(40)]
    want = [s for s in cands if s % 3 == 0][:4]

    def fake_rollout(policy, spec, configs, num_envs, on_done, **kw):
        assert not kw  # the clean look: no texture, no stereo, no randomisation
        for j, c in enumerate(configs):
            on_done(j, j % num_envs, {"reached": goal if c.seed % 3 == 0 else -1})

    monkeypatch.setattr(feasible_pool, "rollout_paired", fake_rollout)
    cfg = load_eval_config(policy=str(tiny_policy_dir), episodes=4, max_steps=MAX_STEPS, num_envs=2, seed=100)
    # The competence gate off: a third of the candidates reaching the goal is below its default, and this
    # test is about which candidates the builder keeps.
    pool, src = ev.resolve_pool(cfg, None, short_spec, tmp_path, progress=False, min_clean_success=0)
    assert [c.seed for c in pool] == want and src == str(tmp_path / "feasible_pool.json")
    assert [c.seed for c in load_pool(tmp_path / "feasible_pool.json", short_spec)] == want

    monkeypatch.setattr(
        feasible_pool,
        "rollout_paired",
        lambda p, s, configs, n, on_done, **kw: [on_done(j, 0, {"reached": -1}) for j in range(len(configs))],
    )
    with pytest.raises(ev.EvalError, match="nothing is task-feasible"):
        ev.resolve_pool(cfg, None, short_spec, tmp_path / "other", progress=False, min_clean_success=0)


def test_black_box_onnx_target_is_evaluated_on_the_same_configs(tmp_path, tiny_policy_dir, pool_file, attack_dir):
    """An ONNX file is a valid target (black-box transfer): same rows, same seeds as a checkpoint target."""
    from sim.policies.checkpoint import load_checkpoint
    from sim.policies.onnx_policy import export_onnx

    pol, card = load_checkpoint(tiny_policy_dir)
    onnx = tmp_path / "target.onnx"
    export_onnx(pol, onnx, card=card)
    cfg = load_eval_config(
        policy=str(onnx),
        conditions=("attack",),
        episodes=2,
        max_steps=MAX_STEPS,
        num_envs=2,
        pool=str(pool_file),
        attack=str(attack_dir),
        gifs=0,
    )
    summary = run_eval(cfg, tmp_path / "ev", progress=False, report=False)
    assert summary["conditions"]["attack"]["n"] == 2 and summary["meta"]["policy"].endswith(".onnx")
    seeds = sorted({l.split(",")[1] for l in (tmp_path / "ev" / "episodes.csv").read_text().splitlines()[1:]})
    assert seeds == [str(c.seed) for c in load_pool(pool_file)[:2]]
