"""Pre-print check: read the optimised texture back from the rasterised print sheet and compare.

Every texel of the mesh's UV layout is a point on the object's surface. The pieces' fold models
(:meth:`trials.fabrication.fabricate.Piece.paper_of_surface`) say where that point comes from on the paper;
adding the piece's page placement gives sheet millimetres, and the page raster (the very figure
saved to the PDF, rasterised with Agg at the print DPI) is sampled there. The resulting *printed-
back* texture is rendered on the mesh with the real renderer next to the optimised one from
several viewpoints (object pixels only). The check also compares each piece's printed size with
the mesh's physical size. Nothing here reads the UV boxes the sheet was drawn from, so a UV,
orientation, placement or scale mistake in the sheet shows up as a difference.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import imageio.v3 as iio
import numpy as np
from PIL import Image, ImageDraw
from tqdm import tqdm

from sim import textures as tx
from sim.geometry import look_at, make_T
from sim.imaging import hstack, labelled
from sim.render import SceneRenderer
from sim.spec import default_scene
from trials.fabrication.base import FabricationError, mesh_ring_mm, sample_page

__all__ = [
    "CheckResult",
    "reconstruct_texture",
    "scale_errors",
    "check_print",
    "write_check",
    "MAX_MEAN_ERROR",
    "MAX_VIEW_ERROR",
    "MAX_REGION_ERROR",
    "MAX_SCALE_ERROR_MM",
]

MAX_MEAN_ERROR = 0.03  # mean abs error / 255 over object pixels, all views
MAX_VIEW_ERROR = 0.05  # the worst single view
MAX_REGION_ERROR = 0.08  # mean abs error / 255 of the texels read back from one printed region
MAX_SCALE_ERROR_MM = 0.3  # printed piece size vs the mesh's physical size
UNREAD_RGB = (255, 0, 255)  # texels no piece prints: loud magenta in the printed-back renders
RENDER_PX = 256
FILL = 0.6  # the object's bounding sphere spans this fraction of the view's field
LIFT_M = 0.5  # object lifted above the table so views from below see it against the backdrop
# (azimuth, elevation) in degrees around the object; two from below for the bottom face.
VIEWS_DEG = ((30, 35), (120, 35), (210, 35), (300, 35), (75, 80), (255, 10), (45, -60), (225, -60))


@dataclass
class CheckResult:
    view_mae: list[float]
    texture_mae: float
    piece_mae: dict[str, float]
    unread_texels: int
    scale: list[dict]
    renders: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = field(
        repr=False, default_factory=list
    )  # (optimised, printed, mask)
    max_mean: float = MAX_MEAN_ERROR
    max_view: float = MAX_VIEW_ERROR
    max_region: float = MAX_REGION_ERROR
    max_scale_mm: float = MAX_SCALE_ERROR_MM

    @property
    def mean_mae(self) -> float:
        return float(np.mean(self.view_mae))

    @property
    def failures(self) -> list[str]:
        out = [
            f"piece {s['piece']}: {s['measure']} printed {s['printed_mm']:.2f} mm, the object needs "
            f"{s['expected_mm']:.2f} mm"
            for s in self.scale
            if abs(s["error_mm"]) > self.max_scale_mm
        ]
        out += [
            f"{name}: printed-back texels differ from the texture by {err:.3f} (max {self.max_region}); "
            "mirrored, rotated or swapped?"
            for name, err in self.piece_mae.items()
            if err > self.max_region
        ]
        if self.mean_mae > self.max_mean or max(self.view_mae) > self.max_view:
            worst = max(self.piece_mae, key=self.piece_mae.get) if self.piece_mae else "?"
            out.append(
                f"printed-back renders differ: mean abs error {self.mean_mae:.4f} (max {self.max_mean}), worst view "
                f"{max(self.view_mae):.4f} (max {self.max_view}); worst piece {worst} "
                f"(texel error {self.piece_mae.get(worst, float('nan')):.4f})"
            )
        if self.unread_texels:
            out.append(f"{self.unread_texels} texel(s) of the mesh are printed on no piece")
        return out

    @property
    def passed(self) -> bool:
        return not self.failures

    def message(self) -> str:
        if self.passed:
            return (
                f"render mean abs error {self.mean_mae:.4f}, worst view {max(self.view_mae):.4f}; "
                f"scale within {max(abs(s['error_mm']) for s in self.scale):.3f} mm"
            )
        return "; ".join(self.failures)

    def summary(self) -> dict:
        return {
            "passed": self.passed,
            "mean_abs_error": self.mean_mae,
            "max_view_abs_error": max(self.view_mae),
            "view_abs_error": self.view_mae,
            "texture_abs_error": self.texture_mae,
            "piece_texture_abs_error": self.piece_mae,
            "unread_texels": self.unread_texels,
            "scale": self.scale,
            "thresholds": {
                "mean_abs_error": self.max_mean,
                "max_view_abs_error": self.max_view,
                "piece_texture_abs_error": self.max_region,
                "scale_mm": self.max_scale_mm,
            },
            "failures": self.failures,
            "views_deg": [list(v) for v in VIEWS_DEG],
        }


def reconstruct_texture(
    layout, rasters: list[np.ndarray], mesh, size: int
) -> tuple[np.ndarray, dict, np.ndarray, np.ndarray]:
    """The texture as the printed sheet would put it on the object.

    Args:
        layout: :class:`trials.fabrication.fabricate.SheetLayout`; rasters: its page images (H_px, W_px, 3).
        mesh: the object (m); size: texture side S in px.
    Returns:
        texture (S, S, 3) uint8 (gutters dilated, unread texels magenta), owner (piece or
        ``"piece tile name"`` -> (S, S) bool texels read from that printed region), covered (S, S)
        bool texels some face maps to, unread (S, S) bool covered texels no piece prints.
    """
    faces = np.asarray(mesh.faces, np.int64)
    verts = np.asarray(mesh.vertices, float) * 1000.0
    face_id, bary = tx.rasterize_uv(np.asarray(mesh.visual.uv, float), faces, size)
    covered = face_id >= 0
    f = face_id[covered]
    points = (verts[faces[f]] * bary[covered][..., None]).sum(-2)
    normals = np.asarray(mesh.face_normals, float)[f]
    rgb = np.zeros((len(f), 3))
    read = np.zeros(len(f), bool)
    owner = {}
    W_mm, H_mm = layout.page_mm
    for piece in layout.pieces:
        if piece.kind == "card":
            continue
        at = layout.where(piece.name)
        page = rasters[at.page]
        paper, ok = piece.paper_of_surface(points, normals)
        ok &= ~read
        px = (paper[ok] + [at.x_mm, at.y_mm]) * [page.shape[1] / W_mm, page.shape[0] / H_mm]
        rgb[ok] = tx_sample(page, px)
        read |= ok
        # Attribute texels to the printed region they were read from, so a failure names it.
        for reg in piece.regions:
            x, y, w, h = reg.rect_mm
            inside = ok & (paper[:, 0] >= x) & (paper[:, 0] <= x + w) & (paper[:, 1] >= y) & (paper[:, 1] <= y + h)
            m = np.zeros(covered.shape, bool)
            m[covered] = inside
            owner[piece.name if len(piece.regions) == 1 else f"{piece.name} tile {reg.name}"] = m
    rgb[~read] = np.asarray(UNREAD_RGB, float)
    full = np.zeros((size, size, 3))
    full[covered] = rgb / 255.0
    unread = np.zeros(covered.shape, bool)
    unread[covered] = ~read
    return tx.finish_bake(full, covered), owner, covered, unread


def tx_sample(page: np.ndarray, xy_px: np.ndarray) -> np.ndarray:

    return sample_page(page, xy_px)


def scale_errors(layout, mesh) -> list[dict]:
    """Printed size (mm) of every piece's measures vs the mesh's physical size."""

    ext = np.asarray(mesh.extents, float) * 1000.0
    rows = []

    def row(piece, measure, printed, expected):
        rows.append(
            {
                "piece": piece,
                "measure": measure,
                "printed_mm": float(printed),
                "expected_mm": float(expected),
                "error_mm": float(printed - expected),
            }
        )

    for p in layout.pieces:
        if p.kind == "cube_net":
            axes = {"x": 0, "y": 1, "z": 2}
            for name, (_, (x, y, w, h)) in p.fold["tiles"].items():
                other = [a for a in "xyz" if a != name[1]]  # the two axes spanning this face
                row(p.name, f"tile {name} width", w, ext[axes[other[0]]])
                row(p.name, f"tile {name} height", h, ext[axes[other[1]]])
        elif p.kind == "wrap":
            ring = mesh_ring_mm(mesh)
            perimeter = np.linalg.norm(np.diff(np.concatenate([ring, ring[:1]]), axis=0), axis=-1).sum()
            row(p.name, "wrap length (perimeter)", p.regions[0].rect_mm[2], perimeter)
            row(p.name, "wrap height", p.regions[0].rect_mm[3], ext[2])
        elif p.kind in ("cap_top", "cap_bottom"):
            cut = np.asarray(p.cut_mm[0], float)
            row(p.name, "cap diameter (cut line)", np.ptp(cut[:, 0]), ext[0])
            row(p.name, "cap printed width", p.regions[0].rect_mm[2], ext[0])
    return rows


def _render_views(
    mesh_name: str, textures: list[np.ndarray], progress: bool = False
) -> list[list[tuple[np.ndarray, np.ndarray]]]:
    """Render the mesh with each texture from :data:`VIEWS_DEG`: per texture, per view (rgb, mask)."""
    spec = default_scene()
    objs = [
        {**o.with_mesh(mesh_name), "scale": 1.0} if o.role == "adversarial" else o.model_dump() for o in spec.objects
    ]
    spec = spec.with_updates(objects=objs)
    k = spec.object_index("adversarial")
    out = [[] for _ in textures]
    with SceneRenderer(spec, RENDER_PX, RENDER_PX) as r:
        T = np.repeat(np.eye(4)[None], len(spec.objects), 0)
        for j in range(len(spec.objects)):
            T[j, :3, 3] = (5.0 + j, 5.0, 0.0)  # far away; hidden below as well
            if j != k:
                r.set_object_visible(j, False)
        T[k] = make_T(np.eye(3), np.array([0.0, 0.0, LIFT_M]))
        r.set_state(T, None)
        lo, hi = np.asarray(r.object_mesh(k).bounds)
        centre = np.array([0.0, 0.0, LIFT_M]) + (lo + hi) / 2
        half_fov = np.arctan(RENDER_PX / 2 / r.K[1, 1])
        distance = np.linalg.norm(hi - lo) / 2 / np.sin(FILL * half_fov)
        for az, el in tqdm(VIEWS_DEG, desc="print check", unit="view", disable=not progress):
            a, e = np.radians(az), np.radians(el)
            eye = centre + distance * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
            T_cam = look_at(eye, centre)
            mask = None
            for t, tex in enumerate(textures):
                r.set_object_texture(k, tex)
                o = r.render(T_cam, with_ids=mask is None)
                if mask is None:
                    mask = o.object_mask(k)
                out[t].append((o.rgb, mask))
    return out


def check_print(layout, rasters, mesh, texture: np.ndarray, progress: bool = False) -> CheckResult:
    """Compare the sheet's printed-back texture with ``texture`` (H, W, 3) uint8 on ``mesh``."""

    h, w = texture.shape[:2]
    if h != w:
        raise FabricationError(f"texture: the check needs a square texture, got {h} x {w}")
    recon, owner, covered, unread_mask = reconstruct_texture(layout, rasters, mesh, h)
    diff = np.abs(recon.astype(float) - texture.astype(float)).mean(-1) / 255.0
    piece_mae = {name: float(diff[m].mean()) for name, m in owner.items() if m.any()}
    unread = int(unread_mask.sum())
    views = _render_views(mesh.metadata.get("source", mesh.metadata["name"]), [texture, recon], progress)
    view_mae, renders = [], []
    for (a, mask), (b, _) in zip(*views):
        d = np.abs(a.astype(float) - b.astype(float)).mean(-1)[mask] / 255.0
        view_mae.append(float(d.mean()) if d.size else 0.0)
        renders.append((a, b, mask))
    return CheckResult(view_mae, float(diff[covered].mean()), piece_mae, unread, scale_errors(layout, mesh), renders)


