"""Staging and locating a user's own object in a sim cell: the plan's scene object stands in the
adversarial slot, a mesh file changed after planning is refused before any trial, and the tag card
from ``advobj fabricate`` locates the object under its own name through the recorded T_obj_tag."""

from __future__ import annotations

import numpy as np
import pytest

from tests.trials.real.own_mesh_helpers import box_obj_mm, own_scene, run_on_scene


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    from sim.spec import load_spec
    from trials.real.plan import make_plan, texture_ref

    d = tmp_path_factory.mktemp("own_stage")
    box_obj_mm(d / "my_box.obj")
    scene = own_scene(d / "my.yaml", "my_box.obj")
    run = run_on_scene(d / "run", scene, size=32)
    spec = load_spec(scene)
    tex = {"my_box/adv3d": texture_ref(run, "my_box/adv3d", spec, str(scene))}
    plan = make_plan(spec, 3, ["A"], ["my_box"], ["clean", "adv3d"], tex, n_tcp_poses=1, n_object_layouts=1)
    return {"dir": d, "scene": scene, "spec": spec, "run": run, "plan": plan}


def _trial(plan, condition):
    return next(t for t in plan.trials if t.condition == condition)


def _look_down_at(world, point, height_m=0.3):
    """Put the TCP so that the wrist camera looks straight down at ``point`` from ``height_m`` above it."""
    from sim.geometry import invert_T, look_at

    T_world_cam = look_at(np.asarray(point) + [0.0, 0.0, height_m], point)
    world.set_tcp_pose(T_world_cam @ invert_T(world.T_tcp_cam))


def test_the_stage_puts_the_plans_scene_object_in_the_adversarial_slot_with_its_texture(cell):
    from sim.world import SimWorld
    from trials.real.stage import SimStage

    plan = cell["plan"]
    with SimWorld(cell["spec"], 96) as world:
        world.reset(0)
        stage = SimStage(world, plan, cell["dir"])
        looks = {}
        for cond in ("clean", "adv3d"):
            stage.prepare(_trial(plan, cond))
            adv = world.spec.adversarial
            assert adv.name == "my_box" and adv.units == "mm" and adv.mesh == str(cell["dir"] / "my_box.obj")
            k = world.spec.object_index("adversarial")
            placed = plan.object_layout(0).objects["adversarial"]
            np.testing.assert_allclose(world.T_world_objects[k][:2, 3], placed.xy_m, atol=1e-9)
            _look_down_at(world, world.object_center_array[k], 0.2)
            out = world.render(world.T_world_tcp @ world.T_tcp_cam, with_ids=True)
            mask = out.object_mask(k)
            assert mask.sum() > 200  # the box fills the middle of the view
            looks[cond] = out.rgb[mask].astype(float)
        assert stage.builds == 2
        assert np.abs(looks["clean"] - looks["adv3d"]).mean() > 10  # the attack texture is on it
        stage.close()


def test_a_mesh_file_changed_after_planning_is_refused_before_any_trial(cell, tmp_path):
    import shutil

    from sim.spec import load_spec
    from sim.world import SimWorld
    from trials.real.plan import make_plan
    from trials.real.stage import SimStage, StageError

    shutil.copy(cell["dir"] / "my_box.obj", tmp_path / "my_box.obj")
    scene = own_scene(tmp_path / "my.yaml", "my_box.obj")
    spec = load_spec(scene)
    plan = make_plan(spec, 0, ["A"], ["my_box"], ["clean"], {}, n_tcp_poses=1, n_object_layouts=1)
    with open(tmp_path / "my_box.obj", "a") as f:
        f.write("# edited after the plan was made\n")
    with SimWorld(spec, 32) as world, pytest.raises(StageError) as err:
        SimStage(world, plan, tmp_path)
    msg = str(err.value)
    assert msg.startswith("shape_objects.my_box.object.mesh: mesh file ") and "changed since it was recorded" in msg


def test_the_fabricated_tag_card_locates_the_object_by_its_name_through_T_obj_tag(cell, tmp_path):
    """The tag card of ``advobj fabricate --scene --shape my_box --tag-id 7``, drawn by the sim camera
    where the card lies (beside the object, on the table), read by the real detector: the object's
    own pose and centre come back from the tag's pose and the recorded T_obj_tag."""
    from calibration.registry import load_registry
    from robot_io.cameras.sim import SimCamera, sim_tags
    from sim.geometry import rotation_angle
    from sim.world import SimWorld
    from trials.fabrication.fabricate import fabricate
    from trials.real.locate import TagLocator, placement_issues
    from trials.real.stage import SimStage

    fabricate(
        cell["run"], tmp_path / "fab", scene=cell["scene"], shape="my_box", tag=(7, 40.0), dpi=60, log=lambda _t: None
    )
    reg = load_registry(tmp_path / "fab" / "objects.yaml")
    assert reg.objects == ("my_box",)
    plan = cell["plan"]
    trial = _trial(plan, "adv3d")
    with SimWorld(cell["spec"], 480) as world:
        world.reset(0)
        stage = SimStage(world, plan, cell["dir"])
        stage.prepare(trial)
        k = world.spec.object_index("adversarial")
        _look_down_at(world, world.T_world_objects[k][:3, 3] + [-0.05, 0.0, 0.0], 0.35)
        camera = SimCamera(world, tags=sim_tags(reg))
        locator = TagLocator(reg, camera.intrinsics, camera.T_tcp_cam, np.eye(4))
        with camera:
            frame = camera.read()
        assert "adversarial" not in locator.locate(frame, world.T_world_tcp)  # the registry names it my_box
        locator.for_trial(plan, trial)
        got = locator.locate(frame, world.T_world_tcp)["adversarial"]
        assert got.tag_ids == (7,)
        T_true = world.T_world_objects[k]
        assert np.linalg.norm(got.T_table_object[:3, 3] - T_true[:3, 3]) < 0.004  # the base centre, not the tag
        assert np.degrees(rotation_angle(got.T_table_object[:3, :3], T_true[:3, :3])) < 2.0
        assert np.linalg.norm(got.center_table_m - world.object_center_array[k]) < 0.004
        layout = plan.object_layout(trial.object_layout).objects
        assert placement_issues({"adversarial": layout["adversarial"]}, {"adversarial": got}, 0.01, 0.0873) == []
        stage.close()
