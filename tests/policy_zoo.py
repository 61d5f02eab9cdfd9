"""Tiny policies for every combination of the policy contract, white-box (torch) and black-box (ONNX).

Built here, never downloaded: a 32 px small_cnn whose head is set so that its actions are
plausible for the contract (absolute targets near the TCP, deltas inside [-1, 1]).
"""

from __future__ import annotations

import itertools

import torch

from sim.policies.card import ActionScaling, PolicyCard
from sim.policies.contract import ActionContract, PolicyContract
from sim.policies.policy import PolicyArch, VisuomotorPolicy

STATES = [(), ("tcp_pose", "gripper")]
ACTIONS = [("delta_tcp", 1, 1), ("absolute_tcp", 1, 1), ("delta_tcp", 4, 2), ("absolute_tcp", 3, 3)]
COMBOS = list(itertools.product(STATES, ACTIONS))
IDS = [f"{'+'.join(s) or 'image'}-{k}-K{K}k{x}" for s, (k, K, x) in COMBOS]


def contract_of(state, action) -> PolicyContract:
    kind, K, k = action
    return PolicyContract(state=state, action=ActionContract(kind=kind, chunk=K, execute=k))


def tiny_policy(contract: PolicyContract, seed: int = 0, size: int = 32) -> VisuomotorPolicy:
    torch.manual_seed(seed)
    arch = PolicyArch(
        arch="small_cnn",
        image_size=size,
        head_hidden=16,
        head_channels=4,
        state_dim=contract.state_dim,
        chunk=contract.action.chunk,
        output="tanh" if contract.action.kind == "delta_tcp" else "linear",
    )
    p = VisuomotorPolicy(arch, contract=contract)
    if contract.action.kind == "absolute_tcp":
        # targets around a point above the table, pointing down: what a reach policy outputs
        with torch.no_grad():
            last = p.mlp[-1]
            last.weight.mul_(0.01)
            bias = torch.tensor([0.0, -0.1, 0.1, 3.1, 0.0, 0.0]).repeat(contract.action.chunk)
            last.bias.copy_(bias)
    return p.eval()


def card_of(policy: VisuomotorPolicy) -> PolicyCard:
    return PolicyCard(
        arch=policy.config,
        contract=policy.contract,
        action=ActionScaling(max_step_m=0.02, max_step_rad=0.1),
        training={"method": "test"},
    )


# --------------------------------------------------------------------------- two cameras
LEROBOT_WRIST = "observation.images.wrist"
LEROBOT_FRONT = "observation.images.front"
LEROBOT_STATE = "observation.state"


