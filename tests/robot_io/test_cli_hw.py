"""``advobj hw check`` on the sim config: reports the camera and arm, moves nothing without --jog."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from trials.cli.main import app

SIM_YAML = Path(__file__).resolve().parents[2] / "examples" / "hardware" / "sim.yaml"


class _Borrowed:
    """The shared test world, lent to the CLI (which closes what it builds) without being closed."""

    def __init__(self, world):
        self._world = world

    def __getattr__(self, name):
        return getattr(self._world, name)

    def close(self):
        pass


@pytest.fixture
def lend_world(monkeypatch, fresh_world):
    import robot_io.config

    monkeypatch.setattr(robot_io.config, "build_world", lambda cfg: _Borrowed(fresh_world))
    return fresh_world


def test_check_reports_fps_latency_and_pose_and_moves_nothing(lend_world):
    T0 = lend_world.T_world_tcp
    result = CliRunner().invoke(app, ["hw", "check", "--config", str(SIM_YAML), "--frames", "5"])
    assert result.exit_code == 0, result.output
    assert "fps over 5 frames" in result.output and "read()" in result.output and "frame age" in result.output
    assert "arm (sim): xyz = [" in result.output and "fault: none" in result.output
    assert "nothing moved" in result.output
    assert (lend_world.T_world_tcp == T0).all()


def test_check_with_jog_moves_up_and_back(lend_world):
    T0 = lend_world.T_world_tcp
    result = CliRunner().invoke(app, ["hw", "check", "-c", str(SIM_YAML), "--frames", "3", "--jog", "--jog-mm", "5"])
    assert result.exit_code == 0, result.output
    assert "jog: up to" in result.output and "back to" in result.output
    assert abs(lend_world.T_world_tcp[2, 3] - T0[2, 3]) < 1e-9


def test_check_rejects_a_bad_config_with_the_field_named(tmp_path):
    bad = tmp_path / "hw.yaml"
    bad.write_text(
        "camera: {type: sim}\narm: {type: sim, speed: 3}\nsafety: {workspace_min_m: [0,0,0], workspace_max_m: "
        "[1,1,1]}\n"
    )
    result = CliRunner().invoke(app, ["hw", "check", "--config", str(bad)])
    assert result.exit_code != 0
    assert "arm.sim.speed" in str(result.exception)


def test_check_keeps_a_ur_watchdog_fed_while_timing_the_camera_and_jogging(monkeypatch, tmp_path):
    import yaml

    from tests.robot_io.fakes import install_depthai, install_ur

    ctrl = install_ur(monkeypatch)
    oak = install_depthai(monkeypatch)
    oak.period_s = 0.03  # 8 frames take ~0.25 s: longer than the 0.1 s the watchdog allows
    hw = tmp_path / "hw.yaml"
    hw.write_text(
        yaml.safe_dump(
            {
                "camera": {"type": "depthai", "width": 64, "height": 48},
                "arm": {"type": "ur_rtde", "host": "10.0.0.2", "watchdog_min_hz": 10},
                "safety": {"workspace_min_m": [0.0, -0.5, 0.0], "workspace_max_m": [0.8, 0.5, 0.6]},
            }
        )
    )
    result = CliRunner().invoke(app, ["hw", "check", "-c", str(hw), "--frames", "8", "--jog", "--jog-mm", "10"])
    assert result.exit_code == 0, result.output
    assert "fps over 8 frames" in result.output and "jog: up to" in result.output
    assert "setWatchdog" in ctrl.names() and ctrl.names().count("moveL") == 2
    assert not ctrl.watchdog_tripped, f"watchdog tripped: longest gap {ctrl.max_feed_gap_s * 1000:.0f} ms"
    assert ctrl.max_feed_gap_s <= 1 / 10


def test_check_reports_a_camera_without_intrinsics_instead_of_aborting(monkeypatch, tmp_path):
    import numpy as np
    import yaml
    from PIL import Image

    from tests.robot_io.fakes import install_ur

    install_ur(monkeypatch)
    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(3):
        Image.fromarray(np.full((24, 32, 3), 40 * i, np.uint8)).save(frames / f"{i}.png")
    hw = tmp_path / "hw.yaml"
    hw.write_text(
        yaml.safe_dump(
            {
                "camera": {"type": "replay", "path": str(frames), "loop": True},  # no intrinsics: they are optional
                "arm": {"type": "ur_rtde", "host": "10.0.0.2"},
                "safety": {"workspace_min_m": [0.0, -0.5, 0.0], "workspace_max_m": [0.8, 0.5, 0.6]},
            }
        )
    )
    result = CliRunner().invoke(app, ["hw", "check", "-c", str(hw), "--frames", "4"])
    assert result.exit_code == 0, result.output
    assert "intrinsics: not configured" in result.output and "32x24" in result.output
    assert "arm (ur_rtde): xyz = [" in result.output


# ---------------------------------------------------------------------------- arms a URDF describes


def _frames(tmp_path: Path) -> Path:
    """A replay camera's folder of three frames (the arm tests need a camera, not its pictures)."""
    import numpy as np
    from PIL import Image

    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(3):
        Image.fromarray(np.full((24, 32, 3), 40 * i, np.uint8)).save(frames / f"{i}.png")
    return frames


