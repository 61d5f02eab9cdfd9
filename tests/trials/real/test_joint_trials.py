"""Real trials with a joint-space policy (issue 31, item 5), end to end on the sim twin.

The cell is the example sim hardware on ``scenes/panda-joint.yaml``: its sim arm is joint-driven by
the scene's Panda (``robot_io.config``), so a session runs a joint-space checkpoint (the untrained
``joint_policy`` of the attack tests, reading the seven joint positions, commanding ``joint_delta``)
through plan -> run -> report -> export unchanged. Every policy command is spied on at the safety
layer (``SafeArm.step_joints``) and at the driver (``SimArm.servo_joints`` / ``servo``): each one the
arm received went through the joint path, and nothing else moved it. Hostile joint policies (NaN, a
jump, targets far outside the limits, pushing a joint against its limit) are swapped in after the
session has loaded the real one; starts are TCP poses (solved by IK) or joint vectors (reached
exactly), and a start the arm cannot take is refused in one line before anything is recorded.

A driver's refusal (:class:`robot_io.errors.ArmRefusedError`) ends the trial, not the session: on
the sim arm, and with the session's arm swapped for a real driver on its byte-level twin (the
serial protocol's, a Feetech bus's) driving the same Panda, mid-trial and at a trial's start; a
fault still ends the session at the next start.
"""

from __future__ import annotations

import csv
import json
import re
import sqlite3
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from robot_io.arms.base import tcp_from_joints
from robot_io.arms.feetech import FeetechArm
from robot_io.arms.feetech_sim import FeetechSimulator
from robot_io.arms.serial import SerialArm
from robot_io.arms.serial_sim import SerialArmSimulator
from robot_io.arms.servo_bus import SimServo
from robot_io.arms.sim import SimArm
from robot_io.errors import ArmFaultError
from robot_io.poses import pose_step
from robot_io.safety import SafeArm
from sim.ik import TOL_M, TOL_RAD
from sim.policies.checkpoint import save_checkpoint
from sim.policies.contract import ActionContract, PolicyContract
from sim.spec import load_spec
from tests.attack.test_joint_attack import joint_policy
from tests.policy_zoo import card_of
from tests.robot_io.test_feetech import centred_joints
from tests.trials.real.trial_session_helpers import REPO, sim_hardware, small_plan
from trials.cli.main import app
from trials.real import store as store_mod
from trials.real.operator import AutoOperator
from trials.real.plan import Pose, load_plan, save_plan
from trials.real.runner import (
    START_AGREE_TOL_M,
    JointArmError,
    StartError,
    check_joint_arm,
    resolve_starts,
)
from trials.real.session import SessionOptions, SessionSetupError, run_session
from trials.real.store import TrialStore

PANDA_SCENE = REPO / "scenes" / "panda-joint.yaml"
MAX_STEPS = 4
FRAME_AGE_MS = 60_000.0
# a start TCP position inside the sim cell's workspace box, beyond the Panda's reach
OUT_OF_REACH_M = (0.85, 0.85, 0.85)


@pytest.fixture(scope="module")
def spec():
    return load_spec(PANDA_SCENE)


@pytest.fixture(scope="module")
def arm(spec):
    return spec.arm.scene_arm()


@pytest.fixture(scope="module")
def files(tmp_path_factory, spec):
    d = tmp_path_factory.mktemp("joint_trials")
    policy = joint_policy(spec)
    save_checkpoint(d / "ck", policy, card_of(policy))
    return {
        "dir": d,
        "policy": d / "ck",
        "plan": small_plan(
            d / "plan.yaml", d, n_tcp=2, n_layouts=1, max_steps=MAX_STEPS, conditions=("clean",), scene=PANDA_SCENE
        ),
        "hw": _patient_hardware(d / "hw.yaml"),
    }


def _patient_hardware(out: Path) -> Path:
    """The example sim hardware, whose frame-age limit a loaded test machine's first inference does not reach
    (these tests count commands; frame ages are the safety layer's tests')."""
    sim_hardware(out)
    doc = yaml.safe_load(out.read_text())
    doc["safety"]["max_frame_age_ms"] = FRAME_AGE_MS
    out.write_text(yaml.safe_dump(doc))
    return out


def _ik_start(arm, T_table_tcp) -> np.ndarray:
    """The joints the session starts a TCP pose at: the arm's solve_start (the simulator's start joints)."""
    res = arm.solve_start(torch.as_tensor(T_table_tcp)[None])
    assert bool(res.converged[0])
    return res.q[0].numpy()


@pytest.fixture
def spy(monkeypatch):
    """Every command of the session, at the safety layer and at the sim arm's driver."""
    calls = {"step_joints": [], "frames": [], "move_joints": [], "servo_joints": [], "tcp": []}
    step_joints, move_joints, servo_joints = SafeArm.step_joints, SafeArm.move_joints, SimArm.servo_joints

    def spy_step_joints(self, q_target, frame):
        res = step_joints(self, q_target, frame)
        calls["step_joints"].append((np.array(q_target, dtype=np.float64), res))
        calls["frames"].append(frame)
        return res

    def spy_move_joints(self, q):
        move_joints(self, q)
        calls["move_joints"].append((np.array(q, dtype=np.float64), self.joint_positions(), self.tcp_pose()))

    def spy_servo_joints(self, q, duration_s):
        calls["servo_joints"].append(np.array(q, dtype=np.float64))
        return servo_joints(self, q, duration_s)

    monkeypatch.setattr(SafeArm, "step_joints", spy_step_joints)
    monkeypatch.setattr(SafeArm, "move_joints", spy_move_joints)
    monkeypatch.setattr(SimArm, "servo_joints", spy_servo_joints)
    for cls, name in ((SafeArm, "step"), (SafeArm, "step_delta"), (SafeArm, "move_to"), (SimArm, "servo")):
        original = getattr(cls, name)

        def tcp_command(self, *args, _name=name, _original=original):
            calls["tcp"].append(_name)
            return _original(self, *args)

        monkeypatch.setattr(cls, name, tcp_command)
    return calls


