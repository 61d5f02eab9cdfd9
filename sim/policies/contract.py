"""The policy contract: what a policy reads besides the image, and what its output means.

One contract serves every consumer (clean evaluation, ``advobj eval``, the attack's validation
and its pose loss, the real-trial runner and the safety layer), so a policy behaves the same
everywhere. It travels in the policy card (checkpoint ``policy.json`` or ONNX metadata).

**State input** (optional, in ``state`` order, concatenated into one ``(B, D)`` float32 vector):

* ``tcp_pose``: 6 values, the TCP position ``[x, y, z]`` (m) and orientation as an axis-angle
  vector ``[rx, ry, rz]`` (rad), in the task's frame: the table frame (z up, origin on the table
  top), which is the sim's world frame. On the real cell the runner converts the arm's base-frame
  pose with the calibrated ``T_base_table``;
* ``gripper``: 1 value, the finger opening (m). A reach task never closes the gripper, so the
  sim and the real cell both report the scene's ``gripper.opening_m``.

**Action output**: ``K = action.chunk`` actions per call, ``(B, 6)`` when ``K = 1``, else
``(B, K, 6)`` (``(B, 6K)`` is accepted too). Of each chunk the first ``k = action.execute`` are
executed, one per control step, before the policy is asked again. Each action is

* ``delta_tcp``: a normalised motion in the current TCP frame, ``[-1, 1]^6`` scaled by the
  card's ``max_step_m`` / ``max_step_rad`` (:mod:`sim.action`);
* ``absolute_tcp``: a target pose ``[x, y, z (m), rx, ry, rz (rad)]`` in the same table frame.
  One step moves toward it by at most the scene's step limits: the motion is the ``delta_tcp``
  that reaches the target, scaled down as a whole (direction kept) until every component is within
  ``[-1, 1]``. The real runner makes the same step from the measured TCP pose and sends it through
  the safety layer, which stays the backstop.

The attack's pose loss takes the intended next TCP position and heading of the first action of
a chunk after this conversion, so it means the same thing for every action kind.

**Named inputs** (:class:`InputBinding`, the card's ``inputs``): each model input is bound to a
source: a camera by name (``wrist`` or one of the scene's ``scene_cameras``), the state vector
above (``state``), or one of its fields alone (``tcp_pose``, ``gripper``); ``joint_positions`` is
reserved for joint-space policies and refused for now. An image input states how a camera frame
becomes the tensor the model takes (:class:`ImageInput`: size, preprocess, value range, channel
order, layout, normalisation). Without bindings, LeRobot's names bind as they come
(``observation.images.<camera>`` -> camera ``<camera>``, ``observation.state`` -> ``state``;
output ``action``), and any other one- or two-input model reads the wrist camera (and the state),
as every policy before named inputs did. :func:`bind_inputs` resolves a model's inputs into an
:class:`InputPlan`; :func:`call_policy` is the one way a consumer hands a policy its views.

The functions are batch-first and accept numpy arrays or torch tensors where a gradient can be
needed (:func:`to_delta`, :func:`to_model_image`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch
from pydantic import Field, model_validator

from sim.configio import StrictModel
from sim.geometry import _is_torch, so3_exp, so3_log
from sim.policies.interface import IMAGE_SIZE_MAX_PX, IMAGE_SIZE_MIN_PX, PolicyError
from sim.spec import WRIST as WRIST_CAMERA
from sim.spec import UnknownCameraError

__all__ = [
    "StateField",
    "STATE_SIZES",
    "ActionContract",
    "PolicyContract",
    "policy_contract",
    "state_vector",
    "decode_actions",
    "first_action",
    "to_delta",
    "call_policy",
    "ActionQueue",
    "WRIST_CAMERA",
    "LEROBOT_IMAGE_PREFIX",
    "LEROBOT_STATE",
    "LEROBOT_ACTION",
    "ImageInput",
    "InputBinding",
    "BoundImage",
    "BoundState",
    "InputPlan",
    "bind_inputs",
    "to_model_image",
    "policy_cameras",
    "check_scene",
    "default_plan",
]

StateField = Literal["tcp_pose", "gripper"]
STATE_SIZES = {"tcp_pose": 6, "gripper": 1}


LEROBOT_IMAGE_PREFIX = "observation.images."
LEROBOT_STATE = "observation.state"
LEROBOT_ACTION = "action"


class ActionContract(StrictModel):
    kind: Literal["delta_tcp", "absolute_tcp"] = Field(
        "delta_tcp",
        description="delta_tcp: normalised TCP-frame motion in [-1, 1]^6; absolute_tcp: target pose [x, y, z (m), "
        "rx, ry, rz (rad)] in the table frame (the sim's world frame)",
    )
    chunk: int = Field(1, ge=1, le=128, description="K: actions the policy outputs per call")
    execute: int = Field(
        1, ge=1, le=128, description="k: actions of each chunk executed before the policy is asked again (k <= K)"
    )

    @model_validator(mode="after")
    def _k_le_K(self):
        if self.execute > self.chunk:
            raise ValueError(f"execute: {self.execute} actions cannot be executed from a chunk of {self.chunk}")
        return self


class PolicyContract(StrictModel):
    state: tuple[StateField, ...] = Field(
        (), description="proprioceptive inputs, concatenated in this order: tcp_pose (6), gripper (1)"
    )
    action: ActionContract = ActionContract()

    @model_validator(mode="after")
    def _unique(self):
        if len(set(self.state)) != len(self.state):
            raise ValueError(f"state: each input may appear once, got {list(self.state)}")
        return self

    @property
    def state_dim(self) -> int:
        return sum(STATE_SIZES[s] for s in self.state)

    @property
    def is_default(self) -> bool:
        return self == PolicyContract()

    def describe(self) -> str:
        a = self.action
        state = "+".join(self.state) if self.state else "none"
        chunk = f", chunks of {a.chunk} (execute {a.execute})" if a.chunk > 1 else ""
        return f"state {state}; {a.kind}{chunk}"


def policy_contract(policy) -> PolicyContract:
    """The contract of ``policy``: its ``contract`` attribute, else its card's, else the default
    (one image in, one ``delta_tcp`` out) that every policy before the contract had."""
    c = getattr(policy, "contract", None)
    if isinstance(c, PolicyContract):
        return c
    card = getattr(policy, "card", None)
    c = getattr(card, "contract", None)
    return c if isinstance(c, PolicyContract) else PolicyContract()


# ------------------------------------------------------------------------------- named inputs
ValueRange = Literal["0..1", "0..255", "-1..1"]
_RANGE = {"0..1": (1.0, 0.0), "0..255": (255.0, 0.0), "-1..1": (2.0, -1.0)}  # x01 * scale + offset
InputSource = Literal["camera", "state", "tcp_pose", "gripper", "joint_positions"]


class ImageInput(StrictModel):
    """How one camera's frame becomes one model input (the model's own convention).

    The frame is ``(H, W, 3)`` RGB; the model receives, per channel in ``channel_order``,
    ``(value - mean) / std`` with ``value`` in ``value_range``, laid out as ``layout``.
    """

    size: tuple[int, int] | None = Field(
        None, description="(H, W) px the model takes; None: the model input's own fixed shape"
    )
    preprocess: Literal["center_crop", "letterbox", "resize"] = Field(
        "center_crop",
        description="how a real camera's frame of another size becomes this size (sim.policyview); the sim renders "
        "each camera at its input's size",
    )
    value_range: ValueRange = Field("0..1", description="pixel values before normalisation: 0..1, 0..255 or -1..1")
    channel_order: Literal["rgb", "bgr"] = "rgb"
    layout: Literal["nchw", "nhwc"] = Field("nchw", description="(B, 3, H, W) or (B, H, W, 3)")
    mean: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="subtracted per channel (value_range units)")
    std: tuple[float, float, float] = Field((1.0, 1.0, 1.0), description="divided per channel (value_range units)")

    @model_validator(mode="after")
    def _check(self):
        if any(s <= 0 for s in self.std):
            raise ValueError(f"std: every channel's std must be positive, got {list(self.std)}")
        if self.size is not None and not all(IMAGE_SIZE_MIN_PX <= v <= IMAGE_SIZE_MAX_PX for v in self.size):
            raise ValueError(f"size: each side must be {IMAGE_SIZE_MIN_PX}..{IMAGE_SIZE_MAX_PX} px, got {self.size}")
        return self

    @property
    def is_identity(self) -> bool:
        """Whether the model takes the canonical ``(B, 3, H, W)`` RGB in [0, 1] unchanged."""
        return (self.value_range, self.channel_order, self.layout, self.mean, self.std) == (
            "0..1",
            "rgb",
            "nchw",
            (0.0, 0.0, 0.0),
            (1.0, 1.0, 1.0),
        )


class InputBinding(StrictModel):
    """What one model input reads: a camera (with its :class:`ImageInput`) or the state."""

    source: InputSource = Field(
        description="camera (name it in camera), state (the contract's state vector), tcp_pose or gripper alone; "
        "joint_positions is reserved for joint-space policies"
    )
    camera: str | None = Field(None, description="source camera: the camera's name (wrist or a scene camera)")
    image: ImageInput | None = Field(None, description="source camera: how its frame becomes the input")

    @model_validator(mode="before")
    @classmethod
    def _default_image(cls, data):
        if isinstance(data, dict) and data.get("source") == "camera" and data.get("image") is None:
            data = {**data, "image": {}}
        return data

    @model_validator(mode="after")
    def _fields(self):
        if self.source == "camera":
            if not self.camera:
                raise ValueError("camera: a camera input names its camera (wrist or one of the scene's cameras)")
        elif self.camera is not None or self.image is not None:
            raise ValueError(f"camera: a {self.source} input reads no camera; drop camera and image")
        return self


def to_model_image(x, image: ImageInput):
    """The model's tensor for canonical frames ``x: (B, 3, H, W)`` RGB in [0, 1] (numpy or torch,
    differentiable): channel order, value range, normalisation, layout as ``image`` says."""
    if image.is_identity:
        return x
    torch_in = _is_torch(x)
    if image.channel_order == "bgr":
        x = x[:, [2, 1, 0]]
    scale, offset = _RANGE[image.value_range]
    mean = np.asarray(image.mean, np.float32).reshape(1, 3, 1, 1)
    std = np.asarray(image.std, np.float32).reshape(1, 3, 1, 1)
    if torch_in:
        mean_t, std_t = torch.as_tensor(mean, device=x.device), torch.as_tensor(std, device=x.device)
        y = (x * scale + offset - mean_t) / std_t
        return y.permute(0, 2, 3, 1) if image.layout == "nhwc" else y
    y = ((np.asarray(x, np.float32) * np.float32(scale) + np.float32(offset)) - mean) / std
    return np.ascontiguousarray(y.transpose(0, 2, 3, 1) if image.layout == "nhwc" else y, dtype=np.float32)


@dataclass(frozen=True)
class BoundImage:
    """A model input reading camera ``camera`` at ``size = (H, W)`` px, converted as ``image`` says."""

    name: str
    camera: str
    size: tuple[int, int]
    image: ImageInput


@dataclass(frozen=True)
class BoundState:
    """A model input reading ``fields`` of the state vector (``(B, len)``, ``slice`` of it)."""

    name: str
    source: str
    slice: tuple[int, int]


@dataclass(frozen=True)
class InputPlan:
    """A model's inputs, each bound (:func:`bind_inputs`), in the model's input order, and its action output."""

    images: tuple[BoundImage, ...]
    states: tuple[BoundState, ...] = ()
    output: str = ""
    order: tuple[str, ...] = field(default=())

    @property
    def cameras(self) -> tuple[str, ...]:
        """The cameras the model reads, in input order (each once)."""
        return tuple(dict.fromkeys(b.camera for b in self.images))

    def image_for(self, camera: str) -> BoundImage:
        return next(b for b in self.images if b.camera == camera)

    def feeds(self, views: dict, state, where: str = "") -> dict:
        """``{input name: array}`` for canonical ``views`` ``{camera: (B, 3, H, W)}`` and the
        ``(B, D)`` state (numpy or torch, as given)."""
        out = {}
        for b in self.images:
            out[b.name] = to_model_image(views[b.camera], b.image)
        for s in self.states:
            if state is None:
                raise PolicyError(f"{where}state: input {s.name!r} reads {s.source}; no state given")
            out[s.name] = state[:, s.slice[0] : s.slice[1]]
        return out


def _camera_of_name(name: str) -> str | None:
    if name.startswith(LEROBOT_IMAGE_PREFIX) and len(name) > len(LEROBOT_IMAGE_PREFIX):
        return name[len(LEROBOT_IMAGE_PREFIX) :]
    return None


def _image_shape(shape, image: ImageInput, where: str, name: str) -> tuple[int, int]:
    """``(H, W)`` of an image input of model shape ``shape`` laid out as ``image.layout``."""
    shape = tuple(shape)
    want = "(B, 3, H, W)" if image.layout == "nchw" else "(B, H, W, 3)"
    ok = len(shape) == 4 and (shape[1] if image.layout == "nchw" else shape[3]) == 3
    hw = (shape[2], shape[3]) if image.layout == "nchw" else (shape[1], shape[2])
    if not ok or not all(isinstance(v, int) for v in hw):
        raise PolicyError(f"{where}input {name!r} must be {want} with a fixed H and W ({image.layout}), got {shape}")
    if not all(IMAGE_SIZE_MIN_PX <= v <= IMAGE_SIZE_MAX_PX for v in hw):
        raise PolicyError(
            f"{where}input {name!r} takes {hw[0]}x{hw[1]} px images; advobj renders "
            f"{IMAGE_SIZE_MIN_PX}..{IMAGE_SIZE_MAX_PX} px"
        )
    if image.size is not None and tuple(image.size) != hw:
        raise PolicyError(
            f"{where}card inputs.{name}.image.size is {image.size[0]}x{image.size[1]} px but the model takes "
            f"{hw[0]}x{hw[1]} px"
        )
    return int(hw[0]), int(hw[1])


def bind_inputs(
    bindings: dict[str, InputBinding] | None,
    model_inputs: list[tuple[str, tuple]],
    model_outputs: list[str],
    contract: PolicyContract,
    action_output: str | None = None,
    where: str = "",
) -> InputPlan:
    """Bind every model input (``(name, shape)`` in the model's order) to its source.

    ``bindings`` is the card's ``inputs`` (None or empty: LeRobot's names as they come, else the
    first input is the wrist camera and a second one the state). Raises :class:`PolicyError` in
    one line for a binding of an input the model lacks, a model input left unbound, an image input
    of the wrong shape, ``joint_positions``, or state inputs that disagree with ``contract.state``.
    ``where`` prefixes messages (e.g. ``"policy.onnx: "``).
    """
    names = [n for n, _ in model_inputs]
    shapes = dict(model_inputs)
    if bindings:
        for name in bindings:
            if name not in shapes:
                raise PolicyError(
                    f"{where}card inputs: {name!r} is not an input of the model (its inputs: {', '.join(names)})"
                )
        for name in names:
            if name not in bindings:
                raise PolicyError(
                    f"{where}input {name!r} of the model is not bound by the card's inputs; bind it to a camera, "
                    "state, tcp_pose or gripper"
                )
        bound = dict(bindings)
    elif any(_camera_of_name(n) or n == LEROBOT_STATE for n in names):
        bound = {}
        for n in names:
            cam = _camera_of_name(n)
            if cam is not None:
                bound[n] = InputBinding(source="camera", camera=cam)
            elif n == LEROBOT_STATE:
                bound[n] = InputBinding(source="state")
            else:
                raise PolicyError(
                    f"{where}input {n!r} is not one of LeRobot's (observation.images.<camera>, observation.state) "
                    "and no card binds it; write the card's inputs"
                )
    else:
        if len(names) not in (1, 2):
            raise PolicyError(
                f"{where}a policy without the card's inputs takes an image (and optionally a state); the model has "
                f"{len(names)} inputs ({', '.join(names)}): bind each in the card's inputs"
            )
        bound = {names[0]: InputBinding(source="camera", camera=WRIST_CAMERA)}
        if len(names) == 2:
            if not contract.state:
                raise PolicyError(
                    f"{where}the graph has a second input {names[1]!r} but no card says what it holds; write a card "
                    "with contract.state (sim.policies.onnx_policy.attach_card writes one into a file)"
                )
            bound[names[1]] = InputBinding(source="state")

    images, states = [], []
    offsets, o = {}, 0
    for s in contract.state:
        offsets[s] = (o, o + STATE_SIZES[s])
        o += STATE_SIZES[s]
    read: list[str] = []
    for name in names:
        b = bound[name]
        if b.source == "joint_positions":
            raise PolicyError(
                f"{where}input {name!r}: source joint_positions is reserved for joint-space policies and not "
                "supported yet"
            )
        if b.source == "camera":
            size = _image_shape(shapes[name], b.image, where, name)
            if any(im.camera == b.camera for im in images):
                raise PolicyError(f"{where}card inputs: camera {b.camera!r} is bound to two inputs")
            images.append(BoundImage(name, b.camera, size, b.image))
            continue
        if b.source == "state":
            if not contract.state:
                raise PolicyError(
                    f"{where}input {name!r} reads the state but the card's contract.state is empty; list its fields"
                )
            sl, fields = (0, o), list(contract.state)
        else:
            if b.source not in contract.state:
                raise PolicyError(
                    f"{where}input {name!r} reads {b.source} but the card's contract.state {list(contract.state)} "
                    f"does not list it"
                )
            sl, fields = offsets[b.source], [b.source]
        shape = tuple(shapes[name])
        width = sl[1] - sl[0]
        if len(shape) != 2 or (isinstance(shape[1], int) and shape[1] != width):
            raise PolicyError(f"{where}input {name!r} must be (B, {width}) for {'+'.join(fields)}, got {shape}")
        read += fields
        states.append(BoundState(name, b.source, sl))
    if not images:
        raise PolicyError(f"{where}no model input reads a camera; bind one to a camera in the card's inputs")
    if contract.state and not states:
        raise PolicyError(
            f"{where}the card's contract reads state {list(contract.state)} but the model has no state input"
        )
    if contract.state and sorted(read) != sorted(contract.state):
        raise PolicyError(
            f"{where}the card's contract reads state {list(contract.state)} but the model's inputs read "
            f"{sorted(read) or 'none'}; bind each state field once"
        )
    if action_output is not None:
        if action_output not in model_outputs:
            raise PolicyError(
                f"{where}card action_output: {action_output!r} is not an output of the model (its outputs: "
                f"{', '.join(model_outputs)})"
            )
        output = action_output
    else:
        output = LEROBOT_ACTION if LEROBOT_ACTION in model_outputs else model_outputs[0]
    return InputPlan(tuple(images), tuple(states), output, tuple(names))


def default_plan(
    image_size: int, contract: PolicyContract, cameras: dict[str, tuple[int, int]] | None = None
) -> InputPlan:
    """The plan of a built-in network: the wrist camera at ``image_size`` (input ``images``) and the
    state (input ``state``); with ``cameras`` (``{camera: (H, W) px}`` in input order, as
    :class:`sim.policies.policy.PolicyArch` lists them), one image input per camera, named by the
    camera, then ``state``."""
    states = (BoundState("state", "state", (0, contract.state_dim)),) if contract.state else ()
    if cameras is None:
        return InputPlan(
            (BoundImage("images", WRIST_CAMERA, (int(image_size), int(image_size)), ImageInput()),), states, "actions"
        )
    images = tuple(BoundImage(name, name, (int(h), int(w)), ImageInput()) for name, (h, w) in cameras.items())
    return InputPlan(images, states, "actions", (*cameras, *(s.name for s in states)))


def policy_cameras(policy) -> tuple[str, ...]:
    """The cameras ``policy`` reads, in its input order: its ``inputs`` plan's, else the wrist camera."""
    plan = getattr(policy, "inputs", None)
    return plan.cameras if isinstance(plan, InputPlan) else (WRIST_CAMERA,)


