"""What an attack run writes besides its texture folder (:mod:`attack.artifact`): textured meshes,
plots and overlays."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import imageio.v3 as iio
import matplotlib
import matplotlib.pyplot as plt
import numpy as np
import torch
import torch.nn.functional as F
import trimesh
from PIL import Image, ImageDraw

from attack.artifact import AttackArtifact, texture_to_uint8, write_config_record
from attack.losses import grad_cam
from attack.optimize import fixed_light_warning
from sim.htmlreport import Bullets, Figure, Flag, Heading, Table, Text, write_page
from sim.imaging import hstack, labelled, upscale
from sim.policies.contract import first_action, to_joint_target
from sim.runinfo import RunInfoError, read_run_info, write_run_info

__all__ = [
    "textured_mesh",
    "export_meshes",
    "plot_losses",
    "gradcam_overlay",
    "gradcam_colour_bar",
    "texture_trail",
    "trail_iterations",
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


# Grad-CAM overlays: the image at this weight plus the map (its share of its maximum) in red.
CAM_IMAGE_WEIGHT = 0.55
CAM_HEAT_WEIGHT = 0.45


def _cam_blend(rgb: np.ndarray, S: np.ndarray) -> np.ndarray:
    """``rgb (H, W, 3)`` in [0, 1] and the map ``S (H, W)`` in [0, 1] -> the overlay, (H, W, 3) uint8."""
    heat = np.stack([S, np.zeros_like(S), np.zeros_like(S)], -1)
    return np.clip(255 * (CAM_IMAGE_WEIGHT * rgb + CAM_HEAT_WEIGHT * heat), 0, 255).astype(np.uint8)


def gradcam_overlay(
    policy, image, state: torch.Tensor | None = None, to_action=None, camera: str | None = None
) -> np.ndarray:
    """``image (3, H, W)`` (or ``{camera: (3, H_c, W_c)}`` for a policy reading several cameras,
    with ``camera`` the one shown) and the policy's ``state (1, D)`` -> (H, W, 3) uint8 with the
    Grad-CAM map blended in red (:func:`gradcam_colour_bar` is its scale)."""
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
    return _cam_blend(shown.detach().cpu().permute(1, 2, 0).numpy(), S)


def gradcam_colour_bar(height_px: int, width_px: int = 96, grey: float = 0.5) -> np.ndarray:
    """The scale of :func:`gradcam_overlay`: ``(height_px, width_px, 3)`` uint8, a strip blending
    the map from 0 (bottom) to its maximum (top) over a ``grey`` image, as the overlays do, with
    ticks at 0, 0.5 and 1 (the map's share of its maximum in that image) and a title bar."""
    bar_px = 18  # the title bar, as sim.imaging.labelled's caption bar
    h = int(height_px) - bar_px
    if h < 24 or width_px < 48:
        raise ValueError(f"colour bar: need at least 42 x 48 px, got {height_px} x {width_px}")
    top, bottom = 8, h - 8
    S = np.clip((bottom - np.arange(h, dtype=np.float64)) / (bottom - top), 0.0, 1.0)
    strip = _cam_blend(np.full((h, 1, 3), grey), S[:, None])  # (h, 1, 3)
    img = np.full((h, width_px, 3), 255, np.uint8)
    img[:, 6:26] = strip
    page = Image.fromarray(img)
    draw = ImageDraw.Draw(page)
    for v in (0.0, 0.5, 1.0):
        y = int(round(bottom - v * (bottom - top)))
        draw.line([(26, y), (31, y)], fill=(0, 0, 0))
        draw.text((34, y - 5), f"{v:g}" + (" max" if v == 1 else ""), fill=(0, 0, 0))
    title = Image.new("RGB", (width_px, bar_px), (0, 0, 0))
    ImageDraw.Draw(title).text((4, 3), "Grad-CAM", fill=(255, 255, 255))
    return np.concatenate([np.asarray(title), np.asarray(page)], 0)


def _gradcam_figure(overlays: list[np.ndarray]) -> np.ndarray:
    """Labelled overlays side by side with their colour bar at the right."""
    return hstack([*overlays, gradcam_colour_bar(max(o.shape[0] for o in overlays))])


# ----------------------------------------------------------------------------- the texture over iterations
TRAIL_DIR = "texture_trail"  # <run>/texture_trail/iteration_000060.png: the texture at marked iterations
TRAIL_MAX_PX = 128
TRAIL_MARKS = 10


def trail_iterations(cfg) -> list[int]:
    """Iterations whose texture the trail keeps: the validated ones (so each shows its held-out
    score), else evenly spaced ones, at most :data:`TRAIL_MARKS` of them, the last always."""
    n = int(cfg.iterations)
    if cfg.validation_every > 0:
        marks = list(range(cfg.validation_every, n, cfg.validation_every)) + [n]
    else:
        marks = sorted({int(round(x)) for x in np.linspace(0, n, TRAIL_MARKS + 1)[1:]} - {0})
    if len(marks) > TRAIL_MARKS:
        marks = [marks[i] for i in sorted({int(round(x)) for x in np.linspace(0, len(marks) - 1, TRAIL_MARKS)})]
    return marks


def _trail_png(out: Path, iteration: int) -> Path:
    return out / TRAIL_DIR / f"iteration_{int(iteration):06d}.png"


def texture_trail(out_dir: str | Path, cfg):
    """``on_iteration`` for :func:`attack.optimize.run_attack`: at each of :func:`trail_iterations`
    it writes the texture (at most :data:`TRAIL_MAX_PX` px) to ``out_dir/texture_trail/``, through a
    fresh temporary file renamed into place, so a resumed run keeps the marks it passed before and
    :func:`write_outputs` shows the texture over iterations."""
    out, marks = Path(out_dir), set(trail_iterations(cfg))

    def on_iteration(run, info) -> None:
        if run.state.iteration not in marks:
            return
        _write_trail(out, run.state.iteration, run.state.texture)

    return on_iteration


def _fit(img: np.ndarray, side: int) -> np.ndarray:
    """A square texture ``(S, S, 3)`` uint8 at ``side`` px: box-filtered when smaller, as it is otherwise."""
    if img.shape[0] == side and img.shape[1] == side:
        return img
    return np.asarray(Image.fromarray(img).resize((side, side), Image.BOX if side < img.shape[0] else Image.NEAREST))


def _write_trail(out: Path, iteration: int, texture: torch.Tensor) -> Path:
    img = texture_to_uint8(texture.detach().cpu())
    img = _fit(img, min(img.shape[0], TRAIL_MAX_PX))
    path = _trail_png(out, iteration)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".trail.", suffix=".png", dir=path.parent)  # O_EXCL
    try:
        with os.fdopen(fd, "wb") as f:
            iio.imwrite(f, img, extension=".png")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _texture_over_iterations(run, out: Path, texture_before: torch.Tensor) -> Path:
    """``texture_over_iterations.png``: the starting texture, the trail's marks this run passed,
    the best validated one and the final one, each labelled with its iteration and, where it was
    validated, its held-out score."""
    h = run.state.history
    scores = dict(zip(getattr(h, "val_iteration", []) or [], getattr(h, "val_t_asr", []) or []))
    best = run.state.best or {}
    shots: dict[int, np.ndarray] = {0: texture_to_uint8(texture_before.detach().cpu())}
    for k in trail_iterations(run.cfg):
        p = _trail_png(out, k)
        if 0 < k < run.state.iteration and p.is_file():
            try:
                shots[k] = iio.imread(p)[..., :3]
            except (OSError, ValueError):
                continue  # a damaged mark is left out, not fatal
    if run.state.best_texture is not None and best.get("iteration") is not None:
        shots.setdefault(int(best["iteration"]), texture_to_uint8(run.state.best_texture.detach().cpu()))
    shots[run.state.iteration] = texture_to_uint8(run.state.texture.detach().cpu())
    side = min(TRAIL_MAX_PX, max(s.shape[0] for s in shots.values()))
    tiles = []
    for k in sorted(shots):
        tags = [t for t, on in (("start", k == 0), ("best", k == best.get("iteration"))) if on]
        label = f"iteration {k}" + (f" ({', '.join(tags)})" if tags else "")
        if k in scores:
            label += f", val {scores[k]:.2f}"
        tiles.append(labelled(_fit(shots[k], side), label, min_side=176))
    cols = min(6, len(tiles))
    rows = [hstack(tiles[i : i + cols]) for i in range(0, len(tiles), cols)]
    width = rows[0].shape[1]
    rows = [np.concatenate([r, np.full((r.shape[0], width - r.shape[1], 3), 255, np.uint8)], 1) for r in rows]
    gap = np.full((4, width, 3), 255, np.uint8)
    path = out / "texture_over_iterations.png"
    iio.imwrite(path, np.concatenate([x for r in rows for x in (r, gap)][:-1], 0))
    return path


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
    _texture_over_iterations(run, out, texture_before)
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
    write_attack_page(run, out, metrics)
    return metrics


