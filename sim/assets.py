"""Object meshes: procedural built-ins and validated mesh files, all with UVs and a texture.

Every mesh returned here:

* has vertices in metres in its object frame: origin at the centre of its base, +z up, so it
  stands on the table (z = 0) at the identity pose (user files keep their origin unless
  ``recenter=True``);
* carries ``trimesh.visual.TextureVisuals`` with per-vertex ``uv`` (in [0, 1] except the table,
  whose UVs tile) and a default texture image (PIL), generated in code;
* has ``metadata["name"]`` and ``metadata["optimizable_faces"]`` ((F,) bool: faces whose texture
  the attack may change; all True except the patch's sides and bottom);
* has consistent, outward winding and no degenerate faces. Vertices are duplicated along UV seams,
  so closed built-ins are watertight once vertices are merged by position.

Built-ins (:data:`BUILTIN_MESHES`): ``tomato_soup_can``, ``mustard_bottle`` (the paper's
simulated goal and adversarial objects, YCB look-alikes), ``cube`` and ``cylinder`` (its
real-world shapes), ``duck`` and ``dog`` (its generalisation study), ``patch`` (the 2D baseline)
and ``table``. Geometry lives here; the looks (shaders) live in :mod:`sim.textures`.

Built-ins with an exact layout (soup can, mustard bottle, cylinder, cube, patch) also carry, for
printing: ``metadata["uv_side_m"]``, the surface length (m) of one UV unit (print the texture as a
square of that side for true size), and the wrap layouts and the patch
``metadata["uv_islands"]``: ``{island: (u0, v0, u1, v1)}`` bounding boxes in UV.

What loading a mesh file changed on the way (degenerate faces dropped, the object rested on the
table or recentred) is recorded in ``metadata["notes"]``, one line each, and said by the commands
that check a scene (:func:`scene_mesh_notes`): the file is as the user made it and the scene
configured, so no other command warns about it.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import io
import json
import math
import os
import re
import stat
import struct
import tempfile
import warnings
import zipfile
from functools import lru_cache
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np
import trimesh
import xatlas
from PIL import Image, ImageDraw, ImageFilter

from sim import textures as tx
from sim.errors import AdvobjError
from sim.files import FileRefusedError, read_regular
from sim.geometry import so3_exp

__all__ = [
    "AssetError",
    "BUILTIN_MESHES",
    "build_mesh",
    "load_mesh_file",
    "scene_mesh_notes",
    "ensure_uv",
    "default_texture",
    "table_mesh",
    "patch_side_m",
    "silhouette_area_m2",
    "texel_density_ratio",
    "PATCH_THICKNESS_M",
    "PATCH_TOP_UV",
    "TABLE_TILE_M",
    "TEXTURE_SIZE",
]

TEXTURE_SIZE = 512  # px, side of the default texture images
TABLE_TILE_M = 0.20  # the table texture repeats every 20 cm
PATCH_THICKNESS_M = 0.002
_PATCH_STRIP = 1.0 / 32.0  # UV width of the patch's reserved (non-optimizable) strips
PATCH_TOP_UV = (_PATCH_STRIP, _PATCH_STRIP, 1.0, 1.0)  # (u0, v0, u1, v1) of the patch top face
_GUTTER = 0.02  # UV gap between islands, as a fraction of the packed atlas side (~10 px at 512)
_DEGENERATE_REL_AREA = 1e-12  # face area below this times (bbox diagonal)^2 counts as degenerate


class AssetError(AdvobjError, ValueError):
    """A mesh source could not be built or loaded; the message names the file or built-in."""


# ============================================================================ mesh assembly
class _Parts(NamedTuple):
    """Raw geometry of a built-in before it becomes a Trimesh (all arrays float64 / int64)."""

    vertices: np.ndarray  # (V, 3) m, object frame
    faces: np.ndarray  # (F, 3)
    uv: np.ndarray  # (V, 2)
    shader: tx.Shader
    tags: np.ndarray | None = None  # (F,) part index passed to the shader
    optimizable: np.ndarray | None = None  # (F,) bool, default all True
    islands: dict | None = None  # name -> (u0, v0, u1, v1)
    uv_side_m: float | None = None  # metres of surface per UV unit (uniform-density layouts)


def _make_trimesh(name: str, vertices, faces, uv, image: np.ndarray, optimizable=None, extra=None) -> trimesh.Trimesh:
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    visual = trimesh.visual.TextureVisuals(uv=np.asarray(uv, dtype=np.float64), image=Image.fromarray(image))
    # process=False: keep seam vertices (merging would drop the UV seams) and face order.
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, visual=visual, process=False)
    opt = np.ones(len(faces), bool) if optimizable is None else np.asarray(optimizable, bool)
    mesh.metadata["name"] = name
    mesh.metadata["optimizable_faces"] = opt
    if extra:
        mesh.metadata.update(extra)
    return mesh


def _to_base_frame(vertices: np.ndarray) -> np.ndarray:
    """Translate (V, 3) so the bounding box's base centre is the origin."""
    lo, hi = vertices.min(0), vertices.max(0)
    return vertices - np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])


