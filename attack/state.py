"""The attack's optimisation state, and the attack checkpoint that holds it (the format's owner).

:class:`AttackState` is everything an iteration advances and a resume restores: the texture, the
iteration count (which fixes the schedule stage), the loss history, both RNG states and the best
validated texture. :func:`attack.optimize.attack_step` takes it one iteration further; the
machinery around it (env, renderer, policy) lives in :class:`attack.optimize.AttackRun`.

Checkpoint layout (``<run>/checkpoint/``, swapped in atomically)::

    state.safetensors   texture (3, S, S) and the torch RNG state
    state.json          iteration, the attack config, the numpy RNG state, history, best score
    best.safetensors    the best validated texture (when there is one)
    texture.npy, ...    the checkpoint's texture as a texture folder (attack.artifact)
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from attack.artifact import AttackArtifact

__all__ = ["History", "AttackState", "better_score", "swap_in", "read_best", "find_checkpoint"]


# The keys of a history written before the objective had named terms, and their names now.
_LEGACY_TERM_KEYS = {"loss_pose": "pose", "loss_saliency": "saliency", "loss_ori": "pose.ori", "loss_dist": "pose.dist"}


@dataclass
class History:
    """What the loop logs per iteration. ``terms`` holds each objective term's mean value per
    image-action pair (by the term's name, e.g. ``pose``, ``saliency``) and its logged parts (as
    ``<term>.<part>``, e.g. ``pose.ori``): a new term adds a key, never a field, so the checkpoint
    format does not change. A term absent from the objective has no key (read as 0)."""

    iteration: list[int] = field(default_factory=list)
    terms: dict[str, list[float]] = field(default_factory=dict)
    grad_norm: list[float] = field(default_factory=list)
    stage: list[int] = field(default_factory=list)
    skipped: int = 0
    seconds: float = 0.0
    # Held-out validation (empty when validation_every = 0); val_iteration counts iterations done.
    val_iteration: list[int] = field(default_factory=list)
    val_t_asr: list[float] = field(default_factory=list)
    val_dist_m: list[float] = field(default_factory=list)
    val_seconds: list[float] = field(default_factory=list)
    # Pose loss on the validation configurations' first frames: a fixed probe set, so unlike
    # the pose term (measured on rollouts that move as the attack succeeds) it is comparable across
    # iterations. NaN where the pose term is off.
    val_probe_pose: list[float] = field(default_factory=list)

    @classmethod
    def from_dict(cls, doc: dict) -> History:
        """A history from ``state.json``, including one written before terms had names."""
        doc = dict(doc)
        terms = {k: list(v) for k, v in doc.pop("terms", {}).items()}
        for old, name in _LEGACY_TERM_KEYS.items():
            if old in doc:
                values = doc.pop(old)
                if any(v != 0.0 for v in values):  # the old format logged 0 for a term that was off
                    terms.setdefault(name, list(values))
        return cls(terms=terms, **doc)

    def to_dict(self) -> dict:
        return dict(self.__dict__)

    def log_terms(self, values: dict[str, float]) -> None:
        """Append one iteration's term values (and parts) by name."""
        for k, v in values.items():
            self.terms.setdefault(k, []).append(float(v))

    def term(self, name: str) -> list[float]:
        """One term's values per iteration; zeros when the objective had no such term."""
        return self.terms.get(name, [0.0] * len(self.iteration))

    # The paper's terms by their old names (plots, metrics and the tradeoff's rows read these).
    loss_pose = property(lambda self: self.term("pose"))
    loss_saliency = property(lambda self: self.term("saliency"))
    loss_ori = property(lambda self: self.term("pose.ori"))
    loss_dist = property(lambda self: self.term("pose.dist"))