def check_scene(policy, spec) -> None:
    """Refuse, in one line, a policy reading a camera ``spec`` does not have, or a scene camera
    rendering another size than its input takes (the wrist camera renders at the policy's size).
    The line names the policy's file when it has one (``.onnx``: ``path``, ``.pt2``: ``source``)."""
    plan = getattr(policy, "inputs", None)
    if not isinstance(plan, InputPlan):
        return
    src = getattr(policy, "source", None) or getattr(policy, "path", None)
    where = f"{src}: " if src else ""
    for b in plan.images:
        try:
            cam = spec.camera_spec(b.camera)  # an unknown name: one line listing the scene's cameras
        except UnknownCameraError as err:
            raise UnknownCameraError(f"{where}input {b.name!r}: {err}") from None
        if b.camera == WRIST_CAMERA:
            if b.size[0] != b.size[1]:
                raise PolicyError(
                    f"{where}input {b.name!r}: the wrist camera renders square images; the model takes "
                    f"{b.size[0]}x{b.size[1]}"
                )
            continue
        if (cam.height, cam.width) != tuple(b.size):
            raise PolicyError(
                f"{where}input {b.name!r}: camera {b.camera!r} renders {cam.height}x{cam.width} px but the model takes "
                f"{b.size[0]}x{b.size[1]} px; give the scene camera that size"
            )


