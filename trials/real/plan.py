"""The real-robot trial plan: which TCP pose, object layout, shape and condition, in which order.

Design (paper Sec. IV-E): per environment and per adversarial-object shape, every one of
``n_tcp_poses`` initial TCP poses is crossed with every one of ``n_object_layouts`` object
layouts (5 x 6 = 30 trials in the paper), and this block is repeated for every condition:

* ``clean``  - the object of that shape with its benign default look (the control);
* ``adv3d``  - that shape with the attack texture ``textures["<shape>/adv3d"]``;
* ``patch``  - the built-in ``patch`` mesh with ``textures["<shape>/patch"]``, placed where the
  adversarial object would stand.

A shape is a built-in mesh (``cube``, ``cylinder``, ...) or the name of an object of the plan's
scene YAML (not its goal), whose mesh may be a file (:func:`trials.fabrication.shapes.scene_shape`):
``advobj trial plan --scene my.yaml --shape my_box``. Such a shape is recorded in
``shape_objects`` with the object as the scene declares it, the sha256 of its mesh file and its
centre, so staging, the locator and a resumed session use that very object; an attack run's
texture for it must have been optimised on that mesh file (same bytes), at the same size.

Scenario tags (``dim``, ``bright``, ``dynamic_lighting``, ``occluded``, ``moved_object``) are
free-form: each tag adds one more full block (every env x shape x condition x pose x layout) whose
trials carry that tag and a ``-<tag>`` id suffix. A tag therefore costs as much as the untagged
design; choose the conditions of a tagged session accordingly (one plan per session is fine).

Poses follow the simulator's distribution: layouts and TCP poses are drawn with
:func:`sim.configs.sample_config` (optionally only from a task-feasible pool), whose world frame is
the table frame (z up, origin on the table top). Layouts come from the first ``n_object_layouts``
configurations; TCP poses from further configurations, keeping a TCP pose only if it is a valid
start for *every* layout (the sampler's own rules: at least ``min_tcp_height_m + 0.04`` high and
1.5 success radii from every object) and sees both objects' centres in the wrist image - a crossed
design reuses one TCP pose with layouts it was not drawn for, and a start with an object out of
view wastes a real trial. A scene with fixed cameras (``scene_cameras``) keeps only layouts whose
object centres every one of them sees: a policy reading such a camera is shown both objects from
the start (scenes without them draw the same plans as before).

A start (``tcp_poses``) is a TCP pose, as drawn, or, edited into the plan for an arm a URDF
describes, a joint vector (``joint_positions``, the arm's chain order) instead of or besides it: a
joint-space policy then starts from exactly those joints (:class:`TcpPose`).

The trial order is drawn from ``seed`` and keeps each environment together (an environment is a
physical setup): the environments come in a random order, and within each environment's block
every trial of it (all shapes, conditions, tags, poses and layouts) comes in a random order.
"""

from __future__ import annotations

import hashlib
import math
import re
from pathlib import Path
from typing import Annotated, Literal, Sequence

import numpy as np
from pydantic import Field, ValidationError, field_validator, model_serializer, model_validator

from calibration.io import write_yaml
from sim.assets import BUILTIN_MESHES
from sim.configio import StrictModel, file_error, read_yaml
from sim.configs import object_local_centers, object_poses_world, sample_config
from sim.errors import AdvobjError, format_validation_error
from sim.geometry import invert_T, make_T, so3_exp, so3_log, transform_points
from sim.paths import SAFE_NAME_RULE, SafeName, name_problem
from sim.spec import default_scene
from trials.fabrication.shapes import SceneShape, ShapeError, load_run, run_mesh_problem, scene_shape, with_shape

__all__ = [
    "PlanError",
    "CONDITIONS",
    "PLAN_ROLES",
    "Pose",
    "ObjectPlacement",
    "TcpPose",
    "ObjectLayout",
    "TextureRef",
    "PlannedTrial",
    "TrialPlan",
    "texture_ref",
    "make_plan",
    "save_plan",
    "load_plan",
    "plan_sha256",
    "design_summary",
]

CONDITIONS = ("clean", "adv3d", "patch")
TEXTURED = ("adv3d", "patch")
PLAN_ROLES = ("goal", "adversarial")
# Names end up in trial ids and file names: keep them to one plain token.
_NAME = re.compile(r"^[A-Za-z0-9_]+$")
_MAX_DRAWS = 5000
#: Plan bounds (see TrialPlan): the policy loop rate and length a session accepts.
MIN_CONTROL_HZ, MAX_CONTROL_HZ, MAX_STEPS = 0.5, 1000.0, 100_000


