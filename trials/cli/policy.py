"""``advobj policy``: train, evaluate and export reference visuomotor policies (.onnx, .pt2)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer
from pydantic import ValidationError

from sim.errors import AdvobjError, format_validation_error
from sim.policies.competence import DEFAULT_MIN_CLEAN_SUCCESS
from sim.runinfo import write_run_info
from sim.runtime import set_torch_threads
from trials.cli.options import name_list

app = typer.Typer(no_args_is_help=True, help="Train, evaluate and export reference visuomotor policies.")

_THREADS_HELP = (
    "torch intra-op threads; 1 (default) avoids OpenMP spin-wait contention with the CPU renderer "
    "on small machines, 0 = torch's default"
)


def _set_threads(threads: int) -> None:
    if threads < 0:
        raise typer.BadParameter("--threads must be >= 0")
    set_torch_threads(threads)


@app.command()
def train(
    arch: Optional[str] = typer.Option(
        None, help="backbone: resnet18, resnet34, vgg16, inception_v3, small_cnn (default: the preset's)"
    ),
    preset: str = typer.Option("quick", help="ci, quick or paper"),
    method: Optional[str] = typer.Option(None, help="dagger or ppo (default: the preset's, dagger)"),
    out: Path = typer.Option(..., help="output checkpoint directory; an interrupted run there resumes"),
    scene: Optional[Path] = typer.Option(None, help="scene YAML (default: the built-in paper scene)"),
    seed: int = typer.Option(0, min=0),
    episodes: Optional[int] = typer.Option(None, help="final clean evaluation episodes (default: the preset's)"),
    curve_episodes: int = typer.Option(
        0, min=0, help="clean episodes after each iteration/chunk, for a learning curve (time excluded from the budget)"
    ),
    stop_at: Optional[float] = typer.Option(
        None, help="stop once the learning-curve success reaches this (needs --curve-episodes)"
    ),
    threads: int = typer.Option(1, help=_THREADS_HELP),
    keep_state: bool = typer.Option(
        False,
        "--keep-state/--no-keep-state",
        help="keep train_state/ (the resume data, hundreds of MB) "
        "once training has finished; by default it is deleted and the final weights kept",
    ),
    device: str = typer.Option("cpu"),
    stem: Optional[str] = typer.Option(
        None,
        help="ResNet/VGG stem: 'small' (no early downsampling, the default of small presets) "
        "or 'standard' (ImageNet stem: ~3-5x cheaper per image on CPU)",
    ),
    cameras: Optional[str] = typer.Option(
        None,
        help="comma-separated cameras the policy reads, e.g. wrist,front with --scene scenes/two-cameras.yaml "
        "(one backbone each; DAgger only); default: wrist",
    ),
    action: Optional[str] = typer.Option(
        None,
        help="what the policy commands: delta_tcp, or joint_delta / joint_position on the scene's arm (it then reads "
        "the joint positions); default: joint_delta when the scene has an arm (e.g. scenes/panda-joint.yaml), "
        "else delta_tcp",
    ),
    iterations: Optional[int] = typer.Option(
        None,
        min=1,
        help="DAgger iterations (default: the preset's); the run length, so an interrupted run resumes with more "
        "(it continues) but not with fewer than it has done",
    ),
    grad_steps: Optional[int] = typer.Option(
        None,
        min=1,
        help="DAgger gradient steps after each iteration's episodes (default: the preset's); part of the run's "
        "config, so a resume must give the same",
    ),
) -> None:
    """Train a policy (DAgger from the privileged expert, or PPO) and evaluate it."""
    from sim.policies.presets import resolve_preset  # lazy: CLI start-up (torch, trimesh)
    from sim.policies.train import train_policy  # lazy: CLI start-up (torch, onnxruntime)
    from sim.spec import load_spec  # lazy: CLI start-up (+22 ms)

    extra = {} if episodes is None else {"final_eval_episodes": episodes}
    if stem is not None:
        if stem not in ("small", "standard"):
            raise typer.BadParameter(f"--stem: expected 'small' or 'standard', got {stem!r}")
        extra["policy"] = {"small_stem": stem == "small"}
    if stop_at is not None and not curve_episodes:
        raise typer.BadParameter("--stop-at needs --curve-episodes > 0")
    if curve_episodes:
        curve = {"eval_episodes": curve_episodes, "stop_at_success": stop_at}
        extra.update(dagger=dict(curve), ppo=dict(curve))
    if iterations is not None:
        extra.setdefault("dagger", {})["iterations"] = iterations
    if grad_steps is not None:
        extra.setdefault("dagger", {})["grad_steps_per_iter"] = grad_steps
    cams = name_list(cameras)
    if cams is not None and not cams:
        raise typer.BadParameter("name at least one camera, e.g. wrist,front", param_hint="--cameras")
    spec = load_spec(scene)  # the cameras' sizes are the scene's
    kinds = ("delta_tcp", "joint_delta", "joint_position")
    if action is not None and action not in kinds:
        raise typer.BadParameter(f"expected one of {', '.join(kinds)}, got {action!r}", param_hint="--action")
    if action is None:
        action = "joint_delta" if spec.arm is not None else "delta_tcp"
    try:
        cfg = resolve_preset(
            preset, arch=arch, method=method, seed=seed, cameras=cams, spec=spec, action=action, **extra
        )
    except AdvobjError as err:  # a camera the scene lacks: the line lists the scene's cameras
        raise typer.BadParameter(str(err), param_hint="--cameras") from None
    except ValidationError as err:
        raise typer.BadParameter(format_validation_error(err, "training config")) from None
    except ValueError as err:
        msg = str(err).splitlines()[0] if "preset" in str(err) else str(err)
        raise typer.BadParameter(msg, param_hint="--action" if msg.startswith("action:") else None) from None
    for flag, value, ppo_own in (
        ("--iterations", iterations, "runs for ppo.total_timesteps"),
        ("--grad-steps", grad_steps, "updates by ppo.n_epochs over each ppo.n_steps rollout"),
    ):
        if value is not None and cfg.method != "dagger":
            raise typer.BadParameter(f"a DAgger setting; {cfg.method} {ppo_own}", param_hint=flag)
    if cfg.contract.is_joint_space:
        typer.echo(
            f"training a joint-space policy: {cfg.contract.describe()} ({', '.join(cfg.contract.joints)}) on the "
            f"scene's arm {spec.arm.urdf}"
        )
    _set_threads(threads)
    card = train_policy(cfg, out, spec, device=device, log=typer.echo, keep_state=keep_state)
    t = card.training["train_time_s"]
    typer.echo(f"trained {cfg.policy.arch} ({cfg.method}, preset {preset}) in {t / 60:.1f} min; checkpoint in {out}/")


@app.command("eval")
def evaluate(
    policy: Path = typer.Argument(..., help="checkpoint directory or .onnx file"),
    episodes: int = typer.Option(200, min=1),
    seed: int = typer.Option(0, min=0, help="first initial-configuration seed"),
    num_envs: int = typer.Option(16, min=1),
    scene: Optional[Path] = typer.Option(None, help="scene YAML (default: the built-in paper scene)"),
    light: str = typer.Option("fixed", help="fixed, bright, dim or random"),
    background: str = typer.Option("fixed", help="fixed or varied"),
    noise: float = typer.Option(0.0, help="sensor noise std (fraction of full scale)"),
    out: Optional[Path] = typer.Option(None, help="output directory (default: <checkpoint>/eval or <file>-eval/)"),
    threads: int = typer.Option(1, help=_THREADS_HELP),
    device: str = typer.Option("cpu"),
) -> None:
    """Clean success rate with a 95% Wilson interval; writes the task-feasible pool."""
    from sim.configs import spec_fingerprint  # lazy: CLI start-up (trimesh, PIL)
    from sim.policies.checkpoint import load_policy  # lazy: CLI start-up (torch, onnxruntime)
    from sim.policies.pool import built_pool_path, write_feasible_pool  # lazy: CLI start-up (torch, trimesh)
    from sim.policies.rollout import EnvConfig, evaluate_policy  # lazy: CLI start-up (torch, trimesh)
    from sim.spec import load_spec  # lazy: CLI start-up (+22 ms)

    _set_threads(threads)
    spec = load_spec(scene)
    # With the scene: a camera the scene lacks (or of another size) is one line before OUT is made.
    pol = load_policy(policy, device=device, spec=spec)
    try:
        env_cfg = EnvConfig(image_size=pol.image_size, light=light, background=background, noise_std=noise)
    except ValueError as err:  # pydantic names the offending field
        raise typer.BadParameter(str(err)) from None
    out = out or (policy / "eval" if policy.is_dir() else policy.with_name(policy.stem + "-eval"))
    resolved = {
        "policy": str(policy),
        "episodes": episodes,
        "num_envs": num_envs,
        "env": env_cfg.model_dump(),
        "scene": {"name": spec.name, "fingerprint": spec_fingerprint(spec)},
        "white_box": pol.white_box,
    }
    write_run_info(out, resolved, seed)
    res = evaluate_policy(pol, spec, episodes, seed, num_envs, env_cfg)
    summary = res.summary([o.name for o in spec.objects])
    (out / "eval.json").write_text(
        json.dumps(
            {
                **summary,
                "seeds": [seed, seed + episodes - 1],
                "episodes": [
                    {"seed": int(s), "success": bool(ok), "reached": int(r), "steps": int(n), "policy_error": bool(e)}
                    for s, ok, r, n, e in zip(res.seeds, res.success, res.reached, res.steps, res.policy_error)
                ],
            },
            indent=1,
        )
    )
    pool = write_feasible_pool(
        built_pool_path(out), spec, res, meta={"policy": str(policy), "seed": seed, "env": env_cfg.model_dump()}
    )
    typer.echo(f"clean success: {res.success_rate}")
    if res.success_rate.rate < DEFAULT_MIN_CLEAN_SUCCESS:
        typer.echo(
            f"below the {DEFAULT_MIN_CLEAN_SUCCESS:.0%} that 'advobj attack run' and 'advobj eval' ask for by default "
            "(--min-clean-success): train it longer, or check the scene is the one it was trained for"
        )
    if res.policy_error.any():
        typer.echo(
            f"policy errors: {int(res.policy_error.sum())} of {len(res.seeds)} episodes ended on a non-finite "
            "action (never executed; counted as failures)"
        )
    typer.echo(f"task-feasible pool: {int(res.success.sum())} configurations -> {pool}")


@app.command()
def export(
    policy: Path = typer.Argument(..., help="checkpoint directory"),
    onnx: Optional[Path] = typer.Option(None, "--onnx", help="output .onnx file"),
    pt2: Optional[Path] = typer.Option(None, "--pt2", help="output .pt2 file (torch.export ExportedProgram)"),
    opset: int = typer.Option(17, min=17, help="ONNX opset (>= 17)"),
    check: bool = typer.Option(
        True, "--check/--no-check", help="compare each file with the checkpoint on 32 random images"
    ),
) -> None:
    """Export a checkpoint to ONNX and/or a .pt2 ExportedProgram, with its card inside.

    Both files can be attacked white-box (advobj attack run --policy FILE); an .onnx file is also
    what onnxruntime runs black-box (evaluation, real trials)."""
    import numpy as np  # lazy: CLI start-up (numpy)
    import torch  # lazy: CLI start-up (torch)

    from sim.policies.checkpoint import load_checkpoint  # lazy: CLI start-up (torch, onnxruntime)
    from sim.policies.onnx_policy import OnnxPolicy, export_onnx  # lazy: CLI start-up (torch, onnxruntime)
    from sim.policies.pt2 import export_pt2, load_pt2  # lazy: CLI start-up (torch)

    if onnx is None and pt2 is None:
        raise typer.BadParameter("give --onnx FILE, --pt2 FILE or both", param_hint="--onnx / --pt2")
    for flag, path, suffix in (("--onnx", onnx, ".onnx"), ("--pt2", pt2, ".pt2")):
        if path is not None and path.suffix.lower() != suffix:
            raise typer.BadParameter(f"{path}: the file name must end in {suffix}", param_hint=flag)
    pol, card = load_checkpoint(policy)
    rng = np.random.default_rng(0)
    out = f"output actions (B, {pol.config.action_dim})"
    if pol.config.is_one_camera:
        x = rng.random((32, 3, pol.image_size, pol.image_size), dtype=np.float32)
        shape = f"input images (B, 3, {pol.image_size}, {pol.image_size}) in [0, 1]"
    else:  # one input per camera, named by it
        x = {b.camera: rng.random((32, 3, *b.size), dtype=np.float32) for b in pol.inputs.images}
        sizes = ", ".join(f"{b.name} (B, 3, {b.size[0]}, {b.size[1]})" for b in pol.inputs.images)
        shape = f"inputs {sizes} in [0, 1]"
    # a policy reading a state (joint positions, the TCP) is checked on random states too
    D = int(pol.config.state_dim)
    st = rng.uniform(-1.0, 1.0, (32, D)).astype(np.float32) if D else None
    shape += (f", state (B, {D})" if D else "") + f", {out}"
    what_in = "32 random images" + (" and states" if D else "")
    written = []
    if onnx is not None:
        export_onnx(pol, onnx, card=card, opset=opset)
        written.append((onnx, f"opset {opset}", lambda: OnnxPolicy(onnx).act(x, st), "onnx"))
    if pt2 is not None:
        export_pt2(pol, pt2, card=card)
        written.append((pt2, f"torch {torch.__version__}", lambda: load_pt2(pt2).act(x, st), "pt2"))
    failed = False
    for path, what, run, name in written:
        msg = f"wrote {path} ({what}, {shape})"
        if check:
            diff = float(np.abs(run() - pol.act(x, st)).max())
            msg += f"; max |{name} - torch| on {what_in} = {diff:.2e}"
            if diff > 1e-4:
                typer.secho(msg, fg=typer.colors.RED)
                failed = True
                continue
        typer.echo(msg)
    if failed:
        raise typer.Exit(1)
