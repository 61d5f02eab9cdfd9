"""``.pt2`` files (torch.export ExportedPrograms) as white-box policies, and their export.

The file is the archive ``torch.export.save`` writes; the policy card travels inside it as the
extra file ``advobj_policy_card.json`` (``extra_files`` of ``torch.export.save``), so an exported
policy is one self-describing file, as an ONNX file with its metadata is. A one-image policy with
a ``(B, 6)`` ``delta_tcp`` output needs no card.

What loading guarantees. ``torch.export.load`` is not safe on an untrusted file as it stands
(torch 2.13, ``torch/export/pt2_archive/_package.py`` and ``torch/_export/serde/serialize.py``):
it unpickles weights and constants marked ``use_pickle`` (``torch.load(weights_only=False)``,
``pickle.loads``), loads TorchScript custom objects, retries the example inputs with
``weights_only=False`` when the safe load fails, loads AOTInductor shared libraries, parses symbolic
shapes with ``sympy.sympify`` (Python ``eval``), resolves a node's target as any attribute path
under ``torch``, ``math`` or ``operator`` (``torch.hub.load`` included), writes parameter names
into the Python source it generates for the module, and runs the archive's guard code with
``exec`` when a module is made with guards. So :func:`load_pt2` reads the file into memory once
and checks the archive before torch sees a byte of it; it refuses:

* an archive that is not exactly what ``torch.export.save`` of a plain model writes: one model,
  stored (uncompressed) entries, no AOTInductor code, no legacy pickled weights;
* any weight or constant stored as a pickle, any custom or opaque object, any subgraph;
* example inputs that ``torch.load(weights_only=True)`` cannot read;
* a node target other than an ATen operator (``torch.ops.aten.*``; ``from_file``, ``save`` and
  ``_print`` excluded) or Python's arithmetic on sizes (``operator``, ``math``, ``torch.sym_*``);
* a symbolic shape outside sympy's own constructors of integers and symbols;
* a name or parameter path that is not letters, digits, ``_`` and ``.``;
* an archive or schema version this torch does not read ("exported by an incompatible torch").

It then calls ``torch.export.load`` on those bytes and ``ExportedProgram.module(check_guards=False)``,
so the guard code is never run. What runs afterwards is ATen kernels on tensors: no Python from
the file is imported or executed. What is not guaranteed: that the graph computes what its author
says (the card is the author's word), or memory and time bounds beyond the file-size cap.
"""

from __future__ import annotations

import io
import json
import logging
import re
import zipfile
from pathlib import Path

import torch
import torch.utils._pytree as pytree
from torch._export.serde.schema import SCHEMA_VERSION
from torch.export.pt2_archive import constants as pt2c

from sim.policies.card import PolicyCard
from sim.policies.contract import WRIST_CAMERA, bind_inputs, policy_cameras, policy_contract
from sim.policies.graph_policy import GraphPolicy, example_inputs, pick_feature_node, split_graph
from sim.policies.interface import PolicyError
from sim.policies.policy import file_inputs

__all__ = ["CARD_ENTRY", "MAX_PT2_BYTES", "export_pt2", "check_archive", "load_pt2"]