# ============================================================================ UV packing
class _Island(NamedTuple):
    """A chart: faces with UVs in metres (texel density 1), its lower-left corner at (0, 0)."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    uv_m: np.ndarray


def _pack(islands: list[_Island], row_width_m: float | None = None):
    """Shelf-pack charts into the unit square at one common scale (uniform texel density).

    Charts go left to right in rows of width ``row_width_m`` (default: the widest chart), in the
    given order. Returns vertices (V, 3), faces (F, 3), uv (V, 2), the island boxes in UV and
    the atlas side in metres (surface length per UV unit).
    """
    sizes = [isl.uv_m.max(0) for isl in islands]
    width = row_width_m or max(s[0] for s in sizes)
    gap = _GUTTER * width
    offsets, x, y, row_h = [], gap, gap, 0.0
    for s in sizes:
        if x > gap and x + s[0] + gap > width + 2 * gap + 1e-12:
            x, y, row_h = gap, y + row_h + gap, 0.0
        offsets.append(np.array([x, y]))
        x += s[0] + gap
        row_h = max(row_h, s[1])
    side = max(width + 2 * gap, y + row_h + gap)
    verts, faces, uvs, boxes, n = [], [], [], {}, 0
    for isl, off, s in zip(islands, offsets, sizes):
        verts.append(isl.vertices)
        faces.append(isl.faces + n)
        uvs.append((isl.uv_m + off) / side)
        boxes[isl.name] = tuple(float(c) for c in (*(off / side), *((off + s) / side)))
        n += len(isl.vertices)
    return np.concatenate(verts), np.concatenate(faces), np.concatenate(uvs), boxes, float(side)


# ============================================================================ primitives
def _superellipse_ring(a: float, b: float, exponent: float, n: int) -> np.ndarray:
    """(n, 2) points, counter-clockwise from (+a, 0), evenly spaced by arc length, on
    ``|x/a|^e + |y/b|^e = 1`` (e = 2: ellipse; larger e: rounder rectangle)."""
    t = np.linspace(0.0, 2 * np.pi, 4096, endpoint=False)
    c, s = np.cos(t), np.sin(t)
    p = np.stack([a * np.sign(c) * np.abs(c) ** (2 / exponent), b * np.sign(s) * np.abs(s) ** (2 / exponent)], -1)
    closed = np.concatenate([p, p[:1]])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=-1))])
    target = np.arange(n) * arc[-1] / n
    return np.stack([np.interp(target, arc, closed[:, k]) for k in range(2)], -1)


def _lathe(rings, segments: int, cap_bottom: bool = True, cap_top: bool = True) -> list[_Island]:
    """Loft of horizontal superelliptic rings: a side wrap chart plus flat cap charts.

    Args:
        rings: sequence of ``(z_m, half_x_m, half_y_m, exponent)``, z non-decreasing.
        segments: points per ring.
    The side chart is area-preserving to first order: u is arc length along each ring (centred,
    so narrow rings make a narrower strip) and v the mean meridian arc length. The seam
    is on the +x side (column 0 is duplicated as column ``segments``).
    """
    rings = [tuple(map(float, r)) for r in rings]
    pts = np.stack([_superellipse_ring(a, b, e, segments) for _, a, b, e in rings])  # (R, n, 2)
    z = np.array([r[0] for r in rings])
    R, n = pts.shape[:2]
    ring3 = np.concatenate([pts, np.broadcast_to(z[:, None, None], (R, n, 1))], -1)
    ring3 = np.concatenate([ring3, ring3[:, :1]], 1)  # seam column
    seg = np.linalg.norm(np.diff(ring3[..., :2], axis=1), axis=-1)  # (R, n)
    s = np.concatenate([np.zeros((R, 1)), np.cumsum(seg, 1)], 1)  # (R, n + 1)
    perim = s[:, -1]
    u = s - perim[:, None] / 2 + perim.max() / 2
    # Rings stay horizontal lines in UV (v = mean meridian arc length), so the per-ring centring
    # of u is a shear, which keeps every triangle's area.
    dv = np.linalg.norm(np.diff(ring3, axis=0), axis=-1).mean(-1)  # (R - 1,)
    v = np.broadcast_to(np.concatenate([[0.0], np.cumsum(dv)])[:, None], (R, n + 1))
    idx = np.arange(R * (n + 1)).reshape(R, n + 1)
    a, b = idx[:-1, :-1], idx[:-1, 1:]
    c, d = idx[1:, 1:], idx[1:, :-1]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    # Drop zero-height, zero-width quads (none for the profiles here; kept for safety).
    tri = ring3.reshape(-1, 3)[faces]
    keep = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=-1) > 1e-14
    islands = [_Island("side", ring3.reshape(-1, 3), faces[keep], np.stack([u, v], -1).reshape(-1, 2))]

    def cap(k: int, up: bool) -> _Island:
        ring = np.concatenate([pts[k], np.full((n, 1), z[k])], -1)
        verts = np.concatenate([[[0.0, 0.0, z[k]]], ring])
        j = np.arange(n)
        f = np.stack([np.zeros(n, np.int64), 1 + j, 1 + (j + 1) % n], -1)
        if not up:
            f = f[:, [0, 2, 1]]
        # Planar UVs seen from outside: the bottom cap is mirrored so it is not read backwards.
        uvm = verts[:, :2] * np.array([1.0 if up else -1.0, 1.0])
        return _Island("top" if up else "bottom", verts, f, uvm - uvm.min(0))

    if cap_top:
        islands.append(cap(R - 1, True))
    if cap_bottom:
        islands.append(cap(0, False))
    return islands


def _grid_quad(origin, du, dv, nu: int, nv: int, uv0, uv_du, uv_dv):
    """A planar quad split into ``nu x nv`` cells (2 triangles each), normal along du x dv.

    Returns vertices (V, 3), faces (F, 3), uv (V, 2); UV = uv0 + a * uv_du + b * uv_dv with
    (a, b) in [0, 1]^2 the position in the quad.
    """
    a, b = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1), indexing="xy")
    a, b = a.ravel(), b.ravel()
    verts = np.asarray(origin, float) + a[:, None] * np.asarray(du, float) + b[:, None] * np.asarray(dv, float)
    uv = np.asarray(uv0, float) + a[:, None] * np.asarray(uv_du, float) + b[:, None] * np.asarray(uv_dv, float)
    idx = np.arange((nu + 1) * (nv + 1)).reshape(nv + 1, nu + 1)
    p, q, r, s = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    faces = np.concatenate([np.stack([p, q, r], -1).reshape(-1, 3), np.stack([p, r, s], -1).reshape(-1, 3)])
    return verts, faces, uv


def _concat(parts):
    verts, faces, uvs, n = [], [], [], 0
    for v, f, u in parts:
        verts.append(v)
        faces.append(f + n)
        uvs.append(u)
        n += len(v)
    return np.concatenate(verts), np.concatenate(faces), np.concatenate(uvs)


def _box_faces(size, uv_of_face):
    """Box ``size = (sx, sy, sz)`` with its base centre at the origin, one grid quad per face.

    ``uv_of_face(name) -> (uv0, uv_du, uv_dv, nu, nv)`` for names ``+x -x +y -y +z -z``; each face's
    (du, dv) follow the wrap order described in :func:`_cube_parts`. Returns (V, 3), (F, 3), (V, 2)
    and (F,) face-name index.
    """
    sx, sy, sz = (float(s) for s in size)
    hx, hy = sx / 2, sy / 2
    geo = {  # origin, du, dv (du x dv points outward)
        "-x": ([-hx, hy, 0], [0, -sy, 0], [0, 0, sz]),
        "-y": ([-hx, -hy, 0], [sx, 0, 0], [0, 0, sz]),
        "+x": ([hx, -hy, 0], [0, sy, 0], [0, 0, sz]),
        "+y": ([hx, hy, 0], [-sx, 0, 0], [0, 0, sz]),
        "+z": ([-hx, -hy, sz], [sx, 0, 0], [0, sy, 0]),
        "-z": ([-hx, hy, 0], [sx, 0, 0], [0, -sy, 0]),
    }
    parts, which = [], []
    for k, (name, (o, du, dv)) in enumerate(geo.items()):
        uv0, uv_du, uv_dv, nu, nv = uv_of_face(name)
        v, f, u = _grid_quad(o, du, dv, nu, nv, uv0, uv_du, uv_dv)
        parts.append((v, f, u))
        which.append(np.full(len(f), k))
    v, f, u = _concat(parts)
    return v, f, u, np.concatenate(which)


def _ellipsoid(radii, center, subdivisions: int = 2, rotvec=(0.0, 0.0, 0.0)):
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    v = (np.asarray(s.vertices) * np.asarray(radii, float)) @ so3_exp(np.asarray(rotvec, float)).T + np.asarray(
        center, float
    )
    return v, np.asarray(s.faces, np.int64)


def _cylinder(radius: float, z0: float, z1: float, xy, sections: int = 12):
    c = trimesh.creation.cylinder(radius=radius, segment=[[xy[0], xy[1], z0], [xy[0], xy[1], z1]], sections=sections)
    return np.asarray(c.vertices, float), np.asarray(c.faces, np.int64)


_ATLAS_MEMO: dict[str, tuple] = {}
_NPY_HEADER_MAX = 4096  # bytes: an npy header of the arrays below is ~128


def atlas_cache_dir() -> Path | None:
    """Where UV atlases are cached across commands: ``$ADVOBJ_CACHE_DIR/uv`` (empty: no disk
    cache), else ``$XDG_CACHE_HOME/advobj/uv`` (default ``~/.cache``)."""
    env = os.environ.get("ADVOBJ_CACHE_DIR")
    if env is not None:
        return Path(env) / "uv" if env else None
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "advobj" / "uv"


# How a mesh, material or cache file's refusal is worded (sim.files' standard words otherwise).
_FILE_WORDS = {
    "missing": "cannot read ({strerror})",
    "directory": "not a regular file",
    "special": "not a regular file",
    "too_large": "{size:,} bytes, more than the {max_bytes:,} advobj reads",
    "grew": "more than the {max_bytes:,} bytes advobj reads",
}


def _read_regular(path, cap: int, label: str, follow: bool = True) -> bytes:
    """The bytes of regular file ``path``, refused (:class:`AssetError` naming ``label``) when it is
    not a regular file (a FIFO or device is never waited on) or holds more than ``cap`` bytes;
    ``follow=False`` also refuses a symlink. Memory stays within ``cap`` (:func:`sim.files.read_regular`)."""
    try:
        return read_regular(path, cap, follow_symlinks=follow)
    except FileRefusedError as err:
        raise AssetError(f"{label}: {err.problem(_FILE_WORDS)}") from None


def _atlas_entry_limits(n_faces: int) -> dict[str, tuple[np.dtype, int]]:
    """Member -> (dtype, largest element count) of an atlas cache entry for ``n_faces`` faces:
    xatlas splits vertices along seams, at most one per face corner."""
    corners = 3 * n_faces
    return {
        "key": (np.dtype(np.uint8), 64),
        "vmap": (np.dtype(np.int64), corners),
        "idx": (np.dtype(np.int64), corners),
        "uv": (np.dtype(np.float64), 2 * corners),
    }


def _read_atlas_entry(entry: Path, key: str, n_vertices: int, n_faces: int):
    """``(vmap, idx, uv)`` from cache file ``entry`` when it is a regular file (never a symlink)
    holding the atlas of ``key`` for a mesh of ``n_vertices`` and ``n_faces``; None otherwise.

    Reading is bounded: the file size, each member's declared size and its npy header's shape are
    checked against what this mesh's atlas can take before anything is decompressed, and no more
    than that is ever inflated.
    """
    limits = _atlas_entry_limits(n_faces)
    cap = sum(d.itemsize * n + _NPY_HEADER_MAX + 512 for d, n in limits.values()) + 4096
    try:
        data = _read_regular(entry, cap, str(entry), follow=False)
    except AssetError:
        return None
    arrays = {}
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as z:
            infos = {i.filename: i for i in z.infolist()}
            if sorted(infos) != sorted(f"{m}.npy" for m in limits):
                return None
            for member, (dtype, most) in limits.items():
                info = infos[f"{member}.npy"]
                if info.file_size > dtype.itemsize * most + _NPY_HEADER_MAX:
                    return None
                with z.open(info) as f:
                    version = np.lib.format.read_magic(f)
                    if version == (1, 0):
                        shape, fortran, got = np.lib.format.read_array_header_1_0(f, max_header_size=_NPY_HEADER_MAX)
                    elif version == (2, 0):
                        shape, fortran, got = np.lib.format.read_array_header_2_0(f, max_header_size=_NPY_HEADER_MAX)
                    else:
                        return None
                    count = math.prod(shape)
                    if got != dtype or fortran or count > most:
                        return None
                    raw = f.read(count * dtype.itemsize + 1)
                if len(raw) != count * dtype.itemsize:
                    return None
                arrays[member] = np.frombuffer(raw, dtype).reshape(shape)
    except Exception:  # noqa: BLE001 - a damaged zip (truncated, bad CRC, odd compression): a miss, rebuilt
        return None
    vmap, idx, uv = arrays["vmap"], arrays["idx"], arrays["uv"]
    n = len(vmap)
    ok = (
        arrays["key"].tobytes() == key.encode()
        and vmap.ndim == 1
        and idx.shape == (n_faces, 3)
        and uv.shape == (n, 2)
        and (n == 0 or (vmap.min() >= 0 and vmap.max() < n_vertices))
        and (idx.size == 0 or (idx.min() >= 0 and idx.max() < n))
        and bool(np.all(np.isfinite(uv)))
        and (uv.size == 0 or (uv.min() >= 0.0 and uv.max() <= 1.0))
    )
    return (vmap.copy(), idx.copy(), uv.copy()) if ok else None


def _write_atlas_entry(folder: Path, key: str, hit) -> None:
    """Store ``hit`` as ``folder/<key>.npz``: written to a fresh temporary file (O_EXCL, random
    name) and renamed over the entry, so no planted link is ever written through."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{key}.", suffix=".tmp", dir=folder)
    except OSError:
        return  # a read-only cache only costs the rebuild next time
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, key=np.frombuffer(key.encode(), np.uint8), vmap=hit[0], idx=hit[1], uv=hit[2])
        os.replace(tmp, folder / f"{key}.npz")
    except OSError:
        try:
            os.unlink(tmp)
        except OSError:
            pass


