"""What the sheet maker (:mod:`trials.fabrication.fabricate`) and the pre-print check
(:mod:`trials.fabrication.print_check`) share: the error, bilinear sampling of a texture or a page
raster, and a lathe mesh's base ring."""

from __future__ import annotations

import numpy as np

from sim.errors import AdvobjError

__all__ = ["FabricationError", "sample_bilinear", "sample_page", "mesh_ring_mm"]


class FabricationError(AdvobjError, ValueError):
    """A sheet cannot be made as asked; the message names the run file, shape, piece or page."""


def sample_bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """GL_LINEAR lookup with clamp to edge, as the renderer samples textures.

    Args:
        image: (H, W, C) texture, image row 0 at v = 1 (:mod:`sim.textures` convention).
        uv: (N, 2) texture coordinates.
    Returns:
        (N, C) float64 in the image's units.
    """
    h, w = image.shape[:2]
    x = np.asarray(uv[:, 0], np.float64) * w - 0.5
    y = (1.0 - np.asarray(uv[:, 1], np.float64)) * h - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    c0, c1 = np.clip(x0, 0, w - 1).astype(np.int64), np.clip(x0 + 1, 0, w - 1).astype(np.int64)
    r0, r1 = np.clip(y0, 0, h - 1).astype(np.int64), np.clip(y0 + 1, 0, h - 1).astype(np.int64)
    img = np.asarray(image, np.float64)
    top = img[r0, c0] * (1 - fx) + img[r0, c1] * fx
    bottom = img[r1, c0] * (1 - fx) + img[r1, c1] * fx
    return top * (1 - fy) + bottom * fy


def sample_page(page: np.ndarray, xy_px: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a page raster (H, W, C) at pixel coordinates ``xy_px`` (N, 2) (x right,
    y down, pixel centres at +0.5) -> (N, C) float64."""
    h, w = page.shape[:2]
    uv = np.stack([xy_px[:, 0] / w, 1.0 - xy_px[:, 1] / h], -1)
    return sample_bilinear(page, uv)


def mesh_ring_mm(mesh) -> np.ndarray:
    """(K, 2) mm: the base ring polygon of a lathe mesh, from +x counter-clockwise."""
    v = np.asarray(mesh.vertices, float) * 1000.0
    r = np.hypot(v[:, 0], v[:, 1])
    base = v[(np.abs(v[:, 2] - v[:, 2].min()) < 1e-6) & (r > 0.5 * r.max())][:, :2]
    ang = np.mod(np.arctan2(base[:, 1], base[:, 0]), 2 * np.pi)
    ang = np.round(ang, 9)
    _, idx = np.unique(ang, return_index=True)
    return base[idx]
