"""``advobj fabricate``: print sheets (cube, cylinder), colour-3D-print meshes and tag cards from an attack run."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def fabricate_command(
    run_dir: Path = typer.Argument(..., help="attack run directory (from 'advobj attack run')"),
    out: Path = typer.Option(..., "--out", help="output directory"),
    scene: Optional[Path] = typer.Option(
        None,
        help="scene YAML whose object --shape (default: its adversarial object) is made: its mesh (a file too), "
        "scale, units and up axis; the run must have optimised that mesh",
    ),
    shape: Optional[str] = typer.Option(
        None,
        help="with --scene: the object's name in it; without: the sheet shape, cube or cylinder (default: the run's "
        "mesh, if it has a net)",
    ),
    page: str = typer.Option("a4", help="paper: a4, letter or a3"),
    dpi: int = typer.Option(300, min=30, max=1200, help="print resolution of the texture images, 30-1200"),
    tag_id: Optional[int] = typer.Option(
        None,
        "--tag-id",
        help="add a tag card with this tag36h11 id: the object's footprint beside the tag, which locates any mesh "
        "in the cell (objects.yaml)",
    ),
    tag_size_mm: float = typer.Option(30.0, "--tag-size-mm", help="tag black-square side, mm"),
    no_check: bool = typer.Option(False, "--no-check", help="skip the pre-print check"),
    units: str = typer.Option(
        "m",
        "--units",
        help="length unit of the exported OBJ: m, or mm for print services (the GLB is "
        "metres, +Y up, by the glTF spec)",
    ),
) -> None:
    """Write sheet.pdf + layout.json (cube/cylinder, or the tag card of any mesh), adversarial.glb/OBJ, and check
    the print."""
    from trials.fabrication.fabricate import fabricate  # lazy: CLI start-up (torch, cv2)

    tag = (tag_id, tag_size_mm) if tag_id is not None else None
    if units not in ("m", "mm"):
        raise typer.BadParameter(f"expected m or mm, got {units!r}", param_hint="--units")
    summary = fabricate(
        run_dir,
        out,
        shape=shape,
        page=page.lower(),
        dpi=dpi,
        tag=tag,
        check=not no_check,
        log=typer.echo,
        obj_units=units,
        scene=scene,
    )
    typer.echo(f"fabricate: outputs in {out} ({summary.get('seconds', 0.0):.1f} s)")
