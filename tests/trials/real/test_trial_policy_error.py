"""A policy that outputs NaN stops its trial as 'policy_error', the trial is committed, the session goes on."""

from __future__ import annotations

import numpy as np
import pytest

from tests.trials.real.trial_session_helpers import sim_hardware, small_plan, tiny_onnx
from trials.real.operator import AutoOperator
from trials.real.plan import load_plan
from trials.real.report import rate_cell
from trials.real.session import SessionOptions, run_session
from trials.real.store import TrialStore


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("policy_error")
    return {
        "policy": tiny_onnx(d / "p.onnx"),
        "plan": small_plan(d / "plan.yaml", d),
        "hw": sim_hardware(d / "hw.yaml"),
    }


class _NaNOnCalls:
    """The session's policy, but every call whose index is in ``bad`` returns NaN actions."""

    def __init__(self, policy, bad):
        self.policy, self.bad, self.calls = policy, set(bad), 0
        self.image_size = policy.image_size

    def act(self, images):
        out = np.asarray(self.policy.act(images), dtype=np.float64)
        self.calls += 1
        return np.full_like(out, np.nan) if self.calls - 1 in self.bad else out


def _run(files, db, bad, **options):
    def swap(runner, world):
        runner.policy = _NaNOnCalls(runner.policy, bad)
        runner.stop_on_reach = False  # every good trial runs max_steps: the call index of each trial is known

    opts = SessionOptions(
        hardware=files["hw"],
        policy=files["policy"],
        plan=files["plan"],
        session="s",
        db=db,
        rate_limit=False,
        **options,
    )
    return run_session(opts, operator=AutoOperator(log=None), on_ready=swap, log=lambda *_: None)


def test_nan_action_stops_the_trial_as_policy_error_and_the_session_goes_on(files, tmp_path):
    plan = load_plan(files["plan"])
    order = [t.trial_id for t in sorted(plan.trials, key=lambda t: t.order)]
    db = tmp_path / "t.sqlite"
    # call 2 is inside the first trial (max_steps 6): it stops there, after 2 steps
    summary = _run(files, db, bad={2}, max_trials=2)
    assert summary.committed == order[:2] and not summary.aborted
    with TrialStore(db) as store:
        rows = {r["trial_id"]: r for r in store.trial_rows()}
        bad = rows[order[0]]
        assert bad["auto_outcome"] == bad["final_outcome"] == "policy_error" and bad["operator_outcome"] is None
        assert bad["stop_reason"].startswith("policy_error: the policy output a non-finite action at step 2")
        assert bad["n_steps"] == 2  # the NaN action is never sent nor stored as a step
        ev = store.con.execute("SELECT kind, action, reason FROM events WHERE kind = 'policy'").fetchall()
        assert [(e["kind"], e["action"]) for e in ev] == [("policy", "error")] and "nan" in ev[0]["reason"]
        assert rows[order[1]]["final_outcome"] != "policy_error" and rows[order[1]]["n_steps"] == plan.max_steps
        steps = store.steps("s", order[0])
        assert all(np.isfinite([s[f"action_{i}"] for i in range(6)]).all() for s in steps)

    # resume: the remaining trials run; the first one is not repeated
    summary = _run(files, db, bad={0})  # the first call of the resumed run fails: the third trial is a policy error too
    assert summary.already_done == 2 and summary.committed == order[2:] and not summary.aborted
    with TrialStore(db) as store:
        outs = {r["trial_id"]: r["final_outcome"] for r in store.trial_rows()}
    assert set(outs) == set(order) and outs[order[2]] == "policy_error"
    assert [o for o in outs.values()].count("policy_error") == 2

    cell = rate_cell([{"final_outcome": o} for o in outs.values()])
    assert cell["policy_error"] == 2 and cell["n"] == len(order) - 2 and cell["unknown"] == 0

    # A policy error is not the operator's to change afterwards; its note is.
    from trials.real.store import StoreError

    with TrialStore(db) as store:
        with pytest.raises(StoreError, match="stopped on a policy error"):
            store.amend_trial("s", order[0], outcome="goal")
        store.amend_trial("s", order[0], note="NaN from the exported graph's LayerNorm")
        row = {r["trial_id"]: r for r in store.trial_rows()}[order[0]]
        assert row["final_outcome"] == "policy_error" and row["note"].startswith("NaN")


def test_a_version_2_store_is_migrated_keeping_its_trials(tmp_path):
    import sqlite3

    from trials.real import store as store_mod

    db = tmp_path / "old.sqlite"
    con = sqlite3.connect(db)
    con.executescript(
        store_mod._SCHEMA
        + "INSERT INTO schema_version VALUES (1);"
        + store_mod._MIGRATIONS[2]
        + "UPDATE schema_version SET version = 2;"
    )
    con.execute(
        "INSERT INTO sessions (name, created_at, plan_sha256, plan_text, hardware_text, policy_path, policy_sha256, "
        "software_version, git_commit, devices_json, calibration_json, config_json) VALUES "
        "('s','t','p','','','','','','','{}','{}','{}')"
    )
    con.execute(
        "INSERT INTO runs (session_id, started_at, software_version, git_commit, hardware_text, devices_json, "
        "config_json) "
        "VALUES (1, 't', '', '', '', '{}', '{}')"
    )
    cols = [r[1] for r in con.execute("PRAGMA table_info(trials)")]
    vals = {c: 0 for c in cols if c != "id"}
    vals.update(
        session_id=1,
        trial_id="t1",
        env="A",
        shape="cube",
        condition="clean",
        tags_json="[]",
        started_at="t",
        stop_reason="max_steps",
        auto_outcome="none",
        auto_reason="",
        distances_json="{}",
        final_outcome="none",
        frames_dir="f",
        texture_sha256=None,
        operator_outcome=None,
        run_id=1,
        note="",
    )
    con.execute(f"INSERT INTO trials ({', '.join(vals)}) VALUES ({', '.join('?' * len(vals))})", list(vals.values()))
    con.execute("INSERT INTO events VALUES (1, 0.0, 'k', 'a', 'r')")
    con.commit()
    con.close()
    with TrialStore(db) as store:
        assert store.con.execute("SELECT version FROM schema_version").fetchone()[0] == store_mod.SCHEMA_VERSION == 8
        assert [r["trial_id"] for r in store.trial_rows()] == ["t1"]
        assert store.con.execute("SELECT count(*) FROM events WHERE trial_row = 1").fetchone()[0] == 1
        assert store.con.execute("PRAGMA foreign_key_check").fetchone() is None
        assert store.con.execute("PRAGMA foreign_keys").fetchone()[0] == 1
        store.con.execute("UPDATE trials SET auto_outcome = 'policy_error', final_outcome = 'policy_error'")
        with pytest.raises(sqlite3.IntegrityError):
            store.con.execute("UPDATE trials SET final_outcome = 'bogus'")
