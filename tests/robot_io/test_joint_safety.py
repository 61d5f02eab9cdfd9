"""The safety layer's joint path (issue 31, item 4): each check alone, then a hostile campaign.

The arm is the shipped Panda (its URDF's position and velocity limits) as a joint-driven
:class:`robot_io.arms.sim.SimArm` on the shared sim world, its base at the world origin. Every
command the twin receives is recorded (its joints after each command), and the checks read them
back through one batched FK: the sim arm executes commands exactly, so what it holds is what it
was sent.
"""

from __future__ import annotations

import collections
import time

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from robot_io.arms.sim import SimArm
from robot_io.safety import (
    JointSafetyLimits,
    SafeArm,
    SafetyLimits,
    SafetyRefusal,
    joint_step_caps,
    limit_joint_command,
)
from sim.ik import SceneArm
from sim.kinematics import shipped_arm

Q_READY = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
PERIOD_S = 0.05
FRAME_AGE_MS = 100.0


@pytest.fixture(scope="module")
def panda():
    return SceneArm(shipped_arm("panda"), np.eye(4), np.eye(4), PERIOD_S, Q_READY.copy())


def joint_limits(**kw) -> SafetyLimits:
    base = dict(
        workspace_min_m=(-0.8, -0.8, 0.05),
        workspace_max_m=(0.8, 0.8, 1.5),
        control_period_s=PERIOD_S,
        max_frame_age_ms=FRAME_AGE_MS,
        max_trial_s=1e9,
        joints=JointSafetyLimits(max_speed_radps=1.5, max_jump_rad=0.6),
    )
    base.update(kw)
    return SafetyLimits(**base)


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def tcp_m(panda, q) -> np.ndarray:
    q = torch.as_tensor(np.asarray(q, dtype=np.float64), device=panda.device)
    return panda.tcp_pose(q)[..., :3, 3].cpu().numpy()


def q_limits(panda):
    return panda.model.limits.q_min.cpu().numpy(), panda.model.limits.q_max.cpu().numpy()


@pytest.fixture
def rig(fresh_world, panda):
    clock = Clock()
    arm = SimArm(fresh_world, scene_arm=panda)
    safe = SafeArm(arm, joint_limits(), clock=clock)
    safe.connect()
    yield safe, arm, clock
    safe.disconnect()


# ---------------------------------------------------------------------------- each check alone


def test_a_target_beyond_a_position_limit_is_clipped_to_it(panda):
    lim = joint_limits()
    lo, hi = q_limits(panda)
    q_now = Q_READY.copy()
    q_now[3] = hi[3] - 0.01  # joint 4's upper limit is 0 rad
    target = q_now.copy()
    target[3] = hi[3] + 0.3
    q_cmd, reasons = limit_joint_command(q_now, target, panda, lim)
    assert q_cmd[3] == hi[3]
    assert any("position limits" in r and "panda_joint4" in r for r in reasons)


def test_each_joint_step_is_capped_at_the_smaller_of_urdf_and_configured_speed(panda):
    lim = joint_limits(joints=JointSafetyLimits(max_speed_radps=2.4, max_jump_rad=0.6))
    caps = joint_step_caps(panda, lim)
    qd_urdf = panda.model.limits.qd_max.cpu().numpy()
    np.testing.assert_allclose(caps, np.minimum(qd_urdf, 2.4) * PERIOD_S)
    assert caps[0] == pytest.approx(2.175 * PERIOD_S) and caps[6] == pytest.approx(2.4 * PERIOD_S)
    target = Q_READY + 0.5
    q_cmd, reasons = limit_joint_command(Q_READY, target, panda, lim)
    dq = q_cmd - Q_READY
    assert np.max(np.abs(dq) / caps) == pytest.approx(1.0)
    np.testing.assert_allclose(dq / dq[0], np.ones(7))  # the direction in joint space is kept
    assert any("capped" in r for r in reasons)


def test_a_command_sooner_than_the_period_may_cover_only_the_time_since_the_last(panda):
    lim = joint_limits()
    q_cmd, _ = limit_joint_command(Q_READY, Q_READY + 0.5, panda, lim, period_s=PERIOD_S / 4)
    assert np.max(np.abs(q_cmd - Q_READY) / joint_step_caps(panda, lim, PERIOD_S / 4)) == pytest.approx(1.0)
    q_zero, reasons = limit_joint_command(Q_READY, Q_READY + 0.5, panda, lim, period_s=0.0)
    np.testing.assert_array_equal(q_zero, Q_READY)
    assert any("ms since the last command" in r for r in reasons)


