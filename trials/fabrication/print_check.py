"""Pre-print check: read the optimised texture back from the rasterised print sheet and compare.

Every texel of the mesh's UV layout is a point on the object's surface. The pieces' fold models
(:meth:`trials.fabrication.fabricate.Piece.paper_of_surface`) say where that point comes from on the paper;
adding the piece's page placement gives sheet millimetres, and the page raster (the very figure
saved to the PDF, rasterised with Agg at the print DPI) is sampled there. The resulting *printed-
back* texture is rendered on the mesh with the real renderer next to the optimised one from
several viewpoints (object pixels only). The check also compares each piece's printed size with
the mesh's physical size. Nothing here reads the UV boxes the sheet was drawn from, so a UV,
orientation, placement or scale mistake in the sheet shows up as a difference.

A tag card (:func:`check_card`) is read back the way a camera reads it: the tag is detected in the
page raster with the project's detector, its printed size compared with the intended one, and the
object's footprint, carried from the detected tag through the recorded ``T_obj_tag`` (the tag's
pose in the object frame), must land on the outline and the origin cross the card draws. A card
drawn mirrored, shifted or at another scale than the ``T_obj_tag`` a locator will use fails there.
A mesh without a net gets the card alone, and this is its whole check.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import imageio.v3 as iio
import numpy as np
from PIL import Image, ImageDraw
from tqdm import tqdm

from calibration.apriltag import detect_tag_corners
from sim import textures as tx
from sim.geometry import invert_T, look_at, make_T, transform_points
from sim.imaging import hstack, labelled
from sim.render import SceneRenderer
from sim.spec import default_scene
from trials.fabrication.base import FabricationError, mesh_ring_mm, sample_page

__all__ = [
    "CheckResult",
    "reconstruct_texture",
    "scale_errors",
    "check_print",
    "check_card",
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
CARD_INK = 245  # a page pixel greyer than this (0-255) carries ink: the card's thin outline is antialiased
CARD_TOL_MM = 0.5  # the footprint from the read-back tag must lie this close to the drawn ink (at least 1.5 px)
MIN_OUTLINE_ON_INK = 0.8  # share of the carried footprint outline that must lie on the drawn outline
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
    card: dict | None = None  # check_card's result, for a layout with a tag card
    card_image: np.ndarray | None = field(repr=False, default=None)  # the card read back, overlaid

    @property
    def mean_mae(self) -> float:
        return float(np.mean(self.view_mae)) if self.view_mae else 0.0

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
        if self.view_mae and (self.mean_mae > self.max_mean or max(self.view_mae) > self.max_view):
            worst = max(self.piece_mae, key=self.piece_mae.get) if self.piece_mae else "?"
            out.append(
                f"printed-back renders differ: mean abs error {self.mean_mae:.4f} (max {self.max_mean}), worst view "
                f"{max(self.view_mae):.4f} (max {self.max_view}); worst piece {worst} "
                f"(texel error {self.piece_mae.get(worst, float('nan')):.4f})"
            )
        if self.unread_texels:
            out.append(f"{self.unread_texels} texel(s) of the mesh are printed on no piece")
        if self.card is not None:
            out += self.card["failures"]
        return out

    @property
    def passed(self) -> bool:
        return not self.failures

    def message(self) -> str:
        if not self.passed:
            return "; ".join(self.failures)
        parts = []
        if self.view_mae:
            parts.append(
                f"render mean abs error {self.mean_mae:.4f}, worst view {max(self.view_mae):.4f}; "
                f"scale within {max(abs(s['error_mm']) for s in self.scale):.3f} mm"
            )
        if self.card is not None:
            c = self.card
            parts.append(
                f"tag card: tag {c['tag_id']} read back {c['tag_size_mm']:.2f} mm (error {c['size_error_mm']:+.2f} "
                f"mm), {100 * c['outline_on_ink']:.0f} % of the footprint carried through T_obj_tag on its outline"
            )
        return "; ".join(parts)

    def summary(self) -> dict:
        return {
            "passed": self.passed,
            "mean_abs_error": self.mean_mae,
            "max_view_abs_error": max(self.view_mae) if self.view_mae else None,
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
            "views_deg": [list(v) for v in VIEWS_DEG] if self.view_mae else [],
            "card": self.card,
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


def _outline_mm(mesh, step_mm: float = 0.5) -> np.ndarray:
    """(N, 2) points every ``step_mm`` along the convex outline of ``mesh`` seen from above (object frame, mm)."""
    xy = np.asarray(mesh.vertices, float)[:, :2] * 1000.0
    hull = cv2.convexHull(xy.astype(np.float32)).reshape(-1, 2).astype(float)
    pts = []
    for a, b in zip(hull, np.roll(hull, -1, 0)):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step_mm)))
        pts.append(a + (b - a) * (np.arange(n) / n)[:, None])
    return np.concatenate(pts)


def check_card(layout, rasters: list[np.ndarray], mesh, T_obj_tag=None) -> tuple[dict, np.ndarray | None]:
    """Read the layout's tag card back from its page raster: ``(result, overlay image)``.

    The tag is found with :func:`calibration.apriltag.detect_tag_corners` in the card's part of the
    page (pixel centres at integers, so a corner at pixel ``p`` lies at ``(p + 0.5) / px_per_mm``
    mm). Its frame on paper (+x along its top edge, +y toward it, as the tag frame of
    :mod:`calibration.apriltag`) carries the mesh's convex outline and frame origin from the object
    frame through ``inv(T_obj_tag)`` (default: the card's recorded one) onto the page, where the
    card's drawn outline and cross must lie within :data:`CARD_TOL_MM` (1.5 px at least).

    Result: ``tag_id``, ``found``, ``tag_size_mm`` (mean side read back), ``size_error_mm``,
    ``outline_on_ink`` (share of the carried outline on ink), ``origin_error_mm`` (distance from
    the carried origin to ink), ``failures`` (one line each, empty when the card passes).
    """
    card = next(p for p in layout.pieces if p.kind == "card")
    f = card.fold
    T_obj_tag = f["T_obj_tag"] if T_obj_tag is None else np.asarray(T_obj_tag, float)
    at = layout.where(card.name)
    page = rasters[at.page]
    ppm = page.shape[1] / layout.page_mm[0]  # px per mm
    tol_mm = max(CARD_TOL_MM, 1.5 / ppm)
    size_tol = max(MAX_SCALE_ERROR_MM, 1.0 / ppm)
    gray = np.asarray(page, float).mean(-1).astype(np.uint8)
    x0, y0 = int(max(0, np.floor((at.x_mm - 2) * ppm))), int(max(0, np.floor((at.y_mm - 2) * ppm)))
    x1 = int(min(gray.shape[1], np.ceil((at.x_mm + card.size_mm[0] + 2) * ppm)))
    y1 = int(min(gray.shape[0], np.ceil((at.y_mm + card.size_mm[1] + 2) * ppm)))
    crop = gray[y0:y1, x0:x1]
    out = {"tag_id": int(f["tag_id"]), "found": False, "tag_size_mm": None, "size_error_mm": None}
    out.update(outline_on_ink=0.0, origin_error_mm=None, thresholds={"size_mm": size_tol, "tolerance_mm": tol_mm})
    hits = [c for i, c in detect_tag_corners(crop) if i == f["tag_id"]]
    if not hits:
        out["failures"] = [f"tag card: tag36h11 id {f['tag_id']} cannot be read from the printed page"]
        return out, None
    c_mm = (hits[0] + [x0, y0] + 0.5) / ppm  # TL, TR, BR, BL of the tag, page mm (y down)
    side = float(np.mean(np.linalg.norm(c_mm - np.roll(c_mm, -1, 0), axis=1)))
    ux = (c_mm[1] - c_mm[0]) + (c_mm[2] - c_mm[3])
    uy = (c_mm[0] - c_mm[3]) + (c_mm[1] - c_mm[2])
    ux, uy = ux / np.linalg.norm(ux), uy / np.linalg.norm(uy)
    centre = c_mm.mean(0)

    def paper(points_obj_mm: np.ndarray) -> np.ndarray:
        """Object-frame points (N, 2) mm on the card's plane -> page mm through the read-back tag."""
        z = np.full((len(points_obj_mm), 1), T_obj_tag[2, 3])
        p_tag = transform_points(invert_T(T_obj_tag), np.concatenate([points_obj_mm / 1000.0, z], 1))
        return centre + 1000.0 * (p_tag[:, :1] * ux + p_tag[:, 1:2] * uy)

    ink = gray < CARD_INK
    dist_mm = cv2.distanceTransform((~ink).astype(np.uint8), cv2.DIST_L2, 5) / ppm

    def off_ink(pts_mm: np.ndarray) -> np.ndarray:
        px = np.clip(np.rint(pts_mm * ppm - 0.5).astype(int), 0, [gray.shape[1] - 1, gray.shape[0] - 1])
        return dist_mm[px[:, 1], px[:, 0]]

    outline = paper(_outline_mm(mesh))
    origin = paper(np.zeros((1, 2)))
    on = float(np.mean(off_ink(outline) <= tol_mm))
    origin_err = float(off_ink(origin)[0])
    out.update(
        found=True,
        tag_size_mm=side,
        size_error_mm=side - float(f["tag_size_mm"]),
        outline_on_ink=on,
        origin_error_mm=origin_err,
    )
    fails = []
    if abs(out["size_error_mm"]) > size_tol:
        fails.append(
            f"tag card: tag {f['tag_id']} printed {side:.2f} mm, the registry says {f['tag_size_mm']:g} mm "
            f"(tolerance {size_tol:.2f} mm)"
        )
    if on < MIN_OUTLINE_ON_INK or origin_err > tol_mm:
        fails.append(
            f"tag card: the footprint carried from the read-back tag through T_obj_tag misses the drawn outline "
            f"({100 * on:.0f} % on it, need {100 * MIN_OUTLINE_ON_INK:.0f} %; origin {origin_err:.2f} mm from the "
            "cross): the card and the T_obj_tag a locator uses disagree"
        )
    out["failures"] = fails
    # The card as read: the page crop, the read-back tag (green) and the carried footprint (red).
    zoom = max(1, int(np.ceil(600 / max(1, crop.shape[1]))))
    img = Image.fromarray(np.asarray(page)[y0:y1, x0:x1]).resize((crop.shape[1] * zoom, crop.shape[0] * zoom), 0)
    draw = ImageDraw.Draw(img)

    def xy(pts_mm):
        return [tuple(v) for v in ((pts_mm * ppm - 0.5 - [x0, y0] + 0.5) * zoom)]

    draw.polygon(xy(c_mm), outline=(0, 170, 0), width=max(1, zoom // 2))
    draw.line(xy(np.concatenate([outline, outline[:1]])), fill=(220, 0, 0), width=max(1, zoom // 2))
    (ox, oy) = xy(origin)[0]
    r = 3 * zoom
    draw.line([(ox - r, oy), (ox + r, oy)], fill=(220, 0, 0), width=max(1, zoom // 2))
    draw.line([(ox, oy - r), (ox, oy + r)], fill=(220, 0, 0), width=max(1, zoom // 2))
    return out, np.asarray(img)


def check_print(layout, rasters, mesh, texture: np.ndarray, progress: bool = False, T_obj_tag=None) -> CheckResult:
    """Compare the sheet's printed-back texture with ``texture`` (H, W, 3) uint8 on ``mesh``, and
    read its tag card back (:func:`check_card`, with ``T_obj_tag`` when given). A layout of the
    tag card alone gets the card check only."""
    card, card_image = (None, None)
    if any(p.kind == "card" for p in layout.pieces):
        card, card_image = check_card(layout, rasters, mesh, T_obj_tag)
    if all(p.kind == "card" for p in layout.pieces):
        return CheckResult([], 0.0, {}, 0, [], card=card, card_image=card_image)
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
    return CheckResult(
        view_mae,
        float(diff[covered].mean()),
        piece_mae,
        unread,
        scale_errors(layout, mesh),
        renders,
        card=card,
        card_image=card_image,
    )


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
    one column per view). The tag card read back (its page crop, the detected tag in green, the
    footprint carried through ``T_obj_tag`` in red) is ``print_check.png`` for the card alone, else
    ``print_check_card.png``."""
    out = Path(out_dir)
    (out / "print_check.json").write_text(json.dumps(result.summary(), indent=2))
    paths = {"json": out / "print_check.json"}
    if result.renders:
        iio.imwrite(out / "print_check.png", _check_figure(result))
        paths["png"] = out / "print_check.png"
    if result.card_image is not None:
        name = "print_check_card.png" if result.renders else "print_check.png"
        iio.imwrite(out / name, result.card_image)
        paths["card_png" if result.renders else "png"] = out / name
    return paths