def _hw_yaml(tmp_path: Path, arm: dict) -> Path:
    import yaml

    hw = tmp_path / "hw.yaml"
    hw.write_text(
        yaml.safe_dump(
            {
                "camera": {"type": "replay", "path": str(_frames(tmp_path)), "loop": True},
                "arm": arm,
                "safety": {"workspace_min_m": [-0.8, -0.8, 0.0], "workspace_max_m": [0.8, 0.8, 0.8]},
            }
        )
    )
    return hw


@pytest.fixture
def ur_serial_twin():
    """The serial arm's twin computing its POSE on a UR5 placed as a UR controller's base (base_link
    turned by pi about z), and its port."""
    import numpy as np

    from robot_io.arms.serial_sim import SerialArmSimulator
    from robot_io.poses import pose_from_vec
    from tests.robot_io.fakes import ur5_scene_arm

    ur5 = ur5_scene_arm(T_base_link=pose_from_vec([0.0, 0.0, 0.0, 0.0, 0.0, np.pi]))
    sim, path = SerialArmSimulator.on_pty(boot_delay_s=0.02, scene_arm=ur5)
    yield sim, path
    sim.close()


UR5_AS_A_UR = {
    "urdf": "ur5",
    "base_link": "base_link",
    "tool_link": "tool0",
    "rotvec_base_link": [0, 0, 3.141592653589793],
}


def test_check_prints_each_joint_with_its_unit_and_distance_to_its_limits(tmp_path, ur_serial_twin):
    from robot_io.check import format_joint, joint_readings

    sim, path = ur_serial_twin
    hw = _hw_yaml(
        tmp_path, {"type": "serial", "port": path, "timeout_ms": 250, "expect_banner": False, "kinematics": UR5_AS_A_UR}
    )
    result = CliRunner().invoke(app, ["hw", "check", "-c", str(hw), "--frames", "3"])
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    readings = joint_readings(sim.scene_arm, sim.q)
    header = lines.index(f"  joints ({len(readings)}, in the URDF's order and units):")
    width = max(len(r.name) for r in readings)
    assert lines[header + 1 : header + 1 + len(readings)] == [f"    {format_joint(r, width)}" for r in readings]
    assert all(r.inside for r in readings) and "OUTSIDE the URDF's limits" not in result.output
    assert "nothing moved" in result.output and not {"MOVE", "MOVEJ"} & {c for _, c in sim.executed}


