"""PPO (the paper's training method) through stable-baselines3, on our backbones, resumable.

* :class:`ReachVecEnv` adapts :class:`sim.env.ReachEnv` to SB3's ``VecEnv`` (auto-reset with
  fresh training seeds, ``terminal_observation`` in ``infos``, channel-first uint8 images).
* :class:`PolicyExtractor` is the SB3 features extractor: it *is* a
  :class:`sim.policies.policy.VisuomotorPolicy` up to the last linear layer, so after training
  the actor's ``action_net`` is copied into that last layer and the result is an ordinary
  white-box policy (:func:`to_visuomotor`). Actor and critic share the trunk.
* Squashing: SB3 samples unbounded Gaussian actions; the env adapter applies ``tanh`` before
  stepping, so the deterministic action is ``tanh(mean)``, which is exactly the policy head's
  ``tanh``. (SB3 first clips samples to the declared space [-5, 5]; ``tanh`` differs from 1 by
  < 1e-4 there.)

SB3's own ``save``/``load`` use pickle; they are never used. The resumable state is safetensors
(weights), ``torch.load(weights_only=True)`` (optimizer) and JSON (progress).
"""

from __future__ import annotations

import copy
import json
import time
from pathlib import Path

import numpy as np
import torch
from gymnasium import spaces
from pydantic import Field
from safetensors.torch import load_file, save_file
from stable_baselines3 import PPO
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.vec_env import VecEnv
from tqdm.auto import tqdm

from sim.configio import StrictModel
from sim.policies.dagger import TRAIN_SEED_BASE
from sim.policies.interface import PolicyError
from sim.policies.policy import PolicyArch, VisuomotorPolicy
from sim.policies.rollout import EnvConfig, run_episodes, set_randomization

__all__ = ["PPOConfig", "ReachVecEnv", "PolicyExtractor", "train_ppo", "to_visuomotor", "ACTION_BOUND"]

ACTION_BOUND = 5.0  # pre-tanh action space; tanh(5) = 0.99991


class PPOConfig(StrictModel):
    total_timesteps: int = Field(200_000, ge=1)
    num_envs: int = Field(8, ge=1)
    n_steps: int = Field(128, ge=2, description="rollout length per env per update")
    batch_size: int = Field(128, ge=2)
    n_epochs: int = Field(4, ge=1)
    lr: float = Field(3e-4, gt=0)
    gamma: float = Field(0.98, gt=0, le=1)
    gae_lambda: float = Field(0.95, ge=0, le=1)
    clip_range: float = Field(0.2, gt=0)
    ent_coef: float = Field(0.0, ge=0)
    log_std_init: float = -0.5
    chunk_timesteps: int = Field(8192, ge=1, description="save (and evaluate) every this many env steps")
    eval_episodes: int = Field(0, ge=0)
    stop_at_success: float | None = Field(None, gt=0, le=1)


def _vec_env_base():
    return VecEnv


