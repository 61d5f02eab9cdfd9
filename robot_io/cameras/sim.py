"""The simulated cameras: render the shared :class:`sim.world.SimWorld` from the sim arm's pose
(:class:`SimCamera`, the wrist camera) or from a fixed pose in the table frame (:class:`SimSceneCamera`).

Hardware-in-the-loop simulation: the wrist camera looks through ``T_world_tcp @ T_tcp_cam`` of the
world the :class:`robot_io.arms.sim.SimArm` moves, a scene camera through one of the scene's
``scene_cameras`` (its size, intrinsics and declared pose, :meth:`sim.world.SimWorld.render`), so a
full trial session runs without hardware.

With ``tags`` (from an object registry, :func:`sim_tags`), the camera also draws each tag36h11 tag
where the registry says it sits on its object (or on the table), at the object's current pose in
the world. A session then locates the objects through the tag detector and the calibrated chain,
exactly as a real cell does, instead of asking the simulator where they are. Tags are printed
flat and unshaded; the render's depth hides a tag behind the gripper or another object (1 cm
tolerance: a print stands on the object's surface). :attr:`SimCamera.hidden` hides the tags of
some objects, as a hand taking them away would.
"""

from __future__ import annotations

import itertools
import time

import numpy as np

from calibration.io import T_to_pose
from robot_io.cameras.base import Camera, CameraIntrinsics, Frame
from sim.geometry import invert_T, make_T, rot_z, so3_exp

__all__ = ["SimCamera", "SimSceneCamera", "SimTag", "sim_tags", "draw_tags", "sim_registry"]


class SimTag:
    """One printed tag: on ``role`` ("table" or a scene role), ``T_object_tag`` from the object's
    registry frame (its centre; the world frame for the table), black square ``size_m``."""

    def __init__(self, tag_id: int, size_m: float, role: str, T_object_tag: np.ndarray):
        import cv2  # lazy: robot_io start-up (cv2)

        self.tag_id, self.size_m, self.role = int(tag_id), float(size_m), str(role)
        self.T_object_tag = np.asarray(T_object_tag, dtype=np.float64)
        d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
        cells = d.markerSize + 2
        marker = cv2.aruco.generateImageMarker(d, self.tag_id, cells * 16, borderBits=1)
        pad = 2 * 16  # a white quiet zone of two cells, as printed by 'calibrate tags'
        self.image = np.pad(marker, pad, constant_values=255)
        h = 0.5 * self.size_m * self.image.shape[0] / marker.shape[0]
        # Tag frame: +x right, +y up on the print, +z out of it; image corners TL, TR, BR, BL.
        self.corners_tag = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def sim_tags(registry) -> list[SimTag]:
    """The tags of a :class:`calibration.registry.ObjectRegistry`, for :class:`SimCamera`."""
    return [SimTag(i, e.size_m, e.object, invert_T(e.T_tag_object.T)) for i, e in sorted(registry.tags.items())]


OCCLUSION_TOLERANCE_M = 0.01


def sim_registry(world, tag_size_m: float = 0.045, table_tags: bool = True):
    """An object registry for the sim scene as a person would tag it: on each of the goal and the
    adversarial object, one tag on top and one on each of its four sides (a bundle, so every pose
    is seen by some tag and the single-tag ambiguity resolves), each at its face of the object's
    bounding box; plus two tags lying on the table, 25 cm either side of the world origin along y.
    Ids: table 0-1, goal 10-14, adversarial 20-24."""
    from calibration.registry import ObjectRegistry, TagEntry  # lazy: robot_io start-up (cv2)

    tags = {}
    if table_tags:
        for i, y in enumerate((-0.25, 0.25)):
            tags[i] = TagEntry(
                object="table", size_m=tag_size_m, T_tag_object=T_to_pose(invert_T(make_T(np.eye(3), [0.0, y, 0.0])))
            )
    side = so3_exp(np.array([np.pi / 2, 0.0, 0.0]))  # tag +z = object -y, tag +y = object +z
    for base, role in ((10, "goal"), (20, "adversarial")):
        k = world.spec.object_index(role)
        lo, hi = world.renderer.object_mesh(k).bounds
        half = 0.5 * (hi - lo)
        poses = [make_T(np.eye(3), [0.0, 0.0, half[2]])]  # on top, face up
        for j, (yaw, r) in enumerate(((0.0, half[1]), (np.pi / 2, half[0]), (np.pi, half[1]), (-np.pi / 2, half[0]))):
            Rz = rot_z(yaw)
            poses.append(make_T(Rz @ side, Rz @ np.array([0.0, -r, 0.0])))
        for j, T_object_tag in enumerate(poses):
            size = min(tag_size_m, 0.8 * 2 * min(half[:2]), 0.8 * 2 * half[2] if j else np.inf)  # fits the face
            tags[base + j] = TagEntry(object=role, size_m=float(size), T_tag_object=T_to_pose(invert_T(T_object_tag)))
    return ObjectRegistry(tags=tags)


