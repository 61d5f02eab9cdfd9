"""Hardware config: every shipped example validates; bad input names the file and field.

The arms a URDF describes use the shipped UR5 and Panda (no SO-100 or Koch URDF is shipped): the
servo-bus arms are the Panda's chain driven by servos, as in test_feetech.py."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

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


# ---------------------------------------------------------------------- arms a URDF describes
PANDA = {"urdf": "panda", "base_link": "panda_link0", "tool_link": "panda_hand"}
UR5 = {"urdf": "ur5", "base_link": "base_link", "tool_link": "tool0"}
REPLAY = {"type": "replay", "path": "frames"}


def _panda_servos(**change) -> list[dict]:
    """One servo per shipped Panda joint, centred in its turn (as tests/robot_io/test_feetech.py's)."""
    from sim.ik import SceneArm
    from sim.kinematics import shipped_arm
    from tests.robot_io.test_feetech import centred_joints

    scene_arm = SceneArm(shipped_arm("panda"), np.eye(4), np.eye(4), 0.05, np.zeros(7))
    out = [dict(id=j.id, name=j.name, sign=j.sign, offset_ticks=j.offset_ticks) for j in centred_joints(scene_arm)]
    for k, fields in change.items():
        out[int(k.removeprefix("j"))].update(fields)
    return out


def _hw(arm: dict, source: str = "hw.yaml", base: Path | None = None):
    return hardware_config_from_dict({"camera": REPLAY, "arm": arm, "safety": SAFETY}, source=source, base=base)


def _refused(arm: dict, base: Path | None = None) -> str:
    """The one-line message a hardware config with ``arm`` is refused with."""
    with pytest.raises(HardwareConfigError) as info:
        _hw(arm, base=base)
    text = str(info.value)
    assert "\n" not in text and text.startswith("hw.yaml: "), text
    return text


def test_a_ur_with_kinematics_takes_joint_commands_placed_in_its_base_frame():
    from robot_io.arms.ur_rtde import URArm

    cfg = _hw(
        {
            "type": "ur_rtde",
            "host": "10.0.0.2",
            "joint_acceleration_radps2": 0.7,
            "kinematics": {**UR5, "rotvec_base_link": [0, 0, np.pi], "t_tool_tcp_m": [0, 0, 0.1]},
        }
    )
    driver = ARM_TYPES["ur_rtde"](cfg, None)
    assert isinstance(driver, URArm) and driver.joint_acceleration_radps2 == 0.7
    kin = build_arm(cfg).kinematics()
    assert kin.joint_names[0] == "shoulder_pan_joint" and kin.n_joints == 6
    assert kin.control_period_s == cfg.safety.control_period_s
    np.testing.assert_allclose(kin.T_world_base[:3, :3], np.diag([-1.0, -1.0, 1.0]), atol=1e-12)
    np.testing.assert_allclose(kin.T_tool_tcp[:3, 3], [0, 0, 0.1])


def test_ur_and_serial_arms_without_kinematics_take_tcp_commands_only():
    for arm in ({"type": "ur_rtde", "host": "h"}, {"type": "serial", "port": "loop://"}):
        cfg = _hw(arm)
        assert cfg.arm.kinematics is None and build_arm(cfg).kinematics() is None
    assert _hw({"type": "ur_rtde", "host": "h"}).arm.joint_acceleration_radps2 > 0


def test_a_relative_urdf_is_resolved_against_the_yaml_folder_and_a_shipped_name_stays_a_name(tmp_path):
    from sim.kinematics import shipped_urdf

    (tmp_path / "urdf").mkdir()
    (tmp_path / "urdf" / "arm.urdf").write_bytes(shipped_urdf("ur5").read_bytes())
    (tmp_path / "hw.yaml").write_text(
        "camera: {type: replay, path: frames}\n"
        "arm:\n  type: serial\n  port: 'loop://'\n"
        "  kinematics: {urdf: urdf/arm.urdf, base_link: base_link, tool_link: tool0, q_home: [0, -1, 1, -1, -1, 0]}\n"
        "safety: {workspace_min_m: [0, 0, 0], workspace_max_m: [1, 1, 1]}\n"
    )
    cfg = load_hardware_config(tmp_path / "hw.yaml")
    assert cfg.arm.kinematics.urdf == str(tmp_path / "urdf" / "arm.urdf")
    kin = build_arm(cfg).kinematics()
    assert kin.n_joints == 6 and kin.q_home.tolist() == [0, -1, 1, -1, -1, 0]
    assert _hw({"type": "serial", "port": "x", "kinematics": UR5}, base=tmp_path).arm.kinematics.urdf == "ur5"


@pytest.mark.parametrize("kind", ["feetech", "dynamixel"])
def test_a_bus_arm_from_the_config_connects_to_its_twin_and_reads_its_joints(kind):
    from robot_io.arms.dynamixel_sim import DynamixelSimulator
    from robot_io.arms.feetech_sim import FeetechSimulator
    from robot_io.arms.servo_bus import ServoJoint, SimServo

    servos = _panda_servos()
    gripper = {"id": 8, "name": "gripper", "offset_ticks": 2048}
    at = [SimServo(s["id"], position_ticks=s["offset_ticks"]) for s in [*servos, gripper]]  # every joint at q = 0
    twin = {"feetech": FeetechSimulator, "dynamixel": DynamixelSimulator}[kind]
    sim, path = twin.on_pty(at)
    try:
        arm = {"type": kind, "port": path, "timeout_ms": 250, "joints": servos[::-1], "gripper": gripper}
        cfg = _hw({**arm, "kinematics": PANDA})
        safe = build_arm(cfg)
        with safe:
            assert safe.kinematics().joint_names == tuple(s["name"] for s in servos)
            np.testing.assert_array_equal(safe.joint_positions(), np.zeros(7))
            assert safe.identity()["servo_ids"] == "1,2,3,4,5,6,7,8"
        driver = ARM_TYPES[kind](cfg, None)
        assert driver.gripper == ServoJoint(8, "gripper", 1, 2048) and driver.baudrate == 1_000_000
    finally:
        sim.close()


@pytest.mark.parametrize("kind", ["feetech", "dynamixel"])
def test_a_bus_arm_needs_its_kinematics_and_its_joints(kind):
    assert "arm.{0}.kinematics: Field required".format(kind) in _refused(
        {"type": kind, "port": "p", "joints": _panda_servos()}
    )
    assert f"arm.{kind}.joints: Field required" in _refused({"type": kind, "port": "p", "kinematics": PANDA})


@pytest.mark.parametrize(
    "change, field",
    [
        ({"j0": {"id": 253}}, "joints.0.id"),
        ({"j0": {"id": 1.5}}, "joints.0.id"),
        ({"j1": {"sign": 0}}, "joints.1.sign"),
        ({"j2": {"ticks_per_rev": 1}}, "joints.2.ticks_per_rev"),
        ({"j3": {"offset_ticks": "2048"}}, "joints.3.offset_ticks"),
        ({"j4": {"name": ""}}, "joints.4.name"),
        ({"j5": {"speed": 3}}, "joints.5.speed"),
    ],
)
def test_a_bad_servo_entry_is_named(change, field):
    assert f"arm.feetech.{field}: " in _refused(
        {"type": "feetech", "port": "p", "joints": _panda_servos(**change), "kinematics": PANDA}
    )


def test_servo_ids_must_be_unique_on_the_bus_gripper_included():
    text = _refused(
        {
            "type": "dynamixel",
            "port": "p",
            "joints": _panda_servos(),
            "gripper": {"id": 3, "name": "gripper"},
            "kinematics": PANDA,
        }
    )
    assert "arm.dynamixel: " in text and "[3] repeat" in text


@pytest.mark.parametrize(
    "joints, words",
    [
        (_panda_servos(j6={"name": "wrist"}), "not in the URDF chain: wrist"),
        (_panda_servos()[:6], "missing: panda_joint7"),
        (_panda_servos(j6={"name": "panda_joint1"}), "twice: panda_joint1"),
        ([*_panda_servos(), {"id": 9, "name": "panda_finger_joint1"}], "not in the URDF chain: panda_finger_joint1"),
    ],
    ids=["unknown", "one_short", "twice", "one_more"],
)
def test_servos_that_are_not_the_chains_joints_are_refused_naming_the_urdf(joints, words):
    text = _refused({"type": "feetech", "port": "p", "joints": joints, "kinematics": PANDA})
    assert "arm.feetech.joints: " in text and words in text and "panda.urdf" in text


def test_a_gripper_named_as_a_chain_joint_is_refused():
    text = _refused(
        {
            "type": "feetech",
            "port": "p",
            "joints": _panda_servos(),
            "gripper": {"id": 8, "name": "panda_joint7"},
            "kinematics": PANDA,
        }
    )
    assert "arm.feetech.gripper.name: 'panda_joint7' is a joint of the URDF chain" in text


def test_a_prismatic_joint_in_a_bus_arms_chain_is_refused():
    fingers = {**PANDA, "tool_link": "panda_leftfinger"}
    joints = [*_panda_servos(), {"id": 9, "name": "panda_finger_joint1"}]
    text = _refused({"type": "feetech", "port": "p", "joints": joints, "kinematics": fingers})
    assert "arm.feetech.joints: " in text and "panda_finger_joint1 is prismatic" in text


def _broken_urdfs(tmp_path: Path) -> dict[str, tuple[dict, str, str]]:
    """name -> (kinematics block, the field named, words of the problem)."""
    (tmp_path / "bad.urdf").write_text("<robot name='x'><link name='a'>\n")
    (tmp_path / "xacro.urdf").write_text("<robot name='x'><link name='${prefix}a'/></robot>\n")
    return {
        "missing": ({**UR5, "urdf": "none.urdf"}, "urdf", "none.urdf: no such URDF file"),
        "malformed": ({**UR5, "urdf": "bad.urdf"}, "urdf", "bad.urdf: not well-formed XML"),
        "xacro": ({**UR5, "urdf": "xacro.urdf"}, "urdf", "xacro.urdf"),
        "no_base_link": ({**UR5, "base_link": "root"}, "base_link", "base_link 'root' is not a link of the URDF"),
        "no_tool_link": ({**UR5, "tool_link": "flange"}, "tool_link", "tool_link 'flange' is not a link"),
        "tool_above_base": ({**UR5, "base_link": "tool0", "tool_link": "base_link"}, "tool_link", "is not below"),
    }


@pytest.mark.parametrize("case", ["missing", "malformed", "xacro", "no_base_link", "no_tool_link", "tool_above_base"])
@pytest.mark.parametrize("kind", ["ur_rtde", "serial", "feetech"])
def test_a_urdf_that_is_missing_malformed_or_lacks_the_links_is_one_line_naming_file_and_field(tmp_path, kind, case):
    kinematics, field, words = _broken_urdfs(tmp_path)[case]
    arm = {"ur_rtde": {"host": "h"}, "serial": {"port": "p"}, "feetech": {"port": "p", "joints": _panda_servos()}}[kind]
    text = _refused({"type": kind, **arm, "kinematics": kinematics}, base=tmp_path)
    assert f"arm.{kind}.kinematics.{field}: " in text and words in text


def test_a_ur_urdf_without_six_joints_is_refused():
    text = _refused({"type": "ur_rtde", "host": "h", "kinematics": PANDA})
    assert "arm.ur_rtde.kinematics.urdf: " in text and "7 joints" in text and "a UR arm has 6" in text


@pytest.mark.parametrize(
    "change, field, words",
    [
        ({"q_home": [0.0] * 5}, "kinematics.q_home", "5 values for the 6 joints"),
        ({"q_home": [7.0, 0, 0, 0, 0, 0]}, "kinematics.q_home.0", "'shoulder_pan_joint' at 7.0 rad is outside"),
        ({"q_home": [0, float("nan"), 0, 0, 0, 0]}, "kinematics.q_home.1", "finite number"),
        ({"t_tool_tcp_m": [0, float("inf"), 0]}, "kinematics.t_tool_tcp_m.1", "finite number"),
        ({"rotvec_base_link": [0, 0, 7.0]}, "kinematics", "rotvec_base_link: the rotation angle"),
        ({"t_base_link_m": [0, 0, 1e6]}, "kinematics", "t_base_link_m: each coordinate"),
        ({"q_min": [0.0] * 6}, "kinematics.q_min", "Extra inputs"),
    ],
)
def test_bad_kinematics_values_are_named(change, field, words):
    text = _refused({"type": "serial", "port": "p", "kinematics": {**UR5, **change}})
    assert f"arm.serial.{field}: " in text and words in text


@settings(max_examples=60, deadline=None)
@given(q=st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=0, max_size=8))
def test_any_q_home_loads_within_the_limits_or_is_one_line_naming_it(q):
    try:
        cfg = _hw({"type": "serial", "port": "p", "kinematics": {**UR5, "q_home": q}})
    except HardwareConfigError as err:
        assert "\n" not in str(err) and "arm.serial.kinematics.q_home" in str(err)
    else:
        assert len(q) == 6 and all(abs(x) <= 2 * np.pi for x in q)  # the UR5's joint limits
        assert cfg.arm.kinematics.q_home == tuple(q)


