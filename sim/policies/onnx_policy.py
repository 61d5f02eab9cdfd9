"""ONNX export and the black-box :class:`OnnxPolicy` (onnxruntime).

The exported graph has the input ``images: (B, 3, S, S)`` float32 in [0, 1] (normalization is
inside the graph), a second input ``state: (B, D)`` float32 when the policy reads proprioception,
and one output ``actions``: ``(B, 6)``, or ``(B, K, 6)`` for chunks (:mod:`sim.policies.contract`);
the batch axis is dynamic. The policy card travels in the model's metadata (key
``advobj_policy_card``), so an exported file is self-describing; for the built-in network it
names the backbone's last feature map (``feature_map``), where a white-box conversion
(:mod:`sim.policies.onnx_torch`) cuts the graph for Grad-CAM. A user's ONNX policy with one
image input and a ``(B, 6)`` delta output needs no card; any other contract is read from the card
(:func:`attach_card` writes one into an existing file).
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from pydantic import ValidationError

from sim.policies.card import PolicyCard
from sim.policies.contract import decode_actions, policy_contract
from sim.policies.interface import IMAGE_SIZE_MAX_PX, IMAGE_SIZE_MIN_PX, PolicyError, prepare_images

__all__ = ["export_onnx", "attach_card", "OnnxPolicy", "CARD_METADATA_KEY", "DEFAULT_OPSET"]

CARD_METADATA_KEY = "advobj_policy_card"
DEFAULT_OPSET = 17


def export_onnx(policy, path: str | Path, card=None, opset: int = DEFAULT_OPSET) -> Path:
    """Export torch ``policy`` to ``path`` (opset >= 17) with ``card`` in the metadata."""
    if opset < 17:
        raise PolicyError(f"opset: need >= 17, got {opset}")

    if card is None and not policy_contract(policy).is_default:
        # without the card the file could not say what its state input or its chunks mean
        raise PolicyError(
            f"card: a policy with the contract ({policy_contract(policy).describe()}) needs its card in the file"
        )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    s = policy.image_size
    D = int(getattr(policy.config, "state_dim", 0))
    was_training = policy.training
    policy.eval()
    try:
        dummy = (torch.rand(2, 3, s, s, device=policy.device),) + (
            (torch.rand(2, D, device=policy.device),) if D else ()
        )
        names = ["images"] + (["state"] if D else [])
        # The TorchScript exporter is deprecated in favour of the torch.export one, which needs
        # onnxscript and is slower; it still exports these plain conv nets exactly (parity tests).
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            torch.onnx.export(
                policy,
                dummy,
                str(path),
                input_names=names,
                output_names=["actions"],
                dynamic_axes={**{n: {0: "batch"} for n in names}, "actions": {0: "batch"}},
                opset_version=opset,
                dynamo=False,
            )
    finally:
        policy.train(was_training)
    if card is not None:
        if card.feature_map is None and isinstance(getattr(policy, "reduce", None), torch.nn.Module):
            card = card.model_copy(update={"feature_map": _backbone_output(onnx.load(str(path)), path)})
        attach_card(path, card)
    else:
        onnx.checker.check_model(onnx.load(str(path)))
    return path


def _backbone_output(model, path) -> str:
    """The ONNX tensor the built-in network's backbone ends in (the input of its head's first
    convolution, ``reduce``): the feature map its Grad-CAM reads, recorded in the exported card so
    a white-box conversion cuts the graph where the checkpoint does."""
    for node in model.graph.node:
        if node.op_type == "Conv" and node.name.startswith("/reduce/"):
            return node.input[0]
    raise PolicyError(f"{path}: the exported graph has no head convolution (/reduce/...) to take the feature map from")


def attach_card(path: str | Path, card) -> Path:
    """Write ``card`` (a :class:`sim.policies.card.PolicyCard`) into ONNX file ``path``'s
    metadata, replacing an earlier card: how a policy exported by other code states its contract."""
    path = Path(path)
    model = onnx.load(str(path))
    keep = [(p.key, p.value) for p in model.metadata_props if p.key != CARD_METADATA_KEY]
    del model.metadata_props[:]
    for k, v in keep + [(CARD_METADATA_KEY, card.model_dump_json())]:
        entry = model.metadata_props.add()
        entry.key, entry.value = k, v
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


class OnnxPolicy:
    """A black-box policy run by onnxruntime behind the shared ``act`` interface.

    Args:
        path: the ``.onnx`` file.
        threads: intra-op threads (0 = onnxruntime's default).
        spin: let idle intra-op threads spin-wait for work. Off by default: on a few shared cores
            spinning threads steal the CPU the (llvmpipe) renderer and the control loop need;
            off costs a little wake-up latency per op (measured in ``benchmarks/bench_control_loop.py``).
    """

    white_box = False

    def __init__(self, path: str | Path, threads: int = 0, spin: bool = False):
        self.path = Path(path)
        if not self.path.is_file():
            raise PolicyError(f"{self.path}: no such ONNX file")
        opts = ort.SessionOptions()
        if threads:
            opts.intra_op_num_threads = threads
        if not spin:
            opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
            opts.add_session_config_entry("session.inter_op.allow_spinning", "0")
        try:
            self.session = ort.InferenceSession(str(self.path), opts, providers=["CPUExecutionProvider"])
        except Exception as err:  # onnxruntime raises its own exception types for bad files
            raise PolicyError(f"{self.path}: not a loadable ONNX model ({str(err).splitlines()[0]})") from None
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        if len(inputs) not in (1, 2) or len(outputs) < 1:
            raise PolicyError(
                f"{self.path}: a policy needs an image input (and optionally a state input) and an action output, "
                f"got {len(inputs)} inputs"
            )
        shape = inputs[0].shape
        if len(shape) != 4 or shape[1] != 3 or not isinstance(shape[2], int) or shape[2] != shape[3]:
            raise PolicyError(f"{self.path}: input {inputs[0].name!r} must be (B, 3, S, S) with fixed S, got {shape}")
        self.input_name, self.output_name = inputs[0].name, outputs[0].name
        self.state_name = inputs[1].name if len(inputs) == 2 else None
        self.image_size = int(shape[2])
        if not IMAGE_SIZE_MIN_PX <= self.image_size <= IMAGE_SIZE_MAX_PX:
            raise PolicyError(
                f"{self.path}: input {inputs[0].name!r} takes {self.image_size} px images; advobj renders "
                f"{IMAGE_SIZE_MIN_PX}..{IMAGE_SIZE_MAX_PX} px"
            )
        meta = self.session.get_modelmeta().custom_metadata_map
        self.card = None
        if CARD_METADATA_KEY in meta:
            try:
                self.card = PolicyCard.model_validate(json.loads(meta[CARD_METADATA_KEY]))
            except (ValidationError, json.JSONDecodeError) as err:
                raise PolicyError(
                    f"{self.path}: metadata {CARD_METADATA_KEY}: not a valid policy card ({str(err).splitlines()[0]})"
                ) from None
            if self.card.arch.image_size != self.image_size:
                raise PolicyError(
                    f"{self.path}: card says {self.card.arch.image_size} px but the graph takes {self.image_size} px"
                )

        self.contract = policy_contract(self)
        D = self.contract.state_dim
        if D and self.state_name is None:
            raise PolicyError(
                f"{self.path}: the card's contract reads state {list(self.contract.state)} but the graph has no "
                "state input"
            )
        if self.state_name is not None:
            st = inputs[1].shape
            if not D:
                raise PolicyError(
                    f"{self.path}: the graph has a second input {self.state_name!r} but no card says what it holds; "
                    f"write a card with contract.state (sim.policies.onnx_policy.attach_card)"
                )
            if len(st) != 2 or (isinstance(st[1], int) and st[1] != D):
                raise PolicyError(
                    f"{self.path}: input {self.state_name!r} must be (B, {D}) for state "
                    f"{list(self.contract.state)}, got {st}"
                )

    def act(self, images, state=None) -> np.ndarray:
        """Actions ``(B, 6)`` (or ``(B, K, 6)``) float32 for env images ``(B, S, S, 3)`` uint8 or
        ``(B, 3, S, S)`` floats, and the ``(B, D)`` state when the contract reads one."""
        x = prepare_images(images, self.image_size)
        feeds = {self.input_name: x}
        if self.state_name is not None:
            if state is None:
                raise PolicyError(f"{self.path}: state: this policy reads {list(self.contract.state)}; no state given")
            st = np.ascontiguousarray(state, dtype=np.float32)
            if st.shape != (len(x), self.contract.state_dim):
                raise PolicyError(f"{self.path}: state: expected ({len(x)}, {self.contract.state_dim}), got {st.shape}")
            feeds[self.state_name] = st
        out = self.session.run([self.output_name], feeds)[0]
        out = decode_actions(np.asarray(out), self.contract, len(x))
        if self.contract.action.chunk == 1:
            out = out[:, 0]
        return out.astype(np.float32)

    def __repr__(self) -> str:
        return f"OnnxPolicy({str(self.path)!r}, image_size={self.image_size})"
