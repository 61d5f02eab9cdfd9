"""The hardware config YAML: which cameras, which arm, the safety limits, the calibration files.

Validated with pydantic (unknown keys are errors; every error names the file and field), and
turned into devices by :func:`build_camera` / :func:`build_scene_camera` / :func:`build_arm`
through explicit type -> class tables. ``build_arm`` returns the arm wrapped in
:class:`robot_io.safety.SafeArm`: callers never hold a raw driver. Relative paths in the YAML are
relative to the YAML file.

Arms: ``sim`` (the sim world's), ``ur_rtde``, ``serial``, and the servo-bus arms LeRobot users own,
``feetech`` (SO-100/SO-101) and ``dynamixel`` (Koch). An arm a URDF describes takes joint commands:
its ``kinematics`` block (:class:`ArmKinematicsConfig`: the URDF, its base and tool links, the TCP in
the tool link) is optional for ``ur_rtde`` and ``serial`` and required for the servo-bus arms, whose
``joints`` map each servo to a joint of that chain. The URDF is read when the config loads, so a
missing or malformed file, absent links, servos that are not the chain's joints or a ``q_home`` of
the wrong length are one line naming the file and the field.

Cameras: ``camera`` is the wrist camera (named ``wrist``); ``scene_cameras`` the fixed ones, by
name (``front: {type: opencv, ..., T_table_cam: front_pose.yaml}``). A real fixed camera needs its
pose in the table frame, the file ``advobj calibrate scene-camera`` writes, and delivers frames of
the size that pose was estimated at; a ``sim`` one is the sim scene's camera of the same name.

A ``sim`` camera (wrist or fixed) and a ``sim`` arm share one :class:`sim.world.SimWorld`
(``build_world``), so a whole trial session runs without hardware.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Literal, Union

import numpy as np
from pydantic import Field, ValidationError, field_validator, model_validator

from calibration.intrinsics import load_camera_yaml
from calibration.io import PoseModel, Vec3, load_model, load_scene_camera_pose, not_a_regular_file
from calibration.io import read_yaml as read_calibration_yaml
from robot_io.arms.dynamixel import DynamixelArm
from robot_io.arms.feetech import FeetechArm
from robot_io.arms.serial import SerialArm
from robot_io.arms.servo_bus import MAX_SERVO_ID, ServoBusError, ServoJoint, order_servo_joints
from robot_io.arms.sim import SimArm
from robot_io.arms.ur_rtde import UR_JOINTS, URArm
from robot_io.cameras.depthai import DepthAICamera
from robot_io.cameras.opencv import OpenCVCamera
from robot_io.cameras.replay import ReplayCamera
from robot_io.cameras.sim import SimCamera, SimSceneCamera
from robot_io.errors import HardwareConfigError
from robot_io.safety import SafeArm, SafetyLimits
from sim.configio import StrictModel, file_error, merged, read_yaml
from sim.errors import format_validation_error
from sim.spec import CAMERA_NAME, WRIST, ArmModelConfig, default_scene, load_scene
from sim.world import SimWorld

__all__ = [
    "HardwareConfig",
    "SimCameraConfig",
    "OpenCVCameraConfig",
    "DepthAICameraConfig",
    "ReplayCameraConfig",
    "SimSceneCameraConfig",
    "OpenCVSceneCameraConfig",
    "DepthAISceneCameraConfig",
    "ReplaySceneCameraConfig",
    "SimArmConfig",
    "URArmConfig",
    "SerialArmConfig",
    "FeetechArmConfig",
    "DynamixelArmConfig",
    "ArmKinematicsConfig",
    "ServoJointConfig",
    "SimConfig",
    "load_hardware_config",
    "hardware_config_from_dict",
    "load_T_tcp_cam",
    "build_world",
    "build_camera",
    "build_scene_camera",
    "scene_camera_pose",
    "build_arm",
    "build_scene_arm",
    "CAMERA_TYPES",
    "ARM_TYPES",
]

Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Px = Annotated[int, Field(gt=0, le=8192)]
SimPx = Annotated[int, Field(gt=0, le=2048)]


class _Strict(StrictModel):
    pass


# ---------------------------------------------------------------------- cameras
class SimCameraConfig(_Strict):
    """Renders the sim world from the sim arm's TCP (needs ``arm.type: sim``)."""

    type: Literal["sim"]
    tags: bool = Field(
        False,
        description="draw tag36h11 tags on the objects and the table (the session's --registry, or one "
        "generated for the scene) and locate the objects through them, as a real cell does",
    )


