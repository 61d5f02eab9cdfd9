"""The trial store: one SQLite database per campaign, frames beside it.

Layout::

    trials.sqlite                      sessions, runs, trials, steps, object_poses, events, amendments
    frames/<session>/<trial_id>/       step_000.png ... (the wrist camera's images, the locator's)
                                       step_000_<camera>.png ... (each fixed camera the policy reads)

Durability rules (issue 8, "atomic trials"):

* WAL journal: readers (``advobj trial report`` while a session runs) never block the writer,
  and a crash leaves the last committed state intact.
* ``synchronous=FULL``: with WAL, ``NORMAL`` survives a killed *process* but may lose the last
  commits on power loss or an OS crash. The operator moves on to the next trial as soon as a trial
  is committed, so a committed trial must be on disk; one fsync per trial costs nothing next to a
  trial's minute of robot time.
* One transaction per trial (:meth:`TrialStore.commit_trial`): the runner buffers everything in
  memory and inserts it in one ``BEGIN IMMEDIATE ... COMMIT``. Killing the process at any moment
  loses at most the trial in progress and leaves no trace of it in the database.
* Frames are written *before* the trial's commit into the trial's own directory; a directory
  without a committed trial is a leftover of a killed run, and the runner clears it when it
  redoes that trial (:func:`frames_dir`).

Resuming (:meth:`TrialStore.open_session` on an existing session name) refuses inputs the
recorded trials depend on when they differ from the session's: the plan, the policy and the
calibration files (sha256 of each). What may legitimately change between sittings (the advobj
version and git commit, the hardware YAML, device serials) is accepted and recorded per run: one
``runs`` row per start or resume, and every trial names the run it was recorded in
(:meth:`TrialStore.check_resume` returns those changes as warnings). The table frame a session
started with (``T_base_table``, estimated or from a file) is stored with it and reused on resume.

Amendments (:meth:`TrialStore.amend_trial`, ``advobj trial amend``): a committed trial's outcome
or note is corrected in one transaction that also appends the values it replaces (and when, and
why) to ``amendments``; nothing is overwritten without its old value on record.

Poses are stored as 6-vectors ``[x, y, z (m), rx, ry, rz (rotation vector, rad)]`` in the
table frame (the sim world frame) unless a column name says ``base``: easy to read in CSV,
lossless at float64. A joint-space policy's step keeps its action, joint target, joints sent and
joints measured in ``joints_json`` (the arm's URDF chain order; its ``action_0..5`` are NULL) and
the TCP of the joints sent (forward kinematics) in the ``cmd_base`` columns.
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import json
import re
import shutil
import sqlite3
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Sequence

import yaml

from sim.errors import AdvobjError
from sim.paths import UnsafePathError, check_name, safe_join
from trials.real.locks import FileLock, LockBusy, describe_holder, holder_identity, pid_running

if TYPE_CHECKING:  # annotations only: numpy is imported where it is used (CLI start-up)
    import numpy as np

__all__ = [
    "SCHEMA_VERSION",
    "DEFAULT_DB",
    "StoreError",
    "SessionMismatch",
    "SessionInfo",
    "StepRecord",
    "JointStepRecord",
    "CameraFrameRecord",
    "ObjectPoseRecord",
    "EventRecord",
    "TrialRecord",
    "TrialStore",
    "pose_vec",
    "frames_root",
    "session_frames_dir",
    "frames_dir",
    "frames_ref",
    "camera_frame_name",
    "clear_frames",
    "check_database",
    "check_session_name",
    "SESSION_NAME_RULE",
    "EXPORT_TABLES",
]

SCHEMA_VERSION = 8
#: The trial database's file name when the operator names none (the ``--db`` default).
DEFAULT_DB = "trials.sqlite"
#: A trial's outcome. ``policy_error``: the policy gave a non-finite action; the trial stopped there
#: (the runner sets it, never the operator; reports count it apart from the rated trials).
OUTCOMES = ("goal", "adversarial", "none", "unknown", "policy_error")
EXPORT_TABLES = ("trials", "steps", "object_poses", "events", "sessions", "runs", "amendments")


class StoreError(AdvobjError, RuntimeError):
    """The trial database cannot be used (unknown schema, not a database, duplicate trial...)."""


class SessionMismatch(StoreError):
    """Resuming a session with a different plan, policy or calibration file than it was started with."""


_POSE = ("x_m", "y_m", "z_m", "rx_rad", "ry_rad", "rz_rad")


def _pose_cols(prefix: str) -> str:
    return ", ".join(f"{prefix}_{c} REAL" for c in _POSE)


_SCHEMA = f"""
CREATE TABLE schema_version (version INTEGER NOT NULL);
CREATE TABLE sessions (
    id INTEGER PRIMARY KEY,
    name TEXT NOT NULL UNIQUE,
    created_at TEXT NOT NULL,
    plan_sha256 TEXT NOT NULL,
    plan_text TEXT NOT NULL,
    hardware_text TEXT NOT NULL,
    policy_path TEXT NOT NULL,
    policy_sha256 TEXT NOT NULL,
    software_version TEXT NOT NULL,
    git_commit TEXT NOT NULL,
    devices_json TEXT NOT NULL,
    calibration_json TEXT NOT NULL,
    config_json TEXT NOT NULL
);
CREATE TABLE trials (
    id INTEGER PRIMARY KEY,
    session_id INTEGER NOT NULL REFERENCES sessions(id),
    trial_id TEXT NOT NULL,
    plan_order INTEGER NOT NULL,
    env TEXT NOT NULL,
    shape TEXT NOT NULL,
    condition TEXT NOT NULL,
    tcp_pose INTEGER NOT NULL,
    object_layout INTEGER NOT NULL,
    tags_json TEXT NOT NULL,
    texture_sha256 TEXT,
    started_at TEXT NOT NULL,
    duration_s REAL NOT NULL,
    n_steps INTEGER NOT NULL,
    stop_reason TEXT NOT NULL,
    auto_outcome TEXT NOT NULL CHECK (auto_outcome IN ('goal', 'adversarial', 'none', 'unknown')),
    auto_reason TEXT NOT NULL,
    distances_json TEXT NOT NULL,
    operator_outcome TEXT CHECK (operator_outcome IN ('goal', 'adversarial', 'none', 'unknown')),
    note TEXT NOT NULL DEFAULT '',
    final_outcome TEXT NOT NULL CHECK (final_outcome IN ('goal', 'adversarial', 'none', 'unknown')),
    placement_checks INTEGER NOT NULL,
    placement_skipped INTEGER NOT NULL,
    {_pose_cols("tcp_final")},
    frames_dir TEXT NOT NULL,
    UNIQUE (session_id, trial_id)
);
CREATE TABLE steps (
    trial_row INTEGER NOT NULL REFERENCES trials(id),
    step INTEGER NOT NULL,
    t_frame_s REAL NOT NULL,
    t_command_s REAL NOT NULL,
    frame_seq INTEGER NOT NULL,
    {", ".join(f"action_{i} REAL NOT NULL" for i in range(6))},
    {_pose_cols("cmd_base")},
    {_pose_cols("meas_base")},
    safety_status TEXT NOT NULL,
    safety_reason TEXT NOT NULL,
    frame_ref TEXT NOT NULL,
    PRIMARY KEY (trial_row, step)
);
CREATE TABLE object_poses (
    trial_row INTEGER NOT NULL REFERENCES trials(id),
    role TEXT NOT NULL,
    phase TEXT NOT NULL CHECK (phase IN ('placement', 'final')),
    found INTEGER NOT NULL,
    {_pose_cols("table")},
    yaw_rad REAL,
    center_x_m REAL, center_y_m REAL, center_z_m REAL,
    tag_ids_json TEXT NOT NULL,
    ambiguous INTEGER NOT NULL,
    n_alternatives INTEGER NOT NULL,
    source TEXT NOT NULL,
    PRIMARY KEY (trial_row, role, phase)
);
CREATE TABLE events (
    trial_row INTEGER NOT NULL REFERENCES trials(id),
    t_s REAL NOT NULL,
    kind TEXT NOT NULL,
    action TEXT NOT NULL,
    reason TEXT NOT NULL
);
CREATE INDEX steps_trial ON steps (trial_row);
CREATE INDEX events_trial ON events (trial_row);
"""

# Schema changes after version 1, applied in order to new and old databases alike (one
# transaction), so a version-1 store keeps its trials. Version 2: the session's table frame, and
# per-run provenance (a version-1 session gets one run from its own provenance columns).
_MIGRATIONS = {
    2: """
