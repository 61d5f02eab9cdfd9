"""The policy's view of a camera frame: preprocessing modes, the intrinsics they imply, and the
comparison with the training camera."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sim.policyview import PREPROCESS_MODES, fov_deg, policy_view, policy_view_K, view_mismatch

K640 = np.array([[420.0, 0.0, 331.2], [0.0, 420.0, 236.9], [0.0, 0.0, 1.0]])


def _dot_frame(K, W, H, p_cam):
    """A black frame with a bright 5x5 blob centred where ``p_cam`` projects (sub-pixel by its centroid)."""
    img = np.zeros((H, W, 3), np.uint8)
    u, v = (K @ (p_cam / p_cam[2]))[:2]
    ys, xs = np.mgrid[0:H, 0:W]
    w = np.exp(-((xs - u) ** 2 + (ys - v) ** 2) / (2 * 2.0**2))
    img[...] = np.clip(255 * w, 0, 255).astype(np.uint8)[..., None]
    return img, (u, v)


@pytest.mark.parametrize("mode", PREPROCESS_MODES)
@pytest.mark.parametrize("p", [(0.0, 0.0, 1.0), (0.12, -0.08, 0.7), (-0.15, 0.1, 0.9)])
def test_a_point_lands_where_the_implied_intrinsics_project_it(mode, p):
    p = np.array(p)
    img, _ = _dot_frame(K640, 640, 480, p)
    out = policy_view(img, 96, mode)
    assert out.shape == (96, 96, 3) and out.dtype == np.uint8
    Kv = policy_view_K(K640, 640, 480, 96, mode)
    u, v = (Kv @ (p / p[2]))[:2]
    g = out[..., 0].astype(float)
    if mode == "letterbox":
        g = np.where(out[..., 0] == 128, 0.0, g)  # the grey bars are not the dot
    ys, xs = np.mgrid[0:96, 0:96]
    m = g > 0.3 * g.max()
    cu, cv = (g * xs)[m].sum() / g[m].sum(), (g * ys)[m].sum() / g[m].sum()
    assert abs(cu - u) < 0.35 and abs(cv - v) < 0.35


def test_center_crop_keeps_square_pixels_and_drops_the_sides_resize_squashes():
    Kc = policy_view_K(K640, 640, 480, 128, "center_crop")
    Kr = policy_view_K(K640, 640, 480, 128, "resize")
    Kl = policy_view_K(K640, 640, 480, 128, "letterbox")
    assert Kc[0, 0] == pytest.approx(Kc[1, 1]) and Kl[0, 0] == pytest.approx(Kl[1, 1])
    assert Kr[0, 0] / Kr[1, 1] == pytest.approx(480 / 640)
    assert fov_deg(Kc, 128, 128)[0] == pytest.approx(
        math.degrees(2 * math.atan(240 / 420.0))
    )  # 480 px of the frame seen
    assert fov_deg(Kl, 128, 128)[0] == pytest.approx(math.degrees(2 * math.atan(320 / 420.0)), rel=1e-2)  # all 640 px
    img = np.full((480, 640, 3), 200, np.uint8)
    lb = policy_view(img, 128, "letterbox")
    assert (lb[:16] == 128).all() and (lb[-16:] == 128).all() and (lb[16:-16] == 200).all()  # bars above and below


@settings(max_examples=60, deadline=None)
@given(W=st.integers(1, 4000), H=st.integers(1, 4000), S=st.integers(1, 256), mode=st.sampled_from(PREPROCESS_MODES))
def test_any_frame_size_gives_the_input_size_and_finite_intrinsics(W, H, S, mode):
    K = np.array([[0.8 * W + 1, 0.0, W / 2], [0.0, 0.8 * W + 1, H / 2], [0.0, 0.0, 1.0]])
    Kv = policy_view_K(K, W, H, S, mode)
    assert np.isfinite(Kv).all() and Kv[0, 0] > 0 and Kv[1, 1] > 0
    if W * H <= 4_000_000:
        assert policy_view(np.zeros((H, W, 3), np.uint8), S, mode).shape == (S, S, 3)


def test_unknown_mode_is_refused():
    with pytest.raises(ValueError, match="preprocess: expected one of center_crop"):
        policy_view(np.zeros((4, 4, 3), np.uint8), 2, "stretch")


def test_view_mismatch_names_fov_aspect_principal_point_and_mount():
    from sim.spec import default_scene

    cam = default_scene().camera
    S = 64
    K_train, T = cam.K(S, S), cam.T_tcp_cam
    assert view_mismatch(K_train, K_train, S, T, T) == []
    wide = policy_view_K(np.array([[200.0, 0, 319.5], [0, 200.0, 239.5], [0, 0, 1]]), 640, 480, S, "center_crop")
    (m,) = view_mismatch(wide, K_train, S, T, T)
    assert m.startswith("field of view 100.4 x 100.4 deg") and "smaller than in training" in m
    squashed = policy_view_K(np.array([[343.0, 0, 319.5], [0, 343.0, 239.5], [0, 0, 1]]), 640, 480, S, "resize")
    assert any("times as wide as tall" in x for x in view_mismatch(squashed, K_train, S, T, T))
    T2 = T.copy()
    T2[:3, 3] += [0.05, 0.0, 0.0]
    (m,) = view_mismatch(K_train, K_train, S, T2, T)
    assert "mount T_tcp_cam differs" in m and "5.0 cm" in m
