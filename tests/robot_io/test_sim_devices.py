"""Hardware-in-the-loop simulation: the sim camera sees what the sim arm does; a session runs from the sim config."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from robot_io.arms.sim import SimArm
from robot_io.cameras.sim import SimCamera
from robot_io.config import build_arm, build_camera, load_hardware_config
from robot_io.errors import ArmFaultError, ArmRefusedError
from robot_io.poses import pose_step
from robot_io.safety import SafeArm
from sim.ik import TOL_M, TOL_RAD

SIM_YAML = Path(__file__).resolve().parents[2] / "examples" / "hardware" / "sim.yaml"


def test_sim_camera_renders_from_the_arm_pose_through_T_tcp_cam(fresh_world):
    arm, cam = SimArm(fresh_world), SimCamera(fresh_world)
    with arm, cam:
        before = cam.read().rgb
        T = arm.tcp_pose()
        T[2, 3] += 0.05
        arm.move_to(T, 0.2)
        after = cam.read().rgb
        expected = fresh_world.render(T @ fresh_world.T_tcp_cam, with_ids=False).rgb
    assert np.abs(after.astype(int) - before.astype(int)).mean() > 0.5
    assert np.abs(after.astype(int) - expected.astype(int)).mean() < 2.0


def test_sim_camera_uses_a_configured_mount(fresh_world):
    T_tcp_cam = fresh_world.T_tcp_cam.copy()
    T_tcp_cam[0, 3] += 0.1
    default, shifted = SimCamera(fresh_world), SimCamera(fresh_world, T_tcp_cam)
    with default, shifted:
        a, b = default.read().rgb, shifted.read().rgb
    assert np.abs(a.astype(int) - b.astype(int)).mean() > 0.5


def test_sim_arm_servo_respects_its_speed_limit(fresh_world):
    with SimArm(fresh_world, max_speed_mps=0.2, max_speed_radps=1.0) as arm:
        T0 = arm.tcp_pose()
        T = T0.copy()
        T[0, 3] += 0.5
        arm.servo(T, 0.1)
        dp, _ = pose_step(T0, arm.tcp_pose())
    assert dp == pytest.approx(0.02)  # 0.2 m/s x 0.1 s
    assert arm.sim_time_s == pytest.approx(0.1)


def test_sim_arm_realtime_moves_take_wall_clock_time(fresh_world):
    with SimArm(fresh_world, realtime=True) as arm:
        T = arm.tcp_pose()
        T[2, 3] += 0.02
        t0 = time.monotonic()
        arm.move_to(T, 0.2)
        assert time.monotonic() - t0 >= 0.09  # 20 mm at 0.2 m/s


@pytest.mark.parametrize("realtime", [False, True])
def test_speed_caps_count_simulated_time_unless_the_sim_arm_runs_in_real_time(fresh_world, limits, realtime):
    # A frozen wall clock: the loop runs "infinitely fast", as the trial runner's --no-rate-limit does.
    safe = SafeArm(SimArm(fresh_world, realtime=realtime), limits, clock=lambda: 50.0)
    with safe:
        T0 = safe.tcp_pose()
        for _ in range(5):
            safe.step_delta([0.05, 0.0, 0.0, 0.0, 0.0, 0.0], 50.0)
        moved = pose_step(T0, safe.tcp_pose())[0]
    # Simulated: each command covered one control period. Real time: none passed after the first.
    assert moved == pytest.approx(limits.step_cap_m * (1 if realtime else 5))


def test_a_whole_session_runs_from_the_sim_config(fresh_world):
    """Camera -> "policy" -> safety -> arm, as a real-trial runner would do it."""
    cfg = load_hardware_config(SIM_YAML)
    camera, arm = build_camera(cfg, fresh_world), build_arm(cfg, fresh_world)
    goal = fresh_world.object_centers()[fresh_world.spec.goal.name]
    with camera, arm:
        arm.start_trial()
        d0 = np.linalg.norm(arm.tcp_pose()[:3, 3] - goal)
        for _ in range(15):
            frame = camera.read()
            T = arm.tcp_pose()
            direction_tcp = T[:3, :3].T @ (goal - T[:3, 3])  # toward the goal, in the TCP frame
            arm.step_delta([*(0.05 * direction_tcp / np.linalg.norm(direction_tcp)), 0, 0, 0], frame)
        d1 = np.linalg.norm(arm.tcp_pose()[:3, 3] - goal)
    assert d1 < d0 - 0.1
    assert all(e.action == "clipped" for e in arm.events)  # 50 mm asks were capped, nothing refused


def _panda_arm(world) -> SimArm:
    """A joint-driven sim arm: the shipped Panda, its base at the world origin, in its ready pose."""
    from sim.ik import SceneArm
    from sim.kinematics import shipped_arm

    q_ready = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
    return SimArm(world, scene_arm=SceneArm(shipped_arm("panda"), np.eye(4), np.eye(4), 0.05, q_ready))


@pytest.mark.parametrize("command", ["servo", "move_to"])
@pytest.mark.parametrize("x_m", [1.5, 1e3, 1e9])
def test_a_tcp_target_out_of_the_joint_driven_arms_reach_is_refused_and_no_fault_is_latched(fresh_world, command, x_m):
    """Like a real driver's refusal of an unreachable pose: one line naming the target, nothing moved,
    no fault left behind, and the next reachable command is executed."""
    with _panda_arm(fresh_world) as arm:
        q0, T0, n0, t0 = arm.joint_positions(), arm.tcp_pose(), arm.commands, arm.sim_time_s
        far = T0.copy()
        far[:3, 3] = (x_m, 0.0, 0.3)
        move = arm.servo if command == "servo" else arm.move_to
        with pytest.raises(ArmRefusedError, match=r"^sim arm: TCP target at \[") as err:
            move(far, 0.05)
        text = str(err.value)
        assert f"[{x_m:.3f}, 0.000, 0.300] m (base frame) is out of reach within the joint limits" in text
        assert "the arm did not move" in text and "\n" not in text
        assert not isinstance(err.value, ArmFaultError) and arm.fault() is None  # a refusal, not a fault
        np.testing.assert_array_equal(arm.joint_positions(), q0)
        np.testing.assert_array_equal(arm.tcp_pose(), T0)
        assert (arm.commands, arm.sim_time_s) == (n0, t0)
        near = T0.copy()
        near[2, 3] += 0.01
        move(near, 0.05)
        assert pose_step(near, arm.tcp_pose())[0] <= TOL_M  # the IK's tolerance
        assert arm.commands == n0 + 1


def test_an_unreachable_step_through_the_safety_layer_raises_the_arms_refusal_and_the_arm_moves_again(
    fresh_world, limits
):
    """The safety layer passes the driver's refusal on (the runner ends the trial on it) after stopping
    the arm; no fault being latched, the next trial's positioning move and steps are executed."""
    arm = _panda_arm(fresh_world)
    wide = limits.model_copy(update={"max_step_m": 10.0, "max_speed_mps": 1e3, "max_accel_mps2": 1e6})
    with SafeArm(arm, wide, clock=lambda: 50.0) as safe:
        T0 = safe.tcp_pose()
        far = T0.copy()
        far[0, 3] = 0.99  # in the workspace box, beyond the Panda's reach
        with pytest.raises(ArmRefusedError, match=r"sim arm: TCP target at \[0\.990, .* is out of reach"):
            safe.step(far, 50.0)
        np.testing.assert_array_equal(safe.tcp_pose(), T0)
        assert safe.fault() is None and safe.events[-1].action == "stopped"
        start = T0.copy()
        start[2, 3] += 0.01
        safe.move_to(start)  # the next trial's positioning move: no fault stands in its way
        assert pose_step(start, safe.tcp_pose())[0] <= TOL_M  # the IK's tolerance
        step = start.copy()
        step[2, 3] += 0.01
        res = safe.step(step, 50.0)
        assert res.status == "ok" and pose_step(step, safe.tcp_pose())[0] <= TOL_M


