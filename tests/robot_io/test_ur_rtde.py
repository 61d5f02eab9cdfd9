"""UR driver against fake ur-rtde modules injected through sys.modules."""

from __future__ import annotations

import sys
import time

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from robot_io.arms.base import KINEMATICS_TOL_M, KINEMATICS_TOL_RAD, tcp_from_joints
from robot_io.arms.ur_rtde import UR_JOINTS, URArm, joint_move_speed_radps
from robot_io.config import build_arm, hardware_config_from_dict
from robot_io.errors import ArmFaultError, ArmRefusedError, HardwareConfigError, MissingExtraError, RobotIOError
from robot_io.poses import pose_from_vec
from robot_io.safety import SafeArm, SafetyLimits
from tests.robot_io.fakes import Q_UR5_READY, FakeURController, install_ur, ur5_scene_arm

SAFETY = {"workspace_min_m": [0.0, -0.5, 0.0], "workspace_max_m": [0.8, 0.5, 0.6], "max_frame_age_ms": 1000}


def ur_config(**arm):
    return hardware_config_from_dict(
        {
            "camera": {"type": "replay", "path": "frames"},
            "arm": {"type": "ur_rtde", "host": "10.0.0.2", **arm},
            "safety": SAFETY,
        }
    )


def run_loop(arm, n):
    for _ in range(n):
        arm.step_delta([0.001, 0.0, 0.0, 0.0, 0.0, 0.0], time.monotonic())


def test_watchdog_is_armed_and_kicked_before_every_servo_command(monkeypatch):
    ctrl = install_ur(monkeypatch)
    # This test checks the order of calls; a descheduled test process (a loaded machine) must not
    # stop the fake's script. Kick timing is checked by the hw-check and long-moveL tests.
    ctrl.trip_stops_script = False
    with build_arm(ur_config(watchdog_min_hz=25)) as arm:
        run_loop(arm, 20)
    names = ctrl.names()
    assert ("setWatchdog", 25.0) in ctrl.calls
    servo_idx = [i for i, n in enumerate(names) if n == "servoL"]
    assert len(servo_idx) == 20
    prev = names.index("setWatchdog")
    for i in servo_idx:
        assert "kickWatchdog" in names[prev:i], "a loop iteration sent servoL without kicking the watchdog"
        prev = i


def test_servo_l_gets_the_step_period_and_smoothing_parameters(monkeypatch):
    ctrl = install_ur(monkeypatch)
    with build_arm(ur_config(lookahead_time_s=0.05, gain=500)) as arm:
        run_loop(arm, 1)
    call = next(c for c in ctrl.calls if c[0] == "servoL")
    _, pose, _, _, t, lookahead, gain = call
    assert t == pytest.approx(arm.limits.control_period_s) and lookahead == 0.05 and gain == 500
    assert pose[0] == pytest.approx(0.401, abs=1e-6)  # 1 mm along the TCP x axis (= base x here)


def test_exception_in_the_loop_stops_the_arm_then_stops_script_and_disconnects(monkeypatch):
    ctrl = install_ur(monkeypatch)
    with pytest.raises(RuntimeError, match="policy exploded"):
        with build_arm(ur_config()) as arm:
            run_loop(arm, 3)
            raise RuntimeError("policy exploded")
    names = ctrl.names()
    tail = names[names.index("servoStop") :]
    assert tail.index("servoStop") < tail.index("stopScript") < tail.index("control_disconnect")
    assert "receive_disconnect" in tail


def test_teardown_continues_when_servo_stop_itself_fails(monkeypatch):
    ctrl = install_ur(monkeypatch)
    arm = URArm("10.0.0.2")
    arm.connect()

    def broken():
        ctrl.log("servoStop")
        raise RuntimeError("controller went away")

    arm._rtde_c.servoStop = broken
    with pytest.raises(RuntimeError, match="went away"):
        arm.disconnect()
    assert {"stopScript", "control_disconnect", "receive_disconnect"} <= set(ctrl.names())


