"""The tag36h11 detector: AprilTag 3 by default, cv2.aruco on request; dictionaries by name; clean exit."""

import subprocess
import sys

import cv2
import numpy as np
import pytest

from calibration import synthetic as S
from calibration.apriltag import (
    TAG_DICTIONARIES,
    TagDetectorOptions,
    detect_tag_corners,
    detect_tags,
    resolve_dictionary,
    tag_object_points,
)
from calibration.intrinsics import to_gray

from .conftest import H, W


def _truth(cam, T, size):
    return cam.project((T[:3, :3] @ tag_object_points(size).T).T + T[:3, 3])


@pytest.mark.parametrize("roll", [0.0, 1.3, 2.9, -2.0])
def test_both_backends_give_the_same_corners_in_the_same_order(K, cam, roll):
    T = S.camera_facing(0.45, np.radians(30), (0.6, 0.8, 0.0), roll, (0.03, -0.02))
    img = S.degrade(S.render_planes([S.tag_plane(11, 0.04, T)], K, W, H), 0.7, 2.0)
    truth = _truth(cam, T, 0.04)
    for backend in ("apriltag3", "aruco"):
        (d,) = detect_tags(img, cam, 0.04, TagDetectorOptions(backend=backend))
        assert d.tag_id == 11 and np.linalg.norm(d.corners_px - truth, axis=1).max() < 0.3, backend
        assert np.linalg.norm(d.T_cam_tag[:3, 3] - T[:3, 3]) < 0.003


def test_apriltag3_raw_corners_follow_the_opencv_pixel_convention(K, cam):
    # Before our edge refinement: the library's corners, reordered and shifted by half a pixel.
    T = S.camera_facing(0.35, np.radians(20), (1.0, 0.0, 0.0), 0.4)
    gray = to_gray(S.render_planes([S.tag_plane(5, 0.04, T)], K, W, H))
    ((tag_id, c),) = detect_tag_corners(gray, "tag36h11", "apriltag3")
    assert tag_id == 5 and np.linalg.norm(c - _truth(cam, T, 0.04), axis=1).max() < 0.5


def test_aruco_dictionaries_are_detected_by_name(K, cam):
    T = S.camera_facing(0.4)
    img = S.render_planes([S.tag_plane(9, 0.04, T, dictionary=cv2.aruco.DICT_4X4_50)], K, W, H)
    assert [d.tag_id for d in detect_tags(img, cam, 0.04, dictionary="4X4_50")] == [9]
    assert detect_tags(img, cam, 0.04) == []  # not a tag36h11 tag


@pytest.mark.parametrize(
    "given,name",
    [
        (None, "tag36h11"),
        ("TAG36H11", "tag36h11"),
        ("DICT_4X4_50", "4X4_50"),
        (cv2.aruco.DICT_APRILTAG_36h11, "tag36h11"),
        (cv2.aruco.DICT_5X5_100, "5X5_100"),
    ],
)
def test_dictionary_names_resolve(given, name):
    assert resolve_dictionary(given) == name and name in TAG_DICTIONARIES


def test_unknown_dictionary_and_backend_are_refused():
    with pytest.raises(ValueError, match="unknown '7x7'; choose from tag36h11"):
        resolve_dictionary("7x7")
    with pytest.raises(ValueError):
        TagDetectorOptions(backend="zbar")


@pytest.mark.parametrize("shape", [(1, 1), (7, 300), (480, 640)])
def test_degenerate_and_blank_images_give_no_tags(shape):
    for backend in ("apriltag3", "aruco"):
        assert detect_tag_corners(np.zeros(shape, np.uint8), None, backend) == []


def test_a_process_that_used_apriltag3_exits_cleanly():
    # pupil-apriltags' own destructor frees the family before the detector and segfaults at exit.
    code = (
        "import numpy as np; from calibration.apriltag import detect_tag_corners; "
        "detect_tag_corners(np.zeros((64, 64), np.uint8)); print('ok')"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr


def test_visible_tag_fraction_measures_how_much_of_an_object_is_covered(K, cam):
    from calibration.io import PoseModel
    from calibration.registry import ObjectRegistry, TagEntry, locate_objects, visible_tag_fraction

    # One object carrying two 40 mm tags side by side on its front face, 6 cm apart.
    reg = ObjectRegistry(
        tags={
            1: TagEntry(object="box", size_m=0.04, T_tag_object=PoseModel(translation_m=(0.03, 0.0, 0.0))),
            2: TagEntry(object="box", size_m=0.04, T_tag_object=PoseModel(translation_m=(-0.03, 0.0, 0.0))),
        }
    )
    T_cam_box = S.camera_facing(0.45, np.radians(15), (0.0, 1.0, 0.0))
    planes = {i: S.tag_plane(i, 0.04, T_cam_box @ np.linalg.inv(reg.tags[i].T_tag_object.T)) for i in (1, 2)}
    both = S.render_planes([planes[1], planes[2]], K, W, H)
    one = S.render_planes([planes[1]], K, W, H)  # tag 2 covered (a hand, another object)
    for img, want in ((both, 1.0), (one, 0.5)):
        obs = locate_objects(detect_tags(img, cam, reg.tag_size), reg, cam)["box"]
        frac = visible_tag_fraction(reg, "box", obs.T_cam_object, obs.tag_ids, cam)
        assert frac == pytest.approx(want, abs=0.03)
    away = S.camera_facing(0.45) @ np.diag([1.0, -1.0, -1.0, 1.0])  # the tags' faces turned from the camera
    assert visible_tag_fraction(reg, "box", away, (), cam) is None
