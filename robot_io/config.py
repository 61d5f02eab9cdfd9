"""The hardware config YAML: which cameras, which arm, the safety limits, the calibration files.

Validated with pydantic (unknown keys are errors; every error names the file and field), and
turned into devices by :func:`build_camera` / :func:`build_scene_camera` / :func:`build_arm`
through explicit type -> class tables. ``build_arm`` returns the arm wrapped in
:class:`robot_io.safety.SafeArm`: callers never hold a raw driver. Relative paths in the YAML are
relative to the YAML file.

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
from robot_io.arms.serial import SerialArm
from robot_io.arms.sim import SimArm
from robot_io.arms.ur_rtde import URArm
from robot_io.cameras.depthai import DepthAICamera
from robot_io.cameras.opencv import OpenCVCamera
from robot_io.cameras.replay import ReplayCamera
from robot_io.cameras.sim import SimCamera, SimSceneCamera
from robot_io.errors import HardwareConfigError
from robot_io.safety import SafeArm, SafetyLimits
from sim.configio import StrictModel, file_error, merged, read_yaml
from sim.errors import format_validation_error
from sim.spec import CAMERA_NAME, WRIST, default_scene, load_scene
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
    "SimConfig",
    "load_hardware_config",
    "hardware_config_from_dict",
    "load_T_tcp_cam",
    "build_world",
    "build_camera",
    "build_scene_camera",
    "scene_camera_pose",
    "build_arm",
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
class SimArmConfig(_Strict):
    type: Literal["sim"]
    max_speed_mps: Positive = 0.5
    max_speed_radps: Positive = 2.0
    realtime: bool = False


class URArmConfig(_Strict):
    type: Literal["ur_rtde"]
    host: Annotated[str, Field(min_length=1, description="controller address")]
    mode: Literal["servoL", "speedL"] = "servoL"
    acceleration_mps2: Positive = 0.5
    lookahead_time_s: Annotated[float, Field(ge=0.03, le=0.2)] = 0.1
    gain: Annotated[float, Field(ge=100, le=2000)] = 300.0
    watchdog_min_hz: Positive = 10.0


class SerialArmConfig(_Strict):
    type: Literal["serial"]
    port: Annotated[str, Field(min_length=1, description="/dev/serial/by-id/..., /dev/ttyACM0 or a pyserial URL")]
    baudrate: Annotated[int, Field(gt=0)] = 115200
    timeout_ms: Positive = 200.0
    retries: Annotated[int, Field(ge=0, le=20)] = 3
    boot_timeout_ms: Positive = 3000.0
    expect_banner: bool = True


ArmConfig = Annotated[Union[SimArmConfig, URArmConfig, SerialArmConfig], Field(discriminator="type")]


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
    return merged(
        cfg,
        {"camera": fixed(cfg.camera), "T_tcp_cam": fix(cfg.T_tcp_cam), "sim": sim, "scene_cameras": scene_cameras},
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
    return _resolve(cfg, base)


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


def _ur_arm(cfg: HardwareConfig, world):
    a = cfg.arm
    return URArm(a.host, a.mode, a.acceleration_mps2, a.lookahead_time_s, a.gain, a.watchdog_min_hz)


def _serial_arm(cfg: HardwareConfig, world):
    a = cfg.arm
    return SerialArm(a.port, a.baudrate, a.timeout_ms, a.retries, a.boot_timeout_ms, a.expect_banner)


CAMERA_TYPES = {"sim": _sim_camera, "opencv": _opencv_camera, "depthai": _depthai_camera, "replay": _replay_camera}
ARM_TYPES = {"sim": _sim_arm, "ur_rtde": _ur_arm, "serial": _serial_arm}


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
