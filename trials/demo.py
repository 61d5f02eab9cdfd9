"""The main job on the built-in scene (``make demo``)."""

from __future__ import annotations

from pathlib import Path

__all__ = ["run_demo"]


def run_demo(out: Path, seed: int = 0) -> dict:
    """Render the built-in scene and roll out the expert; writes into ``out``.

    Writes ``scene.png``, ``expert_rollout.gif``, ``contact_sheet.png`` and ``run.json``.
    """
    import imageio.v3 as iio

    from sim.runinfo import write_run_info
    from trials.scene_tools import contact_sheet, expert_rollout, load_spec, write_gif

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    spec = load_spec(None)
    write_run_info(out, {"job": "demo", "scene": spec.model_dump(mode="json")}, seed)
    frames, info = expert_rollout(spec, seed)
    write_gif(out / "expert_rollout.gif", frames)
    iio.imwrite(out / "contact_sheet.png", contact_sheet(frames))
    iio.imwrite(out / "scene.png", frames[0])
    reached = int(info["reached"][0])
    return {"steps": len(frames) - 1, "reached": spec.objects[reached].name if reached >= 0 else None}