class OpenCVCameraConfig(_Strict):
    type: Literal["opencv"]
    device: str | int = Field(description="/dev/v4l/by-id/... (stable), /dev/videoN or an index")
    width: Px | None = None
    height: Px | None = None
    fps: Positive | None = None
    fourcc: Annotated[str, Field(min_length=4, max_length=4)] | None = None
    timeout_ms: Positive = 1000.0
    intrinsics: Path | None = Field(None, description="camera YAML written by the calibration tools")


class DepthAICameraConfig(_Strict):
    type: Literal["depthai"]
    socket: Literal["CAM_A", "CAM_B", "CAM_C", "CAM_D"] = "CAM_A"
    width: Px = 640
    height: Px = 480
    fps: Positive = 30.0
    timeout_ms: Positive = 1000.0
    intrinsics: Path | None = Field(None, description="overrides the device's factory calibration")


class ReplayCameraConfig(_Strict):
    type: Literal["replay"]
    path: Path = Field(description="a folder of images or a video file")
    loop: bool = False
    fps: Positive | None = None
    intrinsics: Path | None = None


CameraConfig = Annotated[
    Union[SimCameraConfig, OpenCVCameraConfig, DepthAICameraConfig, ReplayCameraConfig], Field(discriminator="type")
]


# ---------------------------------------------------------------------- fixed scene cameras
_T_TABLE_CAM = "the camera's pose in the table frame: the file 'advobj calibrate scene-camera' writes"


class SimSceneCameraConfig(_Strict):
    """A fixed camera of the sim world: the sim scene's camera of the same name (``scene_cameras`` of
    the scene YAML), rendered at that camera's size and intrinsics (needs ``arm.type: sim``)."""

    type: Literal["sim"]
    T_table_cam: Path | None = Field(None, description=f"{_T_TABLE_CAM}; default: the pose the scene declares")


class _RealSceneCamera(_Strict):
    """A real fixed camera: its device fields, and its calibrated pose (required)."""

    T_table_cam: Path | None = Field(
        None, description=f"{_T_TABLE_CAM} (required: a fixed camera without it is refused)"
    )

    @model_validator(mode="after")
    def _extrinsics(self):
        if self.T_table_cam is None:
            raise ValueError(
                "T_table_cam missing: a fixed scene camera with no extrinsics is refused; locate it against the "
                "table's tags with 'advobj calibrate scene-camera' and name the pose file it writes"
            )
        return self


class OpenCVSceneCameraConfig(_RealSceneCamera, OpenCVCameraConfig):
    """A fixed V4L2 / OpenCV camera and its pose file."""


class DepthAISceneCameraConfig(_RealSceneCamera, DepthAICameraConfig):
    """A fixed Luxonis OAK camera and its pose file."""


class ReplaySceneCameraConfig(_RealSceneCamera, ReplayCameraConfig):
    """Recorded frames of a fixed camera (a folder of images or a video file) and its pose file."""


SceneCameraConfig = Annotated[
    Union[SimSceneCameraConfig, OpenCVSceneCameraConfig, DepthAISceneCameraConfig, ReplaySceneCameraConfig],
    Field(discriminator="type"),
]


