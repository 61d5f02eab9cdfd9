"""ONNX files as white-box policies: converted to torch by onnx2torch, checked against onnxruntime.

:func:`convert_onnx` turns the file behind an :class:`sim.policies.onnx_policy.OnnxPolicy` into a
differentiable :class:`sim.policies.graph_policy.GraphPolicy`:

1. every node's operator must have an onnx2torch converter at the file's opset; the first one
   without is refused by name (the file stays usable black-box);
2. onnx2torch builds a ``torch.fx.GraphModule`` (one torch module per ONNX node, initializers as
   buffers), cut into ``features`` and ``head`` at the card's ``feature_map``
   (:mod:`sim.policies.graph_policy`);
3. before the module is used, onnxruntime (the reference: what a lab deploys) and the cut torch
   module run on :data:`~sim.policies.graph_policy.CHECK_FRAMES` frames rendered from the scene;
   an output further from onnxruntime's than ``ATOL + RTOL * |value|`` is refused, naming the
   output and the largest difference.

White-box through conversion therefore means: the gradients are those of a torch program that
computes, on those frames, what onnxruntime computes to within the tolerance; they are not
onnxruntime's (it has none).

onnx2torch is installed without its dependencies (``Makefile``): it lists torchvision, whose
registry build would replace the CPU torch, yet needs it only for two detection operators
(NonMaxSuppression, RoiAlign). Without torchvision those two are refused as unsupported.
"""

from __future__ import annotations

import importlib.util
import sys
import types
import warnings

import numpy as np
import onnx
import torch
from torch import fx

from sim.policies.contract import decode_actions
from sim.policies.graph_policy import (
    GraphPolicy,
    max_abs_difference,
    pick_feature_node,
    reference_frames,
    split_graph,
)
from sim.policies.interface import PolicyError, prepare_images

__all__ = [
    "ATOL",
    "RTOL",
    "NEEDS_TORCHVISION",
    "convert_onnx",
    "fold_constant_nodes",
    "unsupported_operators",
    "onnx2torch_module",
]

# A converted output may differ from onnxruntime's by ATOL + RTOL * |value| (float32 kernels that
# sum in another order differ by ~1e-6 on these policies; tests/sim/policies/test_onnx_white_box.py).
ATOL = 1e-4
RTOL = 1e-4
NEEDS_TORCHVISION = frozenset({"NonMaxSuppression", "RoiAlign"})


def _torchvision_missing(*args, **kwargs):
    raise PolicyError("this operator needs torchvision, which is not installed (NonMaxSuppression, RoiAlign)")


def onnx2torch_module():
    """The ``onnx2torch`` package, imported without torchvision when torchvision is absent
    (its two detection converters then raise instead of importing it)."""
    if "onnx2torch" in sys.modules:
        return sys.modules["onnx2torch"]
    if importlib.util.find_spec("onnx2torch") is None:
        raise PolicyError(
            "white-box ONNX needs onnx2torch: pip install --no-deps onnx2torch==1.5.15 (make venv installs it)"
        )
    stubbed = importlib.util.find_spec("torchvision") is None
    if stubbed:
        tv, ops = types.ModuleType("torchvision"), types.ModuleType("torchvision.ops")
        ops.nms = ops.roi_align = ops.box_convert = _torchvision_missing
        tv.ops = ops
        sys.modules["torchvision"], sys.modules["torchvision.ops"] = tv, ops
    try:
        import onnx2torch  # lazy: optional dependency (onnx2torch)
    except Exception as err:  # noqa: BLE001 - a broken install is one line, not a traceback
        raise PolicyError(f"white-box ONNX: onnx2torch cannot be imported ({type(err).__name__}: {err})") from None
    finally:
        if stubbed:  # nothing else may mistake the stand-in for torchvision
            sys.modules.pop("torchvision", None)
            sys.modules.pop("torchvision.ops", None)
    onnx2torch.torchvision_stubbed = stubbed
    # Its converters warn where a conversion may differ, and its modules trip torch deprecation
    # warnings at every call: the check against onnxruntime decides, and stderr stays one line.
    warnings.filterwarnings("ignore", module=r"onnx2torch(\.|$)")
    return onnx2torch


