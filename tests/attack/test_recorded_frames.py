"""The frame source of a recording (attack.recorded.RecordedFrames), on recordings written from the
simulator in the test: the object composited into them as the simulator renders it, lit as brightly
as the frame, behind the gripper; the lens and the policy's crop mapped exactly; open loop along the
recorded episodes; the toward measure, the episode split and the refusals."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from attack.optimize import resolve_config
from attack.recorded import (
    TOWARD_DEG,
    RecordedAttackError,
    RecordedFrames,
    ViewRays,
    check_split,
    points_toward,
    split_episodes,
)
from attack.render import render_adversarial_batch
from sim.configs import object_local_centers, object_poses_world
from sim.geometry import invert_T, make_T, so3_exp, transform_points
from sim.recording import RecordingCamera
from sim.render import GRIPPER_ID
from sim.spec import default_scene
from sim.world import SimWorld
from tests.attack.recordings_helpers import sim_configs, sim_recording

S = 64  # the policy's (and the recorded wrist camera's) image size
TINY = {
    "iterations": 2,
    "num_envs": 2,
    "rollout_steps": 2,
    "texture_size": 8,
    "checkpoint_every": 1,
    "validation_every": 1,
    "validation_episodes": 3,
}


@pytest.fixture(scope="module")
def spec():
    return default_scene()


@pytest.fixture(scope="module")
def rec(spec, tmp_path_factory):
    """Three episodes of three steps of the built-in scene, wrist camera at 64 px, object hidden."""
    return sim_recording(tmp_path_factory.mktemp("rec") / "rec", spec, size=S, episodes=3, steps=3)


@pytest.fixture(scope="module")
def source(rec, spec):
    src = _source(rec, spec)
    yield src
    src.close()


def _source(rec, spec, size=S, **cfg) -> RecordedFrames:
    """The recording's frame source for a policy reading the wrist camera at ``size`` px."""
    views = {"wrist": ((size, size), "center_crop")}
    return RecordedFrames(rec, spec, resolve_config("quick", {**TINY, **cfg}), views, "wrist", "cpu")