def _run(files, db, plan=None, swap=None, **options):
    """A session of the module's cell; ``swap(runner)`` replaces its policy after the session loaded the real one."""

    def ready(runner, world):
        runner.stop_on_reach = False  # every trial runs its steps: the counts below are known
        if swap is not None:
            runner.policy = swap(runner)

    opts = SessionOptions(
        hardware=files["hw"],
        policy=files["policy"],
        plan=plan or files["plan"],
        session="s",
        db=db,
        **{"rate_limit": False, **options},  # a twin moving in real time needs the loop's rate
    )
    return run_session(opts, operator=AutoOperator(log=None), on_ready=ready, log=None)


class _Scripted:
    """A joint-space policy whose action ``fn(call, q)`` gives from the call index and the joints it reads."""

    image_size = 32

    def __init__(self, arm, fn, kind: str = "joint_delta", chunk: int = 1, execute: int = 1, joints=None):
        self.contract = PolicyContract(
            state=("joint_positions",),
            action=ActionContract(kind=kind, chunk=chunk, execute=execute),
            joints=arm.joint_names if joints is None else joints,
            joint_units=arm.units,
        )
        self.fn, self.calls, self.states = fn, 0, []

    def act(self, images, state):
        q = np.asarray(state, dtype=np.float64)[0]
        self.states.append(q)
        a = np.asarray(self.fn(self.calls, q), dtype=np.float64)
        self.calls += 1
        return a[None]


class _TcpToward:
    """A TCP policy (``absolute_tcp``, reading ``tcp_pose``) asking, every step, for its own orientation
    at table x = ``x_m``: straight along the table's +x, away from the Panda's base."""

    image_size = 32

    def __init__(self, x_m: float):
        self.contract = PolicyContract(state=("tcp_pose",), action=ActionContract(kind="absolute_tcp"))
        self.x_m = x_m

    def act(self, images, state):
        target = np.asarray(state, dtype=np.float64)[0].copy()
        target[0] = self.x_m
        return target[None]


def _joint_plan(files, arm, out: Path, edit) -> Path:
    """The module's plan with its starts edited: ``edit(plan, arm)`` returns the new ``tcp_poses`` entries."""
    plan = load_plan(files["plan"])
    return save_plan(plan.model_copy(update={"tcp_poses": edit(plan, arm)}), out)


def _steps(store, session="s"):
    return {r["trial_id"]: (r, store.steps(session, r["trial_id"])) for r in store.trial_rows([session])}


def _events(store) -> list[dict]:
    """Every event row, with its trial_id."""
    cols, rows = store.table("events")
    return [dict(zip(cols, r)) for r in rows]