class PlanError(AdvobjError, ValueError):
    """A trial plan cannot be built or read; the message names the file and field or option."""


class _Strict(StrictModel):
    pass


def _finite(v):
    if not all(math.isfinite(x) for x in v):
        raise ValueError("values must be finite numbers")
    return v


class Pose(_Strict):
    """A rigid transform as translation (m) + axis-angle rotation (rad)."""

    translation_m: tuple[float, float, float]
    rotvec_rad: tuple[float, float, float]

    _check = field_validator("translation_m", "rotvec_rad")(_finite)

    def T(self) -> np.ndarray:
        """The (4, 4) homogeneous transform."""
        return make_T(
            so3_exp(np.asarray(self.rotvec_rad, dtype=np.float64)), np.asarray(self.translation_m, dtype=np.float64)
        )

    @staticmethod
    def from_T(T) -> "Pose":
        T = np.asarray(T, dtype=np.float64)
        return Pose(
            translation_m=tuple(float(x) for x in T[:3, 3]), rotvec_rad=tuple(float(x) for x in so3_log(T[:3, :3]))
        )


class ObjectPlacement(_Strict):
    """An object's base centre on the table top (table frame, m) and its yaw about +z (rad)."""

    xy_m: tuple[float, float]
    yaw_rad: float

    _check = field_validator("xy_m")(_finite)


class TcpPose(_Strict):
    """A trial's start: the TCP pose in the table frame, the arm's joint positions, or both.

    ``joint_positions`` (an arm a URDF describes: :meth:`robot_io.arms.base.Arm.kinematics`) are in the
    order of the arm's URDF chain, base to tool, each in its joint's unit (rad revolute, m prismatic).
    The session checks their number against the arm and, with both given, that their forward
    kinematics agrees with ``T_table_tcp`` (:data:`trials.real.runner.START_AGREE_TOL_M`,
    ``START_AGREE_TOL_RAD``); a TCP start on such an arm is solved by IK
    (:meth:`sim.ik.SceneArm.solve_start`).
    """

    index: Annotated[int, Field(ge=0)]
    T_table_tcp: Pose | None = Field(None, description="the start TCP pose in the table frame")
    joint_positions: tuple[float, ...] | None = Field(
        None,
        min_length=1,
        description="the start joints in the arm's URDF chain order (rad revolute, m prismatic); with "
        "T_table_tcp too, their forward kinematics must agree with it",
    )

    @model_validator(mode="after")
    def _some_start(self):
        if self.T_table_tcp is None and self.joint_positions is None:
            raise ValueError("a start needs T_table_tcp, joint_positions or both")
        return self

    @model_serializer(mode="wrap")
    def _dump(self, handler):
        # A TCP start dumps as before joint starts existed (plan files and their sha256 unchanged).
        d = handler(self)
        for key in ("T_table_tcp", "joint_positions"):
            if d.get(key) is None:
                d.pop(key, None)
        return d


class ObjectLayout(_Strict):
    """Where the goal and the adversarial object stand, keyed by scene role."""

    index: Annotated[int, Field(ge=0)]
    objects: dict[str, ObjectPlacement]

    @field_validator("objects")
    @classmethod
    def _roles(cls, v):
        if set(v) != set(PLAN_ROLES):
            raise ValueError(f"needs exactly the roles {list(PLAN_ROLES)}, got {sorted(v)}")
        return v


class TextureRef(_Strict):
    """An attack run directory (``texture.npy`` + ``run.json``) and the sha256 of its texture.npy."""

    path: str
    sha256: Annotated[str, Field(pattern=r"^[0-9a-f]{64}$")]


class PlannedTrial(_Strict):
    # The runner makes (and on a retry clears) the directory frames/<session>/<trial_id>: the id
    # must be one safe path component, never '..', '/abs' or a hidden name.
    trial_id: Annotated[SafeName, Field(description=f"{SAFE_NAME_RULE} (it names the trial's frame directory)")]
    order: Annotated[int, Field(ge=0)]
    env: str
    shape: str
    condition: Literal["clean", "adv3d", "patch"]
    tcp_pose: Annotated[int, Field(ge=0)]
    object_layout: Annotated[int, Field(ge=0)]
    tags: list[str] = []


