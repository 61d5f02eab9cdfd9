"""The attack loop: EOT over short policy rollouts, C2F scheduling, PCGrad, normalised updates.

Each iteration (paper Sec. III-B/C):

1. draw ``num_envs`` initial configurations from the task-feasible pool's "attack" part with the schedule's
   Beta weights over camera distance;
2. roll each out for ``rollout_steps`` steps, the policy acting on ``I_adv`` (hybrid render under
   the current texture); rollouts only provide viewpoints (no backprop through the dynamics);
3. accumulate the gradient of each objective term (:mod:`attack.objective`: the pose and saliency
   terms) over all image-action pairs, combine them with PCGrad over the N terms (summed), and take
   ``T <- clip(T - lr * g / ||g||, 0, 1)``.

Steps 1-2 are the frame source's (:class:`attack.sources.SimRollouts`; with ``recordings``,
:class:`attack.recorded.RecordedFrames` instead: recorded frames with the object composited in, open
loop, no simulator env); step 3 is the objective's and :func:`attack_step`'s. :class:`AttackRun`
holds the machinery (env, renderer, policy, objective, source); :class:`attack.state.AttackState`
everything an iteration advances.

A run is resumable bit-for-bit: a checkpoint holds the texture, the iteration (which fixes the
schedule stage), the loss history and every RNG state.

Anytime quality: every checkpoint holds the evaluation-ready ``texture.npy``; with
``validation_every > 0`` a held-out validation pool (the split's "validation" part, disjoint
from the EOT configurations and from every evaluation) is rolled out with the standard renderer
every ``validation_every`` iterations, and ``best/`` keeps the texture with the highest validation
T-ASR so far (a valid ``advobj eval --attack`` source).
"""

from __future__ import annotations

import json
import time
import warnings
from pathlib import Path
from typing import Callable, Literal

import numpy as np
import torch
from PIL import Image
from pydantic import Field, ValidationError
from tqdm import tqdm

from attack.artifact import AttackArtifact, texture_to_uint8
from attack.losses import pose_loss
from attack.objective import FrameBatch, build_objective
from attack.pcgrad import normalized_step, pcgrad_many, sum_gradients
from attack.recorded import VALIDATION_MEASURE, RecordedFrames
from attack.render import HybridRenderer, render_adversarial_batch
from attack.schedule import stage_index
from attack.sources import SimRollouts
from attack.state import AttackState, better_score, find_checkpoint, read_best, swap_in
from sim.configio import StrictModel
from sim.configs import in_part, sample_pool
from sim.env import ReachEnv
from sim.errors import AdvobjError, format_validation_error
from sim.outcome import object_distances
from sim.policies.checkpoint import as_white_box
from sim.policies.contract import (
    WRIST_CAMERA,
    check_scene,
    first_action,
    policy_cameras,
    policy_contract,
    state_vector,
    to_delta,
    to_joint_target,
)
from sim.policies.interface import require_white_box
from sim.policies.rollout import rollout
from sim.variations import Randomization

__all__ = [
    "AttackConfig",
    "AttackError",
    "AttackWarning",
    "PRESETS",
    "resolve_config",
    "fixed_light_warning",
    "initial_texture",
    "AttackRun",
    "attack_step",
    "run_attack",
    "read_cpu_record",
    "CPU_RECORD",
]

#: The key of a checkpoint's ``run.json`` config that holds the loop's CPU time and budget.
CPU_RECORD = "cpu"


class AttackError(AdvobjError, ValueError):
    """Bad attack configuration or inputs."""


class AttackWarning(UserWarning):
    """A setting the attack had to adapt (e.g. a validation pool cut to what the pool allows)."""


class AttackConfig(StrictModel):
    """All knobs of one attack run (see ``docs/configuration.md``)."""

    iterations: int = Field(10_000, ge=1)
    num_envs: int = Field(4, ge=1, description="EOT: initial configurations per iteration")
    rollout_steps: int = Field(10, ge=1)
    lr: float = Field(0.1, gt=0, description="eta: step length of the normalised update")
    lambda_dist: float = Field(0.1, ge=0)
    lambda_sal: float = Field(0.01, ge=0)
    loss: Literal["targeted", "untargeted"] = "targeted"
    use_pose: bool = True
    use_saliency: bool = True
    pcgrad: bool = True
    schedule: Literal["c2f", "f2c", "ns", "coarse", "fine"] = "c2f"
    sampler: Literal["bilinear", "trilinear"] = "trilinear"
    texture_size: int = Field(256, ge=4, le=4096)
    init_texture: Literal["benign", "gray", "random"] = "benign"
    adversarial_mesh: str | None = Field(None, description="override the scene's adversarial mesh (e.g. 'patch')")
    light_randomization: bool = False
    print_aware: bool = False
    pool_size: int = Field(200, ge=1, description="configurations generated when the policy has no task-feasible pool")
    checkpoint_every: int = Field(50, ge=1)
    validation_every: int = Field(0, ge=0, description="iterations between held-out validations (0 = off)")
    validation_episodes: int = Field(16, ge=1, description="held-out configurations per validation")
    validation_max_steps: int | None = Field(
        None, ge=1, description="episode length of a validation rollout (None: the scene's max_steps)"
    )
    recordings: str | None = Field(
        None,
        description="a recording folder (advobj record import): optimise on its frames with the object composited "
        "in (attack.recorded), validate on its held-out episodes, instead of simulator rollouts",
    )
    max_cpu_s: float | None = Field(
        None,
        gt=0,
        le=1e7,
        description="CPU budget (s, every thread of the process; a resumed run counts its earlier sessions): the run "
        "ends at the first iteration that reaches it, validated and checkpointed as a finished one (None: no budget)",
    )
    seed: int = 0
    device: str = "cpu"


