"""The whole attack pipeline at its edges: no NaN/Inf, no crash, no update without a gradient.

Camera pose from (r, theta, phi) around the adversarial object -> standard render -> fragments ->
texture sampler -> composite -> policy -> pose and Grad-CAM saliency losses -> PCGrad -> update,
driven through :class:`attack.optimize.AttackRun` over the full grid phi in {0, 89.9} deg x
r in {0.05, 0.15, 2.0} m x all-0 / all-1 / random textures, a fully occluded object, an object out
of view, a camera inside the object's bounding box and a single-pixel mask.
"""

import dataclasses
import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from attack.objective import build_objective
from attack.optimize import AttackRun, resolve_config
from attack.render import Capture
from attack.sources import Frames
from sim.configs import InitialConfig, sample_config
from sim.geometry import look_at
from sim.policies.policy import VisuomotorPolicy
from sim.spec import default_scene

CFG = {"iterations": 1000, "num_envs": 1, "rollout_steps": 1, "texture_size": 16, "validation_every": 0}


@pytest.fixture(scope="module")
def run():
    torch.manual_seed(0)
    spec = default_scene()
    r = AttackRun(
        VisuomotorPolicy(arch="small_cnn", image_size=32),
        spec,
        resolve_config("quick", CFG),
        pool=[sample_config(spec, 10)],
    )  # an attack-part seed (sim.configs.config_part)
    yield r
    r.close()


def _configure(run, update: dict) -> None:
    """Change the run's config and rebuild the objective it implies (as a new run would)."""
    run.cfg = run.cfg.model_copy(update=update)
    run.objective = build_objective(run.cfg, run.spec.episode)


def _adv_center(run) -> np.ndarray:
    w = run.env.worlds[0]
    return w.object_center_array[run.adv]


def _camera(run, r_m: float, theta_deg: float, phi_deg: float) -> np.ndarray:
    """``T_world_cam`` at (r, theta, phi) from the adversarial object's centre, aimed at it."""
    th, ph = math.radians(theta_deg), math.radians(phi_deg)
    d = np.array([math.sin(ph) * math.cos(th), math.sin(ph) * math.sin(th), math.cos(ph)])
    c = _adv_center(run)
    return look_at(c + r_m * d, c)


def _config_for_camera(run, T_world_cam: np.ndarray) -> InitialConfig:
    """The pool configuration with its TCP moved so the wrist camera sits at ``T_world_cam``."""
    base = run.pool[0]
    T_tcp = T_world_cam @ np.linalg.inv(run.spec.camera.T_tcp_cam)
    return dataclasses.replace(base, T_world_tcp=tuple(tuple(float(v) for v in row) for row in T_tcp))


def _forward(run, T_world_cam, texture, keep_pixels=None):
    """One image-action pair through the pipeline; returns the capture and frame_gradients' output."""
    run.env.reset_envs([0], configs=[_config_for_camera(run, T_world_cam)])
    world = run.env.worlds[0]
    cap = run.hybrid.capture(world)
    if keep_pixels is not None:  # cut the fragments (and the mask) down to the first k pixels
        f = cap.fragments
        sl = slice(0, keep_pixels)
        frags = dataclasses.replace(
            f,
            pix=f.pix[sl],
            face=f.face[sl],
            bary=f.bary[sl],
            uv=f.uv[sl],
            duv=f.duv[sl],
            diffuse=f.diffuse[sl],
            specular=f.specular[sl],
        )
        cap = Capture(cap.i_sim, frags, frags.mask(), cap.goal_mask)
    run.state.texture = texture.clone()
    T = torch.from_numpy(world.T_world_tcp[None]).float()
    p_adv = torch.from_numpy(world.object_center_array[None, run.adv]).float()
    return cap, run.frame_gradients(run.state, Frames([cap], T, p_adv))


def _check(run, cap, out, texture):
    """Everything finite; the update happens iff there is a gradient, and is skipped otherwise."""
    assert set(out["grads"]) == {t.name for t in run.objective.terms}
    for name, g in out["grads"].items():
        assert torch.isfinite(g).all(), name
    for name in ("images", "actions"):
        assert torch.isfinite(out[name]).all(), name
    for k, v in out["values"].items():
        assert math.isfinite(v), k
    f = cap.fragments
    for arr in (f.bary, f.uv, f.duv, f.diffuse, f.specular):
        assert np.isfinite(arr).all()
    g, updated = run.apply_update(run.state, list(out["grads"].values()))
    assert torch.isfinite(g).all() and torch.isfinite(run.state.texture).all()
    assert run.state.texture.min() >= 0 and run.state.texture.max() <= 1
    has_grad = bool(torch.linalg.vector_norm(g) > 0)
    assert updated == has_grad
    if not updated:
        assert torch.equal(run.state.texture, texture)
    if f.num_pixels == 0:  # the texture cannot influence anything: no gradient, no update
        assert not has_grad and not updated
    return updated


TEXTURES = {
    "zeros": lambda: torch.zeros(3, 16, 16),
    "ones": lambda: torch.ones(3, 16, 16),
    "random": lambda: torch.rand(3, 16, 16, generator=torch.Generator().manual_seed(3)),
}


PHIS_DEG = (0.0, 89.9)
RADII_M = (0.05, 0.15, 2.0)  # inside the object's bounding sphere, close with the object in view, far


