"""True-scale printable PDFs: AprilTag sheets and ChArUco boards.

Pages are matplotlib figures whose size is set in inches, drawn on a millimetre axis that spans
the whole page, and saved with the PDF backend: one drawing unit is exactly one printed millimetre
(print at 100 % / "actual size"). Each page carries a 50 mm scale bar to check the printout with a
ruler. Marker images are embedded unresampled (``interpolation="none"``), one image pixel per
marker cell or per board pixel, so edges stay sharp at any zoom.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import cv2
import matplotlib
import numpy as np
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from calibration.errors import CalibrationError
from calibration.intrinsics import BoardSpec

__all__ = [
    "A4_MM",
    "PAGES_MM",
    "MM_PER_INCH",
    "SCALE_BAR_MM",
    "page_figure",
    "scale_bar",
    "image_mm",
    "tag_sheet_pdf",
    "board_pdf",
    "parse_id_ranges",
    "parse_page",
    "TAG36H11_IDS",
]

A4_MM = (210.0, 297.0)
PAGES_MM = {
    "A4": A4_MM,
    "A3": (297.0, 420.0),
    "A2": (420.0, 594.0),
    "letter": (215.9, 279.4),
    "tabloid": (279.4, 431.8),
}
MM_PER_INCH = 25.4
SCALE_BAR_MM = 50.0


TAG36H11_IDS = 587  # ids 0..586


def parse_id_ranges(text: str, n_ids: int = TAG36H11_IDS) -> list[int]:
    """``"0-7,12,20-21"`` -> [0..7, 12, 20, 21]; ValueError naming the bad part.

    Every id must lie in ``0..n_ids - 1`` (the dictionary's ids) and the list may hold at most
    ``n_ids`` entries; both are checked on the ranges' ends, before any range is expanded.
    """
    bounds: list[tuple[int, int]] = []
    total = 0
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        try:
            a, b = (int(x) for x in part.split("-", 1)) if "-" in part else (int(part),) * 2
            if b < a:
                raise ValueError
        except ValueError:
            raise ValueError(f"ids: cannot parse {part!r}; use e.g. 0-7,12") from None
        if a < 0 or b >= n_ids:
            raise ValueError(f"ids: {part} lies outside the dictionary's ids 0..{n_ids - 1}")
        total += b - a + 1
        if total > n_ids:
            raise ValueError(f"ids: more than {n_ids} tags asked for (the dictionary has {n_ids} ids)")
        bounds.append((a, b))
    if not bounds:
        raise ValueError("ids: empty")
    return [i for a, b in bounds for i in range(a, b + 1)]


def parse_page(page: str) -> tuple[float, float]:
    """A page name of :data:`PAGES_MM` (case-insensitive) or ``WxH`` in mm -> (width, height) mm."""
    for name, size in PAGES_MM.items():
        if page.strip().lower() == name.lower():
            return size
    try:
        w, h = (float(x) for x in page.lower().split("x"))
        if not (math.isfinite(w) and math.isfinite(h) and 50.0 <= w <= 5000.0 and 50.0 <= h <= 5000.0):
            raise ValueError
    except ValueError:
        raise ValueError(
            f"page: expected {', '.join(PAGES_MM)} or WIDTHxHEIGHT in mm (50-5000 each), got {page!r}"
        ) from None
    return (w, h)


def cut_marks(ax, x_mm: float, y_mm: float, w_mm: float, h_mm: float, length_mm: float = 2.0):
    """Thin L-shaped marks just outside each corner of a rectangle: cut along them."""
    kw = dict(color="0.45", linewidth=0.25)
    for cx, sx in ((x_mm, -1.0), (x_mm + w_mm, 1.0)):
        for cy, sy in ((y_mm, -1.0), (y_mm + h_mm, 1.0)):
            ax.plot([cx, cx + sx * length_mm], [cy, cy], **kw)
            ax.plot([cx, cx], [cy, cy + sy * length_mm], **kw)


def page_figure(width_mm: float, height_mm: float):
    """A blank page ``(fig, ax)``: figure sized in inches, axis in mm spanning it, y down."""
    matplotlib.use("Agg", force=False)

    fig = Figure(figsize=(width_mm / MM_PER_INCH, height_mm / MM_PER_INCH))
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.set_xlim(0.0, width_mm)
    ax.set_ylim(height_mm, 0.0)  # y down, like the page as read
    ax.set_axis_off()
    return fig, ax


def scale_bar(ax, x_mm: float, y_mm: float):
    """A 50 mm bar with 10 mm ticks, its left end at ``(x_mm, y_mm)``, labelled on its right."""
    ax.add_patch(Rectangle((x_mm, y_mm), SCALE_BAR_MM, 1.0, facecolor="black", edgecolor="none"))
    for k in range(6):
        ax.add_patch(Rectangle((x_mm + 10.0 * k - 0.15, y_mm - 2.0), 0.3, 3.0, facecolor="black", edgecolor="none"))
    ax.text(
        x_mm + SCALE_BAR_MM + 3.0,
        y_mm + 0.5,
        f"{SCALE_BAR_MM:.0f} mm: check with a ruler, print at 100 %",
        fontsize=7,
        va="center",
    )


def image_mm(ax, img: np.ndarray, x_mm: float, y_mm: float, w_mm: float, h_mm: float):
    """Draw ``img`` (grey or RGB uint8, row 0 at the top) unresampled into a page rectangle in mm."""
    ax.imshow(
        img,
        cmap="gray",
        vmin=0,
        vmax=255,
        interpolation="none",
        extent=(x_mm, x_mm + w_mm, y_mm + h_mm, y_mm),
        aspect="auto",
    )


def tag_sheet_pdf(
    path, tag_ids: Sequence[int], tag_size_mm: float, page_mm=A4_MM, margin_mm: float = 8.0, gap_mm: float = 4.0
) -> Path:
    """AprilTags (tag36h11) ``tag_ids`` at ``tag_size_mm`` (black square side) on as many pages as needed.

    Tags sit in a dense grid: each keeps a white quiet zone of two cells and a label strip (id and
    size) below it, inside a cut box marked at its corners; boxes are ``gap_mm`` apart, room for
    the marks and a blade.
    """
    if not tag_size_mm > 0:
        raise CalibrationError("size_mm: must be positive")
    bad = [i for i in tag_ids if not 0 <= i < TAG36H11_IDS]
    if bad:
        raise CalibrationError(f"ids: tag36h11 has ids 0..{TAG36H11_IDS - 1}; got {bad[:5]}")
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    cells = d.markerSize + 2
    cell_mm = tag_size_mm / cells
    quiet_mm = 2 * cell_mm
    label_mm = 3.5
    box_w, box_h = tag_size_mm + 2 * quiet_mm, tag_size_mm + 2 * quiet_mm + label_mm
    pitch_x, pitch_y = box_w + gap_mm, box_h + gap_mm
    W, H = page_mm
    usable_w, usable_h = W - 2 * margin_mm, H - 2 * margin_mm - 10.0  # bottom strip: scale bar
    cols, rows = int((usable_w + gap_mm) // pitch_x), int((usable_h + gap_mm) // pitch_y)
    if cols < 1 or rows < 1:
        raise CalibrationError(
            f"size_mm: a {tag_size_mm:g} mm tag does not fit a {W:g} x {H:g} mm page with {margin_mm:g} mm margins"
        )
    per_page = cols * rows
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with PdfPages(path) as pdf:
        for start in range(0, len(tag_ids), per_page):
            fig, ax = page_figure(W, H)
            for k, tag_id in enumerate(tag_ids[start : start + per_page]):
                r, c = divmod(k, cols)
                bx, by = margin_mm + c * pitch_x, margin_mm + r * pitch_y
                x, y = bx + quiet_mm, by + quiet_mm
                img = cv2.aruco.generateImageMarker(d, int(tag_id), cells, borderBits=1)  # 1 px per cell
                image_mm(ax, img, x, y, tag_size_mm, tag_size_mm)
                ax.text(
                    x + tag_size_mm / 2,
                    y + tag_size_mm + quiet_mm + 0.3,
                    f"tag36h11 id {tag_id}  {tag_size_mm:g} mm",
                    fontsize=5,
                    ha="center",
                    va="top",
                )
                cut_marks(ax, bx, by, box_w, box_h)
            scale_bar(ax, margin_mm, H - margin_mm)
            pdf.savefig(fig)
    return path


def board_pdf(path, board: BoardSpec, margin_mm: float = 8.0, px_per_square: int = 120, page: str = "A4") -> Path:
    """One ``page`` (a name of :data:`PAGES_MM` or ``WxH`` mm, either orientation) with the ChArUco
    ``board`` at true scale; a board that does not fit is refused, saying what would."""
    w_mm = board.squares_x * board.square_size_m * 1000.0
    h_mm = board.squares_y * board.square_size_m * 1000.0
    need = (w_mm + 2 * margin_mm, h_mm + 2 * margin_mm + 12.0)
    try:
        pw, ph = parse_page(page)
    except ValueError as err:
        raise CalibrationError(str(err)) from None
    if need[0] <= pw and need[1] <= ph:
        W, H = pw, ph
    elif need[0] <= ph and need[1] <= pw:
        W, H = ph, pw
    else:
        fits = [
            n for n, (a, b) in PAGES_MM.items() if (need[0] <= a and need[1] <= b) or (need[0] <= b and need[1] <= a)
        ]
        hint = (
            f"--page {fits[0]}"
            if fits
            else f"--page {math.ceil(need[0])}x{math.ceil(need[1])} (a print service's size)"
        )
        raise CalibrationError(
            f"board: {w_mm:g} x {h_mm:g} mm ({need[0]:g} x {need[1]:g} with margins and label) does not fit a "
            f"{pw:g} x {ph:g} mm page ({page}) in either orientation; use fewer or smaller squares "
            f"(--squares-x/--squares-y/--square-mm) or {hint}"
        )
    img = board.cv_board().generateImage(
        (board.squares_x * px_per_square, board.squares_y * px_per_square), marginSize=0, borderBits=1
    )
    fig, ax = page_figure(W, H)
    x, y = (W - w_mm) / 2, margin_mm
    image_mm(ax, img, x, y, w_mm, h_mm)
    ax.text(
        x,
        y + h_mm + 4.0,
        f"ChArUco {board.squares_x}x{board.squares_y}, square {board.square_size_m * 1000:g} mm, "
        f"marker {board.marker_size_m * 1000:g} mm, "
        f"DICT_{board.dictionary}{', legacy pattern' if board.legacy_pattern else ''}",
        fontsize=7,
        va="top",
    )
    scale_bar(ax, x, H - margin_mm)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="pdf")
    return path
