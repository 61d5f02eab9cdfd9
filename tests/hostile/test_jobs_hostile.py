"""Hostile conditions for the job layer and its scale-out options, without starting Ray.

Checked: ``--workers`` with Ray not installed, ``--workers`` above the machine's CPUs and
``--address`` at a service that is not Ray (an HTTP server, a silent listener) each fail in one
line within seconds; staging refuses links out of a job's folder and link loops; a short
``--pool`` is topped up the same serially and through the job layer; ``bench tradeoff`` refuses
a corrupt policy before any row and fails a run whose every row failed.
"""

import http.server
import importlib.util
import json
import shutil
import socket
import sys
import threading
import time
from pathlib import Path

import pytest

from tests.trials import conftest as trials_conftest
from trials.jobs.dag import Grid, GridError, RayExecutor, usable_cpus

MAX_STEPS = trials_conftest.MAX_STEPS
tiny_policy_dir = trials_conftest.tiny_policy_dir  # the suite's tiny policy fixture, shared

H = "tests.trials.jobs.jobs_helpers"
needs_ray_installed = pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="ray not installed")


def _cli(argv, monkeypatch, capsys) -> tuple[int, list[str]]:
    """``advobj ARGV`` in this process: its exit code and its non-blank stderr lines."""
    from trials.cli.main import main

    monkeypatch.setattr(sys, "argv", ["advobj", *argv])
    with pytest.raises(SystemExit) as exc:
        main()
    return exc.value.code, [line for line in capsys.readouterr().err.splitlines() if line.strip()]


def _eval_argv(policy, out, *extra):
    return ["eval", "--policy", str(policy), "-c", "clean", "--episodes", "2", "--out", str(out), *extra]


def test_workers_without_ray_installed_is_one_line_naming_the_ray_extra(tmp_path, tiny_policy_dir, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # 'import ray' now fails as when it is not installed
    code, err = _cli(_eval_argv(tiny_policy_dir, tmp_path / "o", "--workers", "1"), monkeypatch, capsys)
    assert code == 2 and len(err) == 1, err
    assert "--workers" in err[0] and "pip install 'advobj[ray]'" in err[0] and "Traceback" not in err[0]
    assert not (tmp_path / "o").exists()


def test_more_workers_than_the_machine_has_cpus_is_refused_in_one_line(tmp_path, tiny_policy_dir, monkeypatch, capsys):
    code, err = _cli(_eval_argv(tiny_policy_dir, tmp_path / "o", "--workers", "10000"), monkeypatch, capsys)
    assert code == 2 and len(err) == 1, err
    assert f"--workers: at most {usable_cpus()}" in err[0] and "got 10000" in err[0]
    assert not (tmp_path / "o").exists()


class _Quiet(http.server.BaseHTTPRequestHandler):
    def log_message(self, *args):  # the test reads stderr: the server keeps quiet
        pass


@needs_ray_installed
def test_an_address_where_an_http_server_answers_is_refused_in_one_line_within_seconds(
    tmp_path, tiny_policy_dir, monkeypatch, capsys
):
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Quiet)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        address = f"127.0.0.1:{srv.server_address[1]}"
        t0 = time.perf_counter()
        code, err = _cli(_eval_argv(tiny_policy_dir, tmp_path / "o", "--address", address), monkeypatch, capsys)
        assert time.perf_counter() - t0 < 10
    finally:
        srv.shutdown()
        srv.server_close()
    assert code == 2 and len(err) == 1, err
    assert f"--address {address}: the service there is not a Ray cluster" in err[0]


@needs_ray_installed
def test_an_address_where_a_listener_never_answers_is_refused_after_the_connect_timeout(tmp_path):
    with socket.create_server(("127.0.0.1", 0)) as silent:  # accepts (the kernel's backlog) and says nothing
        address = f"127.0.0.1:{silent.getsockname()[1]}"
        g = Grid(tmp_path)
        g.add("a", "k", f"{H}:write_value", tmp_path / "a", {"value": 1})
        t0 = time.perf_counter()
        with pytest.raises(GridError, match=rf"^--address {address}: no answer as a Ray cluster within 1 s"):
            RayExecutor(address=address, echo=None, connect_timeout_s=1.0).run(g)
        assert time.perf_counter() - t0 < 5
    assert not (tmp_path / "a").exists()


def test_staging_ships_links_inside_the_folder_and_refuses_links_out_and_loops(tmp_path):
    import io
    import tarfile

    from trials.jobs.dag import _pack

    d = tmp_path / "in"
    (d / "sub").mkdir(parents=True)
    (d / "sub" / "a.txt").write_text("a")
    (d / "alias.txt").symlink_to(d / "sub" / "a.txt")
    with tarfile.open(fileobj=io.BytesIO(_pack(d)), mode="r:gz") as tar:
        assert tar.extractfile("./alias.txt").read() == b"a"  # shipped as what it points to
    (tmp_path / "secret.txt").write_text("s")
    (d / "leak.txt").symlink_to(tmp_path / "secret.txt")
    with pytest.raises(GridError) as err:
        _pack(d)
    assert str(err.value).startswith(f"{d / 'leak.txt'}: a link to {tmp_path / 'secret.txt'}, outside")
    (d / "leak.txt").unlink()
    (d / "sub" / "up").symlink_to(d)
    with pytest.raises(GridError, match="a folder that holds the link"):
        _pack(d)


