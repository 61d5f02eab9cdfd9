"""The policy interface shared by white-box (torch) and black-box (onnxruntime) policies.

A policy maps wrist-camera images (and, when its contract reads one, a state vector) to actions
through ``act(images[, state])``: ``(B, A)``, ``(B, K, A)`` or ``(B, A K)`` float32 as its
contract says (:mod:`sim.policies.contract`: ``delta_tcp`` in [-1, 1] with the action semantics
of :mod:`sim.action`, or ``absolute_tcp`` poses, ``A = 6``; or ``joint_position`` targets or
``joint_delta`` changes of the arm's ``A`` joints, in the contract's joint order and units; in
chunks of K). ``images`` is either what the
env returns, ``(B, H, W, 3)`` uint8, or network input, ``(B, 3, H, W)`` float in [0, 1];
``state`` is ``(B, D)`` float32. This module is numpy-only so black-box use never needs torch.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from sim.errors import AdvobjError

__all__ = [
    "IMAGE_SIZE_MIN_PX",
    "IMAGE_SIZE_MAX_PX",
    "Policy",
    "PolicyError",
    "WhiteBoxRequired",
    "prepare_images",
    "require_white_box",
]


# The square input sizes a policy may take (px): the one range for the built-in network's arch, the
# env's render size and a loaded file's input (checked before anything renders at that size).
IMAGE_SIZE_MIN_PX = 32
IMAGE_SIZE_MAX_PX = 512


class PolicyError(AdvobjError, ValueError):
    """A policy file, card or input is invalid; the message names the file or field."""


class WhiteBoxRequired(AdvobjError, TypeError):
    """A gradient-based method was given a policy without gradients."""


@runtime_checkable
class Policy(Protocol):
    image_size: int
    white_box: bool

    def act(self, images, state=None) -> np.ndarray: ...


def prepare_images(images, image_size) -> np.ndarray:
    """``(B, 3, H, W)`` float32 in [0, 1] from env images ``(B, H, W, 3)`` uint8 or network input.

    ``image_size``: ``S`` (square) or ``(H, W)`` px. Raises :class:`PolicyError` naming the
    expected shape when ``images`` does not match.
    """
    H, W = (image_size, image_size) if isinstance(image_size, (int, np.integer)) else tuple(image_size)
    a = np.asarray(images)
    if a.ndim == 3:
        a = a[None]
    if a.ndim != 4:
        raise PolicyError(f"images: expected (B, {H}, {W}, 3) uint8 or (B, 3, {H}, {W}) float, got shape {a.shape}")
    if a.dtype == np.uint8:
        if a.shape[-1] != 3:
            raise PolicyError(f"images: uint8 images must be (B, H, W, 3), got shape {a.shape}")
        a = np.ascontiguousarray(a.transpose(0, 3, 1, 2), dtype=np.float32) / np.float32(255.0)
    elif np.issubdtype(a.dtype, np.floating):
        if a.shape[1] != 3:
            raise PolicyError(f"images: float images must be (B, 3, H, W) in [0, 1], got shape {a.shape}")
        a = np.ascontiguousarray(a, dtype=np.float32)
    else:
        raise PolicyError(f"images: expected uint8 or float, got dtype {a.dtype}")
    if a.shape[2:] != (H, W):
        size = f"{H}x{W}" if H != W else f"{H}x{H}"
        raise PolicyError(f"images: policy expects {size} px, got {a.shape[2]}x{a.shape[3]}")
    return a


def require_white_box(policy) -> None:
    """Raise :class:`WhiteBoxRequired` unless ``policy`` exposes ``features``/``head`` gradients.

    The attack calls this first: it needs ``policy.head(policy.features(x))`` in torch.
    """
    if (
        getattr(policy, "white_box", False)
        and callable(getattr(policy, "features", None))
        and callable(getattr(policy, "head", None))
    ):
        return
    kind = type(policy).__name__
    raise WhiteBoxRequired(
        f"the attack needs a white-box policy (a checkpoint directory with policy.json, a .pt2 or an .onnx file), "
        f"got a {kind}; other black-box policies can be evaluated (advobj policy eval) but not attacked"
    )
