"""Recorded frames as the attack's frames: the object composited into a recording, differentiable in its texture.

:class:`RecordedFrames` is the :class:`attack.sources.FrameSource` of a recording
(:mod:`sim.recording`): a user whose policy was trained on real data attacks it on their own
frames, with no simulator in the loop. The attack, its renderer and its losses are the ones of the
simulator's rollouts: this module only makes :class:`attack.render.Capture` records out of recorded
frames, so :func:`attack.render.render_adversarial_batch` composites the texture into them and
the objective (pose term, optional saliency term) reads the policy's actions on them.

One frame, for one recorded step, one camera the policy reads and one object pose:

1. **Where each pixel looks** (:class:`ViewRays`). The policy reads the camera's frame at its input
   size: the frame as recorded when it has that size, else brought to it by the card's
   preprocessing (:func:`sim.policyview.policy_view`: centre crop, letterbox or resize; a pure
   scale-and-shift of pixel coordinates). Each pixel of that view maps back to a pixel of the
   recorded frame, and through the lens (the recording's OpenCV ``K`` and ``dist``, inverted by
   ``cv2.undistortPointsIter`` and checked by projecting back to within 1e-3 px) to a ray.
2. **The object's fragments.** The object is rendered by the scene's own renderer
   (:class:`sim.render.SceneRenderer`, pyrender's ``IntrinsicsCamera``) from the camera's pose in
   the table frame (:meth:`sim.recording.Recording.T_table_cam`), undistorted, with a margin wide
   enough for every ray of the view and at :data:`SUPERSAMPLING` times the view's resolution; each
   view pixel reads the id pass at :data:`SUPERSAMPLING` x :data:`SUPERSAMPLING` sub-pixel rays.
   The object's share of them is its coverage (``alpha``), and its face, barycentrics, UVs and UV
   derivatives are computed on the pixel's own ray (:func:`attack.render.rasterize_fragments`
   with ``rays=``), so the composited object is distorted exactly as the frame is.
3. **Shading** (:func:`attack.render.deferred_shading`, the simulator's): the scene's lights times
   a per-channel gain, the frame's brightness estimated as the ratio of the recorded frame's
   linear light to the scene's render of the table at the pixels where both show the table alone.
   It assumes the scene's table describes the real one (its look and lights are the scene's); EOT
   then multiplies the gain by a draw in ``[1/GAIN_JITTER, GAIN_JITTER]`` with a per-channel tint
   of +-``TINT_JITTER``, replaces the scene's lights by random ones when ``light_randomization``
   is on (:func:`sim.variations.sample_appearance`, as the simulator's attack does), and adds
   Gaussian sensor noise of a standard deviation drawn in ``[0, NOISE_MAX]`` to the object's pixels.
4. **Compositing over the real frame**: ``(1 - alpha) * frame + alpha * object``
   (:class:`attack.render.Fragments`' ``alpha`` and ``noise``). Faces the attack does not
   optimise (``optimizable_faces``) keep the mesh's own look as the scene's renderer draws it.

**What stays in front.** The render holds the scene's gripper at the recorded TCP pose, so where it
stands between the camera and the object the frame's own pixels stay. For a wrist camera (mount
``tcp``) the gripper never moves in the image: this is the static occluder mask, taken from the
calibration (the recording's hand-eye ``T_tcp_cam``) and the scene's gripper model, rather than
estimated from the recording as the pixels that barely change: a plain table barely changes
either, and would hide the object wherever it is uniform, while the model's mask is exact when the
scene's ``gripper`` describes the real one (a fixed camera sees the gripper move in front of the
object the same way). Nothing else occludes: the recording format holds no depth, so a real
object standing in front of the composited one is not known (place the object's region where
nothing stands between it and the cameras).

**Which frames and poses.** Training uses the recording's training episodes, validation its
held-out ones (:func:`split_episodes`: the last :data:`HOLDOUT_FRACTION` of the episodes in the
manifest's order, at least one, when ``validation_every > 0``; :func:`check_split` refuses a split
whose parts overlap or are empty). An object pose is ``(x, y, yaw)`` on the table top, ``x`` and ``y``
uniform in the scene's ``init.region_x_m`` and ``init.region_y_m``, ``yaw`` uniform: the ranges
the simulator places objects in (:mod:`sim.configs`), kept only where the object's centre is in view
of a camera the policy reads (in front of it, farther than ``znear`` plus the object's bounding
radius) and not within 1.5 success radii of the TCP (the simulator's own rule for a start that is
over before it begins). A recording none of whose training frames shows any of that region is
refused in one line, as is one whose held-out frames show none of it.

**An iteration** (:meth:`RecordedFrames.start`) draws ``num_envs`` (step, object pose) candidates
``8 x`` over, weighs them by the schedule's Beta density over the TCP-to-object distance (C2F, as
:class:`attack.sources.SimRollouts` weighs configurations) and keeps ``num_envs``; each is then
followed along its recorded episode for up to ``rollout_steps`` steps, one batch per step. This
source is **open loop**: the camera moves as it did when the episode was recorded, whatever the
policy answers, so :meth:`RecordedFrames.advance` only counts the step. No simulator env is built
or stepped (no :class:`sim.env.ReachEnv`, no rollout).

**Validation** (:meth:`RecordedFrames.validate`) on held-out frames: up to ``validation_episodes``
frames evenly spaced over the held-out episodes' steps, each with one object pose drawn once from
the run's seed (not from the training RNG), the texture rounded to 8 bits as it is saved, nominal
light (the estimated gain, no jitter or noise). It measures the mean pose loss (``L_pose``,
:func:`attack.losses.pose_loss`) and the **toward fraction**: the share of those frames where the
first action of the policy's output moves the TCP in a direction within :data:`TOWARD_DEG` of the
direction from the TCP to the object's centre (``angle(p_next - p_tcp, p_adv - p_tcp)``, with
``p_next`` the position the action would move to, :func:`sim.action.intended_position`; an action
that does not move counts as not toward). Recorded frames cannot say where the policy would have
gone (the episode does not react), so the simulator's T-ASR is not measurable here; the toward
fraction is the best texture's score (``best/``), ties broken by the lower mean distance from
``p_next`` to the object.
"""

