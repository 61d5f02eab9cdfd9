"""``advobj eval``: paired evaluation of a policy under clean and attacked conditions."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from sim.runtime import set_torch_threads
from trials.cli import grid as cli_grid
from trials.cli.options import MIN_CLEAN_SUCCESS, key_values
from trials.experiments.recipes import run_eval_grid


def eval_command(
    policy: Path = typer.Option(
        ..., help="target policy: checkpoint directory or .onnx file (black-box targets welcome)"
    ),
    condition: List[str] = typer.Option(
        ["attack"],
        "--condition",
        "-c",
        help="condition name (repeatable); 'clean' (the scene as it is) always runs, and 'benign' (the attacked "
        "object with the attack's unoptimised start texture: the headline's control) runs with 'attack'. "
        "Names: clean benign attack patch light_bright light_dim light_random noise bkg_varied stereo shape_dog "
        "shape_duck shape_cube shape_cylinder; for a policy reading several cameras, attack_wrist_only and "
        "attack_<camera>_only show the texture to that camera alone (attack: to all)",
    ),
    attack: Optional[Path] = typer.Option(
        None, help="attack run directory (texture for attack/variation/stereo conditions)"
    ),
    patch: Optional[Path] = typer.Option(
        None, help="attack run directory of the 2D patch baseline (adversarial_mesh 'patch')"
    ),
    shape: List[str] = typer.Option(
        [], help="SHAPE=DIR: attack run optimised on that shape (dog, duck, cube, cylinder); repeatable"
    ),
    episodes: int = typer.Option(500, min=1, help="episodes per condition"),
    max_steps: int = typer.Option(60, min=1, help="steps per episode"),
    num_envs: int = typer.Option(8, min=1, help="episodes rolled out in parallel"),
    pool: Optional[Path] = typer.Option(
        None, help="task-feasible pool JSON (default: the policy's, else built by running the clean policy)"
    ),
    scene: Optional[Path] = typer.Option(None, help="scene YAML (default: the built-in paper scene)"),
    seed: int = typer.Option(0, help="first candidate seed when building a task-feasible pool"),
    gifs: int = typer.Option(2, min=0, help="configurations recorded as rollout GIFs"),
    out: Path = typer.Option(Path("runs/eval"), help="evaluation directory"),
    resume: bool = typer.Option(False, "--resume", help="continue an interrupted evaluation in OUT"),
    allow_overlap: bool = typer.Option(
        False,
        "--allow-overlap",
        help="score a texture on configurations it was optimised or selected on "
        "(in-sample; refused by default). The overlap is written to manifest.json and report.md either way",
    ),
    threads: int = typer.Option(
        1,
        min=0,
        help="torch threads; 1 (default) avoids OpenMP spin-waits stealing the CPU renderer's cores, 0 = "
        "torch's default",
    ),
    min_clean_success: float = MIN_CLEAN_SUCCESS,
    workers: Optional[int] = cli_grid.WORKERS,
    address: Optional[str] = cli_grid.ADDRESS,
    shards: Optional[int] = cli_grid.SHARDS,
) -> None:
    """Run E episodes per condition on the same task-feasible configurations; write rows, summary and report."""
    from trials.eval.conditions import with_benign  # lazy: CLI start-up (numpy, trimesh)
    from trials.eval.evaluate import load_eval_config, run_eval  # lazy: CLI start-up (torch, onnxruntime)

    set_torch_threads(threads)
    shapes = key_values(shape, "--shape", "SHAPE", "DIR")
    cfg = load_eval_config(
        policy=str(policy),
        conditions=tuple(with_benign(condition)),
        episodes=episodes,
        max_steps=max_steps,
        num_envs=num_envs,
        pool=None if pool is None else str(pool),
        scene=None if scene is None else str(scene),
        seed=seed,
        gifs=gifs,
        attack=None if attack is None else str(attack),
        patch=None if patch is None else str(patch),
        shapes=shapes,
        allow_overlap=allow_overlap,
    )
    if workers is None and address is None and shards is None:
        summary = run_eval(cfg, out, resume=resume, min_clean_success=min_clean_success)
    else:  # the job layer: a pool job, eval-shard jobs, their merge (a re-run resumes; --resume is implied)
        ex, default_shards = cli_grid.executor(workers, address, typer.echo)
        summary = run_eval_grid(
            cfg, out, ex, shards or default_shards, log=typer.echo, min_clean_success=min_clean_success
        )
    typer.echo(format_summary(summary))
    typer.echo(f"report: {out / 'report.html'} (open it in a browser), {out / 'report.md'}")


def format_summary(summary: dict) -> str:
    from trials.eval.report import fmt_err, fmt_rate, format_headline  # lazy: CLI start-up (matplotlib, PIL)

    headline = format_headline(summary)
    lines = [] if headline is None else [f"headline: {headline}"]
    for name, s in summary["conditions"].items():
        lines.append(
            f"{name:>14}: T-ASR {fmt_rate(s['tasr'])} %  ASR {fmt_rate(s['asr'])} %  "
            f"E_trans {fmt_err(s['e_trans'])}  E_rot {fmt_err(s['e_rot'], 4)} rad  (n={s['n']}, 95% CI)"
        )
    return "\n".join(lines)
