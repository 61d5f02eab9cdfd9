"""Fixed scene cameras of a cell: the config (strict, names, extrinsics required), the sim twin and
the frame-size check that every camera's read() applies."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from calibration.io import save_scene_camera_pose
from robot_io.cameras.base import FrameSizeError
from robot_io.cameras.sim import SimSceneCamera
from robot_io.config import (
    build_camera,
    build_scene_camera,
    hardware_config_from_dict,
    load_hardware_config,
    scene_camera_pose,
)
from robot_io.errors import HardwareConfigError
from sim.geometry import look_at
from sim.spec import load_scene

REPO = Path(__file__).resolve().parents[2]
SAFETY = {"workspace_min_m": [0, 0, 0], "workspace_max_m": [1, 1, 1]}
T_FRONT = look_at(np.array([0.3, -0.6, 0.5]), np.array([0.0, 0.0, 0.05]))


def _cfg(scene_cameras, base=None, camera=None, arm=None):
    data = {
        "camera": camera or {"type": "sim"},
        "arm": arm or {"type": "sim"},
        "safety": SAFETY,
        "scene_cameras": scene_cameras,
    }
    return hardware_config_from_dict(data, source="cell.yaml", base=base)


def test_a_config_without_scene_cameras_is_as_before_and_every_example_still_validates():
    for path in sorted((REPO / "examples" / "hardware").glob("*.yaml")):
        assert load_hardware_config(path).scene_cameras == {}
    assert "scene_cameras" not in hardware_config_from_dict(
        {"camera": {"type": "sim"}, "arm": {"type": "sim"}, "safety": SAFETY}
    ).model_dump(exclude_defaults=True)


def test_a_real_scene_camera_with_no_extrinsics_is_refused_in_one_line_naming_it():
    with pytest.raises(HardwareConfigError) as e:
        _cfg({"front": {"type": "opencv", "device": 2}})
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("cell.yaml: invalid hardware config: scene_cameras.front.opencv: ")
    assert "T_table_cam missing: a fixed scene camera with no extrinsics is refused" in msg
    assert "advobj calibrate scene-camera" in msg


@pytest.mark.parametrize(
    ("name", "match"),
    [
        ("wrist", "'wrist' names the wrist camera"),
        ("Front", "'Front': a camera name is a lower case letter"),
        ("../x", "'../x': a camera name"),
    ],
)
def test_a_scene_camera_name_is_a_plain_lower_case_name_and_not_wrist(name, match):
    with pytest.raises(HardwareConfigError, match=r"scene_cameras: " + match):
        _cfg({name: {"type": "sim"}})


def test_a_sim_scene_camera_needs_the_sim_arm_and_unknown_keys_are_named():
    with pytest.raises(HardwareConfigError, match=r"scene_cameras.front: type 'sim' .* needs arm.type 'sim'"):
        _cfg({"front": {"type": "sim"}}, camera={"type": "replay", "path": "x"}, arm={"type": "ur_rtde", "host": "h"})
    with pytest.raises(HardwareConfigError, match=r"scene_cameras.front.sim.fov_deg: Extra inputs"):
        _cfg({"front": {"type": "sim", "fov_deg": 60}})


def test_scene_camera_paths_are_relative_to_the_yaml(tmp_path):
    cfg = _cfg(
        {"front": {"type": "replay", "path": "rec", "intrinsics": "cam.yaml", "T_table_cam": "front.yaml"}},
        base=tmp_path,
    )
    c = cfg.scene_cameras["front"]
    assert (c.path, c.intrinsics, c.T_table_cam) == (tmp_path / "rec", tmp_path / "cam.yaml", tmp_path / "front.yaml")


@pytest.fixture(scope="module")
def two_camera_world():
    from sim.world import SimWorld

    world = SimWorld(load_scene(REPO / "scenes" / "two-cameras.yaml"), image_size=32, seed=0)
    yield world
    world.close()


def test_the_sim_scene_camera_is_the_scene_s_camera_rendered_by_the_world(two_camera_world):
    world = two_camera_world
    world.reset(seed=2)
    cfg = _cfg({"front": {"type": "sim"}})
    with build_scene_camera(cfg, "front", world) as cam:
        frame = cam.read()
        assert frame.rgb.shape == (128, 128, 3) and cam.label == "front" and cam.frame_size == (128, 128)
        expected = world.render(camera="front", with_ids=False).rgb  # same pose, renderer and (noise-free) look
        np.testing.assert_array_equal(frame.rgb, expected)
        np.testing.assert_allclose(cam.intrinsics.K, world.intrinsics("front"))
        assert cam.identity() == {"serial": "sim", "camera": "front"}
        T = world.T_world_tcp
        T[0, 3] += 0.1  # the arm moves: a fixed camera still sees the table from where it stands
        world.set_tcp_pose(T)
        assert cam.read().seq == 1
    assert scene_camera_pose(cfg, "front") is None  # it stands where the scene puts it


def test_a_sim_scene_camera_with_a_pose_file_renders_from_it(two_camera_world, tmp_path):
    world = two_camera_world
    world.reset(seed=2)
    save_scene_camera_pose(tmp_path / "front.yaml", T_FRONT, 128, 128)
    cfg = _cfg({"front": {"type": "sim", "T_table_cam": "front.yaml"}}, base=tmp_path)
    np.testing.assert_allclose(scene_camera_pose(cfg, "front"), T_FRONT, atol=1e-12)
    with build_scene_camera(cfg, "front", world) as cam:
        moved = cam.read().rgb
    np.testing.assert_array_equal(moved, world.render(T_FRONT, with_ids=False, camera="front").rgb)
    assert np.abs(moved.astype(int) - world.render(camera="front", with_ids=False).rgb.astype(int)).mean() > 1.0


def test_a_sim_scene_camera_the_scene_lacks_and_a_name_the_config_lacks_are_refused(sim_world):
    with pytest.raises(Exception, match=r"unknown camera 'front'; this scene has: wrist"):
        SimSceneCamera(sim_world, "front")
    with pytest.raises(HardwareConfigError, match=r"no camera 'top' in the hardware config \(its scene cameras: front"):
        build_scene_camera(_cfg({"front": {"type": "sim"}}), "top", sim_world)


def _recording(folder: Path, size_wh, n=2) -> Path:
    folder.mkdir()
    for i in range(n):
        iio.imwrite(folder / f"{i:03d}.png", np.full((size_wh[1], size_wh[0], 3), 40 * i, np.uint8))
    return folder


def test_a_real_scene_camera_delivers_frames_of_its_pose_file_s_size_and_refuses_others(tmp_path):
    save_scene_camera_pose(tmp_path / "front.yaml", T_FRONT, 64, 48)
    _recording(tmp_path / "ok", (64, 48))
    _recording(tmp_path / "big", (128, 96))
    cfg = _cfg(
        {
            "front": {"type": "replay", "path": "ok", "T_table_cam": "front.yaml"},
            "top": {"type": "replay", "path": "big", "T_table_cam": "front.yaml"},
        },
        base=tmp_path,
        camera={"type": "replay", "path": "big"},
    )
    with build_scene_camera(cfg, "front") as cam:
        assert cam.read().rgb.shape == (48, 64, 3) and cam.label == "front"
    with build_scene_camera(cfg, "top") as cam, pytest.raises(FrameSizeError) as e:
        cam.read()
    assert str(e.value) == (
        f"camera 'top': a 128x96 px frame, but its pose file {tmp_path / 'front.yaml'} holds for 64x48 px: set the "
        "camera to deliver that size, or calibrate it again at this one"
    )
    with build_camera(cfg) as wrist:  # the wrist camera keeps taking any size, as before
        assert wrist.read().rgb.shape == (96, 128, 3) and wrist.label == "wrist"


def test_a_missing_or_broken_pose_file_is_one_line_naming_it(tmp_path):
    _recording(tmp_path / "ok", (64, 48))
    cfg = _cfg({"front": {"type": "replay", "path": "ok", "T_table_cam": "front.yaml"}}, base=tmp_path)
    with pytest.raises(Exception, match=r"front.yaml: <file>: cannot read"):
        build_scene_camera(cfg, "front")
    (tmp_path / "front.yaml").write_text("T_table_cam: {translation_m: [0, 0, 1]}\nwidth: 0\nheight: 48\n")
    with pytest.raises(Exception, match=r"front.yaml: width: Input should be greater than or equal to 1"):
        scene_camera_pose(cfg, "front")
