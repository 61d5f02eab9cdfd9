"""The job layer on a real local Ray cluster (127.0.0.1): a head node and a second node with a
GPU resource, joined as a user joins a cluster (``address``). Marked ``ray``; ``.ci/run`` runs it.

Checked: a recipe grid gives the same rows and summary figures on Ray (2 shards) as serially; a
GPU job lands on the GPU node only; a worker killed mid-job is retried and its half-written output
never taken as finished; a failing job fails the grid in one line after the running job finished
(kept, and reused by the re-run); without a shared filesystem outputs come back to ``--out``;
``advobj eval --workers 2`` starts and stops its own Ray. Every Ray process started is stopped.
"""

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

# Before ray is imported (it reads this then): the test cluster is this machine only, on
# 127.0.0.1; otherwise Ray rewrites 127.0.0.1 to the machine's outward address.
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
ray = pytest.importorskip("ray")

from tests.trials.conftest import MAX_STEPS  # noqa: E402
from trials.jobs.dag import Grid, GridError, RayExecutor, is_finished  # noqa: E402

pytestmark = pytest.mark.ray
H = "tests.trials.jobs.jobs_helpers"
ROOT = Path(__file__).resolve().parents[3]


def _ray_pids() -> set[int]:
    out = subprocess.run(
        ["pgrep", "-f", "ray/core/src/ray/(raylet/raylet|gcs/gcs_server)"], capture_output=True, text=True
    ).stdout
    return {int(p) for p in out.split()}


@pytest.fixture(scope="module")
def cluster():
    from ray.cluster_utils import Cluster

    before = _ray_pids()
    os.environ["PYTHONPATH"] = (
        str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")
    )  # the test helpers on every worker's path
    c = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "num_gpus": 0, "node_ip_address": "127.0.0.1"})
    gpu_node = c.add_node(num_cpus=1, num_gpus=1, node_ip_address="127.0.0.1")
    c.wait_for_nodes()
    yield c, gpu_node.node_id
    if ray.is_initialized():
        ray.shutdown()
    c.shutdown()
    deadline = time.time() + 30
    while _ray_pids() - before and time.time() < deadline:
        time.sleep(0.5)
    assert not (_ray_pids() - before), "Ray processes left running"


def _ex(cluster, **kw):
    return RayExecutor(address=cluster[0].address, echo=None, poll_s=0.2, **kw)


def _rows(d):
    from trials.eval.episodes import read_rows

    return sorted(tuple(sorted((k, repr(v)) for k, v in r.items())) for r in read_rows(d / "episodes.csv"))


def test_a_recipe_grid_on_ray_writes_the_same_rows_and_figures_as_serially(
    cluster, tmp_path, tiny_policy_dir, pool_file
):
    from trials.experiments.recipes import resolve_experiment, run_experiment

    cfg = resolve_experiment(
        "quick",
        attack_overrides={
            "iterations": 1,
            "num_envs": 1,
            "rollout_steps": 1,
            "texture_size": 8,
            "pool_size": 4,
            "checkpoint_every": 1,
            "validation_every": 0,
        },
        episodes=8,
        max_steps=MAX_STEPS,
        num_envs=3,
        gifs=1,
        pool=str(pool_file),
    )
    run_experiment("table1", cfg, tmp_path / "serial", policy=tiny_policy_dir, progress=False, log=lambda m: None)
    ex = _ex(cluster)
    run_experiment(
        "table1",
        cfg,
        tmp_path / "ray",
        policy=tiny_policy_dir,
        progress=False,
        log=lambda m: None,
        executor=ex,
        shards=2,
    )
    a, b = tmp_path / "serial" / "evals" / "table1", tmp_path / "ray" / "evals" / "table1"
    assert _rows(a) == _rows(b) and len(_rows(a)) == 3 * 8
    sa, sb = (json.loads((d / "summary.json").read_text())["conditions"] for d in (a, b))
    assert json.dumps(sa, sort_keys=True) == json.dumps(sb, sort_keys=True)
    assert (tmp_path / "ray" / "table.md").read_text() == (tmp_path / "serial" / "table.md").read_text()
    assert {"attack-c2f", "attack-patch", "eval-table1-shard0of2", "eval-table1-shard1of2"} <= set(ex.placements)
    assert (tmp_path / "ray" / "logs" / "attack-c2f.log").read_text().count("== finished") == 1


