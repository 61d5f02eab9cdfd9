"""Scene specification: a validated description of the reach scene, loaded from YAML.

Every model forbids unknown keys, and every validation error names the offending field with its
dotted path (``objects.1.pose.yaw_deg: ...``) and the file it came from.
"""

from __future__ import annotations

import math
import re
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import numpy as np
import yaml
from pydantic import Field, ValidationError, field_validator, model_serializer, model_validator

from sim.configio import StrictModel, file_error, merged, read_yaml
from sim.errors import AdvobjError, format_validation_error
from sim.geometry import look_at, make_T, so3_exp

if TYPE_CHECKING:
    from sim.ik import SceneArm
    from sim.kinematics import ArmModel

__all__ = [
    "load_spec",
    "SpecError",
    "TableSpec",
    "LightSpec",
    "LightingSpec",
    "ObjectPose",
    "ObjectSpec",
    "CameraSpec",
    "SceneCameraSpec",
    "LookAt",
    "UnknownCameraError",
    "WRIST",
    "GripperSpec",
    "EpisodeSpec",
    "InitSpec",
    "ArmModelConfig",
    "SceneSpec",
    "load_scene",
    "default_scene",
    "scene_from_dict",
    "ROLES",
]

ROLES = ("goal", "adversarial", "distractor", "obstacle")

Rgb = Annotated[tuple[float, float, float], Field(description="linear RGB in [0, 1]")]
Positive = Annotated[float, Field(gt=0)]


class SpecError(AdvobjError, ValueError):
    """A scene file or dict failed validation; the message names the file and field."""


class _Strict(StrictModel):
    pass


def _check_rgb(v: tuple[float, float, float]) -> tuple[float, float, float]:
    if any(not (0.0 <= c <= 1.0) for c in v):
        raise ValueError("color components must lie in [0, 1]")
    return v


class TableSpec(_Strict):
    size_m: tuple[Positive, Positive] = (1.6, 1.6)
    thickness_m: Positive = 0.03
    # "default" = the built-in wood look; otherwise an image path or an RGB triple.
    texture: str | Rgb = "default"


class LightSpec(_Strict):
    type: Literal["directional", "point"] = "directional"
    intensity: Annotated[float, Field(ge=0)] = 3.0
    color: Rgb = (1.0, 1.0, 1.0)
    # directional: the direction light travels (world frame); point: ignored.
    direction: tuple[float, float, float] = (0.3, 0.2, -1.0)
    # point: position in the world frame (m); directional: ignored.
    position_m: tuple[float, float, float] = (0.0, 0.0, 1.5)

    _v_color = field_validator("color")(_check_rgb)

    @field_validator("direction")
    @classmethod
    def _nonzero(cls, v):
        if math.hypot(*v) < 1e-9:
            raise ValueError("direction must be non-zero")
        return v


class LightingSpec(_Strict):
    ambient: Rgb = (0.35, 0.35, 0.35)
    lights: list[LightSpec] = Field(default_factory=lambda: [LightSpec()])

    _v_amb = field_validator("ambient")(_check_rgb)


class ObjectPose(_Strict):
    """Nominal pose on the table: the object's base centre at (x, y, 0), rotated by yaw about +z."""

    x_m: float = 0.0
    y_m: float = 0.0
    yaw_deg: float = 0.0