def test_a_joint_policy_session_runs_every_command_through_step_joints_and_records_the_joints(
    files, arm, spy, tmp_path
):
    db = tmp_path / "t.sqlite"
    plan = load_plan(files["plan"])
    summary = _run(files, db)
    assert len(summary.committed) == len(plan.trials) and not summary.aborted

    # nothing but joint commands: no TCP step, servo or positioning move reached the arm
    assert spy["tcp"] == []
    sent = [res.q_cmd for _, res in spy["step_joints"] if res.status != "refused"]
    assert len(spy["servo_joints"]) == len(sent) == len(spy["step_joints"])
    for q_driver, q_safe in zip(spy["servo_joints"], sent):
        np.testing.assert_array_equal(q_driver, q_safe)

    with TrialStore(db, create=False) as store:
        trials = _steps(store)
        config = json.loads(store.session("s")["config_json"])
    assert config["joints"] == list(arm.joint_names) and config["joint_units"] == list(arm.units)
    n_steps = sum(len(steps) for _, steps in trials.values())
    assert n_steps == len(spy["step_joints"]) == len(trials) * MAX_STEPS
    lo, hi = arm.model.limits.q_min.numpy(), arm.model.limits.q_max.numpy()
    assert len(spy["move_joints"]) == len(trials)  # one positioning move per trial: to its start
    starts = iter(spy["move_joints"])
    for t in sorted(plan.trials, key=lambda t: t.order):
        row, steps = trials[t.trial_id]
        assert row["stop_reason"] == "max_steps" and row["n_steps"] == MAX_STEPS
        # the TCP start was solved by IK (the simulator's start joints) and reached with move_joints
        T_plan = plan.tcp_pose(t.tcp_pose).T_table_tcp.T()
        q_asked, q_at, T_at = next(starts)
        np.testing.assert_array_equal(q_asked, _ik_start(arm, T_plan))
        np.testing.assert_array_equal(q_at, q_asked)
        dp, dr = pose_step(T_plan, T_at)
        assert dp <= TOL_M and dr <= TOL_RAD
        q_prev = q_at
        for s in steps:
            j = s["joints"]
            assert s["safety_status"] in ("ok", "clipped") and s["action_0"] is None
            # joint_delta: the target is the measured joints plus the action; the arm is at what was sent
            np.testing.assert_allclose(j["q_target"], q_prev + np.asarray(j["action"]), rtol=0, atol=1e-12)
            assert len(j["q_meas"]) == arm.n_joints and np.all((lo <= j["q_cmd"]) & (j["q_cmd"] <= hi))
            np.testing.assert_array_equal(j["q_meas"], j["q_cmd"])
            # the TCP columns: the commanded TCP is the sent joints' FK, the measured one follows FK
            T_meas = tcp_from_joints(arm, j["q_meas"])
            meas = [s[f"meas_base_{c}"] for c in ("x_m", "y_m", "z_m")]
            cmd = [s[f"cmd_base_{c}"] for c in ("x_m", "y_m", "z_m")]
            np.testing.assert_allclose(meas, T_meas[:3, 3], rtol=0, atol=1e-9)
            np.testing.assert_allclose(cmd, tcp_from_joints(arm, j["q_cmd"])[:3, 3], rtol=0, atol=1e-9)
            q_prev = np.asarray(j["q_meas"])

    cli = CliRunner()
    out = tmp_path / "report"
    r = cli.invoke(app, ["trial", "report", "--db", str(db), "--out", str(out)])
    assert r.exit_code == 0, r.output
    report = json.loads((out / "report.json").read_text())
    assert all(row["final_outcome"] in ("goal", "adversarial", "none") for row, _ in trials.values())
    assert report["summary"]["all"]["by_condition"]["clean"]["n"] == len(plan.trials)  # every trial rated
    r = cli.invoke(app, ["trial", "export", "--db", str(db), "--out", str(tmp_path / "csv"), "--format", "csv"])
    assert r.exit_code == 0, r.output
    with (tmp_path / "csv" / "steps.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == n_steps and all(r["action_0"] == "" and json.loads(r["joints_json"])["q_cmd"] for r in rows)


def test_a_tcp_policy_driving_the_joint_arm_out_of_reach_ends_its_trial_with_the_reason_and_the_session_goes_on(
    files, arm, spec, tmp_path
):
    """A TCP policy in a scene with an arm: the sim arm follows it through IK until a target is out of
    reach (inside the workspace box); that target is refused as a real driver refuses it, the trial
    ends there with the reason, and the next trial runs."""
    base_x_m = float(spec.arm.scene_arm().T_world_base[0, 3])
    x_m = 0.89  # inside the cell's workspace box (0.9 m), more than the Panda's reach from its base
    max_steps = 150
    plan = small_plan(
        tmp_path / "plan.yaml", tmp_path, n_tcp=2, n_layouts=1, max_steps=max_steps, conditions=("clean",),
        scene=PANDA_SCENE,
    )  # fmt: skip
    db = tmp_path / "t.sqlite"
    summary = _run(files, db, plan=plan, swap=lambda runner: _TcpToward(x_m))
    assert len(summary.committed) == len(load_plan(plan).trials) == 2 and not summary.aborted
    with TrialStore(db, create=False) as store:
        trials = _steps(store)
    for row, steps in trials.values():
        assert re.match(
            r"^refused: sim arm: TCP target at \[.*\] m \(base frame\) is out of reach "
            r"within the joint limits \(IK from the current joints: .*\); the arm did not move$",
            row["stop_reason"],
        ), row["stop_reason"]
        assert 0 < row["n_steps"] == len(steps) < max_steps
        # it went along +x as far as the arm reaches, and no farther than the refused target
        x = [s["meas_base_x_m"] for s in steps]
        assert x[-1] > x[0] and x[-1] - base_x_m > 0.5
        refused_x = float(re.search(r"TCP target at \[([-0-9.]+),", row["stop_reason"])[1])
        assert x[-1] < refused_x < x_m


@pytest.fixture
def twin_driver(arm):
    """``make(kind)``: a driver of the scene's Panda (not connected) on its byte-level twin over a pty
    (``serial``: the advobj line protocol; ``feetech``: an STS3215 bus, each joint's range centred in
    its servo's turn), at the arm's home joints; every one made is disconnected and closed after the test."""
    made = []

    def make(kind: str):
        if kind == "serial":
            # the heartbeat only faults a device left moving: a slow machine's pause between steps is not one
            twin, path = SerialArmSimulator.on_pty(boot_delay_s=0.02, heartbeat_timeout_ms=60_000.0, scene_arm=arm)
            driver = SerialArm(path, timeout_ms=500.0, expect_banner=False, kinematics=arm)  # booted long before
        else:
            joints = centred_joints(arm)
            twin, path = FeetechSimulator.on_pty(
                [SimServo(j.id, position_ticks=j.to_ticks(q)) for j, q in zip(joints, arm.q_home)]
            )
            driver = FeetechArm(path, joints, arm)
        made.append((twin, driver))
        return driver

    yield make
    for twin, driver in made:
        driver.disconnect()
        twin.close()


def _on_twin(driver, policy):
    """A ``swap`` for :func:`_run`: the session's arm becomes ``driver`` behind the session's own safety
    limits (the sim camera and stage stay the cell's), and its policy ``policy``."""

    def swap(runner):
        runner.arm = SafeArm(driver, runner.arm.limits)
        runner.arm.connect()
        return policy

    return swap


def _joint_starts(plan, arm):
    """Every start given as the joints the session would solve its TCP pose to (reached with move_joints)."""
    return [
        tp.model_copy(update={"T_table_tcp": None, "joint_positions": tuple(_ik_start(arm, tp.T_table_tcp.T()))})
        for tp in plan.tcp_poses
    ]


@pytest.mark.parametrize(
    ("kind", "refusal"),
    [
        ("serial", r"^refused: serial arm \S+ rejected MOVE: ERR RANGE unreachable; the arm did not take it$"),
        ("feetech", r"^refused: feetech arm: TCP target\[0\]: the arm does not reach it .*; the arm did not move$"),
    ],
)
def test_a_twin_refusing_a_target_mid_trial_ends_that_trial_and_the_session_goes_on(
    files, arm, tmp_path, twin_driver, kind, refusal
):
    """A TCP policy heading out of the Panda's reach on a real driver and its byte-level twin: the serial
    device answers ERR RANGE unreachable, the bus arm's IK refuses; an ArmRefusedError, so each trial
    ends at its refused target with the reason, and the next trial runs (every trial is committed)."""
    base_x_m = float(arm.T_world_base[0, 3])
    x_m = 0.89  # inside the cell's workspace box (0.9 m), more than the Panda's reach from its base
    plan = small_plan(
        tmp_path / "tcp.yaml", tmp_path, n_tcp=2, n_layouts=1, max_steps=60, conditions=("clean",), scene=PANDA_SCENE
    )
    plan_path = save_plan(load_plan(plan).model_copy(update={"tcp_poses": _joint_starts(load_plan(plan), arm)}), plan)
    db = tmp_path / "t.sqlite"
    swap = _on_twin(twin_driver(kind), _TcpToward(x_m))
    summary = _run(files, db, plan=plan_path, swap=swap, rate_limit=True)  # a twin moves in real time
    assert len(summary.committed) == len(load_plan(plan_path).trials) == 2 and not summary.aborted
    with TrialStore(db, create=False) as store:
        trials = _steps(store)
        stopped = [e["trial_id"] for e in _events(store) if (e["kind"], e["action"]) == ("safety", "stopped")]
    for row, steps in trials.values():
        assert re.match(refusal, row["stop_reason"]), row["stop_reason"]
        assert 0 < row["n_steps"] == len(steps) < 60
        x = [s["meas_base_x_m"] for s in steps]
        assert x[-1] > x[0] and x[-1] - base_x_m > 0.5  # along +x as far as the arm reaches
        assert row["trial_id"] in stopped  # the safety layer stopped the arm on the refusal


@pytest.mark.parametrize("kind", ["sim", "serial"])
def test_a_start_the_arm_refuses_to_move_to_ends_that_trial_and_the_session_goes_on(
    files, arm, tmp_path, twin_driver, kind
):
    """The first trial's start is a TCP pose out of the Panda's reach (inside the workspace box, so the
    plan passes); a TCP policy's start is not solved up front, so the positioning move meets the arm's
    refusal (the sim arm's IK from its start seeds; the serial device's ERR RANGE unreachable). That trial
    is committed without steps, 'positioning_failed: refused: ...', outcome unknown, and the next one runs."""
    order = sorted(load_plan(files["plan"]).trials, key=lambda t: t.order)
    first = order[0].tcp_pose

    def edit(plan, arm):
        starts = _joint_starts(plan, arm)
        T = plan.tcp_poses[first].T_table_tcp.model_copy(update={"translation_m": OUT_OF_REACH_M})
        starts[first] = plan.tcp_poses[first].model_copy(update={"T_table_tcp": T})
        return starts

    plan_path = _joint_plan(files, arm, tmp_path / "plan.yaml", edit)
    db = tmp_path / "t.sqlite"
    policy = _TcpToward(0.5)
    swap = (lambda runner: policy) if kind == "sim" else _on_twin(twin_driver(kind), policy)
    summary = _run(files, db, plan=plan_path, swap=swap, rate_limit=kind != "sim")
    assert summary.committed == [t.trial_id for t in order] and not summary.aborted
    with TrialStore(db, create=False) as store:
        trials = _steps(store)
        events = _events(store)
    row, steps = trials[order[0].trial_id]
    where = ", ".join(f"{v:.3f}" for v in OUT_OF_REACH_M)
    reason = {
        "sim": rf"sim arm: TCP target at \[{where}\] m \(base frame\) is out of reach within the joint limits",
        "serial": r"serial arm \S+ rejected MOVE: ERR RANGE unreachable; the arm did not take it$",
    }[kind]
    assert re.match(rf"^positioning_failed: refused: {reason}", row["stop_reason"]), row["stop_reason"]
    assert row["n_steps"] == 0 and steps == [] and row["final_outcome"] == "unknown"
    assert row["auto_reason"] == row["stop_reason"] and row["operator_outcome"] is None
    mine = [(e["kind"], e["action"]) for e in events if e["trial_id"] == order[0].trial_id]
    assert ("positioning", "failed") in mine and ("safety", "stopped") in mine
    for t in order[1:]:
        row, steps = trials[t.trial_id]
        assert row["stop_reason"] == "max_steps" and len(steps) == MAX_STEPS


def test_a_fault_ends_the_session_at_the_next_start_and_that_trial_stays_to_do(files, arm, tmp_path):
    """A protective stop in the first trial's loop ends that trial (committed, 'fault: ...'); the arm still
    reporting it, the next trial's positioning move ends the session with the fault and records nothing,
    so resuming after the recovery runs that trial."""
    from robot_io.arms.base import Fault

    order = sorted(load_plan(files["plan"]).trials, key=lambda t: t.order)

    def fault_at_step_2(runner):
        driver = runner.arm._SafeArm__arm  # the sim driver behind the safety layer

        def on_step(trial, k):
            if k == 2:
                driver.inject_fault(Fault("protective_stop", "simulated protective stop", "clear it on the pendant"))

        runner.on_step = on_step
        return runner.policy

    db = tmp_path / "t.sqlite"
    with pytest.raises(ArmFaultError, match="protective_stop"):
        _run(files, db, swap=fault_at_step_2)
    with TrialStore(db, create=False) as store:
        trials = _steps(store)
    assert list(trials) == [order[0].trial_id]
    assert trials[order[0].trial_id][0]["stop_reason"].startswith("fault: arm fault (protective_stop)")
    summary = _run(files, db)  # the fault cleared (a new connection): the trial left to do runs
    assert summary.already_done == 1 and summary.committed == [t.trial_id for t in order[1:]]


def test_joint_vector_starts_are_reached_exactly_and_their_fk_agrees_with_a_tcp_pose_given_too(
    files, arm, spy, tmp_path
):
    def edit(plan, arm):
        first, second = plan.tcp_poses
        q0 = _ik_start(arm, first.T_table_tcp.T())  # both given: FK(q0) agrees with the pose
        q1 = _ik_start(arm, second.T_table_tcp.T())
        q1[0] += 0.05  # joints only: another start than the drawn pose's
        return [
            first.model_copy(update={"joint_positions": tuple(q0)}),
            second.model_copy(update={"T_table_tcp": None, "joint_positions": tuple(q1)}),
        ]

    plan_path = _joint_plan(files, arm, tmp_path / "plan.yaml", edit)
    plan = load_plan(plan_path)
    assert plan.tcp_poses[1].T_table_tcp is None
    assert "joint_positions" not in load_plan(files["plan"]).tcp_poses[0].model_dump()  # TCP plans dump as before
    summary = _run(files, tmp_path / "t.sqlite", plan=plan_path)
    assert len(summary.committed) == len(plan.trials)
    assert spy["tcp"] == []
    order = sorted(plan.trials, key=lambda t: t.order)
    assert len(spy["move_joints"]) == len(order)
    for t, (q_asked, q_at, T_at) in zip(order, spy["move_joints"]):
        q = np.asarray(plan.tcp_pose(t.tcp_pose).joint_positions)
        np.testing.assert_array_equal(q_asked, q)
        np.testing.assert_array_equal(q_at, q)
        np.testing.assert_allclose(T_at, tcp_from_joints(arm, q), rtol=0, atol=1e-12)


def test_an_object_unseen_at_the_end_is_looked_for_from_the_start_joints_and_the_arm_returns_to_its_own(
    files, arm, spy, tmp_path
):
    state = {"hide": False}

    def hide_the_goal_once_after_the_loop(runner):
        locate = runner.locator.locate

        def locate_hiding(frame, T_base_tcp):
            found = locate(frame, T_base_tcp)
            if state["hide"]:
                state["hide"] = False
                found = {role: obj for role, obj in found.items() if role != "goal"}
            return found

        def trial_end(trial):
            state["hide"], state["q_end"] = True, runner.arm.joint_positions()

        runner.locator.locate = locate_hiding
        runner.on_trial_end = trial_end
        return runner.policy

    db = tmp_path / "t.sqlite"
    _run(files, db, swap=hide_the_goal_once_after_the_loop, max_trials=1)
    with TrialStore(db, create=False) as store:
        ((row, _),) = _steps(store).values()
        looks = store.con.execute("SELECT reason FROM events WHERE action = 'look_again'").fetchall()
    assert len(looks) == 1 and "not seen from the final pose: goal; from the start pose: goal" in looks[0]["reason"]
    # start, the start again to look, then back to the joints the trial ended at: all joint moves
    (q_start, _, _), (q_look, _, _), (q_back, q_at, _) = spy["move_joints"]
    np.testing.assert_array_equal(q_look, q_start)
    np.testing.assert_array_equal(q_back, state["q_end"])
    np.testing.assert_array_equal(q_at, state["q_end"])
    assert spy["tcp"] == [] and row["final_outcome"] != "unknown"


@settings(max_examples=40, deadline=None)
@given(
    u=st.lists(st.floats(0.0, 1.0), min_size=7, max_size=7),
    offset=st.floats(0.0, 3.0).filter(lambda x: abs(x - 1.0) > 1e-6),
    direction=st.sampled_from([0, 1, 2]),
)
def test_a_start_given_both_ways_is_taken_iff_its_fk_is_within_the_tolerance_of_its_tcp_pose(
    files, arm, u, offset, direction
):
    """Any joints within the limits (their bounds included), their FK pose moved by ``offset`` times the
    position tolerance: accepted at the joints up to the tolerance, refused beyond it."""
    lo, hi = arm.model.limits.q_min.numpy(), arm.model.limits.q_max.numpy()
    q = np.clip(lo + np.asarray(u[: arm.n_joints]) * (hi - lo), lo, hi)
    T = tcp_from_joints(arm, q)
    T[direction, 3] += offset * START_AGREE_TOL_M
    plan = load_plan(files["plan"])
    first = plan.tcp_poses[0].model_copy(update={"T_table_tcp": Pose.from_T(T), "joint_positions": tuple(q)})
    plan = plan.model_copy(update={"tcp_poses": [first, *plan.tcp_poses[1:]]})
    trials = [t for t in plan.trials if t.tcp_pose == 0]
    if offset <= 1.0:
        (start,) = resolve_starts(plan, trials, np.eye(4), arm, joint_space=True).values()
        np.testing.assert_array_equal(start.q, q)
        np.testing.assert_allclose(start.T_base_tcp, tcp_from_joints(arm, q), rtol=0, atol=1e-12)
    else:
        with pytest.raises(StartError, match=r"joint_positions put the TCP .* mm and .* deg from its T_table_tcp"):
            resolve_starts(plan, trials, np.eye(4), arm, joint_space=True)


def _bad_length(plan, arm):
    first, *rest = plan.tcp_poses
    return [first.model_copy(update={"joint_positions": (0.0,) * (arm.n_joints - 1)}), *rest]


def _disagrees(plan, arm):
    first, *rest = plan.tcp_poses
    q = _ik_start(arm, first.T_table_tcp.T())
    q[0] += 0.1
    return [first.model_copy(update={"joint_positions": tuple(q)}), *rest]


def _outside_limits(plan, arm):
    first, *rest = plan.tcp_poses
    q = arm.q_home.copy()
    q[3] = float(arm.model.limits.q_max[3]) + 0.5
    return [first.model_copy(update={"T_table_tcp": None, "joint_positions": tuple(q)}), *rest]


def _out_of_reach(plan, arm):
    first, *rest = plan.tcp_poses
    T = first.T_table_tcp.model_copy(update={"translation_m": OUT_OF_REACH_M})
    return [first.model_copy(update={"T_table_tcp": T}), *rest]


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (_bad_length, r"^trial plan: tcp_poses\.0 \(trial .*\): joint_positions: \d+ values for the arm's \d+ joints"),
        (_disagrees, r"^trial plan: tcp_poses\.0 \(trial .*\): joint_positions put the TCP .* mm and .* deg from its "),
        (_outside_limits, r"^trial plan: tcp_poses\.0 \(trial .*\): joint_positions\.3: 'panda_joint4' at .* outside"),
        (
            _out_of_reach,
            rf"^trial A-cube-clean-t0-o0: start TCP pose 0 at \[{', '.join(f'{v:.3f}' for v in OUT_OF_REACH_M)}\] m "
            r"\(base frame\) is out of the arm's reach",
        ),
    ],
    ids=["wrong-length", "fk-disagrees", "outside-limits", "ik-fails"],
)
def test_a_start_the_arm_cannot_take_is_refused_in_one_line_before_anything_is_recorded(
    files, arm, tmp_path, edit, message
):
    plan_path = _joint_plan(files, arm, tmp_path / "plan.yaml", edit)
    db = tmp_path / "t.sqlite"
    with pytest.raises(StartError, match=message) as err:
        _run(files, db, plan=plan_path)
    assert "\n" not in str(err.value)
    with TrialStore(db) as store:
        assert store.session("s") is None


