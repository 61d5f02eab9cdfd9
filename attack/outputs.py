"""What an attack run writes besides its texture folder (:mod:`attack.artifact`): textured meshes,
plots and overlays."""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import matplotlib
import matplotlib.pyplot as plt
import numpy as np
import torch
import torch.nn.functional as F
import trimesh
from PIL import Image

from attack.artifact import AttackArtifact, texture_to_uint8, write_config_record
from attack.losses import grad_cam
from sim.imaging import hstack, labelled, upscale
from sim.runinfo import RunInfoError, read_run_info, write_run_info

__all__ = [
    "textured_mesh",
    "export_meshes",
    "plot_losses",
    "gradcam_overlay",
    "write_outputs",
]


def textured_mesh(mesh, texture_rgb: np.ndarray):
    """A copy of ``mesh`` carrying ``texture_rgb (H, W, 3)`` uint8 on its UVs."""
    m = mesh.copy()
    m.visual = trimesh.visual.TextureVisuals(uv=np.asarray(mesh.visual.uv), image=Image.fromarray(texture_rgb))
    return m


OBJ_UNITS = {"m": 1.0, "mm": 1000.0}


def export_meshes(
    out_dir: str | Path, mesh, texture_rgb: np.ndarray, stem: str = "adversarial", obj_units: str = "m"
) -> dict[str, Path]:
    """Write ``stem.glb`` and ``stem.obj`` (+ .mtl + .png) for color 3D printing or re-rendering.

    The GLB follows the glTF spec: metres, +Y up (our +Z becomes +Y), so viewers show the object
    standing. The OBJ stays +Z up (slicers' convention) in ``obj_units`` (m, or mm for print
    services, which assume mm), and says both in its first line, since OBJ has no unit field.
    """
    if obj_units not in OBJ_UNITS:
        raise ValueError(f"--units: expected m or mm, got {obj_units!r}")
    out = Path(out_dir)
    m = textured_mesh(mesh, texture_rgb)
    g = m.copy()
    v = np.asarray(g.vertices, dtype=np.float64)
    g.vertices = np.stack([v[:, 0], v[:, 2], -v[:, 1]], -1)  # +Z up -> glTF's +Y up
    glb = out / f"{stem}.glb"
    glb.write_bytes(g.export(file_type="glb"))
    obj_dir = out / f"{stem}_obj"
    obj_dir.mkdir(parents=True, exist_ok=True)
    o = m.copy()
    o.vertices = np.asarray(o.vertices, dtype=np.float64) * OBJ_UNITS[obj_units]
    obj = obj_dir / f"{stem}.obj"
    o.export(obj, file_type="obj")
    obj.write_text(f"# advobj: units {obj_units}, +Z up (in a scene YAML: units: {obj_units})\n" + obj.read_text())
    return {"glb": glb, "obj": obj}


def plot_losses(path: str | Path, history, measure: str = "T-ASR") -> Path:
    """``loss_curves.png``: the held-out validation T-ASR first (the figure that says whether the
    attack works), then the pose and saliency terms and the gradient norm, with a note on why the
    pose loss is no measure of progress."""
    matplotlib.use("Agg")

    h = history
    val = bool(getattr(h, "val_iteration", None))
    fig, axes = plt.subplots(1, 4 if val else 3, figsize=(16 if val else 12, 3.6))
    axes = list(axes)
    if val:
        ax = axes.pop(0)
        ax.plot(h.val_iteration, h.val_t_asr, marker="o")
        ax.set_ylim(-0.02, 1.02)
        ax.set_title(f"held-out validation {measure.split(' (')[0]}")
        ax.set_xlabel("iteration")
        probe = getattr(h, "val_probe_pose", None)
        if probe and np.isfinite(probe).any():
            axes[0].plot(h.val_iteration[: len(probe)], probe, marker="o", color="k", label="pose, fixed probe set")
    # Every objective term and logged part by its name (attack.objective); saliency on its own axis.
    for name, values in h.terms.items():
        if name != "saliency" and len(values) == len(h.iteration):
            axes[0].plot(h.iteration, values, label=name, alpha=1.0 if "." not in name else 0.7)
    axes[0].set_title("objective terms (mean per pair; see note)")
    if h.terms:
        axes[0].legend()
    axes[1].plot(h.iteration, h.loss_saliency)
    axes[1].set_title("lambda_sal * saliency term")
    axes[2].semilogy(h.iteration, np.maximum(np.asarray(h.grad_norm), 1e-12))
    axes[2].set_title("|g| (after PCGrad)")
    for ax in axes:
        ax.set_xlabel("iteration")
    fig.text(0.5, 0.01, "Note: " + POSE_LOSS_NOTE, ha="center", va="bottom", fontsize=7)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)