def test_protective_stop_becomes_a_clean_explained_error(monkeypatch):
    ctrl = install_ur(monkeypatch)
    with build_arm(ur_config()) as arm:
        run_loop(arm, 2)
        ctrl.protective_stopped = True
        with pytest.raises(ArmFaultError) as info:
            run_loop(arm, 1)
        n_servo = ctrl.names().count("servoL")
        assert n_servo == 2  # nothing sent after the stop was seen
    err = info.value
    assert err.fault.kind == "protective_stop"
    assert "protective stop" in str(err) and "unlockProtectiveStop" in str(err) and "reuploadScript" in str(err)


def test_recover_unlocks_through_the_dashboard_then_reuploads(monkeypatch):
    ctrl = install_ur(monkeypatch)
    with build_arm(ur_config()) as arm:
        ctrl.protective_stopped = True
        assert arm.fault().kind == "protective_stop"
        arm.recover()
        assert arm.fault() is None
    names = ctrl.names()
    assert names.index("unlockProtectiveStop") < names.index("reuploadScript")


@pytest.mark.parametrize(
    "flag,kind",
    [("emergency_stopped", "emergency_stop"), ("program_running", "program_stopped"), ("connected", "connection_lost")],
)
def test_fault_reports_estop_stopped_script_and_lost_link(monkeypatch, flag, kind):
    ctrl = install_ur(monkeypatch)
    with URArm("10.0.0.2") as arm:
        setattr(ctrl, flag, not getattr(ctrl, flag))
        assert arm.fault().kind == kind


def test_speed_l_mode_streams_velocities_and_stops_with_speed_stop(monkeypatch):
    ctrl = install_ur(monkeypatch)
    with build_arm(ur_config(mode="speedL")) as arm:
        run_loop(arm, 1)
    call = next(c for c in ctrl.calls if c[0] == "speedL")
    xd, t = np.array(call[1]), call[3]
    assert xd[0] > 0 and np.allclose(xd[1:], 0.0, atol=1e-6) and xd[0] * t <= 0.0011
    assert "speedStop" in ctrl.names() and "servoStop" not in ctrl.names()


def test_unreachable_controller_is_a_connection_fault(monkeypatch):
    ctrl = FakeURController()
    ctrl.fail_connect = True
    install_ur(monkeypatch, ctrl)
    with pytest.raises(ArmFaultError, match="cannot connect to UR controller at 10.0.0.2"):
        URArm("10.0.0.2").connect()


def test_missing_sdk_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "rtde_control", None)  # makes the import fail
    with pytest.raises(MissingExtraError, match=r"advobj\[ur\]"):
        URArm("10.0.0.2").connect()


def test_a_long_movel_runs_asynchronously_and_the_watchdog_is_kicked_until_it_ends(monkeypatch):
    ctrl = install_ur(monkeypatch)
    with URArm("10.0.0.2", watchdog_min_hz=10) as arm:
        T = arm.tcp_pose()
        T[0, 3] += 0.05
        t0 = time.monotonic()
        arm.move_to(T, 0.1)  # 0.5 s: five watchdog periods
        assert time.monotonic() - t0 >= 0.45  # returned when the move had ended, not when it was sent
        assert np.allclose(arm.tcp_pose()[:3, 3], T[:3, 3], atol=1e-9)
    move = next(c for c in ctrl.calls if c[0] == "moveL")
    assert move[4] is True  # asynchronous
    assert not ctrl.watchdog_tripped, f"watchdog tripped: longest gap {ctrl.max_feed_gap_s * 1000:.0f} ms"
    assert ctrl.max_feed_gap_s <= 1 / 10


def test_movel_waits_for_the_controller_to_start_the_move(monkeypatch):
    # The status register shows the previous, finished operation for a while after moveL returns.
    ctrl = install_ur(monkeypatch)
    ctrl.stale_polls = 5
    with URArm("10.0.0.2") as arm:
        T = arm.tcp_pose()
        T[1, 3] += 0.01
        arm.move_to(T, 0.1)
        assert np.allclose(arm.tcp_pose()[:3, 3], T[:3, 3], atol=1e-9)