def test_a_short_pool_is_topped_up_the_same_serially_and_through_the_job_layer(tmp_path, tiny_policy_dir, monkeypatch):
    """One evaluation-part configuration for 3 episodes: ``run_eval`` and the job layer (a pool
    job, then 2 shards) both top it up to 3 with the same configurations. The candidates' clean
    rollouts are stubbed to reach the goal (an untrained policy reaches none): the rule is what is
    checked."""
    from sim.configs import sample_pool, save_pool
    from sim.policies import pool as feasible_pool
    from sim.spec import default_scene
    from trials.eval.evaluate import load_eval_config, run_eval
    from trials.experiments.recipes import run_eval_grid
    from trials.jobs.dag import SerialExecutor

    spec = default_scene()
    spec = spec.with_updates(episode={**spec.episode.model_dump(), "max_steps": MAX_STEPS})
    short = tmp_path / "short.json"
    save_pool(short, spec, sample_pool(spec, 1, seed=0, part="evaluation"))

    def all_reach_the_goal(policy, spec, configs, num_envs, on_done, **kw):
        assert not kw  # the clean look: no texture, no stereo, no randomisation
        for j in range(len(configs)):
            on_done(j, j % num_envs, {"reached": spec.object_index("goal")})

    monkeypatch.setattr(feasible_pool, "rollout_paired", all_reach_the_goal)
    cfg = load_eval_config(
        policy=str(tiny_policy_dir),
        pool=str(short),
        conditions=("clean",),
        episodes=3,
        max_steps=MAX_STEPS,
        num_envs=2,
        gifs=0,
        seed=5,
    )
    serial = run_eval(cfg, tmp_path / "serial", progress=False)
    grid = run_eval_grid(cfg, tmp_path / "grid", SerialExecutor(None), shards=2)
    assert serial["conditions"]["clean"]["n"] == grid["conditions"]["clean"]["n"] == 3

    def seeds(d):
        return sorted(json.loads((d / "run.json").read_text())["config"]["seeds"])

    assert seeds(tmp_path / "serial") == sorted(
        s for k in range(2) for s in seeds(tmp_path / "grid" / "shards" / f"{k}-of-2")
    )


def test_bench_tradeoff_with_corrupt_policy_weights_fails_before_any_row(
    tmp_path, tiny_policy_dir, monkeypatch, capsys
):
    from sim.policies.checkpoint import WEIGHTS_NAME

    policy = tmp_path / "policy"
    shutil.copytree(tiny_policy_dir, policy)
    (policy / WEIGHTS_NAME).write_bytes(b"\0" * 64)
    t0 = time.perf_counter()
    code, err = _cli(
        ["bench", "tradeoff", "--policy", str(policy), "--out", str(tmp_path / "o"), "--quick-check"],
        monkeypatch,
        capsys,
    )
    assert time.perf_counter() - t0 < 30
    assert code == 2 and len(err) == 1, err
    assert "--policy" in err[0] and WEIGHTS_NAME in err[0]
    assert not (tmp_path / "o").exists()  # no row ran, nothing written


@pytest.mark.parametrize(
    "rows, code",
    [
        ([("a", "error", True), ("b", "error", True)], 2),  # every row failed on the user's input
        ([("a", "error", True), ("b", "error", False)], 1),  # one of them on something else
        ([("a", "error", True), ("b", "ok", False)], 0),  # one row measured: the run did its work
    ],
)
def test_a_tradeoff_run_whose_every_row_failed_exits_non_zero_in_one_line(
    tmp_path, tiny_policy_dir, monkeypatch, capsys, rows, code
):
    from trials.experiments import tradeoff

    def fake_sweep(cfg, out, wanted, **kw):  # the rows' records as the sweep appends them
        Path(out).mkdir(parents=True, exist_ok=True)
        for key, status, input_error in rows:
            tradeoff._append(Path(out), {"key": key, "status": status, "error": "X: bad", "input_error": input_error})

    monkeypatch.setattr(tradeoff, "run_sweep", fake_sweep)
    monkeypatch.setattr(tradeoff, "write_tradeoff_report", lambda out, plot=None: Path(out) / "rows.jsonl")
    argv = ["bench", "tradeoff", "--policy", str(tiny_policy_dir), "--out", str(tmp_path / "o"), "--quick-check"]
    got, err = _cli(argv, monkeypatch, capsys)
    assert got == code, err
    if code:
        assert len(err) == 1 and "all 2 rows this run measured failed (the first, a: X: bad)" in err[0], err