class ObjectSpec(_Strict):
    name: Annotated[str, Field(min_length=1)]
    mesh: Annotated[str, Field(min_length=1, description="built-in mesh name or a mesh file path")]
    scale: Positive | tuple[Positive, Positive, Positive] = 1.0
    pose: ObjectPose = ObjectPose()
    role: Literal["goal", "adversarial", "distractor", "obstacle"]
    # None = the mesh's own default look; a string is an image path; a triple is a flat color.
    texture: str | Rgb | None = None
    # Mesh files as exported (ignored for built-in meshes; see sim.assets.build_mesh).
    units: Literal["m", "cm", "mm"] = Field("m", description="length unit of the mesh file (scans are often mm)")
    up_axis: Literal["z", "y"] | None = Field(
        None, description="the file's up axis; default: +Y for .glb/.gltf (glTF spec), else +Z"
    )
    placement: Literal["auto", "keep"] = Field(
        "auto",
        description="auto: rest on the lowest point and centre in x/y (noted by advobj scene render when "
        "it moves the mesh); keep: the file's origin is the object frame",
    )

    attack_region: str | None = Field(
        None,
        description="an image in the mesh file's own UV layout: its white texels mark the faces the attack may change; "
        "the rest keep the file's texture (default: every face)",
    )

    def with_mesh(self, mesh: str) -> dict:
        """This object's fields with ``mesh`` swapped in and its default look: the texture and, for
        another mesh, the attack region (an image of this mesh's UV layout) are dropped."""
        d = {**self.model_dump(), "mesh": mesh, "texture": None}
        if mesh != self.mesh:
            d["attack_region"] = None
        return d

    def mesh_kwargs(self) -> dict:
        """The arguments of :func:`sim.assets.build_mesh` besides the source and scale."""
        kw = {"units": self.units, "up_axis": self.up_axis, "placement": self.placement}
        if self.attack_region is not None:
            kw["attack_region"] = self.attack_region
        return kw