class TrialPlan(_Strict):
    version: Literal[1] = 1
    seed: int
    scene: str | None
    # Bounds a real cell can run (a plan outside them is refused at load, before any device connects).
    radius_m: Annotated[float, Field(gt=0, le=1.0, description="success radius around an object, m")] = 0.10
    max_steps: Annotated[int, Field(gt=0, le=MAX_STEPS, description="policy steps per trial at most")] = 60
    control_hz: Annotated[
        float,
        Field(
            ge=MIN_CONTROL_HZ,
            le=MAX_CONTROL_HZ,
            description=(
                "policy loop rate; its period 1/control_hz (1 ms to 2 s) becomes the safety layer's control_period_s"
            ),
        ),
    ] = 10.0
    placement_tolerance_m: Annotated[float, Field(gt=0, le=0.5, description="object placement check, m")] = 0.01
    placement_tolerance_rad: Annotated[
        float, Field(gt=0, le=math.pi, description="object placement check (yaw), rad")
    ] = 0.0873
    envs: list[str]
    shapes: list[str]
    conditions: list[str]
    tcp_poses: list[TcpPose]
    object_layouts: list[ObjectLayout]
    textures: dict[str, TextureRef]
    trials: list[PlannedTrial]
    shape_objects: dict[str, SceneShape] = Field(
        default_factory=dict,
        description="shapes that are objects of the scene, by shape name: the object as the scene declares it, its "
        "mesh file's sha256 and its centre (other shapes are built-in meshes)",
    )

    @model_serializer(mode="wrap")
    def _dump(self, handler):
        # A plan of built-in shapes dumps exactly as before scene objects could be named.
        d = handler(self)
        if not self.shape_objects:
            d.pop("shape_objects", None)
        return d

    @model_validator(mode="after")
    def _consistent(self):
        for field in ("envs", "shapes", "conditions"):
            values = getattr(self, field)
            if not values:
                raise ValueError(f"{field}: must not be empty")
            if len(set(values)) != len(values):
                raise ValueError(f"{field}: repeated entries {values}")
            for v in values:
                if not _NAME.match(v):
                    raise ValueError(f"{field}: {v!r} must be letters, digits and '_' only")
        for c in self.conditions:
            if c not in CONDITIONS:
                raise ValueError(f"conditions: unknown condition {c!r}; choose from {', '.join(CONDITIONS)}")
        for field, items in (("tcp_poses", self.tcp_poses), ("object_layouts", self.object_layouts)):
            for i, item in enumerate(items):
                if item.index != i:
                    raise ValueError(
                        f"{field}.{i}.index: expected {i} (indices count 0, 1, 2, ... in list order), got {item.index}"
                    )
        for shape in self.shapes:
            if shape not in self.shape_objects and shape not in BUILTIN_MESHES:
                raise ValueError(
                    f"shapes: {shape!r} is no built-in mesh and has no entry in shape_objects (the scene object)"
                )
        for shape in self.shape_objects:
            if shape not in self.shapes:
                raise ValueError(f"shape_objects.{shape}: not one of the plan's shapes {self.shapes}")
        for shape in self.shapes:
            for c in TEXTURED:
                if c in self.conditions and f"{shape}/{c}" not in self.textures:
                    raise ValueError(f"textures: condition {c!r} of shape {shape!r} needs an entry '{shape}/{c}'")
        seen_ids, seen_orders = set(), set()
        for i, t in enumerate(self.trials):
            where = f"trials.{i}"
            if t.trial_id in seen_ids:
                raise ValueError(f"{where}.trial_id: duplicated trial id {t.trial_id!r}")
            if t.order in seen_orders:
                raise ValueError(f"{where}.order: duplicated order {t.order}")
            seen_ids.add(t.trial_id)
            seen_orders.add(t.order)
            for field, allowed in (("env", self.envs), ("shape", self.shapes), ("condition", self.conditions)):
                if getattr(t, field) not in allowed:
                    raise ValueError(f"{where}.{field}: {getattr(t, field)!r} is not in the plan's {field}s {allowed}")
            if t.tcp_pose >= len(self.tcp_poses):
                raise ValueError(
                    f"{where}.tcp_pose: {t.tcp_pose} out of range (the plan has {len(self.tcp_poses)} TCP poses)"
                )
            if t.object_layout >= len(self.object_layouts):
                raise ValueError(
                    f"{where}.object_layout: {t.object_layout} out of range (the plan has "
                    f"{len(self.object_layouts)} layouts)"
                )
        return self

    def tcp_pose(self, index: int) -> TcpPose:
        """The TCP pose with ``index``."""
        return self.tcp_poses[index]

    def object_layout(self, index: int) -> ObjectLayout:
        """The object layout with ``index``."""
        return self.object_layouts[index]

    def trial(self, trial_id: str) -> PlannedTrial:
        """The trial with ``trial_id`` (KeyError if none)."""
        for t in self.trials:
            if t.trial_id == trial_id:
                return t
        raise KeyError(trial_id)

    def texture_for(self, trial: PlannedTrial) -> TextureRef | None:
        """The texture a trial shows (``None`` for clean: the shape's benign default look)."""
        return None if trial.condition == "clean" else self.textures[f"{trial.shape}/{trial.condition}"]

    def shape_object(self, shape: str) -> SceneShape | None:
        """The scene object a shape names (None: the shape is a built-in mesh)."""
        return self.shape_objects.get(shape)

    def mesh_for(self, trial: PlannedTrial) -> str:
        """The adversarial-role mesh a trial uses: its shape's (a built-in name or the scene object's
        mesh file), or ``patch`` for the 2D patch."""
        if trial.condition == "patch":
            return "patch"
        obj = self.shape_object(trial.shape)
        return trial.shape if obj is None else obj.object.mesh

    def adversarial_for(self, trial: PlannedTrial):
        """What a trial stands in the adversarial slot (:func:`trials.fabrication.shapes.with_shape`):
        ``"patch"``, a built-in mesh name, or the :class:`SceneShape` of a scene object."""
        if trial.condition == "patch":
            return "patch"
        return self.shape_object(trial.shape) or trial.shape

    def object_name(self, trial: PlannedTrial) -> str:
        """The name of the object in the adversarial slot of ``trial``: the scene object's name, the
        built-in shape's, or ``patch`` (a tag registry may register it under that name)."""
        obj = self.adversarial_for(trial)
        return obj if isinstance(obj, str) else obj.object.name