CARD_ENTRY = "advobj_policy_card.json"
MAX_PT2_BYTES = 1 << 30  # a visuomotor policy file; larger ones are refused before they are read
_MAX_JSON_BYTES = 64 << 20
_SAFE = re.compile(r"^[A-Za-z0-9_.\-]*$")
_ROOT = re.compile(r"^[A-Za-z0-9_.\-]+$")
_ENTRY = re.compile(
    r"^(archive_format|archive_version|byteorder|\.data/version|\.data/serialization_id|models/model\.json|"
    r"data/weights/model_weights_config\.json|data/weights/weight_\d+|data/constants/model_constants_config\.json|"
    r"data/constants/tensor_\d+|data/sample_inputs/model\.pt|extra/[A-Za-z0-9_.\-]+)$"
)
_ATEN = re.compile(r"^torch\.ops\.aten\.([A-Za-z_][A-Za-z0-9_]*)\.([A-Za-z_][A-Za-z0-9_]*)$")
_ATEN_DENIED = frozenset({"from_file", "save", "_print"})
_PY_TARGETS = frozenset(
    {f"_operator.{n}" for n in ("getitem", "add", "sub", "mul", "floordiv", "truediv", "mod", "pow", "neg", "pos")}
    | {f"_operator.{n}" for n in ("eq", "ne", "lt", "le", "gt", "ge", "and_", "or_", "not_", "abs")}
    | {f"math.{n}" for n in ("ceil", "floor", "trunc", "sqrt")}
    | {f"torch.{n}" for n in ("sym_float", "sym_int", "sym_max", "sym_min", "sym_not", "sym_ite", "sym_sqrt")}
)
_DENIED_KEYS = frozenset({"as_graph", "as_operator", "as_custom_obj"})
# what torch's deserializer hands to sympy.sympify: srepr-style constructors over symbols and numbers
_SYMPY_NAMES = frozenset(
    {"Symbol", "Integer", "Add", "Mul", "Pow", "Rational", "Max", "Min", "Mod", "Abs", "Eq", "Ne", "Lt", "Le", "Gt"}
    | {"Ge", "And", "Or", "Not", "True", "False", "positive", "integer", "nonnegative", "real", "finite"}
    | {"FloorDiv", "ModularIndexing", "Where", "PythonMod", "CleanDiv", "CeilToInt", "FloorToInt", "CeilDiv"}
    | {"IntTrueDiv", "PowByNatural", "TruncToInt", "Identity", "oo", "zoo"}
)
_EXPR_TOKEN = re.compile(
    r"\s*(?:(?P<name>[A-Za-z_][A-Za-z0-9_]*)|(?P<str>'[A-Za-z_][A-Za-z0-9_]*')|(?P<num>\d+(?:\.\d+)?)|"
    r"(?P<op>\*\*|//|[=!<>]=|[-+*/%(),=<>]))"
)
_SYMBOL = re.compile(r"^[a-z]+\d+$")


def _safe_expr(expr: str) -> bool:
    pos = 0
    while pos < len(expr):
        m = _EXPR_TOKEN.match(expr, pos)
        if m is None or m.end() == pos:
            return expr[pos:].strip() == ""
        name = m.group("name")
        if name is not None and name not in _SYMPY_NAMES and not _SYMBOL.match(name):
            return False
        pos = m.end()
    return True


def _check_target(target, where: str) -> None:
    if not isinstance(target, str):
        raise PolicyError(f"{where}: a node's target is not a name")
    m = _ATEN.match(target)
    if m is not None:
        op, overload = m.groups()
        if op in _ATEN_DENIED:
            raise PolicyError(f"{where}: operator aten.{op} reads or writes outside the tensors; refused")
        packet = getattr(torch.ops.aten, op, None) if not op.startswith("__") else None
        if packet is None or not hasattr(packet, overload):
            raise PolicyError(f"{where}: operator {target} is not an ATen operator of this torch")
        return
    if target not in _PY_TARGETS:
        shown = target if len(target) <= 80 else target[:77] + "..."
        raise PolicyError(
            f"{where}: node target {shown!r} is not an ATen operator; only torch.ops.aten.* and arithmetic on sizes "
            "are run (no custom operators, higher-order operators or Python callables)"
        )


def _walk(o, where: str, key: str = "") -> None:
    """Check every value of the model's JSON that reaches code (see the module docstring)."""
    if isinstance(o, dict):
        for k, v in o.items():
            if not isinstance(k, str) or not _SAFE.match(k):
                raise PolicyError(f"{where}: the graph holds a name that is not letters, digits, '_', '.' or '-'")
            if k in _DENIED_KEYS:
                raise PolicyError(f"{where}: the graph holds {k[3:]} arguments (subgraphs, operators or objects)")
            if k in ("metadata", "in_spec", "out_spec", "guards_code", "torch_version", "as_string", "as_strings"):
                # not run: debug metadata, pytree specs (registered types only), guard code (never made into a
                # function: check_guards=False), literal strings (quoted by repr in the generated code)
                continue
            if k == "target":
                _check_target(v, where)
            elif k == "expr_str":
                if not isinstance(v, str) or not _safe_expr(v):
                    shown = str(v)[:60]
                    raise PolicyError(f"{where}: symbolic shape {shown!r} is not an expression of sizes; refused")
            elif k == "custom_obj_values" and v:
                raise PolicyError(f"{where}: the graph holds custom objects; refused")
            else:
                _walk(v, where, k)
    elif isinstance(o, list):
        for v in o:
            _walk(v, where, key)
    elif isinstance(o, str) and not _SAFE.match(o):
        raise PolicyError(f"{where}: the graph holds a name ({o[:40]!r}) that is not letters, digits, '_', '.' or '-'")


