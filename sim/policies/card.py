"""The policy card (``policy.json``): what a policy is, reads and outputs, and where it came from.

This module owns the card's format; a checkpoint directory (:mod:`sim.policies.checkpoint`) holds
one beside its weights, an ONNX file carries one in its metadata (:mod:`sim.policies.onnx_policy`)
and a ``.pt2`` ExportedProgram in its archive (:mod:`sim.policies.pt2`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal

from pydantic import ConfigDict, Field, ValidationError, model_serializer

from sim.configio import StrictModel
from sim.policies.contract import InputBinding, PolicyContract
from sim.policies.interface import PolicyError
from sim.policies.policy import PolicyArch

__all__ = ["CARD_NAME", "CARD_FORMAT", "ActionScaling", "CleanSuccess", "PolicyCard", "load_card"]

CARD_NAME = "policy.json"
CARD_FORMAT = "advobj-policy/1"


class _Strict(StrictModel):
    model_config = ConfigDict(frozen=False)  # cards are completed (hash, time) after validation


class ActionScaling(_Strict):
    """How a network output in [-1, 1] becomes a motion (see :mod:`sim.action`)."""

    max_step_m: float = Field(gt=0, description="translation per step at |a| = 1, m")
    max_step_rad: float = Field(gt=0, description="rotation per step at |a| = 1, rad")
    frame: str = "tcp"


class CleanSuccess(_Strict):
    """Clean success rate over ``n`` episodes with its Wilson interval."""

    k: int = Field(ge=0)
    n: int = Field(ge=0)
    rate: float | None
    lo: float
    hi: float
    confidence: float
    episodes_seed: int
    image_size: int


class PolicyCard(_Strict):
    format: str = CARD_FORMAT
    arch: PolicyArch = Field(
        default_factory=PolicyArch,
        description="the built-in network (checkpoints); a policy file's card may leave it out (its graph is the "
        "user's), and when given its image_size must be the wrist input's",
    )
    action: ActionScaling
    preprocess: Literal["center_crop", "letterbox", "resize"] = Field(
        "center_crop",
        description="how a camera frame of another size becomes the S x S input (sim.policyview): the centred "
        "square, resized (the sim cameras' square view); the whole frame padded; or squashed",
    )
    contract: PolicyContract = Field(
        default_factory=PolicyContract, description="state inputs and action semantics (sim.policies.contract)"
    )
    inputs: dict[str, InputBinding] = Field(
        default_factory=dict,
        description="policy files: each model input (by name) -> its source: a camera by name with how its frame "
        "becomes the input, the state, tcp_pose or gripper (sim.policies.contract.InputBinding); empty: LeRobot's "
        "names as they come (observation.images.<camera>, observation.state), else the wrist camera (and the state)",
    )
    action_output: str | None = Field(
        None,
        description="policy files: the output holding the actions; None: 'action' if the model has it, else its first",
    )
    feature_map: str | dict[str, str] | None = Field(
        None,
        description="policy files (.onnx, .pt2) attacked white-box: the graph value Grad-CAM and the saliency loss "
        "read (an ONNX tensor name, a .pt2 graph node name); None: the last 4-D map with more than one cell on "
        "every path from the image to the actions (sim.policies.graph_policy); a policy reading several cameras "
        "may name one per camera ({camera: name})",
    )
    training: dict[str, Any] = Field(default_factory=dict, description="resolved training config")
    clean_success: CleanSuccess | None = None
    seed: int | None = None
    git_commit: str = "unknown"
    created_utc: str = ""
    weights_sha256: str = ""

    @model_serializer(mode="wrap")
    def _dump(self, handler):
        # A card without named inputs dumps exactly as before they existed (files, hashes unchanged).
        d = handler(self)
        if "arch" not in self.model_fields_set:  # a policy file's card that left the built-in network out
            d.pop("arch", None)
        if not self.inputs:
            d.pop("inputs", None)
        if self.action_output is None:
            d.pop("action_output", None)
        return d

    def image_size_mismatch(self, plan, where: str = "") -> str | None:
        """One line when the card's explicit ``arch.image_size`` is not the wrist input's size (None: fine)."""
        if "arch" not in self.model_fields_set:
            return None
        wrist = [b for b in plan.images if b.camera == "wrist"]
        if wrist and tuple(wrist[0].size) != (self.arch.image_size,) * 2:
            h, w = wrist[0].size
            return f"{where}card says {self.arch.image_size} px but the model's wrist input takes {h}x{w} px"
        return None

    def arch_mismatch(self) -> str | None:
        """Why the built-in network described by ``arch`` cannot honour ``contract`` (None: it can).

        Checked for checkpoints, whose network is rebuilt from ``arch``; an ONNX card's ``arch``
        only needs the right ``image_size``, since the graph is the user's.
        """
        return self.arch.contract_mismatch(self.contract)


def load_card(path: str | Path) -> PolicyCard:
    """The validated card of checkpoint directory ``path`` (or of a ``policy.json`` file)."""
    p = Path(path)
    card_path = p / CARD_NAME if p.is_dir() else p
    if not card_path.is_file():
        if p.is_file():
            raise PolicyError(
                f"{p}: not a policy checkpoint; expected a directory with {CARD_NAME} and weights.safetensors, or an "
                ".onnx file"
            )
        raise PolicyError(f"{p}: no such policy checkpoint (expected a directory with {CARD_NAME})")
    try:
        doc = json.loads(card_path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise PolicyError(f"{card_path}: not a JSON policy card ({err})") from None
    except RecursionError:
        raise PolicyError(f"{card_path}: not a JSON policy card (nested too deeply)") from None
    if not isinstance(doc, dict) or doc.get("format") != CARD_FORMAT:
        raise PolicyError(f"{card_path}: not an advobj policy card (missing format {CARD_FORMAT!r})")
    try:
        return PolicyCard.model_validate(doc)
    except ValidationError as err:
        e = err.errors()[0]
        loc = ".".join(str(x) for x in e["loc"])
        raise PolicyError(f"{card_path}: {loc}: {e['msg']}") from None