def unsupported_operators(model: onnx.ModelProto) -> list[tuple[str, str, int]]:
    """``(operator, node name, opset)`` of every node onnx2torch has no converter for."""
    o2t = onnx2torch_module()
    from onnx2torch.node_converters.registry import get_converter  # lazy: optional dependency (onnx2torch)

    opsets = {(o.domain if o.domain != "ai.onnx" else ""): o.version for o in model.opset_import}
    bad = []
    for node in model.graph.node:
        domain = node.domain if node.domain != "ai.onnx" else ""
        version = opsets.get(domain)
        if version is None:
            bad.append((f"{domain}::{node.op_type}", node.name, -1))
            continue
        if node.op_type in NEEDS_TORCHVISION and o2t.torchvision_stubbed:
            bad.append((node.op_type, node.name, version))
            continue
        try:
            get_converter(operation_type=node.op_type, version=version, domain=domain)
        except NotImplementedError:
            bad.append((node.op_type if not domain else f"{domain}::{node.op_type}", node.name, version))
    return bad


def fold_constant_nodes(model: onnx.ModelProto) -> onnx.ModelProto:
    """``model`` with ``Identity`` nodes of initializers and tensor ``Constant`` nodes turned into
    initializers (same values, same names). torch.onnx's exporter writes the first for shared
    weights; onnx2torch reads a convolution's weights from initializers only."""
    inits = {i.name: i for i in model.graph.initializer}
    keep, added = [], []
    for node in model.graph.node:
        if node.op_type == "Identity" and node.domain in ("", "ai.onnx") and node.input[0] in inits:
            t = onnx.TensorProto()
            t.CopyFrom(inits[node.input[0]])
            t.name = node.output[0]
        elif node.op_type == "Constant" and len(node.attribute) == 1 and node.attribute[0].name == "value":
            t = onnx.TensorProto()
            t.CopyFrom(node.attribute[0].t)
            t.name = node.output[0]
        else:
            keep.append(node)
            continue
        inits[t.name] = t
        added.append(t)
    if not added:
        return model
    out = onnx.ModelProto()
    out.CopyFrom(model)
    del out.graph.node[:]
    out.graph.node.extend(keep)
    out.graph.initializer.extend(added)
    return out


def _producers(gm: fx.GraphModule) -> dict[str, fx.Node]:
    """ONNX value name -> the fx node holding it (onnx2torch's ``onnx_mapping`` of each module)."""
    out: dict[str, fx.Node] = {}
    for n in gm.graph.nodes:
        if n.op != "call_module":
            continue
        mapping = getattr(gm.get_submodule(n.target), "onnx_mapping", None)
        if mapping is None:
            continue
        names = list(mapping.outputs)
        if len(names) == 1:
            out[names[0]] = n
            continue
        for user in n.users:  # several outputs: onnx2torch reads each through getitem
            if user.op == "call_function" and len(user.args) == 2 and isinstance(user.args[1], int):
                out[names[user.args[1]]] = user
    return out


def _run_reference(onnx_policy, images: np.ndarray, state: np.ndarray | None) -> np.ndarray:
    """onnxruntime's raw first output on the frames, in batches the graph accepts."""
    x = prepare_images(images, onnx_policy.image_size)
    b = onnx_policy.session.get_inputs()[0].shape[0]
    step = b if isinstance(b, int) and b > 0 else len(x)
    outs = []
    for i in range(0, len(x), step):
        feeds = {onnx_policy.input_name: x[i : i + step]}
        if onnx_policy.state_name is not None:
            feeds[onnx_policy.state_name] = np.ascontiguousarray(state[i : i + step], dtype=np.float32)
        outs.append(np.asarray(onnx_policy.session.run([onnx_policy.output_name], feeds)[0]))
    return np.concatenate(outs), step