def trial_id(env: str, shape: str, condition: str, tcp_pose: int, object_layout: int, tag: str | None = None) -> str:
    """``A-cube-adv3d-t2-o4`` (+ ``-<tag>``): stable, readable, unique within a plan."""
    return f"{env}-{shape}-{condition}-t{tcp_pose}-o{object_layout}" + (f"-{tag}" if tag else "")


def texture_ref(path: str | Path, key: str, spec=None, scene: str | None = None) -> TextureRef:
    """A :class:`TextureRef` for ``key`` (``"<shape>/adv3d"`` or ``"<shape>/patch"``) from an attack run.

    Checks the run was optimised on the mesh the trial will use: ``patch`` for ``/patch``, the
    shape itself for ``/adv3d``: a built-in mesh by name, an object of ``spec`` (read from the file
    ``scene``) by its mesh file's bytes and, when the run recorded its scene, its size and
    orientation (:func:`trials.fabrication.shapes.run_mesh_problem`). A run that recorded neither
    ``adversarial_mesh`` nor its scene is taken to be on ``spec``'s adversarial mesh.
    """
    shape, _, cond = key.partition("/")
    if cond not in TEXTURED or not shape:
        raise PlanError(f"--texture {key}: key must be '<shape>/adv3d' or '<shape>/patch'")
    spec = default_scene() if spec is None else spec
    src = load_run(path, spec)
    try:
        want = "patch" if cond == "patch" else (scene_shape(spec, shape, "--texture", scene) or shape)
    except ShapeError as err:
        raise PlanError(str(err)) from None
    problem = run_mesh_problem(src, want, key)
    if problem is not None:
        raise PlanError(f"--texture {key}={path}: {problem}")
    return TextureRef(path=str(path), sha256=src.sha256)


def _check_names(what: str, names: Sequence[str]) -> list[str]:
    names = list(names)
    if not names:
        raise PlanError(f"{what}: give at least one")
    if len(set(names)) != len(names):
        raise PlanError(f"{what}: repeated entries {names}")
    for n in names:
        if not _NAME.match(n):
            raise PlanError(f"{what}: {n!r} must be letters, digits and '_' only (it becomes part of trial ids)")
    return names