def _json(z: zipfile.ZipFile, name: str, where: str):
    if z.getinfo(name).file_size > _MAX_JSON_BYTES:
        raise PolicyError(f"{where}: {name} is over {_MAX_JSON_BYTES >> 20} MiB")
    try:
        return json.loads(z.read(name))
    except (ValueError, RecursionError, UnicodeDecodeError) as err:
        raise PolicyError(f"{where}: {name} is not JSON ({str(err).splitlines()[0][:100]})") from None


def check_archive(data: bytes, where: str) -> str | None:
    """Check the bytes of a ``.pt2`` file as the module docstring says; returns its card's JSON
    (``None`` if it has none). Raises :class:`PolicyError` naming ``where``."""
    try:
        z = zipfile.ZipFile(io.BytesIO(data))
        infos = z.infolist()
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as err:
        raise PolicyError(f"{where}: not a torch.export archive (.pt2 is a zip file: {err})") from None
    if not infos:
        raise PolicyError(f"{where}: not a torch.export archive (empty zip)")
    root = infos[0].filename.split("/", 1)[0]
    files: dict[str, zipfile.ZipInfo] = {}
    for info in infos:
        name = info.filename
        if not _ROOT.match(root) or not name.startswith(root + "/"):
            raise PolicyError(f"{where}: archive entry {name[:80]!r} is outside the archive's folder")
        rel = name[len(root) + 1 :]
        if info.is_dir():
            continue
        if rel.startswith(pt2c.AOTINDUCTOR_DIR):
            raise PolicyError(f"{where}: holds AOTInductor compiled code ({rel[:60]}); only exported programs load")
        if not _ENTRY.match(rel):
            raise PolicyError(
                f"{where}: unexpected archive entry {rel[:80]!r} (pickled weights, custom objects and other models "
                "are not loaded)"
            )
        if info.compress_type != zipfile.ZIP_STORED:
            raise PolicyError(f"{where}: archive entry {rel!r} is compressed; torch.export.save stores entries")
        files[rel] = info
    need = ("archive_format", "archive_version", "models/model.json", "data/weights/model_weights_config.json")
    need += ("data/constants/model_constants_config.json", "data/sample_inputs/model.pt")
    missing = [n for n in need if n not in files]
    if missing:
        raise PolicyError(f"{where}: not a complete torch.export archive (no {missing[0]}; truncated or not a .pt2)")

    def read(rel: str) -> bytes:
        try:
            return z.read(files[rel].filename)
        except (zipfile.BadZipFile, OSError, ValueError, EOFError) as err:
            raise PolicyError(f"{where}: archive entry {rel} is unreadable ({err}); truncated?") from None

    fmt = read("archive_format").decode("utf-8", "replace").strip()
    version = read("archive_version").decode("utf-8", "replace").strip()
    model = _json(z, files["models/model.json"].filename, where)
    if not isinstance(model, dict):
        raise PolicyError(f"{where}: models/model.json is not an exported program")
    made_by = str(model.get("torch_version", "unknown torch"))[:40]
    schema = model.get("schema_version") if isinstance(model.get("schema_version"), dict) else {}
    if (
        fmt != pt2c.ARCHIVE_FORMAT_VALUE
        or version != pt2c.ARCHIVE_VERSION_VALUE
        or schema.get("major") != SCHEMA_VERSION[0]
    ):
        raise PolicyError(
            f"{where}: exported by an incompatible torch ({made_by!r}: archive {fmt!r} version {version!r}, schema "
            f"{schema.get('major')}.{schema.get('minor')}); this torch {torch.__version__} reads archive version "
            f"{pt2c.ARCHIVE_VERSION_VALUE}, schema {SCHEMA_VERSION[0]}.x: export it again with this torch"
        )
    for cfg_name, folder, prefix in (
        ("data/weights/model_weights_config.json", pt2c.WEIGHTS_DIR, pt2c.WEIGHT_FILENAME_PREFIX),
        ("data/constants/model_constants_config.json", pt2c.CONSTANTS_DIR, pt2c.TENSOR_CONSTANT_FILENAME_PREFIX),
    ):
        cfg = _json(z, files[cfg_name].filename, where)
        entries = cfg.get("config") if isinstance(cfg, dict) else None
        if not isinstance(entries, dict):
            raise PolicyError(f"{where}: {cfg_name} is not a payload config")
        for fqn, meta in entries.items():
            if not isinstance(meta, dict) or meta.get("use_pickle") is not False:
                raise PolicyError(f"{where}: {fqn[:60]!r} is stored as a pickle; pickles are never loaded")
            path_name = meta.get("path_name")
            if not isinstance(path_name, str) or not re.fullmatch(prefix + r"\d+", path_name):
                raise PolicyError(f"{where}: {fqn[:60]!r} is not a plain tensor ({str(path_name)[:40]!r})")
            if folder + path_name not in files:
                raise PolicyError(f"{where}: {fqn[:60]!r}: its data {path_name} is missing; truncated?")
            _walk({"fqn": fqn, "meta": meta}, where)
    _walk(model, where)
    try:
        torch.load(io.BytesIO(read("data/sample_inputs/model.pt")), weights_only=True)
    except Exception as err:  # noqa: BLE001 - torch.load's safe unpickler raises many types
        raise PolicyError(
            f"{where}: its example inputs are not plain tensors ({type(err).__name__}); they would be unpickled"
        ) from None
    card = files.get(f"{pt2c.EXTRA_DIR}{CARD_ENTRY}")
    return None if card is None else read(card.filename[len(root) + 1 :]).decode("utf-8", "replace")


