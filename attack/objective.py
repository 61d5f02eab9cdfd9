"""The attack objective as a list of terms: the extension point for new losses.

A **term** is a small object with a ``name``, a ``weight``, a ``schedule`` (a multiplier of the
weight by training progress) and the set of inputs it ``needs`` from a :class:`FrameBatch`. Its
``loss(batch, weight)`` returns one scalar (the sum over the batch's image-action pairs, already
weighted) and a dict of detached per-pair parts to log. The attack loop
(:func:`attack.optimize.attack_step`) never names a term: it takes each term's texture gradient,
combines the N gradients with PCGrad (:func:`attack.pcgrad.pcgrad_many`) or sums them, and logs
every term's value and parts under their names (:class:`attack.state.History` stores them by
name, so a new term changes no checkpoint format).

Adding a term means writing its class here (or anywhere) and adding it in :func:`build_objective`
or passing an objective of your own to the run; nothing else in the loop changes.

The paper's terms (Sec. III-B):

- :class:`PoseTerm` ``L_pose = L_ori + lambda_dist * L_dist`` (Eq. for L_pose);
- :class:`SaliencyTerm` ``lambda_sal * L_saliency`` (Grad-CAM on the adversarial vs goal mask);
- the untargeted ablation's two terms, :class:`DeviationTerm` ``-||a - a_clean||^2`` and
  :class:`GoalAttentionTerm` ``lambda_sal * mean_{M_goal}(S)``.

Inputs a term may need (``needs``): ``actions`` (the executed-next motion as a normalised
``delta_tcp``, differentiable), ``features`` (the policy's feature maps ``A``), ``cam`` (the
differentiable Grad-CAM of that motion), ``masks`` (the adversarial and goal masks) and
``clean_actions`` (the policy's action on the frame without the adversarial texture). The batch
computes each input once, on first use.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, ClassVar, Protocol

import numpy as np
import torch

from attack.losses import (
    deviation_loss,
    goal_attention_loss,
    grad_cam,
    pose_loss,
    saliency_loss,
)

__all__ = [
    "NEEDS",
    "FrameBatch",
    "Term",
    "PoseTerm",
    "SaliencyTerm",
    "DeviationTerm",
    "GoalAttentionTerm",
    "Objective",
    "build_objective",
    "constant_schedule",
]

NEEDS = frozenset({"actions", "features", "cam", "masks", "clean_actions"})


def constant_schedule(iteration: int, iterations: int) -> float:
    """The weight multiplier of a term that weighs the same at every iteration."""
    return 1.0


@dataclass
class FrameBatch:
    """B image-action pairs under one texture, with each input a term may need computed once.

    ``images (B, 3, H, W)`` rendered with the texture (carrying its graph), or ``{camera: (B, 3,
    H_c, W_c)}`` for a policy reading several cameras; ``T_world_tcp (B, 4, 4)``; ``p_adv (B, 3)``
    m; ``adv_mask``/``goal_mask`` ``(B, H, W)`` bool numpy (of ``saliency_camera``'s images when
    there are several: Grad-CAM and the saliency terms read that camera's feature map, the wrist
    camera's when the policy reads it);
    ``policy``: the run's differentiable policy adapter (``features``, ``head``, ``state``,
    ``next_delta``, ``act``); ``clean_images`` a callable giving ``(B, 3, H, W)`` without the
    adversarial texture (only when a term needs ``clean_actions``).
    """

    images: torch.Tensor
    T_world_tcp: torch.Tensor
    p_adv: torch.Tensor
    adv_mask: np.ndarray
    goal_mask: np.ndarray
    policy: object
    clean_images: Callable[[], torch.Tensor] | None = None
    saliency_camera: str | None = None
    _cache: dict = field(default_factory=dict, repr=False)

    def _get(self, key, make):
        if key not in self._cache:
            self._cache[key] = make()
        return self._cache[key]

    @property
    def state(self) -> torch.Tensor | None:
        return self._get("state", lambda: self.policy.policy_state(self.T_world_tcp))

    @property
    def features(self) -> torch.Tensor:
        """``A: (B, C, h, w)`` the policy's feature maps of ``images`` (``{camera: A}`` for several)."""
        return self._get("features", lambda: self.policy.policy.features(self.images))

    @property
    def actions(self) -> torch.Tensor:
        """``(B, 6)`` the executed-next motion as a normalised ``delta_tcp`` (differentiable)."""

        def make():
            A, st = self.features, self.state
            out = self.policy.policy.head(A, st) if st is not None else self.policy.policy.head(A)
            return self.policy.next_delta(out, self.T_world_tcp)

        return self._get("actions", make)

    @property
    def cam(self) -> torch.Tensor:
        """``S: (B, h, w)`` differentiable Grad-CAM of the executed-next motion (for several
        cameras, on the ``saliency_camera``'s feature map, the camera the masks are of)."""

        def make():
            A = self.features
            return grad_cam(A[self.saliency_camera] if isinstance(A, dict) else A, self.actions)

        return self._get("cam", make)

    @property
    def masks(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(adv_mask, goal_mask)`` as ``(B, H, W)`` bool tensors on the images' device."""
        dev = self.images[self.saliency_camera].device if isinstance(self.images, dict) else self.images.device
        return self._get(
            "masks",
            lambda: (torch.from_numpy(self.adv_mask).to(dev), torch.from_numpy(self.goal_mask).to(dev)),
        )

    @property
    def clean_actions(self) -> torch.Tensor:
        """``(B, 6)`` the policy's executed-next motion on the clean frames (no gradient)."""

        def make():
            if self.clean_images is None:
                raise ValueError("clean_actions: this frame source gives no clean frames")
            with torch.no_grad():
                out = self.policy.call_policy(self.clean_images(), self.state)
                return self.policy.next_delta(out, self.T_world_tcp)

        return self._get("clean_actions", make)


class Term(Protocol):
    """One term of the objective; see the module docstring."""

    name: str
    weight: float
    needs: frozenset
    parts: tuple  # the names of the per-pair parts ``loss`` returns (may be empty)
    schedule: Callable[[int, int], float]

    def loss(self, batch: FrameBatch, weight: float) -> tuple[torch.Tensor, dict]: ...


@dataclass
class PoseTerm:
    """``L_pose`` summed over the pairs (Sec. III-B): heading toward and distance to the object."""

    max_step_m: float
    max_step_rad: float
    lambda_dist: float
    weight: float = 1.0
    schedule: Callable[[int, int], float] = constant_schedule
    name: str = "pose"
    needs: ClassVar[frozenset] = frozenset({"actions"})
    parts: ClassVar[tuple] = ("ori", "dist")

    def loss(self, batch: FrameBatch, weight: float):
        lp, parts = pose_loss(
            batch.T_world_tcp, batch.actions, batch.p_adv, self.max_step_m, self.max_step_rad, self.lambda_dist
        )
        return (lp.sum() if weight == 1.0 else weight * lp.sum()), parts


@dataclass
class SaliencyTerm:
    """``lambda_sal * L_saliency`` summed over the images (Sec. III-B): attention onto the object."""

    weight: float
    schedule: Callable[[int, int], float] = constant_schedule
    name: str = "saliency"
    needs: ClassVar[frozenset] = frozenset({"cam", "masks"})

    parts: ClassVar[tuple] = ()

    def loss(self, batch: FrameBatch, weight: float):
        adv_m, goal_m = batch.masks
        return weight * saliency_loss(batch.cam, adv_m, goal_m).sum(), {}


@dataclass
class DeviationTerm:
    """The untargeted ablation's ``-||a - a_clean||^2`` summed over the pairs."""

    weight: float = 1.0
    schedule: Callable[[int, int], float] = constant_schedule
    name: str = "deviation"
    needs: ClassVar[frozenset] = frozenset({"actions", "clean_actions"})

    parts: ClassVar[tuple] = ()

    def loss(self, batch: FrameBatch, weight: float):
        dev = deviation_loss(batch.actions, batch.clean_actions).sum()
        return (dev if weight == 1.0 else weight * dev), {}


@dataclass
class GoalAttentionTerm:
    """The untargeted ablation's ``lambda_sal * mean_{M_goal}(S)``: attention off the goal."""

    weight: float
    schedule: Callable[[int, int], float] = constant_schedule
    name: str = "saliency"
    needs: ClassVar[frozenset] = frozenset({"cam", "masks"})

    parts: ClassVar[tuple] = ()

    def loss(self, batch: FrameBatch, weight: float):
        _, goal_m = batch.masks
        return goal_attention_loss(batch.cam, goal_m, weight).sum(), {}


@dataclass
class Objective:
    """The terms, in order (PCGrad and the history keep this order)."""

    terms: list

    def __post_init__(self):
        names = [t.name for t in self.terms]
        if len(set(names)) != len(names):
            raise ValueError(f"objective: term names must be unique, got {names}")
        for t in self.terms:
            if not set(t.needs) <= NEEDS:
                raise ValueError(f"objective: term {t.name!r} needs {sorted(set(t.needs) - NEEDS)}, not offered")

    @property
    def needs(self) -> frozenset:
        return frozenset().union(*(t.needs for t in self.terms)) if self.terms else frozenset()

    def losses(self, batch: FrameBatch, iteration: int, iterations: int) -> list[tuple[str, torch.Tensor, dict]]:
        """``[(name, scalar loss, parts)]`` per term, each weighted by ``weight * schedule``."""
        out = []
        for t in self.terms:
            s = t.schedule(iteration, iterations)
            w = t.weight if s == 1.0 else t.weight * s
            loss, parts = t.loss(batch, w)
            out.append((t.name, loss, parts))
        return out


def build_objective(cfg, episode) -> Objective:
    """The objective an :class:`attack.optimize.AttackConfig` describes (the paper's terms).

    Targeted: the pose term (``use_pose``) and the saliency term (``use_saliency`` and
    ``lambda_sal > 0``). Untargeted: the deviation term and, with saliency, the goal-attention term.
    """
    sal = cfg.use_saliency and cfg.lambda_sal > 0
    if cfg.loss == "targeted":
        terms = [PoseTerm(episode.max_step_m, episode.max_step_rad, cfg.lambda_dist)] if cfg.use_pose else []
        terms += [SaliencyTerm(cfg.lambda_sal)] if sal else []
    else:
        terms = [DeviationTerm()] + ([GoalAttentionTerm(cfg.lambda_sal)] if sal else [])
    return Objective(terms)
