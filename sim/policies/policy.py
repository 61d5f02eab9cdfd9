"""The white-box visuomotor policy: normalization -> backbone -> MLP head -> tanh action.

``act = head(features(x))`` with

* ``features(x: (B, 3, S, S) float in [0, 1]) -> A: (B, C, h, w)``, the last conv feature map
  (normalization happens inside, so attacks work in image space);
* ``head(A, state=None) -> (B, 6)`` in [-1, 1]: 1x1 conv to ``head_channels``, flatten, (join
  the state vector,) MLP, ``tanh``. Chunked policies output ``(B, K, 6)``; absolute-pose policies
  a linear output (see :mod:`sim.policies.contract`). A joint-space policy outputs ``action_dim``
  values per action, one per joint: ``tanh`` times ``output_scale`` (a ``joint_delta`` policy: each
  joint's most motion per step, so the network cannot command more than the arm executes) or linear
  (``joint_position`` targets).

Grad-CAM is then ``w = d||a|| / dA`` averaged over ``(h, w)`` without hooks. The head flattens the
map instead of global-average-pooling it because the action depends on *where* the goal is in the
image; this ties a policy to its image size (recorded in the policy card).

**Several cameras** (``PolicyArch.cameras``, e.g. ``("wrist", "front")``): the protocol of
:class:`sim.policies.graph_policy.GraphPolicy`, ``features({camera: (B, 3, H_c, W_c)}) ->
{camera: A_c}`` and ``head({camera: A_c}, state)``. Each camera has a backbone of its own (weights
are not shared): a shared trunk's batch norm would mix the cameras' statistics, and the attack's
per-camera Grad-CAM cut needs each map computed from its own image only. A scene camera renders
at its scene's size (``camera_px``, a whole multiple of ``image_size`` per side), averaged down to
``image_size`` before its backbone (differentiable: the attack's gradients reach every rendered
pixel), so every camera costs what the wrist camera does. The ``1x1`` reduction is shared; the
flattened maps are joined in camera order (then the state) before the MLP. The exported file has
one image input per camera, named by it (and ``state``). The default, ``("wrist",)``, is the
original one-camera network, weights and outputs unchanged.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import Field, model_serializer, model_validator
from torch import nn

from sim.configio import StrictModel
from sim.policies.backbones import BACKBONES, build_backbone
from sim.policies.contract import WRIST_CAMERA, InputBinding, InputPlan, PolicyContract, default_plan
from sim.policies.interface import IMAGE_SIZE_MAX_PX, IMAGE_SIZE_MIN_PX, PolicyError, prepare_images

__all__ = [
    "PolicyArch",
    "VisuomotorPolicy",
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "ACTION_DIM",
    "file_inputs",
    "scene_camera_px",
]

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
        "tanh",
        description="tanh for delta_tcp actions in [-1, 1] (and joint_delta, times output_scale); linear for "
        "absolute_tcp poses and joint_position targets",
    )
    action_dim: int = Field(
        ACTION_DIM, ge=1, le=64, description="values per action: 6 (a TCP action) or one per joint (a joint action)"
    )
    output_scale: tuple[float, ...] = Field(
        (),
        description="tanh output: each action value's bound (a joint_delta policy: each joint's most motion per "
        "step, rad or m); empty: 1",
    )
    cameras: tuple[str, ...] = Field(
        (WRIST_CAMERA,),
        min_length=1,
        description="the cameras it reads, in input order: wrist and/or scene cameras by name, one backbone each",
    )
    camera_px: dict[str, tuple[int, int]] = Field(
        default_factory=dict,
        description="(H, W) px of each scene camera it reads (as its scene renders it; each side a whole multiple of "
        "image_size), averaged down to image_size before its backbone",
    )

    @model_validator(mode="after")
    def _camera_sizes(self):
        if self.output_scale:
            if self.output != "tanh":
                raise ValueError("output_scale: scales a tanh output; a linear output has none")
            if len(self.output_scale) != self.action_dim:
                raise ValueError(
                    f"output_scale: one bound per action value: {len(self.output_scale)} for action_dim "
                    f"{self.action_dim}"
                )
            if any(not v > 0 for v in self.output_scale):
                raise ValueError(f"output_scale: each bound must be > 0, got {list(self.output_scale)}")
        cams = self.cameras
        if len(set(cams)) != len(cams):
            raise ValueError(f"cameras: name each camera once, got {list(cams)}")
        scene = [c for c in cams if c != WRIST_CAMERA]
        if set(self.camera_px) != set(scene):
            missing = [c for c in scene if c not in self.camera_px]
            what = f"no size for camera {missing[0]!r}" if missing else "sizes of cameras it does not read"
            raise ValueError(f"camera_px: {what}; give (H, W) px for each scene camera in cameras, none for wrist")
        S = self.image_size
        for name, (h, w) in self.camera_px.items():
            if not all(IMAGE_SIZE_MIN_PX <= v <= IMAGE_SIZE_MAX_PX for v in (h, w)):
                raise ValueError(f"camera_px.{name}: each side must be {IMAGE_SIZE_MIN_PX}..{IMAGE_SIZE_MAX_PX} px")
            if h % S or w % S:
                raise ValueError(
                    f"camera_px.{name}: {h}x{w} px is not a whole multiple of image_size {S} px per side (its frames "
                    "are averaged down to image_size)"
                )
        return self

    @model_serializer(mode="wrap")
    def _dump(self, handler):
        # A one-camera network dumps as before cameras existed: cards, run.json and resume hashes unchanged.
        d = handler(self)
        if isinstance(d, dict):
            if tuple(self.cameras) == (WRIST_CAMERA,):
                d.pop("cameras", None)
            if not self.camera_px:
                d.pop("camera_px", None)
            if self.action_dim == ACTION_DIM:  # a TCP network dumps as before joint actions existed
                d.pop("action_dim", None)
            if not self.output_scale:
                d.pop("output_scale", None)
        return d

    def contract_mismatch(self, contract: PolicyContract) -> str | None:
        """Why this network cannot honour ``contract`` (None: it can), naming the field: its state
        width, chunk and values per action must be the contract's, and its output ``tanh`` for
        ``delta_tcp``, ``tanh`` (optionally scaled) or linear for ``joint_delta``, linear otherwise."""
        c, a = contract, self
        if a.state_dim != c.state_dim:
            return f"arch.state_dim is {a.state_dim} but the contract's state {list(c.state)} has {c.state_dim} values"
        if a.chunk != c.action.chunk:
            return f"arch.chunk is {a.chunk} but contract.action.chunk is {c.action.chunk}"
        if a.action_dim != c.action_dim:
            return f"arch.action_dim is {a.action_dim} but {c.action.kind} actions have {c.action_dim} values"
        allowed = {"delta_tcp": ("tanh",), "joint_delta": ("tanh", "linear")}.get(c.action.kind, ("linear",))
        if a.output not in allowed:
            return f"arch.output is {a.output!r} but {c.action.kind} actions need {' or '.join(map(repr, allowed))}"
        if a.output_scale and c.action.kind != "joint_delta":
            return f"arch.output_scale: {c.action.kind} actions are not scaled (joint_delta's are)"
        return None

    def camera_size(self, camera: str) -> tuple[int, int]:
        """``(H, W)`` px of camera ``camera``'s frames: ``image_size`` square for the wrist camera."""
        return (self.image_size, self.image_size) if camera == WRIST_CAMERA else tuple(self.camera_px[camera])

    @property
    def is_one_camera(self) -> bool:
        """The original network: the wrist camera alone, one image input named ``images``."""
        return tuple(self.cameras) == (WRIST_CAMERA,)

    def input_plan(self, contract: PolicyContract | None = None) -> InputPlan:
        """The network's inputs (:func:`sim.policies.contract.default_plan`) under ``contract``."""
        contract = contract if contract is not None else PolicyContract()
        cams = None if self.is_one_camera else {n: self.camera_size(n) for n in self.cameras}
        return default_plan(self.image_size, contract, cams)


