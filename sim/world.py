"""One simulated scene: object placement, the floating gripper's pose, and its wrist-camera view.

A :class:`SimWorld` is the unit the batched :class:`sim.env.ReachEnv` is made of, and what the
simulated hardware (``robot_io``'s sim camera and sim arm) shares. Several worlds can share one
:class:`sim.render.SceneRenderer` (one GL context): each world applies its own state and look
before rendering.
"""

from __future__ import annotations

import numpy as np

from sim.configs import InitialConfig, object_local_centers, object_poses_world, sample_config
from sim.render import RenderOutput, SceneRenderer
from sim.variations import Appearance, Randomization, add_sensor_noise, sample_appearance

__all__ = ["SimWorld"]


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
    """

    def __init__(
        self,
        spec,
        image_size=None,
        seed: int = 0,
        renderer: SceneRenderer | None = None,
        randomization: Randomization | None = None,
    ):
        self.spec = spec
        self.height, self.width = _image_size(spec, image_size)
        self._owns_renderer = renderer is None
        self.renderer = renderer or SceneRenderer(spec, self.width, self.height)
        if (self.renderer.height, self.renderer.width) != (self.height, self.width):
            raise ValueError("shared renderer has a different image size")
        self.randomization = randomization or Randomization()
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
        self._noise_rng = np.random.default_rng(np.random.SeedSequence([config.seed, 0x0015E]))
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

    def set_scene(self, spec, renderer: SceneRenderer | None = None) -> None:
        """Swap the scene (e.g. another adversarial mesh) keeping the TCP pose and the object poses.

        ``renderer``: a renderer already built for ``spec`` at this world's image size (callers
        switching between a few scenes cache them: building one costs a GL context and mesh
        uploads); ``None`` builds one that this world owns. A renderer this world owned is closed.
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
        self.spec = spec
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

    def camera_pose(self, T_world_tcp: np.ndarray | None = None, right: bool = False) -> np.ndarray:
        """``T_world_cam`` of the wrist camera (or of the stereo pair's right camera)."""
        T = (self._T_world_tcp if T_world_tcp is None else T_world_tcp) @ self.T_tcp_cam
        if right:
            offset = np.eye(4)
            offset[0, 3] = self.spec.camera.stereo_baseline_m
            T = T @ offset
        return T

    # ------------------------------------------------------------------ rendering
    def prepare(self) -> None:
        """Load this world's state and look into the (possibly shared) renderer."""
        self.renderer.apply_appearance(self.appearance)
        self.renderer.set_state(self.T_world_objects, self._T_world_tcp)

    def render(self, T_world_cam: np.ndarray | None = None, with_ids: bool = True, variants=None) -> RenderOutput:
        """Render the current state; default camera = the wrist camera at the current TCP pose."""
        self.prepare()
        out = self.renderer.render(
            self.camera_pose() if T_world_cam is None else T_world_cam, with_ids=with_ids, variants=variants
        )
        out.rgb = add_sensor_noise(out.rgb, self.appearance.noise_std, self._noise_rng)
        return out

    def close(self) -> None:
        if self._owns_renderer:
            self.renderer.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
