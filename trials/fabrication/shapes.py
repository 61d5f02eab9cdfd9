"""The adversarial object a trial places or a print makes, named by its scene.

``advobj trial plan --shape NAME`` and ``advobj fabricate --shape NAME`` take the same names
(:func:`scene_shape`):

* the name of an object of the scene YAML (``--scene``; not its goal): that object as the scene
  declares it, its mesh a built-in name or a mesh file (with its scale, units, up axis, placement,
  attack region and look). Recorded as a :class:`SceneShape` with the sha256 of the mesh file's
  bytes, so a mesh file changed after planning is caught before a trial uses it, and with the
  object's bounding-box centre in its own frame (the point the reach criterion measures to), so a
  real cell's locator needs no mesh file;
* any other name must be a built-in mesh (``cube``, ``cylinder``, ...), swapped into the scene's
  adversarial slot with the adversarial object's scale, as before scene objects could be named.

:func:`with_shape` puts a shape into a scene's adversarial slot (the staged sim scene);
:func:`load_run` reads which mesh an attack run optimised (``run.json``), and
:func:`run_mesh_problem` says why a run's texture does not belong to a shape (another mesh file, or
the same file at another size or orientation).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydantic import Field

from attack.artifact import AttackArtifact
from sim.assets import BUILTIN_MESHES, AssetError, build_mesh, default_up_axis
from sim.configio import StrictModel
from sim.errors import AdvobjError
from sim.spec import ObjectSpec, default_scene
from trials.eval.conditions import ConditionError
from trials.jobs.dag import input_digest

__all__ = [
    "ShapeError",
    "SceneShape",
    "RunSource",
    "scene_shape",
    "with_shape",
    "mesh_file_problem",
    "load_run",
    "same_mesh",
    "run_mesh_problem",
]


class ShapeError(AdvobjError, ValueError):
    """A shape name does not name a usable object; the message names the flag and the scene field."""


class SceneShape(StrictModel):
    """A scene object named as a shape: the object as its scene declares it (paths resolved by the
    scene loader), the sha256 of its mesh file's bytes (None for a built-in mesh) and its
    bounding-box centre in its own frame (m; the point the reach criterion measures to)."""

    object: ObjectSpec = Field(description="the scene's object as its scene declares it (mesh paths resolved)")
    mesh_sha256: str | None = Field(
        None, pattern=r"^[0-9a-f]{64}$", description="sha256 of the mesh file's bytes; null for a built-in mesh"
    )
    center_m: tuple[float, float, float] = Field(
        description="bounding-box centre in the object's own frame (m): the point the reach criterion measures to"
    )


def _mesh_file(mesh: str) -> Path | None:
    """The file a mesh source names (None: a built-in name, or no such file)."""
    if mesh in BUILTIN_MESHES:
        return None
    p = Path(mesh)
    return p if p.is_file() else None


def _looks_like_a_file(name: str) -> bool:
    return "/" in name or "\\" in name or Path(name).suffix != ""


def scene_shape(spec, name: str, flag: str = "--shape", scene: str | None = None) -> SceneShape | None:
    """What ``name`` means as a shape in ``spec`` (read from the file ``scene``; None: the built-in
    scene): a :class:`SceneShape` for an object of the scene other than its goal, None for a
    built-in mesh name that names no such object.

    Refused in one line naming ``flag`` (:class:`ShapeError`): a name that is neither; the goal (a
    goal object whose name is no built-in mesh); a file path (a mesh file is named through a scene
    object); an object whose mesh file is missing or cannot be built.
    """
    where = f"scene {scene}" if scene else "the built-in scene"
    k = next((i for i, o in enumerate(spec.objects) if o.name == name), None)
    if k is None or spec.objects[k].role == "goal":
        if name in BUILTIN_MESHES:
            return None
        if k is not None:
            raise ShapeError(
                f"{flag} {name}: {name!r} is the goal of {where}; name the object to attack and place "
                f"(objects: {', '.join(o.name for o in spec.objects if o.role != 'goal')})"
            )
        if _looks_like_a_file(name):
            raise ShapeError(
                f"{flag} {name}: a mesh file is named through a scene object: declare it in a scene YAML "
                f"(objects: - {{name: my_object, mesh: {name}, role: adversarial, ...}}) and pass "
                f"--scene SCENE {flag} my_object"
            )
        raise ShapeError(
            f"{flag} {name}: no object {name!r} in {where} (its objects: {', '.join(o.name for o in spec.objects)}) "
            f"and no built-in mesh of that name ({', '.join(BUILTIN_MESHES)})"
        )
    obj = spec.objects[k]
    problem = mesh_file_problem(obj.mesh)
    if problem is not None:
        raise ShapeError(f"{flag} {name}: objects.{k}.mesh of {where}: {problem}")
    try:
        mesh = build_mesh(obj.mesh, obj.scale, **obj.mesh_kwargs())
    except AssetError as err:
        raise ShapeError(f"{flag} {name}: objects.{k}.mesh of {where}: {err}") from None
    lo, hi = np.asarray(mesh.bounds, dtype=np.float64)
    path = _mesh_file(obj.mesh)
    return SceneShape(
        object=obj,
        mesh_sha256=None if path is None else input_digest(path),
        center_m=tuple(float(v) for v in (lo + hi) / 2.0),
    )


def mesh_file_problem(mesh: str, sha256: str | None = None) -> str | None:
    """Why the mesh source ``mesh`` cannot be used (None: it can): a mesh file that is missing, or
    whose bytes no longer have ``sha256`` (when given)."""
    if mesh in BUILTIN_MESHES:
        return None
    p = Path(mesh)
    if not p.is_file():
        return f"mesh file {mesh} not found"
    now = None if sha256 is None else input_digest(p)
    if now is not None and now != sha256:
        return f"mesh file {mesh} changed since it was recorded (sha256 {now[:12]}..., recorded {sha256[:12]}...)"
    return None


def with_shape(spec, shape):
    """``spec`` with ``shape`` in its adversarial slot, at the adversarial object's pose.

    ``shape``: a mesh name (``cube``, ``patch``): swapped in with the adversarial object's scale and
    its mesh's own default look (:meth:`sim.spec.ObjectSpec.with_mesh`), as an attack's
    ``adversarial_mesh`` is; or a :class:`SceneShape`: that object as its scene declares it (mesh,
    scale, units, up axis, placement, attack region, look and name). A shape that was another object
    of the scene leaves its own place (it stands in the adversarial slot now).
    """
    adv = spec.adversarial
    if isinstance(shape, str):
        objs = [o.with_mesh(shape) if o.role == "adversarial" else o.model_dump() for o in spec.objects]
        return spec.with_updates(objects=objs)
    mine = {**shape.object.model_dump(), "pose": adv.pose.model_dump(), "role": "adversarial"}
    objs = []
    for o in spec.objects:
        if o.role == "adversarial":
            objs.append(mine)
        elif o.name != shape.object.name:
            objs.append(o.model_dump())
    return spec.with_updates(objects=objs)


# ============================================================================ attack runs
@dataclass(frozen=True)
class RunSource:
    """An attack run's texture and the mesh it was optimised on."""

    run_dir: str
    texture: np.ndarray  # (H, W, 3) uint8
    mesh: str  # built-in name or mesh file path
    scale: object  # the scene's scale of the adversarial object (number or 3-tuple)
    sha256: str  # of texture.npy
    mesh_kwargs: dict = field(
        default_factory=dict
    )  # units / up_axis / placement of a mesh file (sim.assets.build_mesh)
    recorded: bool = True  # run.json holds the run's scene (else the geometry is the fallback scene's)