class TwoCameraPolicy(torch.nn.Module):
    """A tiny policy reading the wrist camera (``wrist_px`` square) and a scene camera
    (``front_px`` square), each through a conv stack of its own, plus the 7-value state
    (tcp_pose + gripper); ``forward(wrist, front, state) -> (B, K, 6)`` tanh deltas (``(B, 6)``
    for K = 1). Images ``(B, 3, H, W)`` in [0, 1], normalised inside as LeRobot's policies do."""

    def __init__(self, wrist_px: int = 32, front_px: int = 128, chunk: int = 1, seed: int = 0):
        super().__init__()
        torch.manual_seed(seed)
        nn = torch.nn
        self.chunk = chunk
        self.example_sizes = (wrist_px, front_px)
        self.wrist = nn.Sequential(nn.Conv2d(3, 4, 3, stride=2, padding=1), nn.ReLU(), nn.Conv2d(4, 4, 3, 2, 1))
        self.front = nn.Sequential(nn.Conv2d(3, 4, 5, stride=4, padding=2), nn.ReLU(), nn.Conv2d(4, 4, 3, 2, 1))
        n = 4 * (wrist_px // 4) ** 2 + 4 * (front_px // 8) ** 2 + 7
        self.mlp = nn.Sequential(nn.Linear(n, 16), nn.ReLU(), nn.Linear(16, 6 * chunk))

    def forward(self, wrist, front, state):
        a = torch.relu(self.wrist((wrist - 0.5) / 0.25)).flatten(1)
        b = torch.relu(self.front((front - 0.5) / 0.25)).flatten(1)
        out = torch.tanh(self.mlp(torch.cat([a, b, state], 1)))
        return out.view(-1, self.chunk, 6) if self.chunk > 1 else out


class LeRobotInputs(torch.nn.Module):
    """``forward(batch: {LeRobot name: tensor}) -> {"action": ...}``: how LeRobot's policies take
    and give their tensors (what torch.export writes into a .pt2's input and output specs)."""

    def __init__(self, inner):
        super().__init__()
        self.inner = inner

    def forward(self, batch: dict):
        return {"action": self.inner(batch[LEROBOT_WRIST], batch[LEROBOT_FRONT], batch[LEROBOT_STATE])}


def two_camera_contract(chunk: int = 1) -> PolicyContract:
    return PolicyContract(
        state=("tcp_pose", "gripper"), action=ActionContract(kind="delta_tcp", chunk=chunk, execute=1)
    )


def two_camera_card(chunk: int = 1, **fields) -> PolicyCard:
    """The card of a LeRobot-named two-camera file: no ``arch``, no ``inputs`` (the names bind)."""
    return PolicyCard(
        contract=two_camera_contract(chunk),
        action=ActionScaling(max_step_m=0.02, max_step_rad=0.1),
        training={"method": "test"},
        **fields,
    )


class TinyACT(torch.nn.Module):
    """An ACT-shaped policy (LeRobot's ACT in miniature): one conv backbone run on each camera
    (wrist ``wrist_px``, front ``front_px``), a 1x1 input projection to ``d`` channels, the two
    cameras' feature maps flattened into tokens beside a state token, learned position
    embeddings, a transformer encoder over the tokens and a decoder whose ``chunk`` queries
    attend to them, and a linear head: ``forward(wrist, front, state) -> (B, chunk, 6)`` tanh
    deltas. Images ``(B, 3, H, W)`` in [0, 1], normalised inside; no dropout."""

    def __init__(self, wrist_px: int = 32, front_px: int = 128, chunk: int = 4, d: int = 16, seed: int = 0):
        super().__init__()
        torch.manual_seed(seed)
        nn = torch.nn
        self.example_sizes = (wrist_px, front_px)
        self.chunk = chunk
        self.backbone = nn.Sequential(
            nn.Conv2d(3, 8, 3, stride=2, padding=1), nn.ReLU(), nn.Conv2d(8, 8, 3, stride=2, padding=1), nn.ReLU()
        )
        self.pool_front = nn.AvgPool2d(4)  # the front camera's larger frame to a few tokens
        self.input_proj = nn.Conv2d(8, d, 1)
        n_tokens = 1 + (wrist_px // 4) ** 2 + (front_px // 16) ** 2
        self.pos = nn.Parameter(torch.randn(1, n_tokens, d) * 0.1)
        self.state_proj = nn.Linear(7, d)
        enc = nn.TransformerEncoderLayer(d, 2, 32, dropout=0.0, batch_first=True)
        dec = nn.TransformerDecoderLayer(d, 2, 32, dropout=0.0, batch_first=True)
        self.encoder = nn.TransformerEncoder(enc, 1, enable_nested_tensor=False)
        self.decoder = nn.TransformerDecoder(dec, 1)
        self.queries = nn.Parameter(torch.randn(1, chunk, d) * 0.1)
        self.action_head = nn.Linear(d, 6)

    def forward(self, wrist, front, state):
        fw = self.input_proj(self.backbone((wrist - 0.5) / 0.25))
        ff = self.input_proj(self.pool_front(self.backbone((front - 0.5) / 0.25)))
        tokens = torch.cat(
            [self.state_proj(state)[:, None], fw.flatten(2).transpose(1, 2), ff.flatten(2).transpose(1, 2)], 1
        )
        memory = self.encoder(tokens + self.pos)
        q = self.queries.expand(state.shape[0], -1, -1)
        return torch.tanh(self.action_head(self.decoder(q, memory)))
