"""The job layer: a recipe's work as a DAG of jobs, run serially in-process or on Ray.

Jobs
    A :class:`Job` is one call ``fn(out, inputs, **params)`` of a module-level function (named
    ``"module:function"``, so any node with advobj installed can import it): ``train-policy``,
    ``pool``, ``attack``, ``eval`` (whole, or the merge of its shards) and ``eval-shard`` in the
    recipes, ``tradeoff-row`` in the speed-vs-accuracy sweep. ``inputs`` maps a role to a path; an
    input that another job produces makes that job a dependency, so an evaluation waits for its texture.

Keys
    A job's key is the SHA-256 of its kind, function, parameters, its inputs' keys and
    :data:`CODE_VERSION`. An input's key is the key of the job that produces it, or the digest of
    an external file or folder (its top-level files' names and bytes, plus ``best/``; a scene's
    YAML, not the meshes it names).

Finished
    A job is finished when ``<out>/job.json`` holds its key. That file is written last, through a
    temporary name and a rename, so a job killed half-way is never taken as finished; its function
    resumes from what it left (every job function here is resumable). A ``job.json`` with another
    key is refused in one line: the folder holds a different job's output.

Executors
    :class:`SerialExecutor` (the default) runs the jobs in-process, in dependency order, with no
    Ray started. :class:`RayExecutor` runs them as Ray tasks on a local Ray started for the run
    (``workers``) or on an existing cluster (``address``). Each task asks for the job's
    ``num_cpus`` and ``num_gpus`` (a GPU job never lands on a node without a GPU); torch inside a
    job uses ``num_cpus`` threads. Ray retries a task whose worker died (``max_retries``); a job
    that raises fails the grid with its error in one line, after the running jobs finish (their
    outputs are kept). Re-running the command resumes.

Outputs
    On one machine, or a cluster whose nodes share the output folder, jobs write straight into
    ``--out``. Without a shared filesystem (detected by a token file every node must see, or forced
    with ``shared_fs=False``) a job's inputs travel to its worker as Ray objects (gzipped tar
    bytes) with its own partial output, the job runs in a temporary folder there, and its output
    folder comes back to the driver as a Ray object, unpacked beside its place, checked for its
    finished marker and renamed into place.

Logs
    Each job's stdout, stderr and log lines go to ``<root>/logs/<job>.log``; the terminal shows one
    progress line for the grid (jobs done / running / queued, ETA from finished jobs' durations).
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import importlib
import importlib.util
import io
import json
import os
import re
import shutil
import socket
import sys
import tarfile
import tempfile
import time
import traceback
import uuid
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

from sim.errors import AdvobjError
from sim.runtime import set_torch_threads

__all__ = [
    "show_progress",
    "CODE_VERSION",
    "Job",
    "Grid",
    "GridError",
    "SerialExecutor",
    "RayExecutor",
    "make_executor",
    "usable_cpus",
    "input_digest",
    "MARKER_NAME",
    "is_finished",
    "clear_finished",
    "read_markers",
    "execute",
]

#: A finished job's marker in its output folder (key, timings); the job layer alone reads and writes it.
MARKER_NAME = "job.json"

# Part of every job key. Bump it when a job function's output changes for the same inputs, so
# finished outputs of the older code are not reused.
CODE_VERSION = "advobj-jobs/1"
# Resumable state that consumers of a job's output never read: not hashed, never shipped.
_PRIVATE_DIRS = ("checkpoint", "train_state", "shards")
_HASHED_DIRS = ("best",)


class GridError(AdvobjError, RuntimeError):
    """A job of the grid failed (its error in one line) or the grid itself is malformed."""

    def __init__(self, message: str, exit_code: int = 2):
        super().__init__(message)
        self.exit_code = exit_code


@dataclass
class Job:
    name: str
    kind: str
    fn: str
    out: str
    params: dict = field(default_factory=dict)
    inputs: dict = field(default_factory=dict)  # role -> path
    deps: tuple = ()
    num_cpus: float = 1.0
    num_gpus: float = 0.0
    local: bool = False  # cheap bookkeeping (merges): always runs in the driver
    fresh_process: bool = False  # a new worker process (measurements of the job's own peak memory)
    key: str = ""

    @property
    def log_name(self) -> str:
        return re.sub(r"[^A-Za-z0-9._-]", "_", self.name)[:120]


# ----------------------------------------------------------------------------- keys and markers
def input_digest(path: str | Path) -> str:
    """Content digest of an external input: a file's bytes, or a folder's top-level files (and
    ``best/``), names and bytes. Private resumable state (checkpoints) is left out."""
    p = Path(path)
    h = hashlib.sha256()
    if p.is_file():
        with open(p, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
        return h.hexdigest()
    if not p.is_dir():
        raise GridError(f"{p}: no such file or folder (a job input)")

    # Not the job layer's own bookkeeping (the marker holds timings, .job.lock is the run lock).
    def mine(f):
        return f.is_file() and f.name != MARKER_NAME and not f.name.startswith(".")

    files = [f for f in sorted(p.iterdir()) if mine(f)]
    files += [f for d in _HASHED_DIRS if (p / d).is_dir() for f in sorted((p / d).iterdir()) if mine(f)]
    for f in files:
        h.update(str(f.relative_to(p)).encode() + b"\0")
        h.update(hashlib.sha256(f.read_bytes()).digest())
    return h.hexdigest()


def job_key(kind: str, fn: str, params: dict, input_keys: dict) -> str:
    doc = {"kind": kind, "fn": fn, "params": params, "inputs": input_keys, "code": CODE_VERSION}
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()[:24]


def _marker(out: str | Path) -> Path:
    return Path(out) / MARKER_NAME


def is_finished(job: Job) -> bool:
    """Whether ``job``'s output is finished; a marker of another job is refused in one line."""
    m = _marker(job.out)
    if not m.is_file():
        return False
    try:
        have = json.loads(m.read_text()).get("key")
    except (OSError, json.JSONDecodeError):
        return False  # a torn marker cannot be: it is renamed into place; treat as unfinished
    if have != job.key:
        raise GridError(
            f"{job.out}: holds the output of a different job ({json.loads(m.read_text()).get('name')!r}, "
            f"key {have}); use another --out or delete that folder"
        )
    return True


