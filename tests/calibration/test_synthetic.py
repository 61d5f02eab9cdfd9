"""The synthetic renderer puts targets where the pinhole model says (the ground truth of every other test)."""

import numpy as np

from calibration import synthetic as S
from calibration.apriltag import TagDetectorOptions, detect_tags, tag_object_points
from sim.geometry import transform_points

from .conftest import H, W


def test_rendered_tag_corners_match_projected_ground_truth(K, cam):
    errs = []
    for s, T in enumerate(S.random_view_poses(4, (0.25, 0.35), 40.0, seed=11)):
        img = S.render_planes([S.tag_plane(3, 0.06, T)], K, W, H)
        (d,) = detect_tags(img, cam, 0.06)
        assert d.tag_id == 3
        truth = cam.project(transform_points(T, tag_object_points(0.06)))
        errs.append(d.corners_px - truth)
    errs = np.concatenate(errs)
    assert np.abs(errs.mean(0)).max() < 0.05  # no systematic pixel-convention offset
    assert np.abs(errs).max() < 0.3


def test_opencv_apriltag_refinement_half_pixel_offset_is_removed(K, cam):
    # Without our edge refinement the raw (offset-corrected) AprilTag corners must still be unbiased.
    opt = TagDetectorOptions(edge_refinement=False)
    errs = []
    for T in S.random_view_poses(4, (0.25, 0.35), 40.0, seed=12):
        (d,) = detect_tags(S.render_planes([S.tag_plane(3, 0.06, T)], K, W, H), cam, 0.06, opt)
        errs.append(d.corners_px - cam.project(transform_points(T, tag_object_points(0.06))))
    assert np.abs(np.concatenate(errs).mean(0)).max() < 0.15


def test_distort_image_moves_points_like_the_distortion_model(K):
    import cv2

    dist = np.array([-0.2, 0.05, 0.0, 0.0, 0.0])
    img = np.zeros((H, W, 3), np.uint8)
    img[200:203, 500:503] = 255  # a bright dot at ideal pixel (501, 201)
    out = S.distort_image(img, K, dist)
    ys, xs = np.nonzero(out[..., 0] > 60)
    found = np.array([xs.mean(), ys.mean()])
    ray = np.linalg.solve(K, [501.0, 201.0, 1.0])
    expect, _ = cv2.projectPoints(ray[None], np.zeros(3), np.zeros(3), K, dist)
    assert np.linalg.norm(found - expect.reshape(2)) < 0.5


def test_degrade_is_reproducible_and_clipped():
    img = np.full((10, 10, 3), 250, np.uint8)
    a = S.degrade(img, 1.0, 20.0, seed=4)
    assert a.dtype == np.uint8 and a.max() == 255
    assert np.array_equal(a, S.degrade(img, 1.0, 20.0, seed=4))
