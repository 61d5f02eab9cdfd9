"""Scene spec validation: good files load, bad ones fail naming the file and the field."""

import numpy as np
import pytest
import yaml

from sim.spec import SpecError, default_scene, load_scene, scene_from_dict


def _write(tmp_path, data, name="scene.yaml"):
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data))
    return p


def _base():
    return default_scene().model_dump(mode="json")


def test_default_scene_is_the_paper_task():
    s = default_scene()
    assert s.goal.mesh == "tomato_soup_can"
    assert s.adversarial.mesh == "mustard_bottle"
    assert s.episode.max_steps == 60 and s.episode.success_radius_m == 0.10
    assert s.camera.width == 128 and s.camera.height == 128


def test_round_trip_through_yaml(tmp_path):
    p = _write(tmp_path, _base())
    assert load_scene(p) == default_scene().model_copy(update={})


def test_unknown_key_is_an_error_naming_file_and_field(tmp_path):
    d = _base()
    d["objects"][1]["colour"] = [1, 0, 0]
    p = _write(tmp_path, d)
    with pytest.raises(SpecError) as e:
        load_scene(p)
    assert str(p) in str(e.value) and "objects.1.colour" in str(e.value)


@pytest.mark.parametrize(
    "mutate, field",
    [
        (lambda d: d["camera"].update(width=-5), "camera.width"),
        (lambda d: d["objects"][0].update(role="target"), "objects.0.role"),
        (lambda d: d["lighting"]["lights"][0].update(direction=[0, 0, 0]), "lighting.lights.0.direction"),
        (lambda d: d["init"].update(r_range_m=[0.8, 0.25]), "init"),
        (lambda d: d["camera"].update(fx=100.0), "camera"),
        (lambda d: d["background"].__setitem__(0, 3.0), "background"),
        (lambda d: d["episode"].update(success_radius_m=0), "episode.success_radius_m"),
    ],
)
def test_bad_values_name_their_field(mutate, field):
    d = _base()
    mutate(d)
    with pytest.raises(SpecError) as e:
        scene_from_dict(d, source="bad.yaml")
    assert "bad.yaml" in str(e.value) and field in str(e.value)


def test_exactly_one_goal_and_one_adversarial_object():
    d = _base()
    d["objects"][1]["role"] = "goal"
    with pytest.raises(SpecError, match="adversarial"):
        scene_from_dict(d)


def test_missing_and_malformed_files_are_reported(tmp_path):
    with pytest.raises(SpecError, match="nope.yaml"):
        load_scene(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("objects: [unclosed")
    with pytest.raises(SpecError, match="bad.yaml"):
        load_scene(bad)
    lst = _write(tmp_path, [1, 2], "list.yaml")
    with pytest.raises(SpecError, match="mapping"):
        load_scene(lst)


def test_relative_mesh_paths_resolve_next_to_the_yaml(tmp_path):
    (tmp_path / "m.obj").write_text("v 0 0 0\n")
    d = _base()
    d["objects"][1]["mesh"] = "m.obj"
    p = _write(tmp_path, d)
    assert load_scene(p).objects[1].mesh == str(tmp_path / "m.obj")


def test_intrinsics_from_fov_and_explicit_rescale():
    cam = default_scene().camera
    K = cam.K()
    assert np.isclose(K[0, 2], 63.5) and np.isclose(K[1, 2], 63.5)
    K64 = cam.K(64, 64)
    assert np.isclose(K64[0, 0] * 2, K[0, 0])
    d = _base()
    d["camera"].update(fx=100.0, fy=100.0, cx=63.5, cy=63.5, fov_deg=None)
    K2 = scene_from_dict(d).camera.K(64, 64)
    assert np.allclose(K2[:2, :], [[50, 0, 31.5], [0, 50, 31.5]])


def test_the_built_in_scenes_fingerprint_is_unchanged_so_existing_pools_stay_valid():
    from sim.configs import spec_fingerprint

    # Every pool written for the built-in scene carries this value; fields added to scene objects
    # later (units, up_axis, placement) must not change it while they are at their defaults.
    assert spec_fingerprint(default_scene()) == "60e09fc80f149e90"