PRESETS: dict[str, dict] = {
    # Seconds on 2 CPU cores: a test-sized run through every stage the quick preset uses (EOT, the C2F
    # stages, held-out validation and best/, checkpoints), as the training presets' "ci"; its budget
    # says nothing about what an attack can do.
    "ci": {
        "iterations": 4,
        "num_envs": 2,
        "rollout_steps": 2,
        "texture_size": 16,
        "lr": 1.0,
        "checkpoint_every": 2,
        "validation_every": 2,
        "validation_episodes": 4,
        "validation_max_steps": 10,
    },
    # A few minutes on 2 CPU cores. The paper's eta = 0.1 moves a 256^2 texture too little in a
    # few hundred steps; a smaller texture and a larger step make the short run count.
    # Validation every 20 iterations on 16 held-out configurations: 1.27 s a call at 64 px, 8.4 s
    # of a 43.3 s run (7 calls; results/table2/attacks.json, arm c2f, "validation").
    "quick": {
        "iterations": 120,
        "num_envs": 4,
        "rollout_steps": 6,
        "texture_size": 64,
        "lr": 1.0,
        "checkpoint_every": 20,
        "validation_every": 20,
        "validation_episodes": 16,
    },
    # The paper's run: 10k iterations, 4 envs x 10 steps (policy at 128x128). A long run is the one
    # most likely to be stopped early, so it keeps a validated best/ texture: 50 validations of 32
    # held-out episodes, a few percent of the run.
    # Lighting randomisation on, as the paper's sim-to-real path: measured with the quick preset it cost
    # 1.5% more time per iteration and bought +1.8 / +3.0 pp T-ASR under the bright / dim lights
    # (p 0.049 / 0.0026, n = 500) at no loss under the nominal one (results/lighting/).
    "paper": {
        "iterations": 10_000,
        "num_envs": 4,
        "rollout_steps": 10,
        "texture_size": 256,
        "lr": 0.1,
        "checkpoint_every": 200,
        "validation_every": 200,
        "validation_episodes": 32,
        "light_randomization": True,
    },
}


def resolve_config(preset: str, overrides: dict | None = None, source: str = "<overrides>") -> AttackConfig:
    """Preset fields, then ``overrides`` (e.g. from ``--config attack.yaml``); unknown keys fail."""
    if preset not in PRESETS:
        raise AttackError(f"preset: unknown preset {preset!r}; choose one of {sorted(PRESETS)}")
    try:
        return AttackConfig(**{**PRESETS[preset], **(overrides or {})})
    except ValidationError as err:
        raise AttackError(format_validation_error(err, "attack config", source)) from None


def fixed_light_warning(cfg: AttackConfig) -> str | None:
    """The warning for a texture optimised under the scene's one fixed light (None when the lights
    are randomised): said before an attack runs, not after the texture is made."""
    if cfg.light_randomization:
        return None
    return (
        "warning: light_randomization is off: the texture is optimised under the scene's one fixed light and "
        "may lose much of its effect under other lights, a real cell's included; for a texture to print, "
        "attack with --light-randomization (or light_randomization: true in --config; the paper preset has it "
        "on; 'advobj experiment lighting' measures the difference)"
    )


# ---------------------------------------------------------------------------------------------
def _with_adversarial_mesh(spec, mesh: str | None):
    """``spec`` with its adversarial object's mesh swapped for ``mesh`` (None: ``spec`` itself)."""
    if mesh is None:
        return spec
    objs = [o.with_mesh(mesh) if o.role == "adversarial" else o.model_dump() for o in spec.objects]
    return spec.with_updates(objects=objs)


def _benign_texture(mesh, size: int) -> np.ndarray:
    img = getattr(getattr(mesh.visual, "material", None), "image", None)
    if img is None:
        return np.full((size, size, 3), 0.5)
    return np.asarray(img.convert("RGB").resize((size, size), Image.BILINEAR), dtype=np.float64) / 255.0