def test_check_refuses_an_arm_whose_urdf_disagrees_with_its_controller_and_moves_nothing(tmp_path, ur_serial_twin):
    from robot_io.errors import HardwareConfigError

    sim, path = ur_serial_twin
    not_turned = {k: v for k, v in UR5_AS_A_UR.items() if k != "rotvec_base_link"}
    hw = _hw_yaml(
        tmp_path, {"type": "serial", "port": path, "timeout_ms": 250, "expect_banner": False, "kinematics": not_turned}
    )
    result = CliRunner().invoke(app, ["hw", "check", "-c", str(hw), "--frames", "3"])
    assert result.exit_code != 0 and isinstance(result.exception, HardwareConfigError)
    text = str(result.exception)
    assert "\n" not in text and "URDF kinematics disagree" in text and "rotvec_base_link" in text
    assert "joints (" not in result.output and not {"MOVE", "MOVEJ"} & {c for _, c in sim.executed}


def test_check_shows_a_servo_whose_offset_ticks_put_its_joint_outside_the_urdf_limits(tmp_path):
    import math

    import numpy as np

    from robot_io.arms.feetech_sim import FeetechSimulator
    from robot_io.arms.servo_bus import ServoJoint, SimServo
    from robot_io.check import format_joint, joint_readings
    from sim.ik import SceneArm
    from sim.kinematics import shipped_arm
    from tests.robot_io.test_feetech import centred_joints

    panda = SceneArm(shipped_arm("panda"), np.eye(4), np.eye(4), 0.05, np.zeros(7))
    joints = centred_joints(panda)  # the middle of each joint's range at the middle of its servo's turn
    lo, hi = panda.model.limits.q_min.numpy(), panda.model.limits.q_max.numpy()
    k = int(np.argmin(hi - lo))  # the joint with the narrowest range
    j = joints[k]
    # An offset_ticks wrong by the ticks of half that range and 0.1 rad more: the joint reads outside.
    shift = math.ceil((0.5 * (hi[k] - lo[k]) + 0.1) * j.ticks_per_rev / (2 * math.pi))
    joints[k] = ServoJoint(j.id, j.name, j.sign, j.offset_ticks + shift, j.ticks_per_rev)
    mid = joints[0].ticks_per_rev // 2
    sim, path = FeetechSimulator.on_pty([SimServo(s.id, position_ticks=mid) for s in joints])
    try:
        servos = [dict(id=s.id, name=s.name, sign=s.sign, offset_ticks=s.offset_ticks) for s in joints]
        kinematics = {"urdf": "panda", "base_link": "panda_link0", "tool_link": "panda_hand"}
        hw = _hw_yaml(
            tmp_path, {"type": "feetech", "port": path, "timeout_ms": 250, "joints": servos, "kinematics": kinematics}
        )
        result = CliRunner().invoke(app, ["hw", "check", "-c", str(hw), "--frames", "3"])
    finally:
        sim.close()
    assert result.exit_code == 0, result.output
    readings = joint_readings(panda, [s.to_rad(mid) for s in joints])
    width = max(len(r.name) for r in readings)
    for r in readings:
        assert f"    {format_joint(r, width)}" in result.output.splitlines()
    assert [r.name for r in readings if not r.inside] == [j.name]
    assert f"  {j.name} OUTSIDE the URDF's limits: check the joint's sign and offset_ticks" in result.output
    assert "OUTSIDE them" in format_joint(readings[k])


def test_serial_sim_prints_its_port_serves_a_driver_and_ends_cleanly_on_ctrl_c():
    import signal
    import subprocess
    import sys

    from robot_io.arms.serial import SerialArm

    root = Path(__file__).resolve().parents[2]
    # Ctrl-C as a terminal delivers it: a background job (CI, nohup) starts with SIGINT ignored, which
    # the child would inherit, so it sets Python's own handler first
    code = (
        "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
        "from trials.cli.main import main; sys.argv[0] = 'advobj'; main()"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code, "hw", "serial-sim", "--boot-delay-ms", "0"],
        cwd=root,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        line = proc.stdout.readline()
        assert line.startswith("serial arm simulator on ") and line.endswith("; set arm.port to it\n"), line
        path = line.removeprefix("serial arm simulator on ").removesuffix("; set arm.port to it\n")
        with SerialArm(path, boot_timeout_ms=2000) as arm:
            assert arm.device_info["fw"].startswith("advobj-sim") and arm.fault() is None
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0 and "Traceback" not in err, err