# ---------------------------------------------------------------------- arms
_ARM_MODEL = ArmModelConfig.model_fields  # the scene's arm schema: its fields are reused below
# ArmModelConfig's names of the base placement -> this block's (its frame is the arm's base frame).
_PLACEMENT_NAMES = {"t_table_base_m": "t_base_link_m", "rotvec_table_base": "rotvec_base_link"}


class ArmKinematicsConfig(_Strict):
    """The arm as a URDF: the chain from ``base_link`` to ``tool_link``, the TCP in the tool link's frame.

    The scene's arm (:class:`sim.spec.ArmModelConfig`, whose fields and rules it reuses) placed in
    the arm's own base frame, the frame of its TCP pose and of the workspace box: the TCP is
    ``T_base_tcp = T_base_link FK(q) T_tool_tcp``. A plain URDF (no xacro; meshes are ignored) with
    both links in it, the tool link below the base link, and every joint between them revolute or
    prismatic with finite position and velocity limits; a joint command is in the chain's order and
    units (rad, m).
    """

    urdf: str = Field(
        min_length=1, description="a shipped arm (panda, ur5) or a URDF file, relative to this YAML's folder"
    )
    base_link: str = Field(
        min_length=1, description="the URDF link the chain starts at; it stands at t_base_link_m, rotvec_base_link"
    )
    tool_link: str = _ARM_MODEL["tool_link"]
    t_base_link_m: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0),
        description="where base_link stands in the arm's base frame (the frame of its TCP pose) (m); zero: it is "
        "that frame",
    )
    rotvec_base_link: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0),
        description="base_link's orientation in the arm's base frame, axis-angle (rad); a UR controller's base "
        "is ur_description's base_link turned by pi about z: [0, 0, 3.141592653589793] with base_link 'base_link'",
    )
    t_tool_tcp_m: tuple[float, float, float] = _ARM_MODEL["t_tool_tcp_m"]
    rotvec_tool_tcp: tuple[float, float, float] = _ARM_MODEL["rotvec_tool_tcp"]
    q_home: tuple[float, ...] | None = _ARM_MODEL["q_home"]

    @model_validator(mode="after")
    def _scene_arm_rules(self):
        try:
            self.arm_model()
        except ValidationError as err:
            e = err.errors()[0]
            field = ".".join(_PLACEMENT_NAMES.get(str(p), str(p)) for p in e["loc"])
            raise ValueError(f"{field}: {e['msg'].removeprefix('Value error, ')}") from None
        return self

    def arm_model(self, control_period_s: float | None = None) -> ArmModelConfig:
        """This arm as the scene's :class:`sim.spec.ArmModelConfig`, its "table" frame the arm's base
        frame; ``control_period_s``: the safety layer's (``None``: the scene default)."""
        data = self.model_dump()
        data["t_table_base_m"] = data.pop("t_base_link_m")
        data["rotvec_table_base"] = data.pop("rotvec_base_link")
        if control_period_s is not None:
            data["control_period_s"] = control_period_s
        return ArmModelConfig.model_validate(data)


class SimArmConfig(_Strict):
    """The sim world's arm; a scene with an ``arm`` (a URDF) makes it joint-driven."""

    type: Literal["sim"]
    max_speed_mps: Positive = 0.5
    max_speed_radps: Positive = 2.0
    realtime: bool = False


_KINEMATICS = "the arm's URDF, its TCP the one the controller reports: given, the arm also takes joint commands"


class URArmConfig(_Strict):
    type: Literal["ur_rtde"]
    host: Annotated[str, Field(min_length=1, description="controller address")]
    mode: Literal["servoL", "speedL"] = "servoL"
    acceleration_mps2: Positive = 0.5
    lookahead_time_s: Annotated[float, Field(ge=0.03, le=0.2)] = 0.1
    gain: Annotated[float, Field(ge=100, le=2000)] = 300.0
    watchdog_min_hz: Positive = 10.0
    joint_acceleration_radps2: Positive = Field(1.4, description="moveJ acceleration of the leading joint")
    kinematics: ArmKinematicsConfig | None = Field(None, description=f"{_KINEMATICS} (servoJ, moveJ); 6 joints")


