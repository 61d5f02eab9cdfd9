"""One simulated scene: object placement, the floating gripper's pose, and its cameras' views.

A :class:`SimWorld` is the unit the batched :class:`sim.env.ReachEnv` is made of, and what the
simulated hardware (``robot_io``'s sim camera and sim arm) shares. Several worlds can share one
:class:`sim.render.SceneRenderer` (one GL context): each world applies its own state and look
before rendering.

Cameras are named as in the scene (:attr:`sim.spec.SceneSpec.camera_names`): ``"wrist"`` is the
wrist camera on the TCP (rendered by :attr:`SimWorld.renderer`, at the world's image size), every
other name a fixed scene camera, rendered at its own size and intrinsics by a renderer of its own
(:func:`camera_renderer`; a renderer's size and intrinsics are fixed when it is built).
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping

import numpy as np

from sim.configs import InitialConfig, object_local_centers, object_poses_world, sample_config
from sim.render import RenderOutput, SceneRenderer
from sim.spec import WRIST
from sim.variations import Appearance, Randomization, add_sensor_noise, sample_appearance

__all__ = ["SimWorld", "camera_renderer"]


def camera_renderer(spec, name: str) -> SceneRenderer:
    """A renderer of scene camera ``name`` of ``spec``, at that camera's size and intrinsics."""
    view = spec.for_camera(name)
    return SceneRenderer(view, view.camera.width, view.camera.height)


def _noise_rng(seed: int, camera: str) -> np.random.Generator:
    """A camera's per-episode sensor-noise stream: the wrist camera's as it always was; each scene
    camera its own, so rendering one more camera never changes another camera's frames."""
    key = [int(seed), 0x0015E] + ([] if camera == WRIST else [zlib.crc32(camera.encode())])
    return np.random.default_rng(np.random.SeedSequence(key))


def _image_size(spec, image_size) -> tuple[int, int]:
    if image_size is None:
        return spec.camera.height, spec.camera.width
    if isinstance(image_size, int):
        return image_size, image_size
    h, w = image_size
    return int(h), int(w)