class _Intrinsics(_Strict):
    """A pinhole camera's image size, intrinsics and clip distances: give either fx/fy/cx/cy or
    ``fov_deg`` (vertical field of view)."""

    width: Annotated[int, Field(gt=0, le=4096)] = 128
    height: Annotated[int, Field(gt=0, le=4096)] = 128
    fx: Positive | None = None
    fy: Positive | None = None
    cx: float | None = None
    cy: float | None = None
    fov_deg: Annotated[float, Field(gt=1, lt=179)] | None = 70.0
    znear_m: Positive = 0.005
    zfar_m: Positive = 10.0

    @model_validator(mode="after")
    def _intrinsics(self):
        given = [v is not None for v in (self.fx, self.fy, self.cx, self.cy)]
        if any(given) and not all(given):
            raise ValueError("give all of fx, fy, cx, cy or none of them (then fov_deg is used)")
        if not any(given) and self.fov_deg is None:
            raise ValueError("give fx, fy, cx, cy or fov_deg")
        if self.znear_m >= self.zfar_m:
            raise ValueError("znear_m must be smaller than zfar_m")
        return self

    def K(self, width: int | None = None, height: int | None = None) -> np.ndarray:
        """Intrinsics (3, 3) at ``width x height`` px (defaults to the spec's size).

        Explicit fx/fy/cx/cy are rescaled with the image so the field of view is preserved.
        """
        w = width or self.width
        h = height or self.height
        if self.fx is not None:
            sx, sy = w / self.width, h / self.height
            fx, fy = self.fx * sx, self.fy * sy
            cx, cy = (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5
        else:
            fy = 0.5 * h / math.tan(math.radians(self.fov_deg) / 2)
            fx = fy
            cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def intrinsics(self) -> dict:
        """This camera's size, intrinsics and clip distances (the fields of this base)."""
        return {k: getattr(self, k) for k in _Intrinsics.model_fields}


class CameraSpec(_Intrinsics):
    """Wrist camera. Give either fx/fy/cx/cy or ``fov_deg`` (vertical field of view)."""

    # Mount extrinsic: camera pose in the TCP frame, as translation (m) + axis-angle (rad).
    t_tcp_cam_m: tuple[float, float, float] = (0.0, -0.04, -0.06)
    rotvec_tcp_cam: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # Stereo option: a second camera offset by this baseline along the first camera's +x.
    stereo_baseline_m: Annotated[float, Field(ge=0)] = 0.0

    @property
    def T_tcp_cam(self) -> np.ndarray:
        return make_T(so3_exp(np.asarray(self.rotvec_tcp_cam)), np.asarray(self.t_tcp_cam_m))


WRIST = "wrist"
CAMERA_NAME = r"[a-z][a-z0-9_]{0,31}"
SCENE_REACH_M = 100.0  # a scene camera's position (and look-at target) lies within this of the table origin

Position = tuple[float, float, float]


def _check_reach(v: Position | None) -> Position | None:
    if v is not None and max(abs(c) for c in v) > SCENE_REACH_M:
        raise ValueError(f"each coordinate must lie within +-{SCENE_REACH_M:g} m of the table origin")
    return v


class LookAt(_Strict):
    """A camera pose given by where the camera stands and the point it looks at (table frame, m).

    The optical axis runs from ``eye_m`` to ``target_m``; the image's up is as close to ``up`` as
    the view allows, so ``up`` must not lie along the view (a camera looking straight down needs
    another ``up`` than the default, e.g. ``[0, 1, 0]``: the image's top then faces the table's +y)."""

    # Where the camera stands (m, each coordinate within +-100).
    eye_m: Position
    # The point the optical axis passes through (m), at least 1 mm from eye_m.
    target_m: Position
    up: Position = Field((0.0, 0.0, 1.0), description="the table-frame direction that appears up in the image")

    _v_eye = field_validator("eye_m")(_check_reach)
    _v_target = field_validator("target_m")(_check_reach)

    @field_validator("up")
    @classmethod
    def _up(cls, v):
        if math.hypot(*v) < 1e-6:
            raise ValueError("up must be non-zero")
        return v

    @model_validator(mode="after")
    def _apart(self):
        if math.dist(self.eye_m, self.target_m) < 1e-3:
            raise ValueError("eye_m and target_m must be at least 1 mm apart")
        view = np.subtract(self.target_m, self.eye_m)
        if np.linalg.norm(np.cross(view / np.linalg.norm(view), np.asarray(self.up) / math.hypot(*self.up))) < 1e-6:
            raise ValueError(
                "up lies along the view (eye_m to target_m), which leaves the image's up undefined; "
                "give an up across the view (e.g. [0, 1, 0] for a camera looking straight down)"
            )
        return self


class SceneCameraSpec(_Intrinsics):
    """A fixed camera in the scene (e.g. a lab's third-person view): size and intrinsics as the
    wrist camera's, and its pose in the table (world) frame, OpenCV convention (+x right, +y down,
    +z along the optical axis). Give the pose either as ``t_table_cam_m`` + ``rotvec_table_cam``
    (``T_table_cam``) or as ``look_at``, not both."""

    name: str = Field(description="a letter, then lower case letters, digits or _ (at most 32); not 'wrist'")
    # The pose T_table_cam as translation + axis-angle, like the wrist camera's mount:
    # where the camera stands (m, each coordinate within +-100).
    t_table_cam_m: Position | None = None
    # Its orientation, axis-angle (rad, norm at most 2 pi): the camera's axes in the table frame.
    rotvec_table_cam: Position | None = None
    # The pose as where the camera stands and what it looks at, instead of the two fields above.
    look_at: LookAt | None = None

    _v_t = field_validator("t_table_cam_m")(_check_reach)

    @field_validator("name")
    @classmethod
    def _name(cls, v):
        if v == WRIST:
            raise ValueError("'wrist' names the wrist camera (the scene's camera field); call this one otherwise")
        if not re.fullmatch(CAMERA_NAME, v):
            raise ValueError(
                f"{v!r}: a camera name is a lower case letter, then lower case letters, digits or _ (<= 32)"
            )
        return v

    @field_validator("rotvec_table_cam")
    @classmethod
    def _angle(cls, v):
        if v is not None and math.hypot(*v) > 2 * math.pi + 1e-9:
            raise ValueError("the rotation angle (the vector's norm) must be at most 2 pi rad")
        return v

    @model_validator(mode="after")
    def _pose(self):
        explicit = (self.t_table_cam_m is not None, self.rotvec_table_cam is not None)
        if self.look_at is not None and any(explicit):
            raise ValueError(
                f"camera {self.name!r}: give its pose as t_table_cam_m + rotvec_table_cam or as look_at, not both"
            )
        if self.look_at is None and not all(explicit):
            missing = [f for f, g in zip(("t_table_cam_m", "rotvec_table_cam"), explicit) if not g]
            raise ValueError(
                f"camera {self.name!r} has no extrinsics: {' and '.join(missing)} missing (its pose in the table "
                "frame; or give look_at: {eye_m, target_m})"
            )
        return self

    @property
    def T_table_cam(self) -> np.ndarray:
        """(4, 4) the camera's pose in the table (world) frame, OpenCV camera axes."""
        if self.look_at is not None:
            a = self.look_at
            T = look_at(np.asarray(a.eye_m), np.asarray(a.target_m), np.asarray(a.up))
            # The nearest rotation: with ``up`` nearly along the view, look_at's cross products
            # leave its axes orthogonal to ~1e-7 only.
            U, _, Vt = np.linalg.svd(T[:3, :3])
            T[:3, :3] = U @ Vt
            return T
        return make_T(so3_exp(np.asarray(self.rotvec_table_cam, dtype=np.float64)), np.asarray(self.t_table_cam_m))


class UnknownCameraError(SpecError):
    """A camera name the scene does not have; the message lists the ones it has."""


class GripperSpec(_Strict):
    """Floating Panda-like two-finger gripper; the TCP sits between the finger tips."""

    finger_length_m: Positive = 0.054
    finger_width_m: Positive = 0.02
    finger_thickness_m: Positive = 0.012
    opening_m: Annotated[float, Field(ge=0)] = 0.06
    palm_size_m: tuple[Positive, Positive, Positive] = (0.2, 0.06, 0.04)
    color: Rgb = (0.85, 0.85, 0.85)


class EpisodeSpec(_Strict):
    max_steps: Annotated[int, Field(gt=0, le=100_000)] = 60
    success_radius_m: Positive = 0.10
    max_step_m: Positive = 0.02
    max_step_rad: Positive = 0.1
    # Kinematic workspace clamp for the floating gripper (no physics engine: a reach task
    # needs kinematics and rendering only).
    min_tcp_height_m: float = 0.01


class InitSpec(_Strict):
    """How initial configurations are drawn: the TCP at (r, theta, phi) from the adversarial object.

    ``phi`` is the polar angle from the object's up axis, ``theta`` the azimuth about it.
    """

    r_range_m: tuple[Positive, Positive] = (0.25, 0.80)
    phi_range_deg: tuple[float, float] = (0.0, 90.0)
    theta_range_deg: tuple[float, float] = (-180.0, 180.0)
    aim_noise_m: Annotated[float, Field(ge=0)] = 0.03
    randomize_objects: bool = True
    region_x_m: tuple[float, float] = (-0.25, 0.25)
    region_y_m: tuple[float, float] = (-0.25, 0.25)
    min_separation_m: Positive = 0.22

    @model_validator(mode="after")
    def _ranges(self):
        for name in ("r_range_m", "phi_range_deg", "theta_range_deg", "region_x_m", "region_y_m"):
            lo, hi = getattr(self, name)
            if lo > hi:
                raise ValueError(f"{name}: lower bound {lo} exceeds upper bound {hi}")
        lo, hi = self.phi_range_deg
        if lo < 0 or hi > 90:
            raise ValueError("phi_range_deg must lie within [0, 90]")
        return self


class ArmModelConfig(_Strict):
    """The arm as a URDF: the kinematic chain from ``base_link`` to ``tool_link`` (:mod:`sim.kinematics`),
    checked when the scene loads: a plain URDF (no xacro; its meshes are ignored), both links in it, the
    tool link below the base link, and every joint between them revolute or prismatic with finite
    position and velocity limits.

    A joint-space policy moves this arm (``ReachEnv(control="joint")``, :class:`sim.ik.SceneArm`): its
    base stands at ``T_table_base`` in the table frame, the TCP (the floating gripper's, which the
    wrist camera is mounted on) sits at ``T_tool_tcp`` in the tool link's frame, and one env step
    lasts ``control_period_s``, so a joint moves at most its URDF velocity limit times that per step.
    """

    urdf: str = Field(
        min_length=1,
        description="a shipped arm (panda, ur5) or a URDF file: relative to the scene file, inside its folder",
    )
    base_link: str = Field(min_length=1, description="the URDF link the arm's poses are expressed in")
    tool_link: str = Field(min_length=1, description="the URDF link whose pose forward kinematics gives")
    t_table_base_m: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="where the base link stands in the table frame (m)"
    )
    rotvec_table_base: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="the base link's orientation in the table frame, axis-angle (rad)"
    )
    t_tool_tcp_m: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="the TCP in the tool link's frame (m); the wrist camera is mounted on the TCP"
    )
    rotvec_tool_tcp: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="the TCP's orientation in the tool link's frame, axis-angle (rad)"
    )
    control_period_s: Positive = Field(
        0.1, le=10.0, description="one env step (s): a joint moves at most its URDF velocity limit times this per step"
    )
    q_home: tuple[float, ...] | None = Field(
        None,
        description="joint positions (rad or m, chain order) the IK of a start pose begins from; None: the middle "
        "of each joint's limits",
    )

    _v_base = field_validator("t_table_base_m")(_check_reach)

    @field_validator("rotvec_table_base", "rotvec_tool_tcp")
    @classmethod
    def _angle(cls, v):
        if math.hypot(*v) > 2 * math.pi + 1e-9:
            raise ValueError("the rotation angle (the vector's norm) must be at most 2 pi rad")
        return v

    @property
    def T_table_base(self) -> np.ndarray:
        """(4, 4) the base link's pose in the table (world) frame."""
        return make_T(so3_exp(np.asarray(self.rotvec_table_base, dtype=np.float64)), np.asarray(self.t_table_base_m))

    @property
    def T_tool_tcp(self) -> np.ndarray:
        """(4, 4) the TCP's pose in the tool link's frame."""
        return make_T(so3_exp(np.asarray(self.rotvec_tool_tcp, dtype=np.float64)), np.asarray(self.t_tool_tcp_m))

    def load(self, device: str = "cpu") -> "ArmModel":
        """The :class:`sim.kinematics.ArmModel` of this chain on ``device``."""
        from sim.kinematics import load_arm, urdf_source  # lazy: robot_io start-up (torch)

        return load_arm(urdf_source(self.urdf), self.base_link, self.tool_link, device=device)

    def scene_arm(self, device: str = "cpu") -> "SceneArm":
        """The :class:`sim.ik.SceneArm` of this arm where the scene puts it, on ``device``."""
        from sim.ik import SceneArm  # lazy: robot_io start-up (torch)

        model = self.load(device)
        chain = model.chain
        home = (chain.q_min + chain.q_max) / 2.0 if self.q_home is None else np.asarray(self.q_home, np.float64)
        return SceneArm(model, self.T_table_base, self.T_tool_tcp, float(self.control_period_s), home)


