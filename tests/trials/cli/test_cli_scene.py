"""The scene CLI end to end (subprocess, as a user runs it) and the no-OpenGL error."""

import os
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio

ADVOBJ = [sys.executable, "-m", "trials.cli.main"]


def _run(args, tmp_path, env_extra=None):
    env = {**os.environ, **(env_extra or {})}
    root = Path(__file__).resolve().parents[3]
    return subprocess.run(ADVOBJ + args, cwd=root, env=env, capture_output=True, text=True, timeout=300)


def test_scene_render_writes_the_wrist_view(tmp_path):
    out = tmp_path / "a.png"
    r = _run(["scene", "render", "--out", str(out), "--size", "64", "--seed", "3"], tmp_path)
    assert r.returncode == 0, r.stderr
    img = iio.imread(out)
    assert img.shape == (64, 64, 3) and img.std() > 5


def test_scene_rollout_expert_writes_a_gif_and_reaches_the_goal(tmp_path):
    out = tmp_path / "r.gif"
    r = _run(["scene", "rollout", "--expert", "--out", str(out), "--size", "48", "--seed", "1"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert "reached tomato_soup_can" in r.stdout
    frames = iio.imread(out, index=None)
    assert frames.shape[0] >= 2


def test_scene_pool_writes_reproducible_configs(tmp_path):
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    for p in (a, b):
        assert _run(["scene", "pool", "--n", "5", "--seed", "7", "--out", str(p)], tmp_path).returncode == 0
    assert a.read_text() == b.read_text()


def test_missing_opengl_gives_one_clear_error_not_a_traceback(tmp_path):
    # A PyOpenGL platform that exists nowhere: no usable GL on any machine, whatever is installed.
    out = tmp_path / "x.png"
    r = _run(["scene", "render", "--out", str(out)], tmp_path, {"PYOPENGL_PLATFORM": "advobj-test-no-such-gl"})
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr and not out.exists()
    errors = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and r.stderr.strip() == errors[0], r.stderr  # one line, nothing else
    assert "No usable OpenGL" in errors[0] and "apt-get install" in errors[0] and "PYOPENGL_PLATFORM" in errors[0]


def test_bad_scene_file_names_file_and_field(tmp_path):
    bad = tmp_path / "s.yaml"
    bad.write_text("objects:\n  - {name: a, mesh: cube, role: goal, colour: red}\n")
    r = _run(["scene", "render", str(bad), "--out", str(tmp_path / "x.png")], tmp_path)
    assert r.returncode == 2 and str(bad) in r.stderr and "objects.0.colour" in r.stderr
    assert "Traceback" not in r.stderr


def test_an_own_mesh_made_around_its_centre_gets_one_note_from_render_and_no_warning_anywhere(tmp_path):
    """Placement auto rests a mesh exported around its centre (Blender's way) on the table: `scene render`
    says so in one `note:` line; neither it nor another command prints a Python warning about it."""
    import trimesh

    (tmp_path / "meshes").mkdir()
    trimesh.creation.box(extents=(0.06, 0.06, 0.1)).export(tmp_path / "meshes" / "centred.obj")
    scene = tmp_path / "my_scene.yaml"
    scene.write_text(
        "objects:\n"
        "  - {name: tomato_soup_can, mesh: tomato_soup_can, role: goal, pose: {x_m: 0.12, y_m: 0.0}}\n"
        "  - {name: my_object, mesh: meshes/centred.obj, role: adversarial, pose: {x_m: -0.12, y_m: 0.0}}\n"
    )
    r = _run(["scene", "render", str(scene), "--size", "32", "--out", str(tmp_path / "a.png")], tmp_path)
    assert r.returncode == 0, r.stderr
    notes = [line for line in r.stdout.splitlines() if line.startswith("note:")]
    assert len(notes) == 1 and "my_object:" in notes[0] and "5.0 cm below its origin" in notes[0], r.stdout
    assert "Warning" not in r.stderr, r.stderr
    r = _run(["scene", "pool", str(scene), "--n", "3", "--out", str(tmp_path / "p.json")], tmp_path)
    assert r.returncode == 0 and "Warning" not in r.stderr and "note:" not in r.stdout, r.stderr
