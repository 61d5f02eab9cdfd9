"""White-box policies from policy files: a torch.fx graph split into ``features`` and ``head``.

An ``.onnx`` file converted to torch (:mod:`sim.policies.onnx_torch`) and a ``.pt2``
ExportedProgram (:mod:`sim.policies.pt2`) both arrive as one ``torch.fx.GraphModule`` computing
``actions = f(images[, state])``. The attack needs more than the function: Grad-CAM and the
saliency loss read a feature map ``A``, so the policy is ``act = head(features(x))``. The graph is
cut at one node:

* the card's ``feature_map`` names it (an ONNX tensor name, or a ``.pt2`` graph node name). The
  exporters of this project write the built-in network's own split (the backbone's last map), so
  a converted policy's Grad-CAM is the checkpoint's;
* without it, the last 4-D ``(B, C, h, w)`` map with more than one cell through which every path
  from the image to the actions passes: the output of the last convolutional block, as Grad-CAM
  is usually taken.

``features`` is the part of the graph that computes that node from the image; ``head`` the part
that computes the actions from it (and from the state). The cut is refused when some path from
the image reaches the actions around the node. :func:`reference_frames` renders the frames a
converted policy is checked on before its first use.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np
import torch
from torch import fx, nn
from torch.nn.attention import SDPBackend, sdpa_kernel

from sim.env import ReachEnv
from sim.policies.contract import (
    WRIST_CAMERA,
    InputPlan,
    PolicyContract,
    default_plan,
    state_vector,
    to_model_image,
)
from sim.policies.interface import PolicyError, prepare_images
from sim.spec import load_spec

__all__ = [
    "CHECK_FRAMES",
    "GraphPolicy",
    "split_graph",
    "pick_feature_node",
    "reference_frames",
    "max_abs_difference",
    "example_inputs",
]

# Frames a converted policy is compared on before its first use (the minimum).
CHECK_FRAMES = 32


def _inputs(gm: fx.GraphModule) -> list[fx.Node]:
    return [n for n in gm.graph.nodes if n.op == "placeholder"]


_SIZE_TARGETS = ("aten.sym_size.int", "aten.sym_size")


def _batch_size_of(n: fx.Node) -> fx.Node | None:
    """The tensor whose batch size (dim 0) node ``n`` reads (torch.export writes ``sym_size.int(x,
    0)`` for a dynamic batch), else None. Such a node carries no data (and no gradient) from ``x``."""
    if n.op == "call_function" and str(n.target) in _SIZE_TARGETS and len(n.args) == 2 and n.args[1] == 0:
        return n.args[0] if isinstance(n.args[0], fx.Node) else None
    return None


def _needed(target: fx.Node, stop, data_only: bool = False) -> set[fx.Node]:
    """Every node ``target`` is computed from (itself included), not looking past ``stop`` (a node,
    a set of nodes or None); with ``data_only``, not past a node reading only a batch size."""
    stops = stop if isinstance(stop, (set, frozenset)) else {stop}
    seen: set[fx.Node] = set()
    todo = [target]
    while todo:
        n = todo.pop()
        if n in seen:
            continue
        seen.add(n)
        if n in stops or (data_only and _batch_size_of(n) is not None):
            continue
        todo.extend(n.all_input_nodes)
    return seen


def _is_cut(node: fx.Node, image: fx.Node, actions: fx.Node) -> bool:
    """Whether every data path from ``image`` to ``actions`` passes through ``node`` (and one does);
    reading the image's batch size is not a data path."""
    return (
        image in _needed(node, None, True)
        and image not in _needed(actions, node, True)
        and node in _needed(actions, node, True)
    )


def _copy(gm: fx.GraphModule, keep: set[fx.Node], inputs: dict[fx.Node, str], out) -> fx.GraphModule:
    """A GraphModule over ``gm``'s modules and tensors computing ``out`` (a node, or a tuple of
    nodes) from new placeholders (``inputs``: the node each one replaces -> its name), with only the
    nodes in ``keep``."""
    g = fx.Graph()
    env: dict[fx.Node, fx.Node] = {}
    for old, name in inputs.items():
        env[old] = g.placeholder(name)
    first = next(iter(env.values()), None)
    for n in gm.graph.nodes:
        if n in env or n not in keep or n.op in ("placeholder", "output"):
            continue
        src = _batch_size_of(n)
        if src is not None and src not in env and first is not None:
            # the batch size of an input this part does not take: its first input's (dim 0 is the batch)
            env[n] = g.call_function(n.target, (first, 0))
            continue
        env[n] = g.node_copy(n, lambda a: env[a])
    g.output(tuple(env[o] for o in out) if isinstance(out, tuple) else env[out])
    g.lint()
    return fx.GraphModule(gm, g)