from __future__ import annotations

import hashlib
import math
import time
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Sequence

import cv2
import numpy as np
import torch

from attack.artifact import texture_to_uint8
from attack.losses import pose_loss
from attack.render import Capture, HybridRenderer, rasterize_fragments, ray_barycentrics
from attack.schedule import sample_configs, stage_params
from attack.sources import Frames
from sim.action import intended_position
from sim.assets import build_mesh
from sim.configs import object_local_centers, object_poses_world
from sim.errors import AdvobjError
from sim.geometry import invert_T, transform_points
from sim.policies.contract import InputPlan, policy_cameras
from sim.policyview import policy_view, policy_view_K
from sim.recording import MANIFEST_NAME, Recording, RecordingCamera, read_recording
from sim.render import FACE_BASE, TABLE_ID, SceneRenderer
from sim.variations import Randomization, sample_appearance

__all__ = [
    "RecordedAttackError",
    "ViewRays",
    "RecordedFrames",
    "policy_views",
    "split_episodes",
    "check_split",
    "points_toward",
    "TOWARD_DEG",
    "SUPERSAMPLING",
    "HOLDOUT_FRACTION",
    "VALIDATION_MEASURE",
]

#: A frame counts as "toward" when the first action's motion is within this angle of the object.
TOWARD_DEG = 45.0
#: Sub-pixel rays per side of a view pixel (coverage in steps of 1 / SUPERSAMPLING^2).
SUPERSAMPLING = 2
#: Held-out share of a recording's episodes (the last ones in the manifest's order), at least one.
HOLDOUT_FRACTION = 0.2
#: EOT over light: the estimated gain times a log-uniform draw in [1/GAIN_JITTER, GAIN_JITTER] ...
GAIN_JITTER = 1.2
#: ... and a per-channel tint in [1 - TINT_JITTER, 1 + TINT_JITTER]; sensor noise std in [0, NOISE_MAX].
TINT_JITTER = 0.04
NOISE_MAX = 0.02
#: The estimated brightness gain is kept within this range (a frame far outside it is not the scene's table).
GAIN_RANGE = (0.25, 4.0)
MAX_RENDER_SIDE_PX = 4096  # the largest side a scene camera (and so the margin render) may have
_CANDIDATES_PER_SLOT = 8
_POSE_TRIES = 32
_REGION_GRID = 5  # points per side of the region checked for visibility
_UNDISTORT_TOL_PX = 1e-3
_GAMMA = 2.2  # pyrender's output encoding (attack.render.shade)
_VIEW_CACHE_BYTES = 128 * 2**20

VALIDATION_MEASURE = (
    f"toward fraction (held-out recorded frames whose first action points within {TOWARD_DEG:g} deg of the object)"
)


class RecordedAttackError(AdvobjError, ValueError):
    """A recording that cannot be attacked on with this policy and scene; the line says why."""


# ----------------------------------------------------------------------------------- the policy
def policy_views(policy) -> dict[str, tuple[tuple[int, int], str]]:
    """``{camera: ((H, W) px, preprocess)}`` of every camera ``policy`` reads, in its input order:
    the size its model takes from that camera and how a frame of another size is brought to it."""
    plan = getattr(policy, "inputs", None)
    if isinstance(plan, InputPlan):
        return {c: (tuple(plan.image_for(c).size), plan.image_for(c).image.preprocess) for c in plan.cameras}
    S = int(policy.image_size)
    return {cam: ((S, S), "center_crop") for cam in policy_cameras(policy)}


# ----------------------------------------------------------------------------------- the split
def split_episodes(episode_ids: Sequence[str], validating: bool, where: str = "recordings") -> tuple[tuple, tuple]:
    """``(training, held-out)`` episode ids: the last :data:`HOLDOUT_FRACTION` of the episodes (at
    least one) are held out when ``validating``, none otherwise; :func:`check_split` is applied."""
    ids = tuple(episode_ids)
    if not validating:
        train, held = ids, ()
    else:
        if len(ids) < 2:
            raise RecordedAttackError(
                f"{where}: {len(ids)} episode; validation holds whole episodes out, so it needs at least 2 "
                "(record more, or set validation_every: 0)"
            )
        n = max(1, round(len(ids) * HOLDOUT_FRACTION))
        train, held = ids[: len(ids) - n], ids[len(ids) - n :]
    check_split(train, held, validating, where)
    return train, held


def check_split(train: Sequence[str], held: Sequence[str], validating: bool, where: str = "recordings") -> None:
    """Refuse a split with no training episode, no held-out episode while validating, or an
    episode on both sides (frames the texture was optimised on would score it)."""
    if not train:
        raise RecordedAttackError(f"{where}: no training episode")
    if validating and not held:
        raise RecordedAttackError(f"{where}: no held-out episode to validate on (or set validation_every: 0)")
    both = sorted(set(train) & set(held))
    if both:
        raise RecordedAttackError(
            f"{where}: episode {both[0]!r} is both a training and a held-out episode; the split must be disjoint"
        )


