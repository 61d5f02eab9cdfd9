"""Hardware-in-the-loop simulation: the sim camera sees what the sim arm does; a session runs from the sim config."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from robot_io.arms.sim import SimArm
from robot_io.cameras.sim import SimCamera
from robot_io.config import build_arm, build_camera, load_hardware_config
from robot_io.poses import pose_step
from robot_io.safety import SafeArm

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
