"""Procedural textures for the built-in assets, generated in code (nothing is downloaded).

Two kinds:

* Surface shaders ``shader(points, normals, tags) -> rgb``: colour as a function of the 3D point
  on the object (metres, object frame), the face normal and an integer per-face tag (the part of
  a composite mesh). :func:`bake_texture` turns a shader into a texture image for any UV layout,
  so the look is independent of how the atlas is packed.
* Image-space tiles (:func:`wood_texture`, :func:`plain_texture`), used with repeat wrap.

UV convention (trimesh / OpenGL): ``(u, v) = (0, 0)`` is the bottom-left of the image, so image
row ``r`` of an ``S``-pixel image spans ``v`` in ``[1 - (r + 1) / S, 1 - r / S]``.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from PIL import Image, ImageDraw

__all__ = [
    "Shader",
    "cross2",
    "rasterize_uv",
    "bake_texture",
    "bake_vertex_values",
    "finish_bake",
    "sample_texture",
    "soup_can_shader",
    "mustard_shader",
    "cube_shader",
    "cylinder_shader",
    "duck_shader",
    "dog_shader",
    "patch_shader",
    "wood_texture",
    "plain_texture",
    "DUCK_PARTS",
    "DOG_PARTS",
]

# (points (N, 3) m, face normals (N, 3) unit, tags (N,) int) -> rgb (N, 3) float in [0, 1]
Shader = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]

_DILATE_PX = 6  # gutter texels filled from their neighbours so bilinear lookups do not bleed


# ----------------------------------------------------------------------------- baking
def cross2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """z of the cross product of 2D vectors ``(..., 2)`` -> ``(...)`` (twice the signed area)."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def rasterize_uv(uv: np.ndarray, faces: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Which face covers each texel, and where.

    Args:
        uv: (V, 2) texture coordinates in [0, 1].
        faces: (F, 3) vertex indices.
        size: texture side S in px.
    Returns:
        face_id: (S, S) int64, -1 where no face maps;
        bary: (S, S, 3) float64 barycentric coordinates of the texel centre in its face (clamped
        to the triangle, so texels on an edge get the edge's value).
    """
    uv = np.asarray(uv, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    px = np.stack([uv[:, 0] * size, (1.0 - uv[:, 1]) * size], -1)  # image x right, y down
    img = Image.new("I", (size, size), -1)
    draw = ImageDraw.Draw(img)
    # Larger faces first so that small faces sharing border texels keep their own texels.
    tri = px[faces]
    area = 0.5 * np.abs(cross2(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
    for f in np.argsort(-area, kind="stable"):
        draw.polygon([tuple(p) for p in tri[f]], fill=int(f), outline=int(f))
    face_id = np.asarray(img, dtype=np.int64)

    bary = np.zeros((size, size, 3))
    rows, cols = np.nonzero(face_id >= 0)
    if len(rows):
        f = face_id[rows, cols]
        p = np.stack([cols + 0.5, rows + 0.5], -1)
        a, b, c = tri[f, 0], tri[f, 1], tri[f, 2]
        v0, v1, v2 = b - a, c - a, p - a
        d00 = (v0 * v0).sum(-1)
        d01 = (v0 * v1).sum(-1)
        d11 = (v1 * v1).sum(-1)
        d20 = (v2 * v0).sum(-1)
        d21 = (v2 * v1).sum(-1)
        den = d00 * d11 - d01 * d01
        den = np.where(np.abs(den) > 1e-18, den, 1.0)  # sub-texel faces: any weights will do
        w1 = (d11 * d20 - d01 * d21) / den
        w2 = (d00 * d21 - d01 * d20) / den
        w = np.clip(np.stack([1.0 - w1 - w2, w1, w2], -1), 0.0, None)
        w /= np.maximum(w.sum(-1, keepdims=True), 1e-12)
        bary[rows, cols] = w
    return face_id, bary


def _dilate(rgb: np.ndarray, covered: np.ndarray, steps: int, fill: np.ndarray) -> np.ndarray:
    """Grow covered texels' colours into the uncovered ones ``steps`` px; the rest get ``fill``."""
    rgb = rgb.copy()
    covered = covered.copy()
    for _ in range(steps):
        acc = np.zeros_like(rgb)
        cnt = np.zeros(covered.shape)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dx == dy == 0:
                    continue
                m = np.roll(covered, (dy, dx), (0, 1))
                acc += np.roll(rgb, (dy, dx), (0, 1)) * m[..., None]
                cnt += m
        grow = (~covered) & (cnt > 0)
        rgb[grow] = acc[grow] / cnt[grow, None]
        covered |= grow
    rgb[~covered] = fill
    return rgb


def bake_vertex_values(
    faces: np.ndarray, uv: np.ndarray, values: np.ndarray, size: int
) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex ``values`` (V, C) interpolated to every texel of an (S, S) texture.

    Returns (S, S, C) float64 values and the (S, S) bool mask of texels some face maps to.
    """
    faces = np.asarray(faces, dtype=np.int64)
    values = np.asarray(values, dtype=np.float64)
    face_id, bary = rasterize_uv(uv, faces, size)
    covered = face_id >= 0
    out = np.zeros((size, size, values.shape[-1]))
    out[covered] = (values[faces[face_id[covered]]] * bary[covered][..., None]).sum(-2)
    return out, covered


def finish_bake(rgb: np.ndarray, covered: np.ndarray, fill=(0.5, 0.5, 0.5)) -> np.ndarray:
    """(S, S, 3) float rgb in [0, 1] -> uint8 image, gutters dilated, unmapped texels ``fill``."""
    rgb = _dilate(np.clip(rgb, 0.0, 1.0), covered, _DILATE_PX, np.asarray(fill, dtype=np.float64))
    return np.round(rgb * 255.0).astype(np.uint8)


def bake_texture(
    vertices: np.ndarray,
    faces: np.ndarray,
    uv: np.ndarray,
    shader: Shader,
    size: int = 512,
    tags: np.ndarray | None = None,
    fill=(0.5, 0.5, 0.5),
) -> np.ndarray:
    """Texture image (S, S, 3) uint8 that shows ``shader`` on the surface under UV layout ``uv``.

    Args:
        vertices: (V, 3) m; faces: (F, 3); uv: (V, 2) in [0, 1].
        shader: see :data:`Shader`.
        tags: (F,) int per-face part tags passed to the shader (default 0).
        fill: rgb in [0, 1] for texels no face maps to (beyond the dilated gutter).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    face_id, bary = rasterize_uv(uv, faces, size)
    covered = face_id >= 0
    f = face_id[covered]
    points = (vertices[faces[f]] * bary[covered][..., None]).sum(-2)
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
    t = np.zeros(len(faces), np.int64) if tags is None else np.asarray(tags, np.int64)
    rgb = np.zeros((size, size, 3))
    rgb[covered] = shader(points, n[f], t[f])
    return finish_bake(rgb, covered, fill)


def sample_texture(image: np.ndarray, uv: np.ndarray, wrap: bool = False) -> np.ndarray:
    """Nearest-texel lookup: ``image`` (H, W, C) at ``uv`` (N, 2) -> (N, C) (wrap = repeat)."""
    h, w = image.shape[:2]
    uv = np.asarray(uv, dtype=np.float64)
    if wrap:
        uv = uv - np.floor(uv)
    col = np.clip(np.floor(uv[:, 0] * w), 0, w - 1).astype(np.int64)
    row = np.clip(np.floor((1.0 - uv[:, 1]) * h), 0, h - 1).astype(np.int64)
    return image[row, col]


# ----------------------------------------------------------------------------- helpers
def _rgb(*c: float) -> np.ndarray:
    return np.asarray(c, dtype=np.float64) / 255.0


def _paint(out: np.ndarray, mask: np.ndarray, color: np.ndarray) -> None:
    out[mask] = color


def _blocks(s: np.ndarray, t: np.ndarray, seed: int, n_rows: int, n_cols: int, fill: float) -> np.ndarray:
    """Text-like marks: True on a pseudo-random subset of an ``n_rows x n_cols`` grid of bars.

    ``s, t`` in [0, 1) are coordinates inside the text box; bars leave gaps between letters and
    lines so the result reads as print at a distance.
    """
    rng = np.random.default_rng(seed)
    on = rng.random((n_rows, n_cols)) < fill
    r = np.clip((t * n_rows).astype(np.int64), 0, n_rows - 1)
    c = np.clip((s * n_cols).astype(np.int64), 0, n_cols - 1)
    fr, fc = t * n_rows - r, s * n_cols - c
    return on[r, c] & (fr > 0.25) & (fr < 0.8) & (fc > 0.12) & (fc < 0.88)


def _in_box(s, t, s0, s1, t0, t1):
    return (s >= s0) & (s < s1) & (t >= t0) & (t < t1)


# ----------------------------------------------------------------------------- shaders
_CAN_RED = _rgb(190, 25, 30)
_CAN_WHITE = _rgb(238, 236, 228)
_CAN_GOLD = _rgb(200, 160, 60)
_LID_GREY = _rgb(165, 165, 170)
_INK = _rgb(30, 25, 25)


def soup_can_shader(height_m: float) -> Shader:
    """Tomato soup can look: red upper band, white lower band, gold rule and medallion, dark
    text-like marks, grey lids with a rim. ``height_m``: can height (sets the band split)."""

    def shade(p, n, tags):
        out = np.empty((len(p), 3))
        out[:] = _LID_GREY
        side = np.abs(n[:, 2]) < 0.5
        theta = np.arctan2(p[:, 1], p[:, 0])  # rad, seam at -pi/pi (the can's back)
        s = (theta / (2 * np.pi)) % 0.5 * 2.0  # the label repeats twice around the can
        z = p[:, 2] / height_m
        red = side & (z >= 0.52)
        white = side & (z < 0.52)
        _paint(out, red, _CAN_RED)
        _paint(out, white, _CAN_WHITE)
        _paint(out, side & (np.abs(z - 0.52) < 0.015), _CAN_GOLD)
        # Script-like white lettering across the red band.
        letters = _in_box(s, z, 0.2, 0.8, 0.68, 0.86) & _blocks((s - 0.2) / 0.6, (z - 0.68) / 0.18, 1, 2, 9, 0.7)
        _paint(out, side & letters, _CAN_WHITE)
        # Gold medallion on the white band, with dark print beside it.
        radius = np.hypot(p[:, 0], p[:, 1]).max(initial=0.0)
        ds, dz = (s - 0.3) * np.pi * radius, (z - 0.3) * height_m  # m along the wall; s spans half
        medal = np.hypot(ds, dz) < 0.1 * height_m
        _paint(out, white & medal, _CAN_GOLD)
        text = _in_box(s, z, 0.45, 0.85, 0.12, 0.42) & _blocks((s - 0.45) / 0.4, (z - 0.12) / 0.3, 2, 4, 8, 0.6)
        _paint(out, white & text, _INK)
        # Lids: a darker rim ring where the lid meets the can wall.
        r = np.hypot(p[:, 0], p[:, 1])
        rim = (~side) & (r > 0.85 * r.max(initial=0.0))
        _paint(out, rim, _LID_GREY * 0.75)
        return out

    return shade


_MUSTARD = _rgb(245, 200, 20)
_MUSTARD_CAP = _rgb(235, 185, 15)
_LABEL_RED = _rgb(200, 30, 35)


def mustard_shader(body_top_m: float, cap_bottom_m: float, half_width_m: float) -> Shader:
    """Mustard bottle look: yellow plastic, a label on both broad faces (red pennant with white
    print), slightly darker cap. ``body_top_m``: top of the straight body (label region);
    ``cap_bottom_m``: where the cap starts; ``half_width_m``: half the body's x extent (the broad
    faces face +-y)."""

    def shade(p, n, tags):
        out = np.empty((len(p), 3))
        out[:] = _MUSTARD
        _paint(out, p[:, 2] >= cap_bottom_m, _MUSTARD_CAP)
        broad = (np.abs(n[:, 1]) > 0.6) & (np.abs(n[:, 2]) < 0.5)
        s = np.clip(0.5 + 0.5 * p[:, 0] / half_width_m * np.sign(p[:, 1]), 0.0, 1.0)  # across the face
        t = p[:, 2] / body_top_m
        pennant = _in_box(s, t, 0.14, 0.86, 0.35, 0.72) & (np.abs(t - 0.535) < 0.185 - 0.1 * np.abs(s - 0.5))
        _paint(out, broad & pennant, _LABEL_RED)
        print_ = _in_box(s, t, 0.22, 0.78, 0.44, 0.62) & _blocks((s - 0.22) / 0.56, (t - 0.44) / 0.18, 3, 2, 8, 0.75)
        _paint(out, broad & print_, _CAN_WHITE)
        small = _in_box(s, t, 0.25, 0.75, 0.12, 0.26) & _blocks((s - 0.25) / 0.5, (t - 0.12) / 0.14, 4, 3, 10, 0.5)
        _paint(out, broad & small, _LABEL_RED * 0.8)
        return out

    return shade


def cube_shader(size_m: float) -> Shader:
    """Cube: a distinct pastel per face with a darker border, so orientation is visible."""
    colors = np.array(
        [
            _rgb(230, 120, 110),
            _rgb(110, 190, 120),
            _rgb(110, 140, 220),
            _rgb(230, 210, 110),
            _rgb(190, 120, 210),
            _rgb(120, 210, 210),
        ]
    )

    def shade(p, n, tags):
        axis = np.argmax(np.abs(n), -1)
        face = 2 * axis + (n[np.arange(len(n)), axis] < 0)
        out = colors[face].copy()
        # Distance to the face border in the face plane, via the two in-plane coordinates.
        q = np.abs(p - np.array([0.0, 0.0, size_m / 2]))
        q[np.arange(len(q)), axis] = 0.0
        border = q.max(-1) > 0.42 * size_m
        out[border] *= 0.6
        return out

    return shade


def cylinder_shader(height_m: float) -> Shader:
    """Plain printable cylinder: light grey wrap with a thin marker stripe at the seam side, white
    caps (the attack replaces it; the stripe shows rotation in renders)."""

    def shade(p, n, tags):
        out = np.empty((len(p), 3))
        out[:] = _rgb(235, 235, 235)
        side = np.abs(n[:, 2]) < 0.5
        _paint(out, side, _rgb(200, 200, 205))
        theta = np.arctan2(p[:, 1], p[:, 0])
        _paint(out, side & (np.abs(theta - np.pi / 2) < 0.15), _rgb(60, 90, 160))
        return out

    return shade


def _tagged(colors: dict[int, np.ndarray], default: np.ndarray) -> Shader:
    def shade(p, n, tags):
        out = np.empty((len(p), 3))
        out[:] = default
        for tag, c in colors.items():
            out[tags == tag] = c
        return out

    return shade


DUCK_PARTS = ("body", "head", "neck", "tail", "beak", "eye", "leg", "foot")
DOG_PARTS = ("body", "head", "snout", "nose", "ear", "leg", "tail", "eye")


def duck_shader() -> Shader:
    """Rubber-duck colours by part (tags index :data:`DUCK_PARTS`)."""
    yellow = _rgb(250, 210, 40)
    orange = _rgb(240, 130, 20)
    return _tagged(
        {0: yellow, 1: yellow, 2: yellow, 3: yellow * 0.92, 4: orange, 5: _rgb(20, 20, 25), 6: orange, 7: orange},
        yellow,
    )


def dog_shader() -> Shader:
    """Toy-dog colours by part (tags index :data:`DOG_PARTS`): tan coat, brown ears and tail."""
    tan = _rgb(200, 150, 95)
    brown = _rgb(110, 70, 40)
    dark = _rgb(25, 20, 20)

    base = _tagged({0: tan, 1: tan, 2: _rgb(225, 195, 150), 3: dark, 4: brown, 5: tan, 6: brown, 7: dark}, tan)

    def shade(p, n, tags):
        out = base(p, n, tags)
        # A brown saddle patch on the back.
        saddle = (tags == 0) & (n[:, 2] > 0.55)
        out[saddle] = brown * 1.15
        return out

    return shade


def patch_shader() -> Shader:
    """2D patch start texture: mid grey top (the attack replaces it), darker edges."""

    def shade(p, n, tags):
        out = np.empty((len(p), 3))
        out[:] = _rgb(90, 90, 95)
        out[n[:, 2] > 0.5] = _rgb(128, 128, 128)
        return out

    return shade


# ----------------------------------------------------------------------------- image tiles
def _periodic_noise(size: int, rng: np.random.Generator, cutoff: float) -> np.ndarray:
    """Smooth noise (size, size) in about [-1, 1] that tiles seamlessly (band-limited via FFT)."""
    f = np.fft.fftfreq(size)
    k = np.hypot(f[:, None], f[None, :]) * size
    spectrum = np.fft.fft2(rng.standard_normal((size, size))) * np.exp(-((k / cutoff) ** 2))
    n = np.real(np.fft.ifft2(spectrum))
    return n / max(np.abs(n).max(), 1e-12)


def wood_texture(size: int = 512, seed: int = 7) -> np.ndarray:
    """Seamlessly tiling light-oak planks (size, size, 3) uint8: 4 planks per tile along y, grain
    along x. Every term is periodic on the tile so repeat wrap shows no seam."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size] / size
    warp = 0.04 * _periodic_noise(size, rng, 4.0)
    planks = 4
    plank = np.floor((yy + 0.0) * planks).astype(np.int64) % planks
    tone = rng.uniform(-0.06, 0.06, planks)[plank]
    grain = np.sin(2 * np.pi * (28 * (yy + warp) + 0.5 * np.sin(2 * np.pi * xx)))
    fine = _periodic_noise(size, rng, 60.0)
    g = 0.5 + 0.25 * grain + 0.12 * fine
    base = np.array([0.78, 0.60, 0.40])
    dark = np.array([0.58, 0.41, 0.25])
    img = base * (1 - g[..., None] * 0.5) + dark * (g[..., None] * 0.5)
    img = img * (1.0 + tone[..., None])
    # Plank joints: a dark line at each plank boundary.
    joint = (yy * planks) % 1.0 < 1.5 * planks / size  # the first row(s) of every plank
    img[joint] *= 0.55
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


def plain_texture(size: int = 512, rgb=(0.7, 0.7, 0.7)) -> np.ndarray:
    """Uniform colour (size, size, 3) uint8 (the default look of meshes without a texture)."""
    return np.tile(np.round(np.asarray(rgb) * 255).astype(np.uint8), (size, size, 1))