def write_attack_page(run, out: Path, metrics: dict) -> Path:
    """``report.html`` (:mod:`sim.htmlreport`): the end-of-run summary (the held-out validation
    first), the validations, the texture over iterations, Grad-CAM before and after with its colour
    bar, the rollout under the final texture, and the files the run wrote."""
    cfg = run.cfg
    adv = run.spec.objects[run.spec.object_index("adversarial")]
    mesh = cfg.adversarial_mesh or adv.mesh or adv.name
    lines = summary_lines(metrics)  # the held-out validation's line second: first on the page
    blocks = [Heading("Summary"), Text(lines[1], strong=True), Text(lines[0]), *(Text(x) for x in lines[2:])]
    if not metrics.get("validation"):
        blocks.append(Flag("Held-out validation was off: this run does not say whether the texture works."))
    if (note := fixed_light_warning(cfg)) is not None and cfg.recordings is None:
        blocks.append(Flag(note.removeprefix("warning: ")))
    v = metrics.get("validation")
    if v:
        measure = v.get("measure", "T-ASR")
        best_it = (v.get("best") or {}).get("iteration")
        rows = [
            [str(k), f"{t:.3f}", f"{d:.3f}" if d == d else "-", "best" if k == best_it else ""]
            for k, t, d in zip(v["iteration"], v["t_asr"], v["dist_m"])
        ]
        n = (v.get("best") or {}).get("episodes", "?")
        blocks += [
            Heading("Held-out validation"),
            Table(
                ["iteration", f"held-out {measure}", "mean final distance to the object (m)", ""],
                rows,
                caption=f"each on the same {n} held-out configurations",
            ),
        ]
    blocks += [
        Heading("The texture over iterations"),
        Figure.from_file(
            out / "texture_over_iterations.png",
            "the starting texture, the texture at the marked iterations, the best validated one and the final one "
            "(val: the held-out score at that iteration)",
        ),
        Heading("Losses"),
        Figure.from_file(out / "loss_curves.png", "held-out validation, the objective's terms and the gradient norm"),
        Heading("Grad-CAM before and after"),
        Figure.from_file(
            out / "gradcam_before_after.png",
            "where the policy looks (Grad-CAM of the motion it executes next, red, scaled to its maximum in each "
            "image; the colour bar shows the red added over a mid-grey image) under the starting and the final texture",
        ),
        Heading("Rollout under the final texture"),
        Figure.from_file(out / "rollout_strip.png", "the policy's view, step by step"),
        Heading("Files"),
        Bullets(
            [
                "`texture.png`, `texture.npy`: the final texture; `best/`: the best validated one",
                *(f"`{p}`: the textured mesh" for p in metrics.get("meshes", {}).values()),
                "`metrics.json`, `run.json`, `configs.json`: figures, provenance and the configurations used",
                "evaluate with `advobj eval --attack` on this folder for T-ASR by viewing angle and distance",
            ]
        ),
    ]
    return write_page(out, f"Attack report: {mesh} ({cfg.schedule}, {run.state.iteration} iterations)", blocks)


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
    joint = env.control == "joint"  # a joint-space policy reads the joints and moves them through FK

    def joints():
        return torch.from_numpy(env.q[:1]).to(run.device, torch.float32) if joint else None

    q0 = joints()
    st = run.policy_state(T0, q0)

    def motion(o):
        return run.next_delta(o, T0, q0)

    iio.imwrite(
        out / "gradcam_before_after.png",
        _gradcam_figure(
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
            T, q = torch.from_numpy(env.T_world_tcp[:1]).to(run.device, torch.float32), joints()
            raw = run.call_policy(imgs, run.policy_state(T, q))
            if joint:  # the joint target of the first action; the other envs hold their joints
                a = to_joint_target(q, first_action(raw).to(q.dtype), run.contract.action.kind).cpu().numpy()
                actions = env.q.copy()
            else:
                a = run.next_delta(raw, T).cpu().numpy()
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
    iio.imwrite(out / "gradcam_before_after.png", _gradcam_figure(overlays))
    with torch.no_grad():
        imgs = run.render_views(views, run.state.texture)
    shown = imgs[cam] if isinstance(imgs, dict) else imgs
    strip = [labelled(texture_to_uint8(img), f"recording {label}", min_side=128) for img, label in zip(shown, labels)]
    iio.imwrite(out / "rollout_strip.png", upscale(hstack(strip)))