def test_a_protective_stop_during_movel_is_an_explained_fault_and_the_move_is_stopped(monkeypatch):
    ctrl = install_ur(monkeypatch)
    ctrl.protective_stop_after_s = 0.1
    with URArm("10.0.0.2") as arm:
        T = arm.tcp_pose()
        T[0, 3] += 0.05
        t0 = time.monotonic()
        with pytest.raises(ArmFaultError) as info:
            arm.move_to(T, 0.1)
        assert time.monotonic() - t0 < 0.3  # seen while moving, not after the move's planned end
    assert info.value.fault.kind == "protective_stop"
    assert "stopL" in ctrl.names()


def test_a_movel_that_does_not_end_times_out_and_is_stopped(monkeypatch):
    ctrl = install_ur(monkeypatch)
    ctrl.stall_moves = True
    with URArm("10.0.0.2") as arm:
        T = arm.tcp_pose()
        T[0, 3] += 0.01
        with pytest.raises(ArmFaultError, match="did not finish within 0.3 s"):
            arm.move_to(T, 0.1, timeout_s=0.3)
    assert "stopL" in ctrl.names() and not ctrl.watchdog_tripped


def test_ctrl_c_during_movel_stops_the_move(monkeypatch):
    ctrl = install_ur(monkeypatch)
    with URArm("10.0.0.2") as arm:
        real, polls = arm._rtde_c.getAsyncOperationProgressEx, []

        def interrupted():
            polls.append(1)
            if len(polls) == 3:
                raise KeyboardInterrupt
            return real()

        arm._rtde_c.getAsyncOperationProgressEx = interrupted
        T = arm.tcp_pose()
        T[0, 3] += 0.05
        with pytest.raises(KeyboardInterrupt):
            arm.move_to(T, 0.1)
        assert "stopL" in ctrl.names() and ctrl.move is None


@pytest.mark.parametrize("flag", ["fail_control_init", "fail_set_watchdog"])
def test_a_failed_connect_releases_what_it_opened(monkeypatch, flag):
    ctrl = install_ur(monkeypatch)
    setattr(ctrl, flag, True)
    arm = URArm("10.0.0.2")
    with pytest.raises(ArmFaultError, match="cannot connect to UR controller"):
        arm.connect()
    names = ctrl.names()
    assert "receive_disconnect" in names and not arm.connected
    if flag == "fail_set_watchdog":  # the control script was already running: stop it too
        assert names.index("stopScript") < names.index("control_disconnect")


def test_an_ur_rtde_without_async_status_is_refused_on_connect(monkeypatch):
    ctrl = FakeURController()
    ctrl.has_async_status = False
    install_ur(monkeypatch, ctrl)
    with pytest.raises(MissingExtraError, match="getAsyncOperationProgressEx"):
        URArm("10.0.0.2").connect()
    assert "control_init" not in ctrl.names()


@pytest.mark.parametrize("case", ["no_getSerialNumber", "dashboard_unreachable"])
def test_identity_without_the_controller_serial_still_connects(monkeypatch, caplog, case):
    ctrl = FakeURController()
    if case == "no_getSerialNumber":
        ctrl.serial_number = None  # an older ur-rtde
    else:
        ctrl.dashboard_unreachable = True
    install_ur(monkeypatch, ctrl)
    with URArm("10.0.0.2") as arm:
        ident = arm.identity()
    assert ident["host"] == "10.0.0.2" and "serial" not in ident
    assert ("model" in ident) == (case == "no_getSerialNumber")
    assert (case == "dashboard_unreachable") == any("serial number" in r.getMessage() for r in caplog.records)


# ---------------------------------------------------------------------------- joint commands


@pytest.fixture(scope="module")
def ur5():
    return ur5_scene_arm()


@pytest.fixture
def joint_ur(monkeypatch, ur5):
    """A connected URArm with the UR5's kinematics, on a fake controller whose TCP is the FK of its joints."""
    ctrl = install_ur(monkeypatch, FakeURController(kinematics=ur5))
    arm = URArm("10.0.0.2", kinematics=ur5)
    arm.connect()
    yield ctrl, arm
    arm.disconnect()


def servo_j_calls(ctrl) -> list[tuple]:
    return [c for c in ctrl.calls if c[0] == "servoJ"]


