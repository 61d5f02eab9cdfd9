"""A fixed scene camera located against the table's tags: synthetic renders with a known pose, the
refusals, the pose file and ``advobj calibrate scene-camera``."""

from __future__ import annotations

import sys

import imageio.v3 as iio
import numpy as np
import pytest
from typer.testing import CliRunner

from calibration import synthetic as S
from calibration.errors import CalibrationError, CalibrationFileError
from calibration.intrinsics import CameraIntrinsics, save_camera_yaml
from calibration.io import T_to_pose, load_scene_camera_pose, save_scene_camera_pose
from calibration.registry import ObjectRegistry, TagEntry, save_registry
from calibration.scene_camera import locate_scene_camera
from sim.geometry import invert_T, look_at, make_T, rotation_angle, so3_exp
from trials.cli.main import app

from .conftest import H, W

# The stated tolerance: PnP over 4 tags of 6 cm seen from 0.8 m at 640x480 px, blurred and noisy.
POSITION_TOL_M = 0.005
ANGLE_TOL_DEG = 0.5
TABLE_TAGS_XY_M = ((-0.15, -0.12), (0.15, -0.12), (-0.15, 0.12), (0.15, 0.12))


def table_registry(xy=TABLE_TAGS_XY_M, size_m: float = 0.06) -> ObjectRegistry:
    """Tags lying face up on the table at ``xy`` (table frame), plus a goal tag (not the table's)."""
    tags = {
        i: TagEntry(object="table", size_m=size_m, T_tag_object=T_to_pose(make_T(np.eye(3), [-x, -y, 0.0])))
        for i, (x, y) in enumerate(xy)
    }
    tags[10] = TagEntry(object="goal", size_m=0.04, T_tag_object=T_to_pose(make_T(np.eye(3), [0.0, 0.0, -0.05])))
    return ObjectRegistry(tags=tags)


# The front camera of scenes/two-cameras.yaml: 0.8 m from the table's centre, 35 deg above the table top.
T_TABLE_FRONT = look_at(np.array([0.33, -0.57, 0.51]), np.array([0.0, 0.0, 0.05]))


def render_table(registry, T_table_cam, K, seed=0):
    img = S.render_planes(S.object_tag_planes(registry, invert_T(T_table_cam)), K, W, H)
    return S.degrade(img, 0.6, 2.0, seed=seed)


@pytest.fixture(scope="module")
def front_views(K):
    reg = table_registry()
    return reg, [render_table(reg, T_TABLE_FRONT, K, seed=i) for i in range(3)]


def _pose_error(T, T_true):
    return float(np.linalg.norm(T[:3, 3] - T_true[:3, 3])), float(np.degrees(rotation_angle(T[:3, :3], T_true[:3, :3])))


def test_the_known_pose_is_recovered_from_the_table_tags_within_tolerance(front_views, cam):
    reg, images = front_views
    fit = locate_scene_camera(images, cam, reg)
    dp, da = _pose_error(fit.T_table_cam, T_TABLE_FRONT)
    assert dp < POSITION_TOL_M and da < ANGLE_TOL_DEG, (dp, da)
    assert fit.tag_ids == (0, 1, 2, 3) and fit.n_images == 3 and fit.n_corners == 3 * 4 * 4
    assert 0 < fit.reprojection_rms_px < 1.0 and all(0 < r < 1.0 for r in fit.per_image_rms_px)
    assert (fit.width, fit.height) == (W, H)


