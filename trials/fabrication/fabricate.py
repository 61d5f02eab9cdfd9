"""True-scale print sheets and colour-3D-print meshes from an attack run.

A *sheet layout* is a list of :class:`Piece` s placed on pages. Each piece carries :class:`Region`
s, each printing one UV box of the optimised texture into a rectangle of the piece, at true
scale (one UV unit = ``uv_side_m`` * 1000 mm of paper), resampled at the print DPI with the
renderer's filtering (bilinear, clamp to edge). Coordinates on paper are millimetres, x right and
y down, in the piece's frame (``*_mm`` local) or the page's (piece origin + local).

Printable shapes (:data:`SHEET_SHAPES`):

* ``cube``: the cross-shaped net of the texture's 4 x 3 tile layout (it *is* a net: the middle
  row wraps -x, -y, +x, +y counter-clockwise seen from above, +z above and -z below -y), printed
  side out, glue tabs on the cut edges of the wrap tiles (+z and -z close onto them);
* ``cylinder``: the side wrap (perimeter x height, a seam tab on its right edge, toothed tabs along
  top and bottom that fold in under the caps) and the two caps, each a disk seen from outside.

How paper becomes the object (the *fold model*, :meth:`Piece.paper_of_surface`) is independent of
the UV mapping: the cube net is folded in 3D edge by edge from its front tile, the wrap rolls up
by arc length from the seam, the caps lie flat. The pre-print check (:mod:`trials.fabrication.print_check`)
uses it to read every texel back from the rasterised page, so a mirrored, rotated, swapped or
mis-scaled print shows up before paper is wasted.

Tag card: an optional piece with an AprilTag (tag36h11) and the object's footprint beside it at
a known offset, for any mesh (a mesh without a net gets a sheet holding the card alone,
:data:`CARD`). Lay it on the table and stand the object on the footprint; the tag then locates
the object without covering any of its optimised surface: the card records the tag's pose in the
object frame ``T_obj_tag`` and :func:`tag_registry` makes the registry entry from it. The object
to make is the run's mesh, or an object of a scene named by the user (``--scene S --shape NAME``,
:mod:`trials.fabrication.shapes`), whose mesh the run must have optimised.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import cv2
import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.patches import Polygon, Rectangle
from PIL import Image, ImageDraw
from tqdm import tqdm

from attack.artifact import RUN_JSON, AttackArtifact
from attack.outputs import export_meshes
from calibration.io import T_to_pose
from calibration.printables import image_mm, page_figure, scale_bar
from calibration.registry import ObjectRegistry, save_registry
from sim.assets import AssetError, build_mesh, region_texture, texel_density_ratio
from sim.geometry import invert_T, make_T, so3_exp
from sim.runinfo import write_run_info
from sim.spec import load_spec
from trials.fabrication.base import FabricationError, mesh_ring_mm, sample_bilinear
from trials.fabrication.print_check import check_print, write_check
from trials.fabrication.shapes import RunSource, ShapeError, load_run, run_mesh_problem, scene_shape

__all__ = [
    "SHEET_SHAPES",
    "CARD",
    "PAGES_MM",
    "CHECK_LINE_MM",
    "Region",
    "Piece",
    "Item",
    "Placed",
    "SheetLayout",
    "LayoutTweak",
    "RunSource",
    "load_run",
    "region_raster",
    "fold_cube_net",
    "cube_pieces",
    "cylinder_pieces",
    "tag_card",
    "build_layout",
    "tag_registry",
    "draw_pages",
    "fabricate",
]

SHEET_SHAPES = ("cube", "cylinder")
CARD = "card"  # a layout of the tag card alone, for a mesh without a net
PAGES_MM = {"a4": (210.0, 297.0), "letter": (215.9, 279.4), "a3": (297.0, 420.0)}
MARGIN_MM = 8.0  # printers do not reach the paper's edge
GAP_MM = 3.0  # clearance kept around every item on a page
TAB_MM = 7.0  # glue-tab depth
CHECK_LINE_MM = 100.0
CUT_LW_PT = 0.5  # ~0.18 mm: thin enough not to eat the texture along edges
FOLD_LW_PT = 0.35
MM_PER_INCH = 25.4
BLEED_MM = 1.0  # texture printed past a cap's cut line so a slightly wide cut shows no white


# ============================================================================ inputs
def optimised_texel_size_mm(mesh, width_px: int, height_px: int) -> dict | None:
    """How large one texel of a ``width_px x height_px`` texture is on the mesh's optimised faces:
    the side (mm) of a texel's footprint per face (sqrt of 3D area over texel count), its
    area-weighted median and 10th/90th percentiles. None if no optimised face has UV area."""
    per_uv = texel_density_ratio(mesh)  # metres per UV unit, per face
    opt = np.asarray(mesh.metadata.get("optimizable_faces", np.ones(len(mesh.faces), bool)), bool)
    ok = opt & np.isfinite(per_uv)
    if not ok.any():
        return None
    # One UV unit holds sqrt(width x height) texels along a side (square pixels in UV space).
    mm = per_uv[ok] * 1000.0 / np.sqrt(float(width_px) * float(height_px))
    w = np.asarray(mesh.area_faces)[ok]
    order = np.argsort(mm)
    cdf = np.cumsum(w[order]) / w.sum()
    q = lambda p: float(mm[order][min(np.searchsorted(cdf, p), len(order) - 1)])  # noqa: E731
    return {"median": q(0.5), "p10": q(0.1), "p90": q(0.9)}


# ============================================================================ layout data
@dataclass(frozen=True)
class Region:
    """One UV box printed upright (u right, v up) into ``rect_mm = (x, y, w, h)`` of its piece.

    ``transform`` exists to inject mistakes in tests of the pre-print check: ``"mirror"``,
    ``"rot90"`` or ``"rot180"`` of the printed image inside its rectangle.
    """

    name: str
    uv_box: tuple[float, float, float, float]  # (u0, v0, u1, v1)
    rect_mm: tuple[float, float, float, float]
    transform: str = "none"


@dataclass(frozen=True)
class Piece:
    """Something cut out of a page: printed regions, cut and fold lines, and how it folds.

    ``kind``: ``cube_net``, ``wrap``, ``cap_top``, ``cap_bottom`` or ``card``. ``fold`` holds the
    kind's geometry for :meth:`paper_of_surface` (mm, object frame). ``footprint_mm``: rectangles
    (x, y, w, h) the piece covers, for packing.
    """

    name: str
    kind: str
    size_mm: tuple[float, float]
    regions: tuple[Region, ...] = ()
    cut_mm: tuple = ()  # closed polygons, each ((x, y), ...)
    fold_mm: tuple = ()  # segments ((x0, y0), (x1, y1))
    footprint_mm: tuple = ()
    labels: tuple = ()  # (text, x_mm, y_mm, fontsize_pt, rotation_deg)
    fold: dict = field(default_factory=dict)

    def paper_of_surface(self, points_mm: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where on this piece the object's surface points come from (the fold model).

        Args:
            points_mm: (N, 3) surface points, object frame, mm; normals: (N, 3) unit outward.
        Returns:
            paper_mm (N, 2) in the piece frame, and valid (N,) bool: the point lies on this piece.
        """
        n = len(points_mm)
        out, ok = np.zeros((n, 2)), np.zeros(n, bool)
        f = self.fold
        if self.kind == "cube_net":
            for name, (T, rect) in f["tiles"].items():
                q = (np.asarray(points_mm) - T[:3, 3]) @ T[:3, :3]  # paper frame: x, y, into page
                facing = normals @ -T[:3, 2] > 0.5
                x, y, w, h = rect
                inside = (
                    (np.abs(q[:, 2]) < 0.5)
                    & (q[:, 0] > x - 0.3)
                    & (q[:, 0] < x + w + 0.3)
                    & (q[:, 1] > y - 0.3)
                    & (q[:, 1] < y + h + 0.3)
                )
                sel = facing & inside & ~ok
                out[sel], ok[sel] = q[sel, :2], True
        elif self.kind == "wrap":
            ring = np.asarray(f["ring_mm"])  # (K, 2) polygon from the seam (+x), counter-clockwise
            x0, y0 = f["origin_mm"]
            side = np.abs(normals[:, 2]) < 0.5
            ang = np.mod(np.arctan2(points_mm[:, 1], points_mm[:, 0]), 2 * np.pi)
            ring_ang = np.mod(np.arctan2(ring[:, 1], ring[:, 0]), 2 * np.pi)
            k = np.clip(np.searchsorted(ring_ang, ang, side="right") - 1, 0, len(ring) - 1)
            seg = np.linalg.norm(np.diff(np.concatenate([ring, ring[:1]]), axis=0), axis=-1)
            s = np.concatenate([[0.0], np.cumsum(seg)])[k] + np.linalg.norm(points_mm[:, :2] - ring[k], axis=-1)
            out[:, 0] = x0 + s
            out[:, 1] = y0 + (f["top_z_mm"] - points_mm[:, 2])
            ok = (
                side
                & (out[:, 0] <= x0 + f["length_mm"] + 0.3)
                & (out[:, 1] >= y0 - 0.3)
                & (out[:, 1] <= y0 + f["height_mm"] + 0.3)
            )
        elif self.kind in ("cap_top", "cap_bottom"):
            cx, cy = f["centre_mm"]
            up = self.kind == "cap_top"
            sign = 1.0 if up else -1.0  # seen from below, +x is on the paper's left
            out[:, 0] = cx + sign * points_mm[:, 0]
            out[:, 1] = cy - points_mm[:, 1]
            facing = normals[:, 2] * sign > 0.5
            ok = (
                facing
                & (np.abs(points_mm[:, 2] - f["z_mm"]) < 0.5)
                & (np.hypot(points_mm[:, 0], points_mm[:, 1]) <= f["radius_mm"] + 0.3)
            )
        return out, ok


