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

from pathlib import Path

import numpy as np
import torch
from torch import fx, nn

from sim.env import ReachEnv
from sim.policies.contract import PolicyContract, state_vector
from sim.policies.interface import PolicyError, prepare_images
from sim.spec import load_spec

__all__ = [
    "CHECK_FRAMES",
    "GraphPolicy",
    "split_graph",
    "pick_feature_node",
    "reference_frames",
    "max_abs_difference",
]

# Frames a converted policy is compared on before its first use (the minimum).
CHECK_FRAMES = 32


def _inputs(gm: fx.GraphModule) -> list[fx.Node]:
    return [n for n in gm.graph.nodes if n.op == "placeholder"]


def _needed(target: fx.Node, stop: fx.Node | None) -> set[fx.Node]:
    """Every node ``target`` is computed from (itself included), not looking past ``stop``."""
    seen: set[fx.Node] = set()
    todo = [target]
    while todo:
        n = todo.pop()
        if n in seen:
            continue
        seen.add(n)
        if n is stop:
            continue
        todo.extend(n.all_input_nodes)
    return seen


def _is_cut(node: fx.Node, image: fx.Node, actions: fx.Node) -> bool:
    """Whether every path from ``image`` to ``actions`` passes through ``node`` (and one does)."""
    return image in _needed(node, None) and image not in _needed(actions, node) and node in _needed(actions, node)


def _copy(gm: fx.GraphModule, keep: set[fx.Node], inputs: dict[fx.Node, str], out: fx.Node) -> fx.GraphModule:
    """A GraphModule over ``gm``'s modules and tensors computing ``out`` from new placeholders
    (``inputs``: the node each one replaces -> its name), with only the nodes in ``keep``."""
    g = fx.Graph()
    env: dict[fx.Node, fx.Node] = {}
    for old, name in inputs.items():
        env[old] = g.placeholder(name)
    for n in gm.graph.nodes:
        if n in env or n not in keep or n.op in ("placeholder", "output"):
            continue
        env[n] = g.node_copy(n, lambda a: env[a])
    g.output(env[out])
    g.lint()
    return fx.GraphModule(gm, g)


def split_graph(
    gm: fx.GraphModule, image: fx.Node, state: fx.Node | None, actions: fx.Node, feature: fx.Node, where: str
) -> tuple[fx.GraphModule, fx.GraphModule]:
    """``(features, head)``: ``features(x) -> A`` (``feature``'s value) and ``head(A[, state]) ->``
    the value of ``actions``. Raises :class:`PolicyError` (prefixed ``where``) when ``feature`` is
    not on every path from ``image`` to ``actions``, or needs the state."""
    if not _is_cut(feature, image, actions):
        raise PolicyError(
            f"{where}: feature map {feature.name!r} is not on every path from the image to the actions; "
            "name one that is in the card's feature_map"
        )
    before = _needed(feature, None)
    if state is not None and state in before:
        raise PolicyError(
            f"{where}: feature map {feature.name!r} is computed from the state; it must read the image only"
        )
    features = _copy(gm, before, {image: "images"}, feature)
    after = _needed(actions, feature) - {feature}
    head_inputs = {feature: "A"}
    if state is not None:
        head_inputs[state] = "state"
    head = _copy(gm, after, head_inputs, actions)
    return features, head


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


def pick_feature_node(gm: fx.GraphModule, image: fx.Node, actions: fx.Node, args: tuple, where: str) -> fx.Node:
    """The default feature map: the last 4-D float map ``(B, C, h, w)`` with ``h * w > 1`` through
    which every path from ``image`` to ``actions`` passes (see the module docstring)."""
    batch = args[0].shape[0]
    shapes = _shapes(gm, args)
    nodes = list(gm.graph.nodes)
    for n in reversed(nodes):
        shape, dtype = shapes.get(n, ((), None))
        if len(shape) != 4 or shape[0] != batch or shape[2] * shape[3] <= 1 or not dtype.is_floating_point:
            continue
        if n is not image and _is_cut(n, image, actions):
            return n
    raise PolicyError(
        f"{where}: no feature map for Grad-CAM: no 4-D (B, C, h, w) tensor with more than one cell lies on every "
        "path from the image to the actions; name one in the card's feature_map"
    )