def test_a_servo_bus_constructors_refusal_is_one_line_naming_the_arm():
    from robot_io.config import ServoJointConfig

    cfg = _hw({"type": "feetech", "port": "p", "joints": _panda_servos(), "kinematics": PANDA})
    unchecked = cfg.model_copy(
        update={"arm": cfg.arm.model_copy(update={"gripper": ServoJointConfig(id=8, name="panda_joint2")})}
    )  # a config not loaded through the checks
    with pytest.raises(HardwareConfigError, match=r"^arm\.feetech: feetech arm: the gripper 'panda_joint2'") as info:
        build_arm(unchecked)
    assert "\n" not in str(info.value)


def test_a_urdf_gone_after_loading_is_one_line_at_build(tmp_path):
    from sim.kinematics import shipped_urdf

    urdf = tmp_path / "arm.urdf"
    urdf.write_bytes(shipped_urdf("ur5").read_bytes())
    cfg = _hw({"type": "serial", "port": "p", "kinematics": {**UR5, "urdf": "arm.urdf"}}, base=tmp_path)
    urdf.unlink()
    with pytest.raises(HardwareConfigError, match=r"^arm\.serial\.kinematics\.urdf: .*arm\.urdf: no such URDF file"):
        build_arm(cfg)


def _chain_urdf(links: list[str], joints: list[str]) -> str:
    """A plain URDF: ``links`` in a line, joint ``k`` (revolute about z, +-2 rad) from link ``k`` to ``k + 1``."""
    body = "".join(f'<link name="{name}"/>' for name in links)
    for k, name in enumerate(joints):
        body += (
            f'<joint name="{name}" type="revolute"><parent link="{links[k]}"/><child link="{links[k + 1]}"/>'
            '<origin xyz="0 0 0.05"/><axis xyz="0 0 1"/><limit lower="-2" upper="2" velocity="3" effort="1"/></joint>'
        )
    return f'<robot name="chain">{body}</robot>'


def test_the_lerobot_arm_block_in_real_trials_md_loads_once_its_urdf_is_there(tmp_path):
    import yaml

    doc = (Path(__file__).resolve().parents[2] / "docs" / "real-trials.md").read_text()
    section = doc.split("## LeRobot arms (SO-100/SO-101, Koch)", 1)[1]
    block = yaml.safe_load(section.split("```yaml", 1)[1].split("```", 1)[0])
    kin, names = block["arm"]["kinematics"], [j["name"] for j in block["arm"]["joints"]]
    # Without the user's URDF it is refused naming it; with a URDF of that chain it loads.
    assert "arm.feetech.kinematics.urdf: " in _refused(block["arm"], base=tmp_path)
    urdf = tmp_path / kin["urdf"]
    urdf.parent.mkdir(parents=True)
    links = [kin["base_link"], *[f"link{k}" for k in range(len(names) - 1)], kin["tool_link"]]
    urdf.write_text(_chain_urdf(links, names))
    cfg = _hw(block["arm"], base=tmp_path)
    assert build_arm(cfg).kinematics().joint_names == tuple(names)