def draw_tags(
    rgb: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    tags,
    T_world_objects: dict,
    depth: np.ndarray | None = None,
) -> np.ndarray:
    """``rgb`` with every tag whose object is in ``T_world_objects`` drawn in (perspective warp).

    ``T_world_objects``: role -> (4, 4) of the object's registry frame in the world. ``depth``
    (H, W) m along the optical axis (0 = nothing): a tag is drawn only where it is not behind it.
    """
    import cv2  # lazy: robot_io start-up (cv2)

    out = rgb.astype(np.float32)
    H, W = rgb.shape[:2]
    T_cam_world = invert_T(T_world_cam)
    for tag in tags:
        T_wo = T_world_objects.get(tag.role)
        if T_wo is None:
            continue
        T_cam_tag = T_cam_world @ T_wo @ tag.T_object_tag
        if float(T_cam_tag[:3, 2] @ T_cam_tag[:3, 3]) >= 0:  # the printed face turned away along the line of sight
            continue
        p = (T_cam_tag[:3, :3] @ tag.corners_tag.T).T + T_cam_tag[:3, 3]
        if np.any(p[:, 2] < 0.02):
            continue  # behind or at the lens
        px = (K @ (p / p[:, 2:3]).T).T[:, :2]
        lo, hi = px.min(0), px.max(0)
        if hi[0] < 0 or hi[1] < 0 or lo[0] > W - 1 or lo[1] > H - 1:
            continue
        side = float(np.linalg.norm(px[1] - px[0]))
        # Pre-shrink the print to about its size in the image (INTER_AREA), so the warp does not alias.
        n = int(np.clip(round(2 * side), 8, tag.image.shape[0]))
        src = cv2.resize(tag.image, (n, n), interpolation=cv2.INTER_AREA).astype(np.float32)
        # The print's outer pixel edges (centres at integers) onto the projected corners.
        Hm = cv2.getPerspectiveTransform(
            np.float32([[-0.5, -0.5], [n - 0.5, -0.5], [n - 0.5, n - 0.5], [-0.5, n - 0.5]]), px.astype(np.float32)
        )
        # White outside the print: its quiet zone is white, so the edge blends white into the scene, not black.
        warped = cv2.warpPerspective(src, Hm, (W, H), flags=cv2.INTER_LINEAR, borderValue=255)
        mask = cv2.warpPerspective(np.ones((n, n), np.float32), Hm, (W, H), flags=cv2.INTER_LINEAR, borderValue=0)
        if depth is not None:
            # The print's depth at each pixel: where its ray meets the tag plane n . X = c.
            nrm, c = T_cam_tag[:3, 2], float(T_cam_tag[:3, 2] @ T_cam_tag[:3, 3])
            v, u = np.nonzero(mask > 0)
            den = nrm[0] * (u - K[0, 2]) / K[0, 0] + nrm[1] * (v - K[1, 2]) / K[1, 1] + nrm[2]
            z = np.divide(c, den, out=np.full(den.shape, np.inf), where=np.abs(den) > 1e-9)
            d = depth[v, u]
            hidden = (d > 0) & (z > d + OCCLUSION_TOLERANCE_M)
            mask[v[hidden], u[hidden]] = 0.0
        out = out * (1.0 - mask[..., None]) + warped[..., None] * mask[..., None]
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


class SimCamera(Camera):
    """Renders ``world`` at the current TCP pose (``world`` is a :class:`sim.world.SimWorld`).

    Args:
        T_tcp_cam: mount extrinsic; ``None`` uses the scene spec's camera mount.
    """

    name = "sim"

    def __init__(self, world, T_tcp_cam: np.ndarray | None = None, tags=None):
        super().__init__()
        self.world = world
        self.T_tcp_cam = np.asarray(world.T_tcp_cam if T_tcp_cam is None else T_tcp_cam, dtype=np.float64)
        self.tags = list(tags or [])
        self.hidden: set[str] = set()  # roles whose tags are not drawn (hidden by a hand, the gripper...)
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
        rgb = out.rgb
        if self.tags:
            rgb = draw_tags(rgb, self.world.K, T_world_cam, self.tags, self.object_frames(), out.depth)
        return Frame(np.ascontiguousarray(rgb), t_capture, next(self._seq))

    def object_frames(self) -> dict:
        """Role -> ``T_world_object`` of each registry frame (the object's centre, yawed with it;
        the world itself for "table"), for the roles whose tags are drawn."""
        w = self.world
        frames = {"table": np.eye(4)}
        centers = w.object_center_array
        for k, o in enumerate(w.spec.objects):
            T = w.T_world_objects[k].copy()
            T[:3, 3] = centers[k]
            frames[o.name] = T
            if getattr(o, "role", None):
                frames[o.role] = T
        return {r: T for r, T in frames.items() if r not in self.hidden}

    def identity(self) -> dict[str, str]:
        return {"serial": "sim"}

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return CameraIntrinsics(self.world.K, np.zeros(5), self.world.width, self.world.height)


class SimSceneCamera(Camera):
    """A fixed camera of ``world``: scene camera ``camera`` of its scene (``scene_cameras``), rendered
    at that camera's size and intrinsics through the world's renderer of it.

    Args:
        T_table_cam: the camera's pose in the table (world) frame; ``None``: the pose the scene
            declares (read at every frame, so a staged scene's own pose counts).
    """

    name = "sim"

    def __init__(self, world, camera: str, T_table_cam: np.ndarray | None = None):
        super().__init__()
        world.spec.camera_spec(camera)  # an unknown name: one line listing the scene's cameras
        self.world = world
        self.camera = self.label = str(camera)
        self.T_table_cam = None if T_table_cam is None else np.asarray(T_table_cam, dtype=np.float64)
        self._seq = itertools.count()

    def _open(self) -> None:
        self._seq = itertools.count()

    def _close(self) -> None:
        pass  # the world (and its renderers) belongs to whoever created it

    def _read(self) -> Frame:
        t_capture = time.monotonic()  # stamped at the start, like an exposure
        out = self.world.render(self.T_table_cam, with_ids=False, camera=self.camera)
        return Frame(np.ascontiguousarray(out.rgb), t_capture, next(self._seq))

    def identity(self) -> dict[str, str]:
        return {"serial": "sim", "camera": self.camera}

    @property
    def intrinsics(self) -> CameraIntrinsics:
        cam = self.world.spec.camera_spec(self.camera)
        return CameraIntrinsics(self.world.intrinsics(self.camera), np.zeros(5), cam.width, cam.height)