def initial_texture(cfg: AttackConfig, mesh) -> torch.Tensor:
    """Starting texture ``(3, S, S)`` float in [0, 1] (float32, on ``cfg.device``), ``S =
    cfg.texture_size``: ``init_texture`` benign, the mesh's own texture image resized (plain grey
    without one); gray, flat mid grey; random, uniform noise from ``cfg.seed``. The evaluation's
    ``benign`` arm shows it unoptimised (:func:`trials.eval.conditions.start_source`)."""
    s = cfg.texture_size
    if cfg.init_texture == "benign":
        arr = _benign_texture(mesh, s)
    elif cfg.init_texture == "gray":
        arr = np.full((s, s, 3), 0.5)
    else:
        arr = np.random.default_rng(cfg.seed).random((s, s, 3))
    return torch.from_numpy(arr).permute(2, 0, 1).to(cfg.device, torch.float32).contiguous()


class AttackRun:
    """An attack on ``policy`` in ``spec``; drives the loop and owns the checkpoints.

    Args:
        policy: a white-box policy: a :class:`sim.policies.policy.VisuomotorPolicy`, a ``.pt2`` or
            converted ``.onnx`` file's :class:`sim.policies.graph_policy.GraphPolicy`; an
            :class:`sim.policies.onnx_policy.OnnxPolicy` is converted here (``sim.policies.checkpoint.as_white_box``).
        spec: the scene; ``cfg.adversarial_mesh`` may swap the adversarial object's mesh.
        cfg: the :class:`AttackConfig`.
        pool: task-feasible initial configurations (``None``: generated from the scene, unfiltered).
        out_dir: run directory (checkpoints live in ``out_dir/checkpoint``).
    """

    def __init__(self, policy, spec, cfg: AttackConfig, pool=None, out_dir: str | Path | None = None):
        # An ONNX file's torch conversion, checked against onnxruntime on frames of this scene
        # (sim.policies.onnx_torch); a refused conversion ends here, before anything is rendered or written.
        policy = as_white_box(policy, cfg.device, spec)
        require_white_box(policy)
        self.cfg = cfg
        self.device = torch.device(cfg.device)
        self.policy = policy.to(self.device).eval()
        for p in self.policy.parameters():
            p.requires_grad_(False)
        self.validation_measure = "T-ASR"
        self.cpu_s = 0.0  # CPU time of the loop so far (run_attack), earlier sessions of a resumed run included
        if cfg.recordings is not None:
            self._init_recorded(policy, spec, pool, out_dir)
            return
        validating = cfg.validation_every > 0
        # The held-out split (sim.configs.config_part): EOT only ever sees the "attack" part and
        # the best texture is picked on the "validation" part; evaluations use neither.
        if pool is None:
            attack_pool = sample_pool(spec, cfg.pool_size, seed=cfg.seed, part="attack")
            val_pool = (
                sample_pool(spec, cfg.validation_episodes, seed=cfg.seed, part="validation") if validating else []
            )
        else:
            pool = list(pool)
            attack_pool, val_pool = in_part(pool, "attack"), in_part(pool, "validation")
        spec = _with_adversarial_mesh(spec, cfg.adversarial_mesh)
        self.spec = spec
        self.image_size = int(policy.image_size)

        # The training rollouts re-plan at every step (the first action of each chunk): the pose
        # loss is defined on the action executed next; validation executes k of K as evaluation does.
        self.contract = policy_contract(policy)
        self.pool = attack_pool
        if not self.pool:
            raise AttackError(
                "pool: no task-feasible configurations in the attack part of the split (sim.configs.config_part) "
                "to attack from; give a larger pool"
            )
        self.val_pool: list = []
        if validating:
            if not val_pool:
                raise AttackError(
                    "validation_episodes: the pool holds no configuration of the validation part of the split; "
                    "give a larger pool or set validation_every: 0"
                )
            if len(val_pool) < cfg.validation_episodes:
                warnings.warn(
                    f"validation_episodes: the pool holds only {len(val_pool)} configurations of the validation "
                    "part; validating on "
                    f"{len(val_pool)} instead of {cfg.validation_episodes}. Give a larger pool (--pool) for a "
                    "steadier validation "
                    "score, or set validation_every: 0",
                    AttackWarning,
                    stacklevel=2,
                )
            self.val_pool = val_pool[: cfg.validation_episodes]
        randomization = Randomization(light="random") if cfg.light_randomization else None
        # Every camera the policy reads, and only those; one hybrid renderer each. The saliency
        # term reads the wrist camera's feature map (the first camera's if the policy has no wrist).
        check_scene(policy, spec)
        self.cameras = policy_cameras(policy)
        self.saliency_camera = WRIST_CAMERA if WRIST_CAMERA in self.cameras else self.cameras[0]
        self.env = ReachEnv(
            spec,
            num_envs=cfg.num_envs,
            seed=cfg.seed,
            randomization=randomization,
            render_obs=False,
            policy_image_size=self.image_size if WRIST_CAMERA in self.cameras else None,
            cameras=self.cameras,
            control=self.contract.control,
        )
        # A joint-space policy's pose loss reads the TCP its joint action leads to: the scene's arm on
        # the run's device, FK differentiable (sim.policies.contract.to_delta).
        self.arm = spec.arm.scene_arm(cfg.device) if self.contract.is_joint_space else None
        self.hybrids = {name: HybridRenderer(self.env.renderers[name], camera=name) for name in self.cameras}
        self.hybrid = self.hybrids[self.saliency_camera]
        self.adv = self.hybrid.adv
        self.objective = build_objective(cfg, spec.episode)
        self.source = SimRollouts(self.env, self.hybrid, spec, self.pool, cfg, self.device, self.hybrids)
        self.adv_mesh = self.env.renderer.object_mesh(self.adv)
        self.state = AttackState.start(initial_texture(cfg, self.adv_mesh), cfg.seed)
        self.out_dir = None if out_dir is None else Path(out_dir)
        self._val_env = None

    def _init_recorded(self, policy, spec, pool, out_dir) -> None:
        """A recordings run (``cfg.recordings``): :class:`attack.recorded.RecordedFrames` is the source
        and scores the held-out episodes; no simulator env or configuration pool exists (``env`` is None)."""
        cfg = self.cfg
        if pool is not None:
            raise AttackError("pool: a recordings attack draws no simulator configurations; give no pool")
        self.spec = spec = _with_adversarial_mesh(spec, cfg.adversarial_mesh)
        self.image_size = int(policy.image_size)
        self.contract = policy_contract(policy)
        if self.contract.is_joint_space:
            raise AttackError(
                f"recordings: a joint-space policy ({self.contract.describe()}) is attacked in the simulator only: a "
                "recording holds no joint positions (attack it without --recordings, on a scene with its arm)"
            )
        self.arm = None
        check_scene(policy, spec)
        self.cameras = policy_cameras(policy)
        self.saliency_camera = WRIST_CAMERA if WRIST_CAMERA in self.cameras else self.cameras[0]
        self.pool, self.val_pool = [], []
        self.env, self.hybrids, self.hybrid, self._val_env = None, {}, None, None
        self.source = RecordedFrames.open(cfg.recordings, spec, cfg, policy, self.saliency_camera, self.device)
        self.validation_measure = VALIDATION_MEASURE
        self.adv, self.adv_mesh = self.source.adv, self.source.object_mesh
        self.objective = build_objective(cfg, spec.episode)
        self.state = AttackState.start(initial_texture(cfg, self.adv_mesh), cfg.seed)
        self.out_dir = None if out_dir is None else Path(out_dir)

    # ------------------------------------------------------------------ validation
    def validate(self) -> dict:
        """Roll the policy out on the held-out configurations with the current texture.

        Same semantics as the evaluation's ``attack`` condition: the standard pyrender renderer
        with the texture (rounded to 8 bits, as ``texture.npy`` is loaded) on the adversarial
        mesh, no appearance variation or sensor noise, up to ``validation_max_steps`` (default the
        scene's ``max_steps``) steps. Uses no training RNG, so it never perturbs the run.

        Returns ``{"t_asr", "dist_m", "episodes", "seconds"}``: the fraction of episodes that reach
        the adversarial object first, and the mean TCP-to-adversarial-object distance (m) at the
        end of the episodes (the tie-breaker: lower is better).
        """
        if self.env is None:  # a recordings run: its held-out recorded frames
            return self.source.validate(self)
        if not self.val_pool:
            raise AttackError("validation_every: validation is off (no held-out configurations)")
        t0 = time.perf_counter()
        configs = self.val_pool
        if self._val_env is None:
            spec = self.spec
            if self.cfg.validation_max_steps is not None:
                spec = spec.with_updates(
                    episode={**spec.episode.model_dump(), "max_steps": self.cfg.validation_max_steps}
                )
            # Batches of equal size (the largest divisor of the pool size up to 8): no idle slots.
            n = max(d for d in range(1, min(8, len(configs)) + 1) if len(configs) % d == 0)
            self._val_env = ReachEnv(
                spec,
                num_envs=n,
                seed=self.cfg.seed,
                policy_image_size=self.image_size if WRIST_CAMERA in self.cameras else None,
                cameras=self.cameras,
                control=self.contract.control,
            )
        env = self._val_env
        for name in self.cameras:  # every camera the policy reads shows the texture
            env.renderers[name].set_object_texture(self.adv, texture_to_uint8(self.state.texture))
        targeted = np.zeros(len(configs), bool)
        dist = np.zeros(len(configs))

        def done(j, slot, res):
            targeted[j] = res["reached"] == self.adv
            dist[j] = object_distances(res["T_world_tcp"][None, :3, 3], env.worlds[slot].object_center_array[None])[
                0, self.adv
            ]

        rollout(env, configs, self.policy, done)
        return {
            "t_asr": float(np.mean(targeted)),
            "dist_m": float(np.mean(dist)),
            "episodes": len(configs),
            "seconds": time.perf_counter() - t0,
        }

    def probe_pose_loss(self) -> float:
        """Mean pose loss over the first frame of every validation configuration under the
        current texture (hybrid render, no rollout): the same images at every call, so a change
        is the texture's doing. NaN when the run has no pose term. Uses no training RNG."""
        cfg = self.cfg
        if self.env is None:  # a recordings run: its held-out recorded frames
            return self.source.probe_pose_loss(self)
        if not any(t.name == "pose" for t in self.objective.terms) or not self.val_pool:
            return float("nan")
        env, total, n = self.env, 0.0, 0
        with torch.no_grad():
            for start in range(0, len(self.val_pool), cfg.num_envs):
                chunk = self.val_pool[start : start + cfg.num_envs]
                env.reset_envs(range(len(chunk)), configs=chunk)
                imgs = self.render_views(self.capture_views(range(len(chunk))), self.state.texture)
                T = torch.from_numpy(env.T_world_tcp[: len(chunk)]).to(self.device, torch.float32)
                q = None if env.q is None else torch.from_numpy(env.q[: len(chunk)]).to(self.device)
                a = self.next_delta(self.call_policy(imgs, self.policy_state(T, q)), T, q)
                p_adv = torch.from_numpy(env.object_centers[: len(chunk), self.adv]).to(self.device, torch.float32)
                lp, _ = pose_loss(
                    T, a, p_adv, self.spec.episode.max_step_m, self.spec.episode.max_step_rad, cfg.lambda_dist
                )
                total += float(lp.sum())
                n += len(chunk)
        return total / max(n, 1)

    def validate_and_keep_best(self) -> bool:
        """Validate, log it in the history and, if the score improved, write ``best/``; returns
        whether it improved."""
        res = self.validate()
        h = self.state.history
        h.val_probe_pose.append(self.probe_pose_loss())
        h.val_iteration.append(self.state.iteration)
        h.val_t_asr.append(res["t_asr"])
        h.val_dist_m.append(res["dist_m"])
        h.val_seconds.append(res["seconds"])
        if not better_score(res, self.state.best):
            return False
        self.state.best = {
            "iteration": self.state.iteration,
            "t_asr": res["t_asr"],
            "dist_m": res["dist_m"],
            "episodes": res["episodes"],
        }
        self.state.best_texture = self.state.texture.detach().clone()
        if self.out_dir is not None:
            self._write_best()
        return True

    def _write_best(self) -> Path:
        tmp = self.out_dir / "best.tmp"
        tmp.mkdir(parents=True, exist_ok=True)
        self._write_attack_source(
            tmp, self.state.best_texture, {"best_of": "held-out validation T-ASR", **self.state.best}
        )
        (tmp / "best.json").write_text(
            json.dumps({**self.state.best, "score": "t_asr (higher), then dist_m (lower)"}, indent=2)
        )
        return swap_in(tmp, self.out_dir / "best")

    def _write_attack_source(self, d: Path, texture: torch.Tensor, extra: dict) -> None:
        """A texture folder (:class:`attack.artifact.AttackArtifact`): what ``advobj eval --attack DIR`` reads."""
        # Only the attack config (the mesh the texture belongs to): the run directory's own
        # run.json has the provenance, and asking git for it at every checkpoint costs seconds.
        config = {"job": "attack", "attack": self.cfg.model_dump(), **extra}
        AttackArtifact.from_tensor(texture, config, self.cfg.seed).save(d, run="plain")

    # ------------------------------------------------------------------ the cameras
    def capture_views(self, slots) -> dict:
        """``{camera: [Capture]}`` of the env's worlds ``slots`` through every camera the policy reads."""
        return {name: [h.capture(self.env.worlds[i]) for i in slots] for name, h in self.hybrids.items()}

    def render_views(self, views: dict, texture: torch.Tensor, color_transform=None):
        """The policy's differentiable input under ``texture``: ``(B, 3, H, W)`` for a one-camera
        policy, else ``{camera: (B, 3, H_c, W_c)}`` (one color transform for all cameras)."""
        imgs = {
            name: render_adversarial_batch(caps, texture, self.cfg.sampler, color_transform)
            for name, caps in views.items()
        }
        return imgs[self.cameras[0]] if len(self.cameras) == 1 else imgs

    # ------------------------------------------------------------------ the policy's contract
    def policy_state(self, T_world_tcp: torch.Tensor, q: torch.Tensor | None = None) -> torch.Tensor | None:
        """The policy's state input for TCP poses ``(B, 4, 4)`` and, under joint control, joint
        positions ``q (B, n)`` (None when it reads none)."""
        qn = None if q is None else q.detach().cpu().numpy()
        st = state_vector(self.contract, T_world_tcp.detach().cpu().numpy(), self.spec.gripper.opening_m, qn)
        return None if st is None else torch.from_numpy(st).to(self.device)

    def call_policy(self, imgs: torch.Tensor, state: torch.Tensor | None) -> torch.Tensor:
        return self.policy(imgs) if state is None else self.policy(imgs, state)

    def next_delta(self, out: torch.Tensor, T_world_tcp: torch.Tensor, q: torch.Tensor | None = None) -> torch.Tensor:
        """``(B, 6)`` normalised delta of the first action of each output (every action kind): a joint
        action's is the motion to the TCP pose its joint step reaches, through the arm's FK,
        differentiably (``q (B, n)``: the joint positions it starts from)."""
        ep = self.spec.episode
        kind = self.contract.action.kind
        return to_delta(T_world_tcp, first_action(out), kind, ep.max_step_m, ep.max_step_rad, q=q, arm=self.arm)

    def env_commands(self, batch: FrameBatch, q: torch.Tensor | None) -> np.ndarray:
        """What the env executes for ``batch``'s frames: the TCP motions ``(B, 6)`` (the batch's
        actions), or under joint control the joint targets ``(B, n)`` of the first action of each
        output (the env applies the joint limits)."""
        if q is None:
            return batch.actions.detach().cpu().numpy()
        with torch.no_grad():
            st = batch.state
            out = self.policy.head(batch.features) if st is None else self.policy.head(batch.features, st)
            a = first_action(out).to(q.dtype)
            return to_joint_target(q, a, self.contract.action.kind).cpu().numpy()

    # ------------------------------------------------------------------ one iteration
    def _color_transform(self, state: AttackState):
        if not self.cfg.print_aware:
            return None
        g = 1.0 + (torch.rand(3, generator=state.torch_gen) - 0.5) * 0.3  # gain in [0.85, 1.15]
        b = (torch.rand(3, generator=state.torch_gen) - 0.5) * 0.1  # bias in [-0.05, 0.05]
        return g.to(self.device), b.to(self.device)

    def frame_gradients(self, state: AttackState, frames) -> dict:
        """Each objective term's texture gradient over one batch of frames (:class:`attack.sources.Frames`).

        Returns ``grads`` (term name -> ``(3, S, S)``, the sum over the batch; zeros where a term
        has no path to the texture, e.g. the object is not visible in any image), ``values`` (term
        name -> its scalar, and ``<term>.<part>`` -> the sum of each logged part), ``actions
        (B, 6)`` (detached), ``commands`` (numpy: what the env executes, :meth:`env_commands`) and
        the rendered ``images (B, 3, H, W)`` (detached; ``{camera: ...}``
        for a policy reading several cameras: the texture is rendered into each, and the loss flows
        through all of them). Draws the print colour transform from ``state``'s torch RNG.
        """
        tex = state.texture.detach().clone().requires_grad_(True)
        ct = self._color_transform(state)
        views = frames.views if frames.views is not None else {self.cameras[0]: frames.captures}
        imgs = self.render_views(views, tex, ct)
        several = isinstance(imgs, dict)
        # No image shows an optimisable pixel of the object (out of view, occluded, too far):
        # nothing reaches the texture. The losses are still logged, and Grad-CAM needs a graph
        # from the images to the feature map (the frozen weights give it none), hence a leaf.
        reaches = any(v.requires_grad for v in imgs.values()) if several else imgs.requires_grad
        if several:
            x = {k: v if v.requires_grad else v.detach().requires_grad_(True) for k, v in imgs.items()}
        else:
            x = imgs if reaches else imgs.detach().requires_grad_(True)
        q = getattr(frames, "q", None)  # joint control: the frames' joint positions
        batch = FrameBatch(
            images=x,
            T_world_tcp=frames.T_world_tcp,
            p_adv=frames.p_adv,
            adv_mask=np.stack([c.adv_mask for c in frames.captures]),
            goal_mask=np.stack([c.goal_mask for c in frames.captures]),
            policy=self if q is None else _JointFrames(self, q),
            clean_images=lambda: frames.clean_images(self.device),
            saliency_camera=self.saliency_camera if several else None,
        )
        losses = self.objective.losses(batch, state.iteration, self.cfg.iterations)
        grads, values = {}, {}
        for k, (name, loss, parts) in enumerate(losses):
            g = torch.zeros_like(state.texture)
            if reaches and loss.requires_grad:
                later = any(lo.requires_grad for _, lo, _ in losses[k + 1 :])
                g = torch.autograd.grad(loss, tex, retain_graph=later)[0]
            grads[name] = g
            values[name] = float(loss.detach())
            for part, v in parts.items():
                values[f"{name}.{part}"] = float(v.sum())
        detached = {k: v.detach() for k, v in imgs.items()} if several else imgs.detach()
        return {
            "grads": grads,
            "values": values,
            "actions": batch.actions.detach(),
            "commands": self.env_commands(batch, q),
            "images": detached,
        }

    def apply_update(self, state: AttackState, grads: list[torch.Tensor]) -> tuple[torch.Tensor, bool]:
        """Combine the term gradients (PCGrad over all N, or their sum) and step ``state.texture``.

        Returns ``(g, updated)``; a zero or non-finite combined gradient (or no term at all) leaves
        the texture unchanged and ``updated`` False.
        """
        if not grads:
            g = torch.zeros_like(state.texture)
        else:
            g = pcgrad_many(grads) if self.cfg.pcgrad else sum_gradients(grads)
        state.texture, updated = normalized_step(state.texture, g, self.cfg.lr)
        return g, updated

    def step(self) -> dict:
        """Run one iteration (:func:`attack_step` on this run's state); returns its logged figures."""
        return attack_step(self, self.state)

    # ------------------------------------------------------------------ checkpoints
    def save_checkpoint(self) -> Path:
        """Atomically write ``out_dir/checkpoint`` (:class:`attack.state.AttackState`'s files)."""
        if self.out_dir is None:
            raise AttackError("out_dir is needed for checkpoints")
        tmp = self.out_dir / "checkpoint.tmp"
        tmp.mkdir(parents=True, exist_ok=True)
        self.state.write(tmp, self.cfg.model_dump())
        # The evaluation-ready texture of this checkpoint (a user can stop here and use it):
        # checkpoint/ is itself a valid ``advobj eval --attack`` source.
        self._write_attack_source(
            tmp, self.state.texture, {"checkpoint_iteration": self.state.iteration, CPU_RECORD: self.cpu_record()}
        )
        return swap_in(tmp, self.out_dir / "checkpoint")

    def cpu_record(self) -> dict:
        """What the loop's CPU time and budget were at this point: ``cpu_s`` (s, the loop's, earlier
        sessions included), ``max_cpu_s`` (the budget, None without one), ``iterations`` done of
        ``iterations_planned``, and whether the budget ended the run (``stopped_at_budget``). Kept in
        the checkpoint's ``run.json`` config (:func:`read_cpu_record`)."""
        cfg = self.cfg
        return {
            "cpu_s": round(self.cpu_s, 3),
            "max_cpu_s": cfg.max_cpu_s,
            "iterations": self.state.iteration,
            "iterations_planned": cfg.iterations,
            "stopped_at_budget": cfg.max_cpu_s is not None
            and self.state.iteration < cfg.iterations
            and self.cpu_s >= cfg.max_cpu_s,
        }

    def load_checkpoint(self, ckpt: str | Path) -> None:
        """Restore a checkpoint written by :meth:`save_checkpoint` (same config required)."""
        ckpt = Path(ckpt)
        try:
            state, config = AttackState.read(ckpt, self.device)
        except (OSError, ValueError, KeyError) as err:
            raise AttackError(f"{ckpt}: unreadable checkpoint ({err})") from None
        # A checkpoint written before a config field existed holds that field's default.
        saved = AttackConfig(**config)
        if saved != self.cfg:
            diff = sorted(k for k in AttackConfig.model_fields if getattr(saved, k) != getattr(self.cfg, k))
            hint = "; ".join(f"{k}: checkpoint {getattr(saved, k)!r}, now {getattr(self.cfg, k)!r}" for k in diff)
            raise AttackError(
                f"{ckpt}: checkpoint was made with a different config (fields: {', '.join(diff)}; {hint}); "
                "resume with the checkpoint's values or start a new run directory"
            )
        self.state = state
        self.cpu_s = float((_checkpoint_config(ckpt).get(CPU_RECORD) or {}).get("cpu_s", 0.0))
        # best/ may be newer than the checkpoint (a crash between the two writes); it is the
        # larger score, and replaying the iterations in between reproduces it exactly.
        disk = read_best(ckpt.parent / "best")
        if disk is not None and better_score(disk[0], self.state.best):
            self.state.best, self.state.best_texture = disk[0], disk[1].to(self.device)

    def close(self) -> None:
        if self.env is None:
            self.source.close()
            return
        self.env.close()
        if self._val_env is not None:
            self._val_env.close()
            self._val_env = None


