"""The evaluation harness behind ``advobj eval``: paired closed-loop episodes per condition.

For every condition the same task-feasible initial configurations are rolled out for up to
``max_steps`` steps with the policy acting on the *attacked* observation. At every step the clean
observation of the same state (the adversarial object in its benign look, same light, same
background, same sensor-noise draw) is rendered too, in the same frame via a renderer variant, and
the policy's action on it gives the per-step action errors (:func:`trials.eval.metrics.action_errors`).
The episodes themselves are :func:`sim.policies.paired.rollout_paired`'s, the core the
task-feasible pool is built with too (:func:`sim.policies.pool.build_feasible`).

Rendering is the standard pyrender path (:class:`sim.render.SceneRenderer`) with the texture on
the mesh. Episodes run ``num_envs`` at a time; a slot whose episode ends is refilled at once, and
each finished episode is appended to ``episodes.csv`` immediately, so an interrupted evaluation
resumes without redoing anything (:mod:`trials.eval.episodes`).
"""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path
from typing import Callable

import numpy as np
from pydantic import Field, ValidationError
from tqdm import tqdm

from attack.artifact import overlap_count
from sim.action import POLICY_ERROR
from sim.configio import StrictModel
from sim.configs import PoolError, in_part, load_pool, save_pool
from sim.errors import AdvobjError, format_validation_error
from sim.imaging import labelled, write_gif
from sim.policies.checkpoint import load_policy
from sim.policies.competence import DEFAULT_MIN_CLEAN_SUCCESS, require_competence
from sim.policies.contract import check_scene, policy_cameras, policy_contract, to_delta
from sim.policies.paired import rollout_paired
from sim.policies.pool import build_feasible, built_pool_path, feasible_pool_path
from sim.runinfo import write_run_info
from sim.spec import load_spec
from trials.eval.conditions import Sources, build_conditions, condition_spec
from trials.eval.episodes import EpisodeStore, read_rows, write_summary
from trials.eval.metrics import action_errors
from trials.eval.report import summarize, write_report

__all__ = [
    "EvalError",
    "EvalWarning",
    "EvalConfig",
    "rollout_condition",
    "resolve_pool",
    "overlap_with_training",
    "run_eval",
    "merge_eval",
    "load_eval_config",
]


class EvalError(AdvobjError, ValueError):
    """Bad evaluation config or inputs."""


class EvalWarning(UserWarning):
    """Something the evaluation cannot check (e.g. a texture without a configuration record)."""


class EvalConfig(StrictModel):
    """Everything that defines an evaluation (stored in ``manifest.json``; resume must match)."""

    policy: str = Field(description="target policy: checkpoint directory or .onnx file")
    conditions: tuple[str, ...] = ("clean", "attack")
    episodes: int = Field(500, ge=1, description="episodes per condition (the paper: 500)")
    max_steps: int = Field(60, ge=1, description="steps per episode (the paper: 60)")
    num_envs: int = Field(8, ge=1, description="episodes rolled out in parallel")
    seed: int = Field(0, ge=0, description="first candidate seed when a task-feasible pool is built")
    pool_factor: int = Field(4, ge=1, description="building a pool tries up to episodes * pool_factor candidates")
    pool: str | None = Field(None, description="task-feasible pool JSON (default: the policy's, else built)")
    scene: str | None = None
    attack: str | None = None
    patch: str | None = None
    shapes: dict[str, str] = Field(default_factory=dict)
    gifs: int = Field(2, ge=0, description="configurations recorded as rollout GIFs per condition")
    device: str = "cpu"
    allow_overlap: bool = Field(
        False, description="score textures on configurations they were optimised or selected on (in-sample)"
    )


def load_eval_config(**fields) -> EvalConfig:
    try:
        return EvalConfig(**fields)
    except ValidationError as err:
        raise EvalError(format_validation_error(err, "evaluation config")) from None


