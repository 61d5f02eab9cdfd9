"""Policy checkpoints: a directory with safetensors weights and a JSON policy card.

Layout::

    <dir>/policy.json          the card (PolicyCard): architecture, image size, normalization,
                               action scaling, training config, clean success, seed, git commit,
                               and the SHA-256 of the weights file
    <dir>/weights.safetensors  the state_dict

Nothing is ever unpickled: weights are safetensors only, and the card's hash must match the
weights file, so a swapped or edited weights file (or a pickle dressed up as one) is refused
before it is parsed.
"""

from __future__ import annotations

import hashlib
import time
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from sim.policies.card import CARD_FORMAT, CARD_NAME, PolicyCard, load_card
from sim.policies.contract import check_scene
from sim.policies.interface import PolicyError
from sim.policies.onnx_policy import OnnxPolicy
from sim.policies.onnx_torch import convert_onnx
from sim.policies.policy import VisuomotorPolicy
from sim.policies.pt2 import load_pt2

__all__ = ["WEIGHTS_NAME", "save_checkpoint", "load_checkpoint", "load_policy", "as_white_box", "is_checkpoint"]

WEIGHTS_NAME = "weights.safetensors"


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def is_checkpoint(path: str | Path) -> bool:
    p = Path(path)
    return p.is_dir() and (p / CARD_NAME).is_file()


def save_checkpoint(out_dir: str | Path, policy, card: PolicyCard) -> PolicyCard:
    """Write ``policy``'s weights and ``card`` (hash and time filled in) into ``out_dir``.

    Files are written to temporaries and renamed, so an interrupted save leaves the previous
    checkpoint intact.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if card.arch != policy.config:
        raise PolicyError("card.arch does not match the policy's architecture")
    if (why := card.arch_mismatch()) is not None:
        raise PolicyError(f"card: {why}")
    state = {k: v.detach().cpu().contiguous() for k, v in policy.state_dict().items()}
    tmp_w = out / (WEIGHTS_NAME + ".tmp")
    save_file(state, str(tmp_w), metadata={"format": CARD_FORMAT})
    card = card.model_copy(
        update={"weights_sha256": _sha256(tmp_w), "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    )
    tmp_c = out / (CARD_NAME + ".tmp")
    tmp_c.write_text(card.model_dump_json(indent=2))
    tmp_w.replace(out / WEIGHTS_NAME)
    tmp_c.replace(out / CARD_NAME)
    return card


def load_checkpoint(path: str | Path, device="cpu"):
    """``(policy, card)`` from checkpoint directory ``path``; the policy is in eval mode on ``device``.

    Refuses (with :class:`PolicyError`) a missing or malformed card, weights whose hash differs
    from the card's, a weights file that is not safetensors, and weights that do not fit the
    architecture.
    """
    p = Path(path)
    card = load_card(p)
    if not p.is_dir():
        raise PolicyError(f"{p}: a checkpoint is a directory holding {CARD_NAME} and {WEIGHTS_NAME}")
    wpath = p / WEIGHTS_NAME
    if not wpath.is_file():
        raise PolicyError(f"{wpath}: weights file missing")
    if not card.weights_sha256:
        raise PolicyError(f"{p / CARD_NAME}: weights_sha256 is empty; cannot verify {WEIGHTS_NAME}")
    if _sha256(wpath) != card.weights_sha256:
        raise PolicyError(
            f"{wpath}: weights do not match the card's weights_sha256 (file modified or replaced); refusing to load"
        )
    try:
        state = load_file(str(wpath), device="cpu")
    except (SafetensorError, OSError, ValueError) as err:
        raise PolicyError(f"{wpath}: not a safetensors weights file ({err})") from None
    if "arch" not in card.model_fields_set:
        raise PolicyError(f"{p / CARD_NAME}: arch: a checkpoint's card names the network its weights are for")
    if (why := card.arch_mismatch()) is not None:
        raise PolicyError(f"{p / CARD_NAME}: {why}")
    policy = VisuomotorPolicy(card.arch, contract=card.contract)
    policy.card = card
    try:
        policy.load_state_dict(state, strict=True)
    except RuntimeError as err:
        first = str(err).splitlines()[0:2]
        raise PolicyError(f"{wpath}: weights do not fit arch {card.arch.arch!r} ({' '.join(first)})") from None
    return policy.to(torch.device(device)).eval(), card


def load_policy(path: str | Path, device="cpu", white_box: bool = False, spec=None):
    """Any policy behind the :class:`sim.policies.interface.Policy` interface.

    A checkpoint directory gives a white-box :class:`VisuomotorPolicy`; a ``.pt2`` ExportedProgram
    a white-box :class:`sim.policies.graph_policy.GraphPolicy` (:mod:`sim.policies.pt2`); an
    ``.onnx`` file the black-box :class:`sim.policies.onnx_policy.OnnxPolicy` (onnxruntime), or
    with ``white_box`` its torch conversion, checked against onnxruntime on frames of ``spec``
    (default: the built-in scene) before it is returned (:mod:`sim.policies.onnx_torch`).
    With ``spec``, a policy reading a camera the scene lacks (or one of another size) is refused
    here (:func:`sim.policies.contract.check_scene`). Anything else is refused.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if p.is_file() and suffix == ".onnx":
        onnx_policy = OnnxPolicy(p)
        policy = convert_onnx(onnx_policy, device, spec) if white_box else onnx_policy
    elif p.is_file() and suffix == ".pt2":
        policy = load_pt2(p, device)
    elif p.is_dir() or p.name == CARD_NAME:
        policy = load_checkpoint(p if p.is_dir() else p.parent, device)[0]
    else:
        policy = None
    if policy is not None:
        if spec is not None:
            check_scene(policy, spec)  # a camera the scene lacks, or of another size: one line, now
        return policy
    if p.exists():
        raise PolicyError(
            f"{p}: not a policy; expected a checkpoint directory (with {CARD_NAME}), an .onnx or a .pt2 file"
        )
    raise PolicyError(f"{p}: no such file or directory")


def as_white_box(policy, device="cpu", spec=None):
    """``policy`` itself when it has gradients; an :class:`OnnxPolicy`'s checked torch conversion
    (frames of ``spec``); anything else unchanged (the attack then refuses it)."""
    if isinstance(policy, OnnxPolicy):
        return convert_onnx(policy, device, spec)
    return policy