def _checkpoint_config(ckpt: Path) -> dict:
    """The ``run.json`` config of checkpoint folder ``ckpt`` (empty when it has none)."""
    try:
        return AttackArtifact.load(ckpt, error=AttackError).config
    except AttackError:
        return {}


def read_cpu_record(run_dir: str | Path) -> dict | None:
    """The CPU record (:meth:`AttackRun.cpu_record`) of the attack run in ``run_dir``, as of its latest
    checkpoint (a finished run's last one); None when it has none."""
    ckpt = find_checkpoint(run_dir)
    rec = None if ckpt is None else _checkpoint_config(ckpt).get(CPU_RECORD)
    return rec if isinstance(rec, dict) else None


class _JointFrames:
    """The run as a batch of joint-controlled frames sees it (:class:`attack.objective.FrameBatch`'s
    ``policy``): the run's policy adapter with the frames' joint positions ``q (B, n)`` bound, so
    the state input and the pose loss's motion read them."""

    def __init__(self, run: AttackRun, q: torch.Tensor):
        self.run, self.q = run, q

    @property
    def policy(self):
        return self.run.policy

    def policy_state(self, T_world_tcp: torch.Tensor) -> torch.Tensor | None:
        return self.run.policy_state(T_world_tcp, self.q)

    def next_delta(self, out: torch.Tensor, T_world_tcp: torch.Tensor) -> torch.Tensor:
        return self.run.next_delta(out, T_world_tcp, self.q)

    def call_policy(self, imgs, state):
        return self.run.call_policy(imgs, state)


