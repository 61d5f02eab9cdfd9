"""ONNX export and the black-box :class:`OnnxPolicy` (onnxruntime).

The exported graph has one input ``images: (B, 3, S, S)`` float32 in [0, 1] (normalization is
inside the graph) and one output ``actions: (B, 6)`` in [-1, 1]; the batch axis is dynamic. The
policy card travels in the model's metadata (key ``advobj_policy_card``), so an exported file is
self-describing. User-supplied ONNX policies need only the same input/output contract.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from sim.policies.interface import PolicyError, prepare_images

__all__ = ["export_onnx", "OnnxPolicy", "CARD_METADATA_KEY", "DEFAULT_OPSET"]

CARD_METADATA_KEY = "advobj_policy_card"
DEFAULT_OPSET = 17


def export_onnx(policy, path: str | Path, card=None, opset: int = DEFAULT_OPSET) -> Path:
    """Export torch ``policy`` to ``path`` (opset >= 17) with ``card`` in the metadata."""
    import warnings

    import onnx
    import torch

    if opset < 17:
        raise PolicyError(f"opset: need >= 17, got {opset}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    s = policy.image_size
    was_training = policy.training
    policy.eval()
    try:
        dummy = torch.rand(2, 3, s, s, device=policy.device)
        # The TorchScript exporter is deprecated in favour of the torch.export one, which needs
        # onnxscript and is slower; it still exports these plain conv nets exactly (parity tests).
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            torch.onnx.export(
                policy,
                (dummy,),
                str(path),
                input_names=["images"],
                output_names=["actions"],
                dynamic_axes={"images": {0: "batch"}, "actions": {0: "batch"}},
                opset_version=opset,
                dynamo=False,
            )
    finally:
        policy.train(was_training)
    model = onnx.load(str(path))
    if card is not None:
        entry = model.metadata_props.add()
        entry.key, entry.value = CARD_METADATA_KEY, card.model_dump_json()
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
        import onnxruntime as ort

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
        if len(inputs) != 1 or len(outputs) < 1:
            raise PolicyError(f"{self.path}: a policy needs exactly one image input and an action output")
        shape = inputs[0].shape
        if len(shape) != 4 or shape[1] != 3 or not isinstance(shape[2], int) or shape[2] != shape[3]:
            raise PolicyError(f"{self.path}: input {inputs[0].name!r} must be (B, 3, S, S) with fixed S, got {shape}")
        self.input_name, self.output_name = inputs[0].name, outputs[0].name
        self.image_size = int(shape[2])
        meta = self.session.get_modelmeta().custom_metadata_map
        self.card = None
        if CARD_METADATA_KEY in meta:
            from sim.policies.checkpoint import PolicyCard

            self.card = PolicyCard.model_validate(json.loads(meta[CARD_METADATA_KEY]))
            if self.card.arch.image_size != self.image_size:
                raise PolicyError(f"{self.path}: card says {self.card.arch.image_size} px but the graph takes {self.image_size} px")

    def act(self, images) -> np.ndarray:
        """Actions ``(B, 6)`` float32 for env images ``(B, S, S, 3)`` uint8 or ``(B, 3, S, S)`` floats."""
        x = prepare_images(images, self.image_size)
        out = self.session.run([self.output_name], {self.input_name: x})[0]
        if out.ndim != 2 or out.shape[1] != 6:
            raise PolicyError(f"{self.path}: output {self.output_name!r} must be (B, 6), got {out.shape}")
        return out.astype(np.float32)

    def __repr__(self) -> str:
        return f"OnnxPolicy({str(self.path)!r}, image_size={self.image_size})"