def test_servo_joints_streams_servo_j_and_joint_positions_reads_them_back(joint_ur, ur5):
    ctrl, arm = joint_ur
    assert arm.kinematics() is ur5
    q = np.array(Q_UR5_READY) + 0.01
    arm.servo_joints(q, 0.05)
    _, q_sent, _, _, t, lookahead, gain = servo_j_calls(ctrl)[-1]
    np.testing.assert_array_equal(q_sent, q)
    assert t == 0.05 and lookahead == arm.lookahead_time_s and gain == arm.gain
    np.testing.assert_array_equal(arm.joint_positions(), q)
    np.testing.assert_allclose(arm.tcp_pose(), tcp_from_joints(ur5, q), atol=1e-9)
    assert ctrl.names().index("kickWatchdog") < ctrl.names().index("servoJ")


@pytest.mark.parametrize("bad", [np.zeros(5), np.zeros(7), np.zeros((2, 6)), [0.0] * 5 + [np.nan], "q"])
@pytest.mark.parametrize("method", ["servo_joints", "move_joints"])
def test_a_malformed_joint_target_is_refused_with_one_line_and_nothing_sent(joint_ur, bad, method):
    ctrl, arm = joint_ur
    with pytest.raises(RobotIOError) as info:
        getattr(arm, method)(bad, 0.05)
    assert "\n" not in str(info.value) and "UR 10.0.0.2: a joint target must be" in str(info.value)
    assert not {"servoJ", "moveJ"} & set(ctrl.names())


def test_kinematics_without_six_joints_is_refused_on_connect_before_anything_opens(monkeypatch):
    from sim.ik import SceneArm
    from sim.kinematics import shipped_arm

    panda = SceneArm(shipped_arm("panda"), np.eye(4), np.eye(4), 0.05, np.zeros(7))
    ctrl = install_ur(monkeypatch)
    arm = URArm("10.0.0.2", kinematics=panda)
    with pytest.raises(RobotIOError, match=f"has 7 joints .*a UR arm has {UR_JOINTS}") as info:
        arm.connect()
    assert "\n" not in str(info.value) and not arm.connected and ctrl.calls == []


# A UR controller's base frame is ur_description's base_link turned by pi about z: the config says
# so with rotvec_base_link, and the fake controller below computes its TCP that way.
UR5_LINKS = {"urdf": "ur5", "base_link": "base_link", "tool_link": "tool0"}
A_URS_BASE = pose_from_vec([0.0, 0.0, 0.0, 0.0, 0.0, np.pi])
MOTION = {"moveL", "moveJ", "servoL", "servoJ", "speedL"}


def _placed(**fields) -> dict:
    """The UR5's kinematics block of a hardware config placed as a real UR's, with ``fields`` changed."""
    return {**UR5_LINKS, "rotvec_base_link": [0.0, 0.0, np.pi], **fields}


@pytest.mark.parametrize(
    "kinematics",
    [
        pytest.param({**UR5_LINKS}, id="base_not_turned"),
        pytest.param(_placed(t_tool_tcp_m=[0.0, 0.0, 2 * KINEMATICS_TOL_M]), id="tcp_offset_twice_the_tolerance"),
        pytest.param(_placed(rotvec_tool_tcp=[0.0, 0.0, 2 * KINEMATICS_TOL_RAD]), id="tcp_turned_twice_the_tolerance"),
    ],
)
def test_kinematics_that_disagree_with_the_controller_are_refused_on_connect_and_nothing_moves(monkeypatch, kinematics):
    ctrl = install_ur(monkeypatch, FakeURController(kinematics=ur5_scene_arm(T_base_link=A_URS_BASE)))
    q_before = list(ctrl.q)
    arm = build_arm(ur_config(kinematics=kinematics))
    with pytest.raises(HardwareConfigError) as info:
        arm.connect()
    text = str(info.value)
    assert "\n" not in text and text.startswith("UR 10.0.0.2: the arm's URDF kinematics disagree with its controller")
    assert "rotvec_base_link" in text and "t_tool_tcp_m" in text and text.endswith("Nothing was moved")
    names = ctrl.names()
    assert not arm.connected and not MOTION & set(names) and ctrl.q == q_before
    assert "setWatchdog" not in names  # refused before the watchdog was armed
    assert {"stopScript", "control_disconnect", "receive_disconnect"} <= set(names)  # and released