def _atlas_key(v32: np.ndarray, f32: np.ndarray) -> str:
    """The cache key of an atlas: sha256 (hex) of xatlas's version and the float32 vertices and
    uint32 faces it sees."""
    try:
        version = importlib.metadata.version("xatlas")
    except importlib.metadata.PackageNotFoundError:
        version = "?"
    return hashlib.sha256(version.encode() + v32.tobytes() + b"|" + f32.tobytes()).hexdigest()


def _atlas(vertices: np.ndarray, faces: np.ndarray):
    """xatlas charts + packing. Returns vertices (V', 3), faces (F, 3) (same order), uv (V', 2)
    and ``vmapping`` (V',) into the input vertices.

    An atlas costs seconds for a scan (10 s at 20k faces) and every command that builds the mesh
    needs it, so it is cached by the content it depends on (the sha256 of the float32 vertices and
    faces xatlas sees, and xatlas's version): in memory, and on disk in :func:`atlas_cache_dir`
    as a plain ``.npz`` (arrays only, read without pickle, :func:`_read_atlas_entry`). An entry that
    is not a regular file, is damaged, or does not hold this mesh's atlas (its key, shapes, index
    and UV ranges) is dropped and rebuilt.
    """
    v32, f32 = np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(faces, np.uint32)
    key = _atlas_key(v32, f32)
    hit = _ATLAS_MEMO.get(key)
    folder = atlas_cache_dir()
    if hit is None and folder is not None:
        entry = folder / f"{key}.npz"
        try:
            st = os.lstat(entry)
        except OSError:
            st = None  # no entry: a miss
        if st is not None:
            hit = _read_atlas_entry(entry, key, len(v32), len(f32))
            if hit is None:
                if not stat.S_ISREG(st.st_mode):
                    warnings.warn(f"{entry}: UV atlas cache entry is not a regular file: replaced", stacklevel=2)
                try:
                    entry.unlink()  # a link itself, never its target
                except OSError:
                    pass
    if hit is None:
        vmap, idx, uv = xatlas.parametrize(v32, f32)
        hit = (np.asarray(vmap, np.int64), np.asarray(idx, np.int64), np.clip(np.asarray(uv, np.float64), 0.0, 1.0))
        if folder is not None:
            _write_atlas_entry(folder, key, hit)
    _ATLAS_MEMO[key] = hit
    vmap, idx, uv = hit
    return np.asarray(vertices, np.float64)[vmap], idx.copy(), uv.copy(), vmap.copy()


# ============================================================================ built-ins
SOUP_CAN_DIAMETER_M = 0.066
SOUP_CAN_HEIGHT_M = 0.101
CYLINDER_DIAMETER_M = 0.066
CYLINDER_HEIGHT_M = 0.100
CUBE_SIZE_M = 0.06
ANIMAL_LENGTH_M = 0.15  # duck and dog: largest extent

# Mustard bottle profile: (z, half-x, half-y, superellipse exponent), metres. A rounded-rectangle
# body 9.6 x 5.8 cm, a shoulder narrowing to a round neck, and a flip-top cap to 19 cm.
_MUSTARD_BODY_TOP_M = 0.120
_MUSTARD_CAP_BOTTOM_M = 0.1625
_MUSTARD_RINGS = (
    (0.000, 0.0455, 0.0265, 3.0),
    (0.004, 0.0480, 0.0290, 3.0),
    (0.030, 0.0480, 0.0290, 3.0),
    (0.060, 0.0480, 0.0290, 3.0),
    (0.090, 0.0480, 0.0290, 3.0),
    (0.120, 0.0480, 0.0290, 3.0),
    (0.130, 0.0465, 0.0285, 2.9),
    (0.139, 0.0420, 0.0270, 2.7),
    (0.147, 0.0345, 0.0240, 2.5),
    (0.154, 0.0260, 0.0205, 2.3),
    (0.159, 0.0190, 0.0170, 2.1),
    (0.1620, 0.0155, 0.0150, 2.0),
    (0.1625, 0.0168, 0.0168, 2.0),
    (0.1860, 0.0160, 0.0160, 2.0),
    (0.1900, 0.0110, 0.0110, 2.0),
)


def _wrap_parts(rings, segments, shader) -> _Parts:
    islands = _lathe(rings, segments)
    v, f, uv, boxes, side = _pack(islands)
    return _Parts(v, f, uv, shader, islands=boxes, uv_side_m=side)


def _soup_can_parts() -> _Parts:
    r, h = SOUP_CAN_DIAMETER_M / 2, SOUP_CAN_HEIGHT_M
    rings = [(z, r, r, 2.0) for z in np.linspace(0.0, h, 9)]
    return _wrap_parts(rings, 48, tx.soup_can_shader(h))


def _cylinder_parts() -> _Parts:
    """Printable cylinder, 6.6 cm x 10 cm, 48 sides. UV layout (unit square, v up, one common
    scale: ``metadata["uv_side_m"]`` = 0.2155 m of surface per UV unit):

    * ``side`` wrap: u in [0.019, 0.981] (the 48-gon perimeter, seam on the +x side, u growing
      counter-clockwise seen from above), v in [0.019, 0.483] (z = 0 to the top);
    * ``top`` cap: the disk in [0.019, 0.326] x [0.503, 0.809], seen from above (u = +x, v = +y);
    * ``bottom`` cap: [0.345, 0.651] x [0.503, 0.809], seen from below (u = -x, v = +y);
    * the rest is unused; 2% gutters separate the charts.

    Exact boxes: ``metadata["uv_islands"]``.
    """
    r, h = CYLINDER_DIAMETER_M / 2, CYLINDER_HEIGHT_M
    rings = [(z, r, r, 2.0) for z in np.linspace(0.0, h, 9)]
    return _wrap_parts(rings, 48, tx.cylinder_shader(h))