def export_pt2(policy, path: str | Path, card=None, max_batch: int = 1024) -> Path:
    """Export torch ``policy`` to ``path`` with ``torch.export`` (dynamic batch) and ``card`` inside.

    The inputs are those of :func:`sim.policies.onnx_policy.export_onnx`: ``images (B, 3, S, S)``
    in [0, 1] and, for a policy that reads state, ``state (B, D)``; the built-in network on several
    cameras takes ``{camera: (B, 3, H_c, W_c)}`` (each input named by its camera). For the built-in
    network the card names the backbone's last map as ``feature_map`` (where Grad-CAM reads; one per
    camera when it reads several) and binds each input to its camera. Stack traces
    (source paths of the exporting machine) are dropped from the graph's metadata.
    """
    if card is None and not policy_contract(policy).is_default:
        raise PolicyError(
            f"card: a policy with the contract ({policy_contract(policy).describe()}) needs its card in the file"
        )
    path = Path(path)
    cameras = policy_cameras(policy)
    if cameras != (WRIST_CAMERA,) and card is None:
        raise PolicyError(f"card: a policy reading cameras {', '.join(cameras)} needs its card in the file")
    path.parent.mkdir(parents=True, exist_ok=True)
    s = policy.image_size
    D = policy_contract(policy).state_dim
    was_training = policy.training
    policy.eval()
    try:
        batch = torch.export.Dim("batch", min=1, max=max_batch)
        args = (torch.rand(2, 3, s, s, device=policy.device),) + (
            (torch.rand(2, D, device=policy.device),) if D else ()
        )
        dyn = tuple({0: batch} for _ in args)
        if cameras != (WRIST_CAMERA,):  # several cameras: {camera: images}, each input named by its camera
            views = {b.camera: torch.rand(2, 3, *b.size, device=policy.device) for b in policy.inputs.images}
            args = (views,) + args[1:]
            dyn = ({k: {0: batch} for k in views},) + dyn[1:]
        ep = torch.export.export(policy, args, dynamic_shapes=dyn)
    finally:
        policy.train(was_training)
    for node in ep.graph.nodes:
        node.meta.pop("stack_trace", None)
    extra = {}
    if card is not None:
        if card.feature_map is None and isinstance(getattr(policy, "reduce", None), torch.nn.Module):
            card = card.model_copy(update={"feature_map": _backbone_output(ep, path, cameras)})
        if cameras != (WRIST_CAMERA,) and not card.inputs:
            card = card.model_copy(update={"inputs": file_inputs(policy.inputs)})
        extra[CARD_ENTRY] = card.model_dump_json()
    tmp = path.with_name(path.name + ".tmp.pt2")
    torch.export.save(ep, str(tmp), extra_files=extra)
    tmp.replace(path)
    return path