class SerialArmConfig(_Strict):
    type: Literal["serial"]
    port: Annotated[str, Field(min_length=1, description="/dev/serial/by-id/..., /dev/ttyACM0 or a pyserial URL")]
    baudrate: Annotated[int, Field(gt=0)] = 115200
    timeout_ms: Positive = 200.0
    retries: Annotated[int, Field(ge=0, le=20)] = 3
    boot_timeout_ms: Positive = 3000.0
    expect_banner: bool = True
    kinematics: ArmKinematicsConfig | None = Field(
        None, description=f"{_KINEMATICS} (JOINTS, MOVEJ; the firmware must have as many joints)"
    )


ServoId = Annotated[int, Field(strict=True, ge=0, le=MAX_SERVO_ID)]


class ServoJointConfig(_Strict):
    """One servo on the bus and the joint it turns: ``q_rad = sign * (ticks - offset_ticks) * 2 pi /
    ticks_per_rev`` (:class:`robot_io.arms.servo_bus.ServoJoint`)."""

    id: ServoId = Field(description="the servo's bus id")
    name: str = Field(min_length=1, description="the joint's name in the URDF (the gripper's: any name)")
    sign: Literal[1, -1] = Field(1, description="1 when rising ticks turn the joint positively, else -1")
    offset_ticks: Annotated[int, Field(strict=True)] = Field(0, description="the servo's reading at q = 0")
    ticks_per_rev: Annotated[int, Field(strict=True, ge=2)] = Field(
        4096, description="encoder ticks per turn (4096: STS3215, Dynamixel X-series)"
    )

    def servo_joint(self) -> ServoJoint:
        return ServoJoint(self.id, self.name, self.sign, self.offset_ticks, self.ticks_per_rev)


class _BusArmConfig(_Strict):
    """A servo-bus arm: servos on one half-duplex bus behind a USB adapter, a URDF for its kinematics."""

    type: Literal["feetech", "dynamixel"]
    port: Annotated[str, Field(min_length=1, description="the bus adapter: /dev/serial/by-id/..., /dev/ttyACM0")]
    baudrate: Annotated[int, Field(gt=0)] = Field(1_000_000, description="the bus speed the servos are set to")
    timeout_ms: Positive = Field(50.0, description="per reply; then the same request is resent")
    retries: Annotated[int, Field(ge=0, le=20)] = Field(3, description="resends before the link counts as lost")
    joints: list[ServoJointConfig] = Field(
        min_length=1, description="one servo per joint of the URDF chain, any order: exactly the chain's joints"
    )
    gripper: ServoJointConfig | None = Field(None, description="the gripper's servo (on the bus, not in the URDF)")
    settle_ticks: Annotated[int, Field(ge=0)] = Field(2, description="a positioning move ends this close to its goal")
    settle_timeout_s: Annotated[float, Field(ge=0)] = Field(
        1.0, description="how much longer than planned a positioning move may take before the arm stops"
    )
    max_speed_radps: Positive = Field(1.0, description="TCP rotation speed of a positioning move")
    torque_off_on_close: bool = Field(
        False, description="release torque on disconnect (the arm then falls under gravity)"
    )
    kinematics: ArmKinematicsConfig = Field(description="the arm's URDF (required: the servos know only ticks)")

    @model_validator(mode="after")
    def _unique_ids(self):
        ids = [j.id for j in self.joints] + ([self.gripper.id] if self.gripper is not None else [])
        twice = sorted({i for i in ids if ids.count(i) > 1})
        if twice:
            raise ValueError(f"servo ids must be unique on the bus (joints and gripper); {twice} repeat")
        return self