def test_a_jump_is_refused_stops_the_arm_and_moves_nothing(rig):
    safe, arm, clock = rig
    before, n = arm.joint_positions(), arm.commands
    target = before.copy()
    target[1] += 0.61  # max_jump_rad is 0.6
    res = safe.step_joints(target, clock.t)
    assert res.status == "refused" and res.q_cmd is None
    assert "jump" in res.reasons[0] and "panda_joint2" in res.reasons[0]
    assert arm.commands == n
    np.testing.assert_array_equal(arm.joint_positions(), before)
    assert safe.events[-1].action == "stopped"


@pytest.mark.parametrize(
    "bad, words",
    [
        ([np.nan] + [0.0] * 6, "non-finite"),
        ([0.0] * 6 + [np.inf], "non-finite"),
        ([0.0] * 6 + [-np.inf], "non-finite"),
        ([0.0] * 6, "shape (6,)"),
        ([0.0] * 8, "shape (8,)"),
        ([[0.0] * 7], "shape (1, 7)"),
        ("seven", "not numbers"),
    ],
)
def test_a_target_not_n_finite_numbers_is_refused(rig, bad, words):
    safe, arm, clock = rig
    n = arm.commands
    res = safe.step_joints(bad, clock.t)
    assert res.status == "refused" and words in res.reasons[0]
    assert arm.commands == n


def test_a_tcp_leaving_the_box_is_stopped_at_the_wall_along_the_joint_line(panda):
    p0 = tcp_m(panda, Q_READY)
    lim = joint_limits(workspace_max_m=(p0[0] + 0.005, 0.8, 1.5))  # the wall 5 mm ahead in x
    target = Q_READY.copy()
    target[1] += 0.5  # shoulder forward: the TCP moves +x
    q_cmd, reasons = limit_joint_command(Q_READY, target, panda, lim)
    p = tcp_m(panda, q_cmd)
    assert lim.contains(p)
    assert p[0] > p0[0]  # moved toward the wall, not frozen
    dq = q_cmd - Q_READY
    assert np.count_nonzero(dq) == 1 and dq[1] > 0  # along the commanded joint line
    assert any("leaves the workspace box" in r for r in reasons)


def test_an_arm_outside_the_box_may_only_move_toward_it(panda):
    p0 = tcp_m(panda, Q_READY)
    lim = joint_limits(workspace_max_m=(p0[0] - 0.05, 0.8, 1.5))  # the TCP is 5 cm past the wall
    away, toward = Q_READY.copy(), Q_READY.copy()
    away[1] += 0.3
    toward[1] -= 0.3
    q_away, reasons = limit_joint_command(Q_READY, away, panda, lim)
    np.testing.assert_array_equal(q_away, Q_READY)
    assert any("toward it only" in r for r in reasons)
    q_toward, _ = limit_joint_command(Q_READY, toward, panda, lim)
    assert tcp_m(panda, q_toward)[0] < p0[0]


def test_a_chunk_is_refused_at_the_first_action_its_frame_is_too_old_for(rig):
    safe, arm, clock = rig
    frame_s = clock.t
    results = []
    for k in range(8):  # one chunk of 8 actions computed from one frame, one per control period
        results.append(safe.step_joints(arm.joint_positions() + 0.01, frame_s).status)
        clock.t += PERIOD_S
    # ages 0, 50, 100 ms pass (limit 100 ms); 150 ms is the first the frame outlives
    assert results[:3] == ["ok"] * 3
    assert results[3:] == ["refused"] * 5
    assert "ms old" in safe.events[-2].reason


def test_the_trial_duration_applies_to_joint_commands(fresh_world, panda):
    from robot_io.errors import SafetyStop

    clock = Clock()
    arm = SimArm(fresh_world, scene_arm=panda)
    with SafeArm(arm, joint_limits(max_trial_s=1.0), clock=clock) as safe:
        assert safe.step_joints(Q_READY, clock.t).status == "ok"
        clock.t += 1.5
        with pytest.raises(SafetyStop, match="trial duration"):
            safe.step_joints(Q_READY, clock.t)


def test_joint_commands_to_an_arm_without_a_urdf_are_refused(fresh_world):
    clock = Clock()
    arm = SimArm(fresh_world)
    with SafeArm(arm, joint_limits(), clock=clock) as safe:
        res = safe.step_joints(Q_READY, clock.t)
    assert res.status == "refused" and "no joint commands" in res.reasons[0]
    assert arm.commands == 0