def _in_image(cam, T_world_cam: np.ndarray, points_world: np.ndarray) -> bool:
    """Whether every point ``(N, 3)`` lies in front of camera ``cam`` (a scene's camera spec) at
    ``T_world_cam`` and inside its image."""
    p = transform_points(invert_T(T_world_cam), points_world)
    if np.any(p[:, 2] <= cam.znear_m):
        return False
    uv = (cam.K() @ (p / p[:, 2:3]).T).T[:, :2]
    return bool(np.all((uv >= -0.5) & (uv <= [cam.width - 0.5, cam.height - 0.5])))


def _in_view(spec, T_world_tcp: np.ndarray, points_world: np.ndarray) -> bool:
    """Whether every point ``(N, 3)`` lies in front of the wrist camera and inside its image."""
    return _in_image(spec.camera, T_world_tcp @ spec.camera.T_tcp_cam, points_world)


def _seen_by_scene_cameras(spec, points_world: np.ndarray) -> bool:
    """Whether every fixed camera of the scene sees every point ``(N, 3)``."""
    return all(_in_image(cam, cam.T_table_cam, points_world) for cam in spec.scene_cameras)


def _valid_start(spec, T_world_tcp: np.ndarray, centers_world: np.ndarray) -> bool:
    """The sampler's start rules for a TCP pose against one layout's object centres ``(K, 3)``."""
    p = T_world_tcp[:3, 3]
    if p[2] < spec.episode.min_tcp_height_m + 0.04:
        return False
    if np.linalg.norm(centers_world - p, axis=-1).min() < 1.5 * spec.episode.success_radius_m:
        return False
    return _in_view(spec, T_world_tcp, centers_world)


def _draw_configs(spec, rng: np.random.Generator, pool):
    """An endless stream of initial configurations: from the pool (shuffled, each once) or sampled."""
    if pool is not None:
        for i in rng.permutation(len(pool)):
            yield pool[int(i)]
        return
    centers = object_local_centers(spec)
    base = int(rng.integers(0, 2**31 - 1))
    for i in range(_MAX_DRAWS):
        yield sample_config(spec, base + i, centers)


def _poses(
    spec, rng: np.random.Generator, n_tcp: int, n_layouts: int, pool, workspace=None
) -> tuple[list[TcpPose], list[ObjectLayout]]:
    """``workspace``: ``(min_m, max_m, T_base_table)``, the safety box in the arm's base frame; only
    TCP poses inside it are drawn."""
    centers_local = object_local_centers(spec)
    goal, adv = spec.object_index("goal"), spec.object_index("adversarial")
    stream = _draw_configs(spec, rng, pool)
    layouts, centers = [], []
    for cfg in stream:
        if len(layouts) == n_layouts:
            break
        xyy = np.asarray(cfg.object_xy_yaw, dtype=np.float64)
        T_objs = object_poses_world(xyy)
        c = np.einsum("kij,kj->ki", T_objs[:, :3, :3], centers_local) + T_objs[:, :3, 3]
        if not _seen_by_scene_cameras(spec, c[[goal, adv]]):
            continue
        centers.append(c)
        objects = {
            role: ObjectPlacement(xy_m=(float(xyy[k, 0]), float(xyy[k, 1])), yaw_rad=float(xyy[k, 2]))
            for role, k in (("goal", goal), ("adversarial", adv))
        }
        layouts.append(ObjectLayout(index=len(layouts), objects=objects))
    tcps, outside = [], []
    for cfg in stream:
        if len(tcps) == n_tcp:
            break
        T = cfg.T_world_tcp_array
        if workspace is not None:
            lo, hi, T_base_table = workspace
            p = (T_base_table @ T)[:3, 3]
            if np.any(p < np.asarray(lo)) or np.any(p > np.asarray(hi)):
                outside.append(p)
                continue
        if all(_valid_start(spec, T, c[[goal, adv]]) for c in centers):
            tcps.append(TcpPose(index=len(tcps), T_table_tcp=Pose.from_T(T)))
    if workspace is not None and len(tcps) < n_tcp:
        lo, hi, _ = workspace
        span = np.array(outside).reshape(-1, 3)
        rng_txt = (
            ", ".join(f"{a} {span[:, i].min():.3f}..{span[:, i].max():.3f}" for i, a in enumerate("xyz"))
            if len(span)
            else "-"
        )
        raise PlanError(
            f"--hardware: found {len(tcps)}/{n_tcp} start TCP poses inside the workspace box "
            f"[{', '.join(f'{v:g}' for v in lo)}] .. [{', '.join(f'{v:g}' for v in hi)}] m (base frame); "
            f"{len(outside)} drawn poses fell outside, spanning {rng_txt} m; the scene's start poses "
            "(init.r_range_m, init.phi_range_deg, init.region_x_m/region_y_m in the scene YAML) must fit the cell: "
            "widen the box if the cell allows it, move the "
            "table frame (--table-frame), or use a scene whose start poses lie inside it"
        )
    if len(layouts) < n_layouts or len(tcps) < n_tcp:
        src = f"the pool's {len(pool)} configurations" if pool is not None else f"{_MAX_DRAWS} sampled configurations"
        raise PlanError(
            f"found {len(layouts)}/{n_layouts} object layouts and {len(tcps)}/{n_tcp} TCP poses valid for every "
            f"layout in {src}; "
            "use fewer poses or layouts, a larger pool, or another seed"
        )
    return tcps, layouts


