"""Diagnostic images a person reads: upscaled to a legible size and labelled in the image itself.

Policy images are 32-128 px; shown as they are, a Grad-CAM map or a rollout frame is a smudge.
:func:`labelled` scales an image up by a whole factor (nearest neighbour, so pixels stay honest)
until its short side is at least ``min_side`` and writes a caption bar above it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["MIN_SIDE", "upscale", "labelled", "hstack", "contact_sheet", "write_gif"]

# Short side of every diagnostic image (px), caption bar excluded.
MIN_SIDE = 256
_BAR_PX = 18


def upscale(img: np.ndarray, min_side: int = MIN_SIDE) -> np.ndarray:
    """``img (H, W, 3)`` uint8 repeated by the smallest whole factor giving ``min(H, W) >= min_side``."""
    img = np.asarray(img)
    k = max(1, -(-int(min_side) // max(1, min(img.shape[:2]))))
    return np.repeat(np.repeat(img, k, axis=0), k, axis=1) if k > 1 else img


def labelled(img: np.ndarray, text: str, min_side: int = MIN_SIDE) -> np.ndarray:
    """``img`` upscaled (:func:`upscale`) with ``text`` on a black bar above it: ``(H' + 18, W', 3)`` uint8."""
    from PIL import Image, ImageDraw  # lazy: CLI start-up (PIL)

    big = upscale(np.asarray(img, dtype=np.uint8)[..., :3], min_side)
    bar = Image.new("RGB", (big.shape[1], _BAR_PX), (0, 0, 0))
    ImageDraw.Draw(bar).text((4, 3), text, fill=(255, 255, 255))
    return np.concatenate([np.asarray(bar), big], 0)


def hstack(images: list[np.ndarray], gap_px: int = 4) -> np.ndarray:
    """Images side by side (heights padded with black), separated by ``gap_px`` of white."""
    h = max(i.shape[0] for i in images)
    cols = []
    for k, i in enumerate(images):
        pad = np.zeros((h - i.shape[0], i.shape[1], 3), np.uint8)
        cols.append(np.concatenate([i, pad], 0))
        if k < len(images) - 1:
            cols.append(np.full((h, gap_px, 3), 255, np.uint8))
    return np.concatenate(cols, 1)


def contact_sheet(frames: list[np.ndarray], cols: int = 8, max_frames: int = 32) -> np.ndarray:
    """Tile evenly spaced frames into one image (rows x cols), padding with black."""
    idx = np.unique(np.linspace(0, len(frames) - 1, min(max_frames, len(frames))).round().astype(int))
    picked = [frames[i] for i in idx]
    h, w, _ = picked[0].shape
    rows = -(-len(picked) // cols)
    sheet = np.zeros((rows * h, cols * w, 3), np.uint8)
    for k, f in enumerate(picked):
        r, c = divmod(k, cols)
        sheet[r * h : (r + 1) * h, c * w : (c + 1) * w] = f
    return sheet


def write_gif(path: str | Path, frames: list[np.ndarray], fps: int = 10) -> Path:
    import imageio.v3 as iio  # lazy: CLI start-up (imageio)

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, np.stack(frames), duration=int(1000 / fps), loop=0)
    return path
