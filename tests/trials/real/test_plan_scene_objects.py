"""advobj trial plan with a user's own object: the scene YAML names it (issue 30, "any mesh to the cell").

A shape is an object's name in --scene (its mesh an OBJ in millimetres here); the plan records the
object, its mesh file's sha256 and its centre; the texture must come from a run on that very mesh.
Bad input (an unknown name, a missing mesh file, a run on another mesh, a file path as the shape)
is one line naming the flag, exit 2, and no file written.
"""

from __future__ import annotations

import hashlib
import shutil
import sys

import numpy as np
import pytest
import yaml

from tests.trials.real.own_mesh_helpers import box_obj_mm, own_scene, run_on_scene
from tests.trials.real.trial_session_helpers import attack_dir


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    d = tmp_path_factory.mktemp("own_plan")
    mesh = box_obj_mm(d / "meshes" / "my_box.obj")
    scene = own_scene(d / "my.yaml", "meshes/my_box.obj")
    return {"dir": d, "mesh": mesh, "scene": scene, "run": run_on_scene(d / "run_box", scene)}


def _plan(cell, **kw):
    from sim.spec import load_spec
    from trials.real.plan import make_plan, texture_ref

    spec = load_spec(cell["scene"])
    tex = {"my_box/adv3d": texture_ref(cell["run"], "my_box/adv3d", spec, str(cell["scene"]))}
    args = dict(n_tcp_poses=2, n_object_layouts=1, scene=str(cell["scene"]))
    return make_plan(spec, 0, ["A"], ["my_box"], ["clean", "adv3d"], tex, **{**args, **kw})


def test_a_scene_object_with_a_mesh_file_is_a_shape_recorded_with_its_sha256_and_centre(cell, tmp_path):
    from trials.real.plan import design_summary, load_plan, save_plan

    plan = _plan(cell)
    obj = plan.shape_object("my_box")
    assert obj is not None and obj.object.name == "my_box" and obj.object.units == "mm"
    assert obj.object.mesh == str(cell["mesh"].resolve())  # resolved by the scene loader, relative to the YAML
    assert obj.mesh_sha256 == hashlib.sha256(cell["mesh"].read_bytes()).hexdigest()
    np.testing.assert_allclose(obj.center_m, [0.0, 0.0, 0.035], atol=1e-9)  # a 7 cm box resting on the table
    t = plan.trials[0]
    assert plan.mesh_for(t) == obj.object.mesh and plan.object_name(t) == "my_box"
    assert [x.trial_id for x in plan.trials if x.condition == "adv3d"][0].startswith("A-my_box-adv3d-")
    assert any("shape my_box: scene object 'my_box', mesh my_box.obj (mm" in line for line in design_summary(plan))
    save_plan(plan, tmp_path / "plan.yaml")
    assert load_plan(tmp_path / "plan.yaml") == plan


def test_a_plan_of_built_in_shapes_records_no_scene_objects(cell, tmp_path):
    from sim.spec import default_scene
    from trials.real.plan import load_plan, make_plan, save_plan

    plan = make_plan(default_scene(), 0, ["A"], ["cube"], ["clean"], {}, n_tcp_poses=1, n_object_layouts=1)
    assert plan.shape_objects == {} and plan.mesh_for(plan.trials[0]) == "cube"
    save_plan(plan, tmp_path / "plan.yaml")
    assert "shape_objects" not in yaml.safe_load((tmp_path / "plan.yaml").read_text())  # its fields as before
    assert load_plan(tmp_path / "plan.yaml") == plan


def test_the_same_mesh_file_copied_elsewhere_is_the_same_mesh(cell, tmp_path):
    """The run's mesh and the plan's object are compared by the file's bytes, not its path."""
    from sim.spec import load_spec
    from trials.real.plan import texture_ref

    shutil.copy(cell["mesh"], tmp_path / "copy.obj")
    scene = own_scene(tmp_path / "copy.yaml", "copy.obj")
    ref = texture_ref(cell["run"], "my_box/adv3d", load_spec(scene), str(scene))
    assert ref.sha256 == hashlib.sha256((cell["run"] / "texture.npy").read_bytes()).hexdigest()


def test_a_texture_from_a_run_on_the_object_at_another_size_is_refused(cell, tmp_path):
    from sim.spec import load_spec
    from trials.real.plan import PlanError, texture_ref

    scene = own_scene(tmp_path / "big.yaml", cell["mesh"], scale=1.5)
    with pytest.raises(
        PlanError, match=r"--texture my_box/adv3d=.*optimised my_box\.obj at scale 1\.0, the object has "
    ):
        texture_ref(cell["run"], "my_box/adv3d", load_spec(scene), str(scene))


