"""Scene helpers behind ``advobj scene ...`` and the first stage of ``advobj demo``: a still and an
expert rollout (the scene loader is :func:`sim.spec.load_spec`; GIFs and contact sheets are
:mod:`sim.imaging`'s)."""

from __future__ import annotations

import numpy as np
from tqdm import tqdm

from sim.env import ReachEnv
from sim.world import SimWorld

__all__ = ["render_still", "expert_rollout"]


def render_still(spec, seed: int, size: int | None = None) -> np.ndarray:
    """Wrist-camera frame of the initial configuration for ``seed`` (H, W, 3) uint8."""
    with SimWorld(spec, image_size=size, seed=seed) as world:
        return world.render(with_ids=False).rgb


def expert_rollout(spec, seed: int, size: int | None = None, progress: bool = True) -> tuple[list[np.ndarray], dict]:
    """Run the privileged expert for one episode; returns the frames and the final ``info``."""
    with ReachEnv(spec, num_envs=1, image_size=size, seed=seed) as env:
        obs, info = env.reset(seed=seed)
        frames = [obs[0]]
        bar = tqdm(total=spec.episode.max_steps, desc="expert rollout", disable=not progress, leave=False)
        while not env.done[0]:
            obs, _, _, _, info = env.step(env.expert_actions())
            frames.append(obs[0])
            bar.update(1)
        bar.close()
    return frames, info