class FeetechArmConfig(_BusArmConfig):
    """SO-100/SO-101: Feetech STS3215 servos, Feetech's STS protocol (docs/real-trials.md, LeRobot arms)."""

    type: Literal["feetech"]


class DynamixelArmConfig(_BusArmConfig):
    """Koch v1.1: Dynamixel X-series servos, Protocol 2.0 (docs/real-trials.md, LeRobot arms)."""

    type: Literal["dynamixel"]


ArmConfig = Annotated[
    Union[SimArmConfig, URArmConfig, SerialArmConfig, FeetechArmConfig, DynamixelArmConfig],
    Field(discriminator="type"),
]


class SimConfig(_Strict):
    """The simulated world behind ``sim`` devices."""

    scene: Path | None = Field(None, description="scene YAML; default: the built-in paper scene")
    seed: int = 0
    # A sim twin renders every frame on the CPU: 2048 px a side covers a 1080p camera's twin; an
    # 8192 px image took minutes a frame, checked here before any world is built.
    image_size: tuple[SimPx, SimPx] | None = Field(
        None, description="(H, W) px, at most 2048 a side; default: the scene camera's"
    )


class HardwareConfig(_Strict):
    camera: CameraConfig
    arm: ArmConfig
    safety: SafetyLimits
    T_tcp_cam: Path | None = Field(None, description="YAML with the camera pose in the TCP frame (hand-eye result)")
    sim: SimConfig = SimConfig()
    scene_cameras: dict[str, SceneCameraConfig] = Field(
        default_factory=dict,
        description="fixed cameras besides the wrist camera (named 'wrist'), by name as a policy's card reads "
        "them: a lower case letter, then lower case letters, digits or _ (at most 32)",
    )

    @field_validator("scene_cameras")
    @classmethod
    def _camera_names(cls, cams):
        for name in cams:
            if name == WRIST:
                raise ValueError("'wrist' names the wrist camera (the camera field); call this one otherwise")
            if not re.fullmatch(CAMERA_NAME, name):
                raise ValueError(
                    f"{name[:40]!r}: a camera name is a lower case letter, then lower case letters, digits or _ (<= 32)"
                )
        return cams

    @model_validator(mode="after")
    def _sim_pairing(self):
        if self.camera.type == "sim" and self.arm.type != "sim":
            raise ValueError("camera.type 'sim' renders from the sim arm's pose: it needs arm.type 'sim'")
        for name, c in self.scene_cameras.items():
            if c.type == "sim" and self.arm.type != "sim":
                raise ValueError(
                    f"scene_cameras.{name}: type 'sim' renders the sim world, which only a sim arm moves in: it needs "
                    "arm.type 'sim'"
                )
        return self


# ---------------------------------------------------------------------- loading
def _regular(path: Path | None, what: str) -> None:
    """Refuse a device, FIFO or socket where a file belongs, before anything opens it (it would block
    or never end)."""
    problem = None if path is None else not_a_regular_file(path)
    if problem is not None:
        raise HardwareConfigError(f"{path}: {what}: {problem}")


def _resolve(cfg: HardwareConfig, base: Path | None) -> HardwareConfig:
    if base is None:
        return cfg

    def fix(p: Path | None) -> Path | None:
        return p if p is None or p.is_absolute() else base / p

    def fixed(c) -> dict:
        keys = ("intrinsics", "path", "T_table_cam")
        return {**c.model_dump(), **{k: fix(getattr(c, k)) for k in keys if hasattr(c, k)}}

    sim = {**cfg.sim.model_dump(), "scene": fix(cfg.sim.scene)}
    scene_cameras = {name: fixed(c) for name, c in cfg.scene_cameras.items()}
    arm = cfg.arm.model_dump()
    kin = getattr(cfg.arm, "kinematics", None)
    if kin is not None:
        from sim.kinematics import SHIPPED_ARMS  # lazy: robot_io start-up (torch)

        if kin.urdf not in SHIPPED_ARMS:  # a shipped arm's name stays a name
            arm["kinematics"]["urdf"] = str(fix(Path(kin.urdf)))
    return merged(
        cfg,
        {
            "camera": fixed(cfg.camera),
            "arm": arm,
            "T_tcp_cam": fix(cfg.T_tcp_cam),
            "sim": sim,
            "scene_cameras": scene_cameras,
        },
        what="hardware config",
        source=str(base),
        error=HardwareConfigError,
    )


