"""The speed-vs-accuracy sweep: rows as data, one real row end to end, resume, report and CLI."""

import json
from dataclasses import asdict

import pytest

from tests.trials.conftest import MAX_STEPS
from trials.experiments.tradeoff import (
    BASELINE_KEY,
    DEPLOYMENTS,
    KNOBS,
    Row,
    TradeoffError,
    build_rows,
    load_tradeoff_config,
    read_results,
    run_sweep,
    select_rows,
    set_size,
    write_tradeoff_report,
)
from trials.experiments.tradeoff_report import pareto_front

TINY_ATTACK = {
    "iterations": 2,
    "num_envs": 1,
    "rollout_steps": 1,
    "texture_size": 8,
    "checkpoint_every": 1000,
    "validation_every": 0,
}


def _tiny(policy, pool, **kw):
    return load_tradeoff_config(
        policy=str(policy),
        pool=str(pool),
        attack_overrides=TINY_ATTACK,
        snapshots=(1,),
        episodes=4,
        big_episodes=2,
        max_steps=MAX_STEPS,
        eval_num_envs=2,
        deploy_episodes=2,
        latency_reps=2,
        **kw,
    )


def test_every_knob_of_the_issue_has_rows_with_the_issue_values():
    cfg = load_tradeoff_config(policy="ref")
    assert cfg.attack_overrides == {"validation_every": 0}  # the sweep evaluates the final texture itself
    rows = build_rows(cfg)
    assert {r.knob for r in rows} == set(KNOBS)
    by = {}
    for r in rows:
        by.setdefault(r.knob, []).append(r)
    # the quick preset is the baseline (4 envs, 6 steps, texture 64, trilinear, saliency and PCGrad on)
    assert [r.key for r in by["baseline"]] == [BASELINE_KEY] and rows[0].key == BASELINE_KEY
    assert {r.overrides["num_envs"] for r in by["eot_envs"]} == {1, 2}
    assert {r.overrides["rollout_steps"] for r in by["rollout_steps"]} == {5, 10}
    assert [r.overrides for r in by["sampler"]] == [{"sampler": "bilinear"}]
    assert [(r.overrides, r.note) for r in by["saliency"]] == [({"use_saliency": False}, "baseline: on")]
    assert [r.overrides for r in by["pcgrad"]] == [{"pcgrad": False}]
    assert all(r.overrides["texture_size"] != 64 for r in by["texture_size"])
    assert {r.value for r in by["policy_resolution"]} == {"96", "128"} and {
        r.policy for r in by["policy_resolution"]
    } == {"px96", "px128"}
    # iterations are snapshots of the baseline run, eval_episodes re-evaluates its texture: both depend on it
    assert [(r.value, r.kind, r.depends) for r in by["iterations"]] == [
        ("30", "snapshot", BASELINE_KEY),
        ("60", "snapshot", BASELINE_KEY),
    ]
    # the baseline texture again on the first third of the same fixed set (300 configurations by default)
    assert cfg.episodes == 300 and cfg.attack_seeds == (0,)
    assert [(r.value, r.depends) for r in by["eval_episodes"]] == [("100", BASELINE_KEY)]
    assert [r.value for r in by["deployment"]] == list(DEPLOYMENTS)
    assert len({r.key for r in rows}) == len(rows)


def test_unknown_knobs_rows_and_bad_settings_are_clear_errors():
    cfg = load_tradeoff_config(policy="ref")
    rows = build_rows(cfg)
    with pytest.raises(TradeoffError, match="unknown knob 'colour'"):
        select_rows(rows, ["colour"])
    with pytest.raises(TradeoffError, match="no row 'eot_envs=3'.*eot_envs=1"):
        select_rows(rows, ["eot_envs=3"])
    with pytest.raises(TradeoffError, match="unknown knob"):
        load_tradeoff_config(policy="ref", values={"colour": [1]})
    with pytest.raises(TradeoffError, match="snapshots"):
        build_rows(load_tradeoff_config(policy="ref", snapshots=(200,)))
    with pytest.raises(TradeoffError, match="deployment"):
        build_rows(load_tradeoff_config(policy="ref", values={"deployment": ["tensorrt"]}))
    with pytest.raises(TradeoffError, match="episodes"):
        load_tradeoff_config(policy="ref", episodes=0)
    # a dependent row brings its dependency along
    assert [r.key for r in select_rows(rows, ["iterations=30"])] == [BASELINE_KEY, "iterations=30"]


ATTACK_KNOBS = ("baseline", "iterations", "eot_envs", "rollout_steps", "sampler", "texture_size", "saliency", "pcgrad")