def convert_onnx(onnx_policy, device="cpu", spec=None) -> GraphPolicy:
    """The white-box :class:`GraphPolicy` of ``onnx_policy``'s file, checked against onnxruntime on
    frames of ``spec`` (default: the built-in scene). Raises :class:`PolicyError` in one line for
    an unsupported operator, a failed conversion, a feature map that does not cut the graph, or
    outputs over the tolerance."""
    path = onnx_policy.path
    try:
        model = onnx.load(str(path))
    except Exception as err:  # noqa: BLE001 - protobuf and onnx raise their own types
        raise PolicyError(f"{path}: not a loadable ONNX model ({str(err).splitlines()[0]})") from None
    model = fold_constant_nodes(model)
    bad = unsupported_operators(model)
    if bad:
        op, node, version = bad[0]
        more = f" (and {len(bad) - 1} more node(s): {', '.join(sorted({b[0] for b in bad[1:]}))})" if bad[1:] else ""
        raise PolicyError(
            f"{path}: operator {op!r} (node {node!r}, opset {version}) has no torch conversion{more}; the file can "
            "be evaluated black-box (advobj policy eval) but not attacked white-box"
        )
    o2t = onnx2torch_module()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # shape inference and the converters' caveats: the check decides
            gm = o2t.convert(model, attach_onnx_mapping=True)
    except Exception as err:  # noqa: BLE001 - a converter's refusal of an attribute is one line
        msg = " ".join(str(err).split())[:300]
        raise PolicyError(f"{path}: onnx2torch cannot convert it ({type(err).__name__}: {msg})") from None
    gm.eval()
    placeholders = [n for n in gm.graph.nodes if n.op == "placeholder"]
    initializers = {i.name for i in model.graph.initializer}
    names = [i.name for i in model.graph.input if i.name not in initializers]
    by_name = dict(zip(names, placeholders))
    image = by_name[onnx_policy.input_name]
    state = by_name.get(onnx_policy.state_name) if onnx_policy.state_name else None
    producers = _producers(gm)
    if onnx_policy.output_name not in producers:
        raise PolicyError(f"{path}: output {onnx_policy.output_name!r} is not computed by any node")
    actions = producers[onnx_policy.output_name]
    S, D = onnx_policy.image_size, onnx_policy.contract.state_dim
    card = onnx_policy.card
    wanted = getattr(card, "feature_map", None)
    if wanted:
        if wanted not in producers:
            raise PolicyError(f"{path}: card feature_map: {wanted!r} is not a tensor computed in the graph")
        feature = producers[wanted]
    else:
        example = (torch.rand(2, 3, S, S),) + ((torch.zeros(2, D),) if state is not None else ())
        try:
            feature = pick_feature_node(gm, image, actions, example, str(path))
        except PolicyError:
            raise
        except Exception as err:  # noqa: BLE001 - the converted graph failing on a plain input
            msg = " ".join(str(err).split())[:200]
            raise PolicyError(f"{path}: the converted graph fails on a ({2}, 3, {S}, {S}) input ({msg})") from None
        wanted = next((k for k, v in producers.items() if v is feature), feature.name)
    features, head = split_graph(gm, image, state, actions, feature, str(path))
    policy = GraphPolicy(
        features, head, S, onnx_policy.contract, card=card, source=path, format="onnx", feature_map=wanted
    )
    images, st = reference_frames(S, onnx_policy.contract, spec)
    ref, step = _run_reference(onnx_policy, images, st)
    n = len(images)
    try:
        x = torch.from_numpy(prepare_images(images, S))
        sv = None if st is None else torch.from_numpy(st)
        with torch.no_grad():
            got = np.concatenate(
                [policy(x[i : i + step], None if sv is None else sv[i : i + step]).numpy() for i in range(0, n, step)]
            )
    except PolicyError:
        raise
    except Exception as err:  # noqa: BLE001 - the converted graph failing on rendered frames
        msg = " ".join(str(err).split())[:200]
        raise PolicyError(
            f"{path}: the converted graph fails on rendered frames ({type(err).__name__}: {msg})"
        ) from None
    want = decode_actions(ref.astype(np.float64), onnx_policy.contract, n)
    got = got.astype(np.float64).reshape(want.shape)
    diff = max_abs_difference(got, want)
    same = (got == want) | (np.isnan(got) & np.isnan(want))
    excess = np.where(same, 0.0, np.abs(got - want) - (ATOL + RTOL * np.abs(want)))
    ok = not np.any(np.nan_to_num(excess, nan=np.inf) > 0)
    if not ok:
        raise PolicyError(
            f"{path}: output {onnx_policy.output_name!r} of the torch conversion differs from onnxruntime by up to "
            f"{diff:.3g} on {n} rendered frames (tolerance {ATOL:g} + {RTOL:g} x |value|); not attacking through a "
            "conversion that computes another policy"
        )
    policy.check = {
        "reference": f"onnxruntime {onnx_policy.session.get_providers()[0]}",
        "frames": n,
        "output": onnx_policy.output_name,
        "max_abs_diff": diff,
        "atol": ATOL,
        "rtol": RTOL,
    }
    return policy.to(torch.device(device))
