"""``advobj attack``: optimise a viewpoint-consistent adversarial texture."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from trials.cli.options import MIN_CLEAN_SUCCESS

app = typer.Typer(
    no_args_is_help=True,
    help="Optimise a 3D adversarial texture against a white-box policy (checkpoint, .pt2 or .onnx).",
)


@app.command()
def run(
    policy: Path = typer.Option(
        ...,
        help="white-box policy: a checkpoint directory, a .pt2 (torch.export) file, or an .onnx file (converted to "
        "torch and checked against onnxruntime on 32 rendered frames first)",
    ),
    preset: str = typer.Option("quick", help="ci (test-sized, seconds) | quick | paper"),
    config: Optional[Path] = typer.Option(None, help="YAML whose fields override the preset's"),
    scene: Optional[Path] = typer.Option(None, help="scene YAML (default: the built-in paper scene)"),
    pool: Optional[Path] = typer.Option(None, help="task-feasible pool JSON (default: the policy's, if any)"),
    out: Path = typer.Option(Path("runs/attack"), help="run directory"),
    resume: bool = typer.Option(False, "--resume", help="continue from the run directory's checkpoint"),
    light_randomization: Optional[bool] = typer.Option(
        None,
        "--light-randomization/--fixed-light",
        help="randomise the lights during optimisation (for a texture to print), or keep the scene's fixed light "
        "(default: the preset's, then --config's: on in paper, off in ci and quick, which say so before they start)",
    ),
    recordings: Optional[Path] = typer.Option(
        None,
        help="a recording folder (advobj record import): optimise on its frames with the object composited in, "
        "validate on its held-out episodes, instead of simulator rollouts (no simulator in the loop; no --pool)",
    ),
    min_clean_success: float = MIN_CLEAN_SUCCESS,
) -> None:
    """Run the attack; writes the texture, textured meshes, plots and metrics into OUT."""
    from attack.outputs import summary_lines  # lazy: CLI start-up (torch, matplotlib)
    from trials.jobs.attack import AttackJob  # lazy: CLI start-up (torch, onnxruntime)

    job = AttackJob(
        policy=policy,
        preset=preset,
        config=config,
        scene=scene,
        pool=pool,
        out=out,
        resume=resume,
        light_randomization=light_randomization,
        recordings=recordings,
        min_clean_success=min_clean_success,
    )
    metrics = job.run(log=typer.echo)
    for line in summary_lines(metrics):
        typer.echo(line)
    typer.echo(f"outputs in {out}/")