@pytest.mark.parametrize("texture", sorted(TEXTURES))
@pytest.mark.parametrize("r", RADII_M)
@pytest.mark.parametrize("phi", PHIS_DEG)
@settings(max_examples=3, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    theta=st.floats(-180.0, 180.0),
    sampler=st.sampled_from(["bilinear", "trilinear"]),
    loss=st.sampled_from(["targeted", "untargeted"]),
)
def test_viewpoint_and_texture_extremes(run, phi, r, texture, theta, sampler, loss):
    """Every (phi, r, texture) corner of the grid; hypothesis draws the azimuth, sampler and loss."""
    _configure(run, {"sampler": sampler, "loss": loss})
    tex = TEXTURES[texture]()
    cap, out = _forward(run, _camera(run, r, theta, phi), tex)
    _check(run, cap, out, tex)


@pytest.mark.parametrize("phi", PHIS_DEG)
def test_extreme_polar_angles_close_up_see_the_object_and_update(run, phi):
    """The grid above is not vacuous at its angular extremes: straight down (phi 0) and grazing
    (phi 89.9) views from 0.15 m show the object and move the texture, for every texture."""
    _configure(run, {"sampler": "trilinear", "loss": "targeted"})
    for name in sorted(TEXTURES):
        best = None
        for theta in (0.0, 90.0, 180.0, 270.0):  # a grazing view may be hidden behind the goal can
            tex = TEXTURES[name]()
            cap, out = _forward(run, _camera(run, 0.15, theta, phi), tex)
            if best is None or cap.fragments.num_pixels > best[0].fragments.num_pixels:
                best = (cap, out, tex)
        cap, out, tex = best
        assert cap.fragments.num_pixels > 20, (phi, name)
        assert _check(run, cap, out, tex), (phi, name)


def test_near_views_do_update_and_far_views_see_almost_nothing(run):
    """Close up the object fills pixels and the texture moves; at 2 m it covers about a pixel."""
    _configure(run, {"sampler": "trilinear", "loss": "targeted"})
    tex = TEXTURES["random"]()
    cap, out = _forward(run, _camera(run, 0.25, 30.0, 45.0), tex)
    assert cap.fragments.num_pixels > 20 and _check(run, cap, out, tex)
    cap, out = _forward(run, _camera(run, 2.0, 30.0, 45.0), tex)
    assert cap.fragments.num_pixels <= 4
    _check(run, cap, out, tex)


def _occluded_by_table(run):
    """Below the table looking up at the object: the table top hides it completely."""
    c = _adv_center(run)
    return look_at(c - np.array([0.0, 0.0, 0.3]) + np.array([0.01, 0.0, 0.0]), c)


def _out_of_view(run):
    """Beside the object, looking away from it."""
    T = _camera(run, 0.3, 0.0, 60.0)
    eye = T[:3, 3]
    return look_at(eye, eye + (eye - _adv_center(run)))


def _inside_bbox(run):
    """Camera at the object's bounding-box centre, looking along +x."""
    c = _adv_center(run) + np.array([0.0, 0.0, 0.005])
    return look_at(c, c + np.array([1.0, 0.0, 0.0]))


@pytest.mark.parametrize("case", ["occluded", "out_of_view", "inside_bbox"])
@pytest.mark.parametrize("texture", ["zeros", "ones"])
def test_scene_extremes(run, case, texture):
    _configure(run, {"sampler": "trilinear", "loss": "targeted"})
    T = {"occluded": _occluded_by_table, "out_of_view": _out_of_view, "inside_bbox": _inside_bbox}[case](run)
    tex = TEXTURES[texture]()
    cap, out = _forward(run, T, tex)
    if case in ("occluded", "out_of_view"):
        assert cap.fragments.num_pixels == 0 and not cap.adv_mask.any()
    _check(run, cap, out, tex)


@pytest.mark.parametrize("texture", ["zeros", "ones", "random"])
def test_single_pixel_mask(run, texture):
    _configure(run, {"sampler": "trilinear", "loss": "targeted"})
    tex = TEXTURES[texture]()
    cap, out = _forward(run, _camera(run, 0.3, 10.0, 50.0), tex, keep_pixels=1)
    assert cap.fragments.num_pixels == 1 and cap.adv_mask.sum() == 1
    _check(run, cap, out, tex)


def test_zero_and_nonfinite_gradients_skip_the_update(run):
    tex = TEXTURES["random"]()
    run.state.texture = tex.clone()
    zero = torch.zeros_like(tex)
    for g_pose, g_sal in (
        (zero, zero),
        (torch.full_like(tex, float("nan")), zero),
        (zero, torch.full_like(tex, float("inf"))),
    ):
        _, updated = run.apply_update(run.state, [g_pose, g_sal])
        assert not updated and torch.equal(run.state.texture, tex)


@pytest.mark.parametrize("case", ["occluded", "out_of_view"])
def test_a_whole_iteration_without_gradient_is_reported_skipped(run, case):
    """run.step() end to end (env reset, capture, losses, PCGrad, update, env step) from a start
    where the object cannot be seen: the step says so and the texture is unchanged."""
    T = {"occluded": _occluded_by_table, "out_of_view": _out_of_view}[case](run)
    _configure(run, {"sampler": "trilinear", "loss": "targeted"})
    pool, pool_r = run.source.pool, run.source.pool_r
    run.source.pool = [_config_for_camera(run, T)]
    run.source.pool_r = np.array([0.5])
    run.state.texture = TEXTURES["random"]()
    before, skipped = run.state.texture.clone(), run.state.history.skipped
    try:
        info = run.step()
    finally:
        run.source.pool, run.source.pool_r = pool, pool_r
    assert info["updated"] is False and run.state.history.skipped == skipped + 1
    assert torch.equal(run.state.texture, before)
    assert all(
        math.isfinite(v)
        for v in (run.state.history.loss_pose[-1], run.state.history.loss_saliency[-1], run.state.history.grad_norm[-1])
    )
