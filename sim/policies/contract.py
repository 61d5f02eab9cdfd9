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

The functions are batch-first and accept numpy arrays or torch tensors where a gradient can be
needed (:func:`to_delta`).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import torch
from pydantic import Field, model_validator

from sim.configio import StrictModel
from sim.geometry import _is_torch, so3_exp, so3_log
from sim.policies.interface import PolicyError

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
]

StateField = Literal["tcp_pose", "gripper"]
STATE_SIZES = {"tcp_pose": 6, "gripper": 1}


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
    """``policy.act(images, state)`` when the contract reads state, else ``policy.act(images)``
    (so plain one-input policies need no ``state`` parameter)."""
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
