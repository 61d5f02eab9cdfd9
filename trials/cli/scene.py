"""``advobj scene``: render the scene, roll out the expert, write config pools."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from sim.errors import AdvobjError

app = typer.Typer(no_args_is_help=True, help="Render the simulated scene and roll out the expert.")

_SIZE = dict(min=16, max=4096, help="square image size in px, 16-4096 (default: the spec camera's)")


def _out_file(out: Path, suffixes: tuple[str, ...], flag: str = "--out") -> Path:
    """``out`` if it can be written as a file of one of ``suffixes``; checked before any work."""
    if out.is_dir():
        raise AdvobjError(f"{flag}: {out} is a directory; give a file name ending in {' or '.join(suffixes)}")
    if out.suffix.lower() not in suffixes:
        raise AdvobjError(f"{flag}: {out} must end in {' or '.join(suffixes)}")
    return out


def _say_mesh_notes(spec) -> None:
    """What loading the scene's mesh files changed (dropped faces, placement), where a user checks a
    new object: the other commands load it quietly."""
    from sim.assets import scene_mesh_notes  # lazy: CLI start-up (trimesh, PIL)

    for line in scene_mesh_notes(spec):
        typer.echo(f"note: {line}")


@app.command()
def render(
    scene: Optional[Path] = typer.Argument(None, help="scene YAML (default: the built-in paper scene)"),
    out: Path = typer.Option(Path("scene.png"), help="output PNG"),
    seed: int = typer.Option(0, min=0, help="initial-configuration seed"),
    size: Optional[int] = typer.Option(None, **_SIZE),
) -> None:
    """Render the wrist-camera view of one initial configuration."""
    import imageio.v3 as iio  # lazy: CLI start-up (imageio)

    from sim.spec import load_spec  # lazy: CLI start-up (+22 ms)
    from trials.jobs.scene import render_still  # lazy: CLI start-up (trimesh, PIL)

    _out_file(out, (".png",))

    spec = load_spec(scene)
    rgb = render_still(spec, seed, size)
    out.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(out, rgb)
    _say_mesh_notes(spec)
    typer.echo(f"wrote {out} ({rgb.shape[1]}x{rgb.shape[0]})")


@app.command()
def rollout(
    scene: Optional[Path] = typer.Argument(None, help="scene YAML (default: the built-in paper scene)"),
    expert: bool = typer.Option(True, "--expert/--no-expert", help="drive with the privileged expert"),
    out: Path = typer.Option(Path("rollout.gif"), help="output GIF"),
    seed: int = typer.Option(0, min=0, help="initial-configuration seed"),
    size: Optional[int] = typer.Option(None, **_SIZE),
) -> None:
    """Roll out one episode and write it as a GIF."""
    if not expert:
        raise typer.BadParameter("only --expert rollouts exist here; policies roll out with 'advobj policy eval'")
    _out_file(out, (".gif",))
    from sim.spec import load_spec  # lazy: CLI start-up (+22 ms)
    from trials.jobs.scene import expert_rollout  # lazy: CLI start-up (trimesh, PIL)

    spec = load_spec(scene)
    frames, info = expert_rollout(spec, seed, size)
    from sim.imaging import write_gif  # lazy: CLI start-up (numpy)

    write_gif(out, frames)
    reached = int(info["reached"][0])
    name = spec.objects[reached].name if reached >= 0 else "nothing"
    _say_mesh_notes(spec)
    typer.echo(f"wrote {out}: {len(frames) - 1} steps, reached {name}")


@app.command()
def pool(
    scene: Optional[Path] = typer.Argument(None, help="scene YAML (default: the built-in paper scene)"),
    n: int = typer.Option(100, min=1, help="number of configurations"),
    seed: int = typer.Option(0, min=0, help="first seed"),
    out: Path = typer.Option(Path("pool.json"), help="output JSON"),
) -> None:
    """Write a pool of initial configurations (reproducible from their seeds)."""
    from sim.configs import sample_pool, save_pool  # lazy: CLI start-up (trimesh, PIL)
    from sim.spec import load_spec  # lazy: CLI start-up (+22 ms)

    _out_file(out, (".json",))

    spec = load_spec(scene)
    save_pool(out, spec, sample_pool(spec, n, seed), meta={"seed": seed, "n": n})
    typer.echo(f"wrote {out}: {n} configurations")
