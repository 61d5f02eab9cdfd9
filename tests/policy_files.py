"""Policy files the white-box loaders must refuse, built here from real exporters (never downloaded).

Each builder writes one file and returns its path: an ONNX graph with an operator onnx2torch has no
converter for, one whose conversion computes another policy than onnxruntime, and ``.pt2`` archives
that are garbage, cut short or stamped by another torch. Used by the loaders' tests, the CLI's
one-line tests and the hostile campaign.
"""

from __future__ import annotations

import json
import warnings
import zipfile
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from sim.policies.pt2 import export_pt2
from tests.policy_zoo import (
    LEROBOT_FRONT,
    LEROBOT_STATE,
    LEROBOT_WRIST,
    LeRobotInputs,
    card_of,
    contract_of,
    tiny_policy,
)

__all__ = [
    "onnx_graph",
    "linear_head",
    "unsupported_op_onnx",
    "mismatched_onnx",
    "tiny_pt2",
    "garbage_pt2",
    "truncated_pt2",
    "other_torch_pt2",
    "rewrite_archive",
    "two_camera_onnx",
    "two_camera_pt2",
    "legacy_onnx_export",
]


def onnx_graph(path, nodes, inits, size: int = 32, opset: int = 17) -> Path:
    """An ONNX policy ``images (B, 3, size, size) -> actions (B, 6)`` of ``nodes``, checked and saved."""
    image = helper.make_tensor_value_info("images", TensorProto.FLOAT, ["B", 3, size, size])
    action = helper.make_tensor_value_info("actions", TensorProto.FLOAT, ["B", 6])
    model = helper.make_model(
        helper.make_graph(nodes, "g", [image], [action], inits), opset_imports=[helper.make_opsetid("", opset)]
    )
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return Path(path)


def linear_head(src: str, n_in: int, seed: int = 0):
    """Nodes and initializers: Flatten(src) @ W -> Tanh -> actions (B, 6)."""
    w = np.random.default_rng(seed).standard_normal((n_in, 6)).astype(np.float32) * 0.05
    nodes = [
        helper.make_node("Flatten", [src], ["flat"]),
        helper.make_node("MatMul", ["flat", "w"], ["mm"]),
        helper.make_node("Tanh", ["mm"], ["actions"]),
    ]
    return nodes, [numpy_helper.from_array(w, "w")]


def unsupported_op_onnx(path, size: int = 32) -> Path:
    """A policy onnxruntime runs whose first node, Shrink, onnx2torch cannot convert."""
    head, inits = linear_head("shrunk", 3 * size * size)
    return onnx_graph(path, [helper.make_node("Shrink", ["images"], ["shrunk"], lambd=0.1)] + head, inits, size)


def mismatched_onnx(path, size: int = 32, out: int = 20) -> Path:
    """A policy whose Resize (nearest, ONNX's default half_pixel and round_prefer_floor) onnx2torch
    converts to torch's nearest (asymmetric, floor): it converts, and computes another policy."""
    nodes = [
        helper.make_node("Shape", ["images"], ["shp"]),
        helper.make_node("Slice", ["shp", "zero", "one"], ["b"]),
        helper.make_node("Concat", ["b", "tail"], ["sz"], axis=0),
        helper.make_node("Resize", ["images", "", "", "sz"], ["small"], mode="nearest"),
    ]
    head, inits = linear_head("small", 3 * out * out)
    inits += [
        numpy_helper.from_array(np.array([0], np.int64), "zero"),
        numpy_helper.from_array(np.array([1], np.int64), "one"),
        numpy_helper.from_array(np.array([3, out, out], np.int64), "tail"),
    ]
    return onnx_graph(path, nodes + head, inits, size)


def tiny_pt2(path) -> Path:
    """The zoo's 32 px image-only policy exported with its card."""
    p = tiny_policy(contract_of((), ("delta_tcp", 1, 1)))
    return export_pt2(p, path, card_of(p))