def load_run(run_dir, spec=None) -> RunSource:
    """Read an ``advobj attack run`` directory (clear errors naming the missing/bad file).

    The mesh is the run's ``adversarial_mesh``, else its recorded scene's adversarial object; the
    geometry (scale, units, up axis, placement) is that object's. A run that recorded no scene
    falls back on ``spec`` (default: the built-in scene).
    """
    art = AttackArtifact.load(run_dir, error=ConditionError)
    scene = art.scene
    adv = next((o for o in scene.get("objects", []) if isinstance(o, dict) and o.get("role") == "adversarial"), None)
    recorded = adv is not None
    if adv is None:
        o = (spec if spec is not None else default_scene()).adversarial
        adv = {"mesh": o.mesh, "scale": o.scale, **o.mesh_kwargs()}
    mesh = art.mesh or adv.get("mesh")
    kw = {k: adv[k] for k in ("units", "up_axis", "placement", "attack_region") if adv.get(k) is not None}
    if mesh != adv.get("mesh"):
        kw.pop("attack_region", None)  # the region is an image of the scene mesh's UV layout
    return RunSource(str(run_dir), art.texture_u8, str(mesh), adv.get("scale", 1.0), art.sha256, kw, recorded)


def same_mesh(a: str | None, b: str | None, base: Path | None = None) -> bool:
    """Whether mesh sources ``a`` and ``b`` are one mesh: the same built-in name, or mesh files with
    the same bytes (``a`` relative: as given, else relative to ``base``, an attack run's folder)."""
    if a is None or b is None:
        return False
    if a == b:
        return True
    pa = _mesh_file(a) or (_mesh_file(str(base / a)) if base is not None and a not in BUILTIN_MESHES else None)
    pb = _mesh_file(b)
    if pa is None or pb is None:
        return False
    return pa.resolve() == pb.resolve() or input_digest(pa) == input_digest(pb)


def _scale3(s) -> np.ndarray:
    return np.broadcast_to(np.asarray(s, dtype=np.float64), (3,))


def run_mesh_problem(src: RunSource, shape, who: str = "it") -> str | None:
    """Why the texture of attack run ``src`` does not belong to ``shape`` (None: it does); ``who``
    names what needs the texture in the message.

    ``shape``: a mesh name, or a :class:`SceneShape` whose mesh must be the run's (a built-in name,
    or a file with the same bytes) and, when the run recorded its scene, at the same scale, units,
    up axis and placement (the texture would fit, but the object would not be the attacked one).
    """
    want = shape if isinstance(shape, str) else shape.object.mesh
    if not same_mesh(src.mesh, want, Path(src.run_dir)):
        of = "" if isinstance(shape, str) else f" (the scene object {shape.object.name!r})"
        return f"the attack run optimised mesh {src.mesh!r}, but {who} needs mesh {want!r}{of}"
    if isinstance(shape, str) or not src.recorded:
        return None
    o, kw = shape.object, src.mesh_kwargs
    if not np.allclose(_scale3(src.scale), _scale3(o.scale), rtol=1e-9, atol=0.0):
        return f"the attack run optimised {Path(want).name} at scale {src.scale}, the object has scale {o.scale}"
    ours = {"units": o.units, "up_axis": o.up_axis or default_up_axis(o.mesh), "placement": o.placement}
    theirs = {
        "units": kw.get("units", "m"),
        "up_axis": kw.get("up_axis") or default_up_axis(src.mesh),
        "placement": kw.get("placement", "auto"),
    }
    for key, v in ours.items():
        if theirs[key] != v:
            return f"the attack run optimised {Path(want).name} with {key} {theirs[key]}, the object has {key} {v}"
    return None
