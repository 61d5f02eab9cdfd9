"""One training run end to end: config -> DAgger or PPO -> clean evaluation -> checkpoint.

Outputs in ``out_dir``: the checkpoint (``policy.json`` + ``weights.safetensors``), ``run.json``
(resolved config, seed, git commit), ``train_state/`` (for resuming), and
``feasible_pool.json`` from the final clean evaluation.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import torch

from sim.configs import spec_fingerprint
from sim.policies.card import ActionScaling, CleanSuccess, PolicyCard
from sim.policies.checkpoint import save_checkpoint
from sim.policies.contract import check_scene
from sim.policies.dagger import train_dagger
from sim.policies.interface import PolicyError
from sim.policies.policy import VisuomotorPolicy
from sim.policies.pool import built_pool_path, write_feasible_pool
from sim.policies.ppo import train_ppo
from sim.policies.presets import TrainConfig
from sim.policies.rollout import EVAL_SEED_BASE, evaluate_policy, make_env
from sim.runinfo import git_commit, write_run_info

__all__ = ["train_policy", "check_resume_length"]


def check_resume_length(cfg: TrainConfig, out_dir: str | Path) -> None:
    """Refuse, in one line and before anything in ``out_dir`` is written (its ``run.json``
    included), resuming the interrupted run there (DAgger or PPO) with another config (its resume
    fingerprint, :meth:`TrainConfig.fingerprint`: e.g. other ``--grad-steps``, another method), or
    a DAgger run with fewer ``dagger.iterations`` than it has already done (its weights would not
    be what the resolved config says). More iterations continue it: the run length is not part of
    the fingerprint. A state that cannot be read is left to the resume itself, which refuses it in
    its own line."""
    path = Path(out_dir) / "train_state" / "progress.json"
    try:
        progress = json.loads(path.read_text())
    except (OSError, ValueError):
        return
    if not isinstance(progress, dict):
        return
    if progress.get("fingerprint") != cfg.fingerprint():
        raise PolicyError(
            f"{path.parent}: holds a run with a different config; use a new --out or delete that directory"
        )
    if cfg.method != "dagger":
        return
    try:
        done = int(progress["iterations_done"])
    except (KeyError, TypeError, ValueError):
        return
    if done > cfg.dagger.iterations:
        raise PolicyError(
            f"dagger.iterations (--iterations): {cfg.dagger.iterations}, but the run in {out_dir} has already done "
            f"{done}; resume it with {done} or more, or train into a new --out"
        )


def train_policy(
    cfg: TrainConfig,
    out_dir: str | Path,
    spec,
    device="cpu",
    progress: bool = True,
    log=print,
    keep_state: bool = False,
) -> PolicyCard:
    """Train per ``cfg`` on scene ``spec``; resumes an interrupted run in the same ``out_dir``.

    Once the checkpoint is saved, ``train_state/`` (the resume data: frames, optimizer; hundreds
    of MB) is deleted unless ``keep_state``; the final weights and card stay. A policy reading a
    camera ``spec`` lacks, or a scene camera of another size than ``cfg.policy.camera_px``, is
    refused in one line before anything is written.
    """
    out_dir = Path(out_dir)
    # before the output folder exists: the cameras, and a joint-space contract against the scene's arm
    check_scene(SimpleNamespace(inputs=cfg.policy.input_plan(cfg.contract), contract=cfg.contract), spec)
    check_resume_length(cfg, out_dir)
    resolved = cfg.model_dump(mode="json")
    resolved["scene"] = {"name": spec.name, "fingerprint": spec_fingerprint(spec)}
    write_run_info(out_dir, resolved, cfg.seed)
    torch.manual_seed(cfg.seed)
    fp = cfg.fingerprint()
    if cfg.method == "dagger":
        env = make_env(
            spec, cfg.env, cfg.dagger.num_envs, seed=cfg.seed, cameras=cfg.policy.cameras, control=cfg.contract.control
        )
        policy = VisuomotorPolicy(cfg.policy, cfg.contract).to(device)
        prog = train_dagger(policy, env, cfg.dagger, cfg.env, out_dir, cfg.seed, fp, device, progress, log)
    else:
        env = make_env(spec, cfg.env, cfg.ppo.num_envs, seed=cfg.seed)
        policy, prog = train_ppo(cfg.policy, env, cfg.ppo, cfg.env, out_dir, cfg.seed, fp, device, progress, log)
        policy = policy.to(device)
    try:
        clean = None
        if cfg.final_eval_episodes:
            res = evaluate_policy(policy, spec, cfg.final_eval_episodes, EVAL_SEED_BASE, env=env, progress=progress)
            p = res.success_rate
            clean = CleanSuccess(
                k=p.k,
                n=p.n,
                rate=p.rate,
                lo=p.lo,
                hi=p.hi,
                confidence=p.confidence,
                episodes_seed=EVAL_SEED_BASE,
                image_size=cfg.env.image_size,
            )
            write_feasible_pool(
                built_pool_path(out_dir), spec, res, meta={"policy": str(out_dir), "seed": EVAL_SEED_BASE}
            )
            log(f"clean success: {p}")
    finally:
        env.close()
    training = {
        **resolved,
        "train_time_s": prog["elapsed_s"],
        "train_cpu_s": prog.get("cpu_s"),
        "history": prog["history"],
        "stopped_early": prog["stopped_early"],
    }
    card = PolicyCard(
        arch=cfg.policy,
        action=ActionScaling(max_step_m=spec.episode.max_step_m, max_step_rad=spec.episode.max_step_rad),
        contract=cfg.contract,
        training=training,
        clean_success=clean,
        seed=cfg.seed,
        git_commit=git_commit(),
    )
    card = save_checkpoint(out_dir, policy.cpu(), card)
    if not keep_state and (out_dir / "train_state").is_dir():
        size = sum(f.stat().st_size for f in (out_dir / "train_state").rglob("*") if f.is_file())
        shutil.rmtree(out_dir / "train_state")
        log(f"deleted {out_dir / 'train_state'} ({size / 1e6:.0f} MB of resume data; --keep-state keeps it)")
    return card