def _mustard_parts() -> _Parts:
    shader = tx.mustard_shader(_MUSTARD_BODY_TOP_M, _MUSTARD_CAP_BOTTOM_M, _MUSTARD_RINGS[1][1])
    return _wrap_parts(_MUSTARD_RINGS, 48, shader)


# Cube net (4 x 3 tiles of 1/4): middle row -x, -y, +x, +y wrapping counter-clockwise seen from
# above (u along the wrap, v up); +z above the -y tile, -z below it. Each tile is inset by a
# gutter so bilinear lookups stay inside their face.
_CUBE_TILES = {"-x": (0, 1), "-y": (1, 1), "+x": (2, 1), "+y": (3, 1), "+z": (1, 2), "-z": (1, 0)}


def _cube_parts() -> _Parts:
    tile, inset = 0.25, 0.25 * _GUTTER

    def uv_of_face(name):
        col, row = _CUBE_TILES[name]
        return (col * tile + inset, row * tile + inset), (tile - 2 * inset, 0), (0, tile - 2 * inset), 3, 3

    v, f, uv, _ = _box_faces((CUBE_SIZE_M,) * 3, uv_of_face)
    return _Parts(v, f, uv, tx.cube_shader(CUBE_SIZE_M), uv_side_m=CUBE_SIZE_M / (tile - 2 * inset))


def _composite_parts(pieces, shader, length_m: float) -> _Parts:
    """Union (by concatenation) of closed parts, scaled to ``length_m`` largest extent, packed by
    xatlas into one atlas; ``pieces``: list of (tag, vertices, faces)."""
    verts, faces, tags, n = [], [], [], 0
    for tag, v, f in pieces:
        verts.append(v)
        faces.append(f + n)
        tags.append(np.full(len(f), tag))
        n += len(v)
    v = np.concatenate(verts)
    v = _to_base_frame(v * (length_m / (v.max(0) - v.min(0)).max()))
    v, f, uv, _ = _atlas(v, np.concatenate(faces))
    return _Parts(v, f, uv, shader, tags=np.concatenate(tags))


def _duck_parts() -> _Parts:
    # Design units: cm; scaled to ANIMAL_LENGTH_M afterwards. Tags index textures.DUCK_PARTS.
    P = [
        (0, *_ellipsoid((6.0, 3.8, 3.2), (0.0, 0.0, 4.2))),  # body
        (3, *_ellipsoid((2.2, 1.6, 1.0), (-5.6, 0.0, 5.6), 1, (0.0, -0.6, 0.0))),  # tail, tilted up
        (2, *_ellipsoid((1.9, 1.9, 2.6), (3.6, 0.0, 7.0), 1)),  # neck
        (1, *_ellipsoid((2.7, 2.5, 2.5), (4.2, 0.0, 9.2))),  # head
        (4, *_ellipsoid((1.8, 1.1, 0.5), (6.8, 0.0, 8.8), 1)),  # beak
        (5, *_ellipsoid((0.45, 0.3, 0.45), (6.1, 1.35, 10.0), 1)),  # eyes
        (5, *_ellipsoid((0.45, 0.3, 0.45), (6.1, -1.35, 10.0), 1)),
        (6, *_cylinder(0.45, 0.3, 1.8, (0.6, 1.5))),  # legs
        (6, *_cylinder(0.45, 0.3, 1.8, (0.6, -1.5))),
        (7, *_ellipsoid((1.4, 0.9, 0.3), (1.3, 1.6, 0.3), 1)),  # feet
        (7, *_ellipsoid((1.4, 0.9, 0.3), (1.3, -1.6, 0.3), 1)),
    ]
    return _composite_parts(P, tx.duck_shader(), ANIMAL_LENGTH_M)


def _dog_parts() -> _Parts:
    # Design units: cm; scaled to ANIMAL_LENGTH_M afterwards. Tags index textures.DOG_PARTS.
    P = [
        (0, *_ellipsoid((5.5, 2.6, 2.6), (0.0, 0.0, 6.2))),  # body
        (1, *_ellipsoid((2.4, 2.2, 2.3), (5.3, 0.0, 9.4))),  # head
        (2, *_ellipsoid((1.8, 1.2, 1.1), (7.4, 0.0, 8.8), 1)),  # snout
        (3, *_ellipsoid((0.45, 0.5, 0.4), (9.1, 0.0, 9.2), 1)),  # nose
        (4, *_ellipsoid((0.5, 1.0, 1.9), (4.6, 2.1, 10.0), 1, (-0.5, 0.0, 0.0))),  # ears, hanging
        (4, *_ellipsoid((0.5, 1.0, 1.9), (4.6, -2.1, 10.0), 1, (0.5, 0.0, 0.0))),
        (7, *_ellipsoid((0.35, 0.3, 0.35), (6.8, 1.2, 10.3), 1)),  # eyes
        (7, *_ellipsoid((0.35, 0.3, 0.35), (6.8, -1.2, 10.3), 1)),
        (5, *_cylinder(0.8, 0.0, 5.2, (3.6, 1.4))),  # legs
        (5, *_cylinder(0.8, 0.0, 5.2, (3.6, -1.4))),
        (5, *_cylinder(0.8, 0.0, 5.2, (-3.6, 1.4))),
        (5, *_cylinder(0.8, 0.0, 5.2, (-3.6, -1.4))),
        (6, *_ellipsoid((0.5, 0.5, 2.4), (-6.2, 0.0, 8.4), 1, (0.0, -0.7, 0.0))),  # tail, up and back
    ]
    return _composite_parts(P, tx.dog_shader(), ANIMAL_LENGTH_M)


def _patch_parts() -> _Parts:
    """Top face -> PATCH_TOP_UV (most of the texture, optimizable); the four sides share the
    bottom strip and the bottom face the left strip (reserved, not optimizable)."""
    side, t = patch_side_m(), PATCH_THICKNESS_M
    r = _PATCH_STRIP
    g = r * 0.25  # gutter between the strips and the top face
    w = 1.0 - r  # top face UV side

    def uv_of_face(name):
        if name == "+z":
            return (r, r), (w, 0), (0, w), 4, 4
        if name == "-z":
            return (0.0, r), (r - g, 0), (0, w), 4, 4
        k = ["-x", "-y", "+x", "+y"].index(name)
        return (r + k * w / 4, 0.0), (w / 4 - g, 0), (0, r - g), 4, 1

    v, f, uv, which = _box_faces((side, side, t), uv_of_face)
    optimizable = which == 4  # "+z" is the 5th face of _box_faces
    return _Parts(
        v, f, uv, tx.patch_shader(), optimizable=optimizable, islands={"top": PATCH_TOP_UV}, uv_side_m=side / w
    )


_BUILDERS: dict[str, Callable[[], _Parts]] = {
    "tomato_soup_can": _soup_can_parts,
    "mustard_bottle": _mustard_parts,
    "cube": _cube_parts,
    "cylinder": _cylinder_parts,
    "duck": _duck_parts,
    "dog": _dog_parts,
    "patch": _patch_parts,
}


@lru_cache(maxsize=None)
def _parts(name: str) -> _Parts:
    return _BUILDERS[name]()


@lru_cache(maxsize=None)
def _builtin_mesh(name: str) -> trimesh.Trimesh:
    p = _parts(name)
    image = tx.bake_texture(p.vertices, p.faces, p.uv, p.shader, TEXTURE_SIZE, p.tags)
    extra = {}
    if p.islands:
        extra["uv_islands"] = p.islands
    if p.uv_side_m:
        extra["uv_side_m"] = p.uv_side_m
    return _make_trimesh(name, p.vertices, p.faces, p.uv, image, p.optimizable, extra)


def _builtin(name: str) -> Callable[[], trimesh.Trimesh]:
    def build() -> trimesh.Trimesh:
        return _builtin_mesh(name).copy()

    build.__name__ = name
    build.__doc__ = f"A fresh copy of the built-in ``{name}`` mesh."
    return build