@dataclass(frozen=True)
class Item:
    """Page furniture: ``kind`` in ``title``, ``scale``, ``colors``; drawn by :func:`draw_pages`."""

    name: str
    kind: str
    size_mm: tuple[float, float]
    data: dict = field(default_factory=dict)

    @property
    def footprint_mm(self):
        return ((0.0, 0.0, *self.size_mm),)


@dataclass(frozen=True)
class Placed:
    name: str
    page: int
    x_mm: float
    y_mm: float


@dataclass(frozen=True)
class SheetLayout:
    """Pieces and furniture placed on pages of ``page_mm`` (width, height, as oriented)."""

    shape: str  # cube, cylinder, or CARD (the tag card alone)
    page_mm: tuple[float, float]
    dpi: int
    uv_side_m: float | None  # None: nothing of the texture is printed (CARD)
    pieces: tuple[Piece, ...]
    items: tuple[Item, ...]
    placements: tuple[Placed, ...]

    @property
    def n_pages(self) -> int:
        return 1 + max(p.page for p in self.placements)

    def where(self, name: str) -> Placed:
        return next(p for p in self.placements if p.name == name)

    def to_json(self) -> dict:
        """The layout in mm (pieces, regions, placements), its scale and DPI: ``layout.json``."""

        def piece(p: Piece):
            at = self.where(p.name)
            d = {
                "name": p.name,
                "kind": p.kind,
                "page": at.page,
                "origin_mm": [at.x_mm, at.y_mm],
                "size_mm": list(p.size_mm),
                "regions": [
                    {"name": r.name, "uv_box": list(r.uv_box), "rect_mm": list(r.rect_mm), "transform": r.transform}
                    for r in p.regions
                ],
            }
            if p.kind == "card":
                d.update({k: p.fold[k] for k in ("tag_id", "tag_size_mm", "tag_centre_mm", "object_centre_mm")})
                d["T_obj_tag"] = T_to_pose(p.fold["T_obj_tag"]).model_dump(mode="json")
            return d

        def item(i: Item):
            at = self.where(i.name)
            return {
                "name": i.name,
                "kind": i.kind,
                "page": at.page,
                "origin_mm": [at.x_mm, at.y_mm],
                "size_mm": list(i.size_mm),
                **i.data,
            }

        return {
            "shape": self.shape,
            "page_mm": list(self.page_mm),
            "pages": self.n_pages,
            "dpi": self.dpi,
            "uv_side_m": self.uv_side_m,
            "mm_per_uv": None if self.uv_side_m is None else self.uv_side_m * 1000.0,
            "check_line_mm": CHECK_LINE_MM,
            "pieces": [piece(p) for p in self.pieces],
            "items": [item(i) for i in self.items],
        }


@dataclass(frozen=True)
class LayoutTweak:
    """Deliberate layout mistakes, to prove the pre-print check catches them (tests, demos).

    scale: every piece drawn this much too large (1.0: true scale); transform: region name ->
    ``mirror``/``rot90``/``rot180``; swap: two region names whose UV boxes trade places.
    """

    scale: float = 1.0
    transform: dict = field(default_factory=dict)
    swap: tuple[str, str] | None = None


# ============================================================================ geometry helpers
def _tab(p0, p1, outward, depth: float):
    """Trapezoidal glue tab on edge p0 -> p1 (mm), ``depth`` along the unit ``outward``: 4 points."""
    p0, p1, o = (np.asarray(v, float) for v in (p0, p1, outward))
    t = (p1 - p0) / np.linalg.norm(p1 - p0)
    inset = min(depth, np.linalg.norm(p1 - p0) / 3)
    return tuple(map(tuple, (p0, p0 + o * depth + t * inset, p1 + o * depth - t * inset, p1)))


def _rect_poly(x, y, w, h):
    return ((x, y), (x + w, y), (x + w, y + h), (x, y + h))


def _rot_about_edge(e0: np.ndarray, e1: np.ndarray, towards: np.ndarray) -> np.ndarray:
    """4x4 rotation by 90 deg about the paper-plane line e0 -> e1 (3D, z = 0) that moves point
    ``towards`` (3D, on the plane) into the page (+z: behind the printed side)."""
    d = (e1 - e0) / np.linalg.norm(e1 - e0)
    for sgn in (1.0, -1.0):
        R = so3_exp(d * sgn * np.pi / 2)
        if (R @ (towards - e0))[2] > 0:
            T = make_T(R, e0 - R @ e0)
            return T
    raise AssertionError("unreachable: one of the two rotations folds into the page")


