"""The safety layer's behaviours, one per test, over a pure-math arm."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from robot_io.arms.base import Arm, Fault
from robot_io.errors import ArmFaultError, SafetyStop
from robot_io.poses import pose_step
from robot_io.safety import SafeArm, SafetyLimits, SafetyRefusal, limit_command
from tests.robot_io.fakes import RecordingArm, make_pose


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


@pytest.fixture
def rig(limits):
    clock = Clock()
    arm = RecordingArm(make_pose(0.4, 0.0, 0.3))
    safe = SafeArm(arm, limits, clock=clock)
    safe.connect()
    return safe, arm, clock


def test_target_outside_workspace_is_clipped_and_logged_with_reason(rig, caplog):
    safe, arm, clock = rig
    T = make_pose(0.4, 0.0, 0.3)
    T[2, 3] = -0.5  # below the table
    with caplog.at_level(logging.INFO, logger="robot_io.safety"):
        res = safe.step(T, clock.t)
    assert res.status == "clipped"
    assert any("outside the workspace" in r for r in res.reasons)
    assert any("outside the workspace" in rec.getMessage() for rec in caplog.records)
    assert any(e.action == "clipped" and "outside the workspace" in e.reason for e in safe.events)
    assert arm.T[2, 3] == pytest.approx(0.3 - safe.limits.step_cap_m)  # moved down one capped step only


def test_nan_action_is_refused_stops_the_arm_and_is_logged(rig, caplog):
    safe, arm, clock = rig
    with caplog.at_level(logging.WARNING, logger="robot_io.safety"):
        res = safe.step_delta([0.0, np.nan, 0.0, 0.0, 0.0, 0.0], clock.t)
    assert res.status == "refused" and res.T_cmd is None
    assert arm.servos == [] and arm.stops == 1
    assert any("non-finite" in rec.getMessage() for rec in caplog.records)


def test_inf_pose_and_non_rotation_are_refused(rig):
    safe, arm, clock = rig
    T = make_pose()
    T[0, 3] = np.inf
    assert safe.step(T, clock.t).status == "refused"
    S = make_pose()
    S[:3, :3] *= 2.0  # a scaling, not a rotation
    assert safe.step(S, clock.t).status == "refused"
    assert arm.servos == [] and arm.stops == 2


def test_stale_frame_stops_the_arm_instead_of_moving(rig, limits):
    safe, arm, clock = rig
    old_frame_time = clock.t - (limits.max_frame_age_ms + 1) / 1000.0
    res = safe.step_delta([0.01, 0, 0, 0, 0, 0], old_frame_time)
    assert res.status == "refused" and "old" in res.reasons[0]
    assert arm.servos == [] and arm.stops == 1
    assert safe.step_delta([0.01, 0, 0, 0, 0, 0], clock.t).status == "ok"


def test_frame_stamped_on_another_clock_is_refused(rig):
    safe, arm, clock = rig
    import time

    res = safe.step_delta(np.zeros(6), time.time())  # wall clock instead of the monotonic one
    assert res.status == "refused" and "time.monotonic" in res.reasons[0]
    assert arm.servos == []


def test_missing_frame_timestamp_is_refused(rig):
    safe, arm, _ = rig
    assert safe.step_delta(np.zeros(6), None).status == "refused"
    assert arm.servos == []


def test_trial_longer_than_the_maximum_stops_and_raises(rig, limits):
    safe, arm, clock = rig
    safe.start_trial()
    clock.t += limits.max_trial_s + 0.1
    with pytest.raises(SafetyStop, match="maximum trial duration"):
        safe.step_delta(np.zeros(6), clock.t)
    assert arm.stops == 1 and arm.servos == []


def test_per_step_translation_and_rotation_are_capped(rig, limits):
    safe, arm, clock = rig
    res = safe.step_delta([0.5, 0.0, 0.0, 0.0, 0.0, 1.0], clock.t)
    dp, dr = pose_step(arm.servos[0][0], arm.servos[0][1])
    assert res.status == "clipped"
    assert dp == pytest.approx(limits.step_cap_m) and dr == pytest.approx(limits.step_cap_rad)


def test_speed_cap_binds_when_tighter_than_step_cap():
    lim = SafetyLimits(
        workspace_min_m=(-1, -1, 0),
        workspace_max_m=(1, 1, 1),
        max_step_m=0.05,
        max_speed_mps=0.1,
        control_period_s=0.1,
        max_accel_mps2=1e6,
    )
    T_cmd, dp, reasons = limit_command(make_pose(), make_pose(0.6), np.zeros(3), lim)
    assert np.linalg.norm(dp) == pytest.approx(0.01)  # 0.1 m/s * 0.1 s
    assert any("capped" in r for r in reasons)


def test_caps_scale_with_the_period_the_command_covers_but_never_beyond_one_loop_period():
    lim = SafetyLimits(
        workspace_min_m=(-1, -1, 0),
        workspace_max_m=(1, 1, 1),
        max_step_m=0.05,
        max_step_rad=0.5,
        max_speed_mps=0.1,
        max_speed_radps=1.0,
        control_period_s=0.1,
        max_accel_mps2=1e6,
    )
    T_far = make_pose(0.6, rotvec=(np.pi, 0.0, 0.3))
    T_cmd, dp, reasons = limit_command(make_pose(), T_far, np.zeros(3), lim, period_s=0.02)
    assert np.linalg.norm(dp) == pytest.approx(0.002)  # 0.1 m/s * 20 ms
    assert pose_step(make_pose(), T_cmd)[1] == pytest.approx(0.02)  # 1 rad/s * 20 ms
    assert any("20.0 ms since the last command" in r for r in reasons)
    _, dp, _ = limit_command(make_pose(), T_far, np.zeros(3), lim, period_s=5.0)
    assert np.linalg.norm(dp) == pytest.approx(0.01)  # a late command still covers one period only
    _, dp, _ = limit_command(make_pose(), T_far, np.array([0.01, 0, 0]), lim, period_s=0.0)
    assert np.linalg.norm(dp) == 0.0  # simultaneous commands: no motion, not even the previous step's


def test_commands_faster_than_the_loop_period_cannot_exceed_the_speed_cap(limits):
    # Calling step_delta in a tight loop once moved an arm 1 m in 64 ms (15.6 m/s under a 0.15 m/s cap).
    clock = Clock()
    T0 = make_pose(-0.5, 0.0, 0.5)
    arm = RecordingArm(T0)
    with SafeArm(arm, limits, clock=clock) as safe:
        t0 = clock.t
        for _ in range(1000):
            clock.t += 64e-6
            safe.step_delta([0.05, 0.0, 0.0, 0.0, 0.0, 0.0], clock.t)
    elapsed_s = clock.t - t0
    moved = pose_step(T0, arm.T)[0]
    assert len(arm.servos) == 1000
    assert moved <= limits.max_speed_mps * (elapsed_s + limits.control_period_s) + 1e-9
    assert any("since the last command" in e.reason for e in safe.events)


def test_a_completed_positioning_move_leaves_the_arm_at_rest_for_a_full_next_step(rig, limits):
    safe, arm, clock = rig
    safe.move_to(make_pose(0.5, 0.0, 0.3))
    res = safe.step_delta([0.5, 0.0, 0.0, 0.0, 0.0, 0.0], clock.t)  # same instant as the move's end
    assert pose_step(arm.servos[0][0], res.T_cmd)[0] == pytest.approx(limits.step_cap_m)


def test_fast_reversal_is_smoothed_by_the_acceleration_cap():
    lim = SafetyLimits(
        workspace_min_m=(-1, -1, 0),
        workspace_max_m=(1, 1, 1),
        max_step_m=0.01,
        max_speed_mps=1.0,
        control_period_s=0.02,
        max_accel_mps2=5.0,
    )
    prev = np.array([0.01, 0.0, 0.0])  # moving +x at full step
    _, dp, reasons = limit_command(make_pose(), make_pose(0.3), prev, lim)  # target behind: reverse
    assert np.linalg.norm(dp - prev) == pytest.approx(5.0 * 0.02**2)
    assert any("acceleration" in r for r in reasons)


def test_workspace_wins_over_acceleration_at_the_wall():
    lim = SafetyLimits(
        workspace_min_m=(-1, -1, 0),
        workspace_max_m=(0.405, 1, 1),
        max_step_m=0.01,
        max_speed_mps=1.0,
        control_period_s=0.02,
        max_accel_mps2=0.1,
    )
    T_cmd, _, reasons = limit_command(make_pose(0.4), make_pose(0.5), np.array([0.01, 0, 0]), lim)
    assert T_cmd[0, 3] == pytest.approx(0.405)
    assert "stopping at the workspace boundary" in reasons


def test_arm_fault_raises_an_explained_error_and_stops(rig):
    safe, arm, clock = rig
    arm.fault_value = Fault("protective_stop", "collision detected", "clear the workspace and unlock")
    with pytest.raises(ArmFaultError, match="protective_stop.*To recover: clear the workspace"):
        safe.step_delta(np.zeros(6), clock.t)
    assert arm.stops == 1 and arm.servos == []


@pytest.mark.parametrize("exc", [RuntimeError("policy crashed"), KeyboardInterrupt()])
def test_exception_or_ctrl_c_in_the_loop_stops_then_disconnects(limits, exc):
    arm = RecordingArm()
    safe = SafeArm(arm, limits)
    with pytest.raises(type(exc)):
        with safe:
            raise exc
    assert arm.stops == 1 and not arm.connected
    assert safe.events[-1].action == "stopped" and type(exc).__name__ in safe.events[-1].reason


def test_driver_error_during_a_step_stops_the_arm(rig):
    safe, arm, clock = rig
    arm.raise_on_servo = OSError("link dropped")
    with pytest.raises(OSError):
        safe.step_delta([0.001, 0, 0, 0, 0, 0], clock.t)
    assert arm.stops == 1


def test_a_failing_stop_does_not_hide_the_original_error(limits):
    arm = RecordingArm()
    arm.stop = lambda: (_ for _ in ()).throw(OSError("port vanished"))
    with pytest.raises(RuntimeError, match="the real problem"):
        with SafeArm(arm, limits):
            raise RuntimeError("the real problem")


def test_positioning_outside_workspace_is_refused_not_clipped(rig):
    safe, arm, _ = rig
    with pytest.raises(SafetyRefusal, match="outside the workspace"):
        safe.move_to(make_pose(2.0, 0.0, 0.3))
    assert arm.moves == []


def test_positioning_speed_is_capped(rig, limits):
    safe, arm, _ = rig
    safe.move_to(make_pose(0.5, 0.0, 0.3), speed_mps=10.0)
    assert arm.moves[0][1] == limits.max_speed_mps
    assert any(e.action == "clipped" and "speed" in e.reason for e in safe.events)


@pytest.mark.parametrize("speed", [0.0, -0.1, float("nan")])
def test_a_non_positive_positioning_speed_is_refused_and_logged(rig, speed):
    safe, arm, _ = rig
    with pytest.raises(SafetyRefusal, match="positive"):
        safe.move_to(make_pose(0.5, 0.0, 0.3), speed_mps=speed)
    assert arm.moves == []
    assert safe.events[-1].action == "refused" and "positioning speed" in safe.events[-1].reason


def test_keepalive_reaches_the_driver(rig):
    safe, arm, _ = rig
    kicks = arm.kicks
    safe.keepalive()
    assert arm.kicks == kicks + 1


def test_the_raw_driver_is_not_exposed(rig):
    safe, _, _ = rig
    public = {k: v for k, v in vars(safe).items() if not k.startswith("_")}
    assert not any(isinstance(v, Arm) for v in public.values())
    assert not any(isinstance(getattr(safe, k, None), Arm) for k in dir(safe) if not k.startswith("_"))


def test_limits_reject_an_inverted_box_naming_the_fields():
    with pytest.raises(ValidationError, match="workspace_min_m"):
        SafetyLimits(workspace_min_m=(0, 0, 1), workspace_max_m=(1, 1, 0))
    with pytest.raises(ValidationError, match="max_step_m"):
        SafetyLimits(workspace_min_m=(0, 0, 0), workspace_max_m=(1, 1, 1), max_step_m=float("nan"))


# ----------------------------------------------------------------------------- several cameras
def test_with_several_cameras_a_stale_scene_camera_frame_stops_the_arm_naming_it(rig, limits):
    safe, arm, clock = rig
    fresh, stale = clock.t - 0.01, clock.t - (limits.max_frame_age_ms + 5) / 1000.0
    res = safe.step_delta([0.01, 0, 0, 0, 0, 0], {"wrist": fresh, "front": stale})
    assert res.status == "refused" and res.reasons == ("camera 'front' frame is 105 ms old (limit 100 ms)",)
    assert arm.servos == [] and arm.stops == 1
    assert safe.events[-1].action == "stopped" and "'front'" in safe.events[-1].reason
    assert safe.step_delta([0.01, 0, 0, 0, 0, 0], {"wrist": fresh, "front": fresh}).status == "ok"
    assert len(arm.servos) == 1


def test_with_several_cameras_a_missing_or_future_stamp_of_any_is_refused_naming_it(rig):
    safe, arm, clock = rig
    res = safe.step_delta(np.zeros(6), {"wrist": clock.t, "front": None})
    assert res.status == "refused" and res.reasons == ("no camera 'front' frame timestamp given",)
    res = safe.step_delta(np.zeros(6), {"wrist": clock.t, "top": clock.t + 1.0})
    assert res.status == "refused" and "camera 'top' frame timestamp is 1000 ms in the future" in res.reasons[0]
    assert safe.step_delta(np.zeros(6), {}).status == "refused"  # no frame at all
    assert arm.servos == []


@settings(max_examples=200, deadline=None)
@given(
    ages_ms=st.dictionaries(
        st.sampled_from(["wrist", "front", "top", "side"]),
        st.floats(0.0, 1e9, allow_nan=False, allow_infinity=False),
        min_size=1,
        max_size=4,
    )
)
def test_the_oldest_frame_decides_for_any_set_of_frame_ages(ages_ms):
    limits = SafetyLimits(workspace_min_m=(-1, -1, 0), workspace_max_m=(1, 1, 1), max_frame_age_ms=100.0)
    clock = Clock()
    clock.t = 1e7  # frames up to 1e9 ms (11.6 days) old still have a positive monotonic stamp
    arm = RecordingArm(make_pose(0.4, 0.0, 0.3))
    safe = SafeArm(arm, limits, clock=clock)
    safe.connect()
    res = safe.step_delta(np.zeros(6), {cam: clock.t - age / 1000.0 for cam, age in ages_ms.items()})
    oldest = max(ages_ms, key=ages_ms.get)
    # the stamps are rounded to float64 seconds: ages within a microsecond of the limit may go either way
    if abs(ages_ms[oldest] - 100.0) > 1e-3:
        assert (res.status == "refused") == (ages_ms[oldest] > 100.0), res
    if res.status == "refused":
        named = res.reasons[0].split("'")[1]  # the camera the refusal names: one of the oldest (ties)
        assert ages_ms[named] >= ages_ms[oldest] - 1e-3 and arm.servos == []
    else:
        assert len(arm.servos) == 1