def make_plan(
    spec,
    seed: int,
    envs: Sequence[str],
    shapes: Sequence[str],
    conditions: Sequence[str],
    textures: dict[str, TextureRef],
    n_tcp_poses: int = 5,
    n_object_layouts: int = 6,
    tags: Sequence[str] = (),
    pool=None,
    scene: str | None = None,
    workspace=None,
    **settings,
) -> TrialPlan:
    """The full-factorial trial plan (see the module docstring), in a random order drawn from ``seed`` (env by env).

    ``pool``: optional list of :class:`sim.configs.InitialConfig` (e.g. a task-feasible pool) to
    draw poses and layouts from instead of the sampler. ``scene``: the scene file name recorded in
    the plan (``None`` = built-in). ``settings``: other :class:`TrialPlan` fields (``radius_m``,
    ``max_steps``, ``control_hz``, ``placement_tolerance_m``, ``placement_tolerance_rad``).
    ``workspace``: ``(min_m, max_m, T_base_table)`` of a cell's safety box: start poses are drawn inside it.
    """
    envs = _check_names("--env", envs)
    conditions = _check_names("--condition", conditions)
    tags = list(tags)
    if tags:
        _check_names("--tag", tags)
    for c in conditions:
        if c not in CONDITIONS:
            raise PlanError(f"--condition: unknown condition {c!r}; choose from {', '.join(CONDITIONS)}")
    shape_objects = {}
    for s in dict.fromkeys(shapes):  # what each name means first: a file path gets its own advice
        try:
            obj = scene_shape(spec, s, "--shape", scene)
        except ShapeError as err:
            raise PlanError(str(err)) from None
        if obj is not None:
            try:
                with_shape(spec, obj)  # the staged scene must hold it (names stay unique, etc.)
            except AdvobjError as err:
                raise PlanError(f"--shape {s}: {err}") from None
            shape_objects[s] = obj
    shapes = _check_names("--shape", shapes)
    for s in shapes:
        for c in TEXTURED:
            if c in conditions and f"{s}/{c}" not in textures:
                raise PlanError(f"--texture: condition {c!r} of shape {s!r} needs --texture {s}/{c}=RUN_DIR")
    unused = sorted(k for k in textures if k.split("/")[0] not in shapes or k.partition("/")[2] not in conditions)
    if unused:
        raise PlanError(
            f"--texture: {', '.join(unused)} not used by the plan's shapes {shapes} and conditions {conditions}"
        )
    if n_tcp_poses < 1 or n_object_layouts < 1:
        raise PlanError(f"--tcp-poses and --object-poses must be at least 1, got {n_tcp_poses} and {n_object_layouts}")

    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x7A1A1]))
    tcps, layouts = _poses(spec, rng, n_tcp_poses, n_object_layouts, pool, workspace)
    cells = []
    for tag in [None, *tags]:
        for env in envs:
            for shape in shapes:
                for cond in conditions:
                    for t in range(n_tcp_poses):
                        for o in range(n_object_layouts):
                            cells.append(
                                (trial_id(env, shape, cond, t, o, tag), env, shape, cond, t, o, [tag] if tag else [])
                            )
    for c in cells:
        if name_problem(c[0]) is not None:
            raise PlanError(
                f"--env/--shape/--tag: trial id {c[0]!r} ({len(c[0])} characters) is too long; trial ids must be "
                f"{SAFE_NAME_RULE}: use shorter names"
            )
    # Environment by environment (a random order of envs), each block in a random order: an
    # environment is a physical setup, and switching it between trials would cost a rebuild each time.
    order = np.empty(len(cells), dtype=np.int64)
    k = 0
    for e in rng.permutation(len(envs)):
        block = [i for i, c in enumerate(cells) if c[1] == envs[int(e)]]
        for i in rng.permutation(block):
            order[int(i)] = k
            k += 1
    trials = sorted(
        (
            PlannedTrial(
                trial_id=c[0],
                order=int(k),
                env=c[1],
                shape=c[2],
                condition=c[3],
                tcp_pose=c[4],
                object_layout=c[5],
                tags=c[6],
            )
            for c, k in zip(cells, order)
        ),
        key=lambda t: t.order,
    )
    defaults = {"radius_m": spec.episode.success_radius_m, "max_steps": spec.episode.max_steps}
    try:
        return TrialPlan(
            seed=int(seed),
            scene=scene,
            envs=envs,
            shapes=shapes,
            conditions=conditions,
            tcp_poses=tcps,
            object_layouts=layouts,
            textures=dict(textures),
            trials=trials,
            shape_objects=shape_objects,
            **{**defaults, **settings},
        )
    except ValidationError as err:
        raise PlanError(format_validation_error(err, "trial plan")) from None


