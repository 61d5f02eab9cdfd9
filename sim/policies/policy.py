"""The white-box visuomotor policy: normalization -> backbone -> MLP head -> tanh action.

``act = head(features(x))`` with

* ``features(x: (B, 3, S, S) float in [0, 1]) -> A: (B, C, h, w)``, the last conv feature map
  (normalization happens inside, so attacks work in image space);
* ``head(A, state=None) -> (B, 6)`` in [-1, 1]: 1x1 conv to ``head_channels``, flatten, (join
  the state vector,) MLP, ``tanh``. Chunked policies output ``(B, K, 6)``; absolute-pose policies
  a linear output (see :mod:`sim.policies.contract`).

Grad-CAM is then ``w = d||a|| / dA`` averaged over ``(h, w)`` without hooks. The head flattens the
map instead of global-average-pooling it because the action depends on *where* the goal is in the
image; this ties a policy to its image size (recorded in the policy card).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import torch
from pydantic import Field
from torch import nn

from sim.configio import StrictModel
from sim.policies.backbones import BACKBONES, build_backbone
from sim.policies.contract import PolicyContract
from sim.policies.interface import IMAGE_SIZE_MAX_PX, IMAGE_SIZE_MIN_PX, PolicyError, prepare_images

__all__ = ["PolicyArch", "VisuomotorPolicy", "IMAGENET_MEAN", "IMAGENET_STD", "ACTION_DIM"]

ACTION_DIM = 6
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

ArchName = Literal[tuple(BACKBONES)]  # type: ignore[valid-type]


class PolicyArch(StrictModel):
    """Everything needed to rebuild the network (stored in the policy card)."""

    arch: ArchName = "resnet18"
    image_size: int = Field(64, ge=IMAGE_SIZE_MIN_PX, le=IMAGE_SIZE_MAX_PX, description="square input size, px")
    small_stem: bool = True
    head_channels: int = Field(32, ge=1)
    head_hidden: int = Field(256, ge=1)
    mean: tuple[float, float, float] = IMAGENET_MEAN
    std: tuple[float, float, float] = IMAGENET_STD
    # The policy contract's shape (sim.policies.contract); the defaults are the original policy.
    state_dim: int = Field(0, ge=0, le=64, description="proprioceptive inputs, joined to the flattened features")
    chunk: int = Field(1, ge=1, le=128, description="actions per call (K)")
    output: Literal["tanh", "linear"] = Field(
        "tanh", description="tanh for delta_tcp actions in [-1, 1]; linear for absolute_tcp poses"
    )


class VisuomotorPolicy(nn.Module):
    """Image-to-action policy; see the module docstring for the white-box contract."""

    white_box = True

    def __init__(self, config: PolicyArch | None = None, contract=None, **kwargs):
        super().__init__()
        self.config = config if config is not None else PolicyArch(**kwargs)
        c = self.config
        self.contract = contract if contract is not None else PolicyContract()
        k = self.contract
        if (c.state_dim, c.chunk, c.output) != (
            k.state_dim,
            k.action.chunk,
            "tanh" if k.action.kind == "delta_tcp" else "linear",
        ):
            raise PolicyError(
                f"contract: ({k.describe()}) does not fit the architecture (state_dim {c.state_dim}, chunk {c.chunk}, "
                f"output {c.output}); pass the matching contract"
            )
        if any(s <= 0 for s in self.config.std):
            raise PolicyError(f"std: normalization std must be positive, got {self.config.std}")
        self.image_size = self.config.image_size
        self.register_buffer("mean", torch.tensor(self.config.mean, dtype=torch.float32).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(self.config.std, dtype=torch.float32).view(1, 3, 1, 1))
        self.backbone = build_backbone(self.config.arch, self.config.small_stem)
        with torch.no_grad():
            c, h, w = self.backbone.eval()(torch.zeros(1, 3, self.image_size, self.image_size)).shape[1:]
        self.backbone.train()
        self.feature_shape = (int(c), int(h), int(w))
        self.reduce = nn.Sequential(nn.Conv2d(c, self.config.head_channels, 1), nn.ReLU())
        self.mlp = nn.Sequential(
            nn.Flatten(),
            nn.Linear(self.config.head_channels * h * w + self.config.state_dim, self.config.head_hidden),
            nn.ReLU(),
            nn.Linear(self.config.head_hidden, ACTION_DIM * self.config.chunk),
        )

    @property
    def device(self) -> torch.device:
        return self.mean.device

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """``x: (B, 3, S, S)`` float in [0, 1] -> last conv feature map ``(B, C, h, w)``."""
        # Shape check in Python; skipped while tracing for ONNX export, where it would be baked in.
        if not torch.jit.is_tracing() and (
            x.ndim != 4 or x.shape[1] != 3 or tuple(x.shape[2:]) != (self.image_size, self.image_size)
        ):
            raise PolicyError(
                f"images: policy expects (B, 3, {self.image_size}, {self.image_size}) float in [0, 1], got "
                f"{tuple(x.shape)}"
            )
        return self.backbone((x - self.mean) / self.std)

    def head(self, A: torch.Tensor, state: torch.Tensor | None = None) -> torch.Tensor:
        """Feature map ``(B, C, h, w)`` (and ``state (B, D)``) -> actions ``(B, 6)``, or ``(B, K, 6)``
        for chunks; in [-1, 1] unless the output is linear."""
        z = torch.flatten(self.reduce(A), 1)
        D = self.config.state_dim
        if D:
            if state is None or (not torch.jit.is_tracing() and tuple(state.shape) != (z.shape[0], D)):
                got = None if state is None else tuple(state.shape)
                raise PolicyError(f"state: policy expects a ({z.shape[0]}, {D}) state input, got {got}")
            z = torch.cat([z, state.to(z.dtype)], 1)
        out = self.mlp(z)  # its Flatten is a no-op on (B, F); kept so old weights load by name
        if self.config.output == "tanh":
            out = torch.tanh(out)
        return out.view(-1, self.config.chunk, ACTION_DIM) if self.config.chunk > 1 else out

    def forward(self, x: torch.Tensor, state: torch.Tensor | None = None) -> torch.Tensor:
        return self.head(self.features(x), state)

    @torch.no_grad()
    def act(self, images, state=None) -> np.ndarray:
        """Actions ``(B, 6)`` (or ``(B, K, 6)``) float32 for env images ``(B, S, S, 3)`` uint8 or
        ``(B, 3, S, S)`` floats, and the ``(B, D)`` state when the policy reads one.

        Runs in eval mode (BN running statistics) and restores the previous mode.
        """
        if isinstance(images, torch.Tensor):
            x = images.to(self.device, torch.float32)
            if images.dtype == torch.uint8:
                x = x.permute(0, 3, 1, 2) / 255.0
        else:
            x = torch.from_numpy(prepare_images(images, self.image_size)).to(self.device)
        st = None if state is None else torch.as_tensor(np.asarray(state, dtype=np.float32), device=self.device)
        was_training = self.training
        self.eval()
        try:
            return self(x, st).cpu().numpy().astype(np.float32)
        finally:
            self.train(was_training)