def test_another_object_of_the_scene_stands_in_the_adversarial_slot(cell, tmp_path):
    """A shape may be any non-goal object of the scene: it takes the adversarial object's place."""
    from sim.spec import load_spec
    from trials.fabrication.shapes import with_shape
    from trials.real.plan import make_plan

    spare = {"name": "spare", "mesh": str(cell["mesh"]), "units": "mm", "role": "distractor", "scale": 0.5}
    scene = own_scene(tmp_path / "two.yaml", "cube", name="cube_a", units="m", extra=[{**spare, "pose": {"x_m": 0.3}}])
    spec = load_spec(scene)
    plan = make_plan(spec, 1, ["A"], ["spare", "cube_a"], ["clean"], {}, n_tcp_poses=1, n_object_layouts=1)
    staged = with_shape(spec, plan.shape_object("spare"))
    assert [o.name for o in staged.objects] == ["tomato_soup_can", "spare"]
    adv = staged.adversarial
    assert adv.name == "spare" and adv.scale == 0.5 and adv.units == "mm" and adv.pose == spec.adversarial.pose


def _main(monkeypatch, capsys, args):
    from trials.cli.main import main

    monkeypatch.setattr(sys, "argv", ["advobj", *map(str, args)])
    with pytest.raises(SystemExit) as exc:
        main()
    return exc.value.code, capsys.readouterr().err.strip()


@pytest.mark.parametrize(
    "case",
    ["unknown object", "missing mesh file", "run on another mesh", "file path as shape", "the goal"],
)
def test_bad_input_is_one_line_naming_the_flag_exit_2_and_nothing_written(cell, tmp_path, monkeypatch, capsys, case):
    scene, shape, texture = cell["scene"], "my_box", [f"my_box/adv3d={cell['run']}"]
    if case == "unknown object":
        shape, texture, want = "my_bx", [], "--shape my_bx: no object 'my_bx' in scene "
    elif case == "missing mesh file":
        scene = own_scene(tmp_path / "gone.yaml", "meshes/gone.obj")
        texture, want = [], "--shape my_box: objects.1.mesh of scene "
    elif case == "run on another mesh":
        texture = [f"my_box/adv3d={attack_dir(tmp_path / 'cube_run', 'cube')}"]
        want = "--texture my_box/adv3d="
    elif case == "file path as shape":
        shape, texture, want = "meshes/my_box.obj", [], "--shape meshes/my_box.obj: a mesh file is named through"
    else:
        scene = own_scene(tmp_path / "goal.yaml", cell["mesh"], goal="soup")
        shape, texture, want = "soup", [], "--shape soup: 'soup' is the goal of scene "
    out = tmp_path / "out" / "plan.yaml"
    args = ["trial", "plan", "--scene", scene, "--shape", shape, "--out", out, "--tcp-poses", 1, "--object-poses", 1]
    args += ["--condition", "clean"] + (["--condition", "adv3d"] if texture else [])
    code, err = _main(monkeypatch, capsys, args + [a for t in texture for a in ("--texture", t)])
    assert code == 2 and len(err.splitlines()) == 1 and want in err, err
    assert "Traceback" not in err and not (tmp_path / "out").exists()
    if case == "missing mesh file":
        assert "mesh file meshes/gone.obj not found" in err
    if case == "run on another mesh":
        assert "optimised mesh 'cube', but my_box/adv3d needs mesh" in err and "the scene object 'my_box'" in err


def test_cli_plans_an_own_mesh_by_its_scene_name_with_a_placement_sheet(cell, tmp_path):
    from typer.testing import CliRunner

    from trials.cli.main import app
    from trials.real.plan import load_plan

    out = tmp_path / "plan.yaml"
    args = ["trial", "plan", "--scene", cell["scene"], "--shape", "my_box", "--texture", f"my_box/adv3d={cell['run']}"]
    args += ["--condition", "clean", "--condition", "adv3d", "--tcp-poses", 2, "--object-poses", 1, "--out", out]
    r = CliRunner().invoke(app, [str(a) for a in args + ["--sheet", tmp_path / "plan.pdf"]])
    assert r.exit_code == 0, r.output
    plan = load_plan(out)
    assert plan.shapes == ["my_box"] and len(plan.trials) == 4 and plan.scene == str(cell["scene"])
    assert plan.shape_object("my_box").object.mesh == str(cell["mesh"].resolve())
    assert (tmp_path / "plan.pdf").read_bytes().startswith(b"%PDF")