class GraphPolicy(nn.Module):
    """A white-box policy from a file: ``features``/``head`` cut out of one fx graph.

    Behaves as :class:`sim.policies.policy.VisuomotorPolicy` does for the attack: ``features(x)``
    for images ``(B, 3, S, S)`` in [0, 1], ``head(A[, state])`` giving ``(B, 6)`` or ``(B, K, 6)``
    as the contract says, ``act`` for rollouts. ``source`` is the file, ``format`` ``onnx`` or
    ``pt2``, ``feature_map`` the node the graph was cut at, ``check`` what the conversion was
    checked against (ONNX: onnxruntime on rendered frames).
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
        feature_map: str = "",
    ):
        super().__init__()
        self.features_graph = features
        self.head_graph = head
        self.image_size = int(image_size)
        self.contract = contract
        self.card = card
        self.source = Path(source)
        self.format = format
        self.feature_map = feature_map
        self.check: dict = {}
        for p in self.parameters():
            p.requires_grad_(False)

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

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """``x: (B, 3, S, S)`` float in [0, 1] -> the feature map ``A``."""
        if x.ndim != 4 or x.shape[1] != 3 or tuple(x.shape[2:]) != (self.image_size, self.image_size):
            raise PolicyError(
                f"images: policy expects (B, 3, {self.image_size}, {self.image_size}) float in [0, 1], got "
                f"{tuple(x.shape)}"
            )
        return self.features_graph(x)

    def head(self, A: torch.Tensor, state: torch.Tensor | None = None) -> torch.Tensor:
        """Feature map (and state ``(B, D)``) -> actions ``(B, 6)``, or ``(B, K, 6)`` for chunks."""
        D = self.contract.state_dim
        if D:
            if state is None or tuple(state.shape) != (A.shape[0], D):
                got = None if state is None else tuple(state.shape)
                raise PolicyError(f"state: policy expects a ({A.shape[0]}, {D}) state input, got {got}")
            out = self.head_graph(A, state.to(A.dtype))
        else:
            out = self.head_graph(A)
        if isinstance(out, (tuple, list)):
            out = out[0]
        K, B = self.contract.action.chunk, A.shape[0]
        if K == 1 and tuple(out.shape) in ((B, 1, 6), (B, 6)):
            return out.reshape(B, 6)
        if K > 1 and tuple(out.shape) in ((B, K, 6), (B, 6 * K)):
            return out.reshape(B, K, 6)
        want = f"({B}, 6)" if K == 1 else f"({B}, {K}, 6) or ({B}, {6 * K})"
        raise PolicyError(
            f"{self.source}: actions: the contract ({self.contract.describe()}) needs outputs of shape {want}, "
            f"got {tuple(out.shape)}"
        )

    def forward(self, x: torch.Tensor, state: torch.Tensor | None = None) -> torch.Tensor:
        return self.head(self.features(x), state)

    @torch.no_grad()
    def act(self, images, state=None) -> np.ndarray:
        """Actions ``(B, 6)`` (or ``(B, K, 6)``) float32 for env images ``(B, S, S, 3)`` uint8 or
        ``(B, 3, S, S)`` floats, and the ``(B, D)`` state when the contract reads one."""
        if isinstance(images, torch.Tensor):
            x = images.to(self.device, torch.float32)
            if images.dtype == torch.uint8:
                x = x.permute(0, 3, 1, 2) / 255.0
        else:
            x = torch.from_numpy(prepare_images(images, self.image_size)).to(self.device)
        st = None if state is None else torch.as_tensor(np.asarray(state, dtype=np.float32), device=self.device)
        return self(x, st).cpu().numpy().astype(np.float32)

    def __repr__(self) -> str:
        return f"GraphPolicy({str(self.source)!r}, format={self.format!r}, image_size={self.image_size})"


def reference_frames(image_size: int, contract: PolicyContract, spec=None, n: int = CHECK_FRAMES):
    """``(images (n, S, S, 3) uint8, state (n, D) float32 or None)``: wrist-camera frames of
    ``spec`` (default: the built-in scene) rendered by the env at the policy's size, from fixed
    initial configurations and the expert's first steps toward the goal (near and far views)."""
    spec = load_spec(None) if spec is None else spec
    envs = 8
    env = ReachEnv(spec, num_envs=envs, policy_image_size=image_size, seed=0)
    try:
        images, poses = [], []
        obs, _ = env.reset(seed=0)
        while True:
            images.append(obs)
            poses.append(env.T_world_tcp)
            if sum(len(i) for i in images) >= n:
                break
            obs, *_ = env.step(env.expert_actions())
    finally:
        env.close()
    images = np.concatenate(images)[:n]
    state = state_vector(contract, np.concatenate(poses)[:n], spec.gripper.opening_m)
    return images, state


def max_abs_difference(a: np.ndarray, b: np.ndarray) -> float:
    """``max |a - b|`` (inf when either holds a non-finite value the other does not share)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape:
        return float("inf")
    same = (a == b) | (np.isnan(a) & np.isnan(b))
    d = np.where(same, 0.0, np.abs(a - b))
    return float(np.nan_to_num(d, nan=np.inf).max(initial=0.0))