# ---------------------------------------------------------------------------------------------
def rollout_condition(
    policy, spec, cond, configs, num_envs: int, on_done: Callable[[int, dict], None], on_frame: Callable | None = None
) -> None:
    """Roll out one episode per config under ``cond``; call ``on_done(j, result)`` as each ends.

    The episodes are :func:`sim.policies.paired.rollout_paired`'s (the same core builds the
    task-feasible pool, :func:`sim.policies.pool.build_feasible`); this adds the condition's scene
    and the per-step action errors.

    Args:
        policy: ``act(images (B, S, S, 3) uint8) -> (B, 6)`` with ``image_size = S`` (or its
            contract's actions: a joint-space policy runs on the scene's arm, and its action errors
            are those of the TCP motions its joint steps lead to, by FK).
        spec: the scene (``max_steps`` already applied); the condition's mesh swap happens here.
        cond: a :class:`trials.eval.conditions.Condition`.
        configs: initial configurations (:class:`sim.configs.InitialConfig`).
        num_envs: parallel slots.
        on_done: ``on_done(j, result)`` with ``j`` the index into ``configs`` and ``result`` a
            dict: ``reached`` (object index, -1 none), ``steps``, ``min_dist (K,)`` m,
            ``e_trans`` and ``e_rot`` (episode means; NaN for a zero-step episode).
        on_frame: optional ``on_frame(j, step, adv_rgb, clean_rgb)`` for every observation the
            policy acts on (left camera), e.g. to write GIFs.
    """
    if not configs:
        return
    spec_c = condition_spec(spec, cond)
    kind, ep = policy_contract(policy).action.kind, spec_c.episode
    slot_of = [-1] * max(1, int(num_envs))  # config index per slot
    err = np.zeros((len(slot_of), 3))  # summed e_trans, e_rot, and the number of policy calls

    def fill(i: int, j: int) -> None:
        slot_of[i] = j
        err[i] = 0.0

    def measure(slots, T, steps, a_adv, a_clean, views, q=None, arm=None):
        # a joint action's error is that of the TCP motions its joint step leads to (FK, q= and arm=)
        e_t, e_r = action_errors(
            to_delta(T, a_adv[:, 0], kind, ep.max_step_m, ep.max_step_rad, q=q, arm=arm),
            to_delta(T, a_clean[:, 0], kind, ep.max_step_m, ep.max_step_rad, q=q, arm=arm),
            ep.max_step_rad,
        )
        if on_frame is not None:
            for k, i in enumerate(slots):
                on_frame(slot_of[i], int(steps[k]), views[k]["adv"][0], views[k]["clean"][0])
        err[slots, 0] += e_t
        err[slots, 1] += e_r
        err[slots, 2] += 1

    def done(j, i, res):
        n = err[i, 2]  # errors are measured where the policy is asked (every step unless chunked)
        on_done(
            j,
            {
                "reached": res["reached"],
                "policy_error": res["policy_error"],
                "steps": res["steps"],
                "min_dist": res["min_dist"],
                "e_trans": float(err[i, 0] / n) if n else float("nan"),
                "e_rot": float(err[i, 1] / n) if n else float("nan"),
            },
        )

    rollout_paired(
        policy,
        spec_c,
        configs,
        num_envs,
        done,
        texture=cond.texture,
        stereo=cond.stereo,
        randomization=cond.randomization,
        on_fill=fill,
        on_actions=measure,
        attacked_cameras=cond.attacked_cameras,
    )