def hardware_config_from_dict(data, source: str = "<dict>", base: Path | None = None) -> HardwareConfig:
    if not isinstance(data, dict):
        raise HardwareConfigError(f"{source}: a hardware config must be a mapping, got {type(data).__name__}")
    try:
        cfg = HardwareConfig.model_validate(data)
    except ValidationError as err:
        raise HardwareConfigError(format_validation_error(err, "hardware config", source)) from None
    cfg = _resolve(cfg, base)
    _check_arm_kinematics(cfg, source)
    return cfg


def _check_arm_kinematics(cfg: HardwareConfig, source: str) -> None:
    """Read the arm's URDF chain and check the config against it: the links, ``q_home`` (one value
    per joint, within its limits), a UR's six joints, and a bus arm's servos (exactly the chain's
    revolute joints; the gripper not one of them). A refusal is one line naming ``source`` and the field."""
    a = cfg.arm
    kin = getattr(a, "kinematics", None)
    if kin is None:
        return
    from sim.kinematics import KinematicsError, read_chain, urdf_source  # lazy: robot_io start-up (torch)

    where = f"arm.{a.type}"

    def refuse(field: str, problem: str) -> HardwareConfigError:
        return HardwareConfigError(f"{source}: invalid hardware config: {where}.{field}: {problem}")

    try:
        chain = read_chain(urdf_source(kin.urdf), kin.base_link, kin.tool_link)
    except KinematicsError as err:
        raise refuse(f"kinematics.{err.field or 'urdf'}", str(err)) from None
    names, n = chain.joint_names, len(chain.joint_names)
    if kin.q_home is not None:
        if len(kin.q_home) != n:
            raise refuse(
                "kinematics.q_home", f"{len(kin.q_home)} values for the {n} joints of the chain ({', '.join(names)})"
            )
        for k, v in enumerate(kin.q_home):
            if not chain.q_min[k] <= v <= chain.q_max[k]:
                raise refuse(
                    f"kinematics.q_home.{k}",
                    f"joint {names[k]!r} at {v} {chain.units[k]} is outside its limits "
                    f"[{chain.q_min[k]:.6g}, {chain.q_max[k]:.6g}]",
                )
    if a.type == "ur_rtde" and n != UR_JOINTS:
        raise refuse(
            "kinematics.urdf",
            f"{chain.urdf}: the chain {kin.base_link} -> {kin.tool_link} has {n} joints ({', '.join(names)}); "
            f"a UR arm has {UR_JOINTS}",
        )
    if a.type in ("feetech", "dynamixel"):
        try:
            order_servo_joints(a.type, tuple(j.servo_joint() for j in a.joints), chain)
        except ServoBusError as err:
            raise refuse("joints", f"{err} (the URDF {chain.urdf})") from None
        if a.gripper is not None and a.gripper.name in names:
            raise refuse(
                "gripper.name", f"{a.gripper.name!r} is a joint of the URDF chain; the gripper is no joint of it"
            )


def load_hardware_config(path: str | Path) -> HardwareConfig:
    """Load and validate a hardware YAML; errors name the file and the field."""
    path = Path(path)
    _regular(path, "hardware config")
    data = read_yaml(path, "hardware config", error=file_error(HardwareConfigError))
    return hardware_config_from_dict(data, source=str(path), base=path.resolve().parent)