def table_mesh(size_xy_m: tuple[float, float], thickness_m: float = 0.03) -> trimesh.Trimesh:
    """Table box ``size_xy_m`` (x, y) m, centred on the origin, top face at z = 0.

    UVs are in metres / :data:`TABLE_TILE_M`, so the (repeat-wrapped) wood texture tiles every
    20 cm at any table size; they exceed [0, 1] by design.
    """
    try:
        sx, sy = (float(s) for s in size_xy_m)
        t = float(thickness_m)
    except (TypeError, ValueError):
        raise AssetError(f"table: size_xy_m must be two numbers, got {size_xy_m!r}") from None
    for label, val in (("size_xy_m[0]", sx), ("size_xy_m[1]", sy), ("thickness_m", t)):
        if not (math.isfinite(val) and val > 0):
            raise AssetError(f"table: {label} must be a positive finite number, got {val}")
    k = 1.0 / TABLE_TILE_M
    dims = {"-x": (sy, t), "+x": (sy, t), "-y": (sx, t), "+y": (sx, t), "+z": (sx, sy), "-z": (sx, sy)}

    def uv_of_face(name):
        a, b = dims[name]
        return (0.0, 0.0), (a * k, 0.0), (0.0, b * k), 1, 1

    v, f, uv, _ = _box_faces((sx, sy, t), uv_of_face)
    v[:, 2] -= t
    return _make_trimesh("table", v, f, uv, tx.wood_texture(TEXTURE_SIZE))


BUILTIN_MESHES: dict[str, Callable[[], trimesh.Trimesh]] = {
    **{name: _builtin(name) for name in _BUILDERS},
    "table": lambda: table_mesh((1.6, 1.6)),
}


def default_texture(name: str, size: int = TEXTURE_SIZE) -> np.ndarray:
    """The default look (size, size, 3) uint8 of built-in ``name`` (``"plain"``: uniform grey)."""
    if not (isinstance(size, (int, np.integer)) and 8 <= size <= 8192):
        raise AssetError(f"{name}: texture size must be an integer in [8, 8192], got {size!r}")
    if name == "table":
        return tx.wood_texture(int(size))
    if name == "plain":
        return tx.plain_texture(int(size))
    if name not in _BUILDERS:
        raise AssetError(f"{name!r}: no default texture; built-ins are {', '.join(BUILTIN_MESHES)} (or 'plain')")
    if size == TEXTURE_SIZE:
        return np.asarray(_builtin_mesh(name).visual.material.image.convert("RGB")).copy()
    p = _parts(name)
    return tx.bake_texture(p.vertices, p.faces, p.uv, p.shader, int(size), p.tags)


# ============================================================================ measurements
def silhouette_area_m2(mesh: trimesh.Trimesh, view_axis: int = 1, resolution: int = 2048) -> float:
    """Area (m^2) of the mesh's orthographic silhouette along ``view_axis`` (1: front view, x-z).

    Rasterises the projected triangles at ``resolution`` px over the larger extent; PIL's fill
    includes boundary pixels, a bias of about half a pixel along the outline (< 0.2% at 2048 px
    for the built-ins).
    """
    keep = [k for k in range(3) if k != view_axis]
    p = np.asarray(mesh.vertices, float)[:, keep]
    lo = p.min(0)
    px = (p.max(0) - lo).max() / resolution
    q = (p - lo) / px
    w, h = (np.ceil(q.max(0)).astype(int) + 2).tolist()
    img = Image.new("1", (w, h), 0)
    draw = ImageDraw.Draw(img)
    for tri in q[np.asarray(mesh.faces)]:
        draw.polygon([tuple(t) for t in tri], fill=1)
    return float(np.count_nonzero(np.asarray(img))) * px * px


@lru_cache(maxsize=None)
def patch_side_m() -> float:
    """Side (m) of the 2D baseline patch: its square top has the area of the mustard bottle's
    largest silhouette (front view, x-z plane), measured on the built mesh, so the 2D and 3D
    attacks get the same visible area."""
    return math.sqrt(silhouette_area_m2(_builtin_mesh("mustard_bottle"), view_axis=1))


def texel_density_ratio(mesh: trimesh.Trimesh) -> np.ndarray:
    """Per-face ``sqrt(3D area / UV area)`` (F,), metres per UV unit (inf for zero UV area)."""
    uv = np.asarray(mesh.visual.uv, float)[np.asarray(mesh.faces)]
    uv_area = 0.5 * np.abs(tx.cross2(uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]))
    with np.errstate(divide="ignore"):
        return np.sqrt(np.asarray(mesh.area_faces) / uv_area)


# ============================================================================ files
_MESH_EXTS = {".obj", ".glb", ".gltf", ".ply", ".stl", ".off", ".dae"}


def _texture_image(visual) -> np.ndarray | None:
    mat = getattr(visual, "material", None)
    if mat is None:
        return None
    img = getattr(mat, "image", None)
    if img is None:
        img = getattr(mat, "baseColorTexture", None)
    if img is None:
        return None
    return np.asarray(img.convert("RGB"))


def _valid_uv(visual, n_vertices: int) -> np.ndarray | None:
    uv = getattr(visual, "uv", None) if getattr(visual, "kind", None) == "texture" else None
    if uv is None:
        return None
    uv = np.asarray(uv, float)
    if uv.shape != (n_vertices, 2) or not np.all(np.isfinite(uv)):
        return None
    return uv


def ensure_uv(mesh: trimesh.Trimesh, name: str) -> trimesh.Trimesh:
    """``mesh`` with UVs in [0, 1] and a texture image; ``name`` labels errors and metadata.

    Kept as is when it already has in-range UVs (a missing image becomes plain grey). Otherwise
    an xatlas atlas is made and the old look is baked into it: the old texture sampled with
    repeat wrap when UVs were out of range, vertex colours when present, else plain grey.
    Metadata (``name``, ``optimizable_faces`` default all True) is filled in.
    """
    vertices = np.asarray(mesh.vertices, float)
    faces = np.asarray(mesh.faces, np.int64)
    if len(faces) == 0:
        raise AssetError(f"{name}: mesh has no faces")
    uv = _valid_uv(mesh.visual, len(vertices))
    image = _texture_image(mesh.visual) if uv is not None else None
    opt = mesh.metadata.get("optimizable_faces")
    if uv is not None and uv.min() >= 0.0 and uv.max() <= 1.0:
        img = image if image is not None else tx.plain_texture(TEXTURE_SIZE)
        return _make_trimesh(name, vertices, faces, uv, img, opt, {"uv_source": "file"})

    try:
        new_v, new_f, new_uv, vmap = _atlas(vertices, faces)
    except Exception as err:  # xatlas rejects some inputs (e.g. non-manifold fans) with errors
        raise AssetError(f"{name}: UV atlas generation failed ({type(err).__name__}: {err})") from None
    size = TEXTURE_SIZE
    if uv is not None and image is not None:  # tiled UVs: resample the old texture into the atlas
        values = uv[vmap]
        texel_uv, covered = tx.bake_vertex_values(new_f, new_uv, values, size)
        rgb = np.zeros((size, size, 3), np.float64)
        rgb[covered] = tx.sample_texture(image, texel_uv[covered], wrap=True) / 255.0
        img = tx.finish_bake(rgb, covered)
    elif getattr(mesh.visual, "kind", None) == "vertex":
        colors = np.asarray(mesh.visual.vertex_colors, float)[vmap, :3] / 255.0
        rgb, covered = tx.bake_vertex_values(new_f, new_uv, colors, size)
        img = tx.finish_bake(rgb, covered)
    else:
        img = tx.plain_texture(size)
    return _make_trimesh(name, new_v, new_f, new_uv, img, opt, {"uv_source": "atlas"})


# Mesh input is bounded before any parser sees it: the file's size, then its face count (read from
# the OBJ's statements or a binary header), against these caps.
MAX_MESH_FACES = 2_000_000
MAX_MESH_FILE_BYTES = 256 << 20
_MAX_MTL_BYTES = 16 << 20
_MAX_REFERENCE_TOKENS = 64  # words after an mtllib / map statement; real ones have a handful
# MTL statements naming an image: every map_* plus these (the OBJ/MTL spec and its PBR extension).
_MTL_IMAGE_KEYS = {"bump", "disp", "decal", "refl", "norm"}