def resolve_pool(
    cfg: EvalConfig,
    policy,
    spec,
    out: Path,
    progress: bool = True,
    final: bool = False,
    min_clean_success: float = DEFAULT_MIN_CLEAN_SUCCESS,
) -> tuple[list, str]:
    """The task-feasible configurations of the split's "evaluation" part, and where they came from.

    Only evaluation-part configurations are ever used (:func:`sim.configs.config_part`): attacks
    draw theirs from the other parts, so no texture is scored on a configuration it was optimised
    or selected on. The base is ``cfg.pool`` (it must match the scene), else the policy's own pool
    (:func:`sim.policies.pool.feasible_pool_path`) if it was made for this scene and episode
    length; its evaluation-part configurations are used as they are. When they are fewer than
    ``cfg.episodes``, more are built here (:func:`sim.policies.pool.build_feasible`, candidate
    seeds of the evaluation part from ``cfg.seed`` on) and the result is saved as
    ``out/feasible_pool.json``, which a resumed evaluation reuses. ``final``: ``cfg.pool`` is the
    pool to use as it is, even short (a grid's pool job already built it; its shards must not
    build more each). Before more are built, the competence gate
    (:func:`sim.policies.competence.require_competence` at ``min_clean_success``, 0: off) refuses a
    policy that does not do the task.
    """
    path = built_pool_path(out)
    if path.is_file():  # built by an earlier (interrupted) run of this evaluation: keep using it
        return in_part(load_pool(path, spec), "evaluation"), str(path)
    base, src = [], None
    if cfg.pool is not None:
        base, src = load_pool(cfg.pool, spec), str(cfg.pool)
    else:
        own = feasible_pool_path(Path(cfg.policy)) if Path(cfg.policy).is_dir() else None
        if own is not None and own.is_file():
            try:
                base, src = load_pool(own, spec), str(own)
            except PoolError:
                base = []  # made for another scene or episode length: build one for this evaluation
    configs = in_part(base, "evaluation")
    if len(configs) >= cfg.episodes or (final and cfg.pool is not None):
        return configs, src
    require_competence(
        policy, spec, min_clean_success, seed=cfg.seed, num_envs=cfg.num_envs, progress=progress, name=cfg.policy
    )
    extra, tried = build_feasible(
        policy,
        spec,
        "evaluation",
        cfg.episodes - len(configs),
        cfg.seed,
        cfg.num_envs,
        exclude=[c.seed for c in base],
        max_candidates=cfg.episodes * cfg.pool_factor,
        progress=progress,
    )
    feasible = configs + extra
    if not feasible:
        raise EvalError(
            f"policy {cfg.policy}: reached the goal in none of {tried} candidate configurations; nothing is "
            "task-feasible"
        )
    save_pool(
        path,
        spec,
        feasible,
        meta={
            "definition": "configs where the clean policy reaches the goal",
            "policy": cfg.policy,
            "part": "evaluation",
            "base": src,
            "from_base": len(configs),
            "candidates": tried,
            "first_seed": cfg.seed,
            "max_steps": spec.episode.max_steps,
        },
    )
    return feasible, str(path)


def overlap_with_training(configs, conds) -> dict:
    """Per condition with a texture: how many of ``configs`` its texture was optimised or selected
    on (``None``: the texture directory has no configuration record), by content id or by pose
    (:func:`attack.artifact.overlap_count`: the same poses under another seed count too)."""
    out = {}
    for cond in conds:
        if cond.source is not None:
            seen = cond.source.trained_on
            out[cond.name] = None if seen is None else overlap_count(configs, seen)
    return out


def _row(cond_name: str, config, res: dict, spec) -> dict:
    goal, adv = spec.object_index("goal"), spec.object_index("adversarial")
    reached = res["reached"]
    outcome = (
        POLICY_ERROR  # a non-finite action ended the episode (the real runner's rule too)
        if res.get("policy_error")
        else "none"
        if reached < 0
        else ("goal" if reached == goal else ("adversarial" if reached == adv else spec.objects[reached].name))
    )
    row = {
        "condition": cond_name,
        "seed": int(config.seed),
        "r_m": float(config.r_m),
        "theta_rad": float(config.theta_rad),
        "phi_rad": float(config.phi_rad),
        "outcome": outcome,
        "reached": int(reached),
        "success": reached == goal,
        "targeted": reached == adv,
        "steps": int(res["steps"]),
        "e_trans": float(res["e_trans"]),
        "e_rot": float(res["e_rot"]),
    }
    for o, d in zip(spec.objects, res["min_dist"]):
        row[f"min_dist_{o.name}"] = float(d)
    return row