def test_positioning_joint_moves_are_refused_outside_limits_or_box_and_done_inside(rig, panda):
    safe, arm, _ = rig
    lo, hi = q_limits(panda)
    outside = Q_READY.copy()
    outside[3] = hi[3] + 0.1
    with pytest.raises(SafetyRefusal, match="outside its limits"):
        safe.move_joints(outside)
    low = Q_READY.copy()
    low[1] = 1.8  # shoulder far forward: the TCP goes below the table
    assert tcp_m(panda, low)[2] < 0.05
    with pytest.raises(SafetyRefusal, match="outside the workspace box"):
        safe.move_joints(low)
    goal = Q_READY + 0.2
    t0 = arm.sim_time_s
    safe.move_joints(goal)
    np.testing.assert_array_equal(arm.joint_positions(), goal)
    np.testing.assert_allclose(arm.tcp_pose()[:3, 3], tcp_m(panda, goal))
    assert arm.sim_time_s - t0 == pytest.approx(0.2 / 1.5)  # the slowest joint at its speed cap


def test_joint_limits_default_when_absent_and_refuse_nan_inf_non_positive_and_unknown_keys(limits):
    assert limits.joints == JointSafetyLimits()
    for bad in (float("nan"), float("inf"), 0.0, -1.0):
        with pytest.raises(ValidationError, match="max_jump_rad"):
            JointSafetyLimits(max_jump_rad=bad)
    with pytest.raises(ValidationError, match="extra"):
        JointSafetyLimits(max_jump_deg=1.0)


@settings(max_examples=300, deadline=None)
@given(
    u_now=st.lists(st.floats(0.0, 1.0), min_size=7, max_size=7),
    dq=st.lists(st.floats(-0.59, 0.59), min_size=7, max_size=7),
    period_s=st.floats(0.0, 1.0),
)
def test_any_finite_target_within_the_jump_gives_a_command_within_every_limit(panda, u_now, dq, period_s):
    lim = joint_limits()
    lo, hi = q_limits(panda)
    q_now = lo + np.asarray(u_now) * (hi - lo)
    q_cmd, _ = limit_joint_command(q_now, q_now + np.asarray(dq), panda, lim, period_s)
    assert ((q_cmd >= lo) & (q_cmd <= hi)).all()
    caps = joint_step_caps(panda, lim, period_s)
    assert (np.abs(q_cmd - q_now) <= caps * (1 + 1e-12) + 1e-15).all()
    box_lo, box_hi = np.asarray(lim.workspace_min_m), np.asarray(lim.workspace_max_m)

    def dist(p):
        return float(np.linalg.norm(np.maximum(np.maximum(box_lo - p, p - box_hi), 0.0)))

    assert dist(tcp_m(panda, q_cmd)) <= dist(tcp_m(panda, q_now))


# ---------------------------------------------------------------------------- the campaign