def test_one_image_suffices_and_a_top_down_camera_is_located_too(K, cam):
    reg = table_registry()
    T_top = look_at(np.array([0.02, -0.03, 0.9]), np.array([0.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    fit = locate_scene_camera([render_table(reg, T_top, K)], cam, reg)
    dp, da = _pose_error(fit.T_table_cam, T_top)
    assert dp < POSITION_TOL_M and da < ANGLE_TOL_DEG, (dp, da)


def test_one_table_tag_in_view_is_refused_as_too_few(K, cam):
    reg = table_registry(xy=TABLE_TAGS_XY_M[:1] + ((3.0, 3.0),))  # tag 1 far off the camera's view
    with pytest.raises(CalibrationError, match=r"table tag 0 seen in 1 image\(s\); at least 2 distinct"):
        locate_scene_camera([render_table(reg, T_TABLE_FRONT, K)], cam, reg)


def test_no_tag_at_all_is_refused_naming_the_registrys_table_tags(cam):
    grey = np.full((H, W, 3), 128, np.uint8)
    with pytest.raises(CalibrationError, match=r"no table tag seen in 2 image\(s\).*table tags: 0, 1, 2, 3"):
        locate_scene_camera([grey, grey], cam, table_registry())


def test_a_camera_that_moved_between_the_images_is_refused_by_its_rms(front_views, K, cam):
    reg, images = front_views
    moved = T_TABLE_FRONT @ make_T(so3_exp(np.radians([0.0, 2.0, 0.0])), [0.03, 0.0, 0.0])
    with pytest.raises(CalibrationError, match=r"RMS reprojection error of .* px, over the limit of 2 px.*image 1"):
        locate_scene_camera([images[0], render_table(reg, moved, K, seed=5)], cam, reg)


def test_a_wrong_camera_file_is_refused_by_its_rms_or_its_size(front_views, K):
    reg, images = front_views
    K_wide = K.copy()
    K_wide[:2, :2] *= 0.7  # another camera's focal length
    wide = CameraIntrinsics(K_wide, np.zeros(5), W, H)
    with pytest.raises(CalibrationError, match="over the limit"):
        locate_scene_camera(images, wide, reg, max_rms_px=0.5)
    small = CameraIntrinsics(K / 2 + np.diag([0, 0, 0.5]), np.zeros(5), W // 2, H // 2)
    with pytest.raises(CalibrationError, match=r"image 0: image: size 640x480 does not match .* 320x240"):
        locate_scene_camera(images, small, reg)


def test_the_pose_file_round_trips_and_names_a_bad_field(tmp_path):
    p = save_scene_camera_pose(tmp_path / "front.yaml", T_TABLE_FRONT, W, H, 0.1234567, (3, 1), 2)
    f = load_scene_camera_pose(p)
    np.testing.assert_allclose(f.T, T_TABLE_FRONT, atol=1e-12)
    assert (f.width, f.height, f.reprojection_rms_px, f.tag_ids, f.n_images) == (W, H, 0.1235, [1, 3], 2)
    p.write_text(p.read_text().replace("width: 640", "width: -3"))
    with pytest.raises(CalibrationFileError, match=r"front.yaml: width: "):
        load_scene_camera_pose(p)
    p.write_text("T_table_cam: {translation_m: [0, 0, .nan]}\nwidth: 640\nheight: 480\n")
    with pytest.raises(CalibrationFileError, match=r"T_table_cam.translation_m.2: Input should be a finite number"):
        load_scene_camera_pose(p)
    p.write_text("T_table_cam: {}\nwidth: 640\n")
    with pytest.raises(CalibrationFileError, match=r"front.yaml: height: Field required"):
        load_scene_camera_pose(p)


@pytest.fixture()
def cli_files(tmp_path, front_views, cam):
    reg, images = front_views
    paths = []
    for i, img in enumerate(images[:2]):
        paths.append(tmp_path / f"front_{i}.png")
        iio.imwrite(paths[-1], img)
    return {
        "images": paths,
        "camera": save_camera_yaml(tmp_path / "front_cam.yaml", cam),
        "registry": save_registry(tmp_path / "objects.yaml", reg),
    }


def test_calibrate_scene_camera_writes_the_pose_the_hardware_config_reads(cli_files, tmp_path):
    out = tmp_path / "front_pose.yaml"
    argv = ["calibrate", "scene-camera", *map(str, cli_files["images"]), "--camera", str(cli_files["camera"])]
    r = CliRunner().invoke(app, argv + ["--registry", str(cli_files["registry"]), "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "RMS " in r.output and "table tags 0, 1, 2, 3 in 2 image(s)" in r.output and f"wrote {out}" in r.output
    f = load_scene_camera_pose(out)
    dp, da = _pose_error(f.T, T_TABLE_FRONT)
    assert dp < POSITION_TOL_M and da < ANGLE_TOL_DEG and (f.width, f.height) == (W, H) and f.n_images == 2


def test_calibrate_scene_camera_refuses_too_few_tags_in_one_line_and_writes_nothing(
    cli_files, tmp_path, monkeypatch, capsys
):
    from trials.cli.main import main

    out = tmp_path / "out" / "front_pose.yaml"
    argv = ["calibrate", "scene-camera", *map(str, cli_files["images"]), "--camera", str(cli_files["camera"])]
    argv += ["--registry", str(cli_files["registry"]), "--out", str(out), "--min-tags", "5"]
    monkeypatch.setattr(sys, "argv", ["advobj", *argv])
    with pytest.raises(SystemExit) as ex:
        main()
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert ex.value.code == 2 and len(lines) == 1, lines
    assert lines[0].startswith("error: table tags 0, 1, 2, 3 seen in 2 image(s); at least 5 distinct"), lines
    assert not out.parent.exists()
