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