def points_toward(T_world_tcp: torch.Tensor, actions: torch.Tensor, p_adv: torch.Tensor, max_step_m: float):
    """``(B,)`` bool: the first action ``(B, 6)`` (normalised ``delta_tcp``) moves the TCP within
    :data:`TOWARD_DEG` of the direction to ``p_adv (B, 3)`` m (see the module docstring)."""
    T = T_world_tcp.to(actions.dtype)
    p = T[:, :3, 3]
    move = intended_position(T, actions, max_step_m) - p
    to = p_adv.to(actions.dtype) - p
    n_move, n_to = move.norm(dim=-1), to.norm(dim=-1)
    cos = (move * to).sum(-1) / (n_move * n_to).clamp_min(1e-12)
    return (n_move > 1e-9) & (cos >= math.cos(math.radians(TOWARD_DEG)))


# ----------------------------------------------------------------------------------- the lens
class ViewRays:
    """Where the pixels of the policy's view of a recorded camera look (module docstring, step 1).

    ``cam``: the :class:`sim.recording.RecordingCamera`; ``size_hw``: the (H, W) px the policy
    reads; ``preprocess``: the card's (used when the frame has another size; a non-square input
    takes frames of its own size only). Pixel coordinates are OpenCV's (centres at integers).

    ``A (3, 3)``: recorded-frame pixels -> view pixels; ``K_view``: ``A @ K`` (the view's pinhole
    intrinsics; exact without distortion); ``sub_xy (H*W, n, 2)`` and ``sub_ok (H*W, n)``: the
    normalised image coordinates of each pixel's ``n = SUPERSAMPLING^2`` sub-pixel rays and whether
    they fall inside the recorded frame (and invert the lens). Called as ``rays(u, v)`` it gives
    ``(P, 3)`` camera-frame directions through integer view points (:func:`rasterize_fragments`).
    """

    def __init__(self, cam: RecordingCamera, size_hw, preprocess: str, supersampling: int = SUPERSAMPLING):
        H, W = (int(v) for v in size_hw)
        if (cam.height, cam.width) == (H, W):
            A = np.eye(3)
        elif H == W:
            A = policy_view_K(np.eye(3), cam.width, cam.height, H, preprocess)
        else:
            raise RecordedAttackError(
                f"camera {cam.name}: frames of {cam.width}x{cam.height} px, the policy reads {W}x{H} px from it, and "
                "its preprocessing makes square views only: the frames must have the size the policy reads"
            )
        self.name, self.K, self.dist = cam.name, np.asarray(cam.K, np.float64), np.asarray(cam.dist, np.float64)
        self.height, self.width, self.preprocess = H, W, preprocess
        self.frame_size = (cam.width, cam.height)
        self.A, self.A_inv = A, np.linalg.inv(A)
        self.K_view = A @ self.K
        gv, gu = np.mgrid[0 : H + 1, 0 : W + 1].astype(np.float64)
        self._grid = self.normalised(gu.ravel(), gv.ravel())[0].reshape(H + 1, W + 1, 2)
        ss = int(supersampling)
        off = (np.arange(ss) + 0.5) / ss - 0.5
        v, u = np.mgrid[0:H, 0:W].astype(np.float64)
        su = (u[:, :, None, None] + off[None, None, None, :]).repeat(ss, 2)
        sv = (v[:, :, None, None] + off[None, None, :, None]).repeat(ss, 3)
        xy, ok = self.normalised(su.ravel(), sv.ravel())
        self.sub_xy, self.sub_ok = xy.reshape(H * W, ss * ss, 2), ok.reshape(H * W, ss * ss)
        self.supersampling = ss
        if not self.sub_ok.any():
            raise RecordedAttackError(f"camera {cam.name}: no pixel of the policy's view falls inside the frame")
        good = self.sub_xy[self.sub_ok]
        self.bounds = good.min(0), good.max(0)  # the normalised coordinates the view spans

    def to_frame(self, u, v) -> tuple[np.ndarray, np.ndarray]:
        """View pixels -> recorded-frame pixels."""
        p = self.A_inv @ np.stack([u, v, np.ones_like(u)])
        return p[0], p[1]

    def normalised(self, u, v) -> tuple[np.ndarray, np.ndarray]:
        """``(xy (N, 2), ok (N,))``: the undistorted normalised coordinates of view points ``(u, v)``
        and whether each lies inside the recorded frame with a lens inversion that projects back."""
        fu, fv = self.to_frame(np.asarray(u, np.float64), np.asarray(v, np.float64))
        w, h = self.frame_size
        ok = (fu >= -0.5) & (fu <= w - 0.5) & (fv >= -0.5) & (fv <= h - 0.5)
        if not self.dist.any():
            xy = np.stack([(fu - self.K[0, 2]) / self.K[0, 0], (fv - self.K[1, 2]) / self.K[1, 1]], -1)
            return xy, ok
        pts = np.stack([fu, fv], -1).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
        xy = cv2.undistortPointsIter(pts, self.K, self.dist, None, None, crit).reshape(-1, 2)
        back = self._distort(xy)
        ok &= np.isfinite(xy).all(-1) & (np.abs(back - pts.reshape(-1, 2)).max(-1) < _UNDISTORT_TOL_PX)
        return xy, ok

    def _distort(self, xy: np.ndarray) -> np.ndarray:
        """Recorded-frame pixels ``(N, 2)`` of normalised undistorted coordinates ``xy (N, 2)``."""
        if not len(xy):
            return np.zeros((0, 2))
        obj = np.concatenate([xy, np.ones((len(xy), 1))], -1)
        out, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), self.K, self.dist)
        return out.reshape(-1, 2)

    def __call__(self, u, v) -> np.ndarray:
        iu, iv = np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)
        xy = self._grid[iv, iu]
        return np.concatenate([xy, np.ones((len(xy), 1))], -1)

    def project(self, p_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(uv (N, 2) view px, ok (N,))`` of camera-frame points ``p_cam (N, 3)`` m; ``ok``: in front
        of the camera, within the normalised span of the view (where the lens model is inverted)
        and inside the view's pixels."""
        p = np.asarray(p_cam, np.float64).reshape(-1, 3)
        z = p[:, 2]
        front = z > 1e-9
        xy = p[:, :2] / np.where(front, z, 1.0)[:, None]
        lo, hi = self.bounds
        ok = front & (xy >= lo).all(-1) & (xy <= hi).all(-1)
        f = self._distort(xy) if self.dist.any() else xy @ self.K[:2, :2].T + self.K[:2, 2]
        uv = (self.A @ np.concatenate([f, np.ones((len(f), 1))], -1).T).T[:, :2]
        ok &= (uv[:, 0] >= -0.5) & (uv[:, 0] <= self.width - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= self.height - 0.5)
        return uv, ok

    def render_camera(self, max_side_px: int = MAX_RENDER_SIDE_PX) -> tuple[dict, np.ndarray, np.ndarray]:
        """The undistorted pinhole camera that covers the view with a margin (``{width, height, fx,
        fy, cx, cy}``, a scene camera's fields, at ``SUPERSAMPLING`` times the view's scale where
        :data:`MAX_RENDER_SIDE_PX` allows), ``lookup (H*W, n)``: each sub-pixel ray's flat pixel index
        in its render, -1 where the ray is not ``sub_ok``, and ``near (H*W, 9)``: the 3 x 3 render
        pixels around each pixel centre's ray (-1 outside the render or the frame), where the face
        that ray meets is looked for."""
        ss = self.supersampling
        fx = ss * abs(self.A[0, 0]) * self.K[0, 0]
        fy = ss * abs(self.A[1, 1]) * self.K[1, 1]
        lo, hi = self.bounds
        span = np.maximum((hi - lo) * (fx, fy), 1.0)
        shrink = min(1.0, (max_side_px - 4) / span.max())
        fx, fy = fx * shrink, fy * shrink
        cx, cy = -lo[0] * fx + 1.5, -lo[1] * fy + 1.5
        width = int(math.ceil((hi[0] - lo[0]) * fx)) + 4
        height = int(math.ceil((hi[1] - lo[1]) * fy)) + 4

        def index(xy, ok):
            col = np.rint(xy[..., 0] * fx + cx).astype(np.int64)
            row = np.rint(xy[..., 1] * fy + cy).astype(np.int64)
            inside = ok & (col >= 0) & (col < width) & (row >= 0) & (row < height)
            return np.where(inside, row * width + col, -1), col, row

        lookup = index(self.sub_xy, self.sub_ok)[0]
        v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        centre_xy, centre_ok = self.normalised(u.ravel(), v.ravel())
        _, col, row = index(centre_xy, centre_ok)
        dc, dr = np.meshgrid([-1, 0, 1], [-1, 0, 1])
        col, row = col[:, None] + dc.ravel(), row[:, None] + dr.ravel()
        inside = centre_ok[:, None] & (col >= 0) & (col < width) & (row >= 0) & (row < height)
        near = np.where(inside, row * width + col, -1)
        return {"width": width, "height": height, "fx": fx, "fy": fy, "cx": cx, "cy": cy}, lookup, near


# ----------------------------------------------------------------------------------- one camera
@dataclass(frozen=True)
class _Look:
    """How one slot's object is lit: ``gain (3,)`` times the estimated brightness, ``noise_std``
    (fraction of full scale) and ``lighting`` (a :class:`sim.spec.LightingSpec`, None: the scene's)."""

    gain: np.ndarray
    noise_std: float = 0.0
    lighting: object | None = None


_NOMINAL = _Look(np.ones(3))


def _linear(srgb: np.ndarray) -> np.ndarray:
    return np.clip(srgb, 0.0, 1.0) ** _GAMMA


def _brightness_gain(real: np.ndarray, sim_lin: np.ndarray, table: np.ndarray) -> np.ndarray:
    """``(3,)`` per-channel gain of the frame's light over the scene's: the median, over the view's
    pixels showing only the table in the render (``table (P,)``), of the ratio of the recorded
    pixel's linear value (``real (P, 3)`` sRGB) to the render's (``sim_lin (P, n, 3)`` linear per
    sub-pixel ray). A median, so the real objects standing on the table (absent from the render)
    do not bias it; 1 without a table pixel, clipped to :data:`GAIN_RANGE`."""
    have = sim_lin[table].mean(1)
    want = _linear(real[table])
    lit = have > 1e-4
    gain = np.ones(3)
    for c in range(3):
        if lit[:, c].any():
            gain[c] = np.median(want[lit[:, c], c] / have[lit[:, c], c])
    return np.clip(gain, *GAIN_RANGE)


class _CameraRig:
    """One camera the policy reads: its :class:`ViewRays` and the scene renderer of its margin view."""

    def __init__(self, spec, rays: ViewRays, device):
        self.rays = rays
        intr, self.lookup, self.near = rays.render_camera()
        self.spec = spec
        view = spec.with_updates(camera={**spec.camera.model_dump(), **intr, "fov_deg": None})
        self.renderer = SceneRenderer(view, intr["width"], intr["height"])
        self.hybrid = HybridRenderer(self.renderer, camera=rays.name, device=device)  # the object's arrays
        self.adv = self.hybrid.adv
        for k in range(len(spec.objects)):  # the recorded frame holds the real scene: only the object is added
            self.renderer.set_object_visible(k, k == self.adv)
        n_faces = len(self.hybrid.faces)
        self.optimised = np.ones(n_faces, bool) if self.hybrid.face_filter is None else self.hybrid.face_filter

    def _lighting(self, lighting):
        r = self.renderer
        if lighting is not None:
            r.set_lights(lighting)
        try:
            out = r.lighting(self.adv)
        finally:
            if lighting is not None:
                r.set_lights(self.spec.lighting)
        if out is None:
            raise RecordedAttackError(
                "scene: the adversarial object's material or lights are not ones deferred shading models "
                "(attack.render.deferred_shading), which compositing into recorded frames needs"
            )
        return out

    def _pixel_faces(self, candidates: np.ndarray, T_cam_obj: np.ndarray) -> np.ndarray:
        """``(H*W,)`` the face each view pixel shows, -1 for none: of the faces seen near the pixel
        (``candidates (H*W, m)``, -1 for none), the nearest one the ray through the pixel's centre
        passes through (the most inside of them where it grazes an edge), so the pixel's
        barycentrics lie on its own ray as a rasteriser's do."""
        out = np.full(len(candidates), -1, np.int64)
        rows = np.flatnonzero((candidates >= 0).any(1))
        if not rows.size:
            return out
        c = candidates[rows]  # (P, m)
        P, m = c.shape
        hr = self.hybrid
        verts = transform_points(T_cam_obj, hr.vertices)
        v, u = np.divmod(rows, self.rays.width)
        d = self.rays(u.astype(np.float64), v.astype(np.float64))  # (P, 3) the centre rays
        tri = verts[hr.faces[np.maximum(c, 0)]].reshape(-1, 3, 3)
        b = ray_barycentrics(tri, np.repeat(d, m, 0))
        depth = np.einsum("pk,pk->p", b, tri[:, :, 2]).reshape(P, m)
        inside = b.reshape(P, m, 3).min(-1)
        hit = (c >= 0) & (inside >= -1e-9) & (depth > 0)
        score = np.where(c >= 0, inside, -np.inf)
        pick = np.where(hit.any(1), np.where(hit, depth, np.inf).argmin(1), score.argmax(1))
        out[rows] = c[np.arange(P), pick]
        return out

    def capture(self, frame: np.ndarray, T_table_cam, T_table_tcp, T_table_obj, look: _Look, rng=None) -> Capture:
        """The :class:`attack.render.Capture` of the object at ``T_table_obj`` composited into
        ``frame`` (the policy's view, ``(H, W, 3)`` uint8) seen from ``T_table_cam`` with the gripper
        at ``T_table_tcp`` (all (4, 4), table frame); ``rng`` draws the noise."""
        rays, r = self.rays, self.renderer
        H, W = rays.height, rays.width
        r.set_state(np.repeat(np.asarray(T_table_obj, np.float64)[None], len(self.spec.objects), 0), T_table_tcp)
        out = r.render(T_table_cam, with_ids=True, with_color=True, with_depth=False)
        ok = self.lookup >= 0
        at = np.maximum(self.lookup, 0)
        ids = np.where(ok, out.ids.reshape(-1)[at], 0)
        face = np.where(ids >= FACE_BASE, ids - FACE_BASE, -1)
        hit = face >= 0
        opt = hit & self.optimised[np.maximum(face, 0)]
        fixed = hit & ~opt
        a_opt, a_fixed = opt.mean(1), fixed.mean(1)
        T_cam_table = invert_T(T_table_cam)
        T_cam_obj = T_cam_table @ T_table_obj
        near = np.where(self.near >= 0, out.ids.reshape(-1)[np.maximum(self.near, 0)], 0)
        near_face = np.where(near >= FACE_BASE, near - FACE_BASE, -1)
        near_face = np.where(self.optimised[np.maximum(near_face, 0)], near_face, -1)
        candidates = np.concatenate([np.where(opt, face, -1), np.where((a_opt > 0)[:, None], near_face, -1)], 1)
        face_px = self._pixel_faces(candidates, T_cam_obj).reshape(H, W)
        real = frame.reshape(-1, 3).astype(np.float64) / 255.0
        sim_lin = _linear(out.rgb.reshape(-1, 3)[at].astype(np.float64) / 255.0)  # (H*W, n, 3)
        gain = _brightness_gain(real, sim_lin, (ids == TABLE_ID).all(1))
        light = gain * look.gain
        hr = self.hybrid
        frags = rasterize_fragments(
            face_px,
            rays.K_view,
            T_cam_obj,
            hr.vertices,
            hr.faces,
            hr.uv,
            vertex_normals=hr.vertex_normals,
            lighting=self._lighting(look.lighting).in_frame(T_cam_table),
            device=hr.device,
            rays=rays,
        )
        P = frags.num_pixels
        noise = rng.normal(0.0, look.noise_std, (P, 3)) if look.noise_std > 0 and P and rng is not None else None
        frags = replace(
            frags, diffuse=frags.diffuse * light, specular=frags.specular * light, alpha=a_opt[frags.pix], noise=noise
        )
        under = real
        if fixed.any():  # the faces the attack leaves alone, as the scene's renderer draws them
            n_fixed = np.maximum(fixed.sum(1), 1)[:, None]
            c_fixed = ((sim_lin * fixed[..., None]).sum(1) / n_fixed * light) ** (1.0 / _GAMMA)
            rest = np.clip(1.0 - a_opt, 1e-12, None)[:, None]
            mixed = (a_fixed[:, None] * np.clip(c_fixed, 0, 1) + (1.0 - a_opt - a_fixed)[:, None] * real) / rest
            under = np.where((a_fixed > 0)[:, None] & (a_opt < 1)[:, None], mixed, real)
        i_frame = np.clip(np.rint(under * 255.0), 0, 255).astype(np.uint8).reshape(H, W, 3)
        adv_mask = (a_opt + a_fixed >= 0.5).reshape(H, W)
        return Capture(i_frame, frags, adv_mask, np.zeros((H, W), bool))

    def close(self) -> None:
        self.renderer.close()


# ----------------------------------------------------------------------------------- the source
@dataclass(frozen=True)
class _Slot:
    episode: str
    step: int  # the first step
    T_table_obj: np.ndarray
    p_adv: np.ndarray
    look: _Look


class RecordedFrames:
    """The attack's frames from a recording: see the module docstring (open loop; no simulator).

    Args:
        recording: the :class:`sim.recording.Recording`.
        spec: the scene (the adversarial object and its mesh, the placement region, lights, gripper,
            step limits; its adversarial mesh already swapped when the attack swaps it).
        cfg: the attack config (``num_envs``, ``rollout_steps``, ``schedule``, ``iterations``,
            ``light_randomization``, ``validation_every``, ``validation_episodes``, ``seed``).
        views: :func:`policy_views` of the policy.
        saliency_camera: the camera whose captures the frames' masks are of.
        device: where the pose tensors go and the shading runs.

    Every refusal (a camera the policy reads that the recording lacks, frames of a size the policy
    cannot read, an episode split that cannot hold out, no frame showing the object's region) is one
    :class:`RecordedAttackError` line naming the recording, raised before any renderer is built.
    """

    def __init__(self, recording: Recording, spec, cfg, views: dict, saliency_camera: str, device):
        self.recording, self.spec, self.cfg = recording, spec, cfg
        self.device = torch.device(device)
        where = str(recording.path)
        self.where = where
        missing = [c for c in views if c not in recording.cameras]
        if missing:
            raise RecordedAttackError(
                f"{where}: the policy reads camera {missing[0]!r}, which the recording does not have (it has "
                f"{', '.join(recording.cameras)})"
            )
        self.rays = {}
        for name, (size, preprocess) in views.items():
            try:
                self.rays[name] = ViewRays(recording.cameras[name], size, preprocess)
            except RecordedAttackError as err:
                raise RecordedAttackError(f"{where}: {err}") from None
        self.cameras = tuple(views)
        self.saliency_camera = saliency_camera
        validating = cfg.validation_every > 0
        self.train, self.held_out = split_episodes([e.id for e in recording.episodes], validating, where)
        self.adv = spec.object_index("adversarial")
        self._center_local = object_local_centers(spec)[self.adv]
        self._radius = self._bounding_radius(spec)
        self._poses = {}
        for e in recording.episodes:
            T_base_tcp = recording.poses(e.id).T_base_tcp
            self._poses[e.id] = (
                recording.T_table_base @ T_base_tcp,
                {c: invert_T(recording.T_table_cam(c, T_base_tcp)) for c in self.cameras},
            )
        region = self._region_points(spec)
        self._train_steps = self._steps_seeing(self.train, region)
        if not self._train_steps:
            raise RecordedAttackError(
                f"{where}: frames with no table visible: no frame of the training episodes shows the region where "
                f"the object is placed ({self._region_text(spec)}) to camera {' or '.join(self.cameras)}; check the "
                "recording's T_table_base and camera extrinsics, and the scene's region"
            )
        self._validation = self._validation_slots(region) if validating else []
        if validating and not self._validation:
            raise RecordedAttackError(
                f"{where}: frames with no table visible: no frame of the held-out episodes "
                f"({', '.join(self.held_out)}) shows the region where the object is placed ({self._region_text(spec)}) "
                f"to camera {' or '.join(self.cameras)}; record more episodes or set validation_every: 0"
            )
        with open(recording.path / MANIFEST_NAME, "rb") as f:
            self.manifest_sha256 = hashlib.sha256(f.read()).hexdigest()
        self.rigs: dict[str, _CameraRig] = {}
        try:
            for name in self.cameras:
                self.rigs[name] = _CameraRig(spec, self.rays[name], self.device)
        except BaseException:
            self.close()
            raise
        self.object_mesh = self.rigs[self.cameras[0]].renderer.object_mesh(self.adv)
        # The policy's views of recorded frames, kept (steps repeat across iterations) up to ~128 MiB.
        view_bytes = max(r.height * r.width * 3 for r in self.rays.values())
        self._view = lru_cache(maxsize=int(np.clip(_VIEW_CACHE_BYTES // view_bytes, 16, 4096)))(self._read_view)
        self._slots: list[_Slot] = []
        self._step = 0
        self._rng: np.random.Generator | None = None
        self._val_frames: list | None = None
        self._val_result: tuple | None = None

    @classmethod
    def open(cls, path, spec, cfg, policy, saliency_camera: str, device) -> "RecordedFrames":
        """:func:`sim.recording.read_recording` of ``path``, then the source for ``policy``."""
        return cls(read_recording(path), spec, cfg, policy_views(policy), saliency_camera, device)

    # ------------------------------------------------------------------ geometry
    @staticmethod
    def _bounding_radius(spec) -> float:
        o = spec.objects[spec.object_index("adversarial")]
        m = build_mesh(o.mesh, o.scale, **o.mesh_kwargs())
        c = (m.bounds[0] + m.bounds[1]) / 2.0
        return float(np.linalg.norm(np.asarray(m.vertices) - c, axis=-1).max())

    @staticmethod
    def _region_text(spec) -> str:
        (x0, x1), (y0, y1) = spec.init.region_x_m, spec.init.region_y_m
        return f"x {x0:g}..{x1:g} m, y {y0:g}..{y1:g} m, the scene's init.region_x_m and init.region_y_m"

    @staticmethod
    def _region_points(spec) -> np.ndarray:
        xs = np.linspace(*spec.init.region_x_m, _REGION_GRID)
        ys = np.linspace(*spec.init.region_y_m, _REGION_GRID)
        gx, gy = np.meshgrid(xs, ys)
        return np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], -1)

    def _in_view(self, episode: str, steps, points: np.ndarray, min_depth_m: float) -> np.ndarray:
        """``(S, N)`` bool: table-frame ``points (N, 3)`` in view of some camera the policy reads at
        ``steps (S,)`` of ``episode``, farther than ``min_depth_m`` along its axis."""
        steps = np.atleast_1d(steps)
        seen = np.zeros((len(steps), len(points)), bool)
        for name in self.cameras:
            p_cam = transform_points(self._poses[episode][1][name][steps], points)  # (S, N, 3)
            _, ok = self.rays[name].project(p_cam.reshape(-1, 3))
            seen |= ok.reshape(seen.shape) & (p_cam[..., 2] > min_depth_m)
        return seen

    def _steps_seeing(self, episodes, region) -> list[tuple[str, int]]:
        """The ``(episode, step)`` pairs at which some camera the policy reads sees a point of ``region``."""
        znear = self.spec.camera.znear_m
        out = []
        for e in episodes:
            seen = self._in_view(e, np.arange(len(self._poses[e][0])), region, znear).any(1)
            out += [(e, int(k)) for k in np.flatnonzero(seen)]
        return out

    def _sample_pose(self, episode: str, step: int, rng: np.random.Generator):
        """``(T_table_obj, p_adv)`` of an object pose in the region, in view and not too close, or None."""
        init, ep = self.spec.init, self.spec.episode
        p_tcp = self._poses[episode][0][step][:3, 3]
        for _ in range(_POSE_TRIES):
            xyy = (rng.uniform(*init.region_x_m), rng.uniform(*init.region_y_m), rng.uniform(-math.pi, math.pi))
            T = object_poses_world([xyy])[0]
            c = T[:3, :3] @ self._center_local + T[:3, 3]
            if np.linalg.norm(c - p_tcp) < 1.5 * ep.success_radius_m:
                continue
            if self._in_view(episode, step, c[None], self.spec.camera.znear_m + self._radius)[0, 0]:
                return T, c
        return None

    # ------------------------------------------------------------------ frames
    def _read_view(self, episode: str, step: int, camera: str) -> np.ndarray:
        """The policy's view of a recorded frame: ``(H, W, 3)`` uint8 (cached: frames repeat)."""
        img = self.recording.image(episode, step, camera)
        rays = self.rays[camera]
        if img.shape[:2] == (rays.height, rays.width):
            return img
        return policy_view(img, rays.height, rays.preprocess)

    def view(self, episode: str, step: int, camera: str) -> np.ndarray:
        """The policy's view of ``camera``'s recorded frame at ``step`` of ``episode``: ``(H, W, 3)`` uint8."""
        return self._view(episode, int(step), camera)

    def capture(self, episode: str, step: int, T_table_obj, camera: str | None = None, gripper: bool = True) -> Capture:
        """The object at ``T_table_obj`` (4, 4) composited into ``camera``'s (default: the saliency
        camera's) view of ``step`` of ``episode`` under the estimated light (no jitter, no noise);
        ``gripper=False`` leaves the scene's gripper out of the render (nothing stays in front)."""
        camera = self.saliency_camera if camera is None else camera
        T_table_tcp, T_cams = self._poses[episode]
        frame = self._view(episode, int(step), camera)
        T_table_cam = invert_T(T_cams[camera][step])
        tcp = T_table_tcp[step] if gripper else None
        return self.rigs[camera].capture(frame, T_table_cam, tcp, np.asarray(T_table_obj, np.float64), _NOMINAL)

    def _captures(self, slots: list[_Slot], offset: int, rng) -> dict:
        out = {name: [] for name in self.cameras}
        for s in slots:
            k = s.step + offset
            T_table_tcp = self._poses[s.episode][0][k]
            for name, rig in self.rigs.items():
                T_table_cam = invert_T(self._poses[s.episode][1][name][k])
                frame = self._view(s.episode, k, name)
                out[name].append(rig.capture(frame, T_table_cam, T_table_tcp, s.T_table_obj, s.look, rng))
        return out

    def _frames(self, slots: list[_Slot], offset: int, rng=None) -> Frames:
        views = self._captures(slots, offset, rng)
        T = np.stack([self._poses[s.episode][0][s.step + offset] for s in slots])
        p = np.stack([s.p_adv for s in slots])
        return Frames(
            views[self.saliency_camera],
            torch.from_numpy(T).to(self.device, torch.float32),
            torch.from_numpy(p).to(self.device, torch.float32),
            views if len(self.cameras) > 1 else None,
        )

    def _draw_look(self, rng: np.random.Generator) -> _Look:
        g = math.exp(rng.uniform(-math.log(GAIN_JITTER), math.log(GAIN_JITTER)))
        gain = g * (1.0 + rng.uniform(-TINT_JITTER, TINT_JITTER, 3))
        noise = float(rng.uniform(0.0, NOISE_MAX))
        lighting = None
        if self.cfg.light_randomization:
            lighting = sample_appearance(self.spec, Randomization(light="random"), rng).lighting
        return _Look(gain, noise, lighting)

    # ------------------------------------------------------------------ the FrameSource protocol
    def start(self, iteration: int, rng: np.random.Generator) -> None:
        """Draw this iteration's ``num_envs`` (step, object pose, look) slots (module docstring)."""
        cfg = self.cfg
        want = _CANDIDATES_PER_SLOT * cfg.num_envs
        cands: list[tuple[str, int, np.ndarray, np.ndarray]] = []
        for _ in range(64 * want):
            if len(cands) == want:
                break
            e, k = self._train_steps[rng.integers(len(self._train_steps))]
            pose = self._sample_pose(e, k, rng)
            if pose is not None:
                cands.append((e, k, *pose))
        if not cands:
            raise RecordedAttackError(
                f"{self.where}: no object pose in the scene's region is in view of the training frames (tried "
                f"{64 * want} draws); check the recording's extrinsics and the scene's region"
            )
        r = np.array([np.linalg.norm(self._poses[e][0][k][:3, 3] - c) for e, k, _, c in cands])
        params = stage_params(cfg.schedule, iteration, cfg.iterations)
        idx = sample_configs(r, params, self.spec.init.r_range_m, cfg.num_envs, rng)
        self._slots = [_Slot(cands[i][0], cands[i][1], cands[i][2], cands[i][3], self._draw_look(rng)) for i in idx]
        self._step = 0
        self._rng = rng

    def next(self) -> Frames | None:
        if self._step >= self.cfg.rollout_steps:
            return None
        active = [s for s in self._slots if s.step + self._step < len(self._poses[s.episode][0])]
        if not active:
            return None
        return self._frames(active, self._step, self._rng)

    def advance(self, actions: np.ndarray) -> None:
        """Open loop: the next batch is the recorded episodes' next step, whatever ``actions`` say."""
        self._step += 1

    # ------------------------------------------------------------------ validation
    def _validation_slots(self, region) -> list[_Slot]:
        steps = self._steps_seeing(self.held_out, region)
        if not steps:
            return []
        n = min(self.cfg.validation_episodes, len(steps))
        picks = np.unique(np.rint(np.linspace(0, len(steps) - 1, n)).astype(int))
        rng = np.random.default_rng(np.random.SeedSequence([int(self.cfg.seed), 0x5EC0DED]))
        slots = []
        for i in picks:
            e, k = steps[i]
            pose = self._sample_pose(e, k, rng)
            if pose is not None:
                slots.append(_Slot(e, k, pose[0], pose[1], _NOMINAL))
        return slots

    def validate(self, run) -> dict:
        """Score ``run``'s current texture on the held-out frames (module docstring): ``{"t_asr": the
        toward fraction (the key the best-texture rule reads), "toward", "dist_m": mean distance from
        the first action's next position to the object, "pose_loss", "episodes": held-out episodes,
        "frames", "seconds"}``. Uses no training RNG."""
        t0 = time.perf_counter()
        key = (run.state.iteration, texture_to_uint8(run.state.texture).tobytes())
        if self._val_result is not None and self._val_result[0] == key:
            return self._val_result[1]
        if self._val_frames is None:
            B = self.cfg.num_envs
            self._val_frames = [
                self._frames(self._validation[i : i + B], 0) for i in range(0, len(self._validation), B)
            ]
        tex = torch.from_numpy(texture_to_uint8(run.state.texture)).permute(2, 0, 1).to(run.device, torch.float32)
        tex = tex / 255.0
        ep = self.spec.episode
        lp_all, dist_all, toward_all = [], [], []
        with torch.no_grad():
            for frames in self._val_frames:
                views = frames.views if frames.views is not None else {self.cameras[0]: frames.captures}
                imgs = run.render_views(views, tex)
                T = frames.T_world_tcp
                a = run.next_delta(run.call_policy(imgs, run.policy_state(T)), T)
                lp, parts = pose_loss(T, a, frames.p_adv, ep.max_step_m, ep.max_step_rad, run.cfg.lambda_dist)
                lp_all.append(lp)
                dist_all.append(parts["dist"])
                toward_all.append(points_toward(T, a, frames.p_adv, ep.max_step_m))
        toward = float(torch.cat(toward_all).float().mean())
        res = {
            "t_asr": toward,
            "toward": toward,
            "dist_m": float(torch.cat(dist_all).mean()),
            "pose_loss": float(torch.cat(lp_all).mean()),
            "episodes": len(self.held_out),
            "frames": len(self._validation),
            "seconds": time.perf_counter() - t0,
        }
        self._val_result = (key, res)
        return res

    def probe_pose_loss(self, run) -> float:
        """The mean pose loss over the held-out frames under the current texture (:meth:`validate`'s)."""
        return self.validate(run)["pose_loss"] if self._validation else float("nan")

    # ------------------------------------------------------------------ outputs
    def examples(self, n: int = 8) -> tuple[Frames, list[str]]:
        """Up to ``n`` consecutive recorded steps of one episode with one object pose (the first
        held-out frame's, else a training frame's drawn from the run's seed), nominal light: the
        frames the run's figures show; and a label per frame."""
        if self._validation:
            s = self._validation[0]
        else:
            rng = np.random.default_rng(np.random.SeedSequence([int(self.cfg.seed), 0xE8A4]))
            s = None
            for e, k in self._train_steps:
                pose = self._sample_pose(e, k, rng)
                if pose is not None:
                    s = _Slot(e, k, pose[0], pose[1], _NOMINAL)
                    break
            if s is None:
                raise RecordedAttackError(f"{self.where}: no training frame shows an object pose to illustrate")
        last = min(len(self._poses[s.episode][0]), s.step + n)
        slots = [replace(s, step=k) for k in range(s.step, last)]
        return self._frames(slots, 0), [f"{s.episode}, step {k}" for k in range(s.step, last)]

    def provenance(self) -> dict:
        """What the run was optimised and validated on (``run.json``'s ``recordings``)."""
        return {
            "path": str(self.recording.path),
            "manifest_sha256": self.manifest_sha256,
            "training_episodes": list(self.train),
            "held_out_episodes": list(self.held_out),
            "cameras": list(self.cameras),
            "validation_frames": [[s.episode, s.step] for s in self._validation],
            "validation_measure": VALIDATION_MEASURE,
        }

    def close(self) -> None:
        for rig in getattr(self, "rigs", {}).values():
            rig.close()
        self.rigs = {}
