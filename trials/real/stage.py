"""Staging a planned trial on sim hardware: the simulated operator who sets up the table.

On a real cell a person places the printed objects. With ``sim`` camera and arm the
:class:`SimStage` does it in the shared :class:`sim.world.SimWorld`:

* the scene for the trial's shape and condition (the adversarial slot holds what
  :meth:`trials.real.plan.TrialPlan.adversarial_for` names, through
  :func:`trials.fabrication.shapes.with_shape`: a built-in mesh swapped in as
  :func:`trials.eval.conditions.condition_spec` does, same pose, the mesh's own default look; or
  the plan's scene object as its scene declares it, at that pose), and the plan's texture on it for
  ``adv3d`` / ``patch`` (``clean`` keeps the benign look). A scene object's mesh file must still
  have the bytes the plan recorded (checked for every shape when the stage is built, before any
  trial);
* the object poses of the trial's layout, optionally with a deliberate misplacement
  (:meth:`misplace`) that the live placement check must catch;
* :meth:`follow_guidance`: the simulated operator moves each object by the correction the check
  asked for, as a person would.

Renderers are cached per (mesh, texture): a session has a handful of combinations, and building a
renderer (GL context, mesh and texture upload) costs far more than a trial's render. The fixed
scene cameras a session reads (``cameras``) get renderers of their own per (mesh, texture) too
(:func:`sim.world.camera_renderer`), handed to the world with the scene, with the trial's texture
on them, so every camera sees the same object; each is drawn once when built, so its first frame
in a policy loop is not aged by the uploads of a first draw.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sim.configs import object_poses_world
from sim.errors import AdvobjError
from sim.render import SceneRenderer
from sim.world import camera_renderer
from trials.eval.conditions import load_attack_source
from trials.fabrication.shapes import mesh_file_problem, with_shape

__all__ = ["StageError", "SimStage", "load_texture"]


class StageError(AdvobjError, ValueError):
    """A plan's texture or mesh file cannot be used (missing, changed since planning, malformed)."""


def load_texture(ref, plan_dir: Path | None = None) -> np.ndarray:
    """The (H, W, 3) uint8 texture of a :class:`trials.real.plan.TextureRef`, checked against its sha256.

    A relative path is tried as given, then relative to ``plan_dir``.
    """
    p = Path(ref.path)
    if not p.is_absolute() and not p.exists() and plan_dir is not None:
        p = plan_dir / p
    src = load_attack_source(p)
    if src.sha256 != ref.sha256:
        raise StageError(
            f"{p}: texture.npy sha256 {src.sha256[:12]}... differs from the plan's {ref.sha256[:12]}...; "
            "the attack run changed since the plan was made"
        )
    return src.texture


class SimStage:
    """Sets the sim world up for each planned trial.

    Args:
        world: the :class:`sim.world.SimWorld` the sim camera and arm share.
        plan: the :class:`trials.real.plan.TrialPlan`.
        plan_dir: where relative texture paths are looked up.
    """

    def __init__(self, world, plan, plan_dir: Path | None = None, cameras=()):
        self.world = world
        self.plan = plan
        self.plan_dir = plan_dir
        self.cameras = tuple(cameras)  # fixed scene cameras that must show the trial's texture too
        self.base_spec = world.spec
        self._renderers: dict[tuple, object] = {}  # (mesh, texture) -> (spec, wrist renderer, {camera: renderer})
        self._textures: dict[str, np.ndarray] = {}
        self._offsets: dict[str, np.ndarray] = {}
        self.builds = 0  # renderers built (the cache's effect is measurable)
        for shape, obj in plan.shape_objects.items():
            problem = mesh_file_problem(obj.object.mesh, obj.mesh_sha256)
            if problem is not None:
                raise StageError(f"shape_objects.{shape}.object.mesh: {problem}; the plan was made for the old file")

    def misplace(self, role: str, dx_m: float = 0.0, dy_m: float = 0.0, dyaw_rad: float = 0.0) -> None:
        """Put ``role`` off its planned pose by this much in the next :meth:`prepare` (tests, demos)."""
        self._offsets[role] = np.array([dx_m, dy_m, dyaw_rad], dtype=np.float64)

    def texture(self, trial) -> tuple[np.ndarray | None, str | None]:
        ref = self.plan.texture_for(trial)
        if ref is None:
            return None, None
        key = f"{trial.shape}/{trial.condition}"
        if key not in self._textures:
            self._textures[key] = load_texture(ref, self.plan_dir)
        return self._textures[key], key

    def prepare(self, trial) -> None:
        """Scene and object poses for ``trial`` (the TCP stays where the arm is)."""
        tex, tex_key = self.texture(trial)
        key = ("patch" if trial.condition == "patch" else trial.shape, tex_key)
        if key not in self._renderers:
            # the plan's object goes through validation with the rest of the scene (with_updates)
            spec = with_shape(self.base_spec, self.plan.adversarial_for(trial))
            r = SceneRenderer(spec, self.world.width, self.world.height)
            cams = {name: camera_renderer(spec, name) for name in self.cameras}
            if tex is not None:
                for each in (r, *cams.values()):
                    each.set_object_texture(spec.object_index("adversarial"), tex)
            for name, each in cams.items():
                each.render(spec.camera_spec(name).T_table_cam, with_ids=False)  # the first draw's uploads
            self._renderers[key] = (spec, r, cams)
            self.builds += 1
        spec, r, cams = self._renderers[key]
        if self.world.spec is not spec:
            self.world.set_scene(spec, renderer=r, camera_renderers=cams)
        layout = self.plan.object_layout(trial.object_layout)
        xyy = np.zeros((len(spec.objects), 3))
        for k, o in enumerate(spec.objects):
            # Other objects of the scene (distractors) keep their nominal pose.
            xyy[k] = (o.pose.x_m, o.pose.y_m, np.radians(o.pose.yaw_deg))
        for role, p in layout.objects.items():
            xyy[spec.object_index(role)] = (p.xy_m[0], p.xy_m[1], p.yaw_rad)
            if role in self._offsets:
                xyy[spec.object_index(role)] += self._offsets.pop(role)
        self.world.place_objects(xyy)

    def follow_guidance(self, issues) -> None:
        """Move each object by the correction the placement check asked for."""
        T = self.world.T_world_objects.copy()
        for issue in issues:
            if issue.missing:
                continue
            k = self.world.spec.object_index(issue.role)
            x, y = T[k, 0, 3] + issue.dx_m, T[k, 1, 3] + issue.dy_m
            yaw = float(np.arctan2(T[k, 1, 0], T[k, 0, 0])) + issue.dyaw_rad
            T[k] = object_poses_world([[x, y, yaw]])[0]
        self.world.T_world_objects = T

    def close(self) -> None:
        """Give the world an own renderer back and free the cached ones."""
        if any(self.world.renderer is r for _, r, _ in self._renderers.values()):
            self.world.set_scene(self.base_spec)
        for _, r, cams in self._renderers.values():
            for each in (r, *cams.values()):
                each.close()
        self._renderers.clear()