# Why the pose loss cannot be read as progress: printed with every summary and on the plot.
POSE_LOSS_NOTE = (
    "the pose loss is measured on rollouts that move as the attack succeeds (the policy walks towards the object, "
    "so the views change), so its level is not comparable across iterations; judge the attack by the held-out "
    "validation T-ASR"
)


def summary_lines(metrics: dict) -> list[str]:
    """The end-of-run summary, the held-out validation T-ASR first."""
    v = metrics.get("validation")
    lines = [f"attack done: {metrics['iterations']} iterations in {metrics['seconds']:.0f} s"]
    if v:
        best = v.get("best") or {}
        lines.append(
            f"held-out validation {v.get('measure', 'T-ASR')} (n = {best.get('episodes', '?')}): {v['t_asr'][0]:.2f} "
            "at the start -> "
            f"{v['t_asr'][-1]:.2f} at the end; best {best.get('t_asr', float('nan')):.2f} at iteration "
            f"{best.get('iteration', '?')} (best/)"
        )
    else:
        lines.append(
            "held-out validation: off (validation_every: 0); evaluate the texture with 'advobj eval' to know "
            "what it does"
        )
    if metrics.get("final_loss_pose") is not None:
        lines.append(
            f"pose loss {metrics['initial_loss_pose']:.3f} -> {metrics['final_loss_pose']:.3f} (first / last tenth "
            "of the run): " + POSE_LOSS_NOTE
        )
    for name, t in (metrics.get("loss_terms") or {}).items():
        if name != "pose" and "." not in name:
            lines.append(f"{name} term {t['initial']:.4g} -> {t['final']:.4g} (first / last tenth of the run)")
    probe = [x for x in ((v or {}).get("probe_pose_loss") or []) if x == x]
    if probe:
        lines.append(
            f"pose loss on the fixed probe set (the validation configurations' first frames, comparable across "
            f"iterations): {probe[0]:.3f} -> {probe[-1]:.3f}"
        )
    return lines


def gradcam_overlay(
    policy, image, state: torch.Tensor | None = None, to_action=None, camera: str | None = None
) -> np.ndarray:
    """``image (3, H, W)`` (or ``{camera: (3, H_c, W_c)}`` for a policy reading several cameras,
    with ``camera`` the one shown) and the policy's ``state (1, D)`` -> (H, W, 3) uint8 with the
    Grad-CAM map blended in red."""
    if isinstance(image, dict):
        x = {k: v[None].detach().clone().requires_grad_(True) for k, v in image.items()}
        shown = image[camera]
    else:
        x = image[None].detach().clone().requires_grad_(True)  # gives A a graph (weights are frozen)
        shown = image
    A = policy.features(x)
    out = policy.head(A) if state is None else policy.head(A, state)
    # ``to_action``: the head's output -> the motion executed next (AttackRun.next_delta), as the
    # saliency loss explains it; without it, the whole output
    S = grad_cam(A[camera] if isinstance(A, dict) else A, to_action(out) if to_action is not None else out.flatten(1))
    S = S.detach()[0]
    S = F.interpolate(S[None, None], size=shown.shape[-2:], mode="bilinear", align_corners=False)[0, 0]
    S = (S / S.max().clamp_min(1e-12)).cpu().numpy()
    rgb = shown.detach().cpu().permute(1, 2, 0).numpy()
    heat = np.stack([S, np.zeros_like(S), np.zeros_like(S)], -1)
    return np.clip(255 * (0.55 * rgb + 0.45 * heat * 1.0 + 0.0), 0, 255).astype(np.uint8)