class _TcpCamFile(PoseModel):
    """The hand-eye result file: :class:`~calibration.io.PoseModel` (its bounds), both fields required."""

    translation_m: Vec3
    rotvec_rad: Vec3


def load_T_tcp_cam(path: str | Path) -> np.ndarray:
    """``T_tcp_cam`` (4, 4) from ``{translation_m: [..], rotvec_rad: [..]}``, top level or under ``T_tcp_cam:``.

    Both fields are required and held to :class:`calibration.io.PoseModel`'s bounds (finite, each
    translation component within +-1 km, rotation vector norm at most 100 rad); an error names the
    file and the field.
    """
    data = read_calibration_yaml(path)
    if isinstance(data, dict) and set(data) == {"T_tcp_cam"}:
        data = data["T_tcp_cam"]
    return load_model(path, _TcpCamFile, data=data).T


def _intrinsics(path: Path | None):
    if path is None:
        return None

    return load_camera_yaml(path)


# ---------------------------------------------------------------------- factories
def build_world(cfg: HardwareConfig):
    """The :class:`sim.world.SimWorld` shared by ``sim`` devices (the caller closes it)."""
    _regular(cfg.sim.scene, "sim.scene")
    spec = load_scene(cfg.sim.scene) if cfg.sim.scene is not None else default_scene()
    return SimWorld(spec, image_size=cfg.sim.image_size, seed=cfg.sim.seed)


def scene_camera_pose(cfg: HardwareConfig, name: str) -> np.ndarray | None:
    """``T_table_cam`` (4, 4) of scene camera ``name`` from its pose file; ``None`` for a sim camera
    without one (it stands where its scene puts it). A bad file: one line naming it and the field."""
    c = cfg.scene_cameras[name]
    if c.T_table_cam is None:
        return None
    _regular(c.T_table_cam, f"scene_cameras.{name}.T_table_cam")
    return load_scene_camera_pose(c.T_table_cam).T


# Each factory builds camera ``name`` (``wrist`` or a scene camera's) from its config ``c``.
def _sim_camera(c, name: str, cfg: HardwareConfig, world):
    if name == WRIST:
        return SimCamera(world, None if cfg.T_tcp_cam is None else load_T_tcp_cam(cfg.T_tcp_cam))
    return SimSceneCamera(world, name, scene_camera_pose(cfg, name))


def _opencv_camera(c, name: str, cfg: HardwareConfig, world):
    return OpenCVCamera(c.device, c.width, c.height, c.fps, c.fourcc, _intrinsics(c.intrinsics), c.timeout_ms)


def _depthai_camera(c, name: str, cfg: HardwareConfig, world):
    return DepthAICamera(c.socket, c.width, c.height, c.fps, _intrinsics(c.intrinsics), c.timeout_ms)


def _replay_camera(c, name: str, cfg: HardwareConfig, world):
    return ReplayCamera(c.path, c.loop, c.fps, _intrinsics(c.intrinsics))


def _sim_arm(cfg: HardwareConfig, world):
    a = cfg.arm
    arm = world.spec.arm  # a scene with an arm: the sim arm is joint-driven (its URDF, where the scene puts it)
    return SimArm(world, a.max_speed_mps, a.max_speed_radps, a.realtime, None if arm is None else arm.scene_arm())


def build_scene_arm(cfg: HardwareConfig):
    """The :class:`sim.ik.SceneArm` of the configured arm's ``kinematics`` (its step bound over the
    safety layer's ``control_period_s``), or ``None`` for an arm without one."""
    kin = getattr(cfg.arm, "kinematics", None)
    if kin is None:
        return None
    from sim.kinematics import KinematicsError  # lazy: robot_io start-up (torch)

    try:
        return kin.arm_model(cfg.safety.control_period_s).scene_arm()
    except KinematicsError as err:  # the file changed since the config was loaded
        raise HardwareConfigError(f"arm.{cfg.arm.type}.kinematics.{err.field or 'urdf'}: {err}") from None