def _texture(seed=0, size=64) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.kron((rng.random((8, 8, 3)) * 255).astype(np.uint8), np.ones((size // 8, size // 8, 1), np.uint8))


def _composite(capture, tex_u8: np.ndarray) -> np.ndarray:
    tex = torch.from_numpy(tex_u8).permute(2, 0, 1).float() / 255.0
    return render_adversarial_batch([capture], tex)[0].permute(1, 2, 0).numpy() * 255.0


# ------------------------------------------------------------------------------- the composite
def test_the_composited_object_matches_the_simulators_render_of_it_at_the_same_pose(rec, spec, source):
    # Each episode's first frame with the object where its configuration stood it, textured alike:
    # the composite against the simulator's own render of the full scene with the object in it.
    # Measured at 64 px: masks IoU 1.0 and mean colour error 0.8-1.1 / 255 on the three frames.
    adv = spec.object_index("adversarial")
    tex = _texture()
    world = SimWorld(spec, image_size=S)
    try:
        for e, config in enumerate(sim_configs(spec, 3)):
            T_obj = object_poses_world(config.object_xy_yaw)[adv]
            cap = source.capture(f"ep{e}", 0, T_obj)
            img = _composite(cap, tex)
            world.reset(config=config)
            world.renderer.set_object_texture(adv, tex)
            ref = world.render(with_ids=True)
            m_sim, m_ours = ref.object_mask(adv), cap.adv_mask
            assert m_sim.sum() > 20
            assert (m_sim & m_ours).sum() / (m_sim | m_ours).sum() >= 0.9
            both = m_sim & m_ours
            assert np.abs(img[both] - ref.rgb[both]).mean() <= 3.0
            frame = source.view(f"ep{e}", 0, "wrist")
            outside = ~cap.fragments.mask()
            assert np.array_equal(img[outside], frame[outside].astype(np.float64))  # the frame, untouched
    finally:
        world.close()


def test_the_object_is_lit_as_brightly_as_the_frame(spec, tmp_path):
    # A cell at half the scene's light: the gain estimated from the table halves the object's light.
    adv = spec.object_index("adversarial")
    config = sim_configs(spec, 1)[0]
    T_obj = object_poses_world(config.object_xy_yaw)[adv]
    caps = {}
    for gain in (1.0, 0.5):
        r = sim_recording(tmp_path / f"g{gain}", spec, size=S, episodes=1, steps=1, light_gain=gain)
        src = _source(r, spec, validation_every=0)
        caps[gain] = src.capture("ep0", 0, T_obj)
        src.close()
    ratio = caps[0.5].fragments.diffuse / caps[1.0].fragments.diffuse
    assert np.allclose(ratio, 0.5, atol=0.03), (ratio.min(), ratio.max())


def test_the_gripper_keeps_its_pixels_in_front_of_the_object(spec, source):
    # The object stood on the table right behind the wrist camera's left finger (the ray through
    # the finger's pixels meets the table there): without the gripper model it would cover the
    # finger's pixels; with it, every gripper pixel keeps the recorded frame's value exactly.
    config = sim_configs(spec, 1)[0]
    world = SimWorld(spec, image_size=S)
    try:
        world.reset(config=config)
        grip = world.render(with_ids=True).ids == GRIPPER_ID
        K, T_world_cam = world.K, world.camera_pose()
    finally:
        world.close()
    v, u = np.nonzero(grip)
    left = u < S / 2
    ray = T_world_cam[:3, :3] @ np.linalg.solve(K, [u[left].mean(), v[left].mean(), 1.0])
    h = object_local_centers(spec)[spec.object_index("adversarial")][2]
    p = T_world_cam[:3, 3] + (h - T_world_cam[2, 3]) / ray[2] * ray
    T_obj = object_poses_world([[p[0], p[1], 0.3]])[0]
    bare = source.capture("ep0", 0, T_obj, gripper=False)
    assert (bare.fragments.mask() & grip).sum() > 20  # the gripper does stand in front of the object
    cap = source.capture("ep0", 0, T_obj)
    assert not (cap.fragments.mask() & grip).any()
    img = _composite(cap, _texture(1))
    frame = source.view("ep0", 0, "wrist").astype(np.float64)
    assert np.array_equal(img[grip], frame[grip])


# ------------------------------------------------------------------------------- the lens
def _distorted_camera(width=48, height=32, mount="tcp"):
    K = np.array([[40.0, 0.0, 23.5], [0.0, 41.0, 15.2], [0.0, 0.0, 1.0]])
    dist = np.array([-0.3, 0.12, 0.002, -0.001, -0.02])
    T = np.eye(4)
    return RecordingCamera("wrist", K, dist, width, height, mount, T if mount == "tcp" else None)


@pytest.mark.parametrize("preprocess", ["center_crop", "letterbox", "resize"])
def test_a_known_point_maps_through_the_lens_and_the_crop_to_the_pixel_opencv_projects_it_to(preprocess):
    cam = _distorted_camera()
    rays = ViewRays(cam, (32, 32), preprocess)
    X = np.array([[0.05, -0.03, 0.4], [-0.1, 0.08, 0.9], [0.0, 0.0, 1.0], [0.2, 0.1, 0.8]])
    px, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    want = (rays.A @ np.c_[px.reshape(-1, 2), np.ones(len(X))].T).T[:, :2]  # OpenCV, then the card's crop
    uv, ok = rays.project(X)
    assert ok.all() and np.abs(uv - want).max() < 1e-9
    xy, ok = rays.normalised(uv[:, 0], uv[:, 1])  # and back: the point's own ray
    assert ok.all() and np.abs(xy - X[:, :2] / X[:, 2:]).max() < 1e-9


@settings(max_examples=60, deadline=None)
@given(
    k1=st.floats(-0.4, 0.4),
    k2=st.floats(-0.2, 0.2),
    p1=st.floats(-0.01, 0.01),
    p2=st.floats(-0.01, 0.01),
    x=st.floats(-0.35, 0.35),
    y=st.floats(-0.25, 0.25),
)
def test_every_ray_of_the_view_inverts_the_lens_to_a_thousandth_of_a_pixel(k1, k2, p1, p2, x, y):
    K = np.array([[40.0, 0.0, 23.5], [0.0, 40.0, 15.5], [0.0, 0.0, 1.0]])
    cam = RecordingCamera("wrist", K, (k1, k2, p1, p2, 0.0), 48, 32, "tcp", np.eye(4))
    rays = ViewRays(cam, (32, 32), "center_crop")
    uv, ok = rays.project(np.array([[x, y, 1.0]]))
    if ok[0]:
        xy, back = rays.normalised(uv[:, 0], uv[:, 1])
        assert back[0] and np.abs(xy[0] - (x, y)).max() < 1e-6
    good = rays.sub_xy[rays.sub_ok]
    assert np.isfinite(good).all()
    f = cv2.projectPoints(np.c_[good, np.ones(len(good))], np.zeros(3), np.zeros(3), K, cam.dist)[0].reshape(-1, 2)
    assert np.isfinite(f).all()


def test_a_distorted_recording_puts_each_object_fragment_on_its_own_pixels_ray(spec, tmp_path):
    # Every composited pixel shows the surface point its ray through the lens meets: that point,
    # projected by OpenCV with the recording's K and distortion, lands on the pixel's centre. The
    # cube's faces span pixels of the render (a sliver thinner than them is never drawn; a pixel
    # whose ray meets only such a sliver shows the nearest face drawn, within a pixel).
    spec = spec.with_updates(
        objects=[o.with_mesh("cube") if o.role == "adversarial" else o.model_dump() for o in spec.objects]
    )
    dist = (-0.25, 0.08, 0.001, -0.002, 0.0)
    r = sim_recording(tmp_path / "rec", spec, size=S, episodes=2, steps=1, dist=dist)
    src = _source(r, spec, validation_every=0)
    try:
        adv = spec.object_index("adversarial")
        T_obj = object_poses_world(sim_configs(spec, 2)[1].object_xy_yaw)[adv]  # episode 1: the object near
        cap = src.capture("ep1", 0, T_obj)
        f = cap.fragments
        full = np.zeros(S * S, bool)
        full[f.pix[f.alpha == 1.0]] = True
        full = full.reshape(S, S)
        core = full.copy()  # whole pixels whose eight neighbours are whole too: away from the silhouette
        for dv in (-1, 0, 1):
            for du in (-1, 0, 1):
                core &= np.roll(np.roll(full, dv, 0), du, 1)
        inner = core.reshape(-1)[f.pix]
        assert inner.sum() > 20
        hr = src.rigs["wrist"].hybrid
        T_cam_obj = src._poses["ep1"][1]["wrist"][0] @ T_obj
        tri = transform_points(T_cam_obj, hr.vertices)[hr.faces[f.face]]
        X = np.einsum("pk,pkc->pc", f.bary, tri)[inner]
        px, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), r.cameras["wrist"].K, np.asarray(dist))
        v, u = np.divmod(f.pix[inner], S)
        assert np.abs(px.reshape(-1, 2) - np.c_[u, v]).max() < 1e-6
        pinhole = sim_recording(tmp_path / "pinhole", spec, size=S, episodes=2, steps=1)
        undistorted = _source(pinhole, spec, validation_every=0)
        assert not np.array_equal(undistorted.capture("ep1", 0, T_obj).adv_mask, cap.adv_mask)
        undistorted.close()
    finally:
        src.close()


# ------------------------------------------------------------------------------- frames, poses, split
def test_the_source_is_open_loop_and_follows_the_recorded_episodes(source):
    src = source
    src.start(0, np.random.default_rng(5))
    slots = list(src._slots)
    seen = []
    while (frames := src.next()) is not None:
        seen.append(frames.T_world_tcp.numpy())
        src.advance(np.full((len(frames), 6), 1.0))  # whatever the policy does
    assert 1 <= len(seen) <= src.cfg.rollout_steps
    for k, T in enumerate(seen):
        active = [s for s in slots if s.step + k < 3]
        want = np.stack([src._poses[s.episode][0][s.step + k] for s in active])
        assert np.allclose(T, want, atol=1e-6)
    assert {s.episode for s in slots} <= set(src.train)


@settings(max_examples=200, deadline=None)
@given(angle=st.floats(0.0, 180.0), scale=st.floats(1e-6, 1.0), dist_m=st.floats(1e-3, 10.0))
def test_an_action_points_toward_the_object_exactly_within_the_stated_angle(angle, scale, dist_m):
    # TCP at the origin with the identity rotation: a delta_tcp action's translation is its motion.
    a = math.radians(angle)
    if abs(angle - TOWARD_DEG) < 1e-6:
        return  # the boundary itself is a float coin toss
    action = torch.tensor([[scale * math.cos(a), scale * math.sin(a), 0.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    p_adv = torch.tensor([[dist_m, 0.0, 0.0]], dtype=torch.float64)
    got = points_toward(torch.eye(4, dtype=torch.float64)[None], action, p_adv, 0.02)
    assert bool(got[0]) == (angle < TOWARD_DEG)


def test_an_action_that_does_not_move_does_not_point_toward_anything():
    got = points_toward(torch.eye(4)[None], torch.zeros(1, 6), torch.tensor([[0.3, 0.0, 0.0]]), 0.02)
    assert not bool(got[0])


def test_the_episode_split_is_disjoint_and_its_check_can_fail():
    assert split_episodes(["a", "b", "c", "d", "e"], True) == (("a", "b", "c", "d"), ("e",))
    assert split_episodes([f"e{i}" for i in range(10)], True)[1] == ("e8", "e9")
    assert split_episodes(["a"], False) == (("a",), ())
    with pytest.raises(RecordedAttackError, match="1 episode; validation holds whole episodes out"):
        split_episodes(["a"], True)
    with pytest.raises(RecordedAttackError, match="episode 'b' is both a training and a held-out episode"):
        check_split(["a", "b"], ["b"], True)
    with pytest.raises(RecordedAttackError, match="no held-out episode"):
        check_split(["a"], [], True)


def test_a_recording_whose_cameras_look_away_from_the_table_is_refused_before_any_renderer(spec, tmp_path):
    upside_down = make_T(so3_exp(np.array([math.pi, 0.0, 0.0])), np.array([0.0, 0.0, 1.0]))
    r = sim_recording(tmp_path / "rec", spec, size=32, episodes=2, steps=1, T_table_base=upside_down)
    with pytest.raises(RecordedAttackError, match="frames with no table visible") as err:
        _source(r, spec, size=32)
    assert "\n" not in str(err.value) and str(r.path) in str(err.value)


def test_the_recorded_camera_poses_are_the_tables_frame_ones(source, rec):
    # T_world_tcp handed to the losses is the table-frame TCP pose; each camera's pose follows it.
    src = source
    T_table_tcp, T_cams = src._poses["ep0"]
    assert np.allclose(T_table_tcp, rec.T_table_base @ rec.poses("ep0").T_base_tcp)
    assert np.allclose(invert_T(T_cams["wrist"]), rec.T_table_cam("wrist", rec.poses("ep0").T_base_tcp))