def test_attack_seeds_run_the_rows_that_change_the_attack_once_per_seed():
    cfg = load_tradeoff_config(policy="ref", attack_seeds=(0, 1, 2))
    rows = build_rows(cfg)
    seeds = {}
    for r in rows:
        seeds.setdefault(r.name, []).append(r.attack_seed)
    for name, got in seeds.items():
        knob = name.split("=")[0]
        want = [0, 1, 2] if knob in ATTACK_KNOBS else ([None] if knob == "deployment" else [0])
        assert got == want, name
    by = {r.key: r for r in rows}
    assert by["iterations=30@seed1"].depends == "baseline=quick@seed1" and by["eot_envs=1@seed2"].depends is None
    assert by["eval_episodes=100"].depends == BASELINE_KEY  # the first seed's baseline texture, once
    assert [r.key for r in select_rows(rows, ["eot_envs=1"])] == ["eot_envs=1", "eot_envs=1@seed1", "eot_envs=1@seed2"]
    assert [r.key for r in select_rows(rows, ["iterations=30@seed2"])] == [
        "baseline=quick@seed2",
        "iterations=30@seed2",
    ]
    r = by["pcgrad=off@seed1"]
    assert Row(**json.loads(json.dumps(asdict(r)))) == r  # what a row's child process reads back
    with pytest.raises(TradeoffError, match="distinct"):
        load_tradeoff_config(policy="ref", attack_seeds=(0, 0))
    with pytest.raises(TradeoffError, match="attack_seeds"):
        load_tradeoff_config(policy="ref", attack_overrides={"seed": 3})
    # one fixed set per policy: episodes configurations, more when an eval_episodes row asks for more
    assert set_size(cfg, "ref") == set_size(cfg, "px96") == 300
    big = load_tradeoff_config(policy="ref", big_episodes=600)
    assert (set_size(big, "ref"), set_size(big, "px96")) == (600, 300)


def test_rows_of_other_settings_without_a_settings_file_are_refused(tmp_path):
    (tmp_path / "rows.jsonl").write_text(json.dumps({"key": "eot_envs=2", "status": "ok", "settings_hash": "0"}) + "\n")
    with pytest.raises(TradeoffError, match="rows measured with other settings"):
        run_sweep(load_tradeoff_config(policy="ref"), tmp_path, ["eot_envs=2"], progress=False)
    assert not (tmp_path / "sweep.json").exists()


def test_one_row_end_to_end_in_a_child_process_then_resume_skips_it(tmp_path, tiny_policy_dir, mixed_pool_file):
    cfg = _tiny(tiny_policy_dir, mixed_pool_file)
    log = []
    run_sweep(cfg, tmp_path, ["eot_envs=2"], progress=False, log=log.append)
    lines = (tmp_path / "rows.jsonl").read_text().splitlines()
    assert len(lines) == 1
    rec = json.loads(lines[0])
    assert rec["status"] == "ok", rec.get("traceback")
    assert (
        rec["key"] == "eot_envs=2" and rec["attack_config"]["num_envs"] == 2 and rec["attack_config"]["iterations"] == 2
    )
    assert (
        rec["episodes"] == 4
        and rec["tasr"]["n"] == 4
        and 0 <= rec["tasr"]["lo"] <= rec["tasr"]["rate"] <= rec["tasr"]["hi"] <= 1
    )
    assert rec["e_trans"]["n"] == 4 and rec["attack_wall_s"] > 0 and rec["eval_cpu_s"] > 0 and rec["peak_rss_mb"] > 50
    assert len(rec["load_start"]) == 3 and rec["git_commit"] and rec["image_size"] == 32
    run_info = json.loads((tmp_path / "attacks" / "eot_envs_2" / "run.json").read_text())
    assert run_info["config"]["attack"]["num_envs"] == 2 and "git_commit" in run_info
    # the fixed evaluation set: the pool's first 4 evaluation-part configurations; the attack
    # sampled from the attack part
    eval_seeds = json.loads((tmp_path / "evals" / "eot_envs_2" / "run.json").read_text())["config"]["seeds"]
    assert len(eval_seeds) == 4 and (tmp_path / "eval_sets" / "ref.json").is_file()
    assert json.loads((tmp_path / "machine.json").read_text())["runs"][0]["start"]["cpu_count"] >= 1
    # the row is a tradeoff-row job with the job layer's marker; its child's spec is row.json, the settings sweep.json
    assert json.loads((tmp_path / "rows" / "eot_envs_2" / "job.json").read_text())["kind"] == "tradeoff-row"
    assert json.loads((tmp_path / "jobs" / "eot_envs_2" / "row.json").read_text())["row"]["knob"] == "eot_envs"
    assert json.loads((tmp_path / "sweep.json").read_text())["settings"]["episodes"] == 4
    assert not (tmp_path / "jobs" / "eot_envs_2" / "job.json").exists() and not (tmp_path / "manifest.json").exists()
    # resume: the finished row is skipped, nothing appended
    log.clear()
    run_sweep(cfg, tmp_path, ["eot_envs=2"], progress=False, log=log.append)
    assert "eot_envs=2: done, skipped" in log and len((tmp_path / "rows.jsonl").read_text().splitlines()) == 1
    # --redo measures it again; the newest record is the one reported
    run_sweep(cfg, tmp_path, ["eot_envs=2"], progress=False, log=log.append, redo=True)
    assert len((tmp_path / "rows.jsonl").read_text().splitlines()) == 2
    (latest,) = read_results(tmp_path)
    assert latest["time_utc"] >= rec["time_utc"] and latest["status"] == "ok"
    # an evaluation set that is no longer task-feasible for the policy's pool is refused
    sets = tmp_path / "eval_sets" / "ref.json"
    doc = json.loads(sets.read_text())
    doc["configs"][0]["seed"] = 10**6
    sets.write_text(json.dumps(doc))
    res = run_sweep(cfg, tmp_path, ["eot_envs=2"], progress=False, log=log.append, redo=True, isolate=False)
    bad = next(r for r in res if r["key"] == "eot_envs=2")
    assert bad["status"] == "error" and "not task-feasible" in bad["error"]
    assert not (tmp_path / "rows" / "eot_envs_2" / "job.json").exists()  # an error row is not finished: runs again
    # other settings in the same directory are refused
    with pytest.raises(TradeoffError, match="other settings.*episodes"):
        run_sweep(
            _tiny(tiny_policy_dir, mixed_pool_file).model_copy(update={"episodes": 3}),
            tmp_path,
            ["eot_envs=2"],
            progress=False,
        )