def _text_variants(text: str) -> list[str]:
    """``text`` as each reader may see it: with CRLF kept or made LF, and with backslash line
    continuations kept, joined (as trimesh does) or turned into a space (as the OBJ spec reads)."""
    out = [text]
    if "\r" in text:
        out.append(text.replace("\r\n", "\n"))
    for t in list(out):
        if "\\" in t:
            out += [t.replace("\\\n", ""), t.replace("\\\n", " ")]
    return out


def _names_after(rest: str, label: str) -> list[str]:
    """Every name a reader may take from the words after a statement's keyword: each word, the
    whole rest (trimesh reads names with spaces so) and every tail of it starting at a word (a
    name with spaces after options such as ``-s 1 1 1``)."""
    words = rest.split()
    if len(words) > _MAX_REFERENCE_TOKENS:
        raise AssetError(f"{label}: a statement has {len(words)} words, more than the {_MAX_REFERENCE_TOKENS} read")
    names, pos = set(words), 0
    for w in words:
        pos = rest.index(w, pos)
        names.add(rest[pos:].strip())
        pos += len(w)
    return sorted(n for n in names if n)


def _beside(base: Path, name: str, label: str, what: str) -> Path:
    """``base / name`` resolved (symlinks followed); refused unless it stays inside ``base``."""
    try:
        target = (base / name).resolve()
        inside = base in target.parents
    except (OSError, ValueError):
        inside = False
    if not inside:
        raise AssetError(
            f"{label}: {what} {name!r} lies outside the mesh's folder {base}; keep materials and images beside the mesh"
        )
    return target


def _lstat_regular(target: Path, name: str, label: str, what: str) -> bool:
    """True for an existing regular file, False when nothing is there; refused otherwise."""
    try:
        mode = os.lstat(target).st_mode
    except OSError:
        return False
    if not stat.S_ISREG(mode):
        raise AssetError(f"{label}: {what} {name!r} is not a regular file")
    return True


def _decode(data: bytes) -> str:
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return data.decode("latin-1")  # every byte one character: "/", "." and spaces read as they are


def _check_obj_references(path: Path, text: str) -> dict[Path, bytes]:
    """Refuse an OBJ whose material libraries or their images lie outside the OBJ's folder (the
    loader would read whatever file they name), or are not regular files (a FIFO would block).

    The statements are read as every reader may: ``mtllib`` anywhere in the text (trimesh takes the
    first occurrence, even in a comment), any whitespace, leading whitespace, several names, line
    continuations; every ``map_*``, ``bump``, ``disp``, ``decal``, ``refl`` and ``norm`` with its
    options. Returns the material libraries read, resolved path -> UTF-8 bytes, for the loader to
    use as checked.
    """
    base = path.resolve().parent
    label = str(path)
    libraries: dict[Path, bytes] = {}
    names: set[str] = set()
    for variant in _text_variants(text):
        for m in re.finditer("mtllib", variant, re.I):
            end = variant.find("\n", m.end())
            line = variant[m.end() : end if end >= 0 else len(variant)]
            for rest in {line, *line.splitlines()[:1]}:
                names.update(_names_after(rest, label))
    for name in sorted(names):
        target = _beside(base, name, label, "mtllib")
        if target in libraries or not _lstat_regular(target, name, label, "mtllib"):
            continue
        mtl = _decode(_read_regular(target, _MAX_MTL_BYTES, f"{label}: mtllib {name!r}", follow=False))
        libraries[target] = mtl.encode("utf-8")
        for variant in _text_variants(mtl):
            for line in {*variant.split("\n"), *variant.splitlines()}:
                words = line.split(None, 1)
                key = words[0].lower() if words else ""
                if len(words) < 2 or not (key.startswith("map_") or key in _MTL_IMAGE_KEYS):
                    continue
                what = f"{target.name}: {words[0]}"
                rest = line[line.lower().index(key) + len(key) :]
                for image in _names_after(rest, label):
                    _beside(base, image, label, what)
                for image in {rest.strip(), *rest.split()[-1:]}:  # what trimesh and the spec open
                    _lstat_regular(_beside(base, image, label, what), image, label, what)
    return libraries


class _FolderResolver(trimesh.resolvers.FilePathResolver):
    """What a mesh file's loader may read besides the file: regular files inside its folder, the
    checked material libraries as checked. A refusal is recorded (the loader swallows errors) and
    the load then fails in one line."""

    def __init__(self, path: Path, served: dict[Path, bytes] | None = None):
        super().__init__(str(path))
        self.base, self.label = Path(self.parent).resolve(), str(path)
        self.served = served or {}
        self.refused: list[str] = []

    def get(self, name):
        name = str(name).strip()
        try:
            target = _beside(self.base, name, self.label, "reference")
            if target in self.served:
                return self.served[target]
            if not _lstat_regular(target, name, self.label, "reference"):
                raise FileNotFoundError(name)
            return _read_regular(target, MAX_MESH_FILE_BYTES, f"{self.label}: reference {name!r}", follow=False)
        except AssetError as err:
            self.refused.append(str(err))
            raise FileNotFoundError(name) from None

    def namespaced(self, namespace: str):
        raise FileNotFoundError(namespace)

    def write(self, name, data):
        raise PermissionError(name)


def _too_many_faces(label: str, n: int, at_least: bool = False) -> AssetError:
    return AssetError(
        f"{label}: {'at least ' if at_least else ''}{n:,} faces, more than the {MAX_MESH_FACES:,} advobj loads; "
        "decimate the mesh first (Blender: Decimate modifier)"
    )


def _check_obj_statements(label: str, text: str) -> None:
    """Before trimesh parses the OBJ: every ``v`` statement has x y z, and the faces (triangles
    after fanning polygons) stay within :data:`MAX_MESH_FACES` (counting stops past the cap)."""
    faces = 0
    if "\\" in text or "\r" in text:
        text = text.replace("\r\n", "\n").replace("\\\n", "")  # as trimesh reads the file
    for m in re.finditer(r"^[ \t]*([vf])[ \t]+([^\n]*)", text, re.M):
        n = len(m.group(2).split())
        if m.group(1) == "f":
            faces += max(n - 2, 1)
            if faces > MAX_MESH_FACES:  # stop here: the scan of a huge file costs no more than the cap
                raise _too_many_faces(label, faces, at_least=True)
        elif n < 3:
            line = text.count("\n", 0, m.start()) + 1
            raise AssetError(f"{label}: line {line}: a vertex needs x y z, got {m.group(0).strip()[:80]!r}")


def _first_nonfinite_vertex_line(text: str) -> int | None:
    for m in re.finditer(r"^[ \t]*v[ \t]+([^\n]*)", text, re.M):
        try:
            if not all(math.isfinite(float(w)) for w in m.group(1).split()[:3]):
                return text.count("\n", 0, m.start()) + 1
        except ValueError:
            return text.count("\n", 0, m.start()) + 1
    return None


def _header_face_count(ext: str, data: bytes) -> int | None:
    """The face count a binary or headed format declares (STL, PLY, OFF, GLB/glTF), None when the
    header does not say; read from the header only."""
    if ext == ".stl" and len(data) >= 84 and not data[:5].lower() == b"solid":
        return struct.unpack("<I", data[80:84])[0]
    if ext == ".stl" and len(data) >= 84 and len(data) == 84 + 50 * struct.unpack("<I", data[80:84])[0]:
        return struct.unpack("<I", data[80:84])[0]  # binary STL whose header text starts with "solid"
    if ext == ".ply":
        head = data[: 1 << 16]
        m = re.search(rb"^element[ \t]+face[ \t]+(\d+)", head, re.M)
        return int(m.group(1)) if m else None
    if ext == ".off":
        words = re.sub(rb"#[^\n]*", b"", data[: 1 << 12]).split()
        if words and words[0].endswith(b"OFF") and len(words) >= 3 and words[2].isdigit():
            return int(words[2])
        return None
    if ext in (".glb", ".gltf"):
        try:
            if ext == ".glb":
                length, kind = struct.unpack("<II", data[12:20])
                doc = json.loads(data[20 : 20 + length]) if kind == 0x4E4F534A else None
            else:
                doc = json.loads(data)
            accessors = doc.get("accessors", [])
            total = 0
            for mesh in doc.get("meshes", []):
                for prim in mesh.get("primitives", []):
                    acc = prim.get("indices", prim.get("attributes", {}).get("POSITION"))
                    count = int(accessors[acc]["count"]) if isinstance(acc, int) else 0
                    total += count // 3 if prim.get("mode", 4) == 4 else max(count - 2, 0)
            return total
        except Exception:  # noqa: BLE001 - not the JSON the format promises: trimesh says so below
            return None
    return None