def _prepare(cfg: EvalConfig, out: Path, policy, progress: bool, final_pool: bool, min_clean_success: float = 0.0):
    """The conditions, scene, configurations, pool source, overlap and resolved config of an
    evaluation (refusing an in-sample one): what every shard and the merge share. With a policy, the
    competence gate at ``min_clean_success`` (:func:`run_eval`) before anything is written."""
    base = load_spec(cfg.scene)
    spec = base.with_updates(episode={**base.episode.model_dump(), "max_steps": cfg.max_steps})
    conds = build_conditions(cfg.conditions, Sources(cfg.attack, cfg.patch, dict(cfg.shapes), spec))
    # A camera the scene lacks (or of another size): one line, before anything is written. The merge
    # of shards passes no policy (each shard checked it with its own).
    if policy is not None:
        check_scene(policy, spec)
    for c in conds if policy is not None else ():
        for name in c.attacked_cameras or ():
            if name not in policy_cameras(policy):
                raise EvalError(
                    f"condition {c.name!r}: the policy reads {', '.join(policy_cameras(policy))}; it does not read "
                    f"camera {name!r}"
                )
    if policy is not None:  # the card's figure now; without one, measured before a pool is built (resolve_pool)
        require_competence(policy, spec, min_clean_success, measure=False, name=cfg.policy)
    configs, pool_src = resolve_pool(
        cfg, policy, spec, out, progress, final=final_pool, min_clean_success=min_clean_success
    )
    out.mkdir(parents=True, exist_ok=True)
    configs = configs[: cfg.episodes]
    overlap = overlap_with_training(configs, conds)
    leaked = {k: v for k, v in overlap.items() if v}
    if leaked and not cfg.allow_overlap:
        k, v = next(iter(leaked.items()))
        raise EvalError(
            f"condition {k!r}: its texture was optimised or selected on {v} of the {len(configs)} evaluation "
            "configurations "
            "(an in-sample score); use a pool of the evaluation part, or pass --allow-overlap to score it anyway"
        )
    unknown = sorted(k for k, v in overlap.items() if v is None)
    if unknown:
        warnings.warn(
            f"condition(s) {', '.join(unknown)}: the texture directory records no training configurations "
            "(configs.json), "
            "so its overlap with the evaluation cannot be checked",
            EvalWarning,
            stacklevel=3,
        )
    resolved = {
        "job": "eval",
        "eval": cfg.model_dump(mode="json"),
        "conditions": [c.to_dict() for c in conds],
        "pool": pool_src,
        "seeds": [int(c.seed) for c in configs],
        "overlap": overlap,
        "scene": spec.model_dump(mode="json"),
    }
    return conds, spec, configs, pool_src, overlap, resolved


def _finish(cfg: EvalConfig, out: Path, rows: list, spec, conds, configs, pool_src, overlap, report: bool) -> dict:
    # In a fixed order: means and intervals then do not depend on the order episodes finished in.
    rows = sorted(rows, key=lambda r: (r["condition"], r["seed"]))
    summary = summarize(
        rows,
        spec,
        [c.name for c in conds],
        meta={
            "pool": pool_src,
            "episodes_requested": cfg.episodes,
            "episodes_available": len(configs),
            "policy": cfg.policy,
            "max_steps": cfg.max_steps,
            "overlap": overlap,
        },
    )
    write_summary(out, summary, default=_json_default)
    if report:
        write_report(out, summary, conds, spec)
    return summary