def _ur_arm(cfg: HardwareConfig, world):
    a = cfg.arm
    return URArm(
        a.host,
        a.mode,
        a.acceleration_mps2,
        a.lookahead_time_s,
        a.gain,
        a.watchdog_min_hz,
        kinematics=build_scene_arm(cfg),
        joint_acceleration_radps2=a.joint_acceleration_radps2,
    )


def _serial_arm(cfg: HardwareConfig, world):
    a = cfg.arm
    return SerialArm(
        a.port, a.baudrate, a.timeout_ms, a.retries, a.boot_timeout_ms, a.expect_banner, kinematics=build_scene_arm(cfg)
    )


def _bus_arm(cfg: HardwareConfig, world):
    a = cfg.arm
    driver = {"feetech": FeetechArm, "dynamixel": DynamixelArm}[a.type]
    try:
        return driver(
            a.port,
            [j.servo_joint() for j in a.joints],
            build_scene_arm(cfg),
            gripper=None if a.gripper is None else a.gripper.servo_joint(),
            baudrate=a.baudrate,
            timeout_ms=a.timeout_ms,
            retries=a.retries,
            settle_ticks=a.settle_ticks,
            settle_timeout_s=a.settle_timeout_s,
            max_speed_radps=a.max_speed_radps,
            torque_off_on_close=a.torque_off_on_close,
        )
    except ServoBusError as err:
        raise HardwareConfigError(f"arm.{a.type}: {err}") from None


CAMERA_TYPES = {"sim": _sim_camera, "opencv": _opencv_camera, "depthai": _depthai_camera, "replay": _replay_camera}
ARM_TYPES = {"sim": _sim_arm, "ur_rtde": _ur_arm, "serial": _serial_arm, "feetech": _bus_arm, "dynamixel": _bus_arm}


def _needs_world(kind: str, world) -> None:
    if world is None:
        raise HardwareConfigError(f"a '{kind}' device needs the shared sim world: pass world=build_world(cfg)")


def build_camera(cfg: HardwareConfig, world=None):
    """The configured wrist camera (not connected). ``sim`` cameras render ``world``."""
    if cfg.camera.type == "sim":
        _needs_world("sim camera", world)
    camera = CAMERA_TYPES[cfg.camera.type](cfg.camera, WRIST, cfg, world)
    camera.label = WRIST
    return camera


def build_scene_camera(cfg: HardwareConfig, name: str, world=None):
    """Fixed camera ``name`` of ``scene_cameras`` (not connected), refusing frames of any other size
    than its pose holds for: a real camera's pose file's size, a sim camera's render size."""
    if name not in cfg.scene_cameras:
        have = ", ".join(cfg.scene_cameras) or "none"
        raise HardwareConfigError(
            f"scene_cameras: no camera {name!r} in the hardware config (its scene cameras: {have})"
        )
    c = cfg.scene_cameras[name]
    if c.type == "sim":
        _needs_world("sim scene camera", world)
    camera = CAMERA_TYPES[c.type](c, name, cfg, world)
    camera.label = name
    if c.type == "sim":
        spec = world.spec.camera_spec(name)
        camera.expect_frame_size(spec.width, spec.height, "the sim scene renders it at")
    else:
        _regular(c.T_table_cam, f"scene_cameras.{name}.T_table_cam")
        pose = load_scene_camera_pose(c.T_table_cam)
        camera.expect_frame_size(pose.width, pose.height, f"its pose file {c.T_table_cam} holds for")
    return camera


def build_arm(cfg: HardwareConfig, world=None) -> SafeArm:
    """The configured arm wrapped in the safety layer (not connected)."""
    if cfg.arm.type == "sim":
        _needs_world("sim arm", world)
    return SafeArm(ARM_TYPES[cfg.arm.type](cfg, world), cfg.safety)
