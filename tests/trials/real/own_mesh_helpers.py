"""A user's own object for the real-trial and fabrication tests: a mesh file in millimetres, a
scene YAML that names it, and an attack run folder optimised on it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[3]
RABBIT = REPO / "tests" / "data" / "meshes" / "scan-rabbit-mm" / "rabbit.stl"  # a photogrammetry scan in mm


def box_obj_mm(path: Path, size_mm=(50.0, 40.0, 70.0)) -> Path:
    """An OBJ in millimetres as a CAD tool exports a box: its origin at a corner (the scene's
    ``placement: auto`` rests it on the table and centres it)."""
    import trimesh

    box = trimesh.creation.box(extents=size_mm)
    box.apply_translation(np.asarray(size_mm, dtype=float) / 2.0)
    path.parent.mkdir(parents=True, exist_ok=True)
    box.export(path)
    return path


def own_scene(
    path: Path,
    mesh,
    name: str = "my_box",
    units: str = "mm",
    goal: str = "tomato_soup_can",
    extra=(),
    scene_fields: dict | None = None,
    **fields,
) -> Path:
    """A scene YAML with the built-in soup can as the goal (named ``goal``) and ``mesh`` as the
    adversarial object ``name`` (``fields`` set on it); ``extra``: more object entries;
    ``scene_fields``: top-level fields of the scene (``episode``, ``init``)."""
    objects = [
        {"name": goal, "mesh": "tomato_soup_can", "role": "goal", "pose": {"x_m": 0.12, "y_m": 0.0}},
        {"name": name, "mesh": str(mesh), "units": units, "role": "adversarial", "pose": {"x_m": -0.12, "y_m": 0.0}},
        *extra,
    ]
    objects[1].update(fields)
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {"name": "own-object", "objects": objects, **(scene_fields or {})}
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def run_on_scene(folder: Path, scene: Path, seed: int = 0, size: int = 16, adversarial_mesh=None) -> Path:
    """An attack run folder as ``advobj attack run --scene SCENE`` leaves it: ``texture.npy`` and a
    ``run.json`` recording the attack config and the scene it optimised on."""
    from attack.artifact import AttackArtifact
    from sim.spec import load_spec

    spec = load_spec(scene)
    texture = np.random.default_rng(seed).random((size, size, 3)).astype(np.float32)
    config = {"attack": {"adversarial_mesh": adversarial_mesh}, "scene": spec.model_dump(mode="json")}
    return AttackArtifact(texture, config).save(folder)