@pytest.mark.parametrize(
    "kinematics",
    [
        pytest.param(_placed(), id="placed_as_the_controller"),
        pytest.param(
            _placed(t_tool_tcp_m=[0.0, 0.0, KINEMATICS_TOL_M / 2], rotvec_tool_tcp=[0.0, 0.0, KINEMATICS_TOL_RAD / 2]),
            id="tcp_within_half_the_tolerance",
        ),
    ],
)
def test_kinematics_that_agree_with_the_controller_within_the_tolerance_connect(monkeypatch, kinematics):
    ctrl = install_ur(monkeypatch, FakeURController(kinematics=ur5_scene_arm(T_base_link=A_URS_BASE)))
    with build_arm(ur_config(kinematics=kinematics)) as arm:
        assert arm.connected and arm.kinematics().n_joints == UR_JOINTS
        np.testing.assert_allclose(arm.joint_positions(), Q_UR5_READY)
    assert not MOTION & set(ctrl.names())


def test_an_arm_without_kinematics_takes_no_joint_commands(monkeypatch):
    ctrl = install_ur(monkeypatch)
    with URArm("10.0.0.2") as arm:
        assert arm.kinematics() is None
        for call in (lambda: arm.joint_positions(), lambda: arm.servo_joints(np.zeros(6), 0.05)):
            with pytest.raises(RobotIOError, match="takes no joint commands"):
                call()
    assert "servoJ" not in ctrl.names()


def test_a_protective_stop_refuses_a_joint_servo_before_it_is_sent(joint_ur):
    ctrl, arm = joint_ur
    ctrl.protective_stopped = True
    with pytest.raises(ArmFaultError) as info:
        arm.servo_joints(np.array(Q_UR5_READY), 0.05)
    assert info.value.fault.kind == "protective_stop" and "unlockProtectiveStop" in str(info.value)
    assert servo_j_calls(ctrl) == []


def test_move_joints_runs_an_asynchronous_move_j_at_the_mean_speed_and_returns_when_there(joint_ur, ur5):
    ctrl, arm = joint_ur
    q = np.array(Q_UR5_READY)
    q[0] += 0.25
    t0 = time.monotonic()
    arm.move_joints(q, 0.5)  # five watchdog periods
    assert time.monotonic() - t0 >= 0.45
    _, q_sent, speed, accel, asynchronous = next(c for c in ctrl.calls if c[0] == "moveJ")
    assert asynchronous is True and speed == pytest.approx(0.25 / 0.5) and accel == arm.joint_acceleration_radps2
    np.testing.assert_allclose(arm.joint_positions(), q, atol=1e-12)
    np.testing.assert_allclose(arm.tcp_pose(), tcp_from_joints(ur5, q), atol=1e-9)
    assert not ctrl.watchdog_tripped and ctrl.max_feed_gap_s <= 1 / arm.watchdog_min_hz


def test_a_move_j_that_does_not_end_times_out_and_is_stopped_with_stop_j(joint_ur):
    ctrl, arm = joint_ur
    ctrl.stall_moves = True
    q = np.array(Q_UR5_READY)
    q[0] += 0.1
    with pytest.raises(ArmFaultError, match="moveJ did not finish within 0.3 s"):
        arm.move_joints(q, 0.2, timeout_s=0.3)
    assert "stopJ" in ctrl.names() and "stopL" not in ctrl.names() and ctrl.move is None
    assert not ctrl.watchdog_tripped


@pytest.mark.parametrize("command", ["move_to", "move_joints"])
def test_a_move_the_controller_rejects_without_a_fault_is_a_refusal_and_the_next_move_runs(joint_ur, command):
    """moveL/moveJ answering False with no fault raised: the controller will not execute the target
    (out of its reach). An ArmRefusedError in one line, nothing moved, no fault; the arm moves again."""
    ctrl, arm = joint_ur
    q0, T0 = arm.joint_positions(), arm.tcp_pose()
    q, T = q0.copy(), T0.copy()
    q[0] += 0.05
    T[2, 3] += 0.01

    def move():
        return arm.move_to(T, 0.1) if command == "move_to" else arm.move_joints(q, 0.1)

    ctrl.reject_moves = True
    with pytest.raises(ArmRefusedError, match=r"^UR 10\.0\.0\.2: the controller rejected the move[LJ] ") as err:
        move()
    assert "the arm did not move" in str(err.value) and "\n" not in str(err.value)
    assert not isinstance(err.value, ArmFaultError) and arm.fault() is None
    np.testing.assert_array_equal(arm.joint_positions(), q0)
    ctrl.reject_moves = False
    move()
    if command == "move_to":
        np.testing.assert_allclose(arm.tcp_pose()[:3, 3], T[:3, 3], atol=1e-9)
    else:
        np.testing.assert_allclose(arm.joint_positions(), q, atol=1e-12)