def state_vector(contract: PolicyContract, T_base_tcp, gripper_m) -> np.ndarray | None:
    """``(B, D)`` float32 state for TCP poses ``(B, 4, 4)`` and openings ``gripper_m`` (scalar or
    ``(B,)``, m); ``None`` when the contract reads no state."""
    if not contract.state:
        return None
    T = np.asarray(T_base_tcp, dtype=np.float64).reshape(-1, 4, 4)
    parts = []
    for s in contract.state:
        if s == "tcp_pose":
            parts.append(np.concatenate([T[:, :3, 3], so3_log(T[:, :3, :3])], -1))
        else:
            parts.append(np.broadcast_to(np.asarray(gripper_m, dtype=np.float64).reshape(-1, 1), (len(T), 1)))
    return np.ascontiguousarray(np.concatenate(parts, -1), dtype=np.float32)


def decode_actions(raw, contract: PolicyContract, batch: int):
    """``(B, K, 6)`` from a policy output of ``(B, 6)`` (K = 1), ``(B, K, 6)`` or ``(B, 6K)``.

    Raises :class:`PolicyError` naming the expected shape. Values are not checked here: a
    non-finite action is the consumer's to refuse (the env raises, the runner logs it).
    """
    K = contract.action.chunk
    shape = tuple(raw.shape)
    if shape == (batch, K, 6):
        return raw
    if shape == (batch, 6 * K):
        return raw.reshape(batch, K, 6)
    want = f"({batch}, 6)" if K == 1 else f"({batch}, {K}, 6) or ({batch}, {6 * K})"
    raise PolicyError(
        f"actions: the policy's contract ({contract.describe()}) needs outputs of shape {want}, got {shape}"
    )