class SimWorld:
    """Scene state plus rendering for a single environment.

    Args:
        spec: the :class:`sim.spec.SceneSpec`.
        image_size: ``None`` (the spec camera's), an int (square) or ``(H, W)`` px.
        seed: seed of the first :meth:`reset` when none is given there.
        renderer: share an existing renderer (same spec and size) instead of creating one.
        randomization: per-episode appearance variation (default: none).
        camera_renderers: ``{scene camera name: renderer}`` to share (built by
            :func:`camera_renderer` for this spec); a scene camera without one gets its own,
            built when it is first rendered.
    """

    def __init__(
        self,
        spec,
        image_size=None,
        seed: int = 0,
        renderer: SceneRenderer | None = None,
        randomization: Randomization | None = None,
        camera_renderers: Mapping[str, SceneRenderer] | None = None,
    ):
        self.spec = spec
        self.height, self.width = _image_size(spec, image_size)
        self._owns_renderer = renderer is None
        self.renderer = renderer or SceneRenderer(spec, self.width, self.height)
        if (self.renderer.height, self.renderer.width) != (self.height, self.width):
            raise ValueError("shared renderer has a different image size")
        self.randomization = randomization or Randomization()
        self._camera_renderers: dict[str, SceneRenderer] = {}
        self._owned_camera_renderers: set[str] = set()
        for name, r in (camera_renderers or {}).items():
            self._check_camera_renderer(name, r)
            self._camera_renderers[name] = r
        self._scene_noise: dict[str, np.random.Generator] = {}
        self._centers_local = object_local_centers(spec)
        self._next_seed = int(seed)
        self.config: InitialConfig | None = None
        self.appearance = Appearance(spec.lighting)
        self._noise_rng = np.random.default_rng(seed)
        self.reset(seed)

    # ------------------------------------------------------------------ state
    def reset(self, seed: int | None = None, config: InitialConfig | None = None) -> InitialConfig:
        """Start a new episode from ``config`` or from the configuration of ``seed``."""
        if config is None:
            seed = self._next_seed if seed is None else int(seed)
            config = sample_config(self.spec, seed, self._centers_local)
        self._next_seed = config.seed + 1
        self.config = config
        self.T_world_objects = object_poses_world(config.object_xy_yaw)
        self._T_world_tcp = config.T_world_tcp_array.copy()
        look_rng = np.random.default_rng(np.random.SeedSequence([config.seed, 0x100C]))
        self.appearance = sample_appearance(self.spec, self.randomization, look_rng)
        self._noise_rng = _noise_rng(config.seed, WRIST)
        self._scene_noise = {}
        return config

    def place_objects(self, object_xy_yaw) -> None:
        """Stand the objects at ``(K, 3)`` (x m, y m, yaw rad), spec order; the TCP and look stay.

        For staged scenes (e.g. a real-trial plan's object layout replayed on sim hardware), where
        the placement comes from outside rather than from a seeded :class:`InitialConfig`.
        """
        a = np.asarray(object_xy_yaw, dtype=np.float64)
        if a.shape != (len(self.spec.objects), 3) or not np.isfinite(a).all():
            raise ValueError(f"object_xy_yaw must be finite ({len(self.spec.objects)}, 3), got {a.shape}")
        self.T_world_objects = object_poses_world(a)

    def set_scene(
        self, spec, renderer: SceneRenderer | None = None, camera_renderers: Mapping[str, SceneRenderer] | None = None
    ) -> None:
        """Swap the scene (e.g. another adversarial mesh) keeping the TCP pose and the object poses.

        ``renderer``: a renderer already built for ``spec`` at this world's image size (callers
        switching between a few scenes cache them: building one costs a GL context and mesh
        uploads); ``None`` builds one that this world owns. A renderer this world owned is closed.
        ``camera_renderers``: as the constructor's, scene cameras' renderers built for ``spec`` to share.
        """
        if len(spec.objects) != len(self.spec.objects):
            raise ValueError(
                f"set_scene: the new scene has {len(spec.objects)} objects, this world {len(self.spec.objects)}"
            )
        new = renderer or SceneRenderer(spec, self.width, self.height)
        if (new.height, new.width) != (self.height, self.width):
            raise ValueError("set_scene: renderer has a different image size")
        if self._owns_renderer and new is not self.renderer:
            self.renderer.close()
        self._owns_renderer = renderer is None
        self.renderer = new
        self._drop_camera_renderers()  # built for the old scene: rebuilt for the new one when rendered
        self.spec = spec
        for name, r in (camera_renderers or {}).items():
            self._check_camera_renderer(name, r)
            self._camera_renderers[name] = r
        self._centers_local = object_local_centers(spec)
        self.appearance = Appearance(spec.lighting)

    @property
    def T_world_tcp(self) -> np.ndarray:
        """(4, 4) current TCP pose in the world (table) frame."""
        return self._T_world_tcp.copy()

    def set_tcp_pose(self, T_world_tcp: np.ndarray) -> None:
        """Teleport the floating gripper (kinematic: there is no physics to simulate)."""
        T = np.asarray(T_world_tcp, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise ValueError("T_world_tcp must be a finite (4, 4) matrix")
        self._T_world_tcp = T.copy()

    @property
    def object_center_array(self) -> np.ndarray:
        """(K, 3) m object centres (bounding-box centres) in the world frame, spec order."""
        R, t = self.T_world_objects[:, :3, :3], self.T_world_objects[:, :3, 3]
        return np.einsum("kij,kj->ki", R, self._centers_local) + t

    def object_centers(self) -> dict[str, np.ndarray]:
        return {o.name: c for o, c in zip(self.spec.objects, self.object_center_array)}

    @property
    def K(self) -> np.ndarray:
        return self.renderer.K

    @property
    def T_tcp_cam(self) -> np.ndarray:
        return self.spec.camera.T_tcp_cam

    def camera_pose(
        self, name: str = WRIST, *, T_world_tcp: np.ndarray | None = None, right: bool = False
    ) -> np.ndarray:
        """``(4, 4) T_world_cam`` of camera ``name`` (OpenCV axes): the wrist camera at the TCP pose
        (``T_world_tcp``, default the current one) or the stereo pair's right camera (``right``);
        a scene camera at its fixed pose (the table frame is the world frame)."""
        if not isinstance(name, str):
            raise TypeError("camera_pose(name): the first argument is a camera name; give a TCP pose as T_world_tcp=")
        cam = self.spec.camera_spec(name)
        if name != WRIST:
            if right or T_world_tcp is not None:
                raise ValueError(
                    f"camera_pose: {name!r} is a fixed scene camera (right= and T_world_tcp= are the wrist's)"
                )
            return cam.T_table_cam
        T = (self._T_world_tcp if T_world_tcp is None else T_world_tcp) @ self.T_tcp_cam
        if right:
            offset = np.eye(4)
            offset[0, 3] = self.spec.camera.stereo_baseline_m
            T = T @ offset
        return T

    def camera_renderer(self, name: str = WRIST) -> SceneRenderer:
        """The renderer of camera ``name`` (built now for a scene camera this world has none of)."""
        if name == WRIST:
            return self.renderer
        self.spec.camera_spec(name)  # an unknown name: one line listing the scene's cameras
        if name not in self._camera_renderers:
            self._camera_renderers[name] = camera_renderer(self.spec, name)
            self._owned_camera_renderers.add(name)
        return self._camera_renderers[name]

    def intrinsics(self, name: str = WRIST) -> np.ndarray:
        """``(3, 3) K`` of camera ``name`` as rendered (the wrist camera's at this world's size)."""
        return self.K if name == WRIST else self.camera_renderer(name).K

    def _check_camera_renderer(self, name: str, r: SceneRenderer) -> None:
        cam = self.spec.camera_spec(name)
        if name == WRIST:
            raise ValueError("camera_renderers: the wrist camera's renderer is renderer=")
        if (r.width, r.height) != (cam.width, cam.height) or not np.allclose(r.K, cam.K()):
            raise ValueError(f"camera_renderers: the renderer of {name!r} was not built for that camera")

    def _drop_camera_renderers(self) -> None:
        for name in self._owned_camera_renderers:
            self._camera_renderers[name].close()
        self._camera_renderers, self._owned_camera_renderers = {}, set()

    # ------------------------------------------------------------------ rendering
    def prepare(self, renderer: SceneRenderer | None = None) -> None:
        """Load this world's state and look into ``renderer`` (default: the wrist camera's; renderers
        may be shared between worlds)."""
        r = self.renderer if renderer is None else renderer
        r.apply_appearance(self.appearance)
        r.set_state(self.T_world_objects, self._T_world_tcp)

    def render(
        self, T_world_cam: np.ndarray | None = None, with_ids: bool = True, variants=None, camera: str = WRIST
    ) -> RenderOutput:
        """Render the current state through ``camera`` (its renderer, size and intrinsics) at
        ``T_world_cam`` (default: the camera's own pose; the wrist camera's at the current TCP pose).
        Sensor noise is drawn from the camera's own per-episode stream."""
        r = self.camera_renderer(camera)
        self.prepare(r)
        out = r.render(
            self.camera_pose(camera) if T_world_cam is None else T_world_cam, with_ids=with_ids, variants=variants
        )
        if camera == WRIST:
            rng = self._noise_rng
        else:
            rng = self._scene_noise.get(camera)
            if rng is None:
                rng = self._scene_noise[camera] = _noise_rng(self.config.seed, camera)
        out.rgb = add_sensor_noise(out.rgb, self.appearance.noise_std, rng)
        return out

    def close(self) -> None:
        if self._owns_renderer:
            self.renderer.close()
        self._drop_camera_renderers()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
