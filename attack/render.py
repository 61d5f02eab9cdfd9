"""Hybrid rendering: a differentiable texture path composited into pyrender's image.

Pipeline, by composition (as in pytorch3d):

1. the standard renderer gives ``I_sim`` plus an id pass (see :mod:`sim.render`);
2. :func:`rasterize_fragments` turns the id pass into a frozen :class:`Fragments` record for the
   adversarial object's visible pixels: face ids, barycentrics (exact ray-triangle intersection),
   UVs, UV screen derivatives (for mip-level selection) and the shading pyrender applies there
   (:func:`deferred_shading`: pyrender's BRDF evaluated in torch from the fragment's position and
   interpolated normal, the scene's lights and the material; no extra render pass);
3. a swappable texture sampler (:func:`sample_bilinear`, :func:`sample_trilinear`) reads the
   texture at those UVs with ``grid_sample`` (the only differentiable step);
4. :func:`shade` applies pyrender's lighting model and color space, and :func:`composite` forms
   ``I_adv = (1 - M) * I_sim + M * I_diff``.

pyrender's shader (``mesh.frag``, metallic-roughness with metallic 0), which :func:`shade` mirrors:
the texture is decoded with the exact sRGB curve, multiplied by the diffuse+ambient light ``D`` and
added to the albedo-independent specular term ``S``, clamped, then encoded with a 2.2 power.
:func:`deferred_shading` computes ``D`` and ``S`` per fragment. The older measurement (still
available as ``HybridRenderer(shading="passes")``, and used automatically for a scene the deferred
model does not describe) renders the object with a grey albedo ``a`` (``(a D + S)^(1/2.2)``) and a
black one (``S^(1/2.2)``) and solves for both per pixel from the 8-bit frames.

Texture convention: ``texture: (3, Ht, Wt)`` float sRGB in [0, 1], row 0 = top of the image;
``uv`` follows trimesh/OpenGL (v = 0 is the bottom row).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from sim.geometry import invert_T
from sim.spec import WRIST

__all__ = [
    "Fragments",
    "rasterize_fragments",
    "ray_barycentrics",
    "deferred_shading",
    "srgb_to_linear",
    "sample_bilinear",
    "sample_trilinear",
    "SAMPLERS",
    "shade",
    "composite",
    "mip_pyramid",
    "Capture",
    "HybridRenderer",
    "render_adversarial",
    "render_adversarial_batch",
    "composite_batch",
]

_GAMMA = 2.2


@dataclass(frozen=True)
class Fragments:
    """Per-pixel surface record of one frame's adversarial object (P visible pixels).

    pix: (P,) long flat pixel indices into the H x W image; face: (P,) long face ids;
    bary: (P, 3) barycentrics; uv: (P, 2); duv: (P, 2, 2) d(uv)/d(x, y) per pixel (rows: u, v);
    diffuse: (P, 3) linear light multiplying the albedo; specular: (P, 3) linear additive light;
    height, width: image size in px.

    Composited into a frame that is not a render of the scene (a recorded camera frame,
    :mod:`attack.recorded`), a pixel may be only partly covered and the frame carries sensor noise:
    ``alpha`` (P,) in (0, 1] is the object's coverage of each pixel (``I = (1 - alpha) * I_frame +
    alpha * colour``) and ``noise`` (P, 3) is added to the shaded colour before that. None (the
    simulator's frames): whole pixels, no noise.
    """

    pix: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    uv: np.ndarray
    duv: np.ndarray
    diffuse: np.ndarray
    specular: np.ndarray
    height: int
    width: int
    alpha: np.ndarray | None = None
    noise: np.ndarray | None = None

    @property
    def num_pixels(self) -> int:
        return int(self.pix.shape[0])

    def mask(self) -> np.ndarray:
        """(H, W) bool visible mask ``M``."""
        m = np.zeros(self.height * self.width, bool)
        m[self.pix] = True
        return m.reshape(self.height, self.width)


# Albedo of the shading pass that measures the diffuse term. The render is affine in the albedo, so
# any value works in exact arithmetic; 1.0 saturates the 8-bit frame where the light is bright
# (top views under the ceiling light: up to 28% of the object's pixels at phi = 5 deg, with errors of
# ~7/255 there), so a mid grey keeps the pass unclipped and the division restores the scale.
SHADING_ALBEDO = 0.5


def _ray_dirs(K: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Camera-frame ray directions (P, 3) through pixel centres (u, v) (OpenCV convention)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    return np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1)


def _barycentric(tri: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Barycentrics (P, 3) of rays from the origin along ``d: (P, 3)`` hitting the planes of
    triangles ``tri: (P, 3, 3)`` (Moller-Trumbore without the inside test: the id pass already
    says which face the pixel shows; grazing rays parallel to the plane return the centroid)."""
    v0, v1, v2 = tri[:, 0], tri[:, 1], tri[:, 2]
    e1, e2 = v1 - v0, v2 - v0
    p = np.cross(d, e2)
    det = np.einsum("pi,pi->p", e1, p)
    ok = np.abs(det) > 1e-14
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = -v0
    b1 = np.einsum("pi,pi->p", s, p) * inv
    q = np.cross(s, e1)
    b2 = np.einsum("pi,pi->p", d, q) * inv
    bary = np.stack([1.0 - b1 - b2, b1, b2], -1)
    bary = np.where(ok[:, None], bary, 1.0 / 3.0)
    return bary


def ray_barycentrics(tri: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Barycentrics ``(P, 3)`` where rays from the camera's origin along ``d (P, 3)`` meet the planes
    of triangles ``tri (P, 3, 3)`` (camera frame), unclamped: a ray passes through its triangle
    where all three are >= 0. For a caller that must pick, among faces seen near a pixel, the one
    the pixel's own ray meets (:mod:`attack.recorded`)."""
    return _barycentric(tri, d)


def _clamp_bary(bary: np.ndarray) -> np.ndarray:
    # Pixel centres on a silhouette can fall a hair outside their face (rasterisation rules);
    # project back onto the triangle so UVs stay inside the face's chart.
    b = np.clip(bary, 0.0, None)
    return b / np.maximum(b.sum(-1, keepdims=True), 1e-12)


def rasterize_fragments(
    face_ids: np.ndarray,
    K: np.ndarray,
    T_cam_object: np.ndarray,
    vertices: np.ndarray,
    faces: np.ndarray,
    uv: np.ndarray,
    white_rgb: np.ndarray | None = None,
    black_rgb: np.ndarray | None = None,
    face_filter: np.ndarray | None = None,
    *,
    vertex_normals: np.ndarray | None = None,
    lighting=None,
    device: torch.device | str = "cpu",
    rays=None,
) -> Fragments:
    """Build :class:`Fragments` from an id pass and either two shading passes or the lights.

    Args:
        face_ids: (H, W) int face index of the object per pixel, -1 elsewhere.
        K: (3, 3) intrinsics (OpenCV). T_cam_object: (4, 4) object pose in the camera frame.
        vertices: (V, 3) m object-frame vertices; faces: (F, 3); uv: (V, 2).
        white_rgb, black_rgb: (H, W, 3) uint8 renders with the object's albedo
            ``SHADING_ALBEDO`` grey / black (the measured shading).
        face_filter: optional (F,) bool; faces marked False are left to ``I_sim`` (e.g. the 2D
            patch's sides, which are not optimised).
        vertex_normals: (V, 3) object-frame normals as the renderer draws them, and
        lighting: a :class:`sim.render.SceneLighting` in the *camera* frame: without the two
            passes, the shading is computed by :func:`deferred_shading` on ``device``.
        rays: ``rays(u, v) -> (P, 3)`` camera-frame ray directions through the image points
            ``(u, v)`` px (pixel centres and their right and lower neighbours); None: the pinhole
            ``K`` (:func:`_ray_dirs`). A camera with lens distortion, or a frame cropped and resized
            after capture, passes its own (:class:`attack.recorded.ViewRays`).
    """
    H, W = face_ids.shape
    flat = face_ids.reshape(-1)
    pix = np.flatnonzero(flat >= 0)
    face = flat[pix].astype(np.int64)
    if face_filter is not None:
        keep = face_filter[face]
        pix, face = pix[keep], face[keep]
    v_img, u_img = np.divmod(pix, W)
    R, t = T_cam_object[:3, :3], T_cam_object[:3, 3]
    verts_cam = vertices @ R.T + t
    tri = verts_cam[faces[face]]  # (P, 3, 3)
    tri_uv = uv[faces[face]]  # (P, 3, 2)
    u_img = u_img.astype(np.float64)
    v_img = v_img.astype(np.float64)

    def uv_at(du: float, dv: float) -> np.ndarray:
        d = _ray_dirs(K, u_img + du, v_img + dv) if rays is None else rays(u_img + du, v_img + dv)
        b = _barycentric(tri, d)
        return np.einsum("pk,pkc->pc", b, tri_uv), b

    # Screen derivatives by intersecting the neighbouring pixels' rays with the same face plane
    # (what a GPU's per-quad differences approximate), before clamping to the triangle.
    uv_x, _ = uv_at(1.0, 0.0)
    uv_y, _ = uv_at(0.0, 1.0)
    uv0_raw, b0 = uv_at(0.0, 0.0)
    bary = _clamp_bary(b0)
    uv_pix = np.einsum("pk,pkc->pc", bary, tri_uv)
    duv = np.stack([uv_x - uv0_raw, uv_y - uv0_raw], -1)  # (P, 2 [u, v], 2 [x, y])

    if white_rgb is not None and black_rgb is not None:
        w = (white_rgb.reshape(-1, 3)[pix].astype(np.float64) / 255.0) ** _GAMMA
        s = (black_rgb.reshape(-1, 3)[pix].astype(np.float64) / 255.0) ** _GAMMA
        diffuse = np.clip(w - s, 0.0, None) / SHADING_ALBEDO
        return Fragments(pix, face, bary, uv_pix, duv, diffuse, s, H, W)
    if vertex_normals is None or lighting is None:
        raise ValueError("rasterize_fragments: give white_rgb and black_rgb, or vertex_normals and lighting")
    # The fragment's varyings as the rasteriser interpolates them (perspective-correct, at the
    # pixel centre): position on the face plane, vertex normals (object frame -> camera frame).
    points = np.einsum("pk,pkc->pc", bary, tri)
    normals = np.einsum("pk,pkc->pc", bary, (vertex_normals @ R.T)[faces[face]])
    diffuse, specular = deferred_shading(points, normals, lighting, device=device)
    return Fragments(pix, face, bary, uv_pix, duv, diffuse.cpu().numpy(), specular.cpu().numpy(), H, W)


_MIN_ROUGHNESS = 0.04  # mesh.frag's min_roughness, also the dielectric F0


def deferred_shading(
    points, normals, lighting, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float64
) -> tuple[torch.Tensor, torch.Tensor]:
    """pyrender's ``mesh.frag`` lighting for fragments of a metallic-0 material, in torch.

    Args:
        points: (P, 3) fragment positions; normals: (P, 3) interpolated vertex normals (any
            length: normalised here, as the shader does); both in the frame of ``lighting`` (a
            :class:`sim.render.SceneLighting`) with the camera at its origin.
        device, dtype: where and in what precision to compute.

    Returns ``(diffuse, specular)``, each ``(P, 3)`` linear, with the shader's output before its
    clamp and 1/2.2 power equal to ``albedo_linear * diffuse + specular``: per light, the
    Cook-Torrance terms of ``compute_brdf`` (Schlick Fresnel with F0 = 0.04, Smith-Schlick G with
    k = (r + 1)^2 / 8, GGX D with a = r^2, the shader's clamps and its ``+ 0.001``), then ambient
    (times the albedo) and the emissive term. Degenerate inputs stay finite where GLSL is
    undefined: a zero normal or ``l = -v`` normalise to zero (the clamps then apply), a point light
    at the fragment counts as 1e-12 m^2 away.
    """

    def t(x):
        return torch.as_tensor(np.asarray(x), dtype=dtype, device=device)

    p, n = t(points).reshape(-1, 3), t(normals).reshape(-1, 3)
    P = p.shape[0]
    n = F.normalize(n, dim=-1, eps=1e-30)
    v = F.normalize(-p, dim=-1, eps=1e-30)  # towards the camera at the origin
    ls, rads = [], []
    L = lighting
    if len(L.dir_dir):
        ls.append(F.normalize(-t(L.dir_dir), dim=-1, eps=1e-30)[None].expand(P, -1, -1))
        rads.append(t(L.dir_rad)[None].expand(P, -1, -1))
    for pos, rad, spot in (
        (L.point_pos, L.point_rad, None),
        (L.spot_pos, L.spot_rad, (L.spot_dir, L.spot_scale, L.spot_offset)),
    ):
        if not len(pos):
            continue
        d = t(pos)[None] - p[:, None]  # (P, N, 3) fragment -> light
        dist2 = (d * d).sum(-1, keepdim=True).clamp_min(1e-12)
        l = F.normalize(d, dim=-1, eps=1e-30)
        att = 1.0 / dist2
        if spot is not None:
            sd, scale, offset = (t(x) for x in spot)
            cd = (sd[None] * -l).sum(-1, keepdim=True).clamp(0.0, 1.0)
            a = (cd * scale[None, :, None] + offset[None, :, None]).clamp(0.0, 1.0)
            att = att * a * a
        ls.append(l)
        rads.append(att * t(rad)[None])
    diffuse = t(L.ambient).expand(P, 3).clone()
    specular = t(L.emissive).expand(P, 3).clone()
    if not ls:
        return diffuse, specular
    l, rad = torch.cat(ls, 1), torch.cat(rads, 1)  # (P, N, 3)
    vv = v[:, None]
    h = F.normalize(l + vv, dim=-1, eps=1e-30)
    nl = (n[:, None] * l).sum(-1).clamp(0.001, 1.0)
    nv = (n * v).sum(-1).abs().clamp(0.001, 1.0)[:, None]
    nh = (n[:, None] * h).sum(-1).clamp(0.0, 1.0)
    vh = (vv * h).sum(-1).clamp(0.0, 1.0)
    f0 = _MIN_ROUGHNESS
    fres = f0 + (1.0 - f0) * (1.0 - vh).clamp(0.0, 1.0) ** 5
    r = float(L.roughness)
    k = (r + 1.0) ** 2 / 8.0
    g = nv / (nv * (1.0 - k) + k) * (nl / (nl * (1.0 - k) + k))
    a2 = (r * r) ** 2
    denom = nh * nh * (a2 - 1.0) + 1.0
    dist = a2 / (math.pi * denom * denom)
    kd = nl * (1.0 - fres) * (1.0 - _MIN_ROUGHNESS) / math.pi  # c_diff = albedo * (1 - 0.04)
    ks = nl * fres * g * dist / (4.0 * nl * nv + 0.001)
    diffuse = diffuse + (kd[..., None] * rad).sum(1)
    specular = specular + (ks[..., None] * rad).sum(1)
    return diffuse, specular


def srgb_to_linear(c: torch.Tensor) -> torch.Tensor:
    """The exact sRGB decoding curve pyrender applies to base-color textures."""
    c = c.clamp(0.0, 1.0)
    return torch.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055).clamp_min(1e-12) ** 2.4)


