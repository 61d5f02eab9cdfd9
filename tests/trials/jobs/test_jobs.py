"""The job layer without Ray: keys, finished markers, reuse, failures, and sharded evaluations
that write the same rows as the evaluation run whole."""

import json

import pytest

from trials.jobs.dag import Grid, GridError, SerialExecutor, clear_finished, input_digest, is_finished, read_markers

H = "tests.trials.jobs.jobs_helpers"


def _attempts(d):
    return (d / "attempts.txt").read_text().split()


def test_same_job_same_key_and_a_changed_param_or_input_changes_it(tmp_path):
    f = tmp_path / "in.txt"
    f.write_text("a")
    keys = []
    for value, text in ((1, "a"), (1, "a"), (2, "a"), (1, "b")):
        f.write_text(text)
        g = Grid(tmp_path / "out")
        keys.append(g.add("j", "k", f"{H}:write_value", tmp_path / "out" / "j", {"value": value}, {"x": f}).key)
    assert keys[0] == keys[1] and len(set(keys)) == 3


def test_a_finished_job_is_reused_and_a_dependency_gets_its_output(tmp_path):
    def grid():
        g = Grid(tmp_path)
        a = g.add("a", "k", f"{H}:write_value", tmp_path / "a", {"value": 2})
        g.add("b", "k", f"{H}:write_value", tmp_path / "b", {"value": 3}, {"a": a})
        return g

    log = []
    g = grid()
    SerialExecutor(log.append, tee=False).run(g)
    SerialExecutor(log.append, tee=False).run(
        g
    )  # the same grid again (a recipe reading its results): nothing new to say
    assert not any("reused" in m for m in log)
    assert json.loads((tmp_path / "b" / "value.json").read_text())["total"] == 5
    assert json.loads((tmp_path / "a" / "value.json").read_text())["torch_threads"] == 1  # threads follow num_cpus
    SerialExecutor(log.append, tee=False).run(grid())
    assert len(_attempts(tmp_path / "a")) == 1 and len(_attempts(tmp_path / "b")) == 1
    assert any("a: finished earlier, reused" in m for m in log)
    assert (tmp_path / "logs" / "a.log").read_text().count("== finished") == 1


def test_a_cleared_job_runs_again_and_markers_give_every_finished_jobs_timings(tmp_path):
    def grid():
        g = Grid(tmp_path)
        return g, g.add("a", "k", f"{H}:write_value", tmp_path / "a", {"value": 2})

    g, a = grid()
    SerialExecutor(None).run(g)
    (m,) = read_markers(tmp_path)
    assert m["name"] == "a" and m["key"] == a.key and m["cpu_s"] >= 0 and m["seconds"] >= 0
    clear_finished(tmp_path / "a")
    clear_finished(tmp_path / "never-ran")  # nothing to clear: no error
    assert not is_finished(a) and read_markers(tmp_path) == []
    g, a = grid()
    SerialExecutor(None).run(g)
    assert is_finished(a) and len(_attempts(tmp_path / "a")) == 2


def test_a_job_that_dies_half_way_is_not_taken_as_finished_and_reruns(tmp_path):
    src = tmp_path / "src"
    src.mkdir()  # no value.json in it: the job fails after writing attempts.txt
    g = Grid(tmp_path)
    job = g.add("bad", "k", f"{H}:write_value", tmp_path / "bad", {"value": 1}, {"a": src})
    with pytest.raises(GridError) as err:
        SerialExecutor(None).run(g)
    assert not is_finished(job) and (tmp_path / "bad" / "attempts.txt").is_file()
    assert err.value.exit_code == 1 and "logs/bad.log" in str(err.value) and "\n" not in str(err.value)
    assert "Traceback" in (tmp_path / "logs" / "bad.log").read_text()
    (src / "value.json").write_text('{"total": 4}')
    g = Grid(tmp_path)
    job = g.add("bad", "k", f"{H}:write_value", tmp_path / "bad", {"value": 1}, {"a": src})
    SerialExecutor(None).run(g)
    assert is_finished(job) and len(_attempts(tmp_path / "bad")) == 2


def test_a_bad_config_fails_the_grid_in_one_line_naming_the_job(tmp_path):
    g = Grid(tmp_path)
    g.add("attack-x", "attack", f"{H}:bad_config", tmp_path / "x", {"field": "iterations"})
    with pytest.raises(GridError, match=r"^job attack-x: attack config: iterations: must be positive$") as err:
        SerialExecutor(None).run(g)
    assert err.value.exit_code == 2


def test_a_folder_holding_another_jobs_output_is_refused(tmp_path):
    g = Grid(tmp_path)
    g.add("a", "k", f"{H}:write_value", tmp_path / "a", {"value": 1})
    SerialExecutor(None).run(g)
    g2 = Grid(tmp_path)
    g2.add("a", "k", f"{H}:write_value", tmp_path / "a", {"value": 7})
    with pytest.raises(GridError, match="holds the output of a different job"):
        SerialExecutor(None).run(g2)