def test_a_positioning_move_the_ik_misses_from_the_current_joints_is_solved_from_the_start_seeds(fresh_world):
    """A reachable pose whose IK from a stretched arm does not converge: a streamed step there is refused
    (a real arm does not jump configurations mid-stream), a positioning move gets there from the scene
    arm's start seeds (its home joints, then restarts), as the simulator solves a start."""
    import torch

    arm = _panda_arm(fresh_world)
    kin = arm.kinematics()
    stretched = np.array([0.0, 1.5, 0.0, -0.1, 0.0, 1.6, 0.785])
    q_far = np.array([0.65, -0.675, -2.179, -2.786, 1.487, 3.158, 0.506])  # another configuration, in the limits
    T_far = kin.tcp_pose(torch.as_tensor(q_far, dtype=torch.float64)).numpy()
    with arm:
        arm.move_joints(stretched, 1.0)
        with pytest.raises(ArmRefusedError, match=r"out of reach .* \(IK from the current joints: "):
            arm.servo(T_far, 0.05)
        np.testing.assert_array_equal(arm.joint_positions(), stretched)
        arm.move_to(T_far, 0.1)
        dp, dr = pose_step(T_far, arm.tcp_pose())
        assert dp <= TOL_M and dr <= TOL_RAD  # the IK's tolerances