def test_a_gpu_job_lands_only_on_the_node_with_a_gpu(cluster, tmp_path):
    g = Grid(tmp_path)
    for k in range(3):
        g.add(f"gpu{k}", "k", f"{H}:node_of", tmp_path / f"gpu{k}", num_cpus=0.5, num_gpus=1)
    ex = _ex(cluster)
    ex.run(g)
    nodes = {json.loads((tmp_path / f"gpu{k}" / "node.json").read_text())["node"] for k in range(3)}
    assert nodes == {cluster[1]}


def test_a_worker_killed_mid_job_is_retried_and_its_half_output_never_taken_as_finished(cluster, tmp_path):
    release = tmp_path / "release"
    g = Grid(tmp_path)
    job = g.add("victim", "k", f"{H}:slow_until_released", tmp_path / "victim", {"release": str(release)})
    seen = {}

    def killer():
        pid_file = tmp_path / "victim" / "pid"
        while not pid_file.is_file():
            time.sleep(0.1)
        pid = int(pid_file.read_text())
        seen["half"] = (tmp_path / "victim" / "half-written.json").is_file()
        seen["finished_before_kill"] = is_finished(job)
        os.kill(pid, signal.SIGKILL)
        pid_file.unlink()
        while not pid_file.is_file():  # the retry's worker
            time.sleep(0.1)
        release.write_text("go")

    t = threading.Thread(target=killer)
    t.start()
    _ex(cluster, max_retries=2).run(g)
    t.join(timeout=60)
    assert seen == {"half": True, "finished_before_kill": False}
    attempts = (tmp_path / "victim" / "attempts.txt").read_text().split()
    assert len(attempts) == 2 and attempts[0] != attempts[1] and is_finished(job)


def test_a_failing_job_fails_the_grid_in_one_line_after_the_running_job_finishes(cluster, tmp_path):
    def grid(bad: bool):
        g = Grid(tmp_path)
        g.add("slow", "k", f"{H}:write_value", tmp_path / "slow", {"value": 1, "sleep_s": 3.0})
        if bad:
            b = g.add("attack-bad", "k", f"{H}:bad_config", tmp_path / "bad", {"field": "lr"})
        else:
            b = g.add("attack-bad", "k", f"{H}:write_value", tmp_path / "bad", {"value": 2})
        g.add("after-bad", "k", f"{H}:write_value", tmp_path / "after", {"value": 3}, {"b": b})
        return g

    with pytest.raises(GridError, match=r"^job attack-bad: attack config: lr: must be positive$"):
        _ex(cluster).run(grid(True))
    assert is_finished(grid(True).jobs["slow"]) and not (tmp_path / "after").exists()
    _ex(cluster).run(grid(False))  # the re-run resumes: the slow job is reused, not redone
    assert len((tmp_path / "slow" / "attempts.txt").read_text().split()) == 1
    assert json.loads((tmp_path / "after" / "value.json").read_text())["total"] == 5


def test_without_a_shared_filesystem_outputs_come_back_to_out(cluster, tmp_path):
    ext = tmp_path / "external"
    ext.mkdir()
    (ext / "value.json").write_text('{"total": 10}')
    (tmp_path / "out" / "a").mkdir(parents=True)
    (tmp_path / "out" / "a" / "attempts.txt").write_text("earlier\n")  # a partial output it resumes from
    g = Grid(tmp_path / "out")
    a = g.add("a", "k", f"{H}:write_value", tmp_path / "out" / "a", {"value": 1}, {"ext": ext})
    g.add("b", "k", f"{H}:write_value", tmp_path / "out" / "b", {"value": 2}, {"a": a, "ext": ext})
    _ex(cluster, shared_fs=False).run(g)
    assert json.loads((tmp_path / "out" / "b" / "value.json").read_text())["total"] == 2 + 11 + 10
    assert all(is_finished(j) for j in g.order())
    assert "== finished" in (tmp_path / "out" / "logs" / "b.log").read_text()
    assert not list((tmp_path / "out").glob(".*incoming*")) and not list((tmp_path / "out").glob(".*replaced*"))
    assert (tmp_path / "out" / "a" / "attempts.txt").read_text().split()[0] == "earlier"


