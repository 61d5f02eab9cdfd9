"""The reach task as a standard ``gymnasium.Env``: one environment, the spaces users' RL code expects.

:class:`sim.env.ReachEnv` is the project's batched env (frozen finished envs, arrays of results).
:class:`ReachGymEnv` is one of them behind gymnasium's API, so Stable-Baselines3 and other RL
code use it without a wrapper, and ``gymnasium.make_vec`` batches it::

    import gymnasium as gym
    env = gym.make("sim.gym_env:advobj/Reach-v0", image_size=64)  # gymnasium imports the module first
    envs = gym.make_vec("advobj/Reach-v0", num_envs=4, vectorization_mode="sync")  # registered from then on

Importing this module registers the id (:func:`register_envs`), the way installed env packages do
under gymnasium 1.x (``import sim.gym_env; gym.register_envs(sim.gym_env)`` is the same);
gymnasium 1.0 removed the ``gymnasium.envs`` plugin entry points that registered ids without an
import.

* observation: the wrist camera's ``(S, S, 3)`` uint8 image (``Box(0, 255)``); with
  ``cameras=("wrist", "front")`` (names of the scene's cameras), a ``Dict`` of each camera's
  ``(H, W, 3)`` uint8 image (a scene camera at its own size; one camera alone stays a ``Box``);
* action: the normalised TCP delta ``(6,)`` float32 in ``[-1, 1]`` (``Box(-1, 1)``, see
  :mod:`sim.action`), clipped into the box before it is applied (gymnasium's contract);
* reward, termination and truncation: :meth:`sim.env.ReachEnv.step`'s (reaching an object
  terminates, ``episode.max_steps`` truncates);
* ``reset(seed=s)`` draws the initial configuration of seed ``s`` (the same seed, the same
  episode); without a seed the next one comes from the env's own generator.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from sim.env import ReachEnv
from sim.spec import WRIST, SceneSpec, default_scene, load_scene

__all__ = ["ReachGymEnv", "ENV_ID", "register_envs"]

ENV_ID = "advobj/Reach-v0"


class ReachGymEnv(gym.Env):
    """One reach environment (see the module docstring).

    Args:
        scene: a :class:`sim.spec.SceneSpec`, a scene YAML path, or None (the built-in scene).
        image_size: the wrist camera's square image size in px (default: the spec camera's width).
        render_mode: None or ``"rgb_array"`` (the current observation; with several cameras, the
            wrist camera's image, or the first camera's).
        cameras: the scene's cameras observed (:attr:`sim.spec.SceneSpec.camera_names`).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        scene=None,
        image_size: int | None = None,
        render_mode: str | None = None,
        cameras: tuple[str, ...] = (WRIST,),
    ):
        spec = scene if isinstance(scene, SceneSpec) else (default_scene() if scene is None else load_scene(scene))
        size = int(image_size or spec.camera.width)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode: expected None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self._env = ReachEnv(spec, num_envs=1, image_size=size, cameras=cameras)
        boxes = {name: spaces.Box(0, 255, self._env.image_shape(name), np.uint8) for name in self._env.cameras}
        self._several = len(boxes) > 1
        self.observation_space = spaces.Dict(boxes) if self._several else next(iter(boxes.values()))
        self.action_space = spaces.Box(-1.0, 1.0, (6,), np.float32)
        self._obs = np.zeros(self._env.image_shape(self._env.obs_camera), np.uint8)
        self._images: dict[str, np.ndarray] = {}

    @staticmethod
    def _one(info: dict) -> dict:
        # The images are the observation; the rest loses its batch axis of one.
        return {
            k: (v[0] if isinstance(v, (np.ndarray, list)) and len(v) == 1 else v)
            for k, v in info.items()
            if k != "images"
        }

    def _observation(self, obs: np.ndarray, info: dict):
        self._obs = obs[0]
        self._images = {name: im[0] for name, im in info["images"].items()}
        return {k: v.copy() for k, v in self._images.items()} if self._several else self._obs.copy()

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        episode_seed = int(seed) if seed is not None else int(self.np_random.integers(0, 2**31 - 1))
        obs, info = self._env.reset(seed=episode_seed)
        return self._observation(obs, info), self._one(info)

    def step(self, action):
        a = np.clip(np.asarray(action, dtype=np.float64).reshape(1, 6), -1.0, 1.0)
        obs, reward, terminated, truncated, info = self._env.step(a)
        return (
            self._observation(obs, info),
            float(reward[0]),
            bool(terminated[0]),
            bool(truncated[0]),
            self._one(info),
        )

    def render(self):
        return self._obs.copy() if self.render_mode == "rgb_array" else None

    def close(self):
        self._env.close()


def register_envs() -> None:
    """Register :data:`ENV_ID` with gymnasium (once; calling it again changes nothing). The entry
    point is named by its import path, so a registry entry never holds a stale class."""
    if ENV_ID not in gym.registry:
        gym.register(ENV_ID, entry_point=f"{__name__}:{ReachGymEnv.__name__}")


register_envs()