def run_eval(
    cfg: EvalConfig,
    out: str | Path,
    resume: bool = False,
    progress: bool = True,
    report: bool = True,
    shard: tuple[int, int] | None = None,
    final_pool: bool = False,
    min_clean_success: float = DEFAULT_MIN_CLEAN_SUCCESS,
) -> dict:
    """Run (or resume) an evaluation into ``out``; returns the summary (also ``summary.json``).

    ``min_clean_success``: the competence gate (:mod:`sim.policies.competence`; 0: off): a card
    that records the policy's clean success on this scene (at this episode length) below it refuses
    the evaluation (:class:`sim.policies.competence.IncompetentPolicyError`) before anything is
    written; without such a card, the success is measured before a task-feasible pool is built.

    ``shard=(k, K)`` runs only configurations ``k, k + K, ...`` of the evaluation (a job of a
    sharded evaluation, merged by :func:`merge_eval`). Sharding changes no configuration, noise
    draw or seed: each episode depends on its configuration alone (the policy acts on fixed-size
    batches, :func:`rollout_condition`), so its row is the same in any shard.
    """
    out = Path(out)
    policy = load_policy(cfg.policy, cfg.device)
    conds, spec, configs, pool_src, overlap, resolved = _prepare(
        cfg, out, policy, progress, final_pool, min_clean_success
    )
    gif_seeds = {int(c.seed) for c in configs[: cfg.gifs]}
    if shard is not None:
        k, n = (int(x) for x in shard)
        if not 0 <= k < n:
            raise EvalError(f"shard: index {k} not in 0..{n - 1}")
        configs = configs[k::n]
        resolved = {**resolved, "shard": [k, n], "seeds": [int(c.seed) for c in configs]}
    store = EpisodeStore(out, resolved, [o.name for o in spec.objects], resume=resume)
    write_run_info(out, resolved, cfg.seed)
    todo = {c.name: [x for x in configs if not store.is_done(c.name, x.seed)] for c in conds}
    bar = tqdm(total=sum(len(v) for v in todo.values()), desc="eval", disable=not progress, dynamic_ncols=True)
    for cond in conds:
        cfgs = todo[cond.name]
        if not cfgs:
            continue
        bar.set_postfix(condition=cond.name, refresh=False)
        frames: dict[int, list] = {}

        def on_frame(j, step, adv_rgb, clean_rgb, cfgs=cfgs, frames=frames, cond=cond):
            if cfgs[j].seed in gif_seeds:
                frames.setdefault(j, []).append(labelled(adv_rgb, f"{cond.name}  config {cfgs[j].seed}  step {step}"))

        def on_done(j, res, cfgs=cfgs, cond=cond, frames=frames):
            if j in frames:
                _write_gif(out / "gifs" / f"{cond.name}_seed{cfgs[j].seed}.gif", frames.pop(j))
            store.append([_row(cond.name, cfgs[j], res, spec)])
            bar.update(1)

        rollout_condition(
            policy, spec, cond, cfgs, cfg.num_envs, on_done, on_frame if gif_seeds & {c.seed for c in cfgs} else None
        )
    bar.close()
    return _finish(cfg, out, store.rows, spec, conds, configs, pool_src, overlap, report and shard is None)


def merge_eval(cfg: EvalConfig, out: str | Path, shard_dirs) -> dict:
    """Merge the shards of one evaluation (:func:`run_eval` with ``shard``) into ``out``: the
    episodes, GIFs, manifest, summary and report the evaluation run whole writes there."""
    out = Path(out)
    conds, spec, configs, pool_src, overlap, resolved = _prepare(cfg, out, None, False, True)
    store = EpisodeStore(out, resolved, [o.name for o in spec.objects], resume=True)
    write_run_info(out, resolved, cfg.seed)
    want = {(c.name, int(x.seed)) for c in conds for x in configs}
    rows = []
    for d in shard_dirs:
        d = Path(d)
        rows += [r for r in read_rows(d) if not store.is_done(r["condition"], r["seed"])]
        for gif in sorted((d / "gifs").glob("*.gif")) if (d / "gifs").is_dir() else []:
            (out / "gifs").mkdir(parents=True, exist_ok=True)
            shutil.copyfile(gif, out / "gifs" / gif.name)
    unique = {}
    for r in rows:  # one row per (condition, seed), whatever a retried shard left behind
        unique.setdefault((r["condition"], r["seed"]), r)
    rows = list(unique.values())
    got = {(r["condition"], r["seed"]) for r in store.rows} | set(unique)
    if got != want or len(store.rows) + len(rows) != len(want):
        raise EvalError(
            f"{out}: the shards hold {len(got)} of the {len(want)} episodes (missing e.g. {sorted(want - got)[:1]})"
        )
    order = {(c.name, int(x.seed)): i for i, (c, x) in enumerate((c, x) for c in conds for x in configs)}
    store.append(sorted(rows, key=lambda r: order[(r["condition"], r["seed"])]))
    return _finish(cfg, out, store.rows, spec, conds, configs, pool_src, overlap, True)


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    raise TypeError(f"not JSON-able: {type(o).__name__}")


def _write_gif(path: Path, frames: list) -> None:
    write_gif(path, frames)