def test_a_job_no_node_can_take_is_refused_in_one_line(cluster, tmp_path):
    g = Grid(tmp_path)
    g.add("greedy", "k", f"{H}:node_of", tmp_path / "greedy", num_cpus=1, num_gpus=4)
    with pytest.raises(
        GridError, match=r"^job greedy: asks for 4 GPU\(s\) with 1 CPU\(s\), and no node of the cluster has that"
    ):
        _ex(cluster).run(g)


def test_eval_with_workers_starts_and_stops_its_own_ray_and_matches_serial(
    cluster, tmp_path, tiny_policy_dir, pool_file, attack_dir
):
    if ray.is_initialized():
        ray.shutdown()  # the CLI child starts its own local Ray; this process must not hold one
    before = _ray_pids()
    common = [
        sys.executable,
        "-m",
        "trials.cli.main",
        "eval",
        "--policy",
        str(tiny_policy_dir),
        "--pool",
        str(pool_file),
        "--attack",
        str(attack_dir),
        "--episodes",
        "6",
        "--max-steps",
        str(MAX_STEPS),
        "--num-envs",
        "2",
        "--gifs",
        "0",
    ]
    env = {**os.environ, "PYOPENGL_PLATFORM": "egl"}
    serial = subprocess.run(
        common + ["--out", str(tmp_path / "serial")], capture_output=True, text=True, env=env, cwd=ROOT
    )
    assert serial.returncode == 0, serial.stderr[-2000:]
    par = subprocess.run(
        common + ["--out", str(tmp_path / "ray"), "--workers", "2"], capture_output=True, text=True, env=env, cwd=ROOT
    )
    assert par.returncode == 0, par.stderr[-2000:]
    assert _rows(tmp_path / "serial") == _rows(tmp_path / "ray")
    assert "[grid]" in par.stdout and "jobs done" in par.stdout
    assert not (_ray_pids() - before)


def test_bad_scale_out_options_fail_in_one_line(tmp_path, tiny_policy_dir):
    for extra, msg in (
        (["--workers", "2", "--address", "auto"], "give one of them"),
        (["--address", "127.0.0.1:1"], "--address"),
    ):
        r = subprocess.run(
            [
                sys.executable,
                "-m",
                "trials.cli.main",
                "eval",
                "--policy",
                str(tiny_policy_dir),
                "--out",
                str(tmp_path / "o"),
            ]
            + extra,
            capture_output=True,
            text=True,
            cwd=ROOT,
            timeout=120,
        )
        assert r.returncode == 2 and msg in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr[-800:]


def test_the_tradeoff_sweep_runs_its_rows_as_ray_jobs_snapshot_after_its_baseline(
    cluster, tmp_path, tiny_policy_dir, mixed_pool_file
):
    from trials.experiments.tradeoff import BASELINE_KEY, load_tradeoff_config, run_sweep

    cfg = load_tradeoff_config(
        policy=str(tiny_policy_dir),
        pool=str(mixed_pool_file),
        snapshots=(1,),
        episodes=4,
        max_steps=MAX_STEPS,
        eval_num_envs=2,
        deploy_episodes=2,
        latency_reps=2,
        attack_overrides={
            "iterations": 2,
            "num_envs": 1,
            "rollout_steps": 1,
            "texture_size": 8,
            "checkpoint_every": 1000,
            "validation_every": 0,
        },
    )
    ex = _ex(cluster)
    res = {
        r["key"]: r for r in run_sweep(cfg, tmp_path, ["iterations"], progress=False, log=lambda m: None, executor=ex)
    }
    base, snap = res[BASELINE_KEY], res["iterations=1"]
    assert base["status"] == "ok" and snap["status"] == "ok", (base.get("traceback"), snap.get("traceback"))
    assert snap["attack_dir"].endswith("iter00001") and base["peak_rss_mb"] > 50
    assert set(ex.placements) == {"row-iterations_1", f"row-{BASELINE_KEY.replace('=', '_')}"}
    assert len((tmp_path / "rows.jsonl").read_text().splitlines()) == 2