def split_graph(
    gm: fx.GraphModule,
    images,
    states,
    actions: fx.Node,
    features,
    where: str,
) -> tuple[fx.GraphModule, fx.GraphModule]:
    """``(features, head)`` cut at one feature node per image input.

    ``images``/``features``: an image placeholder and its feature node, or lists of them in the
    same order (one per camera); ``states``: the state placeholder(s) (None, a node or a list).
    ``features(x_1, ..., x_n) -> A`` (one camera) or ``(A_1, ..., A_n)``, and
    ``head(A_1, ..., A_n[, state_1, ...]) ->`` the value of ``actions``. Raises
    :class:`PolicyError` (prefixed ``where``) when a feature node is not on every path from its
    image to the actions, or is computed from another image or the state.
    """
    single = isinstance(images, fx.Node)
    images = [images] if single else list(images)
    features = [features] if isinstance(features, fx.Node) else list(features)
    states = [] if states is None else ([states] if isinstance(states, fx.Node) else list(states))
    before: set[fx.Node] = set()
    for k, (image, feature) in enumerate(zip(images, features)):
        if not _is_cut(feature, image, actions):
            raise PolicyError(
                f"{where}: feature map {feature.name!r} is not on every path from the image to the actions; "
                "name one that is in the card's feature_map"
            )
        need = _needed(feature, None, True)
        if any(s in need for s in states):
            raise PolicyError(
                f"{where}: feature map {feature.name!r} is computed from the state; it must read the image only"
            )
        others = [im.name for j, im in enumerate(images) if j != k and im in need]
        if others:
            raise PolicyError(
                f"{where}: feature map {feature.name!r} is computed from input {others[0]!r} as well; each camera's "
                "feature map must read its own image only"
            )
        before |= _needed(feature, None)
    if len(set(features)) != len(features):
        raise PolicyError(f"{where}: two cameras share the feature map {features[0].name!r}")
    names = {image: "images" if single else f"images_{k}" for k, image in enumerate(images)}
    feats = _copy(gm, before, names, features[0] if single else tuple(features))
    after = _needed(actions, set(features)) - set(features)
    head_inputs = {f: "A" if single else f"A_{k}" for k, f in enumerate(features)}
    for k, s in enumerate(states):
        head_inputs[s] = "state" if len(states) == 1 else f"state_{k}"
    head = _copy(gm, after, head_inputs, actions)
    return feats, head


def _shapes(gm: fx.GraphModule, args: tuple) -> dict[fx.Node, tuple]:
    """The shape of every tensor-valued node for one forward pass on ``args``."""
    shapes: dict[fx.Node, tuple] = {}

    class Recorder(fx.Interpreter):
        def run_node(self, n):
            out = super().run_node(n)
            if isinstance(out, torch.Tensor):
                shapes[n] = (tuple(out.shape), out.dtype)
            return out

    with torch.no_grad():
        Recorder(gm).run(*args)
    return shapes


def pick_feature_node(
    gm: fx.GraphModule, image: fx.Node, actions: fx.Node, args: tuple, where: str, exclude=()
) -> fx.Node:
    """The default feature map: the last 4-D float map ``(B, C, h, w)`` with ``h * w > 1`` through
    which every path from ``image`` to ``actions`` passes, computed from none of the nodes in
    ``exclude`` (the other images and the state; see the module docstring)."""
    batch = args[0].shape[0]
    shapes = _shapes(gm, args)
    nodes = list(gm.graph.nodes)
    exclude = set(exclude)
    for n in reversed(nodes):
        shape, dtype = shapes.get(n, ((), None))
        if len(shape) != 4 or shape[0] != batch or shape[2] * shape[3] <= 1 or not dtype.is_floating_point:
            continue
        if n is not image and _is_cut(n, image, actions) and not (exclude & _needed(n, None, True)):
            return n
    raise PolicyError(
        f"{where}: no feature map for Grad-CAM: no 4-D (B, C, h, w) tensor with more than one cell lies on every "
        f"path from the image {image.name!r} to the actions; name one in the card's feature_map"
    )