def first_action(actions):
    """The action executed next: ``(B, 6)`` of a ``(B, 6)`` or ``(B, K, 6)`` output."""
    return actions[:, 0] if actions.ndim == 3 else actions


def _rot_log(R):
    if not _is_torch(R):
        return so3_log(R)

    # Differentiable log map for the loss: atan2 form with floored norms (finite gradients at 0);
    # near pi the axis is less accurate than the numpy path, which the execution uses.
    vee = 0.5 * torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    cos = ((R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0) / 2.0).clamp(-1.0, 1.0)
    sin = torch.sqrt((vee * vee).sum(-1).clamp_min(1e-12))
    theta = torch.atan2(sin, cos)
    return vee * (theta / sin)[..., None]


def to_delta(T_base_tcp, actions, kind: str, max_step_m: float, max_step_rad: float):
    """Normalised ``delta_tcp`` motions ``(B, 6)`` in [-1, 1] for actions ``(B, 6)`` of ``kind``.

    ``delta_tcp`` is clipped; ``absolute_tcp`` becomes the motion toward the target, scaled down as
    a whole until every component fits (see the module docstring). numpy or torch.
    """
    if kind == "delta_tcp":
        return actions.clamp(-1.0, 1.0) if _is_torch(actions) else np.clip(actions, -1.0, 1.0)
    T = T_base_tcp.to(actions.dtype) if _is_torch(actions) else np.asarray(T_base_tcp, dtype=np.float64)
    R, p = T[..., :3, :3], T[..., :3, 3]
    Rt = R.transpose(-1, -2) if _is_torch(actions) else np.swapaxes(R, -1, -2)
    dp = (Rt @ (actions[..., :3] - p)[..., None])[..., 0] / max_step_m
    drot = _rot_log(Rt @ so3_exp(actions[..., 3:])) / max_step_rad
    if _is_torch(actions):
        a = torch.cat([dp, drot], -1)
        scale = a.abs().amax(-1, keepdim=True).clamp_min(1.0)
        return a / scale
    a = np.concatenate([dp, drot], -1)
    return a / np.maximum(np.abs(a).max(-1, keepdims=True), 1.0)