ALTER TABLE sessions ADD COLUMN T_base_table_json TEXT;
CREATE TABLE runs (
    id INTEGER PRIMARY KEY,
    session_id INTEGER NOT NULL REFERENCES sessions(id),
    started_at TEXT NOT NULL,
    software_version TEXT NOT NULL,
    git_commit TEXT NOT NULL,
    hardware_text TEXT NOT NULL,
    devices_json TEXT NOT NULL,
    config_json TEXT NOT NULL
);
CREATE INDEX runs_session ON runs (session_id);
ALTER TABLE trials ADD COLUMN run_id INTEGER REFERENCES runs(id);
INSERT INTO runs (session_id, started_at, software_version, git_commit, hardware_text, devices_json, config_json)
    SELECT id, created_at, software_version, git_commit, hardware_text, devices_json, config_json FROM sessions ORDER BY id;
UPDATE trials SET run_id = (SELECT r.id FROM runs r WHERE r.session_id = trials.session_id);
""",  # noqa: E501 (the migration SQL as run)
    3: "policy_error",  # the outcome CHECKs of trials gain 'policy_error': a table rebuild (_allow_policy_error)
    # Version 4: corrections of committed trials, each with the values it replaced.
    4: """
CREATE TABLE amendments (
    trial_row INTEGER NOT NULL REFERENCES trials(id),
    amended_at TEXT NOT NULL,
    old_final_outcome TEXT NOT NULL,
    old_operator_outcome TEXT,
    old_note TEXT NOT NULL,
    new_final_outcome TEXT NOT NULL,
    new_note TEXT NOT NULL,
    reason TEXT NOT NULL
);
CREATE INDEX amendments_trial ON amendments (trial_row);
""",
    # Version 5: what the paper's lighting and occlusion scenarios need per trial: the light level
    # the camera saw, and how much of each object's expected tag area was visible.
    5: """
ALTER TABLE trials ADD COLUMN light_level REAL;
ALTER TABLE object_poses ADD COLUMN visible_fraction REAL;
""",
    # Version 6: who runs a session now (issue 25): one row per locked session, beside the OS lock
    # (trials.real.locks), so a refused runner names the holder and a stale lock is recognised.
    6: """
CREATE TABLE session_locks (
    session TEXT PRIMARY KEY,
    host TEXT NOT NULL,
    pid INTEGER NOT NULL,
    proc_start TEXT,
    since TEXT NOT NULL
);
""",
    # Version 7: the frames of the fixed scene cameras a policy reads beside the wrist camera (issue
    # 27): per step, {camera: {frame_ref, frame_seq, t_frame_s}}; NULL when the policy reads none.
    7: """