class ReachVecEnv(_vec_env_base()):
    """SB3 ``VecEnv`` over a :class:`sim.env.ReachEnv`; observations ``(N, 3, H, W)`` uint8."""

    def __init__(self, env, seed_base: int):
        self.env = env
        self._seed_cursor = int(seed_base)
        obs_space = spaces.Box(0, 255, (3, env.height, env.width), np.uint8)
        act_space = spaces.Box(-ACTION_BOUND, ACTION_BOUND, (6,), np.float32)
        self.render_mode = None
        super().__init__(env.num_envs, obs_space, act_space)
        self._actions = None
        self._return = np.zeros(env.num_envs)  # running episode returns, for SB3's episode stats

    def _draw_seeds(self, n: int) -> list[int]:
        s = list(range(self._seed_cursor, self._seed_cursor + n))
        self._seed_cursor += n
        return s

    def _obs(self) -> np.ndarray:
        return np.ascontiguousarray(self.env.observe().transpose(0, 3, 1, 2))

    def reset(self):
        self._return[:] = 0.0
        self.env.reset_envs(range(self.num_envs), seeds=self._draw_seeds(self.num_envs))
        return self._obs()

    def step_async(self, actions):
        self._actions = np.asarray(actions, dtype=np.float64)

    def step_wait(self):
        obs, reward, terminated, truncated, info = self.env.step(np.tanh(self._actions))
        dones = terminated | truncated
        self._return += reward
        infos = [{} for _ in range(self.num_envs)]
        done_idx = np.flatnonzero(dones)
        for i in done_idx:
            infos[i] = {
                "terminal_observation": obs[i].transpose(2, 0, 1).copy(),
                "TimeLimit.truncated": bool(truncated[i] and not terminated[i]),
                "is_success": bool(info["success"][i]),
                "episode": {"r": float(self._return[i]), "l": int(info["step"][i]), "t": 0.0},
            }
            self._return[i] = 0.0
        if len(done_idx):
            self.env.reset_envs(done_idx, seeds=self._draw_seeds(len(done_idx)))
        return self._obs(), reward.astype(np.float32), dones, infos

    def close(self):
        pass  # the ReachEnv belongs to the caller

    def get_attr(self, attr_name, indices=None):
        return [getattr(self, attr_name)] * len(self._get_indices(indices))

    def set_attr(self, attr_name, value, indices=None):
        setattr(self, attr_name, value)

    def env_method(self, method_name, *args, indices=None, **kwargs):
        raise NotImplementedError("ReachVecEnv has no per-env methods")

    def env_is_wrapped(self, wrapper_class, indices=None):
        return [False] * len(self._get_indices(indices))


def _extractor_base():
    return BaseFeaturesExtractor


class PolicyExtractor(_extractor_base()):
    """A VisuomotorPolicy up to its last linear layer: images ``(B, 3, H, W)`` in [0, 1] -> ``(B, hidden)``."""

    def __init__(self, observation_space, arch: dict):
        policy = VisuomotorPolicy(PolicyArch(**arch))
        super().__init__(observation_space, features_dim=policy.config.head_hidden)
        self.policy = policy

    def forward(self, obs):
        return self.policy.mlp[:-1](self.policy.reduce(self.policy.features(obs)))


# SB3 registers the shared trunk under three names; only ``features_extractor.*`` is stored.
_ALIASES = ("pi_features_extractor.", "vf_features_extractor.")


def _unaliased_state(module) -> dict:
    return {k: v.detach().cpu().contiguous() for k, v in module.state_dict().items() if not k.startswith(_ALIASES)}


def _make_model(vec_env, arch, cfg: PPOConfig, seed: int, device):
    return PPO(
        "CnnPolicy",
        vec_env,
        learning_rate=cfg.lr,
        n_steps=cfg.n_steps,
        batch_size=cfg.batch_size,
        n_epochs=cfg.n_epochs,
        gamma=cfg.gamma,
        gae_lambda=cfg.gae_lambda,
        clip_range=cfg.clip_range,
        ent_coef=cfg.ent_coef,
        seed=seed,
        device=device,
        verbose=0,
        policy_kwargs=dict(
            features_extractor_class=PolicyExtractor,
            features_extractor_kwargs=dict(arch=arch.model_dump(mode="json")),
            net_arch=dict(pi=[], vf=[]),
            share_features_extractor=True,
            log_std_init=cfg.log_std_init,
            ortho_init=False,  # keep the trunk's own initialisation
        ),
    )


def to_visuomotor(model):
    """The trained actor as a :class:`VisuomotorPolicy` (shares nothing with ``model``), eval mode."""
    policy = copy.deepcopy(model.policy.features_extractor.policy)
    policy.mlp[-1].load_state_dict(model.policy.action_net.state_dict())
    return policy.eval()


