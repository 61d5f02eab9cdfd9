"""Rendering shortcuts are exact: frustum culling and isolated renders change no pixel that is used."""

import numpy as np
import pytest

from sim.configs import sample_config
from sim.geometry import look_at
from sim.render import SceneRenderer, spheres_outside_frustum
from sim.spec import default_scene


@pytest.fixture(scope="module")
def scene():
    spec = default_scene()
    r = SceneRenderer(spec, 48, 48)
    r.add_variant(spec.object_index("adversarial"), "white", None, (1.0, 1.0, 1.0))
    yield spec, r
    r.close()


def _poses(spec, n: int, seed: int):
    """Object layouts from the scene's configs and cameras aimed near (and past) the objects, so
    objects are fully in view, cut by the image border, or out of view."""
    from sim.configs import object_poses_world

    rng = np.random.default_rng(seed)
    for i in range(n):
        cfg = sample_config(spec, 100 + i)
        T_objs = object_poses_world(cfg.object_xy_yaw)
        anchor = T_objs[rng.integers(len(T_objs)), :3, 3] + np.array([0.0, 0.0, 0.05])
        eye = anchor + rng.normal(0.0, 1.0, 3) * np.array([0.4, 0.4, 0.2]) + np.array([0.0, 0.0, 0.35])
        target = anchor + rng.normal(0.0, 0.25, 3)  # aim off the object: many partial views
        yield T_objs, cfg.T_world_tcp_array, look_at(eye, target)


def _occluded_views(spec, n: int):
    """Cameras looking at the adversarial object past the goal object (which hides part of it),
    with the gripper on the wrist as in an episode."""
    from sim.configs import object_local_centers, object_poses_world

    adv, goal = spec.object_index("adversarial"), spec.object_index("goal")
    local = object_local_centers(spec)
    T_cam_tcp = np.linalg.inv(spec.camera.T_tcp_cam)
    for i in range(n):
        cfg = sample_config(spec, 300 + i)
        T_objs = object_poses_world(cfg.object_xy_yaw)
        c = np.einsum("kij,kj->ki", T_objs[:, :3, :3], local) + T_objs[:, :3, 3]
        away = (c[goal] - c[adv]) / np.linalg.norm(c[goal] - c[adv])
        eye = c[goal] + away * (0.15 + 0.05 * i) + np.array([0.0, 0.0, 0.03 * (i % 3)])
        T_cam = look_at(eye, c[adv] + np.array([0.0, 0.0, 0.02 * (i % 2)]))
        yield T_objs, T_cam @ T_cam_tcp, T_cam


def test_sphere_frustum_test_matches_projection():
    K = np.array([[50.0, 0, 31.5], [0, 50.0, 31.5], [0, 0, 1]])
    c = np.array(
        [[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [2.0, 0.0, 1.0], [0.0, 0.0, 20.0], [0.66, 0.0, 1.0], [0.0, 0.0, 0.001]]
    )
    r = np.array([0.1, 0.1, 0.1, 0.1, 0.05, 0.001])
    out = spheres_outside_frustum(c, r, K, 64, 64, znear=0.01, zfar=10.0)
    # in view, behind, far right, beyond zfar, touching the right edge (u = 64.5 +- 2.5 px), before znear
    assert out.tolist() == [False, True, True, True, False, True]


def test_frustum_culling_is_pixel_exact_over_random_views(scene):
    spec, r = scene
    culled = partial = 0
    for T_objs, T_tcp, T_cam in _poses(spec, 60, seed=0):
        r.set_state(T_objs, T_tcp)
        r.frustum_cull = False
        full = r.render(T_cam)
        r.frustum_cull = True
        fast = r.render(T_cam)
        assert np.array_equal(full.rgb, fast.rgb) and np.array_equal(full.ids, fast.ids)
        assert np.array_equal(full.depth, fast.depth)
        culled += len(r.culled)
        for k in range(len(spec.objects)):
            m = full.object_mask(k)
            partial += bool(m.any() and (m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any()))
        # A culled object is never visible without culling.
        for k in r.culled:
            assert not full.object_mask(k).any()
    assert culled >= 10 and partial >= 10, (culled, partial)


def test_isolated_render_equals_the_full_one_under_the_objects_mask(scene):
    spec, r = scene
    adv = spec.object_index("adversarial")
    compared = occluded = 0
    import itertools

    for T_objs, T_tcp, T_cam in itertools.chain(_poses(spec, 30, seed=1), _occluded_views(spec, 8)):
        r.set_state(T_objs, T_tcp)
        full = r.render(T_cam, with_ids=True)
        mask = full.object_mask(adv)
        if not mask.any():
            continue
        for variants in ({}, {adv: "white"}):
            a = r.render(T_cam, with_ids=False, variants=variants).rgb
            b = r.render(T_cam, with_ids=False, variants=variants, isolate=adv).rgb
            assert np.abs(a[mask].astype(int) - b[mask].astype(int)).max() == 0
        iso = r.render(T_cam, with_ids=True, isolate=adv)
        occluded += int((iso.object_mask(adv) & ~mask).any())  # something hid part of it
        compared += 1
    assert compared >= 10 and occluded >= 1, (compared, occluded)
