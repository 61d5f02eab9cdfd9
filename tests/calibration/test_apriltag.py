"""AprilTag poses: accuracy on renders, both IPPE solutions, ambiguity/oblique flags, bad images, bundles."""

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration import synthetic as S
from calibration.apriltag import (
    TagDetectorOptions,
    detect_tags,
    estimate_bundle_pose,
    tag_object_points,
    tag_pose_solutions,
)
from sim.geometry import make_T, rotation_angle, transform_points

from .conftest import H, W


def _render_tag(K, T, size=0.04, tag_id=7, blur=0.7, noise=2.0, seed=0, dictionary=None):
    return S.degrade(
        S.render_planes([S.tag_plane(tag_id, size, T, dictionary=dictionary)], K, W, H), blur, noise, seed=seed
    )


def _views(distance, tilt_deg, n, seed=0):
    out = []
    for s in range(n):
        rng = np.random.default_rng(seed * 100 + s)
        a = rng.uniform(0, np.pi)
        out.append(
            S.camera_facing(
                distance,
                np.radians(tilt_deg),
                (np.cos(a), np.sin(a), 0),
                rng.uniform(-0.5, 0.5),
                rng.uniform(-0.04, 0.04, 2),
            )
        )
    return out


@pytest.mark.parametrize("tilt_deg", [0.0, 25.0, 45.0])
def test_tag_position_within_3mm_at_half_metre(K, cam, tilt_deg):
    for s, T in enumerate(_views(0.5, tilt_deg, 5, seed=int(tilt_deg))):
        (d,) = detect_tags(_render_tag(K, T, seed=s), cam, 0.04)
        assert np.linalg.norm(d.T_cam_tag[:3, 3] - T[:3, 3]) < 0.003


def test_frontal_tag_orientation_within_one_degree(K, cam):
    # 60 mm tag at 0.5 m (~90 px): the tilt of a frontal tag is observable to < 1 deg.
    for s, T in enumerate(_views(0.5, 0.0, 6, seed=5)):
        (d,) = detect_tags(_render_tag(K, T, size=0.06, seed=s), cam, 0.06)
        assert np.degrees(rotation_angle(d.T_cam_tag[:3, :3], T[:3, :3])) < 1.0
        assert not d.flags


def test_small_frontal_tag_with_poor_orientation_is_flagged(K, cam):
    # 40 mm at 0.5 m (~37 px): position stays good, tilt does not; every > 1 deg error must be flagged.
    for s, T in enumerate(_views(0.5, 0.0, 8, seed=6)):
        (d,) = detect_tags(_render_tag(K, T, seed=s), cam, 0.04)
        err = np.degrees(rotation_angle(d.T_cam_tag[:3, :3], T[:3, :3]))
        if err > 1.0:
            assert {"ambiguous", "uncertain_orientation"} & set(d.flags), (err, d.flags)
        assert d.orientation_std_deg > 0.3  # the reported uncertainty admits it
        assert np.linalg.norm(d.T_cam_tag[:3, 3] - T[:3, 3]) < 0.003


def test_both_ippe_solutions_are_reported_best_first(K, cam):
    T = _views(0.4, 30.0, 1, seed=7)[0]
    (d,) = detect_tags(_render_tag(K, T), cam, 0.04)
    assert len(d.solutions) == 2
    e = [s.reprojection_rms_px for s in d.solutions]
    assert e[0] <= e[1] and d.ambiguity_ratio == pytest.approx(e[0] / e[1])
    assert d.solution_angle_deg > 1.0  # a genuinely different second pose
    assert not d.ambiguous  # at 30 deg tilt the wrong one fits clearly worse
    js = d.to_dict()
    assert js["id"] == 7 and len(js["solutions"]) == 2 and js["ambiguous"] is False


def test_oblique_70_degree_views_are_flagged_or_missed(K, cam):
    seen = 0
    for s, T in enumerate(_views(0.35, 70.0, 6, seed=8)):
        dets = detect_tags(_render_tag(K, T, size=0.06, seed=s), cam, 0.06)
        for d in dets:
            seen += 1
            assert "oblique" in d.flags
            ray = T[:3, 3] / np.linalg.norm(T[:3, 3])
            true_view = np.degrees(np.arccos(abs(T[:3, 2] @ ray)))  # tilt plus the off-axis angle
            assert d.view_angle_deg == pytest.approx(true_view, abs=2.0)
            assert np.linalg.norm(d.T_cam_tag[:3, 3] - T[:3, 3]) < 0.01
    assert seen >= 1  # handled, not just dropped


def test_unknown_size_gives_corners_without_pose(K, cam):
    (d,) = detect_tags(_render_tag(K, _views(0.4, 20.0, 1)[0]), cam, None)
    assert d.solutions == () and "unknown_size" in d.flags and d.T_cam_tag is None