def _near_joint7_limit(plan, arm):
    """Every start a joint vector with the last joint 0.15 rad below its upper limit."""
    out = []
    for tp in plan.tcp_poses:
        q = _ik_start(arm, tp.T_table_tcp.T())
        q[-1] = float(arm.model.limits.q_max[-1]) - 0.15
        out.append(tp.model_copy(update={"T_table_tcp": None, "joint_positions": tuple(q)}))
    return out


def _nan_at_1(arm):
    return _Scripted(arm, lambda k, q: np.full(arm.n_joints, np.nan if k == 1 else 0.0))


def _inf_at_0(arm):
    return _Scripted(arm, lambda k, q: np.where(np.arange(arm.n_joints) == 2, np.inf, 0.0))


def _jump_at_1(arm):
    jump = np.zeros(arm.n_joints)
    jump[0] = 0.6  # beyond the default max_jump_rad (0.5)
    return _Scripted(arm, lambda k, q: jump if k == 1 else np.zeros(arm.n_joints))


def _far_outside_limits(arm):
    return _Scripted(arm, lambda k, q: np.full(arm.n_joints, 1e3), kind="joint_position")


@pytest.mark.parametrize(
    ("hostile", "steps", "stop"),
    [
        (_nan_at_1, 1, r"^policy_error: the policy output a non-finite action at step 1 \(\[nan, "),
        (_inf_at_0, 0, r"^policy_error: the policy output a non-finite action at step 0 \(\[0, 0, inf, "),
        (_jump_at_1, 2, r"^refused: joint jump: 'panda_joint1' target .* is 0\.6 rad from its position"),
        (_far_outside_limits, 1, r"^refused: joint jump: 'panda_joint1' target 1000 rad"),
    ],
    ids=["nan", "inf", "jump", "far-outside-limits"],
)
def test_a_hostile_joint_action_is_never_sent_and_ends_the_trial_with_the_reason(
    files, arm, spy, tmp_path, hostile, steps, stop
):
    db = tmp_path / "t.sqlite"
    summary = _run(files, db, swap=lambda runner: hostile(arm), max_trials=1)
    assert len(summary.committed) == 1
    with TrialStore(db, create=False) as store:
        ((row, recorded),) = _steps(store).values()
        events = store.con.execute("SELECT kind, action, reason FROM events").fetchall()
    assert row["n_steps"] == len(recorded) == steps
    assert re.match(stop, row["stop_reason"]), row["stop_reason"]
    policy_error = row["stop_reason"].startswith("policy_error")
    assert (row["final_outcome"] == "policy_error") == policy_error
    # the non-finite action never reached the safety layer; a refused one reached it and no further
    assert len(spy["step_joints"]) == steps
    sent = [res for _, res in spy["step_joints"] if res.status != "refused"]
    assert len(spy["servo_joints"]) == len(sent) and spy["tcp"] == []
    if not policy_error:
        last = recorded[-1]
        assert last["safety_status"] == "refused" and last["joints"]["q_cmd"] is None and last["cmd_base_x_m"] is None
        assert any(e["kind"] == "safety" and e["action"] == "refused" for e in events)