def test_only_needed_jobs_are_pending(tmp_path):
    g = Grid(tmp_path)
    s = [g.add(f"s{k}", "k", f"{H}:write_value", tmp_path / f"s{k}", {"value": k}) for k in range(2)]
    m = g.add("m", "k", f"{H}:write_value", tmp_path / "m", {"value": 0}, after=tuple(s))
    assert [j.name for j in g.pending()] == ["s0", "s1", "m"]
    SerialExecutor(None).run(g)
    import shutil

    shutil.rmtree(tmp_path / "s0")  # a finished merge needs none of its shards
    assert g.pending() == [] and is_finished(m)


def test_input_digest_covers_top_level_files_and_best_but_not_checkpoints(tmp_path):
    d = tmp_path / "run"
    (d / "checkpoint").mkdir(parents=True)
    (d / "best").mkdir()
    (d / "texture.npy").write_bytes(b"1")
    h0 = input_digest(d)
    (d / "checkpoint" / "step.pt").write_bytes(b"x")
    assert input_digest(d) == h0
    (d / "best" / "texture.npy").write_bytes(b"2")
    assert input_digest(d) != h0
    with pytest.raises(GridError, match="no such file"):
        input_digest(tmp_path / "nope")


STEPS = 8


def _eval_cfg(policy, pool, attack, **kw):
    from trials.eval.evaluate import load_eval_config

    return load_eval_config(
        policy=str(policy),
        pool=str(pool),
        attack=str(attack),
        conditions=("clean", "attack"),
        episodes=9,
        max_steps=STEPS,
        num_envs=3,
        gifs=1,
        **kw,
    )


@pytest.fixture(scope="module")
def pool8(tmp_path_factory):
    """Evaluation-part configurations for 8-step episodes (long enough for trajectories to differ)."""
    from sim.configs import sample_pool, save_pool
    from sim.spec import default_scene

    spec = default_scene()
    spec = spec.with_updates(episode={**spec.episode.model_dump(), "max_steps": STEPS})
    path = tmp_path_factory.mktemp("pool8") / "pool.json"
    save_pool(path, spec, sample_pool(spec, 12, seed=0, part="evaluation"))
    return path


def _rows(d):
    from trials.eval.episodes import read_rows

    return sorted(tuple(sorted((k, repr(v)) for k, v in r.items())) for r in read_rows(d / "episodes.csv"))


def test_a_sharded_evaluation_writes_the_same_rows_and_summary_as_the_whole_one(
    tmp_path, tiny_policy_dir, pool8, attack_dir
):
    from trials.eval.evaluate import run_eval
    from trials.experiments.recipes import run_eval_grid

    cfg = _eval_cfg(tiny_policy_dir, pool8, attack_dir)
    whole = run_eval(cfg, tmp_path / "whole", progress=False)
    sharded = run_eval_grid(cfg, tmp_path / "sharded", SerialExecutor(None), shards=3)
    assert _rows(tmp_path / "whole") == _rows(tmp_path / "sharded") and len(_rows(tmp_path / "whole")) == 18
    assert json.dumps(whole["conditions"], sort_keys=True) == json.dumps(
        sharded["conditions"], sort_keys=True
    )  # NaN-aware
    assert sorted(p.name for p in (tmp_path / "whole" / "gifs").iterdir()) == sorted(
        p.name for p in (tmp_path / "sharded" / "gifs").iterdir()
    )
    assert (tmp_path / "sharded" / "report.md").is_file()
    # re-running reuses the finished merge; a different shard count reuses it too (same key)
    log = []
    run_eval_grid(cfg, tmp_path / "sharded", SerialExecutor(log.append, tee=False), shards=2)
    assert (
        any("eval: finished earlier, reused" in m for m in log)
        and not (tmp_path / "sharded" / "shards" / "0-of-2").exists()
    )


def test_the_scale_out_docs_quote_the_committed_grid_benchmark():
    import importlib.util
    from pathlib import Path

    root = Path(__file__).resolve().parents[3]
    spec = importlib.util.spec_from_file_location("bench_grid", root / "benchmarks" / "bench_grid.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    rec = json.loads((root / "results" / "bench-grid" / "bench_grid.json").read_text())
    assert bench.docs_block(rec) in (root / "docs" / "scale-out.md").read_text()
    assert rec["same_rows"] is True


def test_a_second_run_writing_the_same_folder_at_once_fails_in_one_line(tmp_path):
    import fcntl

    g = Grid(tmp_path)
    job = g.add("a", "k", f"{H}:write_value", tmp_path / "a", {"value": 1})
    (tmp_path / "a").mkdir()
    with open(tmp_path / "a" / ".job.lock", "w") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        with pytest.raises(GridError, match=r"another run is writing there now \(job a\)"):
            SerialExecutor(None).run(g)
    SerialExecutor(None).run(g)
    assert is_finished(job)