def call_policy(policy, images, state):
    """``policy.act(images[, state])``: the one way a consumer hands a policy its views.

    ``images`` is one camera's frames (``(B, H, W, 3)`` uint8, or canonical ``(B, 3, H, W)`` float
    in [0, 1]) for a policy reading one camera, or ``{camera: frames}`` holding at least every camera
    the policy reads (:func:`policy_cameras`). A policy reading one camera is handed that camera's
    array, so plain one-input policies need neither a dict nor a ``state`` parameter; a policy
    reading several is handed ``{camera: frames}`` in its input order.
    """
    cams = policy_cameras(policy)
    if isinstance(images, dict):
        missing = [c for c in cams if c not in images]
        if missing:
            raise PolicyError(
                f"images: the policy reads cameras {', '.join(cams)}; no images of {missing[0]!r} (given: "
                f"{', '.join(images) or 'none'})"
            )
        images = images[cams[0]] if len(cams) == 1 else {c: images[c] for c in cams}
    elif len(cams) > 1:
        raise PolicyError(f"images: the policy reads cameras {', '.join(cams)}; pass {{camera: images}} for each")
    return policy.act(images) if state is None else policy.act(images, state)


class ActionQueue:
    """Per-slot chunks of actions waiting to be executed: the one implementation of ``k of K``.

    ``needs(slots)`` says which slots must ask the policy; ``push`` stores a decoded chunk's first
    ``k`` actions; ``pop`` takes the next action of each slot; ``clear`` drops a slot's queue (a
    new episode must not finish the previous episode's chunk).
    """

    def __init__(self, contract: PolicyContract, num_slots: int):
        self.contract = contract
        self._q: list[list[np.ndarray]] = [[] for _ in range(int(num_slots))]

    def needs(self, slots) -> list[int]:
        return [int(i) for i in slots if not self._q[int(i)]]

    def push(self, slots, chunks: np.ndarray) -> None:
        k = self.contract.action.execute
        for i, c in zip(slots, np.asarray(chunks, dtype=np.float64)):
            self._q[int(i)] = list(c[:k])

    def pop(self, slots) -> np.ndarray:
        out = [self._q[int(i)].pop(0) for i in slots]
        return np.stack(out) if out else np.zeros((0, 6))

    def clear(self, slot: int) -> None:
        self._q[int(slot)] = []