def test_a_joint_pushed_against_its_limit_is_clipped_there_and_never_passes_it(files, arm, spy, tmp_path):
    plan_path = _joint_plan(files, arm, tmp_path / "plan.yaml", _near_joint7_limit)
    push = np.zeros(arm.n_joints)
    push[-1] = 0.3  # toward the upper limit, 0.15 rad away, below a jump
    db = tmp_path / "t.sqlite"
    policy = _Scripted(arm, lambda k, q: push)
    _run(files, db, plan=plan_path, swap=lambda runner: policy, max_trials=1)
    with TrialStore(db, create=False) as store:
        ((row, recorded),) = _steps(store).values()
    # the policy read the measured joints: the start's, then each step's (float32, as the sim's state)
    (q_start, _, _), *_ = spy["move_joints"]
    read = [q_start, *(s["joints"]["q_meas"] for s in recorded[:-1])]
    np.testing.assert_allclose(policy.states, np.float32(read), rtol=0, atol=0)
    hi = float(arm.model.limits.q_max[-1])
    assert row["n_steps"] == MAX_STEPS and row["stop_reason"] == "max_steps"
    assert all(s["safety_status"] == "clipped" for s in recorded)
    assert "outside the position limits: 'panda_joint7' clipped to" in recorded[0]["safety_reason"]
    assert all(s["joints"]["q_target"][-1] > hi >= s["joints"]["q_cmd"][-1] for s in recorded)
    assert recorded[-1]["joints"]["q_meas"][-1] == hi  # it got there, and no farther
    assert max(q[-1] for q in spy["servo_joints"]) == hi