def train_ppo(
    arch,
    env,
    cfg: PPOConfig,
    env_cfg: EnvConfig,
    out_dir: str | Path,
    seed: int = 0,
    fingerprint: str = "",
    device="cpu",
    progress: bool = True,
    log=print,
):
    """Train with PPO in ``env`` (``cfg.num_envs`` envs); resumes from ``out_dir/train_state``.

    Returns ``(policy, progress_record)`` with the policy as a :class:`VisuomotorPolicy`.
    """
    if env.num_envs != cfg.num_envs:
        raise ValueError(f"env has {env.num_envs} envs, config says num_envs={cfg.num_envs}")
    state_dir = Path(out_dir) / "train_state"
    set_randomization(env, env_cfg)
    vec = ReachVecEnv(env, TRAIN_SEED_BASE + seed * 1_000_000)
    model = _make_model(vec, arch, cfg, seed, device)
    prog = {
        "fingerprint": fingerprint,
        "timesteps": 0,
        "elapsed_s": 0.0,
        "cpu_s": 0.0,
        "history": [],
        "stopped_early": False,
    }
    if (state_dir / "progress.json").is_file():
        prog = json.loads((state_dir / "progress.json").read_text())
        if prog.get("fingerprint") != fingerprint:
            raise PolicyError(
                f"{state_dir}: holds a run with a different config; use a new --out or delete that directory"
            )
        missing = model.policy.load_state_dict(
            load_file(str(state_dir / "model.safetensors")), strict=False
        ).missing_keys
        if any(not k.startswith(_ALIASES) for k in missing):
            raise PolicyError(f"{state_dir}: saved PPO weights do not fit this architecture")
        model.policy.optimizer.load_state_dict(torch.load(state_dir / "optim.pt", weights_only=True))
        model.num_timesteps = int(prog["timesteps"])
        vec._seed_cursor += int(prog["timesteps"])  # fresh configurations after a resume
        log(f"resuming PPO after {prog['timesteps']} steps ({prog['elapsed_s']:.0f} s so far)")
    clean = EnvConfig(image_size=env_cfg.image_size)
    bar = tqdm(total=cfg.total_timesteps, initial=prog["timesteps"], desc="ppo", unit="step", disable=not progress)
    while prog["timesteps"] < cfg.total_timesteps and not prog["stopped_early"]:
        t0, c0 = time.perf_counter(), time.process_time()
        chunk = min(cfg.chunk_timesteps, cfg.total_timesteps - prog["timesteps"])
        model.learn(total_timesteps=chunk, reset_num_timesteps=False)
        done = model.num_timesteps - prog["timesteps"]
        record = {"timesteps": int(model.num_timesteps)}
        if model.ep_info_buffer:
            record["train_mean_return"] = float(np.mean([ep["r"] for ep in model.ep_info_buffer]))
        if cfg.eval_episodes:
            te, ce = time.perf_counter(), time.process_time()
            set_randomization(env, clean)
            res = run_episodes(env, to_visuomotor(model), range(cfg.eval_episodes))
            set_randomization(env, env_cfg)
            vec.reset()  # evaluation used the envs; start fresh training episodes
            model._last_obs = vec._obs()
            record["clean_success"] = res.success_rate.rate
            # Evaluation is measurement, not training: its time is excluded from the budget.
            t0 += time.perf_counter() - te
            c0 += time.process_time() - ce
            if cfg.stop_at_success is not None and res.success_rate.rate >= cfg.stop_at_success:
                prog["stopped_early"] = True
        prog["elapsed_s"] += time.perf_counter() - t0
        prog["cpu_s"] = (
            prog.get("cpu_s", 0.0) + time.process_time() - c0
        )  # CPU time of all threads: the cost on an idle machine
        prog["timesteps"] = int(model.num_timesteps)
        record["elapsed_s"], record["cpu_s"] = prog["elapsed_s"], prog["cpu_s"]
        prog["history"].append(record)
        state_dir.mkdir(parents=True, exist_ok=True)
        save_file(_unaliased_state(model.policy), str(state_dir / "model.safetensors.tmp"))
        torch.save(model.policy.optimizer.state_dict(), state_dir / "optim.pt.tmp")
        (state_dir / "progress.json.tmp").write_text(json.dumps(prog, indent=2))
        for name in ("model.safetensors", "optim.pt", "progress.json"):
            (state_dir / (name + ".tmp")).replace(state_dir / name)
        bar.update(done)
        bar.set_postfix(clean=record.get("clean_success"), ret=record.get("train_mean_return"))
    bar.close()
    return to_visuomotor(model), prog