def test_a_protective_stop_during_move_j_is_an_explained_fault_and_the_move_is_stopped(joint_ur):
    ctrl, arm = joint_ur
    ctrl.protective_stop_after_s = 0.1
    q = np.array(Q_UR5_READY)
    q[0] += 0.25
    t0 = time.monotonic()
    with pytest.raises(ArmFaultError) as info:
        arm.move_joints(q, 0.5)
    assert time.monotonic() - t0 < 0.3  # seen while moving, not after the move's planned end
    assert info.value.fault.kind == "protective_stop" and "stopJ" in ctrl.names()
    assert abs(arm.joint_positions()[0] - Q_UR5_READY[0]) < 0.25  # frozen part-way


def test_stop_after_a_joint_servo_in_speed_l_mode_ends_both_streams(monkeypatch, ur5):
    ctrl = install_ur(monkeypatch, FakeURController(kinematics=ur5))
    with URArm("10.0.0.2", mode="speedL", kinematics=ur5) as arm:
        arm.servo_joints(np.array(Q_UR5_READY), 0.05)
        arm.stop()
        names = ctrl.names()
        assert {"servoStop", "speedStop"} <= set(names[names.index("servoJ") :])


@given(
    distance=st.floats(min_value=0.0, max_value=1e300, allow_subnormal=True),
    duration=st.floats(min_value=1e-300, max_value=1e300),
)
def test_the_move_j_speed_is_the_mean_speed_never_faster(distance, duration):
    try:
        v = joint_move_speed_radps(distance, duration)
    except RobotIOError as err:  # only a mean speed past the float range
        with np.errstate(over="ignore"):
            assert distance / np.float64(duration) == np.inf and "no finite speed" in str(err)
        return
    assert np.isfinite(v) and v > 0
    if distance > 0 and v > 1e-3:
        assert v <= distance / duration * (1 + 1e-12)  # the leading joint never cruises above the mean


@pytest.mark.parametrize("distance,duration", [(np.nan, 1.0), (1.0, np.inf), (-1.0, 1.0), (1.0, -0.1), (0.1, 0.0)])
def test_the_move_j_speed_refuses_a_move_it_cannot_time(distance, duration):
    with pytest.raises(RobotIOError, match="joint move"):
        joint_move_speed_radps(distance, duration)


def test_joint_steps_through_the_safety_layer_never_send_the_ur_a_target_outside_limits(joint_ur, ur5):
    ctrl, arm = joint_ur
    limits = SafetyLimits(**SAFETY)
    safe = SafeArm(arm, limits)
    lo, hi = ur5.model.limits.q_min.numpy(), ur5.model.limits.q_max.numpy()
    q0 = np.array(Q_UR5_READY)
    q0[5] = hi[5] - 0.01  # the last wrist joint near its limit: turning it leaves the TCP where it is
    arm.servo_joints(q0, 0.05)
    n_before = len(servo_j_calls(ctrl))
    for bad in (np.full(6, np.nan), np.zeros(5), q0 + np.where(np.arange(6) == 0, 2.0, 0.0)):
        assert safe.step_joints(bad, time.monotonic()).status == "refused"
    assert len(servo_j_calls(ctrl)) == n_before  # NaN, wrong length, a jump: nothing reached the driver
    past = q0.copy()
    past[5] = hi[5] + 0.2
    res = safe.step_joints(past, time.monotonic())
    assert res.status == "clipped"
    q_sent = np.array(servo_j_calls(ctrl)[-1][1])
    assert ((q_sent >= lo) & (q_sent <= hi)).all() and q_sent[5] == hi[5]
    np.testing.assert_array_equal(arm.joint_positions(), q_sent)
