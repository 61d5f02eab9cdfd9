"""The attack's output folder (a *texture folder*): the one owner of its format.

Layout::

    texture.npy    (H, W, 3) float32 in [0, 1]: the texture evaluation, fabrication and trials use
    texture.png    its 8-bit image
    run.json       {"config": {"attack": {..., "adversarial_mesh": ...}, "scene": ..., ...}, "seed": ...}
                   plus provenance (commit, versions) when written by a finished run
    configs.json   the configurations the texture was optimised ("attack") and selected
                   ("validation") on; ``best/`` and ``checkpoint/`` folders use their run folder's

An attack run folder, its ``best/`` and the tradeoff sweep's snapshots are all texture folders:
every reader and writer goes through :class:`AttackArtifact`, so the format is defined here only.
Nothing is unpickled: ``texture.npy`` is read with ``allow_pickle=False``.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from sim.configs import config_id, pose_id
from sim.errors import AdvobjError
from sim.runinfo import write_run_info

__all__ = [
    "TEXTURE_NPY",
    "TEXTURE_PNG",
    "RUN_JSON",
    "CONFIG_RECORD",
    "ArtifactError",
    "AttackArtifact",
    "texture_to_uint8",
    "write_texture_png",
    "write_config_record",
    "read_config_record",
    "overlap_count",
]

TEXTURE_NPY = "texture.npy"
TEXTURE_PNG = "texture.png"
RUN_JSON = "run.json"
CONFIG_RECORD = "configs.json"
_RECORD_FORMAT = "advobj-attack-configs/1"


class ArtifactError(AdvobjError, ValueError):
    """A texture folder is missing a file or holds a malformed one; the message names the file."""


def texture_to_uint8(texture) -> np.ndarray:
    """``(3, H, W)`` float [0, 1] (torch) or ``(H, W, 3)`` -> ``(H, W, 3)`` uint8."""
    if not isinstance(texture, np.ndarray) and hasattr(texture, "detach"):
        texture = texture.detach().cpu().permute(1, 2, 0).numpy()
    return np.clip(np.rint(np.asarray(texture) * 255.0), 0, 255).astype(np.uint8)


def write_texture_png(path: str | Path, texture) -> Path:
    path = Path(path)
    iio.imwrite(path, texture_to_uint8(texture))
    return path


def write_config_record(out_dir: str | Path, attack_configs, validation_configs) -> Path:
    """Write ``out_dir/configs.json``: seed, content id (:func:`sim.configs.config_id`) and pose id
    (:func:`sim.configs.pose_id`, without the seed) of every configuration the attack may draw for
    EOT and every one its best texture is selected on."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    doc = {
        "format": _RECORD_FORMAT,
        **{
            part: [{"seed": int(c.seed), "id": config_id(c), "pose": pose_id(c)} for c in cs]
            for part, cs in (("attack", attack_configs), ("validation", validation_configs))
        },
    }
    tmp = out / (CONFIG_RECORD + ".tmp")
    tmp.write_text(json.dumps(doc))
    tmp.replace(out / CONFIG_RECORD)
    return out / CONFIG_RECORD


def read_config_record(texture_dir: str | Path) -> set[str] | None:
    """The configuration ids a texture folder was optimised or selected on, or ``None`` when no
    record exists: each entry's content id, and ``"pose:<pose id>"`` where the record has pose ids
    (:func:`overlap_count` matches either). ``best/`` and ``checkpoint/`` textures use their run
    folder's record."""
    d = Path(texture_dir)
    for cand in (d / CONFIG_RECORD, d.parent / CONFIG_RECORD):
        if cand.is_file():
            try:
                doc = json.loads(cand.read_text())
                if not isinstance(doc, dict) or doc.get("format") != _RECORD_FORMAT:
                    raise ValueError(f"format is not {_RECORD_FORMAT!r}")
                return {
                    key
                    for part in ("attack", "validation")
                    for e in doc[part]
                    for key in (e["id"], *((f"pose:{e['pose']}",) if "pose" in e else ()))
                }
            except (OSError, ValueError, KeyError, TypeError) as err:
                raise ValueError(f"{cand}: not a configuration record ({err})") from None
    return None


def overlap_count(configs, seen) -> int:
    """How many of ``configs`` a configuration record (:func:`read_config_record`) holds: by content
    id, or by pose id where the record has them (the same poses under another seed count)."""
    return sum(1 for c in configs if config_id(c) in seen or f"pose:{pose_id(c)}" in seen)