def hostile_campaign(safe, arm, clock, panda, n_actions: int, seed: int) -> dict:
    """Send ``n_actions`` hostile joint actions through ``safe``; return the counts and the violations.

    Kinds: NaN/Inf entries, wrong lengths, targets far outside the position limits, jumps, random
    walks pushing at the position limits (and so at the box), and chunks of 2 to 12 actions from one
    frame that outlive the frame age. Checked after the run on every command the twin received.
    """
    rng = np.random.default_rng(seed)
    lo, hi = q_limits(panda)
    jump = safe.limits.joints.max_jump_rad
    kinds = ("nan", "length", "far", "jump", "walk", "chunk")
    tried = dict.fromkeys(kinds, 0)
    status = {"ok": 0, "clipped": 0, "refused": 0}
    q_before, q_after, periods = [], [], []
    sent = 0
    push = rng.choice([-1.0, 1.0], 7)
    while sent < n_actions:
        kind = kinds[int(rng.choice(len(kinds), p=(0.1, 0.1, 0.1, 0.1, 0.4, 0.2)))]
        q = arm.joint_positions()
        chunk = 1
        if kind == "nan":
            targets = [q + rng.normal(0, 0.05, 7)]
            targets[0][rng.integers(7)] = rng.choice([np.nan, np.inf, -np.inf])
        elif kind == "length":
            targets = [rng.normal(0, 1, int(rng.choice([0, 1, 6, 8, 14])))]
        elif kind == "far":
            targets = [q + rng.choice([-1, 1], 7) * rng.uniform(0.0, jump, 7) + (hi - lo) * rng.choice([-3, 3], 7)]
            if rng.random() < 0.5:  # within the jump, beyond the limits
                targets = [np.where(rng.random(7) < 0.5, lo - rng.uniform(0, 0.3, 7), hi + rng.uniform(0, 0.3, 7))]
        elif kind == "jump":
            targets = [q + rng.uniform(-1e6, 1e6, 7) * rng.choice([1e-6, 1e-3, 1.0], 7)]
        elif kind == "walk":
            if rng.random() < 0.05:
                push = rng.choice([-1.0, 1.0], 7)
            targets = [q + push * rng.uniform(0, 0.9 * jump, 7) + rng.normal(0, 0.05, 7)]
        else:
            chunk = int(rng.integers(2, 13))
            step = rng.normal(0, 0.03, 7)
            targets = [q + (i + 1) * step for i in range(chunk)]
        frame_s = clock.t
        for target in targets[: n_actions - sent]:
            tried[kind] += 1
            sent += 1
            before = arm.commands
            q0, t0 = arm.joint_positions(), arm.sim_time_s
            res = safe.step_joints(target, frame_s)
            status[res.status] += 1
            if arm.commands != before:
                q_before.append(q0)
                q_after.append(arm.joint_positions())
                periods.append(arm.sim_time_s - t0)
            clock.t += PERIOD_S * (rng.uniform(0.5, 2.5) if kind == "chunk" else 1.0)
    qb, qa = np.asarray(q_before).reshape(-1, 7), np.asarray(q_after).reshape(-1, 7)
    caps = joint_step_caps(panda, safe.limits)
    p = tcp_m(panda, qa) if len(qa) else np.zeros((0, 3))
    box_lo, box_hi = np.asarray(safe.limits.workspace_min_m), np.asarray(safe.limits.workspace_max_m)
    return {
        "tried": sent,
        "by_kind": tried,
        "status": status,
        "commands": len(qa),
        "outside_position_limits": int(((qa < lo) | (qa > hi)).any(1).sum()),
        "over_speed_cap": int((np.abs(qa - qb) > caps * (1 + 1e-12) + 1e-15).any(1).sum()),
        "tcp_outside_box": int(((p < box_lo) | (p > box_hi)).any(1).sum()),
        "non_finite": int((~np.isfinite(qa)).any(1).sum()),
        "commands_at_a_position_limit": int(((qa == lo) | (qa == hi)).any(1).sum()),
        "refused_stale_frame": sum("ms old" in e.reason for e in safe.events if e.action == "refused"),
    }


def run_campaign(world, panda, n_actions: int, seed: int) -> dict:
    clock = Clock()
    arm = SimArm(world, scene_arm=panda)
    with SafeArm(arm, joint_limits(), clock=clock) as safe:
        safe.events = collections.deque(maxlen=None)  # keep every event: the counts read them
        t0 = time.perf_counter()
        counts = hostile_campaign(safe, arm, clock, panda, n_actions, seed)
        counts["seconds"] = round(time.perf_counter() - t0, 1)
    return counts


def assert_nothing_passed(counts: dict, n_actions: int) -> None:
    bad = ("outside_position_limits", "over_speed_cap", "tcp_outside_box", "non_finite")
    assert counts["tried"] >= n_actions, counts
    assert all(counts[k] == 0 for k in bad), counts
    # the campaign exercised every outcome, and the arm did move
    assert counts["commands"] > n_actions // 10, counts
    assert counts["status"]["clipped"] > 0 and counts["status"]["refused"] > 0, counts
    assert min(counts["by_kind"].values()) > 0, counts
    assert counts["commands_at_a_position_limit"] > 0 and counts["refused_stale_frame"] > 0, counts


def test_5000_hostile_joint_actions_pass_nothing_outside_the_limits(fresh_world, panda):
    counts = run_campaign(fresh_world, panda, 5_000, seed=1)
    assert_nothing_passed(counts, 5_000)
    print(counts)


@pytest.mark.slow
def test_100000_hostile_joint_actions_pass_nothing_outside_the_limits(fresh_world, panda):
    counts = run_campaign(fresh_world, panda, 100_000, seed=2)
    assert_nothing_passed(counts, 100_000)
    print(counts)


def test_a_joint_driven_sim_arm_follows_tcp_commands_through_ik(fresh_world, panda):
    arm = SimArm(fresh_world, scene_arm=panda)
    with arm:
        np.testing.assert_allclose(arm.tcp_pose()[:3, 3], tcp_m(panda, Q_READY))
        q_goal = Q_READY + 0.05
        T_goal = panda.tcp_pose(torch.as_tensor(q_goal, device=panda.device)).cpu().numpy()
        arm.servo(T_goal, PERIOD_S)
        np.testing.assert_allclose(arm.tcp_pose()[:3, 3], T_goal[:3, 3], atol=1e-4)  # the IK's tolerance
        np.testing.assert_allclose(arm.tcp_pose()[:3, 3], tcp_m(panda, arm.joint_positions()))