class GraphPolicy(nn.Module):
    """A white-box policy from a file: ``features``/``head`` cut out of one fx graph.

    Behaves as :class:`sim.policies.policy.VisuomotorPolicy` does for the attack. For a policy
    reading one camera: ``features(x)`` for images ``(B, 3, H, W)`` in [0, 1] gives ``A``,
    ``head(A[, state])`` gives ``(B, 6)`` or ``(B, K, 6)`` as the contract says. For several:
    ``features({camera: (B, 3, H_c, W_c)})`` gives ``{camera: A_c}`` and ``head`` takes that dict.
    Each camera's canonical frames (RGB in [0, 1], NCHW) become the model's own tensor inside
    ``features`` (:func:`sim.policies.contract.to_model_image`), so gradients reach image space.
    ``inputs`` is the :class:`sim.policies.contract.InputPlan` (which camera each input reads),
    ``source`` the file, ``format`` ``onnx`` or ``pt2``, ``feature_map`` the node(s) the graph
    was cut at, ``check`` what the conversion was checked against (ONNX: onnxruntime on rendered
    frames).
    """

    white_box = True

    def __init__(
        self,
        features: fx.GraphModule,
        head: fx.GraphModule,
        image_size: int,
        contract: PolicyContract,
        card=None,
        source: str | Path = "",
        format: str = "",
        feature_map="",
        inputs: InputPlan | None = None,
    ):
        super().__init__()
        self.features_graph = features
        self.head_graph = head
        self.image_size = int(image_size)
        self.contract = contract
        self.inputs = inputs if inputs is not None else default_plan(image_size, contract)
        self.card = card
        self.source = Path(source)
        self.format = format
        self.feature_map = feature_map
        self.check: dict = {}
        for p in self.parameters():
            p.requires_grad_(False)
        # A .pt2 keeps attention as one op (aten.scaled_dot_product_attention), which on the CPU
        # runs a fused kernel without second derivatives; Grad-CAM in the saliency term needs them,
        # so such graphs run attention through the math kernel (the same function, matmul + softmax).
        self.math_attention = any(
            "scaled_dot_product" in str(n.target) for gm in (features, head) for n in gm.graph.nodes
        )

    def _kernels(self):
        if not self.math_attention:
            return contextlib.nullcontext()
        return sdpa_kernel([SDPBackend.MATH])

    @property
    def cameras(self) -> tuple[str, ...]:
        return self.inputs.cameras

    @property
    def device(self) -> torch.device:
        for t in (*self.parameters(), *self.buffers()):
            return t.device
        return torch.device("cpu")

    def train(self, mode: bool = True):
        # A file's graph is fixed in the mode it was exported in (batch norm with running
        # statistics, no dropout): only the flag changes, nothing below is retraced.
        self.training = bool(mode)
        return self

    def _views(self, x) -> dict:
        cams = self.cameras
        if not isinstance(x, dict):
            if len(cams) != 1:
                raise PolicyError(f"images: policy reads cameras {', '.join(cams)}; pass {{camera: images}}")
            x = {cams[0]: x}
        for b in self.inputs.images:
            v = x.get(b.camera)
            if v is None:
                raise PolicyError(f"images: policy reads camera {b.camera!r}; no images of it given")
            if v.ndim != 4 or v.shape[1] != 3 or tuple(v.shape[2:]) != tuple(b.size):
                which = f" from camera {b.camera!r}" if len(cams) > 1 else ""
                raise PolicyError(
                    f"images: policy expects (B, 3, {b.size[0]}, {b.size[1]}) float in [0, 1]{which}, got "
                    f"{tuple(v.shape)}"
                )
        return x

    def features(self, x):
        """``x: (B, 3, H, W)`` float in [0, 1] (or ``{camera: x}``) -> the feature map ``A`` (or
        ``{camera: A}``)."""
        views = self._views(x)
        with self._kernels():
            out = self.features_graph(*(to_model_image(views[b.camera], b.image) for b in self.inputs.images))
        if isinstance(x, dict) or len(self.inputs.images) > 1:
            outs = out if isinstance(out, (tuple, list)) else (out,)
            return {b.camera: a for b, a in zip(self.inputs.images, outs)}
        return out

    def head(self, A, state: torch.Tensor | None = None) -> torch.Tensor:
        """Feature map(s) (and state ``(B, D)``) -> actions ``(B, n)``, or ``(B, K, n)`` for chunks
        (``n``: 6 for a TCP action, one per joint for a joint action)."""
        maps = [A[b.camera] for b in self.inputs.images] if isinstance(A, dict) else [A]
        B = maps[0].shape[0]
        D = self.contract.state_dim
        states = []
        if D:
            if state is None or tuple(state.shape) != (B, D):
                got = None if state is None else tuple(state.shape)
                raise PolicyError(f"state: policy expects a ({B}, {D}) state input, got {got}")
            st = state.to(maps[0].dtype)
            states = [st[:, b.slice[0] : b.slice[1]] for b in self.inputs.states]
        with self._kernels():
            out = self.head_graph(*maps, *states)
        if isinstance(out, (tuple, list)):
            out = out[0]
        K, n = self.contract.action.chunk, self.contract.action_dim  # n: 6 for a TCP action, one per joint
        if K == 1 and tuple(out.shape) in ((B, 1, n), (B, n)):
            return out.reshape(B, n)
        if K > 1 and tuple(out.shape) in ((B, K, n), (B, n * K)):
            return out.reshape(B, K, n)
        want = f"({B}, {n})" if K == 1 else f"({B}, {K}, {n}) or ({B}, {n * K})"
        raise PolicyError(
            f"{self.source}: actions: the contract ({self.contract.describe()}) needs outputs of shape {want}, "
            f"got {tuple(out.shape)}"
        )

    def forward(self, x, state: torch.Tensor | None = None) -> torch.Tensor:
        return self.head(self.features(x), state)

    def _tensor(self, images, size) -> torch.Tensor:
        if isinstance(images, torch.Tensor):
            x = images.to(self.device, torch.float32)
            return x.permute(0, 3, 1, 2) / 255.0 if images.dtype == torch.uint8 else x
        return torch.from_numpy(prepare_images(images, size)).to(self.device)

    @torch.no_grad()
    def act(self, images, state=None) -> np.ndarray:
        """Actions ``(B, 6)`` (or ``(B, K, 6)``) float32 for env images ``(B, H, W, 3)`` uint8 or
        ``(B, 3, H, W)`` floats (one camera), or ``{camera: images}``, and the ``(B, D)`` state when
        the contract reads one."""
        if isinstance(images, dict):
            x = {b.camera: self._tensor(images[b.camera], b.size) for b in self.inputs.images if b.camera in images}
        else:
            x = self._tensor(images, self.inputs.images[0].size)
        st = None if state is None else torch.as_tensor(np.asarray(state, dtype=np.float32), device=self.device)
        return self(x, st).cpu().numpy().astype(np.float32)

    def __repr__(self) -> str:
        cams = "" if self.cameras == (WRIST_CAMERA,) else f", cameras={list(self.cameras)}"
        return f"GraphPolicy({str(self.source)!r}, format={self.format!r}, image_size={self.image_size}{cams})"


