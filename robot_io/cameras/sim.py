"""The simulated wrist camera: renders the shared :class:`sim.world.SimWorld` from the sim arm's pose.

Hardware-in-the-loop simulation: the camera looks through ``T_world_tcp @ T_tcp_cam`` of the
world the :class:`robot_io.arms.sim.SimArm` moves, so a full trial session runs without hardware.
"""

from __future__ import annotations

import itertools
import time

import numpy as np

from robot_io.cameras.base import Camera, CameraIntrinsics, Frame

__all__ = ["SimCamera"]


class SimCamera(Camera):
    """Renders ``world`` at the current TCP pose (``world`` is a :class:`sim.world.SimWorld`).

    Args:
        T_tcp_cam: mount extrinsic; ``None`` uses the scene spec's camera mount.
    """

    name = "sim"

    def __init__(self, world, T_tcp_cam: np.ndarray | None = None):
        super().__init__()
        self.world = world
        self.T_tcp_cam = np.asarray(world.T_tcp_cam if T_tcp_cam is None else T_tcp_cam, dtype=np.float64)
        self._seq = itertools.count()

    def _open(self) -> None:
        self._seq = itertools.count()

    def _close(self) -> None:
        pass  # the world (and its GL context) belongs to whoever created it

    def _read(self) -> Frame:
        # Stamp at the start: the image shows the scene as it was then (like an exposure time).
        t_capture = time.monotonic()
        T_world_cam = self.world.T_world_tcp @ self.T_tcp_cam
        out = self.world.render(T_world_cam, with_ids=False)
        return Frame(np.ascontiguousarray(out.rgb), t_capture, next(self._seq))

    def identity(self) -> dict[str, str]:
        return {"serial": "sim"}

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return CameraIntrinsics(self.world.K, np.zeros(5), self.world.width, self.world.height)
