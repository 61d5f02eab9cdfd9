"""Hostile conditions for the job layer that need a real local Ray on 127.0.0.1 (marked ``ray``).

Checked: a driver SIGKILLed mid-run with a local Ray of 2 workers leaves none of the processes it
started, and its Ray wrote no token into the home folder; the ``--address`` protocol check lets a
real Ray cluster through; staging refuses a link out of a job's input folder in one line.
"""

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

# Before ray is imported (it reads this then): the test Ray stays on 127.0.0.1.
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
ray = pytest.importorskip("ray")

from trials.jobs.dag import Grid, GridError, RayExecutor, usable_cpus  # noqa: E402

pytestmark = pytest.mark.ray
H = "tests.trials.jobs.jobs_helpers"
ROOT = Path(__file__).resolve().parents[2]


def _parents() -> dict[int, int]:
    """pid -> parent pid of every live (not zombie) process."""
    out = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2 :].split()  # after "pid (comm) "
        if fields[0] != "Z":
            out[int(d.name)] = int(fields[1])
    return out


def _cmd(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()[:150]
    except OSError:
        return "?"


def _descendants(pid: int) -> set[int]:
    parents = _parents()
    found, frontier = set(), {pid}
    while frontier:
        frontier = {p for p, pp in parents.items() if pp in frontier} - found
        found |= frontier
    return found


def test_a_sigkilled_driver_leaves_no_ray_process_and_no_token_in_home(tmp_path):
    if ray.is_initialized():
        ray.shutdown()
    home = tmp_path / "home"
    home.mkdir()
    release = tmp_path / "release"  # never written: the jobs run until killed
    driver = textwrap.dedent(
        f"""
        from trials.jobs.dag import Grid, RayExecutor
        g = Grid({str(tmp_path / "out")!r})
        for k in range(2):
            g.add(f"slow{{k}}", "k", "{H}:slow_until_released", {str(tmp_path / "out")!r} + f"/slow{{k}}",
                  {{"release": {str(release)!r}}})
        RayExecutor(workers={min(2, usable_cpus())}, echo=None, poll_s=0.2).run(g)
        """
    )
    env = {**os.environ, "HOME": str(home), "PYTHONPATH": str(ROOT)}
    env.pop("RAY_AUTH_TOKEN", None)
    proc = subprocess.Popen([sys.executable, "-c", driver], env=env, cwd=ROOT, stdout=subprocess.DEVNULL)
    try:
        pid_file = tmp_path / "out" / "slow0" / "pid"
        deadline = time.time() + 120
        while not pid_file.is_file() and time.time() < deadline and proc.poll() is None:
            time.sleep(0.2)
        assert pid_file.is_file(), "the job never started"
        started = {p: _cmd(p) for p in _descendants(proc.pid)}  # the command line tells a reused pid apart
        assert int(pid_file.read_text()) in started and len(started) >= 3  # Ray's own processes and the worker
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    # Ray's own fate-sharing: its processes get SIGKILL when the driver dies (PR_SET_PDEATHSIG), the
    # workers follow their raylet at once; its two agents notice the raylet gone within seconds, then
    # try to tell the (dead) GCS for up to 60 s before they exit.
    agents = {p for p, cmd in started.items() if "Agent" in cmd}

    def alive(pids):
        live = _parents()
        return {p: started[p] for p in pids if p in live and _cmd(p) == started[p]}

    for grace_s, which in ((30, set(started) - agents), (90, set(started))):
        deadline = time.time() + grace_s
        while (left := alive(which)) and time.time() < deadline:
            time.sleep(0.5)
        for pid in left:  # the test's own cleanup: only processes this driver started
            os.kill(pid, signal.SIGKILL)
        assert not left, f"left running {grace_s} s after the driver was killed: {left}"
    assert not (home / ".ray").exists()


@pytest.fixture(scope="module")
def local_ray():
    if ray.is_initialized():
        ray.shutdown()
    os.environ["PYTHONPATH"] = str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")
    ray.init(address="local", num_cpus=1, include_dashboard=False, logging_level="ERROR")
    yield ray.get_runtime_context().gcs_address
    ray.shutdown()


def test_the_address_check_lets_a_real_ray_cluster_through(local_ray):
    from trials.jobs.dag import _check_reachable

    t0 = time.perf_counter()
    _check_reachable(local_ray, timeout_s=5.0)
    assert time.perf_counter() - t0 < 5.0


def test_staging_refuses_a_link_out_of_the_input_folder_in_one_line(local_ray, tmp_path):
    secret = tmp_path / "secret.txt"
    secret.write_text("not for the cluster")
    src = tmp_path / "src"
    src.mkdir()
    (src / "value.json").write_text('{"total": 1}')
    (src / "leak.txt").symlink_to(secret)
    g = Grid(tmp_path / "out")
    g.add("a", "k", f"{H}:write_value", tmp_path / "out" / "a", {"value": 1}, {"src": src})
    with pytest.raises(GridError) as err:
        RayExecutor(address=local_ray, echo=None, poll_s=0.2, shared_fs=False).run(g)
    line = str(err.value)
    assert "\n" not in line and f"{src / 'leak.txt'}" in line and "outside the job's folder" in line
    assert not (tmp_path / "out" / "a" / "value.json").exists()