def test_a_chunked_joint_policy_is_asked_once_per_executed_part_of_a_chunk(files, arm, spy, tmp_path):
    chunk, execute = 3, 2
    policy = _Scripted(arm, lambda k, q: np.zeros((chunk, arm.n_joints)), chunk=chunk, execute=execute)
    db = tmp_path / "t.sqlite"
    _run(files, db, swap=lambda runner: policy, max_trials=1)
    with TrialStore(db, create=False) as store:
        ((row, recorded),) = _steps(store).values()
    assert row["n_steps"] == MAX_STEPS == len(spy["step_joints"])
    assert policy.calls == -(-MAX_STEPS // execute)
    # a chunk's later action is sent with the frame its chunk was computed from (the safety layer ages it)
    read = [s["frame_seq"] for s in recorded]  # one new frame every step
    assert len(set(read)) == MAX_STEPS
    assert [f["wrist"].seq for f in spy["frames"]] == [read[k - k % execute] for k in range(MAX_STEPS)]


def test_a_joint_policy_whose_joints_are_not_the_arms_is_refused_at_session_start(files, arm, tmp_path):
    db = tmp_path / "t.sqlite"
    reversed_joints = tuple(reversed(arm.joint_names))
    with pytest.raises(JointArmError, match=r"^--policy: contract\.joints: position 0 is 'panda_joint7' where") as err:
        _run(files, db, swap=lambda runner: _Scripted(arm, lambda k, q: q * 0, joints=reversed_joints))
    assert "\n" not in str(err.value)
    with TrialStore(db) as store:
        assert store.session("s") is None


def test_a_joint_policy_on_an_arm_without_kinematics_is_refused_in_one_line(arm):
    contract = _Scripted(arm, lambda k, q: None).contract
    with pytest.raises(
        JointArmError, match=r"^--policy: a joint-space policy .* on the ur_rtde arm, which takes no joint"
    ):
        check_joint_arm(contract, None, "ur_rtde")
    check_joint_arm(PolicyContract(), None, "ur_rtde")  # a TCP policy runs on any arm


@pytest.mark.parametrize(
    "edit",
    [
        lambda names, units: (names[::-1], units),
        lambda names, units: ((*names[:-1], "panda_finger_joint1"), units),
        lambda names, units: (names[:-1], units[:-1]),
        lambda names, units: (names, (*units[:-1], "m")),
    ],
    ids=["reversed", "not-the-arms", "one-short", "wrong-unit"],
)
def test_a_real_arm_and_a_scenes_arm_refuse_the_same_joints_with_the_same_line(spec, arm, edit):
    """check_joint_arm (the session's arm) and check_joints (the scene's arm) are one comparison:
    for the same URDF they refuse the same card with the same reason, each naming its arm."""
    from sim.policies.contract import check_joints
    from sim.policies.interface import PolicyError

    joints, units = edit(arm.joint_names, arm.units)
    contract = PolicyContract(
        state=("joint_positions",), action=ActionContract(kind="joint_delta"), joints=joints, joint_units=units
    )
    with pytest.raises(PolicyError) as scene_err:
        check_joints(contract, spec)
    with pytest.raises(JointArmError, match=r"^--policy: contract\.joint") as arm_err:
        check_joint_arm(contract, arm, "sim")
    assert str(arm_err.value) == "--policy: " + str(scene_err.value).replace("the arm's chain", "the sim arm's chain")
    assert "\n" not in str(arm_err.value)


def test_a_joint_policy_on_a_sim_cell_whose_scene_has_no_arm_is_refused_before_any_device(files, tmp_path):
    plan = small_plan(tmp_path / "plan.yaml", tmp_path, n_tcp=1, n_layouts=1, conditions=("clean",))  # built-in scene
    with pytest.raises(SessionSetupError, match=r"^--policy: .*ck: contract: a joint-space policy .* needs a scene"):
        _run(files, tmp_path / "t.sqlite", plan=plan)


def test_a_version_7_store_is_migrated_its_tcp_steps_kept_and_joint_actions_may_leave_the_action_columns_empty(
    tmp_path, monkeypatch
):
    db = tmp_path / "v7.sqlite"
    monkeypatch.setattr(store_mod, "SCHEMA_VERSION", 7)
    with TrialStore(db) as store:
        assert store.con.execute("SELECT version FROM schema_version").fetchone()[0] == 7
        notnull = {r[1]: r[3] for r in store.con.execute("PRAGMA table_info(steps)")}
        assert notnull["action_0"] == 1 and "joints_json" not in notnull
    con = sqlite3.connect(db)
    con.execute(
        "INSERT INTO sessions (id, name, created_at, plan_sha256, plan_text, hardware_text, policy_path, "
        "policy_sha256, software_version, git_commit, devices_json, calibration_json, config_json) VALUES "
        "(1, 's', 't', 'p', '', '', '', '', '', '', '{}', '{}', '{}')"
    )
    con.execute(
        "INSERT INTO trials (id, session_id, trial_id, plan_order, env, shape, condition, tcp_pose, "
        "object_layout, tags_json, started_at, duration_s, n_steps, stop_reason, auto_outcome, auto_reason, "
        "distances_json, final_outcome, placement_checks, placement_skipped, frames_dir) VALUES "
        "(1, 1, 't0', 0, 'A', 'cube', 'clean', 0, 0, '[]', 't', 1.0, 1, 'max_steps', 'none', '', '{}', "
        "'none', 1, 0, 'f')"
    )
    cols = [r[1] for r in con.execute("PRAGMA table_info(steps)")]
    values = {c: 0.5 for c in cols}
    values.update(trial_row=1, step=0, frame_seq=3, safety_status="ok", safety_reason="", frame_ref="f/0.png")
    values["camera_frames_json"] = None
    con.execute(
        f"INSERT INTO steps ({', '.join(values)}) VALUES ({', '.join('?' * len(values))})", list(values.values())
    )
    con.commit()
    con.close()
    monkeypatch.undo()
    with TrialStore(db) as store:
        assert store.con.execute("SELECT version FROM schema_version").fetchone()[0] == store_mod.SCHEMA_VERSION == 8
        notnull = {r[1]: r[3] for r in store.con.execute("PRAGMA table_info(steps)")}
        assert all(notnull[f"action_{i}"] == 0 for i in range(6)) and "joints_json" in notnull
        (step,) = store.con.execute("SELECT * FROM steps").fetchall()
        assert step["action_5"] == 0.5 and step["frame_seq"] == 3 and step["joints_json"] is None
        assert store.con.execute("SELECT name FROM sqlite_master WHERE name = 'steps_trial'").fetchone() is not None


def test_a_tcp_start_the_ik_leaves_a_few_mm_short_starts_as_in_the_simulator_at_fk_of_its_joints(files, spec, arm):
    """The runner takes a start pose by the simulator's rule (sim.ik.IkResult.start_reached): the
    evaluation seed 10050039's start is 3.5 mm short of the IK's tolerance, a start in both; the
    trial then starts where the arm will be, at FK of its joints, not at the pose asked for."""
    from sim.configs import object_local_centers, sample_config
    from sim.ik import START_TOL_M

    T_ask = sample_config(spec, 10050039, object_local_centers(spec)).T_world_tcp_array
    plan = load_plan(files["plan"])
    first = plan.tcp_poses[0].model_copy(update={"T_table_tcp": Pose.from_T(T_ask), "joint_positions": None})
    plan = plan.model_copy(update={"tcp_poses": [first, *plan.tcp_poses[1:]]})
    trials = [t for t in plan.trials if t.tcp_pose == 0]
    (start,) = resolve_starts(plan, trials, np.eye(4), arm, joint_space=True).values()
    np.testing.assert_allclose(start.T_base_tcp, tcp_from_joints(arm, start.q), rtol=0, atol=1e-12)
    assert 1e-4 < np.linalg.norm(start.T_base_tcp[:3, 3] - T_ask[:3, 3]) <= START_TOL_M
    # and the simulator starts the same configuration at the same joints
    from sim.env import ReachEnv

    with ReachEnv(spec, num_envs=1, image_size=32, control="joint", render_obs=False) as e:
        e.reset(seed=10050039)
        np.testing.assert_allclose(e.q[0], start.q, rtol=0, atol=1e-9)