def attack_step(run: AttackRun, state: AttackState) -> dict:
    """One iteration of the attack: frames from ``run.source`` under ``state``'s texture, each
    objective term's gradient summed over them, the combined gradient, the normalised step.
    Advances ``state`` (texture, iteration, history, RNGs) and the source's scratch episodes;
    returns the logged figures (``terms``: each term's mean per image-action pair)."""
    cfg = run.cfg
    names = [t.name for t in run.objective.terms]
    grads = {n: torch.zeros_like(state.texture) for n in names}
    sums = {n: 0.0 for n in names}
    sums.update({f"{t.name}.{p}": 0.0 for t in run.objective.terms for p in getattr(t, "parts", ())})
    pairs = 0
    run.source.start(state.iteration, state.rng)
    while (frames := run.source.next()) is not None:
        out = run.frame_gradients(state, frames)
        for n in names:
            grads[n] += out["grads"][n]
        for k, v in out["values"].items():
            sums[k] = sums.get(k, 0.0) + v
        pairs += len(frames)
        run.source.advance(out["commands"])
    # Mean over image-action pairs (the normalised step makes the scale moot, but the
    # logged gradient norm is comparable across runs).
    for n in names:
        grads[n] /= max(pairs, 1)
    g, updated = run.apply_update(state, [grads[n] for n in names])
    h = state.history
    h.iteration.append(state.iteration)
    h.log_terms({k: v / max(pairs, 1) for k, v in sums.items()})
    h.grad_norm.append(float(torch.linalg.vector_norm(g)))
    h.stage.append(stage_index(state.iteration, cfg.iterations) if cfg.schedule in ("c2f", "f2c") else -1)
    h.skipped += 0 if updated else 1
    state.iteration += 1
    terms = {n: h.terms[n][-1] for n in names}
    return {
        "terms": terms,
        "pose": terms.get("pose", 0.0),
        "sal": terms.get("saliency", 0.0),
        "pairs": pairs,
        "updated": updated,
    }