class SceneSpec(_Strict):
    name: str = "scene"
    background: Rgb = (0.55, 0.6, 0.65)
    table: TableSpec = TableSpec()
    lighting: LightingSpec = LightingSpec()
    objects: list[ObjectSpec]
    camera: CameraSpec = CameraSpec()
    gripper: GripperSpec = GripperSpec()
    episode: EpisodeSpec = EpisodeSpec()
    init: InitSpec = InitSpec()
    scene_cameras: list[SceneCameraSpec] = Field(
        default_factory=list,
        description="fixed cameras besides the wrist camera (which is named 'wrist'), each posed in the table frame",
    )
    arm: ArmModelConfig | None = Field(
        None,
        description="the arm as a URDF with its base and tool links, where it stands and its TCP; a joint-space "
        "policy moves it (a TCP policy moves the floating gripper, as without an arm)",
    )

    _v_bg = field_validator("background")(_check_rgb)

    @model_serializer(mode="wrap")
    def _dump(self, handler):
        # Without scene cameras or an arm a scene dumps exactly as before they existed: the run
        # records and the evaluation config hashes that hold a scene's dump stay the same.
        d = handler(self)
        if not self.scene_cameras:
            d.pop("scene_cameras", None)
        if self.arm is None:
            d.pop("arm", None)
        return d

    @field_validator("scene_cameras")
    @classmethod
    def _camera_names(cls, cams):
        names = [c.name for c in cams]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"camera names must be unique, repeated: {sorted(dup)}")
        return cams

    @model_validator(mode="after")
    def _roles(self):
        names = [o.name for o in self.objects]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"object names must be unique, repeated: {sorted(dup)}")
        problems = [
            f"exactly one object must have role '{role}', found {n}"
            for role in ("goal", "adversarial")
            if (n := sum(o.role == role for o in self.objects)) != 1
        ]
        if problems:
            raise ValueError("; ".join(problems))
        return self

    def object_index(self, role: str) -> int:
        """Index of the (unique) object with ``role`` (goal or adversarial)."""
        for i, o in enumerate(self.objects):
            if o.role == role:
                return i
        raise KeyError(role)

    @property
    def goal(self) -> ObjectSpec:
        return self.objects[self.object_index("goal")]

    @property
    def adversarial(self) -> ObjectSpec:
        return self.objects[self.object_index("adversarial")]

    @property
    def camera_names(self) -> tuple[str, ...]:
        """Every camera of the scene: ``"wrist"`` (the :attr:`camera` field), then the scene cameras."""
        return (WRIST, *(c.name for c in self.scene_cameras))

    def camera_spec(self, name: str) -> CameraSpec | SceneCameraSpec:
        """The camera called ``name``: :attr:`camera` for ``"wrist"``, else that scene camera.

        Both carry what a renderer needs: ``width``/``height``, ``K()``, ``znear_m``/``zfar_m``;
        a scene camera also its fixed pose ``T_table_cam``. An unknown name raises
        :class:`UnknownCameraError` listing the scene's cameras.
        """
        if name == WRIST:
            return self.camera
        for c in self.scene_cameras:
            if c.name == name:
                return c
        raise UnknownCameraError(f"unknown camera {name!r}; this scene has: {', '.join(self.camera_names)}")

    def for_camera(self, name: str) -> "SceneSpec":
        """This scene seen through camera ``name``: its size, intrinsics and clip distances in the
        :attr:`camera` slot, so a :class:`sim.render.SceneRenderer` built from it renders that
        camera (the slot's mount fields are unused there: the renderer takes each pose as given).
        The wrist camera's is this scene itself."""
        cam = self.camera_spec(name)
        if name == WRIST:
            return self
        return self.with_updates(camera=CameraSpec(**cam.intrinsics()))

    def with_updates(self, **changes) -> "SceneSpec":
        """A validated copy with top-level fields replaced."""
        return scene_from_dict({**self.model_dump(), **changes}, source="<update>")


