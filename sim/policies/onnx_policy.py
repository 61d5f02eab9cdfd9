"""ONNX export and the black-box :class:`OnnxPolicy` (onnxruntime).

The exported graph has the input ``images: (B, 3, S, S)`` float32 in [0, 1] (normalization is
inside the graph), a second input ``state: (B, D)`` float32 when the policy reads proprioception,
and one output ``actions``: ``(B, 6)``, or ``(B, K, 6)`` for chunks (:mod:`sim.policies.contract`);
the batch axis is dynamic. A built-in network reading several cameras has one image input per
camera, named by it (``wrist``, ``front``: ``(B, 3, H_c, W_c)``), then ``state``; its card binds
them. The policy card travels in the model's metadata (key
``advobj_policy_card``), so an exported file is self-describing; for the built-in network it
names the backbone's last feature map (``feature_map``), where a white-box conversion
(:mod:`sim.policies.onnx_torch`) cuts the graph for Grad-CAM. A user's ONNX policy with one
image input and a ``(B, 6)`` delta output needs no card; any other contract is read from the card
(:func:`attach_card` writes one into an existing file). A file of another lab may have other inputs:
the card's ``inputs`` bind each to a camera or the state (LeRobot's ``observation.images.<camera>``
and ``observation.state`` bind by name), and :class:`OnnxPolicy` feeds each as the card says
(:func:`sim.policies.contract.bind_inputs`).
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
from sim.policies.contract import WRIST_CAMERA, bind_inputs, decode_actions, policy_cameras, policy_contract
from sim.policies.interface import PolicyError, prepare_images
from sim.policies.policy import file_inputs

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
    cameras = policy_cameras(policy)
    if cameras != (WRIST_CAMERA,) and card is None:
        raise PolicyError(f"card: a policy reading cameras {', '.join(cameras)} needs its card in the file")
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
        if cameras != (WRIST_CAMERA,):  # the built-in network on several cameras: one input per camera, by name
            views = {b.camera: torch.rand(2, 3, *b.size, device=policy.device) for b in policy.inputs.images}
            dummy = (views, dummy[1] if D else {})  # a trailing {}: the dict is an input, not keyword arguments
            names = [b.name for b in policy.inputs.images] + (["state"] if D else [])
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
            card = card.model_copy(update={"feature_map": _backbone_output(onnx.load(str(path)), path, cameras)})
        if cameras != (WRIST_CAMERA,) and not card.inputs:
            card = card.model_copy(update={"inputs": file_inputs(policy.inputs)})
        attach_card(path, card)
    else:
        onnx.checker.check_model(onnx.load(str(path)))
    return path


def _backbone_output(model, path, cameras=(WRIST_CAMERA,)) -> str | dict[str, str]:
    """The ONNX tensor the built-in network's backbone ends in (the input of its head's first
    convolution, ``reduce``): the feature map its Grad-CAM reads, recorded in the exported card so
    a white-box conversion cuts the graph where the checkpoint does. Reading several cameras, the
    head reduces each camera's map in camera order: ``{camera: tensor}``."""
    found = [node.input[0] for node in model.graph.node if node.op_type == "Conv" and node.name.startswith("/reduce/")]
    if len(found) < len(cameras) or not found:
        raise PolicyError(
            f"{path}: the exported graph has no head convolution (/reduce/...) to take the feature map from"
        )
    return found[0] if len(cameras) == 1 else dict(zip(cameras, found))


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
        if not inputs or not outputs:
            raise PolicyError(f"{self.path}: a policy needs an image input and an action output")
        meta = self.session.get_modelmeta().custom_metadata_map
        self.card = None
        if CARD_METADATA_KEY in meta:
            try:
                self.card = PolicyCard.model_validate(json.loads(meta[CARD_METADATA_KEY]))
            except (ValidationError, json.JSONDecodeError) as err:
                raise PolicyError(
                    f"{self.path}: metadata {CARD_METADATA_KEY}: not a valid policy card ({str(err).splitlines()[0]})"
                ) from None
        self.contract = policy_contract(self)
        card = self.card
        self.inputs = bind_inputs(
            None if card is None else card.inputs,
            [(i.name, tuple(i.shape)) for i in inputs],
            [o.name for o in outputs],
            self.contract,
            None if card is None else card.action_output,
            f"{self.path}: ",
        )
        if card is not None and (why := card.image_size_mismatch(self.inputs, f"{self.path}: ")):
            raise PolicyError(why)
        first = self.inputs.images[0]
        wrist = [b for b in self.inputs.images if b.camera == WRIST_CAMERA]
        self.image_size = int((wrist or [first])[0].size[0])
        # the single-camera names older callers read (the reference check, the CLI's report)
        self.input_name = first.name
        self.state_name = self.inputs.states[0].name if self.inputs.states else None
        self.output_name = self.inputs.output

    def _views(self, images) -> dict:
        """``{camera: (B, 3, H, W)}`` canonical frames of ``images`` (one array: the sole camera)."""
        plan = self.inputs
        if not isinstance(images, dict):
            if len(plan.cameras) != 1:
                raise PolicyError(f"{self.path}: images: reads cameras {', '.join(plan.cameras)}; pass a dict")
            images = {plan.cameras[0]: images}
        out = {}
        for b in plan.images:
            if b.camera not in images:
                raise PolicyError(f"{self.path}: images: no images of camera {b.camera!r}")
            try:
                out[b.camera] = prepare_images(images[b.camera], b.size)
            except PolicyError as err:
                raise PolicyError(f"{self.path}: camera {b.camera!r}: {err}") from None
        return out

    def feeds(self, images, state=None) -> dict:
        """onnxruntime's feeds for env images (one array or ``{camera: array}``) and the ``(B, D)`` state."""
        views = self._views(images)
        B = len(next(iter(views.values())))
        st = None
        if self.inputs.states:
            if state is None:
                raise PolicyError(f"{self.path}: state: this policy reads {list(self.contract.state)}; no state given")
            st = np.ascontiguousarray(state, dtype=np.float32)
            if st.shape != (B, self.contract.state_dim):
                raise PolicyError(f"{self.path}: state: expected ({B}, {self.contract.state_dim}), got {st.shape}")
        return {k: np.ascontiguousarray(v, np.float32) for k, v in self.inputs.feeds(views, st).items()}

    def act(self, images, state=None) -> np.ndarray:
        """Actions ``(B, 6)`` (or ``(B, K, 6)``) float32 for env images ``(B, H, W, 3)`` uint8 or
        ``(B, 3, H, W)`` floats (one array for a one-camera policy, else ``{camera: array}``), and
        the ``(B, D)`` state when the contract reads one."""
        feeds = self.feeds(images, state)
        B = len(next(iter(feeds.values())))
        out = self.session.run([self.output_name], feeds)[0]
        out = decode_actions(np.asarray(out), self.contract, B)
        if self.contract.action.chunk == 1:
            out = out[:, 0]
        return out.astype(np.float32)

    def __repr__(self) -> str:
        return f"OnnxPolicy({str(self.path)!r}, image_size={self.image_size})"
