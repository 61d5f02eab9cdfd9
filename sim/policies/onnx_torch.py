"""ONNX files as white-box policies: converted to torch by onnx2torch, checked against onnxruntime.

:func:`convert_onnx` turns the file behind an :class:`sim.policies.onnx_policy.OnnxPolicy` into a
differentiable :class:`sim.policies.graph_policy.GraphPolicy`:

1. every node's operator must have an onnx2torch converter at the file's opset; the first one
   without is refused by name (the file stays usable black-box);
2. onnx2torch builds a ``torch.fx.GraphModule`` (one torch module per ONNX node, initializers as
   buffers), cut into ``features`` and ``head`` at the card's ``feature_map``
   (:mod:`sim.policies.graph_policy`). Before, shapes are inferred with data propagation and
   ``CumSum``'s default direction is written out (onnx2torch misreads both in LeRobot's ACT export);
   after, an image's batch-size read becomes the node a ``.pt2`` has for it, which is no data path;
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

from sim.policies.contract import check_scene, decode_actions
from sim.policies.graph_policy import (
    GraphPolicy,
    example_inputs,
    max_abs_difference,
    pick_feature_node,
    reference_frames,
    split_graph,
)
from sim.policies.interface import PolicyError
from sim.spec import load_spec

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


def _explicit_cumsum_direction(model: onnx.ModelProto) -> onnx.ModelProto:
    """``model`` with ONNX's default ``reverse=0`` written into every ``CumSum`` that leaves it out
    (torch.onnx's exporter does): onnx2torch (1.5.15) reads a missing ``reverse`` as 1 and converts
    such a node to a reversed cumulative sum (LeRobot's ACT sums its 2-D position embedding so)."""
    for node in model.graph.node:
        if node.op_type == "CumSum" and node.domain in ("", "ai.onnx"):
            if not any(a.name == "reverse" for a in node.attribute):
                node.attribute.append(onnx.helper.make_attribute("reverse", 0))
    return model


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


def _read_batch_sizes(gm: fx.GraphModule, images: list[fx.Node]) -> None:
    """Rewrite each ``Gather(Shape(image), 0)`` of ``gm`` (the batch size read off an image: LeRobot's
    ACT sizes its latent and its decoder's queries so) as ``index + aten.sym_size.int(image, 0)``, the
    node a .pt2 has for it, which the feature-map cut knows carries no data from the image; same value,
    dtype, shape and device as the Gather's."""
    from onnx2torch.node_converters.gather import OnnxGather  # lazy: optional dependency (onnx2torch)
    from onnx2torch.node_converters.shape import OnnxShape  # lazy: optional dependency (onnx2torch)

    def module(n: fx.Node):
        return gm.get_submodule(n.target) if n.op == "call_module" else None

    changed = False
    for image in images:
        for shape in list(image.users):
            if not isinstance(module(shape), OnnxShape) or module(shape)._start != 0:
                continue
            for gather in list(shape.users):
                index = gather.args[1] if len(gather.args) == 2 else None
                if not isinstance(module(gather), OnnxGather) or module(gather)._axis != 0:
                    continue
                if not isinstance(index, fx.Node) or index.op != "get_attr" or gather.args[0] is not shape:
                    continue
                value = gm.get_buffer(index.target) if "." in index.target else getattr(gm, index.target)
                if value.dtype.is_floating_point or value.numel() != 1 or int(value.reshape(-1)[0]) != 0:
                    continue
                with gm.graph.inserting_before(gather):
                    batch = gm.graph.call_function(torch.ops.aten.sym_size.int, (image, 0))
                    gather.replace_all_uses_with(gm.graph.call_function(torch.add, (index, batch)))
                gm.graph.erase_node(gather)
                changed = True
            if not shape.users:
                gm.graph.erase_node(shape)
    if changed:
        gm.graph.lint()
        gm.recompile()


def _run_reference(onnx_policy, images, state: np.ndarray | None) -> tuple[np.ndarray, int]:
    """onnxruntime's raw action output on the frames (one array or ``{camera: array}``), in batches
    the graph accepts; ``(outputs, batch)``."""
    feeds = onnx_policy.feeds(images, state)
    n = len(next(iter(feeds.values())))
    b = onnx_policy.session.get_inputs()[0].shape[0]
    step = b if isinstance(b, int) and b > 0 else n
    outs = []
    for i in range(0, n, step):
        part = {k: v[i : i + step] for k, v in feeds.items()}
        outs.append(np.asarray(onnx_policy.session.run([onnx_policy.output_name], part)[0]))
    return np.concatenate(outs), step


def _feature_nodes(card, plan, gm, images, state_nodes, actions, producers, where, example):
    """One feature node per image input (card ``feature_map``: a name, or ``{camera: name}``; else
    picked, :func:`sim.policies.graph_policy.pick_feature_node`); ``(nodes, names)``."""
    wanted = getattr(card, "feature_map", None)
    if isinstance(wanted, str):
        wanted = {plan.images[0].camera: wanted} if len(plan.images) == 1 else None
        if wanted is None:
            raise PolicyError(
                f"{where}: card feature_map: this policy reads cameras {', '.join(plan.cameras)}; name one map per "
                "camera ({camera: name})"
            )
    wanted = dict(wanted or {})
    for cam in wanted:
        if cam not in plan.cameras:
            raise PolicyError(f"{where}: card feature_map: {cam!r} is not a camera the policy reads")
    nodes, names = [], []
    for b, image in zip(plan.images, images):
        name = wanted.get(b.camera)
        if name:
            if name not in producers:
                raise PolicyError(f"{where}: card feature_map: {name!r} is not a tensor computed in the graph")
            node = producers[name]
        else:
            others = set(images) - {image} | set(state_nodes)
            try:
                node = pick_feature_node(gm, image, actions, example, where, exclude=others)
            except PolicyError:
                raise
            except Exception as err:  # noqa: BLE001 - the converted graph failing on a plain input
                msg = " ".join(str(err).split())[:200]
                raise PolicyError(f"{where}: the converted graph fails on a batch of 2 plain inputs ({msg})") from None
            name = next((k for k, v in producers.items() if v is node), node.name)
        nodes.append(node)
        names.append(name)
    return nodes, names


def _rows(views: dict, i: int, step: int, single: bool):
    part = {c: v[i : i + step] for c, v in views.items()}
    return next(iter(part.values())) if single else part


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
    model = _explicit_cumsum_direction(fold_constant_nodes(model))
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
        # Shapes computed in the graph (LeRobot's ACT builds its decoder input with ConstantOfShape of a
        # Concat of the batch size) are known only with data propagation; onnx2torch's own inference runs
        # without it and would size a LayerNormalization from an unknown axis (0).
        model = onnx.shape_inference.infer_shapes(model, data_prop=True)
    except Exception:  # noqa: BLE001, S110 - inference is a hint: onnx2torch infers again, the check decides
        pass
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
    plan = onnx_policy.inputs
    images = [by_name[b.name] for b in plan.images]
    state_nodes = [by_name[s.name] for s in plan.states]
    _read_batch_sizes(gm, images)
    producers = _producers(gm)
    if onnx_policy.output_name not in producers:
        raise PolicyError(f"{path}: output {onnx_policy.output_name!r} is not computed by any node")
    actions = producers[onnx_policy.output_name]
    S = onnx_policy.image_size
    card = onnx_policy.card
    example = example_inputs(plan, onnx_policy.contract)
    feats, wanted = _feature_nodes(card, plan, gm, images, state_nodes, actions, producers, str(path), example)
    single = len(images) == 1
    features, head = split_graph(
        gm,
        images[0] if single else images,
        state_nodes,
        actions,
        feats[0] if single else feats,
        str(path),
    )
    feature_map = wanted[0] if single else dict(zip(plan.cameras, wanted))
    policy = GraphPolicy(
        features,
        head,
        S,
        onnx_policy.contract,
        card=card,
        source=path,
        format="onnx",
        feature_map=feature_map,
        inputs=plan,
    )
    check_scene(policy, load_spec(None) if spec is None else spec)
    frames, st = reference_frames(S, onnx_policy.contract, spec, cameras=plan.cameras)
    ref, step = _run_reference(onnx_policy, frames, st)
    n = len(ref)
    try:
        views = onnx_policy._views(frames)
        xs = {c: torch.from_numpy(v) for c, v in views.items()}
        sv = None if st is None else torch.from_numpy(st)
        with torch.no_grad():
            got = np.concatenate(
                [
                    policy(_rows(xs, i, step, single), None if sv is None else sv[i : i + step]).numpy()
                    for i in range(0, n, step)
                ]
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