ALTER TABLE steps ADD COLUMN camera_frames_json TEXT;
""",
    # Version 8: joint-space policies (issue 31): a step's joints, {action, q_target, q_cmd, q_meas}
    # (NULL for a TCP step), and the action columns NULL for a joint action (which has one value
    # per joint, not 6: it is in joints_json): a table rebuild (_joint_steps).
    8: "joint_steps",
}
_OLD_OUTCOMES_SQL = "IN ('goal', 'adversarial', 'none', 'unknown')"
_NEW_OUTCOMES_SQL = "IN ('goal', 'adversarial', 'none', 'unknown', 'policy_error')"


def _joint_steps(con: sqlite3.Connection) -> None:
    """Version 8: ``steps`` with nullable ``action_0..5`` and a ``joints_json`` column.

    The same rebuild as :func:`_allow_policy_error` (SQLite cannot drop a NOT NULL): a new table
    from the old one's own DDL, rows copied, the old one dropped, the new one renamed, its index
    made again; inside the caller's transaction.
    """
    ddl = con.execute("SELECT sql FROM sqlite_master WHERE type='table' AND name='steps'").fetchone()[0]
    copy = ddl.replace("CREATE TABLE steps", "CREATE TABLE steps_v8", 1)
    new = copy
    for i in range(6):
        new = new.replace(f"action_{i} REAL NOT NULL", f"action_{i} REAL", 1)
    if new != copy:  # a NOT NULL to drop
        con.execute(new)
        con.execute("INSERT INTO steps_v8 SELECT * FROM steps")
        con.execute("DROP TABLE steps")
        con.execute("ALTER TABLE steps_v8 RENAME TO steps")
        con.execute("CREATE INDEX steps_trial ON steps (trial_row)")
    con.execute("ALTER TABLE steps ADD COLUMN joints_json TEXT")


def _allow_policy_error(con: sqlite3.Connection) -> None:
    """Version 3: rebuild ``trials`` with 'policy_error' in its outcome CHECKs (SQLite cannot alter a CHECK).

    SQLite's documented procedure: a new table from the old one's own DDL (so every later column is
    kept), rows copied with their ids (the steps/object_poses/events references stay valid), the old
    one dropped and the new one renamed. Runs inside the caller's transaction, foreign keys off.
    """
    ddl = con.execute("SELECT sql FROM sqlite_master WHERE type='table' AND name='trials'").fetchone()[0]
    if _OLD_OUTCOMES_SQL not in ddl:
        raise sqlite3.DatabaseError("trials table: outcome constraint not the version-2 one")
    new = ddl.replace(_OLD_OUTCOMES_SQL, _NEW_OUTCOMES_SQL).replace("CREATE TABLE trials", "CREATE TABLE trials_v3", 1)
    con.execute(new)
    con.execute("INSERT INTO trials_v3 SELECT * FROM trials")
    con.execute("DROP TABLE trials")
    con.execute("ALTER TABLE trials_v3 RENAME TO trials")


# ---------------------------------------------------------------------- records
def pose_vec(T) -> list[float]:
    """``[x, y, z, rx, ry, rz]`` of a (4, 4) transform (NaN-filled for ``None``)."""
    import numpy as np  # lazy: CLI start-up (numpy)

    from sim.geometry import so3_log  # lazy: CLI start-up (+3 ms)

    if T is None:
        return [float("nan")] * 6
    T = np.asarray(T, dtype=np.float64)
    return [float(v) for v in T[:3, 3]] + [float(v) for v in so3_log(T[:3, :3])]


@dataclass(frozen=True)
class SessionInfo:
    """Everything recorded once per session (provenance and the exact inputs)."""

    name: str
    plan_sha256: str
    plan_text: str
    hardware_text: str
    policy_path: str
    policy_sha256: str
    software_version: str
    git_commit: str
    devices: dict | None  # {"camera": identity, "arm": identity}; None until the devices are connected
    calibration: dict
    config: dict = field(default_factory=dict)
    T_base_table: np.ndarray | None = None  # the table frame the trials are in (stored at the session's start)


@dataclass(frozen=True)
class CameraFrameRecord:
    """One fixed scene camera's frame of a step (the wrist camera's is the step's own columns)."""

    frame_ref: str  # path relative to the database's directory, in the trial's frame directory
    frame_seq: int
    t_frame_s: float  # capture, s since the trial's policy loop started


@dataclass(frozen=True)
class JointStepRecord:
    """A joint-space policy's step: joints in the arm's URDF chain order (rad, or m for a prismatic joint)."""

    q_target: Sequence[float]  # the target the action asks for (joint_delta: measured joints + action)
    q_cmd: Sequence[float] | None  # what the safety layer sent (clipped to the limits); None when refused
    q_meas: Sequence[float]  # measured after the command


@dataclass(frozen=True)
class StepRecord:
    step: int
    t_frame_s: float  # frame capture, s since the trial's policy loop started
    t_command_s: float  # arm accepted (or refused) the command, same clock
    frame_seq: int
    action: Sequence[float]  # raw policy output (before the scene's action scaling); a joint action: one per joint
    T_base_tcp_cmd: np.ndarray | None  # None when refused; a joint step: the TCP at the sent joints (FK)
    T_base_tcp_meas: np.ndarray  # measured after the command
    safety_status: str
    safety_reason: str
    frame_ref: str  # the wrist camera's frame, path relative to the database's directory
    camera_frames: dict[str, CameraFrameRecord] = field(default_factory=dict)  # scene camera -> its frame
    joints: JointStepRecord | None = None  # a joint-space policy's step; None: a TCP action


@dataclass(frozen=True)
class ObjectPoseRecord:
    role: str
    phase: str  # "placement" (the accepted check) or "final" (after the policy loop)
    T_table_object: np.ndarray | None  # None = not found
    center_table_m: np.ndarray | None
    tag_ids: tuple[int, ...]
    ambiguous: bool
    n_alternatives: int
    source: str  # "tags" or "sim"
    visible_fraction: float | None = None  # seen / expected tag area (tags only): 1 = unoccluded


@dataclass(frozen=True)
class EventRecord:
    t_s: float  # s since the trial started
    kind: str  # "safety", "operator", "placement"
    action: str
    reason: str


@dataclass
class TrialRecord:
    """One finished trial, as buffered by the runner and inserted in one transaction."""

    trial_id: str
    plan_order: int
    env: str
    shape: str
    condition: str
    tcp_pose: int
    object_layout: int
    tags: list[str]
    texture_sha256: str | None
    started_at: str  # ISO 8601 UTC
    duration_s: float
    stop_reason: str
    auto_outcome: str
    auto_reason: str
    distances_m: dict
    operator_outcome: str | None
    note: str
    placement_checks: int
    placement_skipped: bool
    T_table_tcp_final: np.ndarray
    frames_dir: str
    steps: list[StepRecord] = field(default_factory=list)
    object_poses: list[ObjectPoseRecord] = field(default_factory=list)
    events: list[EventRecord] = field(default_factory=list)
    light_level: float | None = None  # mean grey level (0-1) of the first frame of the policy loop

    @property
    def final_outcome(self) -> str:
        return self.operator_outcome or self.auto_outcome


def _camera_frames_json(frames: dict) -> str | None:
    if not frames:
        return None
    return json.dumps(
        {
            str(cam): {"frame_ref": f.frame_ref, "frame_seq": int(f.frame_seq), "t_frame_s": float(f.t_frame_s)}
            for cam, f in frames.items()
        },
        sort_keys=True,
    )


# The steps table's columns in the order commit_trial writes them (named: the insert does not rely on their order).
_STEP_COLUMNS = ", ".join(
    [
        "trial_row",
        "step",
        "t_frame_s",
        "t_command_s",
        "frame_seq",
        *(f"action_{i}" for i in range(6)),
        *(f"cmd_base_{c}" for c in _POSE),
        *(f"meas_base_{c}" for c in _POSE),
        "safety_status",
        "safety_reason",
        "frame_ref",
        "camera_frames_json",
        "joints_json",
    ]
)


def _joints_json(s: StepRecord) -> str | None:
    """``{action, q_target, q_cmd, q_meas}`` of a joint step (None for a TCP step)."""
    j = s.joints
    if j is None:
        return None

    def floats(v):
        return None if v is None else [float(x) for x in v]

    return json.dumps(
        {
            "action": floats(s.action),
            "q_target": floats(j.q_target),
            "q_cmd": floats(j.q_cmd),
            "q_meas": floats(j.q_meas),
        }
    )


def _action_columns(s: StepRecord) -> list[float | None]:
    """The six ``action_i`` columns: a TCP action's values; NULL for a joint action (in ``joints_json``)."""
    if s.joints is not None:
        return [None] * 6
    a = [float(v) for v in s.action]
    if len(a) != 6:
        raise StoreError(f"step {s.step}: a TCP action has 6 values, got {len(a)}")
    return a


