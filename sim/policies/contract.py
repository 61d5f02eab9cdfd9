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
  sim and the real cell both report the scene's ``gripper.opening_m``;
* ``joint_positions``: one value per joint in ``joints`` order, each in its ``joint_units`` entry
  (rad for a revolute joint, m for a prismatic one). Read by joint-space policies only.

**Joints** (joint-space policies: a ``joint_position`` or ``joint_delta`` action): ``joints`` names
the arm's actuated joints in the order of ``joint_positions`` and of every joint action, and
``joint_units`` each one's unit. Both must be those of the scene's arm (:class:`sim.spec.ArmModelConfig`:
the URDF's chain from base link to tool link, base to tool), checked by :func:`check_scene`; a joint
policy needs a scene with an arm.

**Action output**: ``K = action.chunk`` actions per call, ``(B, 6)`` when ``K = 1``, else
``(B, K, 6)`` (``(B, 6K)`` is accepted too). Of each chunk the first ``k = action.execute`` are
executed, one per control step, before the policy is asked again. Each action is

* ``delta_tcp``: a normalised motion in the current TCP frame, ``[-1, 1]^6`` scaled by the
  card's ``max_step_m`` / ``max_step_rad`` (:mod:`sim.action`);
* ``absolute_tcp``: a target pose ``[x, y, z (m), rx, ry, rz (rad)]`` in the same table frame.
  One step moves toward it by at most the scene's step limits: the motion is the ``delta_tcp``
  that reaches the target, scaled down as a whole (direction kept) until every component is within
  ``[-1, 1]``. The real runner makes the same step from the measured TCP pose and sends it through
  the safety layer, which stays the backstop;
* ``joint_position``: target joint positions, ``n`` values in ``joints`` order and units;
* ``joint_delta``: a change of the joint positions, ``q_target = q + a`` (same order and units).
  A joint action is ``(B, n)`` (``(B, K, n)`` or ``(B, n K)`` in chunks). The arm then moves toward
  the target by :meth:`sim.ik.SceneArm.limit_step`: the target clipped to the joint position limits,
  the motion scaled down as a whole until no joint exceeds its URDF velocity limit over the scene's
  ``arm.control_period_s``; the TCP and the wrist camera follow by forward kinematics.

The attack's pose loss takes the intended next TCP position and heading of the first action of
a chunk after this conversion (:func:`to_delta`; a joint action's through the arm's forward
kinematics, differentiably), so it means the same thing for every action kind.

**Named inputs** (:class:`InputBinding`, the card's ``inputs``): each model input is bound to a
source: a camera by name (``wrist`` or one of the scene's ``scene_cameras``), the state vector
above (``state``), or one of its fields alone (``tcp_pose``, ``gripper``, ``joint_positions``). An
image input states how a camera frame
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

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal, get_args

import numpy as np
import torch
from pydantic import Field, model_serializer, model_validator

from sim.configio import StrictModel
from sim.geometry import _is_torch, so3_exp, so3_log
from sim.policies.interface import IMAGE_SIZE_MAX_PX, IMAGE_SIZE_MIN_PX, PolicyError
from sim.spec import WRIST as WRIST_CAMERA
from sim.spec import UnknownCameraError

__all__ = [
    "StateField",
    "STATE_SIZES",
    "TCP_ACTIONS",
    "JOINT_ACTIONS",
    "JOINT_UNITS",
    "ActionContract",
    "PolicyContract",
    "policy_contract",
    "state_vector",
    "decode_actions",
    "first_action",
    "to_delta",
    "to_joint_target",
    "from_joint_target",
    "check_joints",
    "joint_mismatch",
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

StateField = Literal["tcp_pose", "gripper", "joint_positions"]
#: Values per state field; ``joint_positions`` has one per joint of the contract (``len(joints)``).
STATE_SIZES = {"tcp_pose": 6, "gripper": 1}
TCP_ACTIONS = ("delta_tcp", "absolute_tcp")
JOINT_ACTIONS = ("joint_position", "joint_delta")
#: The unit a joint's position is stated in (velocities: per second), as sim.kinematics.JOINT_UNITS
#: says; ``contract.joint_units`` accepts these only (an unknown unit is refused naming its entry).
JointUnit = Literal["rad", "m"]
JOINT_UNITS = get_args(JointUnit)


LEROBOT_IMAGE_PREFIX = "observation.images."
LEROBOT_STATE = "observation.state"
LEROBOT_ACTION = "action"


class ActionContract(StrictModel):
    kind: Literal["delta_tcp", "absolute_tcp", "joint_position", "joint_delta"] = Field(
        "delta_tcp",
        description="delta_tcp: normalised TCP-frame motion in [-1, 1]^6; absolute_tcp: target pose [x, y, z (m), "
        "rx, ry, rz (rad)] in the table frame (the sim's world frame); joint_position: target joint positions, "
        "joint_delta: their change (both in the contract's joints order and joint_units)",
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
        (),
        description="proprioceptive inputs, concatenated in this order: tcp_pose (6), gripper (1), joint_positions "
        "(one per joint)",
    )
    action: ActionContract = ActionContract()
    joints: tuple[str, ...] = Field(
        (),
        description="joint-space policies: the arm's joints (URDF names, base to tool) in the order of "
        "joint_positions and of each joint action; must be the scene arm's chain in its order",
    )
    joint_units: tuple[JointUnit, ...] = Field(
        (), description="joint-space policies: each joint's position unit, rad (revolute) or m (prismatic)"
    )

    @model_validator(mode="after")
    def _unique(self):
        if len(set(self.state)) != len(self.state):
            raise ValueError(f"state: each input may appear once, got {list(self.state)}")
        joint_action = self.action.kind in JOINT_ACTIONS
        if "joint_positions" in self.state and not joint_action:
            raise ValueError(
                f"state: joint_positions is read by joint-space policies (action joint_position or joint_delta); "
                f"this one's action is {self.action.kind}"
            )
        if joint_action and not self.joints:
            raise ValueError(
                f"joints: a {self.action.kind} policy names the arm's joints in the order of its actions (and units "
                "in joint_units)"
            )
        if self.joints and not joint_action:
            raise ValueError(
                f"joints: a {self.action.kind} policy commands no joints; leave out joints and joint_units"
            )
        if len(set(self.joints)) != len(self.joints):
            raise ValueError(f"joints: each joint may appear once, got {list(self.joints)}")
        if len(self.joint_units) != len(self.joints):
            raise ValueError(
                f"joint_units: one unit per joint: {len(self.joints)} joints, {len(self.joint_units)} units"
            )
        return self

    @model_serializer(mode="wrap")
    def _dump(self, handler):
        # A TCP contract dumps as before joints existed: cards, run records and hashes unchanged.
        d = handler(self)
        if isinstance(d, dict) and not self.joints:
            d.pop("joints", None)
            d.pop("joint_units", None)
        return d

    def state_size(self, field: str) -> int:
        """Values of state field ``field`` (``joint_positions``: one per joint)."""
        return len(self.joints) if field == "joint_positions" else STATE_SIZES[field]

    @property
    def state_dim(self) -> int:
        return sum(self.state_size(s) for s in self.state)

    @property
    def is_joint_space(self) -> bool:
        """Whether the policy commands the arm's joints (``joint_position`` or ``joint_delta``)."""
        return self.action.kind in JOINT_ACTIONS

    @property
    def control(self) -> str:
        """What the policy moves: ``"joint"`` (the arm's joints) or ``"tcp"`` (``ReachEnv(control=...)``)."""
        return "joint" if self.is_joint_space else "tcp"

    @property
    def action_dim(self) -> int:
        """Values per action: 6 for a TCP action, one per joint for a joint action."""
        return len(self.joints) if self.is_joint_space else 6

    @property
    def is_default(self) -> bool:
        return self == PolicyContract()

    def describe(self) -> str:
        a = self.action
        state = "+".join(self.state) if self.state else "none"
        chunk = f", chunks of {a.chunk} (execute {a.execute})" if a.chunk > 1 else ""
        joints = f" over {len(self.joints)} joints" if self.joints else ""
        return f"state {state}; {a.kind}{joints}{chunk}"


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
        description="camera (name it in camera), state (the contract's state vector), tcp_pose, gripper or "
        "joint_positions alone"
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
    of the wrong shape, or state inputs that disagree with ``contract.state``.
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
                    "state, tcp_pose, gripper or joint_positions"
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
        offsets[s] = (o, o + contract.state_size(s))
        o += contract.state_size(s)
    read: list[str] = []
    for name in names:
        b = bound[name]
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


def joint_mismatch(
    contract: PolicyContract, names: Sequence[str], units: Sequence[str], chain: str, urdf: str
) -> str | None:
    """Why a joint-space ``contract`` cannot drive an arm whose actuated joints are ``names`` (the
    URDF chain's order, base link to tool link), each in its ``units`` entry (``"rad"`` or ``"m"``):
    one line naming the card field (``contract.joints`` or ``contract.joint_units.<k>``), or ``None``
    when it can. A TCP contract needs no joints: ``None``.

    ``chain`` names the arm's chain in the line (``"the arm's chain panda_link0 -> panda_hand in
    panda.urdf"``) and ``urdf`` the file its joints' kinds come from. The one comparison behind
    :func:`check_joints` (a scene's arm) and ``trials.real.runner.check_joint_arm`` (a real arm's).
    """
    if not contract.is_joint_space:
        return None
    names, units, got = tuple(names), tuple(units), tuple(contract.joints)
    if got != names:
        unknown = [j for j in got if j not in names]
        if unknown:
            why = f"joint {unknown[0]!r} is not in {chain}"
        elif len(got) != len(names):
            why = f"{len(got)} joints for the {len(names)} of {chain}"
        else:
            k = next(i for i, (a, b) in enumerate(zip(got, names)) if a != b)
            why = f"position {k} is {got[k]!r} where {chain} has {names[k]!r} (the order is base to tool)"
        return f"contract.joints: {why}; the arm's joints: {', '.join(names)}"
    for k, (u, want) in enumerate(zip(contract.joint_units, units)):
        if u != want:
            kind = "revolute" if want == "rad" else "prismatic"
            return f"contract.joint_units.{k}: joint {names[k]!r} is {kind} in {urdf}, so its unit is {want}, not {u}"
    return None


def check_joints(contract: PolicyContract, spec, where: str = "") -> None:
    """Refuse, in one line naming the card field, a joint-space ``contract`` that ``spec``'s arm
    cannot run: a scene without an arm, joints that are not the arm's chain in its order (the URDF's
    actuated joints from base link to tool link), or a unit that is not its joint's
    (:func:`joint_mismatch`). A TCP contract passes (it runs in every scene)."""
    if not contract.is_joint_space:
        return
    if spec.arm is None:
        raise PolicyError(
            f"{where}contract: a joint-space policy ({contract.describe()}) needs a scene with an arm (arm: urdf, "
            f"base_link, tool_link); scene {spec.name!r} has none"
        )
    from sim.kinematics import read_chain, urdf_source  # lazy: robot_io start-up (torch)

    arm = spec.arm
    chain = read_chain(urdf_source(arm.urdf), arm.base_link, arm.tool_link)
    where_chain = f"the arm's chain {arm.base_link} -> {arm.tool_link} in {chain.urdf.name}"
    why = joint_mismatch(contract, chain.joint_names, chain.units, where_chain, chain.urdf.name)
    if why is not None:
        raise PolicyError(f"{where}{why}")


def check_scene(policy, spec) -> None:
    """Refuse, in one line, a policy reading a camera ``spec`` does not have, or a scene camera
    rendering another size than its input takes (the wrist camera renders at the policy's size),
    or a joint-space policy ``spec``'s arm cannot run (:func:`check_joints`).
    The line names the policy's file when it has one (``.onnx``: ``path``, ``.pt2``: ``source``)."""
    src = getattr(policy, "source", None) or getattr(policy, "path", None)
    where = f"{src}: " if src else ""
    check_joints(policy_contract(policy), spec, where)
    plan = getattr(policy, "inputs", None)
    if not isinstance(plan, InputPlan):
        return
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


def state_vector(contract: PolicyContract, T_base_tcp, gripper_m, q=None) -> np.ndarray | None:
    """``(B, D)`` float32 state for TCP poses ``(B, 4, 4)``, openings ``gripper_m`` (scalar or
    ``(B,)``, m) and, for a contract reading ``joint_positions``, the joint positions ``q (B, n)`` in
    the contract's joint order and units; ``None`` when the contract reads no state."""
    if not contract.state:
        return None
    T = np.asarray(T_base_tcp, dtype=np.float64).reshape(-1, 4, 4)
    parts = []
    for s in contract.state:
        if s == "tcp_pose":
            parts.append(np.concatenate([T[:, :3, 3], so3_log(T[:, :3, :3])], -1))
        elif s == "joint_positions":
            n = len(contract.joints)
            if q is None:
                raise PolicyError(
                    "state: the policy reads joint_positions; no joint positions given (a joint-space policy runs "
                    "on the scene's arm: ReachEnv(control='joint'))"
                )
            qa = np.asarray(q, dtype=np.float64)
            if qa.shape != (len(T), n):
                raise PolicyError(
                    f"state: joint_positions must be ({len(T)}, {n}) for joints {', '.join(contract.joints)}, "
                    f"got {qa.shape}"
                )
            parts.append(qa)
        else:
            parts.append(np.broadcast_to(np.asarray(gripper_m, dtype=np.float64).reshape(-1, 1), (len(T), 1)))
    return np.ascontiguousarray(np.concatenate(parts, -1), dtype=np.float32)


def decode_actions(raw, contract: PolicyContract, batch: int):
    """``(B, K, A)`` from a policy output of ``(B, A)`` (K = 1), ``(B, K, A)`` or ``(B, A K)``, with
    ``A = contract.action_dim`` (6 for a TCP action, one per joint for a joint action).

    Raises :class:`PolicyError` naming the expected shape. Values are not checked here: a
    non-finite action is the consumer's to refuse (the env raises, the runner logs it).
    """
    K, A = contract.action.chunk, contract.action_dim
    shape = tuple(raw.shape)
    if shape == (batch, K, A):
        return raw
    if shape == (batch, A * K):
        return raw.reshape(batch, K, A)
    want = f"({batch}, {A})" if K == 1 else f"({batch}, {K}, {A}) or ({batch}, {A * K})"
    raise PolicyError(
        f"actions: the policy's contract ({contract.describe()}) needs outputs of shape {want}, got {shape}"
    )


def first_action(actions):
    """The action executed next: ``(B, A)`` of a ``(B, A)`` or ``(B, K, A)`` output."""
    return actions[:, 0] if actions.ndim == 3 else actions


def _rot_log(R):
    # numpy: the execution's log map; torch: the differentiable one of the loss (sim.ik.rotvec)
    if not _is_torch(R):
        return so3_log(R)
    from sim.ik import rotvec  # lazy: robot_io start-up (torch)

    return rotvec(R)


def _motion(T, p_target, R_target, max_step_m: float, max_step_rad: float):
    """The normalised ``delta_tcp`` (unclipped) that moves TCP poses ``T (B, 4, 4)`` to positions
    ``p_target (B, 3)`` and orientations ``R_target (B, 3, 3)``: the inverse of :func:`sim.action.next_tcp_pose`."""
    R, p = T[..., :3, :3], T[..., :3, 3]
    Rt = R.transpose(-1, -2) if _is_torch(T) else np.swapaxes(R, -1, -2)
    dp = (Rt @ (p_target - p)[..., None])[..., 0] / max_step_m
    drot = _rot_log(Rt @ R_target) / max_step_rad
    return torch.cat([dp, drot], -1) if _is_torch(T) else np.concatenate([dp, drot], -1)


def to_joint_target(q, actions, kind: str):
    """Commanded joint positions ``(B, n)`` of joint actions ``(B, n)`` of ``kind`` at joint positions
    ``q (B, n)``: ``joint_position`` is the target itself, ``joint_delta`` ``q + a``. The arm then
    moves toward it within its limits (:meth:`sim.ik.SceneArm.limit_step`). numpy or torch."""
    if kind == "joint_position":
        return actions
    if kind == "joint_delta":
        return q + actions
    raise PolicyError(f"action: {kind} is not a joint action ({', '.join(JOINT_ACTIONS)})")


def from_joint_target(q, q_target, kind: str):
    """The joint action of ``kind`` that commands ``q_target (B, n)`` at ``q (B, n)``: the inverse of
    :func:`to_joint_target` (how the expert's joint targets become training labels)."""
    if kind == "joint_position":
        return q_target
    if kind == "joint_delta":
        return q_target - q
    raise PolicyError(f"action: {kind} is not a joint action ({', '.join(JOINT_ACTIONS)})")


def to_delta(T_base_tcp, actions, kind: str, max_step_m: float, max_step_rad: float, *, q=None, arm=None):
    """Normalised ``delta_tcp`` motions ``(B, 6)`` for actions ``(B, A)`` of ``kind``: the motion the
    env executes next, as the pose loss reads it.

    ``delta_tcp`` is clipped to [-1, 1]; ``absolute_tcp`` becomes the motion toward the target,
    scaled down as a whole until every component fits (see the module docstring). A joint action
    (``joint_position``, ``joint_delta``) needs the joint positions ``q (B, n)`` and the scene's arm
    (:class:`sim.ik.SceneArm`): the joints move by :meth:`~sim.ik.SceneArm.limit_step`, the TCP
    follows by forward kinematics, and the motion to that TCP pose is returned unclipped (it can
    exceed 1: a joint step is bounded by the velocity limits, not by the TCP step limits), so
    ``sim.action.intended_position`` and ``intended_heading`` of it are the FK pose. Differentiable
    in ``actions`` through the FK (torch); numpy in, numpy out.
    """
    if kind == "delta_tcp":
        return actions.clamp(-1.0, 1.0) if _is_torch(actions) else np.clip(actions, -1.0, 1.0)
    if kind in JOINT_ACTIONS:
        if q is None or arm is None:
            raise PolicyError(
                f"action: a {kind} action moves the arm's joints; its motion needs the joint positions and the "
                "scene's arm (q=, arm=)"
            )
        if not _is_torch(actions):
            a = torch.as_tensor(np.asarray(actions, dtype=np.float64), device=arm.device)
            qt = torch.as_tensor(np.asarray(q, dtype=np.float64), device=arm.device)
            T = torch.as_tensor(np.asarray(T_base_tcp, dtype=np.float64), device=arm.device)
            return to_delta(T, a, kind, max_step_m, max_step_rad, q=qt, arm=arm).cpu().numpy()
        qt = q.to(actions.dtype)
        T_next = arm.tcp_pose(arm.limit_step(qt, to_joint_target(qt, actions, kind)))
        return _motion(T_base_tcp.to(actions.dtype), T_next[..., :3, 3], T_next[..., :3, :3], max_step_m, max_step_rad)
    T = T_base_tcp.to(actions.dtype) if _is_torch(actions) else np.asarray(T_base_tcp, dtype=np.float64)
    a = _motion(T, actions[..., :3], so3_exp(actions[..., 3:]), max_step_m, max_step_rad)
    if _is_torch(actions):
        scale = a.abs().amax(-1, keepdim=True).clamp_min(1.0)
        return a / scale
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
        return np.stack(out) if out else np.zeros((0, self.contract.action_dim))

    def clear(self, slot: int) -> None:
        self._q[int(slot)] = []