def fold_cube_net(tiles: dict, root: str, T_obj_root: np.ndarray) -> dict:
    """Fold a net of square tiles, printed side out, into 3D.

    Args:
        tiles: name -> (x, y, w, h) mm rectangles on the paper (x right, y down); tiles sharing
            an edge are joined by a fold.
        root: the tile whose placement is given; T_obj_root: (4, 4) maps the paper frame (x right,
            y down, z into the page, mm) onto the object (mm) for that tile.
    Returns:
        name -> (4, 4) ``T_obj_paper`` of every tile reachable from the root; each tile's points
        ``(x, y, 0)`` land on the folded object, its printed side facing ``-T[:3, 2]``.
    """
    out = {root: np.asarray(T_obj_root, float)}
    queue = [root]
    while queue:
        a = queue.pop(0)
        ax, ay, aw, ah = tiles[a]
        for b, (bx, by, bw, bh) in tiles.items():
            if b in out:
                continue
            # A shared edge: touching along x or y with an overlap longer than 1 mm.
            edge = None
            ox = min(ax + aw, bx + bw) - max(ax, bx)
            oy = min(ay + ah, by + bh) - max(ay, by)
            lo_x, lo_y = max(ax, bx), max(ay, by)
            if ox > 1 and (abs(ay + ah - by) < 0.01 or abs(by + bh - ay) < 0.01):
                yy = ay + ah if abs(ay + ah - by) < 0.01 else ay
                edge = (np.array([lo_x, yy, 0.0]), np.array([lo_x + ox, yy, 0.0]))
            elif oy > 1 and (abs(ax + aw - bx) < 0.01 or abs(bx + bw - ax) < 0.01):
                xx = ax + aw if abs(ax + aw - bx) < 0.01 else ax
                edge = (np.array([xx, lo_y, 0.0]), np.array([xx, lo_y + oy, 0.0]))
            if edge is None:
                continue
            centre_b = np.array([bx + bw / 2, by + bh / 2, 0.0])
            out[b] = out[a] @ _rot_about_edge(*edge, centre_b)
            queue.append(b)
    return out


# ============================================================================ pieces
def _apply_tweak(regions: list[Region], tweak: LayoutTweak) -> list[Region]:
    if tweak.swap:
        a, b = tweak.swap
        boxes = {r.name: r.uv_box for r in regions}
        if a not in boxes or b not in boxes:
            raise FabricationError(f"tweak.swap: regions {a!r}, {b!r}; the layout has {sorted(boxes)}")
        regions = [
            replace(r, uv_box=boxes[b] if r.name == a else boxes[a] if r.name == b else r.uv_box) for r in regions
        ]
    return [replace(r, transform=tweak.transform.get(r.name, r.transform)) for r in regions]


def cube_pieces(mesh, tweak: LayoutTweak = LayoutTweak()) -> list[Piece]:
    """The cube net: one piece of six tiles (60 mm for the built-in cube) with seven glue tabs.

    Tiles sit where their UV tiles sit in the texture (tiles of 1/4 UV, v up = paper up), so the
    net folds as the UV layout wraps (:func:`sim.assets._cube_parts`). Tabs go on every cut edge
    of the four wrap tiles except -x's left edge (+y's right-edge tab glues under it).
    """
    uv = np.asarray(mesh.visual.uv, float)
    faces = np.asarray(mesh.faces)
    normals = np.asarray(mesh.face_normals, float)
    side_mm = float(mesh.metadata["uv_side_m"]) * 1000.0 * tweak.scale
    names = {(0, 1): "+x", (0, -1): "-x", (1, 1): "+y", (1, -1): "-y", (2, 1): "+z", (2, -1): "-z"}
    tiles, regions = {}, []
    for (axis, sgn), name in names.items():
        sel = normals[:, axis] * sgn > 0.9
        box = uv[faces[sel].ravel()]
        u0, v0 = box.min(0)
        u1, v1 = box.max(0)
        col, row = int((u0 + u1) / 2 * 4), int((v0 + v1) / 2 * 4)
        w, h = (u1 - u0) * side_mm, (v1 - v0) * side_mm
        rect = (col * w, (2 - row) * h, w, h)
        tiles[name] = rect
        regions.append(Region(name, (float(u0), float(v0), float(u1), float(v1)), rect))
    regions = _apply_tweak(regions, tweak)
    a = tiles["-y"][2]
    cut, folds, footprint, labels = [], [], [], []
    tabbed = {
        ("-x", "top"),
        ("-x", "bottom"),
        ("+x", "top"),
        ("+x", "bottom"),
        ("+y", "top"),
        ("+y", "bottom"),
        ("+y", "right"),
    }
    rects = list(tiles.values())

    def shared(p0, p1):
        mid = (np.asarray(p0) + np.asarray(p1)) / 2
        hits = sum(x - 0.01 <= mid[0] <= x + w + 0.01 and y - 0.01 <= mid[1] <= y + h + 0.01 for x, y, w, h in rects)
        return hits > 1

    fold_keys = set()
    for name, (x, y, w, h) in tiles.items():
        footprint.append((x, y, w, h))
        edges = {
            "top": ((x, y), (x + w, y), (0, -1)),
            "bottom": ((x + w, y + h), (x, y + h), (0, 1)),
            "left": ((x, y + h), (x, y), (-1, 0)),
            "right": ((x + w, y), (x + w, y + h), (1, 0)),
        }
        for side, (p0, p1, o) in edges.items():
            if shared(p0, p1):  # a fold between two tiles: draw it once
                key = tuple(sorted((tuple(np.round(p0, 3)), tuple(np.round(p1, 3)))))
                if key not in fold_keys:
                    fold_keys.add(key)
                    folds.append((p0, p1))
            elif (name, side) in tabbed:
                tab = _tab(p0, p1, o, TAB_MM)
                cut.append(tab)
                folds.append((p0, p1))
                xs, ys = zip(*tab)
                footprint.append((min(xs), min(ys), max(xs) - min(xs), max(ys) - min(ys)))
                cx, cy = np.mean(tab, axis=0)
                labels.append(("glue", cx, cy, 4, 90 if o[0] else 0))
            else:
                cut.append((p0, p1))
    # Root: the front tile -y, paper x -> object +x, paper y (down) -> object -z, into page -> +y.
    T_root = np.eye(4)
    T_root[:3, :3] = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
    cube_mm = np.asarray(mesh.extents, float) * 1000.0
    centre = np.array([tiles["-y"][0] + a / 2, tiles["-y"][1] + a / 2, 0.0])
    T_root[:3, 3] = np.array([0.0, -cube_mm[1] / 2, cube_mm[2] / 2]) - T_root[:3, :3] @ centre
    folded = fold_cube_net(tiles, "-y", T_root)
    width = max(x + w for x, y, w, h in footprint)
    height = max(y + h for x, y, w, h in footprint)
    return [
        Piece(
            "cube_net",
            "cube_net",
            (width, height),
            tuple(regions),
            tuple(map(tuple, cut)),
            tuple(folds),
            tuple(footprint),
            tuple(labels),
            {"tiles": {n: (folded[n], tiles[n]) for n in tiles}},
        )
    ]