def test_iteration_rows_evaluate_snapshots_of_the_baseline_run(tmp_path, tiny_policy_dir, mixed_pool_file):
    cfg = _tiny(tiny_policy_dir, mixed_pool_file)
    res = {
        r["key"]: r for r in run_sweep(cfg, tmp_path, ["iterations"], progress=False, log=lambda m: None, isolate=False)
    }
    base, snap = res[BASELINE_KEY], res["iterations=1"]
    assert base["status"] == "ok" and snap["status"] == "ok", (base.get("traceback"), snap.get("traceback"))
    assert snap["attack_dir"].endswith("iter00001") and 0 < snap["attack_wall_s"] <= base["attack_wall_s"]
    assert snap["attack_config"] == base["attack_config"] and snap["episodes"] == base["episodes"] == 4
    assert "in-process" in snap["note"]


def test_pareto_front_on_a_hand_made_set():
    pts = [(10, 0.5), (20, 0.4), (20, 0.6), (5, 0.1), (30, 0.6), (40, 0.9)]
    # (20, .4) is beaten by (10, .5); (30, .6) by (20, .6)
    assert pareto_front(pts) == [3, 0, 2, 5]
    assert pareto_front([(1, 0.5), (1, 0.5)]) == [0, 1]  # ties dominate nothing
    assert pareto_front([]) == []


def _synthetic(key, knob, value, kind, wall, rate, policy="ref", n=100, **kw):
    k = round(rate * n)
    p = {"k": k, "n": n, "rate": k / n, "lo": max(0, rate - 0.1), "hi": min(1, rate + 0.1), "confidence": 0.95}
    m = {"mean": 0.2, "lo": 0.15, "hi": 0.25, "n": n, "confidence": 0.95}
    seed = kw.pop("attack_seed", 0 if kind != "deployment" else None)
    rec = {
        "key": key,
        "name": key.split("@")[0],
        "knob": knob,
        "value": value,
        "kind": kind,
        "attack_seed": seed,
        "policy": policy,
        "status": "ok",
        "note": "",
        "image_size": 64,
        "attack_wall_s": wall,
        "attack_cpu_s": wall / 2,
        "eval_wall_s": 60.0,
        "eval_cpu_s": 30.0,
        "row_wall_s": wall + 60.0,
        "row_cpu_s": wall / 2 + 30.0,
        "peak_rss_mb": 700.0,
        "episodes": n,
        "eval_name": key.replace("=", "_").replace("@", "_"),
        "tasr": p,
        "asr": p,
        "e_trans": m,
        "e_rot": m,
        "load_start": [1.0, 1.0, 1.0],
        "load_end": [2.0, 1.0, 1.0],
    }
    rec.update(kw)
    return rec