@pytest.mark.parametrize("case", ["blank", "black", "saturated", "noise", "wrong_dictionary", "tiny"])
def test_bad_images_give_empty_or_flagged_results_never_exceptions(K, cam, case):
    T = S.camera_facing(0.4)
    img = {
        "blank": lambda: np.full((H, W, 3), 128, np.uint8),
        "black": lambda: np.zeros((H, W, 3), np.uint8),
        "saturated": lambda: np.full((H, W), 255, np.uint8),
        "noise": lambda: np.random.default_rng(0).integers(0, 256, (H, W), dtype=np.uint8),
        "wrong_dictionary": lambda: _render_tag(K, T, dictionary=cv2.aruco.DICT_4X4_50, tag_id=3),
        "tiny": lambda: _render_tag(K, S.camera_facing(1.5), size=0.012, blur=0.0, noise=0.0),  # ~4 px
    }[case]()
    dets = detect_tags(img, cam, 0.04)
    assert dets == [] or all(d.flags for d in dets)


def test_saturated_tag_image_does_not_raise(K, cam):
    img = np.clip(_render_tag(K, S.camera_facing(0.3)).astype(int) * 4, 0, 255).astype(np.uint8)
    for d in detect_tags(img, cam, 0.04):
        assert d.solutions


def test_image_of_another_resolution_is_refused(cam):
    with pytest.raises(ValueError, match="does not match the camera"):
        detect_tags(np.zeros((100, 100), np.uint8), cam, 0.04)


def _bundle_scene(K, T_cam_obj, size=0.04, spacing=0.12, seed=0):
    """Four tags on the corners of a square plate (object frame = plate centre, tags face +z)."""
    offsets = [(-1, 1), (1, 1), (1, -1), (-1, -1)]
    corners, planes = {}, []
    for i, (ox, oy) in enumerate(offsets):
        T_obj_tag = make_T(np.eye(3), [ox * spacing / 2, oy * spacing / 2, 0.0])
        corners[10 + i] = transform_points(T_obj_tag, tag_object_points(size))
        planes.append(S.tag_plane(10 + i, size, T_cam_obj @ T_obj_tag, margin=0.3))
    img = S.degrade(S.render_planes(planes, K, W, H), 0.7, 2.0, seed=seed)
    return img, corners


def test_multi_tag_bundle_resolves_the_frontal_ambiguity(K, cam):
    for s, T in enumerate(_views(0.5, 0.0, 4, seed=9)):
        img, corners = _bundle_scene(K, T, seed=s)
        dets = detect_tags(img, cam, 0.04)
        assert len(dets) == 4
        bp = estimate_bundle_pose(dets, corners, cam)
        assert not bp.ambiguous and bp.tag_ids == (10, 11, 12, 13)
        assert np.degrees(rotation_angle(bp.T_cam_frame[:3, :3], T[:3, :3])) < 0.5
        assert np.linalg.norm(bp.T_cam_frame[:3, 3] - T[:3, 3]) < 0.002
        # The same plate seen through one tag alone carries the single-tag uncertainty.
        single = estimate_bundle_pose([dets[0]], {10: corners[10]}, cam)
        assert single.reprojection_rms_px < 0.5


def test_bundle_without_posed_tags_is_none(cam):
    assert estimate_bundle_pose([], {1: tag_object_points(0.04)}, cam) is None


@settings(max_examples=60, deadline=None)
@given(
    dist=st.floats(0.05, 5.0),
    tilt=st.floats(0.0, 89.5),
    axis=st.floats(0.0, np.pi),
    roll=st.floats(-np.pi, np.pi),
    noise=st.floats(0.0, 2.0),
    seed=st.integers(0, 1000),
)
def test_pose_solutions_are_stable_from_frontal_to_grazing(cam, dist, tilt, axis, roll, noise, seed):
    """IPPE on projected corners: never raises, finite poses in front of the camera, sorted errors."""
    T = S.camera_facing(dist, np.radians(tilt), (np.cos(axis), np.sin(axis), 0.0), roll)
    px = cam.project(transform_points(T, tag_object_points(0.04)))
    px = px + np.random.default_rng(seed).normal(0, noise, px.shape)
    sols = tag_pose_solutions(px, 0.04, cam)
    errs = [s.reprojection_rms_px for s in sols]
    assert errs == sorted(errs)
    for s in sols:
        assert np.all(np.isfinite(s.T_cam_tag)) and s.T_cam_tag[2, 3] > 0
    if noise == 0.0 and tilt < 85 and sols:
        best = sols[0].T_cam_tag
        assert np.linalg.norm(best[:3, 3] - T[:3, 3]) < 1e-3 * dist + 1e-6 or len(sols) == 2


def test_detector_option_file_rejects_unknown_keys():
    with pytest.raises(ValueError):
        TagDetectorOptions(ambiguity=0.5)