def load_mesh_file(path: str | os.PathLike, recenter: bool = False, prepare=None) -> trimesh.Trimesh:
    """Load a mesh file (OBJ / GLB / GLTF / PLY / STL / OFF via trimesh) and validate it.

    A multi-part file (``trimesh.Scene``) is concatenated in world placement. Raises
    :class:`AssetError` naming the file for: a missing or non-regular file, an unreadable or
    unsupported format, more than :data:`MAX_MESH_FILE_BYTES` or :data:`MAX_MESH_FACES` (both checked
    before parsing), an OBJ reference leaving the file's folder (:func:`_check_obj_references`), a
    vertex without x y z, no faces, non-finite vertices, or zero total area. Individually degenerate faces
    (area below 1e-12 x bbox diagonal^2) are removed, which ``metadata["notes"]`` records. The origin is kept unless
    ``recenter`` (then: base centre of the bounding box). ``prepare(vertices) -> vertices`` runs on
    the loaded geometry before the UV atlas (units, axes, placement; it may refuse the mesh, and
    then no atlas is built). UVs per :func:`ensure_uv`.
    """
    path = Path(path)
    label = str(path)
    ext = path.suffix.lower()
    if not os.path.lexists(path):
        raise AssetError(f"{label}: mesh file not found")
    if ext not in _MESH_EXTS:
        hint = (
            (
                " (MuJoCo's binary mesh: use the STL/OBJ the MJCF was made from, or write the loaded model's "
                "mesh_vert/mesh_face "
                "out with trimesh)"
            )
            if ext == ".msh"
            else ""
        )
        raise AssetError(
            f"{label}: {path.suffix or 'no extension'} is not a mesh format advobj reads{hint}; give "
            f"{', '.join(sorted(e.lstrip('.').upper() for e in _MESH_EXTS))}"
        )
    if not path.exists():
        raise AssetError(f"{label}: mesh file not found")
    data = _read_regular(path, MAX_MESH_FILE_BYTES, label)  # a FIFO or device is refused, never waited on
    served, text = {}, None
    if ext == ".obj":
        text = _decode(data)
        served = _check_obj_references(path, text)
        _check_obj_statements(label, text)
        data = text.encode("utf-8")  # trimesh parses exactly the text checked here
    else:
        declared = _header_face_count(ext, data)
        if declared is not None and declared > MAX_MESH_FACES:
            raise _too_many_faces(label, declared)
    resolver = _FolderResolver(path, served)
    loaded = failure = None
    try:
        loaded = trimesh.load(io.BytesIO(data), file_type=ext.lstrip("."), resolver=resolver, process=False)
    except ImportError:
        # trimesh only reaches for its optional charset detector when the bytes are not text.
        failure = f"{label}: cannot read mesh (not valid {ext.lstrip('.').upper()} data)"
    except Exception as err:
        failure = f"{label}: cannot read mesh ({type(err).__name__}: {err})"
    if resolver.refused:
        raise AssetError(resolver.refused[0])
    if failure is not None:
        raise AssetError(" ".join(failure.split()))
    if isinstance(loaded, trimesh.Scene):
        geoms = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)] if loaded.geometry else []
        if not geoms:
            raise AssetError(f"{label}: file contains no triangle mesh")
        mesh = geoms[0] if len(geoms) == 1 else trimesh.util.concatenate(geoms)
    elif isinstance(loaded, trimesh.Trimesh):
        mesh = loaded
    else:
        raise AssetError(f"{label}: file contains no triangle mesh (got {type(loaded).__name__})")

    vertices = np.asarray(mesh.vertices, float)
    faces = np.asarray(mesh.faces, np.int64)
    if len(faces) == 0 or len(vertices) == 0:
        raise AssetError(f"{label}: mesh is empty (no faces)")
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise AssetError(f"{label}: vertices need x y z (got {vertices.shape[-1]} coordinates)")
    if len(faces) > MAX_MESH_FACES:
        raise _too_many_faces(label, len(faces))
    if not np.all(np.isfinite(vertices)):
        line = _first_nonfinite_vertex_line(text) if text is not None else None
        raise AssetError(
            f"{label}: {int((~np.isfinite(vertices)).any(-1).sum())} vertices are not finite (NaN/inf)"
            + (f", the first on line {line}" if line else "")
        )
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise AssetError(f"{label}: face indices out of range")
    used = vertices[np.unique(faces)]
    diag = float(np.linalg.norm(used.max(0) - used.min(0)))
    area = np.asarray(mesh.area_faces, float)
    bad = ~(area > _DEGENERATE_REL_AREA * diag * diag)
    if bad.all():
        raise AssetError(f"{label}: zero total area (all {len(faces)} faces are degenerate)")
    notes = []
    if bad.any():
        notes.append(f"{label}: removed {int(bad.sum())} degenerate face(s) of {len(faces)}")
        mesh = mesh.copy()
        mesh.update_faces(~bad)
        mesh.remove_unreferenced_vertices()
    if prepare is not None:
        mesh = mesh.copy() if mesh is loaded else mesh
        mesh.vertices = prepare(np.asarray(mesh.vertices, dtype=np.float64))
    out = ensure_uv(mesh, path.stem)
    out.metadata["source"] = label
    out.metadata["notes"] = notes
    if recenter:
        out.vertices = _to_base_frame(np.asarray(out.vertices, float))
    return out


# ============================================================================ entry point
def _scale_vector(source, scale) -> np.ndarray:
    try:
        s = np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,)).copy()
        if np.ndim(scale) not in (0, 1):
            raise ValueError
    except (TypeError, ValueError):
        raise AssetError(f"{source}: scale must be a positive number or 3 positive numbers, got {scale!r}") from None
    if not (np.all(np.isfinite(s)) and np.all(s > 0)):
        raise AssetError(f"{source}: scale must be positive and finite, got {scale!r}")
    return s


UNITS_M = {"m": 1.0, "cm": 0.01, "mm": 0.001}
# An object a wrist-camera policy reaches for: a coin is about 2 cm, a cereal box 30 cm. Outside
# this range a mesh is almost always in the wrong units (a scan in mm is 1000x too big).
PLAUSIBLE_SIZE_M = (0.01, 0.60)
PLACEMENT_WARN_M = 0.001  # offsets below 1 mm are rounding, not a misplaced origin


def _y_up_to_z_up(v: np.ndarray) -> np.ndarray:
    """+Y-up (glTF, Blender's OBJ/glTF export) to our +Z-up: a +90 deg turn about x."""
    return np.stack([v[:, 0], -v[:, 2], v[:, 1]], -1)


def default_up_axis(source) -> str:
    """The up axis a file's format implies: +Y for glTF (by its spec), +Z otherwise."""
    return "y" if Path(os.fspath(source)).suffix.lower() in (".glb", ".gltf") else "z"


def _size_hint(longest_m: float, scale) -> str:
    for unit, f in (("mm", 0.001), ("cm", 0.01)):
        if PLAUSIBLE_SIZE_M[0] <= longest_m * f <= PLAUSIBLE_SIZE_M[1]:
            return (
                f"set `units: {unit}` on the object if the file is in {unit} ({longest_m * f * 100:.1f} cm then), "
                "or a `scale:` that gives its real size"
            )
    return "set `units: mm|cm|m` or a `scale:` on the object that gives its real size"