def run_attack(
    run: AttackRun,
    progress: bool = True,
    on_iteration: Callable[[AttackRun, dict], None] | None = None,
    desc: str = "attack",
) -> AttackRun:
    """Iterate to ``cfg.iterations`` with validation and checkpoints; Ctrl-C saves a checkpoint,
    then re-raises. The one attack loop: ``on_iteration(run, info)`` runs after each iteration's
    validation and checkpoint (the tradeoff sweep writes its snapshots there). With
    ``cfg.max_cpu_s``, the first iteration at which the loop's CPU time (``time.process_time``: every
    thread, validation included; a resumed run adds its earlier sessions') reaches the budget is the
    last: validated and checkpointed as the final one; the checkpoint records the CPU time, the budget
    and the iterations done (:func:`read_cpu_record`)."""
    cfg = run.cfg
    bar = tqdm(total=cfg.iterations, initial=run.state.iteration, desc=desc, disable=not progress, dynamic_ncols=True)
    t0, c0 = time.perf_counter(), time.process_time()
    start_seconds, start_cpu = run.state.history.seconds, run.cpu_s
    validating = cfg.validation_every > 0
    budget = cfg.max_cpu_s
    try:
        if validating and not run.state.history.val_iteration:
            run.validate_and_keep_best()  # the starting texture is the first "best so far"
        spent = budget is not None and run.cpu_s >= budget  # a resumed run that had reached its budget
        while run.state.iteration < cfg.iterations and not spent:
            info = run.step()
            run.cpu_s = start_cpu + time.process_time() - c0
            spent = budget is not None and run.cpu_s >= budget  # the CPU budget ends the run here
            last = run.state.iteration == cfg.iterations or spent
            if validating and (run.state.iteration % cfg.validation_every == 0 or last):
                run.validate_and_keep_best()
            run.state.history.seconds = start_seconds + time.perf_counter() - t0
            run.cpu_s = start_cpu + time.process_time() - c0
            post = {name: f"{v:.4g}" for name, v in info["terms"].items()}
            if run.state.history.val_t_asr:
                post["val_t_asr"] = f"{run.state.history.val_t_asr[-1]:.2f}"
            bar.set_postfix(post, refresh=False)
            bar.update(1)
            if run.out_dir is not None and (run.state.iteration % cfg.checkpoint_every == 0 or last):
                run.save_checkpoint()
            if on_iteration is not None:
                on_iteration(run, info)
    except KeyboardInterrupt:
        if run.out_dir is not None:
            run.cpu_s = start_cpu + time.process_time() - c0
            run.save_checkpoint()
        raise
    finally:
        bar.close()
    return run