class VisuomotorPolicy(nn.Module):
    """Image-to-action policy; see the module docstring for the white-box contract."""

    white_box = True

    def __init__(self, config: PolicyArch | None = None, contract=None, **kwargs):
        super().__init__()
        self.config = config if config is not None else PolicyArch(**kwargs)
        c = self.config
        self.contract = contract if contract is not None else PolicyContract()
        k = self.contract
        if (why := c.contract_mismatch(k)) is not None:
            raise PolicyError(
                f"contract: ({k.describe()}) does not fit the architecture ({why}); pass the matching contract"
            )
        if any(s <= 0 for s in self.config.std):
            raise PolicyError(f"std: normalization std must be positive, got {self.config.std}")
        self.image_size = self.config.image_size
        self.cameras = tuple(self.config.cameras)
        #: the model's inputs (sim.policies.contract.InputPlan): what policy_cameras, call_policy and check_scene read
        self.inputs: InputPlan = c.input_plan(self.contract)
        if c.output_scale:  # not in the weights file: it is the card's (arch.output_scale)
            self.register_buffer("out_scale", torch.tensor(c.output_scale, dtype=torch.float32), persistent=False)
        self.register_buffer("mean", torch.tensor(self.config.mean, dtype=torch.float32).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(self.config.std, dtype=torch.float32).view(1, 3, 1, 1))
        if c.is_one_camera:
            self.backbone = build_backbone(self.config.arch, self.config.small_stem)
            trunk = self.backbone
        else:  # one trunk per camera, built in camera order (module docstring)
            self.backbones = nn.ModuleDict({n: build_backbone(c.arch, c.small_stem) for n in self.cameras})
            trunk = self.backbones[self.cameras[0]]
        with torch.no_grad():
            c, h, w = trunk.eval()(torch.zeros(1, 3, self.image_size, self.image_size)).shape[1:]
        for m in self.backbones.values() if not self.config.is_one_camera else (trunk,):
            m.train()
        self.feature_shape = (int(c), int(h), int(w))
        self.reduce = nn.Sequential(nn.Conv2d(c, self.config.head_channels, 1), nn.ReLU())
        self.mlp = nn.Sequential(
            nn.Flatten(),
            nn.Linear(
                len(self.cameras) * self.config.head_channels * h * w + self.config.state_dim, self.config.head_hidden
            ),
            nn.ReLU(),
            nn.Linear(self.config.head_hidden, self.config.action_dim * self.config.chunk),
        )

    @property
    def device(self) -> torch.device:
        return self.mean.device

    def _check(self, x: torch.Tensor, camera: str) -> None:
        # Shape check in Python; skipped while tracing for ONNX export, where it would be baked in.
        H, W = self.config.camera_size(camera)
        if not torch.jit.is_tracing() and (x.ndim != 4 or x.shape[1] != 3 or tuple(x.shape[2:]) != (H, W)):
            which = "" if self.config.is_one_camera else f" from camera {camera!r}"
            raise PolicyError(f"images: policy expects (B, 3, {H}, {W}) float in [0, 1]{which}, got {tuple(x.shape)}")

    def _trunk(self, x: torch.Tensor, camera: str) -> torch.Tensor:
        self._check(x, camera)
        if self.config.is_one_camera:
            return self.backbone((x - self.mean) / self.std)
        H, W = self.config.camera_size(camera)
        S = self.image_size
        if (H, W) != (S, S):  # a scene camera's frame, averaged down to the backbone's size
            x = F.avg_pool2d(x, (H // S, W // S))
        return self.backbones[camera]((x - self.mean) / self.std)

    def features(self, x):
        """``x: (B, 3, S, S)`` float in [0, 1] -> last conv feature map ``(B, C, h, w)``; for several
        cameras ``{camera: (B, 3, H_c, W_c)}`` -> ``{camera: (B, C, h, w)}`` (a dict in, a dict out)."""
        if isinstance(x, dict):
            missing = [n for n in self.cameras if n not in x]
            if missing:
                raise PolicyError(
                    f"images: policy reads cameras {', '.join(self.cameras)}; no images of {missing[0]!r} given"
                )
            return {n: self._trunk(x[n], n) for n in self.cameras}
        if not self.config.is_one_camera:
            raise PolicyError(f"images: policy reads cameras {', '.join(self.cameras)}; pass {{camera: images}}")
        return self._trunk(x, WRIST_CAMERA)

    def head(self, A, state: torch.Tensor | None = None) -> torch.Tensor:
        """Feature map ``(B, C, h, w)`` (or ``{camera: map}``) and ``state (B, D)`` -> actions
        ``(B, 6)``, or ``(B, K, 6)`` for chunks; in [-1, 1] unless the output is linear."""
        if isinstance(A, dict):
            z = torch.cat([torch.flatten(self.reduce(A[n]), 1) for n in self.cameras], 1)
        else:
            if not self.config.is_one_camera:
                raise PolicyError(f"features: policy reads cameras {', '.join(self.cameras)}; pass {{camera: map}}")
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
            if self.config.output_scale:
                out = out * self.out_scale
        return out.view(-1, self.config.chunk, self.config.action_dim) if self.config.chunk > 1 else out

    def forward(self, x, state: torch.Tensor | None = None) -> torch.Tensor:
        return self.head(self.features(x), state)

    def _tensor(self, images, camera: str) -> torch.Tensor:
        if isinstance(images, torch.Tensor):
            x = images.to(self.device, torch.float32)
            return x.permute(0, 3, 1, 2) / 255.0 if images.dtype == torch.uint8 else x
        return torch.from_numpy(prepare_images(images, self.config.camera_size(camera))).to(self.device)

    @torch.no_grad()
    def act(self, images, state=None) -> np.ndarray:
        """Actions ``(B, 6)`` (or ``(B, K, 6)``) float32 for env images ``(B, S, S, 3)`` uint8 or
        ``(B, 3, S, S)`` floats, or ``{camera: images}`` (each at its camera's size), and the
        ``(B, D)`` state when the policy reads one.

        Runs in eval mode (BN running statistics) and restores the previous mode.
        """
        if isinstance(images, dict):
            missing = [n for n in self.cameras if n not in images]
            if missing:
                raise PolicyError(
                    f"images: policy reads cameras {', '.join(self.cameras)}; no images of {missing[0]!r} given"
                )
            x = {n: self._tensor(images[n], n) for n in self.cameras}
        else:
            if not self.config.is_one_camera:
                raise PolicyError(f"images: policy reads cameras {', '.join(self.cameras)}; pass {{camera: images}}")
            x = self._tensor(images, WRIST_CAMERA)
        st = None if state is None else torch.as_tensor(np.asarray(state, dtype=np.float32), device=self.device)
        was_training = self.training
        self.eval()
        try:
            return self(x, st).cpu().numpy().astype(np.float32)
        finally:
            self.train(was_training)


def file_inputs(plan: InputPlan) -> dict[str, InputBinding]:
    """The card ``inputs`` of an exported network reading ``plan``: each image input bound to its
    camera, the state input to the state (what :func:`sim.policies.contract.bind_inputs` reads back
    from an ``.onnx`` or ``.pt2`` of the built-in network on several cameras)."""
    out = {b.name: InputBinding(source="camera", camera=b.camera) for b in plan.images}
    out.update({s.name: InputBinding(source="state") for s in plan.states})
    return out


def scene_camera_px(spec, cameras) -> dict[str, tuple[int, int]]:
    """``PolicyArch.camera_px`` for reading ``cameras`` in scene ``spec``: each scene camera's
    ``(H, W)`` px as the scene renders it. A camera the scene lacks raises
    :class:`sim.spec.UnknownCameraError` in one line listing the scene's cameras."""
    out = {}
    for name in cameras:
        cam = spec.camera_spec(name)
        if name != WRIST_CAMERA:
            out[name] = (int(cam.height), int(cam.width))
    return out
