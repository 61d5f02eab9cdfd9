"""Numerical safety of the attack's math at the extremes (hypothesis, float32)."""

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from attack.losses import grad_cam, masked_mean, pose_loss, safe_cosine, saliency_loss
from attack.pcgrad import normalized_step, pcgrad
from attack.render import sample_bilinear, sample_trilinear, shade
from sim.geometry import look_at

finite = st.floats(-1e3, 1e3, allow_nan=False, width=32)
vec3 = st.lists(finite, min_size=3, max_size=3)


@settings(max_examples=300, deadline=None)
@given(vec3, vec3)
def test_cosine_is_finite_with_finite_gradient_even_for_zero_vectors(a, b):
    ta = torch.tensor([a], dtype=torch.float32, requires_grad=True)
    tb = torch.tensor([b], dtype=torch.float32, requires_grad=True)
    c = safe_cosine(ta, tb)
    c.sum().backward()
    assert torch.isfinite(c).all() and torch.isfinite(ta.grad).all() and torch.isfinite(tb.grad).all()
    assert -1.0001 <= float(c.detach()) <= 1.0001


def test_cosine_of_zero_vector_is_zero():
    z = torch.zeros(1, 3)
    assert float(safe_cosine(z, torch.ones(1, 3))) == 0.0


@settings(max_examples=200, deadline=None)
@given(
    st.floats(0.05, 2.0),  # r (m), including the extremes
    st.floats(0.0, 89.9),  # phi (deg), grazing included
    st.floats(-np.pi, np.pi),
    st.lists(st.floats(-1, 1, width=32), min_size=6, max_size=6),
    st.booleans(),
)
def test_pose_loss_finite_over_distance_and_grazing_views(r, phi_deg, theta, action, adv_at_tcp):
    p_adv = np.array([0.0, 0.0, 0.1])
    phi = np.radians(phi_deg)
    eye = p_adv + r * np.array([np.sin(phi) * np.cos(theta), np.sin(phi) * np.sin(theta), np.cos(phi)])
    T = torch.tensor(look_at(eye, p_adv + np.array([1e-3, 0, 0])), dtype=torch.float32)[None]
    a = torch.tensor([action], dtype=torch.float32, requires_grad=True)
    # adv_at_tcp: the intended position lands exactly on the object (zero-length v_target).
    target = T[:, :3, 3].clone() if adv_at_tcp else torch.from_numpy(p_adv[None]).float()
    if adv_at_tcp:
        a = torch.zeros(1, 6, requires_grad=True)
    loss, parts = pose_loss(T, a, target, 0.02, 0.1, 0.1)
    loss.sum().backward()
    assert torch.isfinite(loss).all() and torch.isfinite(a.grad).all()


@settings(max_examples=200, deadline=None)
@given(
    st.integers(1, 4),
    st.integers(1, 6),
    st.integers(1, 6),
    st.floats(0, 1),
    st.sampled_from(["empty", "full", "one", "random"]),
)
def test_saliency_terms_finite_and_zero_for_empty_masks(b, h, w, scale, kind):
    S = torch.rand(b, h, w) * scale
    H, W = 4 * h, 4 * w
    if kind == "empty":
        m = torch.zeros(b, H, W, dtype=torch.bool)
    elif kind == "full":
        m = torch.ones(b, H, W, dtype=torch.bool)
    elif kind == "one":  # a single-pixel mask
        m = torch.zeros(b, H, W, dtype=torch.bool)
        m[:, 0, 0] = True
    else:
        m = torch.rand(b, H, W) > 0.5
    l = saliency_loss(S, m, m)
    assert torch.isfinite(l).all()
    if kind == "empty":
        assert torch.all(l == 0)
    assert torch.all(masked_mean(S, torch.zeros(b, h, w)) == 0)


def test_grad_cam_is_differentiable_and_finite_for_zero_actions():
    x = torch.rand(2, 3, 8, 8, requires_grad=True)
    conv = torch.nn.Conv2d(3, 4, 3, padding=1)
    A = conv(x)
    a = A.mean(dim=(2, 3))[:, :3] * 0.0  # zero action: the norm's gradient must stay finite
    S = grad_cam(A, a)
    S.sum().backward()
    assert torch.isfinite(S).all() and torch.isfinite(x.grad).all()


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2), st.integers(2, 40))
def test_zero_or_nonfinite_gradient_skips_the_update(kind, n):
    T = torch.rand(3, n, n)
    g = [torch.zeros_like(T), torch.full_like(T, float("nan")), torch.full_like(T, float("inf"))][kind]
    T2, updated = normalized_step(T, g, 0.1)
    assert not updated and torch.equal(T2, T)


@settings(max_examples=300, deadline=None)
@given(
    st.lists(st.floats(-1e3, 1e3, width=32), min_size=8, max_size=8),
    st.lists(st.floats(-1e3, 1e3, width=32), min_size=8, max_size=8),
)
def test_pcgrad_removes_conflict_and_sums(g1, g2):
    a, b = torch.tensor(g1, dtype=torch.float64), torch.tensor(g2, dtype=torch.float64)
    g = pcgrad(a, b)
    assert torch.isfinite(g).all()
    if torch.dot(a, b) >= 0:
        assert torch.allclose(g, a + b)
    elif torch.dot(a, a) > 1e-12 and torch.dot(b, b) > 1e-12:
        p1 = a - torch.dot(a, b) / torch.dot(b, b) * b
        p2 = b - torch.dot(a, b) / torch.dot(a, a) * a
        assert abs(float(torch.dot(p1, b))) <= 1e-6 * (1 + float(a.norm() * b.norm()))
        assert torch.allclose(g, p1 + p2)


@settings(max_examples=200, deadline=None)
@given(st.sampled_from([0.0, 1.0]), st.integers(1, 50), st.floats(-3, 3), st.floats(1e-6, 1e3))
def test_samplers_and_shading_handle_texels_at_exactly_0_and_1(value, p, uv_off, duv_scale):
    tex = torch.full((3, 16, 16), value, requires_grad=True)
    uv = torch.rand(p, 2) + uv_off  # also far outside [0, 1]: clamp-to-edge
    duv = torch.randn(p, 2, 2) * duv_scale / 16
    for f in (sample_bilinear, sample_trilinear):
        c = f(tex, uv, duv)
        out = shade(c, torch.rand(p, 3) * 2, torch.rand(p, 3) * 0.1)
        out.sum().backward()
        assert torch.isfinite(out).all() and torch.isfinite(tex.grad).all()
        assert torch.allclose(c, torch.full_like(c, value), atol=1e-6)
        tex.grad = None
