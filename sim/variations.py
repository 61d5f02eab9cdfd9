"""Appearance variations: light presets, random lights, background variation, sensor noise.

These are the paper's robustness conditions (Light Bright, Light Dim, Bkg Varied, Add Noise) and
the domain randomisation used in training and in the attack's lighting randomisation. An
:class:`Appearance` is drawn once per episode and applied by the renderer before each frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from sim.spec import LightingSpec, LightSpec

__all__ = [
    "Randomization",
    "Appearance",
    "sample_appearance",
    "add_sensor_noise",
    "table_variant_texture",
    "NUM_TABLE_VARIANTS",
]

NUM_TABLE_VARIANTS = 8
# background "mixed": share of episodes that keep the spec's own table and backdrop.
MIXED_SPEC_SHARE = 0.25


@dataclass(frozen=True)
class Randomization:
    """What varies between episodes.

    light: "fixed" (the spec's), "bright", "dim" (the paper's presets) or "random" (domain
    randomisation: intensity, direction, ambient and a slight tint).
    background: "fixed", "varied" (table texture and backdrop colour drawn per episode) or "mixed"
        (training: the spec's own table and backdrop in a quarter of the episodes, varied in the
        rest, so that a policy trained with randomisation has also seen the nominal scene).
    noise_std: Gaussian sensor noise, standard deviation as a fraction of full scale (0 = off).
    """

    light: Literal["fixed", "bright", "dim", "random"] = "fixed"
    background: Literal["fixed", "varied", "mixed"] = "fixed"
    noise_std: float = 0.0

    def __post_init__(self):
        if self.light not in ("fixed", "bright", "dim", "random"):
            raise ValueError(f"randomization.light: unknown preset {self.light!r}")
        if self.background not in ("fixed", "varied", "mixed"):
            raise ValueError(f"randomization.background: unknown value {self.background!r}")
        if not (0.0 <= self.noise_std <= 0.5):
            raise ValueError(f"randomization.noise_std must lie in [0, 0.5], got {self.noise_std}")


@dataclass(frozen=True)
class Appearance:
    """A resolved look for one episode (hashable: the renderer skips re-applying an equal one)."""

    lighting: LightingSpec
    table_variant: int = -1  # -1 = the spec's table texture
    background: tuple[float, float, float] | None = None  # None = the spec's
    noise_std: float = 0.0


def _scaled(lighting: LightingSpec, light_gain: float, ambient_gain: float) -> LightingSpec:
    amb = tuple(float(min(1.0, a * ambient_gain)) for a in lighting.ambient)
    lights = [l.model_copy(update={"intensity": l.intensity * light_gain}) for l in lighting.lights]
    return LightingSpec(ambient=amb, lights=lights)


def sample_appearance(spec, randomization: Randomization, rng: np.random.Generator) -> Appearance:
    """Draw the look of one episode from ``randomization`` (deterministic given ``rng``)."""
    base = spec.lighting
    if randomization.light == "bright":
        lighting = _scaled(base, 1.8, 1.5)
    elif randomization.light == "dim":
        lighting = _scaled(base, 0.35, 0.5)
    elif randomization.light == "random":
        az = rng.uniform(-np.pi, np.pi)
        el = rng.uniform(np.radians(35), np.radians(85))
        direction = (-np.cos(el) * np.cos(az), -np.cos(el) * np.sin(az), -np.sin(el))
        tint = np.clip(1.0 + rng.normal(0.0, 0.06, 3), 0.8, 1.0)
        light = LightSpec(
            type="directional",
            intensity=float(rng.uniform(1.2, 5.0)),
            color=tuple(float(c) for c in tint),
            direction=direction,
        )
        amb = float(rng.uniform(0.15, 0.5))
        lighting = LightingSpec(ambient=(amb, amb, amb), lights=[light])
    else:
        lighting = base
    table_variant, background = -1, None
    varied = randomization.background == "varied"
    if randomization.background == "mixed":
        varied = bool(rng.random() >= MIXED_SPEC_SHARE)
    if varied:
        table_variant = int(rng.integers(NUM_TABLE_VARIANTS))
        background = tuple(float(c) for c in rng.uniform(0.1, 0.9, 3))
    return Appearance(lighting, table_variant, background, float(randomization.noise_std))


def table_variant_texture(index: int, size: int = 256) -> np.ndarray:
    """Procedural table texture ``index`` (H, W, 3) uint8: tinted grain, checks or speckle."""
    rng = np.random.default_rng(1000 + index)
    base = rng.uniform(0.2, 0.9, 3)
    yy, xx = np.mgrid[0:size, 0:size] / size
    kind = index % 3
    if kind == 0:  # grain
        pattern = 0.5 + 0.5 * np.sin(2 * np.pi * (6 * yy + 0.3 * np.sin(2 * np.pi * 3 * xx)))
    elif kind == 1:  # checks
        n = int(rng.integers(2, 6))
        pattern = ((np.floor(xx * n) + np.floor(yy * n)) % 2).astype(float)
    else:  # speckle
        pattern = rng.random((size, size))
    contrast = rng.uniform(0.15, 0.45)
    img = base[None, None, :] * (1.0 - contrast + contrast * pattern[..., None])
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


def add_sensor_noise(rgb: np.ndarray, std: float, rng: np.random.Generator) -> np.ndarray:
    """``rgb: (..., H, W, 3)`` uint8 plus Gaussian noise of ``std`` (fraction of full scale)."""
    if std <= 0:
        return rgb
    noisy = rgb.astype(np.float32) + rng.normal(0.0, std * 255.0, size=rgb.shape).astype(np.float32)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
