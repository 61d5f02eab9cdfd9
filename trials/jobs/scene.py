"""Scene-level jobs behind ``advobj scene ...`` and the first stage of ``advobj demo``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["load_spec", "render_still", "expert_rollout", "contact_sheet", "write_gif"]


def load_spec(path: str | Path | None):
    from sim.spec import default_scene, load_scene

    return default_scene() if path is None else load_scene(path)


def render_still(spec, seed: int, size: int | None = None) -> np.ndarray:
    """Wrist-camera frame of the initial configuration for ``seed`` (H, W, 3) uint8."""
    from sim.world import SimWorld

    with SimWorld(spec, image_size=size, seed=seed) as world:
        return world.render(with_ids=False).rgb


def expert_rollout(spec, seed: int, size: int | None = None, progress: bool = True) -> tuple[list[np.ndarray], dict]:
    """Run the privileged expert for one episode; returns the frames and the final ``info``."""
    from tqdm import tqdm

    from sim.env import ReachEnv

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


def contact_sheet(frames: list[np.ndarray], cols: int = 8, max_frames: int = 32) -> np.ndarray:
    """Tile evenly spaced frames into one image (rows x cols), padding with black."""
    idx = np.unique(np.linspace(0, len(frames) - 1, min(max_frames, len(frames))).round().astype(int))
    picked = [frames[i] for i in idx]
    h, w, _ = picked[0].shape
    rows = -(-len(picked) // cols)
    sheet = np.zeros((rows * h, cols * w, 3), np.uint8)
    for k, f in enumerate(picked):
        r, c = divmod(k, cols)
        sheet[r * h : (r + 1) * h, c * w : (c + 1) * w] = f
    return sheet


def write_gif(path: str | Path, frames: list[np.ndarray], fps: int = 10) -> Path:
    import imageio.v3 as iio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, np.stack(frames), duration=int(1000 / fps), loop=0)
    return path