def design_summary(plan: TrialPlan) -> list[str]:
    """Human-readable lines: the design and the number of trials per env x shape x condition x tag."""
    per_block = len(plan.tcp_poses) * len(plan.object_layouts)
    tags = sorted({tag for t in plan.trials for tag in t.tags})
    lines = [
        f"{len(plan.trials)} trials, seed {plan.seed}, scene {plan.scene or 'built-in'}",
        f"design: {len(plan.tcp_poses)} TCP poses x {len(plan.object_layouts)} object layouts = {per_block} trials "
        "per env x shape x condition" + (f", plus one such block per tag ({', '.join(tags)})" if tags else ""),
        f"envs {', '.join(plan.envs)}; shapes {', '.join(plan.shapes)}; conditions {', '.join(plan.conditions)}",
    ]
    for shape, obj in plan.shape_objects.items():
        o = obj.object
        sha = "" if obj.mesh_sha256 is None else f", sha256 {obj.mesh_sha256[:12]}..."
        lines.append(
            f"shape {shape}: scene object {o.name!r}, mesh {Path(o.mesh).name} ({o.units}, scale {o.scale}{sha})"
        )
    counts: dict[tuple, int] = {}
    for t in plan.trials:
        key = (t.env, t.shape, t.condition, ",".join(t.tags) or "-")
        counts[key] = counts.get(key, 0) + 1
    for (env, shape, cond, tag), n in sorted(counts.items()):
        lines.append(f"  env {env}  shape {shape:<10} {cond:<6} tags {tag:<16} {n} trials")
    return lines


_HEADER = """advobj real-robot trial plan (advobj trial plan). Run the trials in 'order' (one environment after the other).
Frames: the table frame = the simulator's world frame (z up, origin on the table top).
Object placements: base centre xy (m) and yaw (rad) per scene role; TCP poses: T_table_tcp and/or
joint_positions (the arm's URDF chain order; rad, or m for a prismatic joint).
Shapes: built-in meshes, or objects of the plan's scene (shape_objects: the object, its mesh file's sha256).
Conditions: clean = the shape's benign look; adv3d = the shape with textures['<shape>/adv3d'];
patch = the built-in 'patch' mesh with textures['<shape>/patch'] where the adversarial object stands.
Each scenario tag adds one full block of trials carrying that tag (trial id suffix -<tag>)."""  # noqa: E501 (written into plan files as is)


def save_plan(plan: TrialPlan, path: str | Path) -> Path:
    """Write ``plan`` as YAML with a header comment (frames, conditions, design summary)."""
    header = _HEADER + "\n\n" + "\n".join(design_summary(plan))
    return write_yaml(path, plan.model_dump(mode="json"), header=header)


def load_plan(path: str | Path) -> TrialPlan:
    """Read and validate a plan YAML; errors name the file and the dotted field."""
    path = Path(path)
    data = read_yaml(path, "trial plan", error=file_error(PlanError))
    try:
        return TrialPlan.model_validate(data)
    except ValidationError as err:
        raise PlanError(format_validation_error(err, "trial plan", str(path))) from None


def plan_sha256(path: str | Path) -> str:
    """sha256 of the plan file's bytes: ties recorded trials to the exact plan they followed."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()