def cylinder_pieces(mesh, tweak: LayoutTweak = LayoutTweak()) -> list[Piece]:
    """Side wrap (seam tab right, toothed tabs top and bottom) and the two caps of the cylinder.

    The wrap's left edge is the seam (+x); rolled printed side out with its top edge up, the
    paper runs counter-clockwise seen from above, as u does. Caps are disks seen from outside:
    the top with +x to the right, the bottom (seen from below) with +x to the left, +y up on both;
    a triangle outside each cut marks the seam direction.
    """
    islands = mesh.metadata["uv_islands"]
    side_mm = float(mesh.metadata["uv_side_m"]) * 1000.0 * tweak.scale
    ring = mesh_ring_mm(mesh)
    height = float(mesh.extents[2]) * 1000.0
    radius = float(np.hypot(ring[:, 0], ring[:, 1]).max())
    regs = {}
    for name in ("side", "top", "bottom"):
        u0, v0, u1, v1 = islands[name]
        regs[name] = Region(
            name, tuple(float(c) for c in (u0, v0, u1, v1)), (0.0, 0.0, (u1 - u0) * side_mm, (v1 - v0) * side_mm)
        )
    regs = {r.name: r for r in _apply_tweak(list(regs.values()), tweak)}

    # Side wrap.
    L, H = regs["side"].rect_mm[2:]
    side_region = replace(regs["side"], rect_mm=(0.0, TAB_MM, L, H))
    y0, y1 = TAB_MM, TAB_MM + H
    n_teeth = max(4, len(ring) // 2)
    cut, folds = [], [((0.0, y0), (L, y0)), ((0.0, y1), (L, y1)), ((L, y0), (L, y1))]
    for k in range(n_teeth):
        a, b = k * L / n_teeth, (k + 1) * L / n_teeth
        cut.append(_tab((a, y0), (b, y0), (0, -1), TAB_MM * 0.8))
        cut.append(_tab((b, y1), (a, y1), (0, 1), TAB_MM * 0.8))
    cut.append(_tab((L, y0), (L, y1), (1, 0), TAB_MM))
    cut.append(((0.0, y0), (0.0, y1)))
    labels = [
        ("seam: glue under the left edge", L + TAB_MM / 2, (y0 + y1) / 2, 4, 90),
        ("top", (n_teeth // 2 + 0.5) * L / n_teeth, y0 - TAB_MM * 0.35, 3.5, 0),
    ]
    wrap = Piece(
        "side",
        "wrap",
        (L + TAB_MM, H + 2 * TAB_MM),
        (side_region,),
        tuple(cut),
        tuple(folds),
        ((0.0, 0.0, L + TAB_MM, H + 2 * TAB_MM),),
        tuple(labels),
        {"ring_mm": ring, "origin_mm": (0.0, y0), "top_z_mm": height, "length_mm": L, "height_mm": H},
    )

    caps = []
    mark = 4.0  # room for the seam triangle
    for name, kind, z in (("top", "cap_top", height), ("bottom", "cap_bottom", 0.0)):
        d = regs[name].rect_mm[2]
        c = mark + d / 2
        sign = 1.0 if kind == "cap_top" else -1.0
        poly = tuple((c + sign * x * tweak.scale, c - y * tweak.scale) for x, y in ring)
        tri_x = c + sign * (d / 2 + 0.5)
        tri = ((tri_x, c), (tri_x + sign * 3.0, c - 1.5), (tri_x + sign * 3.0, c + 1.5))
        caps.append(
            Piece(
                f"cap_{name}",
                kind,
                (d + 2 * mark, d + 2 * mark),
                (replace(regs[name], rect_mm=(mark, mark, d, d)),),
                (poly,),
                (),
                ((0.0, 0.0, d + 2 * mark, d + 2 * mark),),
                ((f"{name} cap", c, c + d / 2 + 2.5, 4, 0),),
                {"centre_mm": (c, c), "z_mm": z, "radius_mm": radius, "seam_mark": tri},
            )
        )
    return [wrap, *caps]


def tag_card(tag_id: int, tag_size_mm: float, shape: str, mesh) -> Piece:
    """A card with the tag (left) and the object's footprint (right), their centres on one line.

    Tag frame (:mod:`calibration.registry`): +x right, +y up on the printed tag, +z out of its
    face. The footprint is the object seen from above, drawn with its +x to the right and +y up
    (its -y, front, toward the card's bottom edge), a cross on its frame's origin: for the cube a
    square, for the cylinder a circle (a tick at the seam, +x), for any other mesh the convex
    outline of its vertices (a tick at the front). The card lies face up on the table, so the tag's
    pose in the object frame ``T_obj_tag`` (``fold["T_obj_tag"]``, (4, 4) m) is a pure
    translation: the printed offset in x and y, and the table's height in the object frame (its
    lowest point) in z.
    """
    if not 0 <= tag_id < 587:
        raise FabricationError(f"tag_id: tag36h11 has ids 0..586, got {tag_id}")
    if not tag_size_mm > 0:
        raise FabricationError(f"tag_size_mm: must be positive, got {tag_size_mm}")
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    cells = d.markerSize + 2
    quiet = 2 * tag_size_mm / cells
    img = cv2.aruco.generateImageMarker(d, int(tag_id), cells, borderBits=1)
    lo, hi = np.asarray(mesh.bounds, float) * 1000.0  # object frame, mm
    ext = hi - lo
    m, gap, label = 3.0, 8.0, 8.0
    tag_block = tag_size_mm + 2 * quiet
    h = max(tag_block, ext[1]) + 2 * m + label
    cy = m + max(tag_block, ext[1]) / 2
    tag_c = (m + tag_block / 2, cy)
    # The object's frame origin on the card (paper y down = object -y): its footprint box beside the
    # tag block, centred on the tag's line.
    obj_c = (m + tag_block + gap - lo[0], cy + (lo[1] + hi[1]) / 2)
    w = m + tag_block + gap + ext[0] + m
    box_cx = obj_c[0] + (lo[0] + hi[0]) / 2
    if shape == "cylinder":
        outline = tuple(
            (box_cx + ext[0] / 2 * math.cos(t), cy - ext[1] / 2 * math.sin(t))
            for t in np.linspace(0, 2 * np.pi, 97)[:-1]
        )
        note = "stand the cylinder here, seam (+x) at the tick"
        tick = (box_cx + ext[0] / 2, cy)
    elif shape == "cube":
        outline = _rect_poly(box_cx - ext[0] / 2, cy - ext[1] / 2, ext[0], ext[1])
        note = "stand the cube here, front (-y) face toward the tick"
        tick = (box_cx, cy + ext[1] / 2)
    else:
        xy = np.asarray(mesh.vertices, float)[:, :2] * 1000.0
        hull = cv2.convexHull(xy.astype(np.float32)).reshape(-1, 2).astype(float)
        outline = tuple((obj_c[0] + x, obj_c[1] - y) for x, y in hull)
        note = "stand the object on its outline, front (-y) toward the tick"
        tick = (box_cx, cy + ext[1] / 2)
    t_obj_tag = np.round(np.array([tag_c[0] - obj_c[0], -(tag_c[1] - obj_c[1]), lo[2]]) / 1000.0, 9) + 0.0
    return Piece(
        "tag_card",
        "card",
        (w, h),
        (),
        (_rect_poly(0, 0, w, h),),
        (),
        ((0.0, 0.0, w, h),),
        (
            (f"tag36h11 id {tag_id}, {tag_size_mm:g} mm", tag_c[0], h - m - label / 2, 5, 0),
            (note, box_cx, h - m - label / 2, 4, 0),
        ),
        {
            "tag_image": img,
            "tag_id": int(tag_id),
            "tag_size_mm": float(tag_size_mm),
            "tag_centre_mm": tag_c,
            "object_centre_mm": obj_c,
            "outline": outline,
            "shape": shape,
            "tick": tick,
            "T_obj_tag": make_T(np.eye(3), t_obj_tag),
        },
    )


def tag_registry(card: Piece, mesh, name: str = "adversarial", T_obj_tag=None) -> dict:
    """The object-registry entry (``examples/calibration/objects.yaml`` format) for the tag card.

    The registry's object frame is the object's centre (its bounding-box centre, the point the
    reach criterion measures to) with the object's axes, so ``T_tag_object`` is ``inv(T_obj_tag)``
    followed by the centre's offset in the object frame: a locator recovers the object's own pose
    as the tag's pose composed with ``inv(T_obj_tag)``. ``name``: the registry's object name (the
    scene object's name, or ``adversarial``); ``T_obj_tag``: the card's own by default.
    """
    f = card.fold
    T_obj_tag = f["T_obj_tag"] if T_obj_tag is None else np.asarray(T_obj_tag, float)
    lo, hi = np.asarray(mesh.bounds, float)
    T_tag_centre = invert_T(T_obj_tag) @ make_T(np.eye(3), (lo + hi) / 2)
    pose = T_to_pose(T_tag_centre)  # rounded to a micrometre: the printed offsets are whole mm and fractions
    t = [round(v, 6) + 0.0 for v in pose.translation_m]
    return {
        "tags": {
            f["tag_id"]: {
                "object": name,
                "size_m": f["tag_size_mm"] / 1000.0,
                "T_tag_object": {"translation_m": t, "rotvec_rad": list(pose.rotvec_rad)},
            }
        }
    }


# ============================================================================ furniture
_FIXED_SWATCHES = (
    (255, 0, 0),
    (0, 255, 0),
    (0, 0, 255),
    (255, 255, 255),
    (191, 191, 191),
    (128, 128, 128),
    (64, 64, 64),
    (0, 0, 0),
)


def texture_swatches(texture: np.ndarray, n: int = 4) -> list[tuple[int, int, int]]:
    """The ``n`` most common colours of ``texture`` (H, W, 3) uint8 (means of 4-bit bins)."""
    flat = texture.reshape(-1, 3).astype(np.int64)
    key = (flat[:, 0] >> 4) << 8 | (flat[:, 1] >> 4) << 4 | (flat[:, 2] >> 4)
    counts = np.bincount(key, minlength=4096)
    out = []
    for k in np.argsort(-counts, kind="stable")[:n]:
        if counts[k] == 0:
            break
        out.append(tuple(int(c) for c in np.rint(flat[key == k].mean(0))))
    return out


_ASSEMBLY = {
    "cube": "net: middle row -x, -y (front), +x, +y; +z (top) above -y, -z below; printed side out",
    "cylinder": "wrap: left edge is the seam (+x), 'top' edge up; caps: the triangles point at the seam",
    CARD: "lay the card flat, tag face up; stand the object on its outline, front (-y) at the tick",
}


def furniture(src: RunSource, shape: str, texture: np.ndarray) -> tuple[list[Item], list[Item]]:
    """(per-page items: title, scale; once-only items: colour check, none for the tag card alone)."""
    swatches = [*_FIXED_SWATCHES, *texture_swatches(texture)]
    cut = "cut along the solid line" if shape == CARD else "cut solid lines, fold dashed, glue the tabs"
    title = Item(
        "title",
        "title",
        (100.0, 17.0),
        {
            "lines": [
                f"advobj fabricate: {'tag card' if shape == CARD else shape}  |  PRINT AT 100 % (actual size, "
                "no fit-to-page)",
                f"source: {Path(src.run_dir).name}  mesh: {Path(src.mesh).name}",
                f"texture sha256: {src.sha256[:32]}",
                f"date: {time.strftime('%Y-%m-%d')}  {cut}",
                _ASSEMBLY[shape],
            ]
        },
    )
    scale = Item("scale", "scale", (108.0, 15.0), {"check_line_mm": CHECK_LINE_MM})
    if shape == CARD:
        return [title, scale], []
    cols = 6
    rows = math.ceil(len(swatches) / cols)
    colors = Item(
        "colors",
        "colors",
        (cols * 15.0, rows * 14.0 + 4.0),
        {"swatches": [list(s) for s in swatches], "swatch_mm": 9.0},
    )
    return [title, scale], [colors]


# ============================================================================ packing
class _Page:
    def __init__(self, W: float, H: float):
        self.W, self.H = W, H
        self.occ = np.zeros((int(math.ceil(H)), int(math.ceil(W))), bool)
        m = int(math.ceil(MARGIN_MM))
        self.occ[:m], self.occ[-m:], self.occ[:, :m], self.occ[:, -m:] = True, True, True, True

    def find(self, rects) -> tuple[int, int] | None:
        """Top-most, then left-most integer mm offset where all ``rects`` are free, or None."""
        S = np.zeros((self.occ.shape[0] + 1, self.occ.shape[1] + 1), np.int32)
        S[1:, 1:] = self.occ.cumsum(0).cumsum(1)
        ok = None
        for x, y, w, h in rects:
            x0, y0 = int(math.floor(x)), int(math.floor(y))
            x1, y1 = int(math.ceil(x + w)), int(math.ceil(y + h))
            ny, nx = self.occ.shape[0] - y1 + 1, self.occ.shape[1] - x1 + 1
            if ny <= 0 or nx <= 0:
                return None
            c = (
                S[y1 : y1 + ny, x1 : x1 + nx]
                - S[y0 : y0 + ny, x1 : x1 + nx]
                - S[y1 : y1 + ny, x0 : x0 + nx]
                + S[y0 : y0 + ny, x0 : x0 + nx]
            )
            free = c == 0
            if ok is None:
                ok = free
            else:
                hh, ww = min(ok.shape[0], ny), min(ok.shape[1], nx)
                ok = ok[:hh, :ww] & free[:hh, :ww]
        ys, xs = np.nonzero(ok)
        if len(ys) == 0:
            return None
        return int(xs[0]), int(ys[0])  # row-major order: smallest y first

    def take(self, rects, ox: int, oy: int) -> None:
        for x, y, w, h in rects:
            y0, y1 = max(0, int(math.floor(oy + y - GAP_MM))), int(math.ceil(oy + y + h + GAP_MM))
            x0, x1 = max(0, int(math.floor(ox + x - GAP_MM))), int(math.ceil(ox + x + w + GAP_MM))
            self.occ[y0:y1, x0:x1] = True


def _pack(pieces, per_page, once, W, H) -> list[Placed]:
    pages: list[_Page] = []
    placed: list[Placed] = []

    def new_page():
        pages.append(_Page(W, H))
        return len(pages) - 1

    for p in pieces:
        for k, pg in enumerate(pages):
            at = pg.find(p.footprint_mm)
            if at:
                break
        else:
            k = new_page()
            at = pages[k].find(p.footprint_mm)
            if at is None:
                raise FabricationError(
                    f"piece {p.name!r} ({p.size_mm[0]:.1f} x {p.size_mm[1]:.1f} mm) does not fit a "
                    f"{W:g} x {H:g} mm page with {MARGIN_MM:g} mm margins; use a larger --page"
                )
        pages[k].take(p.footprint_mm, *at)
        placed.append(Placed(p.name, k, float(at[0]), float(at[1])))

    def put(item, k, name=None):
        at = pages[k].find(item.footprint_mm)
        if at is None:
            return False
        pages[k].take(item.footprint_mm, *at)
        placed.append(Placed(name or item.name, k, float(at[0]), float(at[1])))
        return True

    def furnish(k):
        for it in per_page:
            if not put(it, k, it.name if k == 0 else f"{it.name}@{k}"):
                raise FabricationError(
                    f"page {k + 1}: no room for the {it.name} block ({it.size_mm[0]:g} x {it.size_mm[1]:g} mm) "
                    f"beside the pieces on a {W:g} x {H:g} mm page; use a larger --page"
                )

    if not pages:
        new_page()
    for k in range(len(pages)):
        furnish(k)
    for it in once:
        if not any(put(it, k) for k in range(len(pages))):
            k = new_page()
            furnish(k)
            if not put(it, k):
                raise FabricationError(
                    f"{it.name} ({it.size_mm[0]:.1f} x {it.size_mm[1]:.1f} mm) does not fit a {W:g} x {H:g} mm page"
                )
    return placed  # per-page furniture beyond page 1 is named 'name@k'; the rest keep their names


def build_layout(
    src: RunSource,
    mesh,
    shape: str,
    page: str = "a4",
    dpi: int = 300,
    tag: tuple[int, float] | None = None,
    tweak: LayoutTweak = LayoutTweak(),
) -> SheetLayout:
    """Pieces, furniture and their page placements for ``shape``; the page orientation (portrait or
    landscape) is the one needing fewer pages (portrait on a tie). ``shape`` :data:`CARD`: the tag
    card alone (``tag`` needed), for a mesh without a net, whose card footprint is its outline."""
    if shape not in SHEET_SHAPES and shape != CARD:
        raise FabricationError(
            f"shape {shape!r} has no flat net; sheets exist for {', '.join(SHEET_SHAPES)} "
            "(other meshes: use the GLB/OBJ for colour 3D printing)"
        )
    if shape == CARD and tag is None:
        raise FabricationError("a tag card layout needs a tag: give --tag-id")
    if page not in PAGES_MM:
        raise FabricationError(f"page {page!r}: choose one of {', '.join(PAGES_MM)}")
    if not 30 <= dpi <= 1200:
        raise FabricationError(f"dpi: must be in 30..1200, got {dpi}")
    if not (0.5 <= tweak.scale <= 2.0):
        raise FabricationError(f"tweak.scale: must be in 0.5..2, got {tweak.scale}")
    pieces = cube_pieces(mesh, tweak) if shape == "cube" else cylinder_pieces(mesh, tweak) if shape != CARD else []
    if tag is not None:
        pieces.append(tag_card(int(tag[0]), float(tag[1]), shape, mesh))
    per_page, once = furniture(src, shape, src.texture)
    best, err = None, None
    w, h = PAGES_MM[page]
    for W, H in ((w, h), (h, w)):
        try:
            placed = _pack(pieces, per_page, once, W, H)
        except FabricationError as e:
            err = err or e
            continue
        n = 1 + max(p.page for p in placed)
        if best is None or n < best[0]:
            best = (n, (W, H), placed)
    if best is None:
        raise err
    n_pages = best[0]
    items = list(once)
    for k in range(n_pages):
        items += [it if k == 0 else replace(it, name=f"{it.name}@{k}") for it in per_page]
    uv_side = None if shape == CARD else float(mesh.metadata["uv_side_m"])
    return SheetLayout(shape, best[1], int(dpi), uv_side, tuple(pieces), tuple(items), tuple(best[2]))


# ============================================================================ rasters and drawing
def region_raster(texture: np.ndarray, region: Region, dpi: int) -> np.ndarray:
    """The region's print image (h_px, w_px, 3) uint8 at ``dpi``, row 0 at the top of its rect."""
    w_mm, h_mm = region.rect_mm[2:]
    nw, nh = max(1, round(w_mm / MM_PER_INCH * dpi)), max(1, round(h_mm / MM_PER_INCH * dpi))
    a, b = np.meshgrid((np.arange(nw) + 0.5) / nw, (np.arange(nh) + 0.5) / nh, indexing="xy")
    if region.transform == "mirror":
        a = 1 - a
    elif region.transform == "rot180":
        a, b = 1 - a, 1 - b
    elif region.transform == "rot90":
        a, b = b, 1 - a
    elif region.transform != "none":
        raise FabricationError(f"region {region.name}: unknown transform {region.transform!r}")
    u0, v0, u1, v1 = region.uv_box
    uv = np.stack([u0 + a.ravel() * (u1 - u0), v1 - b.ravel() * (v1 - v0)], -1)
    rgb = sample_bilinear(texture, uv).reshape(nh, nw, 3)
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8)


def _cap_mask(piece: Piece, region: Region, shape_hw) -> np.ndarray:
    """(h, w) bool: raster pixels within BLEED_MM of the cap's cut polygon."""
    h, w = shape_hw
    x0, y0, rw, rh = region.rect_mm
    cx, cy = piece.fold["centre_mm"]
    poly = np.asarray(piece.cut_mm[0], float)
    grow = poly + (poly - [cx, cy]) * (
        BLEED_MM / np.maximum(np.linalg.norm(poly - [cx, cy], axis=-1, keepdims=True), 1e-9)
    )
    px = (grow - [x0, y0]) * [w / rw, h / rh]
    img = Image.new("1", (w, h), 0)
    ImageDraw.Draw(img).polygon([tuple(p) for p in px], fill=1)
    return np.asarray(img, bool)


def _draw_piece(ax, piece: Piece, at: Placed, texture: np.ndarray, dpi: int) -> None:
    ox, oy = at.x_mm, at.y_mm
    for r in piece.regions:
        img = region_raster(texture, r, dpi)
        if piece.kind in ("cap_top", "cap_bottom"):
            img = np.where(_cap_mask(piece, r, img.shape[:2])[..., None], img, 255).astype(np.uint8)
        x, y, w, h = r.rect_mm
        image_mm(ax, img, ox + x, oy + y, w, h)
    if piece.kind == "card":
        f = piece.fold
        s = f["tag_size_mm"]
        tx, ty = f["tag_centre_mm"]
        image_mm(ax, f["tag_image"], ox + tx - s / 2, oy + ty - s / 2, s, s)
        ax.add_patch(
            Polygon(
                np.asarray(f["outline"]) + [ox, oy], closed=True, fill=False, lw=FOLD_LW_PT, ls=(0, (4, 2)), ec="0.3"
            )
        )
        cx, cy = f["object_centre_mm"]
        ax.plot([ox + cx - 3, ox + cx + 3], [oy + cy, oy + cy], lw=FOLD_LW_PT, c="0.3")
        ax.plot([ox + cx, ox + cx], [oy + cy - 3, oy + cy + 3], lw=FOLD_LW_PT, c="0.3")
        kx, ky = f["tick"]
        d = (1.0, 0.0) if f["shape"] == "cylinder" else (0.0, 1.0)
        ax.plot([ox + kx, ox + kx + 4 * d[0]], [oy + ky, oy + ky + 4 * d[1]], lw=1.0, c="k")
    if "seam_mark" in piece.fold:
        ax.add_patch(Polygon(np.asarray(piece.fold["seam_mark"]) + [ox, oy], closed=True, fc="k", ec="none"))
    for poly in piece.cut_mm:
        pts = np.asarray(poly, float) + [ox, oy]
        closed = piece.kind in ("cap_top", "cap_bottom", "card")
        ax.add_patch(Polygon(pts, closed=closed, fill=False, lw=CUT_LW_PT, ec="k", joinstyle="miter"))
    for p0, p1 in piece.fold_mm:
        ax.plot([ox + p0[0], ox + p1[0]], [oy + p0[1], oy + p1[1]], lw=FOLD_LW_PT, ls=(0, (3, 2)), c="0.45")
    # Fold ticks just outside both ends of each fold line: visible after cutting the tabs off.
    for p0, p1 in piece.fold_mm:
        p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
        t = (p1 - p0) / np.linalg.norm(p1 - p0)
        for e, s in ((p0, -1), (p1, 1)):
            q0, q1 = e + s * t * 1.0, e + s * t * 3.0
            ax.plot([ox + q0[0], ox + q1[0]], [oy + q0[1], oy + q1[1]], lw=FOLD_LW_PT, c="0.45")
    for text, x, y, size, rot in piece.labels:
        ax.text(ox + x, oy + y, text, fontsize=size, ha="center", va="center", rotation=rot, color="0.35")


def _draw_item(ax, item: Item, at: Placed, page: int, n_pages: int) -> None:
    x, y = at.x_mm, at.y_mm
    if item.kind == "title":
        lines = list(item.data["lines"])
        lines[0] += f"  |  page {page + 1}/{n_pages}"
        for k, line in enumerate(lines):
            ax.text(
                x,
                y + 1.5 + 3.2 * k,
                line,
                fontsize=5.5 if k else 6.5,
                va="center",
                weight="bold" if k == 0 else "normal",
            )
    elif item.kind == "scale":
        L = item.data["check_line_mm"]
        ax.text(
            x,
            y + 1.5,
            f"{L:g} mm check line: measure end tick to end tick, must read {L:g} mm",
            fontsize=5.5,
            va="center",
        )
        ax.plot([x, x + L], [y + 5.0, y + 5.0], lw=0.6, c="k", solid_capstyle="butt")
        for e in (x, x + L):
            ax.plot([e, e], [y + 3.0, y + 7.0], lw=0.6, c="k", solid_capstyle="butt")
        scale_bar(ax, x, y + 11.5)
    elif item.kind == "colors":
        s = item.data["swatch_mm"]
        ax.text(x, y + 1.5, "colour check: compare printed swatches with these sRGB values", fontsize=5, va="center")
        for k, rgb in enumerate(item.data["swatches"]):
            r, c = divmod(k, 6)
            sx, sy = x + c * 15.0, y + 4.0 + r * 14.0
            ax.add_patch(Rectangle((sx, sy), s, s, facecolor=np.asarray(rgb) / 255.0, edgecolor="0.5", lw=0.3))
            ax.text(sx + s / 2, sy + s + 2.0, ",".join(map(str, rgb)), fontsize=3.5, ha="center", va="center")


def draw_pages(
    layout: SheetLayout, texture: np.ndarray, pdf_path=None, raster: bool = True, progress=None
) -> list[np.ndarray]:
    """Draw every page once: save it to ``pdf_path`` (if given) and rasterise it with Agg at the
    layout DPI. Returns the page rasters (H_px, W_px, 3) uint8 (empty if ``raster`` is False)."""
    matplotlib.use("Agg", force=False)

    W, H = layout.page_mm
    pieces = {p.name: p for p in layout.pieces}
    items = {i.name: i for i in layout.items}
    rasters = []
    pdf = PdfPages(pdf_path, metadata={"Title": f"advobj {layout.shape} print sheet"}) if pdf_path else None
    try:
        for k in range(layout.n_pages):
            fig, ax = page_figure(W, H)
            for at in layout.placements:
                if at.page != k:
                    continue
                if at.name in pieces:
                    _draw_piece(ax, pieces[at.name], at, texture, layout.dpi)
                else:
                    _draw_item(ax, items[at.name], at, k, layout.n_pages)
            if pdf is not None:
                pdf.savefig(fig)
            if raster:
                fig.set_dpi(layout.dpi)
                canvas = FigureCanvasAgg(fig)
                canvas.draw()
                rasters.append(np.asarray(canvas.buffer_rgba())[..., :3].copy())
            if progress:
                progress(1)
    finally:
        if pdf is not None:
            pdf.close()
    return rasters


# ============================================================================ orchestration
def _run_json(run_dir) -> Path:
    """The texture folder's ``run.json`` (named in errors about what it records)."""
    return Path(run_dir) / RUN_JSON


def _attack_field(run_dir, name: str):
    """A field of the attack config in ``run_dir/run.json`` (None when absent or unreadable)."""
    try:
        return AttackArtifact.load(run_dir).attack_config.get(name)
    except (OSError, ValueError):
        return None


def fabricate(
    run_dir,
    out_dir,
    shape: str | None = None,
    page: str = "a4",
    dpi: int = 300,
    tag: tuple[int, float] | None = None,
    check: bool = True,
    tweak: LayoutTweak = LayoutTweak(),
    log=print,
    progress: bool = True,
    obj_units: str = "m",
    scene=None,
) -> dict:
    """Everything ``advobj fabricate`` writes into ``out_dir``; returns a summary dict.

    ``scene``: a scene YAML whose object ``shape`` (default: its adversarial object) is made: its
    mesh, scale, units, up axis and placement (:func:`trials.fabrication.shapes.scene_shape`); the
    attack run must have optimised that mesh. Without it, ``shape`` is a sheet shape (cube,
    cylinder) and the run's own mesh is made.

    Always: ``adversarial.glb`` + ``adversarial_obj/`` (colour 3D printing) and ``run.json``.
    For cube and cylinder: ``sheet.pdf``, ``layout.json``, ``objects.yaml`` (with a tag) and,
    unless ``check`` is False, ``print_check.png`` / ``print_check.json``; a failed check raises
    :class:`FabricationError` after writing them. For any other mesh with a tag: the tag card alone
    (``sheet.pdf``, ``layout.json``, ``objects.yaml``, the check of the card). The card's
    ``T_obj_tag`` (the tag's pose in the object frame) is in ``layout.json`` and the summary, and
    ``objects.yaml`` holds the registry entry made from it, named after the scene object (else
    ``adversarial``).
    """
    t0 = time.perf_counter()
    # every option first: nothing is written for a run that would be refused later (build_layout checks again)
    if not (isinstance(dpi, int) and 30 <= dpi <= 1200):
        raise FabricationError(f"--dpi: must be in 30..1200, got {dpi}")
    if page not in PAGES_MM:
        raise FabricationError(f"--page: {page!r} is not one of {', '.join(PAGES_MM)}")
    if Path(out_dir).is_file():
        raise FabricationError(f"--out: {out_dir} is a file; give an output directory")
    if obj_units not in ("m", "mm"):
        raise FabricationError(f"--units: expected m or mm, got {obj_units!r}")
    if tag is not None and not 0 <= int(tag[0]) < 587:
        raise FabricationError(f"--tag-id: tag36h11 has ids 0..586, got {tag[0]}")
    if tag is not None and not (math.isfinite(tag[1]) and 1.0 <= tag[1] <= 500.0):
        raise FabricationError(f"--tag-size-mm: must be 1..500 mm, got {tag[1]}")
    spec = None if scene is None else load_spec(scene)
    src = load_run(run_dir)
    obj = None
    if spec is not None:
        try:
            obj = scene_shape(spec, shape or spec.adversarial.name, "--shape", str(scene))
        except ShapeError as err:
            raise FabricationError(str(err)) from None
    if obj is not None:
        problem = run_mesh_problem(src, obj)
        if problem is not None:
            raise FabricationError(f"--shape {obj.object.name}: {problem} (run {run_dir})")
        # the object as the scene declares it: the texture's mesh, at the scene's size
        src = replace(src, mesh=obj.object.mesh, scale=obj.object.scale, mesh_kwargs=obj.object.mesh_kwargs())
        sheet_shape = obj.object.mesh if obj.object.mesh in SHEET_SHAPES else None
    else:
        if shape is not None and shape not in SHEET_SHAPES:
            raise FabricationError(
                f"--shape {shape}: no flat net for this shape; sheets exist for {', '.join(SHEET_SHAPES)}"
                + ("" if scene is not None else "; to make an object of your scene, give --scene SCENE --shape OBJECT")
            )
        if shape is not None and shape != src.mesh:
            raise FabricationError(
                f"--shape {shape}: the texture in {run_dir} was optimised on {src.mesh!r}, not {shape!r}; "
                "its UV layout would not fit the net"
            )
        sheet_shape = shape if shape is not None else (src.mesh if src.mesh in SHEET_SHAPES else None)
    name = "adversarial" if obj is None else obj.object.name
    light_dr = _attack_field(run_dir, "light_randomization")
    try:
        mesh = build_mesh(src.mesh, src.scale, **src.mesh_kwargs)
    except AssetError as err:
        where = f"--scene {scene}: object {name!r}" if obj is not None else f"{_run_json(run_dir)}"
        raise FabricationError(f"{where}: mesh {src.mesh!r} cannot be built ({err})") from None
    if sheet_shape is not None and np.any(np.asarray(src.scale, float) != 1.0):
        raise FabricationError(
            f"{_run_json(run_dir) if obj is None else f'--scene {scene}: object {name!r}'}: the object is scaled by "
            f"{src.scale}; print sheets need the built-in size (scale 1)"
        )
    if light_dr is False:
        # The paper optimises under lighting randomisation for the real cell; a fixed-light texture
        # may lose much of its effect under the cell's own lights (experiment lighting measures it).
        log(
            "fabricate: warning: this texture was optimised under the scene's fixed light "
            "(light_randomization: false); "
            "for a real cell, optimise with light_randomization: true ('advobj experiment lighting' measures the "
            "difference)"
        )
    layout_shape = sheet_shape if sheet_shape is not None else (CARD if tag is not None else None)
    config = {
        "job": "fabricate",
        "run_dir": str(run_dir),
        "scene": None if scene is None else str(scene),
        "object": None if obj is None else name,
        "mesh": src.mesh,
        "mesh_sha256": None if obj is None else obj.mesh_sha256,
        "scale": src.scale,
        "shape": sheet_shape,
        "page": page,
        "dpi": dpi,
        "tag": list(tag) if tag else None,
        "check": check,
        "texture_sha256": src.sha256,
        "light_randomization": light_dr,
        "tweak": asdict(tweak) if tweak != LayoutTweak() else None,
    }
    out = Path(out_dir)
    write_run_info(out, config, None)

    printed = region_texture(mesh, src.texture)
    if printed is not src.texture:
        n_opt = int(np.count_nonzero(mesh.metadata["optimizable_faces"]))
        log(
            f"fabricate: {n_opt} of {len(mesh.faces)} faces were optimised (attack_region); the others keep the "
            "mesh's own "
            f"texture, written at {printed.shape[1]} x {printed.shape[0]} texels"
        )
    paths = export_meshes(out, mesh, printed, obj_units=obj_units)
    density = optimised_texel_size_mm(mesh, src.texture.shape[1], src.texture.shape[0])
    summary = {"glb": str(paths["glb"]), "obj": str(paths["obj"]), "shape": sheet_shape, "texel_mm": density}
    if density is not None:
        log(
            f"fabricate: the optimised texture is {src.texture.shape[1]} x {src.texture.shape[0]} texels; on the "
            "object one texel spans "
            f"{density['median']:.2f} mm (median over the optimised faces; {density['p10']:.2f}-{density['p90']:.2f} "
            "mm for 80 % of "
            f"their area), whatever the print resolution"
        )
    if layout_shape is None:
        log(
            f"fabricate: {Path(src.mesh).name!r} has no flat net; wrote {paths['glb'].name} and "
            f"{paths['obj'].parent.name}/ for colour 3D printing "
            f"(sheets exist for {', '.join(SHEET_SHAPES)}; --tag-id adds a tag card that locates it in the cell)"
        )
        summary["seconds"] = time.perf_counter() - t0
        return summary

    layout = build_layout(src, mesh, layout_shape, page, dpi, tag, tweak)
    (out / "layout.json").write_text(json.dumps(layout.to_json(), indent=2))
    card = next((p for p in layout.pieces if p.kind == "card"), None)
    if card is not None:
        save_registry(out / "objects.yaml", ObjectRegistry.model_validate(tag_registry(card, mesh, name)))
        pose = T_to_pose(card.fold["T_obj_tag"])
        summary["T_obj_tag"] = pose.model_dump(mode="json")
        log(
            f"fabricate: tag {card.fold['tag_id']} on the card lies at "
            f"[{', '.join(f'{v * 1000:.1f}' for v in pose.translation_m)}] mm in the frame of {name!r} "
            f"(T_obj_tag, in layout.json); objects.yaml registers it as object {name!r}"
        )
    with tqdm(total=layout.n_pages, desc="sheet pages", unit="page", disable=not progress) as bar:
        rasters = draw_pages(layout, src.texture, out / "sheet.pdf", raster=check, progress=bar.update)
    summary.update(
        pdf=str(out / "sheet.pdf"),
        pages=layout.n_pages,
        page_mm=list(layout.page_mm),
        sheet_seconds=time.perf_counter() - t0,
    )
    log(
        f"fabricate: wrote {out / 'sheet.pdf'} ({layout.n_pages} page(s), {layout.page_mm[0]:g} x "
        f"{layout.page_mm[1]:g} mm, "
        f"{dpi} dpi, {summary['sheet_seconds']:.1f} s): print at 100 % and check the {CHECK_LINE_MM:g} mm line"
    )
    if check:
        t1 = time.perf_counter()
        result = check_print(layout, rasters, mesh, src.texture, progress=progress)
        summary["check_seconds"] = time.perf_counter() - t1
        write_check(out, result)
        summary["check"] = result.summary()
        log(f"fabricate: pre-print check {'PASSED' if result.passed else 'FAILED'}: {result.message()}")
        if not result.passed:
            raise FabricationError(f"pre-print check failed: {result.message()} (see {out / 'print_check.png'})")
    summary["seconds"] = time.perf_counter() - t0
    return summary
