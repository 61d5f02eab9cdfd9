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