def scene_from_dict(data: dict, source: str = "<dict>") -> SceneSpec:
    """Validate ``data`` into a :class:`SceneSpec`; errors name ``source`` and each field."""
    if not isinstance(data, dict):
        raise SpecError(f"{source}: a scene spec must be a mapping, got {type(data).__name__}")
    try:
        spec = SceneSpec.model_validate(data)
    except ValidationError as err:
        raise SpecError(format_validation_error(err, "scene spec", source)) from None
    return _check_arm(_resolve_paths(spec, source), source)


def _check_arm(spec: SceneSpec, source: str) -> SceneSpec:
    """``spec`` with its arm's URDF checked (the file parses, both links exist and the chain between
    them is usable) and, for a scene file, a URDF path made absolute: relative to the file, and
    required to lie inside its folder. A shipped arm's name stays a name."""
    if spec.arm is None:
        return spec
    from sim.kinematics import SHIPPED_ARMS, KinematicsError, read_chain, urdf_source  # lazy: robot_io start-up (torch)

    root = None if source.startswith("<") else Path(source).resolve().parent
    arm = spec.arm
    try:
        path = urdf_source(arm.urdf, root=root)
        chain = read_chain(path, arm.base_link, arm.tool_link)
    except KinematicsError as err:
        raise SpecError(f"{source}: arm.{err.field or 'urdf'}: {err}") from None
    if arm.q_home is not None:
        n = len(chain.joint_names)
        if len(arm.q_home) != n:
            raise SpecError(
                f"{source}: arm.q_home: {len(arm.q_home)} values for the {n} joints of the chain "
                f"({', '.join(chain.joint_names)})"
            )
        for k, v in enumerate(arm.q_home):
            if not chain.q_min[k] <= v <= chain.q_max[k]:
                raise SpecError(
                    f"{source}: arm.q_home[{k}]: joint {chain.joint_names[k]!r} at {v} {chain.units[k]} is outside its "
                    f"limits [{chain.q_min[k]:.6g}, {chain.q_max[k]:.6g}]"
                )
    if root is None or arm.urdf in SHIPPED_ARMS:
        return spec
    return merged(
        spec, {"arm": {**arm.model_dump(), "urdf": str(path)}}, what="scene spec", source=source, error=SpecError
    )


