"""Hardware config: every shipped example validates; bad input names the file and field."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robot_io.config import (
    ARM_TYPES,
    CAMERA_TYPES,
    build_arm,
    build_camera,
    hardware_config_from_dict,
    load_hardware_config,
    load_T_tcp_cam,
)
from robot_io.errors import HardwareConfigError
from robot_io.safety import SafeArm

EXAMPLES = sorted((Path(__file__).resolve().parents[2] / "examples" / "hardware").glob("*.yaml"))
SAFETY = {"workspace_min_m": [0, 0, 0], "workspace_max_m": [1, 1, 1]}


def test_examples_exist_for_sim_ur_and_serial():
    kinds = {(load_hardware_config(p).camera.type, load_hardware_config(p).arm.type) for p in EXAMPLES}
    assert {("sim", "sim"), ("opencv", "ur_rtde"), ("depthai", "serial")} <= kinds


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.name)
def test_every_example_validates_and_names_known_types(path):
    cfg = load_hardware_config(path)
    assert cfg.camera.type in CAMERA_TYPES and cfg.arm.type in ARM_TYPES
    assert cfg.safety.contains(np.mean([cfg.safety.workspace_min_m, cfg.safety.workspace_max_m], axis=0))
    if cfg.T_tcp_cam is not None:
        assert cfg.T_tcp_cam.is_absolute()  # resolved against the YAML's folder


def test_unknown_key_is_an_error_naming_file_and_field(tmp_path):
    p = tmp_path / "hw.yaml"
    p.write_text(
        "camera: {type: opencv, device: 0, exposure: 3}\narm: {type: sim}\nsafety:\n"
        "  workspace_min_m: [0, 0, 0]\n  workspace_max_m: [1, 1, 1]\n"
    )
    with pytest.raises(HardwareConfigError) as info:
        load_hardware_config(p)
    assert str(p) in str(info.value) and "camera.opencv.exposure" in str(info.value)


def test_unknown_device_type_lists_the_known_ones():
    with pytest.raises(HardwareConfigError, match=r"arm: .*'kuka'.*'sim', 'ur_rtde', 'serial'"):
        hardware_config_from_dict({"camera": {"type": "sim"}, "arm": {"type": "kuka"}, "safety": SAFETY})


def test_missing_required_fields_are_named():
    with pytest.raises(HardwareConfigError, match=r"arm.ur_rtde.host"):
        hardware_config_from_dict(
            {"camera": {"type": "replay", "path": "x"}, "arm": {"type": "ur_rtde"}, "safety": SAFETY}
        )
    with pytest.raises(HardwareConfigError, match=r"safety.workspace_max_m"):
        hardware_config_from_dict(
            {"camera": {"type": "sim"}, "arm": {"type": "sim"}, "safety": {"workspace_min_m": [0, 0, 0]}}
        )


def test_out_of_range_values_are_named():
    with pytest.raises(HardwareConfigError, match=r"safety.max_speed_mps"):
        hardware_config_from_dict(
            {"camera": {"type": "sim"}, "arm": {"type": "sim"}, "safety": {**SAFETY, "max_speed_mps": -1}}
        )
    with pytest.raises(HardwareConfigError, match=r"arm.ur_rtde.gain"):
        hardware_config_from_dict(
            {"camera": {"type": "sim"}, "arm": {"type": "ur_rtde", "host": "h", "gain": 5}, "safety": SAFETY}
        )


def test_sim_camera_needs_the_sim_arm():
    with pytest.raises(HardwareConfigError, match="needs arm.type 'sim'"):
        hardware_config_from_dict(
            {"camera": {"type": "sim"}, "arm": {"type": "serial", "port": "loop://"}, "safety": SAFETY}
        )


def test_unreadable_and_malformed_files_are_named(tmp_path):
    with pytest.raises(HardwareConfigError, match="cannot read"):
        load_hardware_config(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("camera: [unclosed\n")
    with pytest.raises(HardwareConfigError, match="not valid YAML"):
        load_hardware_config(bad)


def test_factories_return_a_safety_wrapped_arm_and_need_the_world_for_sim_devices():
    cfg = hardware_config_from_dict(
        {"camera": {"type": "replay", "path": "frames"}, "arm": {"type": "serial", "port": "loop://"}, "safety": SAFETY}
    )
    assert isinstance(build_arm(cfg), SafeArm)
    assert build_camera(cfg).name == "replay"
    sim_cfg = hardware_config_from_dict({"camera": {"type": "sim"}, "arm": {"type": "sim"}, "safety": SAFETY})
    with pytest.raises(HardwareConfigError, match="world=build_world"):
        build_arm(sim_cfg)


def test_calibration_files_are_loaded_and_validated(tmp_path):
    from calibration.intrinsics import CameraIntrinsics, save_camera_yaml

    save_camera_yaml(
        tmp_path / "cam.yaml",
        CameraIntrinsics(np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]]), np.zeros(5), 640, 480),
    )
    (tmp_path / "T_tcp_cam.yaml").write_text(
        "T_tcp_cam:\n  translation_m: [0.0, -0.05, 0.02]\n  rotvec_rad: [0, 0, 1.5708]\n"
    )
    (tmp_path / "frames").mkdir()
    cfg = hardware_config_from_dict(
        {
            "camera": {"type": "replay", "path": "frames", "intrinsics": "cam.yaml"},
            "arm": {"type": "serial", "port": "loop://"},
            "safety": SAFETY,
            "T_tcp_cam": "T_tcp_cam.yaml",
        },
        base=tmp_path,
    )
    assert build_camera(cfg).intrinsics.K[0, 0] == 600.0
    T = load_T_tcp_cam(cfg.T_tcp_cam)
    assert T[1, 3] == pytest.approx(-0.05) and T[0, 1] == pytest.approx(-1.0, abs=1e-4)
    (tmp_path / "bad.yaml").write_text("translation_m: [0, 0]\nrotvec_rad: [0, 0, 0]\n")
    with pytest.raises(Exception, match=r"bad.yaml: translation_m"):
        load_T_tcp_cam(tmp_path / "bad.yaml")
