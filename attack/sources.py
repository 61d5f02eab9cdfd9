"""Where the attack's frames come from: a :class:`FrameSource` gives batches of :class:`Frames`.

An iteration (:func:`attack.optimize.attack_step`) asks its source to ``start`` (drawing this
iteration's configurations from the run's RNG), then takes ``next()`` batches until it returns
``None``, telling the source the actions the policy chose on each batch with ``advance``. A
closed-loop source moves by them (the simulator's rollouts); an open-loop one (recordings) may
ignore them. The attack renders the texture into each frame's captured fragments, so a source
gives :class:`attack.render.Capture` records, the TCP poses and the adversarial object's centres.

:class:`SimRollouts` is today's source: EOT over short closed-loop rollouts in the simulator
(paper Sec. III-C): ``num_envs`` initial configurations drawn from the task-feasible pool's
"attack" part with the schedule's Beta weights over camera distance, each rolled out for
``rollout_steps`` steps under the current texture (rollouts only provide viewpoints; no gradient
flows through the dynamics). :class:`attack.recorded.RecordedFrames` is the other: a recording's
frames (:mod:`sim.recording`) with the object composited in, open loop, with no simulator in it.

Adding a source means one class with these three methods (and its test); the loop is unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from attack.schedule import sample_configs, stage_params
from sim.variations import Randomization, sample_appearance

__all__ = ["Frames", "FrameSource", "SimRollouts"]


@dataclass
class Frames:
    """One batch of B frames the attack renders its texture into.

    ``captures``: B :class:`attack.render.Capture` (of the saliency camera: the wrist camera, or the
    first the policy reads); ``T_world_tcp (B, 4, 4)`` and ``p_adv (B, 3)`` (m, world frame) as
    float32 tensors on the run's device; ``views``: ``{camera: B captures}`` of every camera the
    policy reads when it reads several (``captures`` is one of them), else None; ``q (B, n)``: the
    arm's joint positions (float64, the run's device) when the env moves the arm by its joints
    (``ReachEnv(control="joint")``), else None.
    """

    captures: list
    T_world_tcp: torch.Tensor
    p_adv: torch.Tensor
    views: dict | None = None
    q: torch.Tensor | None = None

    def __len__(self) -> int:
        return len(self.captures)

    @staticmethod
    def _stack(captures, device) -> torch.Tensor:
        return (
            torch.stack([torch.from_numpy(c.i_sim).permute(2, 0, 1) for c in captures]).to(device, torch.float32)
            / 255.0
        )

    def clean_images(self, device):
        """``(B, 3, H, W)`` float in [0, 1]: the frames as captured, without the attack's texture
        (``{camera: (B, 3, H_c, W_c)}`` when the frames hold several cameras' views)."""
        if self.views is not None:
            return {name: self._stack(caps, device) for name, caps in self.views.items()}
        return self._stack(self.captures, device)


class FrameSource(Protocol):
    """Batches of frames for one iteration; see the module docstring."""

    def start(self, iteration: int, rng: np.random.Generator) -> None: ...

    def next(self) -> Frames | None: ...

    def advance(self, actions: np.ndarray) -> None: ...


class SimRollouts:
    """Closed-loop rollouts in a :class:`sim.env.ReachEnv` (the module docstring).

    Args:
        env: the run's env (``render_obs=False``; frames come from ``hybrid``).
        hybrid: the :class:`attack.render.HybridRenderer` of the saliency camera.
        hybrids: ``{camera: HybridRenderer}`` of every camera the policy reads (None or one: ``hybrid`` alone).
        spec: the scene (its ``init.r_range_m`` bounds the distance schedule).
        pool: the attack part's initial configurations.
        cfg: the attack config (``schedule``, ``iterations``, ``num_envs``, ``rollout_steps``,
            ``light_randomization``).
        device: where the pose tensors go.
    """

    def __init__(self, env, hybrid, spec, pool: list, cfg, device, hybrids: dict | None = None):
        self.env, self.hybrid, self.spec, self.pool, self.cfg = env, hybrid, spec, list(pool), cfg
        # several cameras: {camera: HybridRenderer}, hybrid among them
        self.hybrids = hybrids if hybrids is not None and len(hybrids) > 1 else None
        self.device = torch.device(device)
        self.pool_r = np.array([c.r_m for c in self.pool])
        self._step = 0
        self._active = np.zeros(0, np.int64)

    def start(self, iteration: int, rng: np.random.Generator) -> None:
        cfg, env = self.cfg, self.env
        params = stage_params(cfg.schedule, iteration, cfg.iterations)
        idx = sample_configs(self.pool_r, params, self.spec.init.r_range_m, cfg.num_envs, rng)
        env.reset_envs(range(cfg.num_envs), configs=[self.pool[i] for i in idx])
        if cfg.light_randomization:
            for w in env.worlds:
                w.appearance = sample_appearance(self.spec, Randomization(light="random"), rng)
        self._step = 0

    def next(self) -> Frames | None:
        env = self.env
        if self._step >= self.cfg.rollout_steps:
            return None
        active = np.flatnonzero(~env.done)
        if active.size == 0:
            return None
        self._active = active
        if self.hybrids is None:
            views = None
            caps = [self.hybrid.capture(env.worlds[i]) for i in active]
        else:
            views = {name: [h.capture(env.worlds[i]) for i in active] for name, h in self.hybrids.items()}
            caps = views[self.hybrid.camera]
        T = torch.from_numpy(env.T_world_tcp[active]).to(self.device, torch.float32)
        p_adv = torch.from_numpy(env.object_centers[active, self.hybrid.adv]).to(self.device, torch.float32)
        q = None if env.q is None else torch.from_numpy(env.q[active]).to(self.device)
        return Frames(caps, T, p_adv, views, q)

    def advance(self, actions: np.ndarray) -> None:
        """Step the env by ``actions`` of the frames' envs: TCP motions ``(B, 6)``, or joint targets ``(B, n)``
        under joint control (the other envs have finished and ignore theirs)."""
        full = np.zeros((self.cfg.num_envs, np.shape(actions)[1]))
        full[self._active] = actions
        self.env.step(full)
        self._step += 1