def _resolve_paths(spec: SceneSpec, source: str) -> SceneSpec:
    """Make relative mesh/texture paths relative to the YAML file that named them.

    A texture image named in a scene file must lie inside the scene file's folder (relative, or
    absolute but inside it): a scene is data that may come from elsewhere, and its texture field
    would otherwise read any local image.
    """
    if source.startswith("<"):
        return spec
    base = Path(source).resolve().parent

    def fix(p):
        # Built-in names never collide with files next to the YAML in practice; only rewrite
        # names that resolve to an existing file there.
        if isinstance(p, str) and not Path(p).is_absolute() and (base / p).is_file():
            return str(base / p)
        return p

    def texture(p, field: str, what: str = "texture"):
        if not isinstance(p, str) or p == "default":
            return p
        target = (base / p).resolve()
        if base not in target.parents:
            raise SpecError(
                f"{source}: {field}: {what} {p!r} lies outside the scene file's folder {base}; "
                "put the image next to the scene (or below it) and name it relatively"
            )
        return str(target)

    objects = [
        {
            **o.model_dump(),
            "mesh": fix(o.mesh),
            "texture": texture(o.texture, f"objects.{i}.texture"),
            "attack_region": texture(o.attack_region, f"objects.{i}.attack_region", "image"),
        }
        for i, o in enumerate(spec.objects)
    ]
    table = {**spec.table.model_dump(), "texture": texture(spec.table.texture, "table.texture")}
    return merged(spec, {"objects": objects, "table": table}, what="scene spec", source=source, error=SpecError)


def load_scene(path: str | Path) -> SceneSpec:
    """Load and validate a scene YAML file."""
    path = Path(path)
    return scene_from_dict(read_yaml(path, "scene file", error=file_error(SpecError)), source=str(path))


def load_spec(path: str | Path | None) -> SceneSpec:
    """The scene of ``path`` (a scene YAML), or the built-in scene when ``path`` is None."""
    return default_scene() if path is None else load_scene(path)


def default_scene() -> SceneSpec:
    """The built-in scene reproducing the paper's task (soup can goal, mustard bottle adversary)."""
    text = resources.files("sim").joinpath("data/default_scene.yaml").read_text()
    return scene_from_dict(yaml.safe_load(text), source="<built-in default_scene.yaml>")