def _backbone_output(ep, path, cameras=(WRIST_CAMERA,)) -> str | dict[str, str]:
    """The node the built-in network's backbone ends in: the input of its head's first
    convolution (module ``reduce.0``); reading several cameras, ``{camera: node}`` (the head
    reduces each camera's map in camera order)."""
    found = []
    for node in ep.graph.nodes:
        stack = node.meta.get("nn_module_stack") or {}
        paths = [v[0] for v in stack.values()]
        if node.op == "call_function" and paths and paths[-1] == "reduce.0" and node.args:
            found.append(node.args[0].name)
    if not found or len(found) < len(cameras):
        raise PolicyError(f"{path}: the exported graph has no head convolution (reduce.0) to take the feature map from")
    return found[0] if len(cameras) == 1 else dict(zip(cameras, found))


def _card(text: str | None, where: str):
    if text is None:
        return None
    try:
        return PolicyCard.model_validate(json.loads(text))
    except Exception as err:  # noqa: BLE001 - pydantic and json name the field
        raise PolicyError(f"{where}: {CARD_ENTRY}: not a valid policy card ({str(err).splitlines()[0]})") from None


def _leaf_names(spec, flat_names: list[str]) -> list[str]:
    """The name of each flat input (output) of a program: its key when it sits in a dict (LeRobot's
    ``{"observation.images.wrist": ...}``), else the program's own name for it."""
    try:
        tree = pytree.tree_unflatten(list(range(len(flat_names))), spec)
        leaves = pytree.tree_flatten_with_path(tree)[0]
    except Exception:  # noqa: BLE001 - a spec that does not describe the flat values: the program's names
        return list(flat_names)
    names = list(flat_names)
    for path, k in leaves:
        keys = [e.key for e in path if isinstance(e, pytree.MappingKey)]
        if isinstance(k, int) and 0 <= k < len(names) and keys and isinstance(keys[-1], str):
            names[k] = keys[-1]
    return names