def _sha(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


_SESSION_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")
SESSION_NAME_RULE = "1-64 letters, digits, '.', '_' or '-', starting with a letter or digit"


def check_session_name(value, what: str = "session") -> str:
    """``value`` if it is a session name, else :class:`UnsafePathError` naming ``what`` (``--session``).

    Stricter than :func:`sim.paths.check_name`: a session name becomes ``frames/<session>``, a lock
    file's name and a command-line value, so it starts with a letter or digit (never ``--``, ``-x``
    or ``_``), and holds no separator, space or control character.
    """
    if not isinstance(value, str) or _SESSION_NAME.fullmatch(value) is None:
        shown = repr(value) if isinstance(value, str) else f"a {type(value).__name__}"
        raise UnsafePathError(f"{what}: {shown[:80]} is not a safe name for a session: use {SESSION_NAME_RULE}")
    return value


def frames_root(db_path: str | Path) -> Path:
    """``<db dir>/frames``: every session's images live below it."""
    return Path(db_path).resolve().parent / "frames"


def session_frames_dir(db_path: str | Path, session: str, what: str = "session") -> Path:
    """``<db dir>/frames/<session>`` (resolved), refused unless ``session`` is a safe name inside ``frames/``.

    ``what`` names the input the session name came from in the error (``--session`` on the CLI).
    """
    check_session_name(session, what)
    return safe_join(frames_root(db_path), session, what=what)


def frames_dir(db_path: str | Path, session: str, trial_id: str) -> Path:
    """``<db dir>/frames/<session>/<trial_id>`` (resolved): where one trial's images go.

    Both names must be safe (:func:`sim.paths.check_name`) and the resolved directory must lie
    inside ``frames/`` (no symlink out of it): the runner clears and rewrites this directory.
    """
    check_session_name(session, "session")
    check_name(trial_id, "trial_id")
    return safe_join(frames_root(db_path), session, trial_id, what=f"frames of trial {trial_id!r}")


def frames_ref(session: str, trial_id: str) -> str:
    """The trial's frame directory relative to the database's directory, as stored (``frames/<session>/<trial_id>``)."""
    return f"frames/{check_session_name(session, 'session')}/{check_name(trial_id, 'trial_id')}"


def camera_frame_name(step: int, camera: str | None = None) -> str:
    """The file name of step ``step``'s frame in the trial's frame directory: ``step_007.png`` for the
    wrist camera (``camera`` None), ``step_007_<camera>.png`` for a fixed scene camera beside it."""
    if camera is None:
        return f"step_{int(step):03d}.png"
    return f"step_{int(step):03d}_{check_name(camera, 'camera')}.png"


def _now_iso() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def _one_line(err) -> str:
    return " ".join(str(err).split())


def _quick_check(con: sqlite3.Connection, path: Path) -> None:
    """``PRAGMA quick_check`` of an open database; a damaged one raises :class:`StoreError` (one line,
    nothing written)."""
    rows = [str(r[0]) for r in con.execute("PRAGMA quick_check").fetchall()]
    if rows != ["ok"]:
        more = f" (and {len(rows) - 1} more problems)" if len(rows) > 1 else ""
        raise StoreError(
            f"{path}: damaged trial database, refused without writing to it (SQLite quick_check: "
            f"{_one_line(rows[0] if rows else 'no answer')}{more}); restore it from a backup or give another --db"
        )


def check_database(path: str | Path) -> None:
    """Refuse an existing damaged or non-SQLite file at ``path`` (only read: nothing is created or written).

    Lets a command check its ``--db`` before any other work; :class:`TrialStore` checks again when it opens.
    """
    path = Path(path)
    if not path.exists():
        return
    if not path.is_file():
        raise StoreError(f"{path}: not a file (--db names the trial database file)")
    try:
        # read-write but only read: a read-only connection to a WAL database leaves its -wal/-shm behind
        con = sqlite3.connect(path, timeout=30.0)
    except sqlite3.DatabaseError as err:
        raise StoreError(f"{path}: not a usable trial database ({_one_line(err)})") from None
    try:
        _quick_check(con, path)
    except sqlite3.DatabaseError as err:
        raise StoreError(f"{path}: not a usable trial database ({_one_line(err)})") from None
    finally:
        con.close()


# ---------------------------------------------------------------------- store
class TrialStore:
    """The SQLite trial database at ``path`` (created on first use).

    One connection per store object; use one store per process (the runner writes, reports read).
    """

    def __init__(self, path: str | Path, create: bool = True):
        self.path = Path(path)
        self._session_locks: dict[str, tuple[FileLock, dict]] = {}  # session -> (its OS lock, the holder row)
        if not create and not self.path.is_file():
            raise StoreError(f"{self.path}: no trial database here (run 'advobj trial run' first)")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            # isolation_level=None: no implicit transactions; every write transaction is explicit.
            self.con = sqlite3.connect(self.path, isolation_level=None, timeout=30.0)
        except sqlite3.DatabaseError as err:
            raise StoreError(f"{self.path}: not a usable trial database ({_one_line(err)})") from None
        try:
            _quick_check(self.con, self.path)  # before the first write (the journal mode is one)
            self._runs: dict[int, int] = {}  # session id -> the run this process recorded (open_session)
            self.con.row_factory = sqlite3.Row
            mode = self.con.execute("PRAGMA journal_mode=WAL").fetchone()[0]
            self.con.execute("PRAGMA synchronous=FULL")
            self.con.execute("PRAGMA foreign_keys=ON")
            self._init_schema()
        except sqlite3.DatabaseError as err:
            self.con.close()
            raise StoreError(f"{self.path}: not a usable trial database ({_one_line(err)})") from None
        except BaseException:
            self.con.close()
            raise
        if mode.lower() != "wal":
            raise StoreError(
                f"{self.path}: cannot switch to WAL journal mode (got {mode!r}); is it on a network file system?"
            )

    def _init_schema(self) -> None:
        have = {r[0] for r in self.con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        if not have:
            self._write_schema(_SCHEMA, 1)
            return
        if "schema_version" not in have:
            raise StoreError(f"{self.path}: an SQLite database but not a trial store (no schema_version table)")
        row = self.con.execute("SELECT version FROM schema_version").fetchone()
        version = None if row is None else row[0]
        if isinstance(version, int) and 1 <= version < SCHEMA_VERSION:
            self._write_schema(None, version)
            return
        if version != SCHEMA_VERSION:
            newer = isinstance(version, int) and version > SCHEMA_VERSION
            raise StoreError(
                f"{self.path}: trial store schema version {version}, this advobj reads version {SCHEMA_VERSION}"
                + ("; upgrade advobj" if newer else "")
            )

    def _write_schema(self, base: str | None, version: int) -> None:
        """Create the version-1 schema (``base``) and/or migrate from ``version`` to the current one, in
        one transaction."""
        steps = [] if base is None else [base]
        steps += [_MIGRATIONS[v] for v in range(version + 1, SCHEMA_VERSION + 1)]
        self.con.execute("PRAGMA foreign_keys=OFF")  # a table rebuild drops a referenced table (checked below)
        self.con.execute("BEGIN IMMEDIATE")
        try:
            if base is None and self.con.execute("SELECT version FROM schema_version").fetchone()[0] == SCHEMA_VERSION:
                steps = []  # another process migrated it while this one waited for the lock
            for step in steps:
                if step == "policy_error":
                    _allow_policy_error(self.con)
                    continue
                if step == "joint_steps":
                    _joint_steps(self.con)
                    continue
                for stmt in step.split(";"):
                    if stmt.strip():
                        self.con.execute(stmt)
            if self.con.execute("PRAGMA foreign_key_check").fetchone() is not None:
                raise sqlite3.DatabaseError("foreign key check failed after the schema migration")
            if base is not None:
                self.con.execute("INSERT INTO schema_version VALUES (?)", (SCHEMA_VERSION,))
            else:
                self.con.execute("UPDATE schema_version SET version = ?", (SCHEMA_VERSION,))
            self.con.execute("COMMIT")
        except BaseException:
            self.con.execute("ROLLBACK")
            raise
        finally:
            self.con.execute("PRAGMA foreign_keys=ON")

    def close(self) -> None:
        for name in list(self._session_locks):
            self.release_session(name)
        self.con.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ------------------------------------------------------------------ sessions
    def session(self, name: str) -> sqlite3.Row | None:
        return self.con.execute("SELECT * FROM sessions WHERE name = ?", (name,)).fetchone()

    def check_resume(self, info: SessionInfo) -> list[str]:
        """Whether session ``info.name`` may be resumed with ``info``; returns the accepted changes as warnings.

        Raises :class:`SessionMismatch` naming every refused difference (old vs new sha256 and
        file): the plan, the policy, a calibration file. Trials recorded with other inputs are
        another experiment and must not be pooled under this session's provenance. A new
        advobj version or git commit, an edited hardware YAML or other device serials are
        legitimate between sittings (a bug fix, a new USB port): they are recorded per run and
        returned as warnings. A new session: nothing to check, ``[]``.
        """
        row = self.session(info.name)
        if row is None:
            return []
        config = json.loads(row["config_json"])
        old_files = config.get("calibration_files") or {}
        new_files = info.config.get("calibration_files") or {}

        def what(sha, path):
            return ("no file" if sha is None else f"sha256 {sha[:12]}...") + (f" ({path})" if path else "")

        refused = []
        if row["plan_sha256"] != info.plan_sha256:
            refused.append(
                f"plan: {what(row['plan_sha256'], config.get('plan'))} at the session's start, "
                f"now {what(info.plan_sha256, info.config.get('plan'))}"
            )
        if row["policy_sha256"] != info.policy_sha256:
            refused.append(
                f"policy: {what(row['policy_sha256'] or None, row['policy_path'])} at the session's start, "
                f"now {what(info.policy_sha256 or None, info.policy_path)}"
            )
        old_cal = json.loads(row["calibration_json"])
        for key in sorted(set(old_cal) | set(info.calibration)):
            if old_cal.get(key) != info.calibration.get(key):
                refused.append(
                    f"calibration {key}: {what(old_cal.get(key), old_files.get(key))} at the session's start, "
                    f"now {what(info.calibration.get(key), new_files.get(key))}"
                )
        if refused:
            raise SessionMismatch(
                f"session {info.name!r} in {self.path} was started with other inputs; its trials must not be "
                "mixed with "
                "trials run with these:\n  "
                + "\n  ".join(refused)
                + "\nresume with the original plan, policy and calibration files, or start a new --session"
            )
        last = self.con.execute(
            "SELECT * FROM runs WHERE session_id = ? ORDER BY id DESC LIMIT 1", (row["id"],)
        ).fetchone()
        if last is None:
            return []
        changed = []
        if last["software_version"] != info.software_version:
            changed.append(f"advobj version {last['software_version']} -> {info.software_version}")
        if last["git_commit"] != info.git_commit:
            changed.append(f"git commit {last['git_commit']} -> {info.git_commit}")
        if last["hardware_text"] != info.hardware_text:
            changed.append(
                f"hardware YAML (sha256 {_sha(last['hardware_text'])[:12]}... -> {_sha(info.hardware_text)[:12]}...)"
            )
        changed += self._device_change(last, info)
        return self._changes_message(info, last, changed)

    def device_changes(self, info: SessionInfo) -> list[str]:
        """Warnings for devices that differ from the session's last run (call once they are connected:
        a driver reads serial numbers from the device)."""
        row = self.session(info.name)
        last = (
            None
            if row is None
            else self.con.execute(
                "SELECT * FROM runs WHERE session_id = ? ORDER BY id DESC LIMIT 1", (row["id"],)
            ).fetchone()
        )
        return [] if last is None else self._changes_message(info, last, self._device_change(last, info))

    @staticmethod
    def _device_change(last, info: SessionInfo) -> list[str]:
        # devices=None: not known yet (before connecting), compared later by device_changes().
        if info.devices is None or json.loads(last["devices_json"]) == info.devices:
            return []
        return [f"devices {last['devices_json']} -> {json.dumps(info.devices)}"]

    @staticmethod
    def _changes_message(info: SessionInfo, last, changed: list[str]) -> list[str]:
        return [
            f"session {info.name!r}: {c} since the last run (started {last['started_at']}); "
            "new trials are recorded under this run (table runs)"
            for c in changed
        ]

    def open_session(self, info: SessionInfo) -> int:
        """The id of session ``info.name``: created, or resumed if :meth:`check_resume` allows; records this run."""
        import numpy as np  # lazy: CLI start-up (numpy)

        self.check_resume(info)
        row = self.session(info.name)
        T_json = (
            None if info.T_base_table is None else json.dumps(np.asarray(info.T_base_table, dtype=np.float64).tolist())
        )
        self.con.execute("BEGIN IMMEDIATE")
        try:
            if row is None:
                cur = self.con.execute(
                    "INSERT INTO sessions (name, created_at, plan_sha256, plan_text, hardware_text, policy_path, "
                    "policy_sha256, "
                    "software_version, git_commit, devices_json, calibration_json, config_json, T_base_table_json) "
                    "VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?)",
                    (
                        info.name,
                        _now_iso(),
                        info.plan_sha256,
                        info.plan_text,
                        info.hardware_text,
                        info.policy_path,
                        info.policy_sha256,
                        info.software_version,
                        info.git_commit,
                        json.dumps(info.devices),
                        json.dumps(info.calibration),
                        json.dumps(info.config, default=str),
                        T_json,
                    ),
                )
                sid = int(cur.lastrowid)
            else:
                sid = int(row["id"])
                if row["T_base_table_json"] is None and T_json is not None:  # a session from schema version 1
                    self.con.execute("UPDATE sessions SET T_base_table_json = ? WHERE id = ?", (T_json, sid))
            cur = self.con.execute(
                "INSERT INTO runs (session_id, started_at, software_version, git_commit, hardware_text, devices_json, "
                "config_json) "
                "VALUES (?,?,?,?,?,?,?)",
                (
                    sid,
                    _now_iso(),
                    info.software_version,
                    info.git_commit,
                    info.hardware_text,
                    json.dumps(info.devices),
                    json.dumps(info.config, default=str),
                ),
            )
            self._runs[sid] = int(cur.lastrowid)
            self.con.execute("COMMIT")
        except BaseException:
            self.con.execute("ROLLBACK")
            raise
        return sid

    def stored_T_base_table(self, name: str) -> np.ndarray | None:
        """The table frame session ``name`` was started with (None: no such session, or none stored)."""
        import numpy as np  # lazy: CLI start-up (numpy)

        row = self.session(name)
        if row is None or row["T_base_table_json"] is None:
            return None
        return np.asarray(json.loads(row["T_base_table_json"]), dtype=np.float64).reshape(4, 4)

    # ------------------------------------------------------------------ session locks
    def session_lock_path(self, name: str) -> Path:
        """``<db>-session-<name>.lock`` beside the database: the session's OS lock file."""
        check_session_name(name, "--session")
        return self.path.resolve().parent / f"{self.path.name}-session-{name}.lock"

    def lock_session(self, name: str, take_over_stale: bool = False, log=None) -> None:
        """Make this process the only runner of session ``name`` until :meth:`release_session` (or
        :meth:`close`): an OS lock on :meth:`session_lock_path` plus a ``session_locks`` row naming
        this process (host, pid, process start, since when).

        Another runner holding it: :class:`LockBusy` in one line naming it (host, pid), nothing
        written. The OS lock free but a row naming another holder (a run that was killed, or one on
        another host sharing this folder): taken over when that holder was on this host and its
        process is gone (logged), else refused unless ``take_over_stale`` (``--take-over-stale-lock``).
        """
        if name in self._session_locks:
            return
        lock = FileLock(self.session_lock_path(name))
        me = holder_identity(session=name, db=str(self.path))
        other = lock.acquire(me)
        if other is not None:
            if not other:
                row = self._lock_row(name)
                other = {} if row is None else row
            raise LockBusy(
                f"--session {name}: in use by {describe_holder(other)}; one session takes one runner: wait for that "
                "run to end or stop it (refused before any device connected and before anything was changed)"
            )
        try:
            self._claim_lock_row(name, me, take_over_stale, lock.path, log or (lambda _text: None))
        except BaseException:
            lock.release()
            raise
        self._session_locks[name] = (lock, me)

    def _lock_row(self, name: str) -> dict | None:
        row = self.con.execute("SELECT host, pid, proc_start, since FROM session_locks WHERE session = ?", (name,))
        row = row.fetchone()
        return None if row is None else {**dict(row), "session": name}

    def _claim_lock_row(self, name: str, me: dict, take_over: bool, path: Path, log) -> None:
        self.con.execute("BEGIN IMMEDIATE")
        try:
            old = self._lock_row(name)
            if old is not None:
                here = old["host"] == me["host"]
                gone = here and not pid_running(old["pid"], old["proc_start"])
                if not gone and not take_over:
                    where = (
                        f"still runs on this host but holds no lock on {path.name}"
                        if here
                        else "ran on another host, where this one cannot tell whether it still runs"
                    )
                    raise LockBusy(
                        f"--session {name}: the store names {describe_holder(old)} as its runner and that process "
                        f"{where}; if it no longer runs this session, pass --take-over-stale-lock"
                    )
                log(
                    f"session {name}: taking over the lock of {describe_holder(old)}: "
                    + ("that process is no longer running" if gone else "--take-over-stale-lock given")
                )
            self.con.execute(
                "INSERT OR REPLACE INTO session_locks (session, host, pid, proc_start, since) VALUES (?,?,?,?,?)",
                (name, me["host"], me["pid"], me["proc_start"], me["since"]),
            )
            self.con.execute("COMMIT")
        except BaseException:
            self.con.execute("ROLLBACK")
            raise

    def holds_session_lock(self, name: str) -> bool:
        """Whether this store holds session ``name``'s lock (its OS lock, and the row still names it)."""
        held = self._session_locks.get(name)
        if held is None or not held[0].held:
            return False
        row = self._lock_row(name)
        me = held[1]
        return row is not None and (row["host"], row["pid"], row["since"]) == (me["host"], me["pid"], me["since"])

    def check_session_owner(self, name: str) -> None:
        """:class:`LockBusy` unless this store holds session ``name`` (call before deleting or
        committing anything of it)."""
        if self.holds_session_lock(name):
            return
        row = self._lock_row(name)
        raise LockBusy(
            f"session {name}: this run does not hold its lock"
            + (f" (the store names {describe_holder(row)} as its runner)" if row else "")
            + "; nothing of the session is changed by it"
        )

    def release_session(self, name: str) -> None:
        """Drop session ``name``'s lock row (if it still names this process) and its OS lock."""
        held = self._session_locks.pop(name, None)
        if held is None:
            return
        lock, me = held
        try:
            self.con.execute("BEGIN IMMEDIATE")
            try:
                self.con.execute(
                    "DELETE FROM session_locks WHERE session = ? AND host = ? AND pid = ? AND since = ?",
                    (name, me["host"], me["pid"], me["since"]),
                )
                self.con.execute("COMMIT")
            except BaseException:
                self.con.execute("ROLLBACK")
                raise
        except sqlite3.Error:
            pass  # the row stays: a later runner on this host sees its pid gone and takes over
        finally:
            lock.release()

    @contextlib.contextmanager
    def session_locked(self, name: str, take_over_stale: bool = False, log=None):
        """``with store.session_locked(name):`` the session's lock for the block (kept if already held)."""
        if name in self._session_locks:
            yield
            return
        self.lock_session(name, take_over_stale, log)
        try:
            yield
        finally:
            self.release_session(name)

    def session_names(self) -> list[str]:
        return [r[0] for r in self.con.execute("SELECT name FROM sessions ORDER BY id")]

    def committed_trial_ids(self, session_id: int) -> set[str]:
        return {r[0] for r in self.con.execute("SELECT trial_id FROM trials WHERE session_id = ?", (session_id,))}

    # ------------------------------------------------------------------ trials
    def commit_trial(self, session_id: int, rec: TrialRecord) -> int:
        """Insert one whole trial atomically; returns its row id. Nothing of it remains on failure."""
        import numpy as np  # lazy: CLI start-up (numpy)

        for name, value in (("auto_outcome", rec.auto_outcome), ("operator_outcome", rec.operator_outcome)):
            if value is not None and value not in OUTCOMES:
                raise StoreError(f"trial {rec.trial_id}: {name} {value!r} is not one of {', '.join(OUTCOMES)}")
        c = self.con
        c.execute("BEGIN IMMEDIATE")
        try:
            owner = c.execute("SELECT name FROM sessions WHERE id = ?", (session_id,)).fetchone()
            if owner is not None and owner[0] in self._session_locks:
                self.check_session_owner(owner[0])  # taken over meanwhile (--take-over-stale-lock): commit nothing
            cur = c.execute(
                "INSERT INTO trials (session_id, trial_id, plan_order, env, shape, condition, tcp_pose, object_layout, "
                "tags_json, "
                "texture_sha256, started_at, duration_s, n_steps, stop_reason, auto_outcome, auto_reason, "
                "distances_json, "
                "operator_outcome, note, final_outcome, placement_checks, placement_skipped, "
                + ", ".join(f"tcp_final_{p}" for p in _POSE)
                + ", frames_dir, run_id, light_level) VALUES ("
                + ",".join("?" * 31)
                + ")",
                (
                    session_id,
                    rec.trial_id,
                    rec.plan_order,
                    rec.env,
                    rec.shape,
                    rec.condition,
                    rec.tcp_pose,
                    rec.object_layout,
                    json.dumps(list(rec.tags)),
                    rec.texture_sha256,
                    rec.started_at,
                    float(rec.duration_s),
                    len(rec.steps),
                    rec.stop_reason,
                    rec.auto_outcome,
                    rec.auto_reason,
                    json.dumps(rec.distances_m),
                    rec.operator_outcome,
                    rec.note or "",
                    rec.final_outcome,
                    int(rec.placement_checks),
                    int(rec.placement_skipped),
                    *pose_vec(rec.T_table_tcp_final),
                    rec.frames_dir,
                    self._runs.get(session_id),
                    None if rec.light_level is None else float(rec.light_level),
                ),
            )
            row = int(cur.lastrowid)
            c.executemany(
                f"INSERT INTO steps ({_STEP_COLUMNS}) VALUES (" + ",".join("?" * 28) + ")",
                [
                    (
                        row,
                        s.step,
                        float(s.t_frame_s),
                        float(s.t_command_s),
                        int(s.frame_seq),
                        *_action_columns(s),
                        *pose_vec(s.T_base_tcp_cmd),
                        *pose_vec(s.T_base_tcp_meas),
                        s.safety_status,
                        s.safety_reason,
                        s.frame_ref,
                        _camera_frames_json(s.camera_frames),
                        _joints_json(s),
                    )
                    for s in rec.steps
                ],
            )
            c.executemany(
                "INSERT INTO object_poses VALUES (" + ",".join("?" * 19) + ")",
                [
                    (
                        row,
                        o.role,
                        o.phase,
                        int(o.T_table_object is not None),
                        *pose_vec(o.T_table_object),
                        None
                        if o.T_table_object is None
                        else float(np.arctan2(o.T_table_object[1, 0], o.T_table_object[0, 0])),
                        *([None] * 3 if o.center_table_m is None else [float(v) for v in o.center_table_m]),
                        json.dumps([int(i) for i in o.tag_ids]),
                        int(o.ambiguous),
                        int(o.n_alternatives),
                        o.source,
                        None if o.visible_fraction is None else float(o.visible_fraction),
                    )
                    for o in rec.object_poses
                ],
            )
            c.executemany(
                "INSERT INTO events VALUES (?,?,?,?,?)",
                [(row, float(e.t_s), e.kind, e.action, e.reason) for e in rec.events],
            )
            c.execute("COMMIT")
        except sqlite3.IntegrityError as err:
            c.execute("ROLLBACK")
            raise StoreError(
                f"trial {rec.trial_id}: cannot store it ({err}); is another runner working on this session?"
            ) from None
        except BaseException:
            c.execute("ROLLBACK")
            raise
        return row

    def amend_trial(
        self, session: str, trial_id: str, outcome: str | None = None, note: str | None = None, reason: str = ""
    ) -> dict:
        """Correct a committed trial's outcome and/or note; the replaced values go to ``amendments``.

        ``outcome``: goal, adversarial, none or unknown (it becomes the operator's outcome, or clears
        it when equal to the automatic one). ``note``: replaces the trial's note. Returns the
        amendment row. Raises :class:`StoreError` naming the session or trial when there is none.
        """
        if outcome is None and note is None:
            raise StoreError("amend: give --outcome and/or --note")
        if outcome is not None and outcome not in ("goal", "adversarial", "none", "unknown"):
            raise StoreError(f"--outcome: {outcome!r} is not one of goal, adversarial, none, unknown")
        c = self.con
        c.execute("BEGIN IMMEDIATE")
        try:
            row = c.execute(
                "SELECT t.id, t.auto_outcome, t.operator_outcome, t.final_outcome, t.note FROM trials t "
                "JOIN sessions s ON s.id = t.session_id WHERE s.name = ? AND t.trial_id = ?",
                (session, trial_id),
            ).fetchone()
            if row is None:
                known = c.execute("SELECT 1 FROM sessions WHERE name = ?", (session,)).fetchone()
                raise StoreError(
                    f"--trial: no committed trial {trial_id!r} in session {session!r}"
                    if known
                    else f"--session: no session {session!r} in {self.path}"
                )
            if outcome is not None and row["auto_outcome"] == "policy_error":
                raise StoreError(
                    f"--outcome: trial {trial_id!r} stopped on a policy error (the policy's action was never sent); "
                    "its outcome is not the operator's to change, amend its --note only"
                )
            new_final = row["final_outcome"] if outcome is None else outcome
            new_op = (
                row["operator_outcome"] if outcome is None else (None if outcome == row["auto_outcome"] else outcome)
            )
            new_note = row["note"] if note is None else note
            amended_at = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
            c.execute(
                "INSERT INTO amendments VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    row["id"],
                    amended_at,
                    row["final_outcome"],
                    row["operator_outcome"],
                    row["note"],
                    new_final,
                    new_note,
                    reason,
                ),
            )
            c.execute(
                "UPDATE trials SET operator_outcome = ?, final_outcome = ?, note = ? WHERE id = ?",
                (new_op, new_final, new_note, row["id"]),
            )
            c.execute("COMMIT")
        except BaseException:
            c.execute("ROLLBACK")
            raise
        return {
            "trial_id": trial_id,
            "amended_at": amended_at,
            "old_final_outcome": row["final_outcome"],
            "new_final_outcome": new_final,
            "old_note": row["note"],
            "new_note": new_note,
            "reason": reason,
        }

    def amendments(self, sessions: Sequence[str] | None = None) -> list[dict]:
        q = (
            "SELECT s.name AS session, t.trial_id AS trial_id, a.* FROM amendments a JOIN trials t ON t.id = "
            "a.trial_row "
            "JOIN sessions s ON s.id = t.session_id"
            + (f" WHERE s.name IN ({','.join('?' * len(sessions))})" if sessions else "")
            + " ORDER BY a.rowid"
        )
        return [dict(r) for r in self.con.execute(q, tuple(sessions or ()))]

    def planned_trials(self, session: str) -> int:
        """How many trials the session's plan has (from the plan text stored with it)."""
        row = self.con.execute("SELECT plan_text FROM sessions WHERE name = ?", (session,)).fetchone()
        try:
            return len((yaml.safe_load(row["plan_text"]) or {}).get("trials", []))
        except (yaml.YAMLError, AttributeError, TypeError):
            return 0

    # ------------------------------------------------------------------ reading
    def trial_rows(self, sessions: Sequence[str] | None = None) -> list[dict]:
        """One dict per committed trial (plan order within each session), the report's input."""
        q = (
            "SELECT s.name AS session, t.* FROM trials t JOIN sessions s ON s.id = t.session_id"
            + (f" WHERE s.name IN ({','.join('?' * len(sessions))})" if sessions else "")
            + " ORDER BY s.id, t.plan_order"
        )
        out = []
        for r in self.con.execute(q, tuple(sessions or ())):
            d = dict(r)
            d["tags"] = json.loads(d.pop("tags_json"))
            d["distances_m"] = json.loads(d.pop("distances_json"))
            d["placement_skipped"] = bool(d["placement_skipped"])
            out.append(d)
        return out

    def steps(self, session: str, trial_id: str) -> list[dict]:
        """The trial's steps in order; ``camera_frames`` holds each scene camera's frame
        (``{camera: {frame_ref, frame_seq, t_frame_s}}``, empty for a wrist-only policy), ``joints``
        a joint-space policy's ``{action, q_target, q_cmd, q_meas}`` (None for a TCP action, whose
        values are ``action_0..5``)."""
        q = (
            "SELECT st.* FROM steps st JOIN trials t ON t.id = st.trial_row JOIN sessions s ON s.id = t.session_id "
            "WHERE s.name = ? AND t.trial_id = ? ORDER BY st.step"
        )
        out = []
        for r in self.con.execute(q, (session, trial_id)):
            d = dict(r)
            d["camera_frames"] = json.loads(d.pop("camera_frames_json") or "{}")
            d["joints"] = json.loads(d.pop("joints_json") or "null")
            out.append(d)
        return out

    def table(self, name: str) -> tuple[list[str], list[tuple]]:
        """Column names and rows of one exportable table, with session name and trial id joined in."""
        if name not in EXPORT_TABLES:
            raise StoreError(f"unknown table {name!r}; exportable: {', '.join(EXPORT_TABLES)}")
        if name == "sessions":
            q = "SELECT * FROM sessions ORDER BY id"
        elif name == "runs":
            q = "SELECT s.name AS session, r.* FROM runs r JOIN sessions s ON s.id = r.session_id ORDER BY r.id"
        elif name == "trials":
            q = (
                "SELECT s.name AS session, t.* FROM trials t JOIN sessions s ON s.id = t.session_id ORDER BY s.id, "
                "t.plan_order"
            )
        else:
            q = (
                f"SELECT s.name AS session, t.trial_id AS trial_id, x.* FROM {name} x JOIN trials t ON t.id = "
                "x.trial_row "
                "JOIN sessions s ON s.id = t.session_id ORDER BY s.id, t.plan_order, x.rowid"
            )
        cur = self.con.execute(q)
        cols = [d[0] for d in cur.description]
        return cols, [tuple(r) for r in cur.fetchall()]

    def integrity_check(self) -> str:
        return str(self.con.execute("PRAGMA integrity_check").fetchone()[0])

    # ------------------------------------------------------------------ export
    def export_csv(self, out_dir: str | Path, tables: Iterable[str] = EXPORT_TABLES) -> list[Path]:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        paths = []
        for name in tables:
            cols, rows = self.table(name)
            p = out / f"{name}.csv"
            with p.open("w", newline="") as f:
                w = csv.writer(f)
                w.writerow(cols)
                w.writerows(rows)
            paths.append(p)
        return paths

    def export_parquet(self, out_dir: str | Path, tables: Iterable[str] = EXPORT_TABLES) -> list[Path]:
        import pyarrow as pa  # lazy: CLI start-up (pyarrow)
        import pyarrow.parquet as pq  # lazy: CLI start-up (pyarrow)

        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        paths = []
        for name in tables:
            cols, rows = self.table(name)
            types = self._column_types(name)
            arrays = [pa.array([r[i] for r in rows], type=types.get(c)) for i, c in enumerate(cols)]
            p = out / f"{name}.parquet"
            pq.write_table(pa.Table.from_arrays(arrays, names=cols), p)
            paths.append(p)
        return paths

    def _column_types(self, name: str) -> dict:
        """Arrow types from the declared SQLite types (so an empty or all-NULL column keeps its type)."""
        import pyarrow as pa  # lazy: CLI start-up (pyarrow)

        m = {"INTEGER": pa.int64(), "REAL": pa.float64(), "TEXT": pa.string()}
        types = {"session": pa.string(), "trial_id": pa.string()}
        for r in self.con.execute(f"PRAGMA table_info({name})"):
            types.setdefault(r[1], m.get(r[2].upper(), pa.string()))
        return types


def clear_frames(path: Path) -> None:
    """Remove a trial's frame directory left by an interrupted run (no-op if absent).

    ``path`` comes from :func:`frames_dir` (checked to lie inside ``frames/``); a symlink is
    never followed: it is refused, not removed through.
    """
    if path.is_symlink():
        raise StoreError(f"{path}: a trial's frame directory is a symlink; refusing to clear it")
    if path.exists():
        shutil.rmtree(path)