def _write_outcomes(out, name, targeted_seeds, n=10):
    """A row's evaluation folder with only what the paired tests read: condition, seed, targeted."""
    d = out / "evals" / name
    d.mkdir(parents=True)
    lines = ["condition,seed,targeted"] + [f"attack,{s},{int(s in targeted_seeds)}" for s in range(n)]
    lines += [f"clean,{s},0" for s in range(n)]
    (d / "episodes.csv").write_text("\n".join(lines) + "\n")


def test_report_tables_and_plot_from_synthetic_rows(tmp_path):
    lat = {"b1": {"median": 1.5, "p90": 2.0, "cpu_mean": 1.25}, "b8": {"median": 0.5, "p90": 0.6}}
    rows = [
        _synthetic(BASELINE_KEY, "baseline", "quick", "attack", 100.0, 0.6, n=10),
        _synthetic("baseline=quick@seed1", "baseline", "quick", "attack", 90.0, 0.5, n=10, attack_seed=1),
        _synthetic("iterations=30", "iterations", "30", "snapshot", 25.0, 0.2, n=10),
        _synthetic("eot_envs=1", "eot_envs", "1", "attack", 30.0, 0.2, n=10),
        _synthetic("eot_envs=1@seed1", "eot_envs", "1", "attack", 32.0, 0.5, n=10, attack_seed=1),
        _synthetic("policy_resolution=96", "policy_resolution", "96", "attack", 300.0, 0.7, policy="px96"),
        _synthetic("eval_episodes=5", "eval_episodes", "5", "episodes", 100.0, 1.0, n=5),
        {
            "key": "deployment=onnx-int8",
            "knob": "deployment",
            "value": "onnx-int8",
            "kind": "deployment",
            "policy": "ref",
            "status": "ok",
            "latency_ms": lat,
            "action_err_max": 0.02,
            "action_err_mean": 0.003,
            "clean_success": {"k": 49, "n": 50, "rate": 0.98, "lo": 0.9, "hi": 1.0},
            "model_bytes": 2048,
            "frames": 300,
            "peak_rss_mb": 500.0,
            "load_start": [1, 1, 1],
            "load_end": [1, 1, 1],
        },
        {
            "key": "sampler=bilinear",
            "knob": "sampler",
            "value": "bilinear",
            "kind": "attack",
            "attack_seed": 0,
            "policy": "ref",
            "status": "error",
            "error": "RuntimeError: boom",
        },
    ]
    # the paired outcomes on configurations 0..9: baseline seed 0 targeted on 0-5, eot_envs=1 on 0-1
    # (4 discordant pairs, all the baseline's: p = 2 / 2^4 = 0.125), seed 1's baseline on 0-4 and
    # its eot_envs=1 on 5-9 (10 discordant, 5 each way: p = 1)
    _write_outcomes(tmp_path, "baseline_quick", range(6))
    _write_outcomes(tmp_path, "baseline_quick_seed1", range(5))
    _write_outcomes(tmp_path, "iterations_30", range(2))
    _write_outcomes(tmp_path, "eot_envs_1", range(2))
    _write_outcomes(tmp_path, "eot_envs_1_seed1", range(5, 10))
    _write_outcomes(tmp_path, "eval_episodes_5", range(5), n=5)  # the baseline texture again: the same outcomes
    (tmp_path / "rows.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows) + '{"torn')
    (tmp_path / "machine.json").write_text(
        json.dumps(
            {
                "runs": [
                    {
                        "start": {
                            "cpu_model": "Test CPU",
                            "cpu_count": 2,
                            "cpus_usable": 2,
                            "mem_total_gb": 4,
                            "torch": "2.x",
                            "torch_threads": 1,
                            "onnxruntime": "1.x",
                            "numpy": "2.x",
                            "python": "3.11",
                            "platform": "linux",
                            "loadavg": [0.5, 0.4, 0.3],
                        }
                    }
                ]
            }
        )
    )
    assert len(read_results(tmp_path)) == len(rows)  # the torn last line is ignored
    text = write_tradeoff_report(tmp_path).read_text()
    assert "Test CPU; 2 logical cores" in text and "torch 2.x with 1 intra-op thread" in text
    assert "| baseline | quick | 0 | 64 | 100 | 50 | 60 | 30 | 700 | 10 | 60 [50, 70] |" in text
    assert "| sampler | bilinear | 0 |" in text and "failed: RuntimeError: boom" in text
    assert "| onnx-int8 | 1.50 (2.00) | 1.25 | 0.50 | n/a | 2.00e-02 | 3.00e-03 | 49/50 = 98 [90, 100] | 2 |" in text
    # every run, paired with the baseline of its own attack seed (pairs, baseline only, row only, diff, p)
    assert "| eot_envs=1 | 0 | 64 | 10 | 2/10 | 20.0 [10.0, 30.0] | 10 | 4 | 0 | -40.0 | 0.125 |" in text
    assert "| eot_envs=1@seed1 | 1 | 64 | 10 | 5/10 | 50.0 [40.0, 60.0] | 10 | 5 | 5 | +0.0 | 1 |" in text
    assert "| eval_episodes=5 | 0 | 64 | 5 | 5/5 | 100.0 [90.0, 100.0] | 5 | 0 | 0 | +0.0 | 1 |" in text
    assert "| baseline=quick | 0 | 64 | 10 | 6/10 | 60.0 [50.0, 70.0] | baseline | | | | |" in text
    assert "| policy_resolution=96 | 0 | 64 | 100 | 70/100 | 70.0 [60.0, 80.0] | not paired | | | | |" in text
    # per setting over attack seeds: mean, min, max, mean paired difference, McNemar rejections
    assert "| eot_envs=1 | 0, 1 | 10 | 35.0 | 20.0 | 50.0 | -20.0 | 0 / 0 / 2 | 31 | 16 | 60 | 30 |" in text
    assert "| baseline=quick | 0, 1 | 10 | 55.0 | 50.0 | 60.0 | baseline |" in text
    # table order follows the knob order of the issue
    assert (
        text.index("| baseline | quick")
        < text.index("| iterations | 30")
        < text.index("| eot_envs | 1")
        < text.index("| policy_resolution | 96")
    )
    for name in ("tradeoff_pareto.png", "tradeoff_pareto_cpu.png"):
        assert (tmp_path / name).read_bytes()[:4] == b"\x89PNG"


def test_cli_help_and_a_tiny_deployment_run(tmp_path, tiny_policy_dir, mixed_pool_file):
    from typer.testing import CliRunner

    from trials.cli.main import app

    runner = CliRunner()
    res = runner.invoke(app, ["bench", "tradeoff", "--help"])
    assert res.exit_code == 0 and "--quick-check" in res.output and "--rows" in res.output
    out = tmp_path / "sweep"
    res = runner.invoke(
        app,
        [
            "bench",
            "tradeoff",
            "--quick-check",
            "--policy",
            str(tiny_policy_dir),
            "--pool",
            str(mixed_pool_file),
            "--out",
            str(out),
            "--max-steps",
            str(MAX_STEPS),
            "--rows",
            "deployment=onnx-fp32",
            "--plot",
            str(tmp_path / "p.png"),
        ],
    )
    assert res.exit_code == 0, res.output
    (rec,) = read_results(out)
    assert rec["status"] == "ok", rec.get("traceback")
    assert (
        rec["action_err_max"] < 1e-4
        and rec["latency_ms"]["b1"]["median"] > 0
        and rec["latency_ms"]["b8"]["cpu_mean"] > 0
        and rec["frames"] > 0
    )
    assert "| onnx-fp32 |" in (out / "report.md").read_text() and (tmp_path / "p.png").is_file()


def test_cli_attack_seeds_reach_the_sweep_settings_and_a_malformed_list_is_one_line(
    tmp_path, tiny_policy_dir, mixed_pool_file, monkeypatch, capsys
):
    import sys

    from typer.testing import CliRunner

    from trials.cli.main import app, main

    argv = ["bench", "tradeoff", "--policy", str(tiny_policy_dir), "--out", str(tmp_path / "bad")]
    monkeypatch.setattr(sys, "argv", ["advobj", *argv, "--attack-seeds", "0,x"])
    with pytest.raises(SystemExit) as exc:
        main()
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert exc.value.code == 2 and len(err) == 1 and "--attack-seeds" in err[0], err
    assert not (tmp_path / "bad").exists()
    runner = CliRunner()
    out = tmp_path / "sweep"
    res = runner.invoke(
        app,
        [
            "bench",
            "tradeoff",
            "--quick-check",
            "--policy",
            str(tiny_policy_dir),
            "--pool",
            str(mixed_pool_file),
            "--out",
            str(out),
            "--max-steps",
            str(MAX_STEPS),
            "--attack-seeds",
            "1,2",
            "--rows",
            "deployment=onnx-fp32",
        ],
    )
    assert res.exit_code == 0, res.output
    assert json.loads((out / "sweep.json").read_text())["settings"]["attack_seeds"] == [1, 2]