def _first(images, camera: str):
    """Frame 0 of the policy's input: ``(3, H, W)``, or ``{camera: (3, H_c, W_c)}``."""
    return {k: v[0] for k, v in images.items()} if isinstance(images, dict) else images[0]


def _records_config(out: Path, attack_config: dict) -> bool:
    """Whether ``out/run.json`` exists and records ``attack_config`` as its attack config."""
    try:
        return read_run_info(out)["config"].get("attack") == attack_config
    except RunInfoError:
        return False


def write_outputs(run, out_dir: str | Path, texture_before: torch.Tensor) -> dict:
    """Write a finished run's folder: the texture (``texture.npy``, ``texture.png``), ``run.json``,
    ``configs.json``, the textured meshes, the plots and ``metrics.json``; returns the metrics.

    ``run.json`` (the attack config and the scene the texture was optimised in, with provenance) is
    kept when it already records this run's attack config: ``advobj attack run`` writes its own
    before the run, with the preset, the policy and the pool. ``configs.json`` records the
    configurations the attack drew from and validated on (:func:`attack.artifact.write_config_record`),
    which ``advobj eval`` checks its own against. With these, the folder is what ``advobj eval
    --attack`` and ``advobj fabricate`` read. The checkpoint and ``best/`` are
    :func:`attack.optimize.run_attack`'s (a run with ``out_dir``).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tex = run.state.texture.detach().cpu()
    AttackArtifact.from_tensor(tex).save(out, run="none")  # run.json: the job's if it wrote one, else below
    if not _records_config(out, run.cfg.model_dump()):
        write_run_info(
            out,
            {"job": "attack", "attack": run.cfg.model_dump(), "scene": run.spec.model_dump(mode="json")},
            run.cfg.seed,
        )
    write_config_record(out, run.pool, run.val_pool)
    paths = export_meshes(out, run.adv_mesh, texture_to_uint8(tex))
    plot_losses(out / "loss_curves.png", run.state.history, run.validation_measure)
    if run.env is None:  # a recordings run (attack.recorded): its figures show recorded frames
        _recorded_figures(run, out, texture_before)
    else:
        _rollout_figures(run, out, texture_before)
    h = run.state.history
    tail = max(1, len(h.iteration) // 10)
    pose = h.terms.get("pose")
    metrics = {
        "iterations": run.state.iteration,
        "seconds": h.seconds,
        "seconds_per_iteration": h.seconds / max(1, len(h.iteration)),
        # The same without the held-out validation rollouts (comparable with validation off).
        "seconds_per_iteration_training": (h.seconds - float(np.sum(getattr(h, "val_seconds", []) or [0.0])))
        / max(1, len(h.iteration)),
        "final_loss_pose": float(np.mean(pose[-tail:])) if pose else None,
        "initial_loss_pose": float(np.mean(pose[:tail])) if pose else None,
        "final_loss_saliency": float(np.mean(h.loss_saliency[-tail:])) if h.loss_saliency else None,
        # every term of the objective by name (attack.objective), first and last tenth of the run
        "loss_terms": {
            k: {"initial": float(np.mean(v[:tail])), "final": float(np.mean(v[-tail:]))}
            for k, v in h.terms.items()
            if v
        },
        "skipped_updates": h.skipped,
        "validation": None
        if not getattr(h, "val_iteration", None)
        else {
            "iteration": h.val_iteration,
            "t_asr": h.val_t_asr,
            "dist_m": h.val_dist_m,
            "seconds_per_call": float(np.median(h.val_seconds)),
            "seconds_total": float(np.sum(h.val_seconds)),
            "best": run.state.best,
            "probe_pose_loss": h.val_probe_pose,
            "measure": run.validation_measure,  # what "t_asr" holds (a recordings run: attack.recorded)
        },
        "texture_change_l2": float(torch.linalg.vector_norm(tex - texture_before.cpu())),
        "meshes": {k: str(v.relative_to(out)) for k, v in paths.items()},
    }
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return metrics


def _rollout_figures(run, out: Path, texture_before: torch.Tensor) -> None:
    """Grad-CAM before/after and a rollout strip from the same configuration (the pool's first)."""
    env = run.env
    env.reset_envs([0], configs=[run.pool[0]])
    views = run.capture_views([0])
    before = _first(run.render_views(views, texture_before.to(run.device)), run.saliency_camera)
    after = _first(run.render_views(views, run.state.texture), run.saliency_camera)
    cam = run.saliency_camera
    seed = run.pool[0].seed
    T0 = torch.from_numpy(env.T_world_tcp[:1]).to(run.device, torch.float32)
    st = run.policy_state(T0)

    def motion(o):
        return run.next_delta(o, T0)

    iio.imwrite(
        out / "gradcam_before_after.png",
        hstack(
            [
                labelled(
                    gradcam_overlay(run.policy, before, st, motion, cam), f"Grad-CAM, starting texture (config {seed})"
                ),
                labelled(
                    gradcam_overlay(run.policy, after, st, motion, cam), f"Grad-CAM, final texture (config {seed})"
                ),
            ]
        ),
    )
    frames = []
    for _ in range(8):
        if env.done[0]:
            break
        imgs = run.render_views(run.capture_views([0]), run.state.texture)
        img = imgs[cam][0] if isinstance(imgs, dict) else imgs[0]
        frames.append(labelled(texture_to_uint8(img), f"attack, step {len(frames)}", min_side=128))
        with torch.no_grad():
            T = torch.from_numpy(env.T_world_tcp[:1]).to(run.device, torch.float32)
            a = run.next_delta(run.call_policy(imgs, run.policy_state(T)), T).cpu().numpy()
        actions = np.zeros((env.num_envs, 6))
        actions[0] = a[0]
        env.step(actions)
    iio.imwrite(out / "rollout_strip.png", upscale(hstack(frames)))


def _recorded_figures(run, out: Path, texture_before: torch.Tensor) -> None:
    """Grad-CAM before/after on a recorded frame with the object composited in, and a strip of that
    episode's next recorded steps under the final texture (open loop: the recorded trajectory)."""
    frames, labels = run.source.examples(8)
    views = frames.views if frames.views is not None else {run.cameras[0]: frames.captures}
    cam = run.saliency_camera
    T0 = frames.T_world_tcp[:1]
    st = run.policy_state(T0)

    def motion(o):
        return run.next_delta(o, T0)

    overlays = []
    for texture, what in ((texture_before.to(run.device), "starting"), (run.state.texture, "final")):
        one = _first(run.render_views({k: v[:1] for k, v in views.items()}, texture), cam)
        overlays.append(
            labelled(gradcam_overlay(run.policy, one, st, motion, cam), f"Grad-CAM, {what} texture ({labels[0]})")
        )
    iio.imwrite(out / "gradcam_before_after.png", hstack(overlays))
    with torch.no_grad():
        imgs = run.render_views(views, run.state.texture)
    shown = imgs[cam] if isinstance(imgs, dict) else imgs
    strip = [labelled(texture_to_uint8(img), f"recording {label}", min_side=128) for img, label in zip(shown, labels)]
    iio.imwrite(out / "rollout_strip.png", upscale(hstack(strip)))