def clear_finished(out: str | Path) -> None:
    """Forget that the job writing into ``out`` finished (its marker removed), so the next run does
    it again; its output stays, for the job function to resume from or overwrite."""
    _marker(out).unlink(missing_ok=True)


def read_markers(root: str | Path) -> list[dict]:
    """The markers of every finished job under ``root`` (``name``, ``kind``, ``key``, ``seconds``,
    ``cpu_s``, ...), in path order; unreadable ones are skipped."""
    docs = []
    for m in sorted(Path(root).rglob(MARKER_NAME)):
        try:
            doc = json.loads(m.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError):
            continue
        if isinstance(doc, dict):
            docs.append(doc)
    return docs


def _write_marker(job: Job, seconds: float, cpu_s: float) -> None:
    m = _marker(job.out)
    m.parent.mkdir(parents=True, exist_ok=True)
    tmp = m.with_name(f".{MARKER_NAME}.{uuid.uuid4().hex}.tmp")
    tmp.write_text(
        json.dumps(
            {
                "name": job.name,
                "kind": job.kind,
                "key": job.key,
                "params": job.params,
                "inputs": job.inputs,
                "seconds": round(seconds, 3),
                "cpu_s": round(cpu_s, 3),
                "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            },
            indent=2,
            default=str,
        )
    )
    tmp.replace(m)


# ----------------------------------------------------------------------------- the DAG
class Grid:
    """The jobs of one run, added in dependency order (a job's inputs exist before it)."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.jobs: dict[str, Job] = {}
        self._by_out: dict[str, str] = {}
        self._digests: dict[str, str] = {}
        self.reported: set[str] = set()  # jobs already named on the terminal (reused, or run by this grid)

    def add(
        self,
        name: str,
        kind: str,
        fn: str,
        out: str | Path,
        params: dict | None = None,
        inputs: dict | None = None,
        num_cpus: float = 1.0,
        num_gpus: float = 0.0,
        local: bool = False,
        after: tuple = (),
        key_params: dict | None = None,
        fresh_process: bool = False,
    ) -> Job:
        """Add a job (or return the same one added before). ``inputs`` maps a role to a path or to
        a :class:`Job` of this grid (then a dependency). ``after`` adds dependencies that are not
        part of the key, and ``key_params`` replaces ``params`` in the key: an evaluation merged
        from shards has the key of the same evaluation run whole, so either reuses the other."""
        params = json.loads(json.dumps(params or {}, default=str))
        paths, keys, deps = {}, {}, []
        for role, v in (inputs or {}).items():
            if v is None:
                continue
            if isinstance(v, Job):
                paths[role], keys[role] = v.out, v.key
                deps.append(v.name)
            else:
                # Absolute: a job's recorded config must not depend on which executor (or working
                # directory) ran it, or a run interrupted under one could not resume under another.
                p = str(Path(v).resolve())
                producer = self.producer(p)
                if producer is not None:
                    paths[role], keys[role] = p, producer.key
                    deps.append(producer.name)
                else:
                    if p not in self._digests:
                        self._digests[p] = input_digest(p)
                    paths[role], keys[role] = p, self._digests[p]
        for a in after:
            deps.append(a.name if isinstance(a, Job) else str(a))
        out = Path(out).resolve()
        job = Job(
            name,
            kind,
            fn,
            str(out),
            params,
            paths,
            tuple(dict.fromkeys(deps)),
            float(num_cpus),
            float(num_gpus),
            local,
            fresh_process,
        )
        job.key = job_key(
            kind, fn, params if key_params is None else json.loads(json.dumps(key_params, default=str)), keys
        )
        old = self.jobs.get(name)
        if old is not None:
            if old.key != job.key:
                raise GridError(f"job {name}: added twice with different parameters")
            return old
        if job.out in self._by_out:
            raise GridError(f"{job.out}: two jobs write there ({self._by_out[job.out]}, {name})")
        self.jobs[name] = job
        self._by_out[job.out] = name
        return job

    def order(self) -> list[Job]:
        return list(self.jobs.values())  # insertion order is a topological order (inputs first)

    def pending(self) -> list[Job]:
        """Unfinished jobs that something still needs: every unfinished job but those whose
        consumers are all finished (a finished merge needs none of its shards)."""
        jobs = self.order()
        finished = {j.name for j in jobs if is_finished(j)}
        needed: set[str] = set()
        for j in reversed(jobs):
            if j.name in finished:
                continue
            consumers = [c.name for c in jobs if j.name in c.deps]
            if not consumers or any(c in needed for c in consumers):
                needed.add(j.name)
        return [j for j in jobs if j.name in needed]

    def producer(self, path: str | Path) -> Job | None:
        """The job whose output folder holds ``path`` (itself or a parent), if any."""
        p = Path(path).resolve()
        for q in (p, *p.parents):
            name = self._by_out.get(str(q))
            if name is not None:
                return self.jobs[name]
        return None


# ----------------------------------------------------------------------------- running one job
_SHOW_PROGRESS = False


def show_progress() -> bool:
    """Whether the running job should draw its own progress bars: yes when its output is also on
    the terminal (the serial executor), no in a Ray worker (only its log file sees them)."""
    return _SHOW_PROGRESS


class _Tee(io.TextIOBase):
    def __init__(self, *streams):
        self.streams = streams

    def write(self, text):
        for s in self.streams:
            s.write(text)
        return len(text)

    def flush(self):
        for s in self.streams:
            s.flush()


def _resolve(fn: str) -> Callable:
    mod, _, attr = fn.partition(":")
    return getattr(importlib.import_module(mod), attr)


def _cpu_seconds() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def execute(job: Job, log_path: str | Path, tee: bool = False) -> dict:
    """Run ``job`` in this process: torch threads = its CPUs, output to its log (and, with
    ``tee``, to the terminal too), marker last."""
    global _SHOW_PROGRESS
    start_unix = time.time()
    log_path = Path(log_path)
    log_path.parent.mkdir(parents=True, exist_ok=True)
    threads = max(1, int(job.num_cpus))

    set_torch_threads(threads)
    t0, c0 = time.perf_counter(), _cpu_seconds()
    Path(job.out).mkdir(parents=True, exist_ok=True)
    lock = _lock(job)
    with lock, open(log_path, "a", buffering=1) as log:
        out, err = (_Tee(log, sys.stdout), _Tee(log, sys.stderr)) if tee else (log, log)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            print(f"== {job.name} ({job.kind}) key {job.key} on pid {os.getpid()}, {threads} torch thread(s)", file=log)
            _SHOW_PROGRESS = tee
            try:
                _resolve(job.fn)(Path(job.out), {k: Path(v) for k, v in job.inputs.items()}, **job.params)
            except BaseException:
                traceback.print_exc(file=log)
                raise
            finally:
                _SHOW_PROGRESS = False
        dt, dc = time.perf_counter() - t0, _cpu_seconds() - c0
        print(f"== finished in {dt:.1f} s wall, {dc:.1f} s CPU", file=log)
    _write_marker(job, dt, dc)
    return {"name": job.name, "seconds": dt, "cpu_s": dc, "start_unix": start_unix, "end_unix": time.time()}


@contextlib.contextmanager
def _lock(job: Job):
    """An exclusive lock on the job's output folder while it runs: two runs sharing an ``--out``
    never write one folder at once (the second fails in one line; re-run it afterwards)."""
    path = Path(job.out) / ".job.lock"
    with open(path, "w") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise GridError(
                f"{job.out}: another run is writing there now (job {job.name}); wait for it or use another --out"
            ) from None
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _one_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return (" ".join(text[-1].split()) if text else "") or type(err).__name__


def _job_error(job: Job, err: BaseException, log_path: Path) -> GridError:
    cause = getattr(err, "cause", None) or err  # a RayTaskError carries the job's own exception
    if isinstance(cause, AdvobjError):
        return GridError(f"job {job.name}: {' '.join(str(cause).split())}", 2)
    return GridError(f"job {job.name} failed ({type(cause).__name__}: {_one_line(cause)}); its log: {log_path}", 1)


# ----------------------------------------------------------------------------- progress
class _Progress:
    """One line for the grid: done / running / queued and an ETA from finished jobs' durations."""

    def __init__(self, total: int, skipped: int, slots: int, echo: Callable[[str], None] | None):
        self.total, self.done, self.slots, self.echo = total, skipped, max(1, slots), echo
        self.durations: list[float] = []
        self.t0 = time.perf_counter()

    def line(self, running: int, queued: int) -> str:
        # "running": handed to the executor (on Ray, possibly waiting there for a free CPU)
        eta = "?"
        if self.durations:
            left = running + queued
            s = sum(self.durations) / len(self.durations) * left / min(self.slots, max(1, left))
            eta = f"{s / 60:.1f} min" if s >= 60 else f"{s:.0f} s"
        return f"[grid] {self.done}/{self.total} jobs done, {running} running, {queued} queued, ETA {eta}"

    def show(self, running: int, queued: int, note: str = "") -> None:
        if self.echo is not None:
            self.echo(self.line(running, queued) + (f"  ({note})" if note else ""))


# ----------------------------------------------------------------------------- executors
def _report_reused(grid: Grid, todo: list, echo) -> None:
    if echo is None:
        return
    left = {j.name for j in todo}
    for j in grid.order():
        if j.name not in left and j.name not in grid.reported:
            echo(
                f"[grid] {j.name}: finished earlier, reused"
                if is_finished(j)
                else f"[grid] {j.name}: not needed (its consumers are finished)"
            )
            grid.reported.add(j.name)


class SerialExecutor:
    """Every job in this process, one after the other, in dependency order. No Ray."""

    slots = 1

    def __init__(self, echo: Callable[[str], None] | None = print, tee: bool = True):
        self.echo, self.tee = echo, tee

    def run(self, grid: Grid) -> dict:
        todo = grid.pending()
        _report_reused(grid, todo, self.echo)
        prog = _Progress(len(grid.jobs), len(grid.jobs) - len(todo), 1, self.echo)
        results = {}
        for i, job in enumerate(todo):
            prog.show(1, len(todo) - i - 1, f"running {job.name}")
            log_path = grid.root / "logs" / f"{job.log_name}.log"
            try:
                results[job.name] = execute(job, log_path, tee=self.tee)
            except Exception as err:
                raise _job_error(job, err, log_path) from err
            prog.done += 1
            prog.durations.append(results[job.name]["seconds"])
        if todo:
            prog.show(0, 0, "all finished")
        grid.reported.update(results)  # ran now: not "reused" on the next call
        return results


def _check_links(root: Path) -> None:
    """Every symbolic link under folder ``root`` points inside it, at no folder holding the link,
    else one line naming the link: staging ships what a link points to, so a link out of the
    folder would ship a file of the driver's machine the job was never given, and a link to its
    own folder would never end."""
    top = root.resolve()
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            link = Path(dirpath) / name
            if not link.is_symlink():
                continue
            target = link.resolve()
            if target != top and top not in target.parents:
                raise GridError(
                    f"{link}: a link to {target}, outside the job's folder {root}; staging ships only what the "
                    "folder holds (copy the file in)"
                )
            if target.is_dir() and (target == link.parent.resolve() or target in link.parent.resolve().parents):
                raise GridError(f"{link}: a link to {target}, a folder that holds the link (a loop)")


def _pack(path: str | Path, private: bool = False) -> bytes:
    """A file or folder as gzipped tar bytes; links are stored as what they point to, and must
    point inside the folder (:func:`_check_links`). Private resumable state is left out unless
    ``private`` (a job's own partial output, to resume from)."""
    p = Path(path)
    if p.is_dir():
        _check_links(p)
    buf = io.BytesIO()
    skip = () if private else _PRIVATE_DIRS
    with tarfile.open(fileobj=buf, mode="w:gz", dereference=True) as tar:
        if p.is_file():
            tar.add(p, arcname=p.name)
        else:
            tar.add(p, arcname=".", filter=lambda ti: None if any(part in skip for part in Path(ti.name).parts) else ti)
    return buf.getvalue()


def _unpack(blob: bytes, dest: Path) -> None:
    dest.mkdir(parents=True, exist_ok=True)
    with tarfile.open(fileobj=io.BytesIO(blob), mode="r:gz") as tar:
        tar.extractall(dest, filter="data")  # the 'data' filter refuses absolute paths, '..' and links out


def _staged_task(doc: dict, blobs: dict) -> dict:
    """A job on a node that does not share the output folder: inputs unpacked in a temporary
    folder, the job run there, its output folder and log packed back."""
    tmp = Path(tempfile.mkdtemp(prefix="advobj-job-"))
    try:
        inputs = {}
        own = blobs.pop("__out__", None)
        if own is not None:  # the job's partial output on the driver: resume from it
            _unpack(own[2], tmp / "out")
        for role, (kind, name, blob) in blobs.items():
            d = tmp / "in" / role
            _unpack(blob, d)
            inputs[role] = str(d / name) if kind == "file" else str(d)
        job = Job(**{**doc, "inputs": inputs, "out": str(tmp / "out"), "deps": tuple(doc["deps"])})
        log_path = tmp / "job.log"
        res = execute(job, log_path)
        res.update(out_blob=_pack(tmp / "out"), log=log_path.read_text(), node=_node_id())
        return res
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _shared_task(doc: dict) -> dict:
    doc = dict(doc)
    log = doc.pop("_log")
    job = Job(**{**doc, "deps": tuple(doc["deps"])})
    res = execute(job, log)
    res["node"] = _node_id()
    return res


def _node_id() -> str:
    try:
        import ray  # lazy: optional dependency (ray)

        return ray.get_runtime_context().get_node_id()
    except Exception:
        return "local"


def usable_cpus() -> int:
    """The CPUs this process may run on: its affinity mask where the OS keeps one, else the count."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


_RAY_EXTRA = "pip install 'advobj[ray]'"


def _ray_installed() -> bool:
    if "ray" in sys.modules:
        return sys.modules["ray"] is not None  # None: its import was refused (or failed) before
    return importlib.util.find_spec("ray") is not None


def _import_ray(flag: str):
    """``ray``, or one line naming ``flag`` and how to install it (a broken install included)."""
    try:
        import ray  # lazy: optional dependency (ray)
    except ImportError as err:
        raise GridError(f"{flag}: Ray cannot be imported ({_one_line(err)}); install it with {_RAY_EXTRA}") from None
    return ray


def _check_placeable(jobs: list, ray) -> None:
    """A job that asks for more CPUs or GPUs than any node has would wait forever: one line now."""
    nodes = [n.get("Resources", {}) for n in ray.nodes() if n.get("Alive")]
    for job in jobs:
        if job.local:
            continue
        if not any(r.get("CPU", 0) >= job.num_cpus and r.get("GPU", 0) >= job.num_gpus for r in nodes):
            what = f"{job.num_gpus:g} GPU(s)" if job.num_gpus else f"{job.num_cpus:g} CPU(s)"
            raise GridError(
                f"job {job.name}: asks for {what} with {job.num_cpus:g} CPU(s), and no node of the cluster has that"
                + (" (--device cuda on a cluster without GPUs?)" if job.num_gpus else "")
            )


# The client connection preface of HTTP/2 (RFC 9113, section 3.4) and an empty SETTINGS frame.
_H2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + b"\x00\x00\x00\x04\x00\x00\x00\x00\x00"
_H2_SETTINGS = 0x04


def _check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """``HOST:PORT`` is a Ray cluster's GCS, checked within ``timeout_s``, else one line.

    ``ray.init`` given a port where something else listens (a web server, a database) waits there
    for minutes, and a reachable port says nothing about what answers on it. A Ray head's GCS is a
    gRPC server, and gRPC speaks HTTP/2: a server answers the client's connection preface with a
    SETTINGS frame (9-byte header: 3 bytes of length, then type 0x04). So the check opens one TCP
    connection, sends the preface and reads 9 bytes, the whole under one deadline: a SETTINGS frame
    is Ray, anything else (an HTTP/1 server's ``HTTP/1.1 400``, a close) is not, and silence past
    the deadline is refused too. This costs one round trip, starts nothing and leaves no state, where
    running ``ray.init`` itself under a watchdog would leave a half-connected Ray in the process.
    A cluster with TLS on (``RAY_USE_TLS``) expects a TLS handshake first: only the connection is
    checked then."""
    host, sep, port = address.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise GridError(f"--address: expected 'auto' or HOST:PORT, got {address!r}")
    deadline = time.monotonic() + timeout_s
    head = b""
    try:
        with socket.create_connection((host, int(port)), timeout=timeout_s) as conn:
            if os.environ.get("RAY_USE_TLS", "0").lower() in ("1", "true"):
                return
            conn.sendall(_H2_PREFACE)
            while len(head) < 9:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError
                conn.settimeout(left)
                got = conn.recv(9 - len(head))
                if not got:
                    break
                head += got
    except TimeoutError:
        raise GridError(
            f"--address {address}: no answer as a Ray cluster within {timeout_s:g} s "
            "(give the head node's GCS port, 6379 by default)"
        ) from None
    except OSError as err:
        if not head:
            raise GridError(f"--address {address}: no Ray cluster answers there ({err.strerror or err})") from None
    if len(head) < 9 or head[3] != _H2_SETTINGS:
        raise GridError(
            f"--address {address}: the service there is not a Ray cluster (it does not answer in gRPC); give the "
            "head node's GCS port, 6379 by default"
        )


def _own_token() -> None:
    """A Ray started for the run authenticates its processes with a token (on by default in Ray
    2.60) and, when none is given, writes a new one to ``~/.ray/auth_token``: outside ``--out``,
    and left there. A token of this process's own in its environment (``RAY_AUTH_TOKEN``, inherited
    by every process Ray starts from it) writes none. Kept for the process's life, as Ray keeps the
    token it loaded: a later Ray of this process gets the same one. A token, token file or mode the
    user set is left alone."""
    if not any(k in os.environ for k in ("RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH", "RAY_AUTH_MODE")):
        os.environ["RAY_AUTH_TOKEN"] = uuid.uuid4().hex + uuid.uuid4().hex


def _sees(path: str, token: str) -> bool:
    try:
        return Path(path).read_text() == token
    except OSError:
        return False


class RayExecutor:
    """The jobs as Ray tasks: ``workers`` starts a local Ray for the run (``workers`` CPUs, the
    machine's GPUs), ``address`` joins a running cluster (``"auto"`` or ``HOST:PORT``)."""

    def __init__(
        self,
        workers: int | None = None,
        address: str | None = None,
        max_retries: int = 2,
        shared_fs: bool | None = None,
        echo: Callable[[str], None] | None = print,
        poll_s: float = 2.0,
        connect_timeout_s: float = 5.0,
    ):
        if (workers is None) == (address is None):
            raise GridError("--workers/--address: give exactly one (a local Ray with N workers, or a cluster to join)")
        if workers is not None and workers < 1:
            raise GridError(f"--workers: must be at least 1, got {workers}")
        if workers is not None and workers > usable_cpus():
            # Ray starts a worker process per CPU it is told of: more than the machine has only
            # fills its memory (and the jobs would share the same cores anyway).
            raise GridError(
                f"--workers: at most {usable_cpus()} on this machine (the CPUs this process may use), got {workers}"
            )
        self.flag = "--workers" if workers is not None else "--address"
        if not _ray_installed():
            raise GridError(f"{self.flag}: runs the jobs on Ray, which is not installed; install it with {_RAY_EXTRA}")
        self.workers, self.address, self.max_retries = workers, address, int(max_retries)
        self.shared_fs, self.echo, self.poll_s = shared_fs, echo, float(poll_s)
        self.connect_timeout_s = float(connect_timeout_s)
        self.slots = workers or 1
        self.placements: dict[str, str] = {}  # job name -> node id (tests and the benchmark read it)
        self.timings: dict[str, dict] = {}

    # -- cluster
    def _init(self):
        import ray  # lazy: optional dependency (ray)

        if ray.is_initialized():
            return False
        env = {k: os.environ[k] for k in ("PYOPENGL_PLATFORM", "PYTHONPATH") if k in os.environ}
        # The project importable on every local worker, whatever the driver's working directory.
        root = str(Path(__file__).resolve().parents[2])
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        kw = dict(include_dashboard=False, logging_level="ERROR", log_to_driver=False, runtime_env={"env_vars": env})
        try:
            if self.address is not None:
                ray.init(address=self.address, **kw)
            else:  # "local": a new Ray for this run, never a cluster that happens to be running
                _own_token()
                ray.init(address="local", num_cpus=self.workers, **kw)
        except (ConnectionError, RuntimeError, ValueError) as err:
            what = "--workers: the local Ray did not start"
            if self.address is not None:
                what = f"--address {self.address}: cannot join the Ray cluster"
            raise GridError(f"{what} ({' '.join(str(err).split())[:200]})") from None
        self.slots = max(1, int(ray.cluster_resources().get("CPU", 1)))
        return True

    def _detect_shared(self, root: Path) -> bool:
        import ray  # lazy: optional dependency (ray)
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy  # lazy: optional dependency (ray)

        if self.shared_fs is not None:
            return self.shared_fs
        root.mkdir(parents=True, exist_ok=True)
        token = uuid.uuid4().hex
        token_path = root / f".grid-token-{token[:12]}"
        token_path.write_text(token)
        probe = ray.remote(num_cpus=0)(_sees)
        nodes = [n["NodeID"] for n in ray.nodes() if n.get("Alive")]
        try:
            seen = ray.get(
                [
                    probe.options(scheduling_strategy=NodeAffinitySchedulingStrategy(n, soft=False)).remote(
                        str(token_path.resolve()), token
                    )
                    for n in nodes
                ],
                timeout=120,
            )
        except ray.exceptions.GetTimeoutError:
            raise GridError("the cluster's nodes did not answer the shared-filesystem probe within 120 s") from None
        token_path.unlink(missing_ok=True)
        return all(seen)

    # -- run
    def run(self, grid: Grid) -> dict:
        if not grid.pending():
            _report_reused(grid, [], self.echo)
            return {}
        if self.address not in (None, "auto"):
            _check_reachable(self.address, self.connect_timeout_s)  # before ray.init, which would wait there
        if self.address is None and "ray" not in sys.modules:
            # A Ray started for this run is single-machine: keep it on the loopback interface (Ray
            # otherwise advertises the machine's outward address). Read when ray is imported.
            os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
        ray = _import_ray(self.flag)
        # A local Ray started here shares the driver's fate: ray.init installs a SIGTERM handler that
        # exits through its atexit ray.shutdown, Ctrl-C reaches the ``finally`` below, and on Linux
        # its GCS and raylet are asked to die with the driver (PR_SET_PDEATHSIG), the workers with
        # their raylet; Ray's two agents exit within about a minute (they first try to report to the
        # dead GCS). tests/hostile/test_jobs_hostile_ray.py SIGKILLs a driver and checks all that.
        started = self._init()
        try:
            return self._run(grid, ray)
        finally:
            if started:
                ray.shutdown()

    def _run(self, grid: Grid, ray) -> dict:
        todo = grid.pending()
        _report_reused(grid, todo, self.echo)
        if not todo:
            return {}
        _check_placeable(todo, ray)
        shared = self._detect_shared(grid.root)
        prog = _Progress(len(grid.jobs), len(grid.jobs) - len(todo), self.slots, self.echo)
        waiting = {j.name: j for j in todo}
        finished = {j.name for j in grid.order() if j.name not in waiting}
        running: dict = {}  # ObjectRef -> (job, submit time)
        results, first_error = {}, None
        staged = ray.remote(_staged_task)
        direct = ray.remote(_shared_task)
        direct_fresh = ray.remote(max_calls=1)(_shared_task)
        last = 0.0

        def log_of(job):
            return grid.root / "logs" / f"{job.log_name}.log"

        def submit(job):
            opts = dict(
                num_cpus=job.num_cpus, num_gpus=job.num_gpus, max_retries=self.max_retries, retry_exceptions=False
            )
            doc = asdict(job)
            if shared:
                doc["_log"] = str(log_of(job).resolve())
                doc["out"] = str(Path(job.out).resolve())
                doc["inputs"] = {k: str(Path(v).resolve()) for k, v in job.inputs.items()}
                return (direct_fresh if job.fresh_process else direct).options(**opts).remote(doc)
            blobs = {r: ("file" if Path(p).is_file() else "dir", Path(p).name, _pack(p)) for r, p in job.inputs.items()}
            if Path(job.out).is_dir():
                blobs["__out__"] = ("dir", "out", _pack(job.out, private=True))
            return staged.options(**opts).remote(doc, blobs)

        while waiting or running:
            progressed = True
            while first_error is None and progressed:  # a local job finishing can make others ready
                progressed = False
                for name in [n for n, j in waiting.items() if all(d in finished for d in j.deps)]:
                    job = waiting.pop(name)
                    try:
                        if job.local:
                            results[name] = execute(job, log_of(job))
                            finished.add(name)
                            prog.done += 1
                            prog.durations.append(results[name]["seconds"])
                            progressed = True
                        else:
                            running[submit(job)] = (job, time.time())
                    except Exception as err:  # the driver's own part failed (packing, a local merge)
                        first_error = first_error or _job_error(job, err, log_of(job))
                        break
            if not running:
                if waiting and first_error is None:
                    raise GridError(f"jobs {', '.join(waiting)}: wait for jobs that never run")
                break
            done, _ = ray.wait(list(running), num_returns=1, timeout=self.poll_s)
            for ref in done:
                job, t_sub = running.pop(ref)
                try:
                    res = ray.get(ref)
                    if not shared:
                        self._land(job, res, log_of(job))
                except Exception as err:
                    if not shared:
                        tb = getattr(err, "traceback_str", None) or "".join(traceback.format_exception(err))
                        log_of(job).parent.mkdir(parents=True, exist_ok=True)
                        with open(log_of(job), "a") as f:
                            f.write(tb)
                    first_error = first_error or _job_error(job, err, log_of(job))
                    continue
                now = time.time()
                # Scheduling overhead: submission to the job's start on its worker, and its end
                # to the driver holding the result (output landed, for a staged job).
                res["start_delay_s"] = res["start_unix"] - t_sub
                res["collect_s"] = now - res["end_unix"]
                res["submit_unix"] = t_sub
                self.placements[job.name] = res.get("node", "?")
                self.timings[job.name] = {
                    k: res[k]
                    for k in ("seconds", "cpu_s", "start_delay_s", "collect_s", "submit_unix", "start_unix", "end_unix")
                    if k in res
                }
                results[job.name] = {k: v for k, v in res.items() if k not in ("out_blob", "log")}
                finished.add(job.name)
                prog.done += 1
                prog.durations.append(res["seconds"])
            now = time.time()
            if done or now - last > 30:
                prog.show(len(running), len(waiting))
                last = now
        grid.reported.update(results)  # ran now: not "reused" on the next call
        if first_error is not None:
            raise first_error
        prog.show(0, 0, "all finished")
        return results

    @staticmethod
    def _land(job: Job, res: dict, log_path: Path) -> None:
        """A staged job's output folder into place: unpacked beside it, then renamed over it."""
        out = Path(job.out)
        incoming = out.with_name(f".{out.name}.incoming-{uuid.uuid4().hex[:8]}")
        _unpack(res["out_blob"], incoming)
        try:
            landed = json.loads(_marker(incoming).read_text()).get("key")
        except (OSError, json.JSONDecodeError):
            landed = None
        if landed != job.key:
            shutil.rmtree(incoming, ignore_errors=True)
            raise GridError(f"job {job.name}: its output came back without its finished marker; re-run to resume")
        old = out.with_name(f".{out.name}.replaced-{uuid.uuid4().hex[:8]}")
        if out.exists():
            out.rename(old)  # aside first: the folder is never missing, nor half-replaced
        out.parent.mkdir(parents=True, exist_ok=True)
        incoming.rename(out)
        shutil.rmtree(old, ignore_errors=True)
        log_path.parent.mkdir(parents=True, exist_ok=True)
        with open(log_path, "a") as f:
            f.write(res.get("log", ""))


def make_executor(
    workers: int | None = None, address: str | None = None, echo: Callable[[str], None] | None = print, **kw
):
    """The serial executor unless ``workers`` or ``address`` asks for Ray."""
    if workers is None and address is None:
        return SerialExecutor(echo)
    return RayExecutor(workers=workers, address=address, echo=echo, **kw)
