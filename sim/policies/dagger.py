"""DAgger from the privileged expert (:func:`sim.expert.expert_actions`), resumable.

Each iteration ``i``:

1. roll out ``episodes_per_iter`` episodes with domain randomisation on; each episode is driven
   by the expert with probability ``beta_i = max(beta_min, beta0 * beta_decay**i)`` and by the
   current policy otherwise (per-episode mixing: the policy-driven episodes then double as an
   on-policy success estimate at no extra cost);
2. label every visited state with the expert's action and add it to the aggregated data set
   (oldest frames dropped beyond ``max_frames``);
3. take ``grad_steps_per_iter`` Adam steps of MSE regression on minibatches of the aggregate;
4. optionally evaluate ``eval_episodes`` clean episodes (no randomisation) for the learning curve;
5. save the state (weights, optimizer, data set, history) so an interrupted run resumes here.

A policy reading several cameras (``PolicyArch.cameras``, rendered by ``ReachEnv(cameras=...)``)
is trained by the same loop: every visited state keeps one frame per camera (``{camera: (T, H_c,
W_c, 3)}``, from ``info["images"]``), labelled with the same expert action, and each minibatch hands
the policy ``{camera: images}``.

A joint-space policy (its contract's action ``joint_delta`` or ``joint_position``, in an env with
``control="joint"``) is trained by the same loop too: every visited state also keeps the policy's
state vector (the joint positions, ``states``), the expert's joint target (its TCP motion solved
by IK, :meth:`sim.env.ReachEnv.expert_actions`) is labelled as the joint action that executes it
(:meth:`sim.ik.SceneArm.limit_step`, then :func:`sim.policies.contract.from_joint_target`), and the
policy's own actions are executed as joint targets. The progress record counts the expert steps
whose IK fell short of the expert's TCP target (``expert_ik_misses``).

The state directory holds only safetensors, ``.npz`` arrays (loaded with ``allow_pickle=False``;
the wrist camera's frames under ``images`` as they always were, a scene camera's under
``images.<camera>``, a state-reading policy's state vectors under ``states``) and the optimizer
state (``torch.load(weights_only=True)``): nothing executable.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch
from pydantic import Field
from safetensors.torch import load_file, save_file
from tqdm.auto import tqdm

from sim.configio import StrictModel
from sim.policies.contract import (
    WRIST_CAMERA,
    call_policy,
    from_joint_target,
    policy_cameras,
    policy_contract,
    state_vector,
    to_joint_target,
)
from sim.policies.interface import PolicyError
from sim.policies.rollout import EnvConfig, run_episodes, set_randomization

__all__ = ["DaggerConfig", "train_dagger", "TRAIN_SEED_BASE", "collect"]

# Training configurations come from seeds >= TRAIN_SEED_BASE; evaluation uses small seeds.
TRAIN_SEED_BASE = 10_000_000

# The key of the state vectors among a batch's arrays: no camera can be called this (a camera name
# starts with a letter, sim.spec.CAMERA_NAME).
_STATE = "_state"


class DaggerConfig(StrictModel):
    iterations: int = Field(8, ge=1)
    episodes_per_iter: int = Field(64, ge=1)
    num_envs: int = Field(16, ge=1)
    beta0: float = Field(1.0, ge=0.0, le=1.0)
    beta_decay: float = Field(0.5, ge=0.0, le=1.0)
    beta_min: float = Field(0.0, ge=0.0, le=1.0)
    grad_steps_per_iter: int = Field(300, ge=0)
    batch_size: int = Field(64, ge=1)
    lr: float = Field(1e-3, gt=0)
    weight_decay: float = Field(0.0, ge=0)
    max_frames: int = Field(60_000, ge=1)
    eval_episodes: int = Field(0, ge=0, description="clean episodes after each iteration (learning curve)")
    stop_at_success: float | None = Field(None, gt=0, le=1, description="stop once clean eval success reaches this")

    def beta(self, iteration: int) -> float:
        return max(self.beta_min, self.beta0 * self.beta_decay**iteration)


def collect(env, policy, expert_mask: np.ndarray, seeds: list[int]):
    """One batch of episodes; returns ``(frames, actions (T, A) f32, success, driven)`` with
    ``frames = {camera: (T, H_c, W_c, 3) uint8}`` for every camera the policy reads and, for a
    policy reading a state, ``frames["_state"] (T, D) f32`` (the module docstring).

    ``expert_mask[j]`` says env ``j`` executes expert actions; the others execute the policy's.
    Every visited state (of every env) is labelled with the expert's action.
    """
    contract = policy_contract(policy)
    if contract.control != env.control:
        raise PolicyError(
            f"control: the policy ({contract.describe()}) needs an env made with control={contract.control!r}, "
            f"this one has {env.control!r}"
        )
    joint = contract.is_joint_space
    gripper_m = float(env.spec.gripper.opening_m)
    cams = policy_cameras(policy)
    missing = [c for c in cams if c not in env.cameras]
    if missing:
        raise PolicyError(
            f"cameras: the policy reads {', '.join(cams)} but the env renders {', '.join(env.cameras)}; make it "
            f"with cameras={cams}"
        )
    env.reset_envs(range(env.num_envs), seeds=seeds)
    views = env.images()
    frames: dict[str, list] = {c: [] for c in cams}
    states: list = []
    labels = []
    while not env.done.all():
        active = ~env.done
        q = env.q
        state = state_vector(contract, env.T_world_tcp, gripper_m, q)
        expert = env.expert_actions()
        if joint:  # the joint target as the action that executes it (the env's own limits applied)
            reached = env.arm.limit_step(torch.from_numpy(q), torch.from_numpy(expert)).numpy()
            label = from_joint_target(q, reached, contract.action.kind)
        else:
            label = expert
        for c in cams:
            frames[c].append(views[c][active])
        if state is not None:
            states.append(state[active])
        labels.append(label[active].astype(np.float32))
        act = expert.copy()
        if not expert_mask.all():
            st = None if state is None else state[~expert_mask]
            out = np.asarray(call_policy(policy, {c: views[c][~expert_mask] for c in cams}, st), dtype=np.float64)
            act[~expert_mask] = to_joint_target(q[~expert_mask], out, contract.action.kind) if joint else out
        *_, info = env.step(act)
        views = info["images"]
    success = env.reached == env.goal_index
    out = {c: np.concatenate(f) for c, f in frames.items()}
    if states:
        out[_STATE] = np.concatenate(states)
    return out, np.concatenate(labels), success, ~expert_mask


def _npz_key(camera: str) -> str:
    """The ``data.npz`` array of camera ``camera``'s frames: ``images`` for the wrist camera (as
    before several cameras), ``images.<camera>`` for a scene camera."""
    if camera == _STATE:
        return "states"
    return "images" if camera == WRIST_CAMERA else f"images.{camera}"


class _State:
    """The resumable training state on disk (``<out>/train_state``)."""

    def __init__(self, out_dir: Path):
        self.dir = out_dir / "train_state"

    def exists(self) -> bool:
        return (self.dir / "progress.json").is_file()

    def save(self, policy, optimizer, images, actions, progress: dict) -> None:
        """``images``: ``{camera: (T, H_c, W_c, 3) uint8}`` (one array: the wrist camera's)."""
        frames = images if isinstance(images, dict) else {WRIST_CAMERA: images}
        self.dir.mkdir(parents=True, exist_ok=True)
        save_file(
            {k: v.detach().cpu().contiguous() for k, v in policy.state_dict().items()},
            str(self.dir / "model.safetensors.tmp"),
        )
        torch.save(optimizer.state_dict(), self.dir / "optim.pt.tmp")
        with open(self.dir / "data.npz.tmp", "wb") as f:
            np.savez(f, **{_npz_key(c): v for c, v in frames.items()}, actions=actions)
        (self.dir / "progress.json.tmp").write_text(json.dumps(progress, indent=2))
        # progress.json is renamed last: it marks the set as complete.
        for name in ("model.safetensors", "optim.pt", "data.npz", "progress.json"):
            (self.dir / (name + ".tmp")).replace(self.dir / name)

    def load(self, policy, optimizer, fingerprint: str | None = None):
        """``(frames {camera: array}, actions, progress)``; with ``fingerprint``, a state of another
        config is refused before its data are read."""
        try:
            progress = json.loads((self.dir / "progress.json").read_text())
            if fingerprint is not None and progress.get("fingerprint") != fingerprint:
                raise PolicyError(
                    f"{self.dir}: holds a run with a different config; use a new --out or delete that directory"
                )
            policy.load_state_dict(load_file(str(self.dir / "model.safetensors")))
            # weights_only: a pickle that builds any object is refused, never executed.
            optimizer.load_state_dict(torch.load(self.dir / "optim.pt", weights_only=True))
            with np.load(self.dir / "data.npz", allow_pickle=False) as d:
                images = {c: d[_npz_key(c)] for c in _data_keys(policy)}
                actions = d["actions"]
        except PolicyError:
            raise
        except Exception as err:  # any damaged or foreign file: refuse to resume, in one line
            msg = " ".join(str(err).split())[:300]
            raise PolicyError(
                f"{self.dir}: cannot resume training from this state ({type(err).__name__}: {msg}); "
                "move the directory away to start over"
            ) from None
        return images, actions, progress


def _data_keys(policy) -> tuple[str, ...]:
    """The arrays of a training data set: every camera the policy reads, and its states if it reads any."""
    return policy_cameras(policy) + ((_STATE,) if policy_contract(policy).state else ())


def _train_steps(policy, optimizer, images, actions, steps: int, batch: int, rng: np.random.Generator, device) -> float:
    """``steps`` Adam steps on minibatches of ``images`` (``{camera: (T, H_c, W_c, 3)}``, and the
    ``(T, D)`` states under ``"_state"`` for a policy reading them) and ``actions``."""
    n = len(actions)
    if steps == 0 or n == 0:
        return float("nan")
    policy.train()
    losses = []
    for _ in range(steps):
        idx = rng.integers(0, n, size=min(batch, n))
        views = {
            c: torch.from_numpy(v[idx]).to(device).permute(0, 3, 1, 2).float().div_(255.0)
            for c, v in images.items()
            if c != _STATE
        }
        x = views[WRIST_CAMERA] if tuple(views) == (WRIST_CAMERA,) else views  # one camera: the tensor, as always
        y = torch.from_numpy(actions[idx]).to(device)
        st = torch.from_numpy(images[_STATE][idx]).to(device) if _STATE in images else None
        loss = torch.nn.functional.mse_loss(policy(x) if st is None else policy(x, st), y)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    policy.eval()
    return float(np.mean(losses[-max(1, steps // 5) :]))


def train_dagger(
    policy,
    env,
    cfg: DaggerConfig,
    env_cfg: EnvConfig,
    out_dir: str | Path,
    seed: int = 0,
    fingerprint: str = "",
    device="cpu",
    progress: bool = True,
    log=print,
) -> dict:
    """Train ``policy`` in place with DAgger in ``env``; resumes from ``out_dir/train_state``.

    Args:
        policy: a :class:`sim.policies.policy.VisuomotorPolicy` on ``device``.
        env: a :class:`sim.env.ReachEnv` with ``cfg.num_envs`` envs at the policy's image size,
            rendering every camera the policy reads (``cameras=policy.cameras``).
        env_cfg: the training randomisation (evaluation switches it off temporarily).
        fingerprint: identifies the run's resolved config; resuming with another one is refused.

    Returns the progress record: per-iteration frames, loss, wall time, success rates.
    """
    out_dir = Path(out_dir)
    if env.num_envs != cfg.num_envs:
        raise ValueError(f"env has {env.num_envs} envs, config says num_envs={cfg.num_envs}")
    optimizer = torch.optim.Adam(policy.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    state = _State(out_dir)
    cams = policy_cameras(policy)
    contract = policy_contract(policy)
    keys = _data_keys(policy)
    images = {c: np.zeros((0, *env.image_shape(c)), np.uint8) for c in cams}
    if contract.state:
        images[_STATE] = np.zeros((0, contract.state_dim), np.float32)
    actions = np.zeros((0, contract.action_dim), np.float32)
    prog = {
        "fingerprint": fingerprint,
        "iterations_done": 0,
        "elapsed_s": 0.0,
        "cpu_s": 0.0,
        "history": [],
        "stopped_early": False,
    }
    if state.exists():
        images, actions, prog = state.load(policy, optimizer, fingerprint)
        log(
            f"resuming after iteration {prog['iterations_done']} ({len(actions)} frames, "
            f"{prog['elapsed_s']:.0f} s so far)"
        )
    clean = EnvConfig(image_size=env_cfg.image_size)
    N = cfg.num_envs
    batches = -(-cfg.episodes_per_iter // N)
    bar = tqdm(total=cfg.iterations, initial=prog["iterations_done"], desc="dagger", unit="iter", disable=not progress)
    for it in range(prog["iterations_done"], cfg.iterations):
        if prog["stopped_early"]:
            break
        t0, c0 = time.perf_counter(), time.process_time()
        torch.manual_seed(seed * 1000 + it)
        rng = np.random.default_rng([seed, it])
        beta = cfg.beta(it)
        set_randomization(env, env_cfg)
        driven_success = []
        new_x, new_y = [], []
        misses = env.expert_ik_misses
        # Per-episode progress inside the iteration: the first one alone can take minutes.
        episodes = tqdm(
            total=batches * N,
            desc=f"dagger {it + 1}/{cfg.iterations}: episodes",
            unit="ep",
            leave=False,
            disable=not progress,
        )
        try:
            for b in range(batches):
                seeds = [TRAIN_SEED_BASE + seed * 1_000_000 + it * 10_000 + b * N + j for j in range(N)]
                expert_mask = rng.random(N) < beta
                x, y, success, driven = collect(env, policy, expert_mask, seeds)
                new_x.append(x)
                new_y.append(y)
                driven_success += success[driven].tolist()
                episodes.update(N)
                if driven_success:
                    episodes.set_postfix(policy_success=f"{np.mean(driven_success):.2f}")
        finally:
            episodes.close()
        images = {c: np.concatenate([images[c], *(x[c] for x in new_x)])[-cfg.max_frames :] for c in keys}
        actions = np.concatenate([actions, *new_y])[-cfg.max_frames :]
        loss = _train_steps(policy, optimizer, images, actions, cfg.grad_steps_per_iter, cfg.batch_size, rng, device)
        record = {
            "iteration": it,
            "beta": beta,
            "frames": int(len(actions)),
            "loss": loss,
            "policy_driven_success": float(np.mean(driven_success)) if driven_success else None,
            "policy_driven_episodes": len(driven_success),
        }
        if env.control == "joint":
            record["expert_ik_misses"] = int(env.expert_ik_misses - misses)
        if cfg.eval_episodes:
            te, ce = time.perf_counter(), time.process_time()
            set_randomization(env, clean)
            res = run_episodes(env, policy, range(cfg.eval_episodes))
            record["clean_success"] = res.success_rate.rate
            log(f"iteration {it + 1}/{cfg.iterations}: clean success {res.success_rate}")
            # Evaluation is measurement, not training: its time is excluded from the budget.
            t0 += time.perf_counter() - te
            c0 += time.process_time() - ce
            if cfg.stop_at_success is not None and res.success_rate.rate >= cfg.stop_at_success:
                prog["stopped_early"] = True
        prog["elapsed_s"] += time.perf_counter() - t0
        prog["cpu_s"] = (
            prog.get("cpu_s", 0.0) + time.process_time() - c0
        )  # CPU time of all threads: the cost on an idle machine
        record["elapsed_s"], record["cpu_s"] = prog["elapsed_s"], prog["cpu_s"]
        prog["history"].append(record)
        prog["iterations_done"] = it + 1
        state.save(policy, optimizer, images, actions, prog)
        bar.update(1)
        bar.set_postfix(loss=f"{loss:.4f}", frames=len(actions), clean=record.get("clean_success"))
    bar.close()
    set_randomization(env, env_cfg)
    policy.eval()
    return prog