ROW_LABELS = ("optimised", "printed back", "|diff| x 4")


def _check_figure(result: CheckResult) -> np.ndarray:
    """``print_check.png``: one column per view (its azimuth, elevation and error above it), rows
    :data:`ROW_LABELS` named at the left: the optimised texture's render, the printed-back one's,
    and their absolute difference times 4 on the object's pixels."""
    cols = []
    for (a, b, mask), (az, el), err in zip(result.renders, VIEWS_DEG, result.view_mae):
        d = np.abs(a.astype(np.int16) - b.astype(np.int16)) * 4
        d[~mask] = 0
        col = np.concatenate([a, b, np.clip(d, 0, 255).astype(np.uint8)], 0)
        cols.append(labelled(col, f"view az {az}, el {el}: error {err:.4f}", min_side=1))
    grid = hstack(cols)
    top_px, row_px = grid.shape[0] - 3 * result.renders[0][0].shape[0], result.renders[0][0].shape[0]
    side = Image.new("RGB", (96, grid.shape[0]), (255, 255, 255))
    draw = ImageDraw.Draw(side)
    for i, text in enumerate(ROW_LABELS):
        draw.text((6, top_px + i * row_px + row_px // 2 - 5), text, fill=(0, 0, 0))
    return np.concatenate([np.asarray(side), grid], 1)


def write_check(out_dir, result: CheckResult) -> dict[str, Path]:
    """``print_check.json`` and ``print_check.png`` (rows: optimised, printed back, |diff| x4;
    one column per view)."""
    out = Path(out_dir)
    (out / "print_check.json").write_text(json.dumps(result.summary(), indent=2))
    iio.imwrite(out / "print_check.png", _check_figure(result))
    return {"json": out / "print_check.json", "png": out / "print_check.png"}