def reference_frames(image_size: int, contract: PolicyContract, spec=None, n: int = CHECK_FRAMES, cameras=None):
    """``(images, state (n, D) float32 or None)``: frames of ``spec`` (default: the built-in scene)
    rendered by the env (the wrist camera at the policy's size ``image_size``), from fixed initial
    configurations and the expert's first steps toward the goal (near and far views); a joint-space
    ``contract`` on the scene's arm (the state reads its joint positions). ``images``
    is the wrist camera's ``(n, S, S, 3)`` uint8 when ``cameras`` is None or ``("wrist",)``, else
    ``{camera: (n, H_c, W_c, 3) uint8}`` of each camera named (one that ``spec`` lacks is one line)."""
    spec = load_spec(None) if spec is None else spec
    cams = (WRIST_CAMERA,) if cameras is None else tuple(cameras)
    envs = 8
    env = ReachEnv(
        spec,
        num_envs=envs,
        policy_image_size=image_size if WRIST_CAMERA in cams else None,
        seed=0,
        cameras=cams,
        control=contract.control,
    )
    try:
        images, poses, joints = [], [], []
        env.reset(seed=0)
        while True:
            images.append(env.images())
            poses.append(env.T_world_tcp)
            joints.append(env.q)
            if sum(len(i[cams[0]]) for i in images) >= n:
                break
            env.step(env.expert_actions())
    finally:
        env.close()
    frames = {c: np.concatenate([i[c] for i in images])[:n] for c in cams}
    q = None if joints[0] is None else np.concatenate(joints)[:n]
    state = state_vector(contract, np.concatenate(poses)[:n], spec.gripper.opening_m, q)
    return (frames[WRIST_CAMERA] if cams == (WRIST_CAMERA,) else frames), state


def example_inputs(plan, contract, batch: int = 2) -> tuple:
    """Random model inputs of ``plan`` (in the model's input order), as the graph takes them."""
    out = {}
    for b in plan.images:
        x = torch.rand(batch, 3, *b.size)
        out[b.name] = to_model_image(x, b.image)
    for s in plan.states:
        out[s.name] = torch.zeros(batch, s.slice[1] - s.slice[0])
    return tuple(out[n] for n in plan.order) if plan.order else tuple(out.values())


def max_abs_difference(a: np.ndarray, b: np.ndarray) -> float:
    """``max |a - b|`` (inf when either holds a non-finite value the other does not share)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape:
        return float("inf")
    same = (a == b) | (np.isnan(a) & np.isnan(b))
    d = np.where(same, 0.0, np.abs(a - b))
    return float(np.nan_to_num(d, nan=np.inf).max(initial=0.0))