def _to_grid(uv: torch.Tensor) -> torch.Tensor:
    # grid_sample's y runs from the top row (-1) to the bottom (+1); uv's v runs bottom-up.
    return torch.stack([2.0 * uv[:, 0] - 1.0, 1.0 - 2.0 * uv[:, 1]], -1).view(1, 1, -1, 2)


def sample_bilinear(texture: torch.Tensor, uv: torch.Tensor, duv: torch.Tensor | None = None) -> torch.Tensor:
    """Bilinear texture lookup: ``texture (3, Ht, Wt)``, ``uv (P, 2)`` -> ``(P, 3)``.

    Clamp-to-edge addressing, as the renderer's object textures use.
    """
    out = F.grid_sample(
        texture[None], _to_grid(uv).to(texture.dtype), mode="bilinear", padding_mode="border", align_corners=False
    )
    return out[0, :, 0, :].T


def mip_pyramid(texture: torch.Tensor) -> list[torch.Tensor]:
    """Mip levels of ``texture (3, Ht, Wt)`` down to 1 px: 2x2 box filter, as glGenerateMipmap."""
    levels = [texture]
    t = texture
    while t.shape[-1] > 1 or t.shape[-2] > 1:
        h, w = max(1, t.shape[-2] // 2), max(1, t.shape[-1] // 2)
        t = F.adaptive_avg_pool2d(t[None], (h, w))[0]
        levels.append(t)
    return levels


def mip_level(duv: torch.Tensor, tex_hw: tuple[int, int]) -> torch.Tensor:
    """OpenGL's level of detail ``lambda = log2(rho)`` per pixel from ``duv (P, 2, 2)``."""
    h, w = tex_hw
    scale = torch.tensor([w, h], dtype=duv.dtype, device=duv.device)[:, None]
    d = duv * scale  # texels per pixel step
    rho = torch.maximum(d[:, :, 0].norm(dim=-1), d[:, :, 1].norm(dim=-1))
    return torch.log2(rho.clamp_min(1e-8))


def sample_trilinear(texture: torch.Tensor, uv: torch.Tensor, duv: torch.Tensor | None = None) -> torch.Tensor:
    """Mip-mapped (trilinear) lookup, as ``GL_LINEAR_MIPMAP_LINEAR``: ``(P, 3)``.

    Without ``duv`` it falls back to bilinear (level 0).
    """
    if duv is None:
        return sample_bilinear(texture, uv)
    levels = mip_pyramid(texture)
    top = len(levels) - 1
    lam = mip_level(duv, texture.shape[-2:]).clamp(0.0, top)
    lo = lam.floor().long()
    hi = (lo + 1).clamp(max=top)
    frac = (lam - lo.to(lam.dtype)).to(texture.dtype)
    out = torch.zeros(uv.shape[0], 3, dtype=texture.dtype, device=texture.device)
    for k in torch.unique(torch.cat([lo, hi])).tolist():
        # Weight of level k: (1 - frac) as the finer level, frac as the coarser one; at the top
        # level lo == hi and the two add up to 1.
        weight = (1 - frac) * (lo == k) + frac * (hi == k)
        idx = torch.nonzero(weight > 0).squeeze(1)
        if idx.numel():
            out = out.index_add(0, idx, weight[idx, None] * sample_bilinear(levels[k], uv[idx]))
    return out


SAMPLERS = {"bilinear": sample_bilinear, "trilinear": sample_trilinear}


def shade(albedo_srgb: torch.Tensor, diffuse: torch.Tensor, specular: torch.Tensor) -> torch.Tensor:
    """pyrender's output color (P, 3) in [0, 1] for sampled texture colors ``albedo_srgb (P, 3)``."""
    lin = srgb_to_linear(albedo_srgb) * diffuse + specular
    # clamp_min keeps the gradient of x^(1/2.2) finite at x = 0 (black texels, unlit pixels).
    return lin.clamp(0.0, 1.0).clamp_min(1e-6) ** (1.0 / _GAMMA)


def composite(i_sim: torch.Tensor, pix: torch.Tensor, colors: torch.Tensor) -> torch.Tensor:
    """``I_adv = (1 - M) * I_sim + M * I_diff`` for one image.

    i_sim: (3, H, W) float in [0, 1]; pix: (P,) flat pixel indices of ``M``; colors: (P, 3).
    Returns (3, H, W); gradients flow only into ``colors``.
    """
    c, h, w = i_sim.shape
    flat = i_sim.reshape(c, h * w)
    out = flat.index_put((torch.arange(c, device=pix.device)[:, None], pix[None, :]), colors.T.to(flat.dtype))
    return out.reshape(c, h, w)


@dataclass(frozen=True)
class Capture:
    """Everything the attack needs from one standard-renderer frame.

    i_sim: (H, W, 3) uint8 standard render (adversarial object in its benign look);
    fragments: the adversarial object's visible, optimisable pixels;
    adv_mask, goal_mask: (H, W) bool visible masks (for the saliency loss).
    """

    i_sim: np.ndarray
    fragments: Fragments
    adv_mask: np.ndarray
    goal_mask: np.ndarray


class HybridRenderer:
    """Wraps a :class:`sim.render.SceneRenderer` to capture :class:`Capture` records.

    Each frame is two pyrender passes, both read by the frame's consumers: colour (``I_sim``) and
    ids (masks, face ids). The adversarial object's shading is computed by
    :func:`deferred_shading` from the scene's current lights (:meth:`sim.render.SceneRenderer.lighting`).

    ``shading="passes"`` measures it instead, as before: white- (grey) and black-albedo looks of
    the object are registered and rendered as two more passes per frame, read only under the id
    pass's mask, so with ``isolate_shading`` they draw that object alone (pixel-exact, see
    :meth:`sim.render.SceneRenderer.render`). The deferred path falls back to the passes for a
    frame whose lighting or material it does not model (``lighting`` returns ``None``).
    ``device``: where the deferred shading runs (the fragments are stored as numpy arrays).
    ``camera``: the camera ``renderer`` renders (the wrist camera, or a scene camera whose renderer
    is ``env.renderers[camera]``); a policy reading several cameras has one HybridRenderer each.
    """

    def __init__(
        self,
        renderer,
        face_filter: np.ndarray | None = None,
        isolate_shading: bool = True,
        shading: str = "deferred",
        device: torch.device | str = "cpu",
        camera: str = WRIST,
    ):
        if shading not in ("deferred", "passes"):
            raise ValueError(f"HybridRenderer: shading must be 'deferred' or 'passes', not {shading!r}")
        self.renderer = renderer
        self.camera = camera
        self.isolate_shading = bool(isolate_shading)
        self.shading = shading
        self.device = device
        self.adv = renderer.face_coded
        self.goal = renderer.spec.object_index("goal")
        mesh = renderer.object_mesh(self.adv)
        self.vertices = np.asarray(mesh.vertices, dtype=np.float64)
        self.faces = np.asarray(mesh.faces, dtype=np.int64)
        # The normals the colour mesh is drawn with (float32 vertex attributes).
        self.vertex_normals = np.asarray(mesh.vertex_normals, dtype=np.float32).astype(np.float64)
        uv = getattr(mesh.visual, "uv", None)
        if uv is None:
            raise ValueError(f"adversarial mesh {mesh.metadata.get('name', '?')} has no UVs")
        self.uv = np.asarray(uv, dtype=np.float64)
        if face_filter is None:
            face_filter = mesh.metadata.get("optimizable_faces")
        self.face_filter = None if face_filter is None else np.asarray(face_filter, bool)
        self._variants = False
        if shading == "passes":
            self._add_shading_variants()

    def _add_shading_variants(self) -> None:
        if not self._variants:
            self.renderer.add_variant(self.adv, "white", None, (SHADING_ALBEDO,) * 3)
            self.renderer.add_variant(self.adv, "black", None, (0.0, 0.0, 0.0))
            self._variants = True

    def capture(self, world, T_world_cam: np.ndarray | None = None) -> Capture:
        """Render ``world`` (a :class:`sim.world.SimWorld` sharing this renderer) through this
        renderer's camera, at ``T_world_cam`` (default: the camera's pose in ``world``)."""

        world.prepare(self.renderer)  # a scene camera's renderer is not the world's own
        T_world_cam = world.camera_pose(self.camera) if T_world_cam is None else T_world_cam
        r = self.renderer
        out = r.render(T_world_cam, with_ids=True, with_depth=False)  # nothing here reads depth
        adv_mask = out.object_mask(self.adv)
        T_cam_world = invert_T(T_world_cam)
        T_cam_obj = T_cam_world @ world.T_world_objects[self.adv]
        geometry = (out.face_ids, r.K, T_cam_obj, self.vertices, self.faces, self.uv)
        lighting = r.lighting(self.adv) if self.shading == "deferred" else None
        if lighting is not None:
            frags = rasterize_fragments(
                *geometry,
                face_filter=self.face_filter,
                vertex_normals=self.vertex_normals,
                lighting=lighting.in_frame(T_cam_world),
                device=self.device,
            )
        else:
            if adv_mask.any():
                self._add_shading_variants()
                iso = self.adv if self.isolate_shading else None
                white = r.render(T_world_cam, with_ids=False, variants={self.adv: "white"}, isolate=iso).rgb
                black = r.render(T_world_cam, with_ids=False, variants={self.adv: "black"}, isolate=iso).rgb
            else:  # nothing to shade: skip two passes
                white = black = out.rgb
            frags = rasterize_fragments(*geometry, white, black, self.face_filter)
        return Capture(out.rgb, frags, adv_mask, out.object_mask(self.goal))


def render_adversarial_batch(
    captures: list[Capture],
    texture: torch.Tensor,
    sampler: str = "trilinear",
    color_transform: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> torch.Tensor:
    """``I_adv: (B, 3, H, W)`` float in [0, 1] for ``B`` captures of one size (differentiable in
    ``texture (3, Ht, Wt)``).

    Batch-first: the B frames' fragments are concatenated, so the texture is sampled (and its mip
    pyramid built) once, shaded once and composited by one scatter, instead of once per frame.
    Every pixel is computed independently, so the result equals the frame-by-frame one up to float
    rounding (vectorised kernels round a tensor's tail differently: 1 ulp at a few pixels).

    color_transform: optional per-channel ``(gain (3,), bias (3,))`` applied to the sampled texture
    colors, modelling printer/camera color error (the print-aware option).
    """
    if not captures:
        raise ValueError("render_adversarial_batch: no captures")
    device, dtype = texture.device, texture.dtype
    sizes = {c.i_sim.shape for c in captures}
    if len(sizes) != 1:
        raise ValueError(f"render_adversarial_batch: frames of different sizes {sorted(sizes)}")
    i_sim = (
        torch.from_numpy(np.stack([c.i_sim for c in captures])).to(device=device, dtype=dtype).permute(0, 3, 1, 2)
        / 255.0
    )
    frags = [c.fragments for c in captures]
    counts = [f.num_pixels for f in frags]
    if sum(counts) == 0:
        return i_sim
    cat = lambda name: torch.from_numpy(np.concatenate([getattr(f, name) for f in frags])).to(device)  # noqa: E731
    uv, duv = cat("uv").to(dtype), cat("duv").to(dtype)
    albedo = SAMPLERS[sampler](texture, uv, duv)
    if color_transform is not None:
        gain, bias = color_transform
        albedo = (albedo * gain + bias).clamp(0.0, 1.0)
    colors = shade(albedo, cat("diffuse").to(dtype), cat("specular").to(dtype))
    frame = torch.repeat_interleave(torch.arange(len(frags), device=device), torch.tensor(counts, device=device))
    pix = cat("pix")
    if any(f.alpha is not None or f.noise is not None for f in frags):
        colors = _over_frame(i_sim, frame, pix, colors, frags)
    return composite_batch(i_sim, frame, pix, colors)


def _over_frame(i_sim, frame, pix, colors, frags) -> torch.Tensor:
    """``colors (P, 3)`` with each fragment's sensor ``noise`` added and laid over its frame's own
    pixel by its coverage ``alpha`` (:class:`Fragments`; a frame without them: whole, noiseless)."""
    dtype, device = colors.dtype, colors.device

    def stacked(name, fill, shape):
        parts = [
            getattr(f, name) if getattr(f, name) is not None else np.full((f.num_pixels, *shape), fill) for f in frags
        ]
        return torch.from_numpy(np.concatenate(parts).astype(np.float64)).to(device, dtype)

    colors = (colors + stacked("noise", 0.0, (3,))).clamp(0.0, 1.0)
    a = stacked("alpha", 1.0, ())[:, None]
    b, c, h, w = i_sim.shape
    under = i_sim.reshape(b, c, h * w)[frame, :, pix]  # (P, 3) the frame's pixel under each fragment
    return a * colors + (1.0 - a) * under


def composite_batch(i_sim: torch.Tensor, frame: torch.Tensor, pix: torch.Tensor, colors: torch.Tensor) -> torch.Tensor:
    """:func:`composite` for a batch: ``i_sim (B, 3, H, W)``, pixel ``p`` of frame ``frame[p]`` at
    flat index ``pix[p]`` takes ``colors[p] (3,)``. Returns ``(B, 3, H, W)``."""
    b, c, h, w = i_sim.shape
    flat = i_sim.reshape(b, c, h * w)
    ch = torch.arange(c, device=pix.device)
    out = flat.index_put((frame[None, :], ch[:, None], pix[None, :]), colors.T.to(flat.dtype))
    return out.reshape(b, c, h, w)


def render_adversarial(
    capture: Capture,
    texture: torch.Tensor,
    sampler: str = "trilinear",
    color_transform: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> torch.Tensor:
    """``I_adv: (3, H, W)`` of one capture: :func:`render_adversarial_batch` of one frame."""
    return render_adversarial_batch([capture], texture, sampler, color_transform)[0]