def garbage_pt2(path) -> Path:
    Path(path).write_bytes(b"PK\x03\x04" + bytes(range(256)) * 4)
    return Path(path)


def truncated_pt2(path) -> Path:
    """A real .pt2 cut in half (an interrupted copy)."""
    full = tiny_pt2(Path(path).with_name(Path(path).stem + "-full.pt2"))
    data = full.read_bytes()
    full.unlink()
    Path(path).write_bytes(data[: len(data) // 2])
    return Path(path)


def rewrite_archive(src, dst, change) -> Path:
    """Copy the archive ``src`` to ``dst`` entry by entry; ``change(name, data)`` returns the new bytes."""
    with zipfile.ZipFile(src) as z, zipfile.ZipFile(dst, "w", zipfile.ZIP_STORED) as out:
        for info in z.infolist():
            out.writestr(info.filename, change(info.filename, z.read(info.filename)))
    return Path(dst)


def other_torch_pt2(path) -> Path:
    """A real .pt2 whose version records say a later torch wrote it (archive version and schema)."""
    full = tiny_pt2(Path(path).with_name(Path(path).stem + "-full.pt2"))

    def change(name, data):
        if name.endswith("/archive_version"):
            return b"1"
        if name.endswith("models/model.json"):
            doc = json.loads(data)
            doc["schema_version"], doc["torch_version"] = {"major": 99, "minor": 0}, "9.9.0"
            return json.dumps(doc).encode()
        return data

    out = rewrite_archive(full, path, change)
    full.unlink()
    return out


def legacy_onnx_export(*args, **kwargs) -> None:
    """``torch.onnx.export(*args, dynamo=False, **kwargs)`` with its DeprecationWarning silenced, as
    ``sim.policies.onnx_policy.export_onnx`` does: the TorchScript exporter is deprecated in favour of
    the torch.export one, which needs onnxscript (not installed); it still exports these plain
    networks exactly. For modules ``export_onnx`` does not take (other inputs than a
    ``VisuomotorPolicy``'s)."""
    import torch

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(*args, dynamo=False, **kwargs)


def two_camera_onnx(path, policy, card, names=(LEROBOT_WRIST, LEROBOT_FRONT, LEROBOT_STATE), output="action"):
    """``policy`` (:class:`tests.policy_zoo.TwoCameraPolicy` or one taking the same three tensors)
    exported by torch.onnx with input ``names`` and ``output``, its card in the metadata."""
    import torch

    from sim.policies.onnx_policy import attach_card

    wrist, front = policy.example_sizes if hasattr(policy, "example_sizes") else (32, 128)
    args = (torch.rand(2, 3, wrist, wrist), torch.rand(2, 3, front, front), torch.rand(2, 7))
    legacy_onnx_export(
        policy.eval(),
        args,
        str(path),
        input_names=list(names),
        output_names=[output],
        dynamic_axes={**{n: {0: "batch"} for n in names}, output: {0: "batch"}},
        opset_version=17,
    )
    return attach_card(path, card)


def two_camera_pt2(path, policy, card, wrist: int = 32, front: int = 128) -> Path:
    """``policy`` wrapped to take LeRobot's dict (:class:`tests.policy_zoo.LeRobotInputs`),
    exported by torch.export with a dynamic batch and its card inside."""
    import torch

    from sim.policies.pt2 import CARD_ENTRY

    batch = {
        LEROBOT_WRIST: torch.rand(2, 3, wrist, wrist),
        LEROBOT_FRONT: torch.rand(2, 3, front, front),
        LEROBOT_STATE: torch.rand(2, 7),
    }
    B = torch.export.Dim("batch", min=1, max=1024)
    ep = torch.export.export(LeRobotInputs(policy).eval(), (batch,), dynamic_shapes=({k: {0: B} for k in batch},))
    for node in ep.graph.nodes:
        node.meta.pop("stack_trace", None)
    torch.export.save(ep, str(path), extra_files={CARD_ENTRY: card.model_dump_json()})
    return Path(path)