def build_mesh(
    source: str | os.PathLike,
    scale: float | tuple[float, float, float] = 1.0,
    units: str = "m",
    up_axis: str | None = None,
    placement: str = "auto",
    warn=None,
    attack_region: str | os.PathLike | None = None,
) -> trimesh.Trimesh:
    """A fresh mesh from a built-in name (:data:`BUILTIN_MESHES`) or a mesh file path, scaled.

    ``scale``: one factor or per-axis (x, y, z) factors of the object frame, applied after
    loading (UVs unchanged). Raises :class:`AssetError` naming the source.

    Mesh files as they come from a scanner or Blender (built-ins are already in metres, +Z up,
    resting on z = 0, centred):

    * ``units`` (m, cm, mm): the file's length unit.
    * ``up_axis`` (z, y; None = by format, :func:`default_up_axis`): which axis points up in the
      file; +Y is turned to +Z.
    * ``placement``: ``auto`` rests the object on its lowest point (z = 0) and centres its
      bounding box in x/y, noting it (``metadata["notes"]``, and ``warn(text)`` when given) when
      that moves it by more than 1 mm; ``keep`` keeps the file's origin (the object frame is the file's).
    * The longest side (after units and scale) must lie within :data:`PLAUSIBLE_SIZE_M`; otherwise
      the mesh is refused in one line suggesting the units that would fit.
    * ``attack_region``: an image in the file's own UV layout whose white texels mark the faces the
      attack may change (:func:`attack_region_faces`); the rest keep the file's texture, in the
      sim and in print. Mesh files with their own UVs only.
    """
    if not isinstance(source, (str, os.PathLike)):
        raise AssetError(f"mesh source must be a built-in name or a file path, got {source!r}")
    s = _scale_vector(source, scale)
    key = os.fspath(source)
    if units not in UNITS_M:
        raise AssetError(f"{key}: units must be one of {', '.join(UNITS_M)}, got {units!r}")
    if up_axis not in (None, "z", "y") or placement not in ("auto", "keep"):
        raise AssetError(f"{key}: up_axis must be z or y and placement auto or keep, got {up_axis!r} / {placement!r}")
    if isinstance(source, str) and key in BUILTIN_MESHES:
        if attack_region is not None:
            raise AssetError(f"{key}: attack_region applies to mesh files; a built-in mesh's optimised faces are fixed")
        mesh = BUILTIN_MESHES[key]()
        if not np.all(s == 1.0):
            mesh.vertices = np.asarray(mesh.vertices) * s
        return mesh
    if Path(key).suffix.lower() not in _MESH_EXTS and not Path(key).exists():
        raise AssetError(f"{key!r}: not a built-in mesh ({', '.join(BUILTIN_MESHES)}) nor a mesh file path")
    placed: list[str] = []  # what placement did, said after loading (after the file's own notes)

    def prepare(v: np.ndarray) -> np.ndarray:
        v = v * UNITS_M[units]
        if (up_axis or default_up_axis(key)) == "y":
            v = _y_up_to_z_up(v)
        v = v * s
        lo, hi = v.min(0), v.max(0)
        longest = float((hi - lo).max())
        if not PLAUSIBLE_SIZE_M[0] <= longest <= PLAUSIBLE_SIZE_M[1]:
            shown = f"{longest:.3g} m" if longest >= 1 else f"{longest * 100:.3g} cm"
            raise AssetError(
                f"{key}: its longest side is {shown} (units {units}, scale {scale}), not a plausible object "
                f"({PLAUSIBLE_SIZE_M[0] * 100:g} cm to {PLAUSIBLE_SIZE_M[1] * 100:g} cm); "
                f"{_size_hint(longest / float(s.max()) / UNITS_M[units], scale)}"
            )
        if placement == "auto":
            shift = np.array([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
            say = placed.append
            if lo[2] < -PLACEMENT_WARN_M:
                say(
                    f"{key}: the mesh reaches {-lo[2] * 100:.1f} cm below its origin (below the table): rested on "
                    "its lowest point"
                )
            elif lo[2] > PLACEMENT_WARN_M:
                say(f"{key}: the mesh floats {lo[2] * 100:.1f} cm above its origin: rested on its lowest point")
            if np.hypot(shift[0], shift[1]) > PLACEMENT_WARN_M:
                say(
                    f"{key}: the origin is {np.hypot(shift[0], shift[1]) * 100:.1f} cm from the base centre in x/y: "
                    "recentred "
                    "(placement: keep keeps the file's origin)"
                )
            v = v + shift
        return v

    mesh = load_mesh_file(key, prepare=prepare)
    mesh.metadata["notes"] = [*mesh.metadata.get("notes", []), *placed]
    for text in mesh.metadata["notes"] if warn is not None else ():
        warn(text)
    if attack_region is not None:
        mesh.metadata["optimizable_faces"] = attack_region_faces(mesh, attack_region, key)
        mesh.metadata["attack_region"] = os.fspath(attack_region)
    return mesh


def scene_mesh_notes(spec) -> list[str]:
    """What loading the mesh files of scene ``spec`` changed (:func:`build_mesh`'s
    ``metadata["notes"]``), one line per note naming its object: degenerate faces dropped, an object
    rested on the table or recentred. Empty for a scene of built-in meshes. ``advobj scene render``
    and ``scene rollout`` print them, where a user checks a new object."""
    out = []
    for o in spec.objects:
        if o.mesh not in BUILTIN_MESHES:
            out += [f"{o.name}: {text}" for text in build_mesh(o.mesh, o.scale, **o.mesh_kwargs()).metadata["notes"]]
    return out


def region_texture(mesh: trimesh.Trimesh, texture_u8: np.ndarray) -> np.ndarray:
    """The texture to put on ``mesh`` for an attack texture ``(h, w, 3)`` uint8: the attack's texels
    where the mesh's optimised faces lie in UV space, the mesh file's own texture everywhere else.

    The one composition behind every look of an attacked object: the renderer applies it to any
    texture set on a mesh (evaluation, the attack's validation, staged trials) and ``advobj
    fabricate`` prints it, so outside an ``attack_region`` all of them show what the attack's
    training renders saw there (the file's texture).

    Only a mesh file with its own UVs and an ``attack_region`` keeps part of its texture; then the
    result has the larger of the two resolutions (the attack's texture resampled bilinearly, as the
    renderer samples it), and the optimised faces' UV triangles, grown by 2 texels against seams,
    take the attack's texels. Any other mesh gets the attack's texture as it is.
    """
    opt = np.asarray(mesh.metadata.get("optimizable_faces", np.ones(len(mesh.faces), bool)), bool)
    image = getattr(getattr(mesh.visual, "material", None), "image", None)
    if mesh.metadata.get("uv_source") != "file" or opt.all() or image is None:
        return texture_u8
    own = np.asarray(image.convert("RGB"))
    h, w = max(own.shape[0], texture_u8.shape[0]), max(own.shape[1], texture_u8.shape[1])
    base = np.asarray(Image.fromarray(own).resize((w, h), Image.BILINEAR)) if own.shape[:2] != (h, w) else own
    attack = np.asarray(Image.fromarray(texture_u8).resize((w, h), Image.BILINEAR))
    region = Image.new("L", (w, h), 0)
    draw = ImageDraw.Draw(region)
    uv = np.asarray(mesh.visual.uv, float)[np.asarray(mesh.faces)[opt]]
    for tri in uv:
        draw.polygon([(u * w, (1.0 - v) * h) for u, v in tri], fill=255)
    mask = np.asarray(region.filter(ImageFilter.MaxFilter(5))) > 0
    return np.where(mask[..., None], attack, base).astype(np.uint8)


def attack_region_faces(mesh: trimesh.Trimesh, region: str | os.PathLike, label: str = "mesh") -> np.ndarray:
    """(F,) bool: the faces whose UV centroid falls on a white (> 50 %) texel of image ``region``.

    The image is read in the mesh's own UV layout (u right, v up, any size); the mesh must keep
    the UVs of its file (an atlas made here would not match an image painted on the file's).
    """
    path = Path(region)
    if mesh.metadata.get("uv_source") != "file":
        raise AssetError(
            f"{label}: attack_region needs the mesh file's own UVs in [0, 1]; this mesh had none (advobj made a "
            "UV atlas), "
            "so an image painted on the file's layout cannot match it: unwrap the mesh (Blender: Smart UV Project) "
            "and export again"
        )
    try:
        with Image.open(path) as im:
            gray = np.asarray(im.convert("L"), dtype=np.float64) / 255.0
    except FileNotFoundError:
        raise AssetError(f"{path}: attack_region image not found") from None
    except (OSError, ValueError, Image.DecompressionBombError) as err:
        raise AssetError(f"{path}: attack_region is not a readable image ({type(err).__name__}: {err})") from None
    h, w = gray.shape
    uv = np.asarray(mesh.visual.uv, float)[np.asarray(mesh.faces)].mean(1)
    col = np.clip((uv[:, 0] * w).astype(np.int64), 0, w - 1)
    row = np.clip(((1.0 - uv[:, 1]) * h).astype(np.int64), 0, h - 1)
    faces = gray[row, col] > 0.5
    if not faces.any():
        raise AssetError(
            f"{path}: attack_region marks no face of {label} white; paint the region to attack white on its UV layout"
        )
    return faces