@dataclass(frozen=True)
class AttackArtifact:
    """One texture folder's content.

    ``texture``: (H, W, 3) float32 in [0, 1]. ``config``: ``run.json``'s ``config`` (the attack
    config under ``"attack"``, its mesh under ``"attack"]["adversarial_mesh"``, optionally the
    scene). ``seed``: the run's seed. Set by :meth:`load`: ``path``, ``sha256`` (of the stored
    ``texture.npy`` bytes, which guards resumes and trial plans against a changed texture) and
    ``trained_on`` (the ids of ``configs.json``, None without a record).
    """

    texture: np.ndarray = field(repr=False)
    config: dict = field(default_factory=dict, repr=False)
    seed: int | None = None
    path: Path | None = None
    sha256: str = ""
    trained_on: frozenset | None = field(default=None, repr=False)

    # ------------------------------------------------------------------ views
    @property
    def attack_config(self) -> dict:
        a = self.config.get("attack") if isinstance(self.config, dict) else None
        return a if isinstance(a, dict) else {}

    @property
    def mesh(self) -> str | None:
        """The mesh the texture belongs to (None: the scene's adversarial mesh)."""
        return self.attack_config.get("adversarial_mesh")

    @property
    def scene(self) -> dict:
        s = self.config.get("scene") if isinstance(self.config, dict) else None
        return s if isinstance(s, dict) else {}

    @property
    def texture_u8(self) -> np.ndarray:
        """(H, W, 3) uint8: what the renderers put on the mesh (and ``texture.png`` shows)."""
        return texture_to_uint8(self.texture)

    # ------------------------------------------------------------------ building
    @classmethod
    def from_tensor(cls, texture, config: dict | None = None, seed: int | None = None) -> AttackArtifact:
        """From an attack's texture ``(3, S, S)`` torch tensor (clamped to [0, 1])."""
        t = texture.detach().cpu().clamp(0, 1).permute(1, 2, 0).numpy().astype(np.float32)
        return cls(np.ascontiguousarray(t), dict(config or {}), seed)

    # ------------------------------------------------------------------ I/O
    def save(self, folder: str | Path, run: str = "plain") -> Path:
        """Write ``texture.npy`` and ``texture.png`` into ``folder``, and ``run.json``:

        ``run="plain"``: ``{config, seed}`` only (fast: checkpoints and ``best/`` are written often);
        ``run="provenance"``: with the commit, versions and argv (:func:`sim.runinfo.write_run_info`);
        ``run="none"``: leave ``run.json`` to the caller (a job writing its own provenance).
        """
        d = Path(folder)
        d.mkdir(parents=True, exist_ok=True)
        np.save(d / TEXTURE_NPY, np.asarray(self.texture, dtype=np.float32))
        write_texture_png(d / TEXTURE_PNG, self.texture)
        if run == "provenance":
            write_run_info(d, self.config, self.seed)
        elif run == "plain":
            (d / RUN_JSON).write_text(json.dumps({"config": self.config, "seed": self.seed}, indent=2, default=str))
        elif run != "none":
            raise ValueError(f"run: 'plain', 'provenance' or 'none', got {run!r}")
        return d

    @classmethod
    def load(cls, folder: str | Path, error: type[Exception] = ArtifactError) -> AttackArtifact:
        """Read a texture folder; any missing or malformed file raises ``error`` in one line."""
        p = Path(folder)
        if not p.is_dir():
            raise error(
                f"{p}: not an attack run directory (expected {TEXTURE_NPY} and {RUN_JSON} from 'advobj attack run')"
            )
        tex_path, run_path = p / TEXTURE_NPY, p / RUN_JSON
        if not tex_path.is_file():
            raise error(f"{tex_path}: missing; is the attack run finished?")
        try:
            raw = tex_path.read_bytes()
            tex = np.load(tex_path, allow_pickle=False)
        except (OSError, ValueError) as err:
            raise error(f"{tex_path}: not a texture array ({err})") from None
        if tex.ndim != 3 or tex.shape[-1] != 3 or not np.issubdtype(tex.dtype, np.floating):
            raise error(f"{tex_path}: expected an (H, W, 3) float array in [0, 1], got {tex.shape} {tex.dtype}")
        if not np.isfinite(tex).all() or tex.min() < 0 or tex.max() > 1:
            raise error(f"{tex_path}: texture values must be finite and in [0, 1]")
        if not run_path.is_file():
            raise error(f"{run_path}: missing; the attack's run.json says which mesh the texture belongs to")
        try:
            doc = json.loads(run_path.read_text())
            config = doc["config"]
            if not isinstance(config["attack"], dict):
                raise TypeError("config.attack is not a mapping")
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError, AttributeError) as err:
            raise error(f"{run_path}: cannot read config.attack ({type(err).__name__}: {err})") from None
        try:
            seen = read_config_record(p)
        except ValueError as err:
            raise error(str(err)) from None
        seed = doc.get("seed") if isinstance(doc.get("seed"), int) else None
        return cls(
            np.asarray(tex, dtype=np.float32),
            config,
            seed,
            p,
            hashlib.sha256(raw).hexdigest(),
            None if seen is None else frozenset(seen),
        )

    @staticmethod
    def texture_sha256(folder: str | Path) -> str:
        """sha256 of a folder's stored ``texture.npy`` bytes (without validating the rest)."""
        return hashlib.sha256((Path(folder) / TEXTURE_NPY).read_bytes()).hexdigest()