def load_pt2(path: str | Path, device="cpu") -> GraphPolicy:
    """The white-box :class:`GraphPolicy` of the ``.pt2`` file ``path`` (checked as the module
    docstring says). Raises :class:`PolicyError` in one line naming the file."""
    p = Path(path)
    where = str(p)
    if not p.is_file():
        raise PolicyError(f"{where}: no such .pt2 file")
    size = p.stat().st_size
    if size > MAX_PT2_BYTES:
        raise PolicyError(f"{where}: {size >> 20} MiB is over the {MAX_PT2_BYTES >> 20} MiB a policy file may have")
    data = p.read_bytes()
    card = _card(check_archive(data, where), where)
    log = logging.getLogger("torch.export")
    level = log.level
    log.setLevel(logging.CRITICAL)  # torch logs a traceback before its legacy fallback; the error is ours
    try:
        ep = torch.export.load(io.BytesIO(data))
        gm = ep.module(check_guards=False)
    except PolicyError:
        raise
    except Exception as err:  # noqa: BLE001 - torch's deserializer raises many types
        msg = " ".join(str(err).split())[:200]
        raise PolicyError(f"{where}: torch cannot load it ({type(err).__name__}: {msg})") from None
    finally:
        log.setLevel(level)
    users = list(ep.graph_signature.user_inputs)
    metas = {n.name: n.meta.get("val") for n in ep.graph.nodes if n.op == "placeholder"}
    if not users or len(ep.graph_signature.user_outputs) < 1:
        raise PolicyError(f"{where}: a policy takes an image (and optionally a state) and returns actions")
    in_names = _leaf_names(ep.call_spec.in_spec, users)
    out_names = _leaf_names(ep.call_spec.out_spec, list(ep.graph_signature.user_outputs))

    class _Carrier:  # policy_contract reads a card attribute
        pass

    carrier = _Carrier()
    carrier.card = card
    contract = policy_contract(carrier)
    plan = bind_inputs(
        None if card is None else card.inputs,
        [(name, tuple(getattr(metas.get(u), "shape", ()))) for name, u in zip(in_names, users)],
        out_names,
        contract,
        None if card is None else card.action_output,
        f"{where}: ",
    )
    if card is not None and (why := card.image_size_mismatch(plan, f"{where}: ")):
        raise PolicyError(why)
    wrist = [b for b in plan.images if b.camera == WRIST_CAMERA]
    S = int((wrist or list(plan.images))[0].size[0])
    nodes = {n.name: n for n in gm.graph.nodes}
    placeholders = dict(zip(in_names, (n for n in gm.graph.nodes if n.op == "placeholder")))
    images = [placeholders[b.name] for b in plan.images]
    state_nodes = [placeholders[st.name] for st in plan.states]
    out_node = next(n for n in gm.graph.nodes if n.op == "output")
    flat = out_node.args[0]
    if isinstance(flat, (tuple, list)) and len(flat) == len(out_names):
        flat = flat[out_names.index(plan.output)]
    while isinstance(flat, (tuple, list)):
        flat = flat[0]
    if not isinstance(flat, torch.fx.Node):
        raise PolicyError(f"{where}: the program's output {plan.output!r} is not a tensor")
    actions = flat
    example = example_inputs(plan, contract)
    single = len(images) == 1
    try:
        wanted = card.feature_map if card is not None else None
        if isinstance(wanted, str):
            if not single:
                raise PolicyError(
                    f"{where}: card feature_map: this policy reads cameras {', '.join(plan.cameras)}; name one map "
                    "per camera ({camera: name})"
                )
            wanted = {plan.cameras[0]: wanted}
        wanted = dict(wanted or {})
        for cam in wanted:
            if cam not in plan.cameras:
                raise PolicyError(f"{where}: card feature_map: {cam!r} is not a camera the policy reads")
        feats = []
        for b, image in zip(plan.images, images):
            name = wanted.get(b.camera)
            if name:
                if name not in nodes:
                    raise PolicyError(f"{where}: card feature_map: {name!r} is not a node of the program")
                feats.append(nodes[name])
            else:
                others = set(images) - {image} | set(state_nodes)
                feats.append(pick_feature_node(gm, image, actions, example, where, exclude=others))
        features, head = split_graph(
            gm, images[0] if single else images, state_nodes, actions, feats[0] if single else feats, where
        )
        feature_map = feats[0].name if single else {b.camera: f.name for b, f in zip(plan.images, feats)}
        policy = GraphPolicy(
            features, head, S, contract, card=card, source=p, format="pt2", feature_map=feature_map, inputs=plan
        )
        views = {b.camera: torch.rand(2, 3, *b.size) for b in plan.images}
        st = torch.zeros(2, contract.state_dim) if contract.state_dim else None
        with torch.no_grad():
            policy(views if not single else views[plan.cameras[0]], st)
    except PolicyError:
        raise
    except Exception as err:  # noqa: BLE001 - the program failing on a plain input
        msg = " ".join(str(err).split())[:200]
        raise PolicyError(
            f"{where}: the program fails on a batch of 2 plain inputs ({type(err).__name__}: {msg})"
        ) from None
    policy.check = {"reference": "none (the exported program is the policy)", "format": "pt2"}
    return policy.to(torch.device(device))