@dataclass
class AttackState:
    """What an iteration advances; see the module docstring."""

    texture: torch.Tensor  # (3, S, S) float in [0, 1]
    rng: np.random.Generator
    torch_gen: torch.Generator
    iteration: int = 0
    history: History = field(default_factory=History)
    best: dict | None = None  # {"iteration", "t_asr", "dist_m", "episodes"} of the best validation
    best_texture: torch.Tensor | None = None

    @classmethod
    def start(cls, texture: torch.Tensor, seed: int) -> AttackState:
        return cls(texture, np.random.default_rng(seed), torch.Generator().manual_seed(seed))

    def write(self, folder: Path, config: dict) -> None:
        """``state.safetensors``, ``state.json`` (and ``best.safetensors``) into ``folder``."""
        save_file(
            {"texture": self.texture.detach().cpu().contiguous(), "torch_rng": self.torch_gen.get_state()},
            str(folder / "state.safetensors"),
        )
        doc = {
            "iteration": self.iteration,
            "config": config,
            "numpy_rng": self.rng.bit_generator.state,
            "history": self.history.to_dict(),
            "best": self.best,
        }
        (folder / "state.json").write_text(json.dumps(doc))
        if self.best_texture is not None:
            # Resume restores the best texture from here even if best/ was deleted meanwhile.
            save_file({"texture": self.best_texture.cpu().contiguous()}, str(folder / "best.safetensors"))

    @classmethod
    def read(cls, folder: Path, device) -> tuple[AttackState, dict]:
        """``(state, config dict)`` of a checkpoint folder; ``OSError``/``ValueError`` if unreadable."""
        doc = json.loads((folder / "state.json").read_text())
        tensors = load_file(str(folder / "state.safetensors"))
        gen = torch.Generator()
        gen.set_state(tensors["torch_rng"])
        rng = np.random.default_rng()
        rng.bit_generator.state = doc["numpy_rng"]
        best, best_texture = doc.get("best"), None
        if best is not None and (folder / "best.safetensors").is_file():
            best_texture = load_file(str(folder / "best.safetensors"))["texture"].to(device)
        state = cls(
            tensors["texture"].to(device),
            rng,
            gen,
            int(doc["iteration"]),
            History.from_dict(doc["history"]),
            best,
            best_texture,
        )
        return state, doc["config"]


def better_score(new: dict, best: dict | None) -> bool:
    """Is validation result ``new`` strictly better than ``best``: higher T-ASR, ties broken by the
    lower mean final distance to the adversarial object (equal on both: not better)."""
    if best is None:
        return True
    if new["t_asr"] != best["t_asr"]:
        return new["t_asr"] > best["t_asr"]
    return new["dist_m"] < best["dist_m"]


def swap_in(tmp: Path, final: Path) -> Path:
    """Replace directory ``final`` by ``tmp`` by renames: at every instant ``final/`` or
    ``final.old/`` (see :func:`find_checkpoint`) is complete."""

    old = final.with_name(final.name + ".old")
    if final.exists():
        shutil.rmtree(old, ignore_errors=True)
        final.replace(old)
    tmp.replace(final)
    shutil.rmtree(old, ignore_errors=True)
    return final


def read_best(best_dir: Path) -> tuple[dict, torch.Tensor] | None:
    """``(best.json, texture (3, S, S))`` of a ``best/`` directory (or its crash-left ``.old``)."""
    for d in (best_dir, best_dir.with_name(best_dir.name + ".old")):
        try:
            info = json.loads((d / "best.json").read_text())
            tex = AttackArtifact.load(d).texture
        except (OSError, ValueError):
            continue
        return info, torch.from_numpy(np.ascontiguousarray(tex.transpose(2, 0, 1))).to(torch.float32)
    return None


def find_checkpoint(out_dir: str | Path) -> Path | None:
    """The newest complete checkpoint in ``out_dir`` (``checkpoint/``, else a crash-left ``.old``)."""
    for name in ("checkpoint", "checkpoint.old"):
        c = Path(out_dir) / name
        if (c / "state.json").is_file() and (c / "state.safetensors").is_file():
            return c
    return None
