"""Renderer and env: masks agree with projections, ids are exact, determinism, expert success."""

import numpy as np
import pytest

from sim.action import ActionError
from sim.configs import PoolError, load_pool, sample_pool, save_pool
from sim.env import ReachEnv
from sim.render import FACE_BASE, SceneRenderer
from sim.spec import default_scene
from sim.world import SimWorld


@pytest.fixture(scope="module")
def spec():
    return default_scene()


@pytest.fixture(scope="module")
def world(spec):
    w = SimWorld(spec, image_size=96, seed=3)
    yield w
    w.close()


def _project(K, T_world_cam, p_world):
    T_cam_world = np.linalg.inv(T_world_cam)
    p = T_cam_world[:3, :3] @ p_world + T_cam_world[:3, 3]
    uv = K @ (p / p[2])
    return p[2], uv[:2]


def test_each_visible_mask_contains_the_projection_of_its_object_centre(spec, world):
    checked = 0
    for seed in range(12):
        world.reset(seed)
        out = world.render()
        T_cam = world.camera_pose()
        for k, c in enumerate(world.object_center_array):
            z, (u, v) = _project(world.K, T_cam, c)
            mask = out.object_mask(k)
            iu, iv = int(round(u)), int(round(v))
            inside = z > 0 and 2 <= iu < world.width - 2 and 2 <= iv < world.height - 2
            if not inside or not mask.any():
                continue
            # The centre's pixel shows the object unless something stands in front of it.
            if out.depth[iv, iu] >= z - 0.1:
                assert mask[iv - 1 : iv + 2, iu - 1 : iu + 2].any(), (seed, k)
                checked += 1
    assert checked >= 10


def test_id_pass_codes_are_exact_and_faces_are_in_range(spec, world):
    world.reset(5)
    out = world.render()
    ids = np.unique(out.ids)
    n_faces = len(world.renderer.object_mesh(spec.object_index("adversarial")).faces)
    faces = ids[ids >= FACE_BASE] - FACE_BASE
    assert faces.size > 0 and faces.max() < n_faces
    allowed = {0, 1, 2} | {16 + k for k in range(len(spec.objects))}
    assert set(ids[ids < FACE_BASE].tolist()) <= allowed


def test_color_and_id_passes_cover_the_same_pixels(world):
    world.reset(7)
    out = world.render()
    background = out.ids == 0
    # Where nothing is hit, the color pass shows the backdrop.
    if background.any():
        assert np.abs(out.rgb[background].astype(int) - out.rgb[background][0]).max() <= 1
    assert out.depth[~background].min() > 0


def test_same_seed_gives_identical_frames(spec):
    a = ReachEnv(spec, num_envs=2, image_size=64, seed=11)
    oa, _ = a.reset(seed=11)
    for _ in range(3):
        oa, *_ = a.step(a.expert_actions())
    a.close()
    b = ReachEnv(spec, num_envs=2, image_size=64, seed=11)
    ob, _ = b.reset(seed=11)
    for _ in range(3):
        ob, *_ = b.step(b.expert_actions())
    b.close()
    assert np.array_equal(oa, ob)


def test_expert_reaches_goal_on_ci_pool(spec):
    """Target >= 98% (the issue); 50 episodes keep CI fast, the benchmark runs more."""
    env = ReachEnv(spec, num_envs=10, image_size=32, seed=0)
    succ = total = 0
    for batch in range(5):
        env.reset(seed=1000 + 10 * batch)
        while not env.done.all():
            _, _, _, _, info = env.step(env.expert_actions())
        succ += int(info["success"].sum())
        total += env.num_envs
        assert (info["step"] <= spec.episode.max_steps).all()
    env.close()
    assert succ / total >= 0.98, f"expert success {succ}/{total}"


def test_nan_action_is_an_error_and_finished_envs_freeze(spec):
    env = ReachEnv(spec, num_envs=2, image_size=32, seed=0)
    env.reset(seed=0)
    bad = np.zeros((2, 6))
    bad[1, 3] = np.nan
    with pytest.raises(ActionError, match="env"):
        env.step(bad)
    with pytest.raises(ActionError, match="shape"):
        env.step(np.zeros((3, 6)))
    while not env.done.all():
        env.step(env.expert_actions())
    T = env.T_world_tcp
    obs, r, te, tr, info = env.step(np.ones((2, 6)))
    assert np.array_equal(env.T_world_tcp, T) and not te.any() and not tr.any() and (r == 0).all()
    env.close()


def test_config_pool_round_trip_and_mismatch(spec, tmp_path):
    pool = sample_pool(spec, 5, seed=42)
    p = save_pool(tmp_path / "pool.json", spec, pool)
    assert load_pool(p, spec) == pool
    other = spec.with_updates(init={**spec.init.model_dump(), "min_separation_m": 0.3})
    with pytest.raises(PoolError, match="different scene"):
        load_pool(p, other)
    (tmp_path / "junk.json").write_text("{]")
    with pytest.raises(PoolError, match="junk.json"):
        load_pool(tmp_path / "junk.json")


def test_initial_configs_respect_the_paper_ranges(spec):
    for c in sample_pool(spec, 50, seed=0):
        assert 0.25 <= c.r_m <= 0.80
        assert 0.0 <= np.degrees(c.phi_rad) <= 90.0


def _current_rss_bytes() -> int:
    # Resident pages now (not the peak ru_maxrss, which never shrinks and hides a slow leak).
    import os

    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def test_renderer_memory_does_not_grow_over_many_frames(spec):
    n = 1500
    r = SceneRenderer(spec, 64, 64)
    w = SimWorld(spec, image_size=64, seed=0, renderer=r)
    try:
        frame_bytes = w.render().rgb.nbytes  # 12 kB
        for _ in range(200):  # warm-up: GL buffers, allocator arenas, caches
            w.render()
        before = _current_rss_bytes()
        for _ in range(n):
            w.render()
        grown = _current_rss_bytes() - before
    finally:
        r.close()
    # Keeping one RGB frame per render would grow by n * frame_bytes (~18 MB); allocator noise
    # after warm-up measured ~2 MB, so a quarter of that leak is the bound.
    allowance = n * frame_bytes // 4
    assert grown < allowance, f"RSS grew {grown / 1e6:.1f} MB over {n} frames (allowance {allowance / 1e6:.1f} MB)"


def test_mixed_background_keeps_the_spec_table_in_a_quarter_of_episodes_and_varied_never(spec):
    """Training randomisation must also show the nominal scene: 'varied' never draws the spec's
    own table and backdrop (a policy trained on it alone failed on the clean scene), 'mixed' does
    in MIXED_SPEC_SHARE of the episodes."""
    from sim.variations import MIXED_SPEC_SHARE, Randomization, sample_appearance

    def spec_share(background):
        rng = np.random.default_rng(0)
        draws = [sample_appearance(spec, Randomization(background=background), rng) for _ in range(2000)]
        own = [a.table_variant == -1 and a.background is None for a in draws]
        assert all(a.table_variant >= 0 and a.background is not None for a, o in zip(draws, own) if not o)
        return float(np.mean(own))

    assert spec_share("fixed") == 1.0 and spec_share("varied") == 0.0
    assert abs(spec_share("mixed") - MIXED_SPEC_SHARE) < 0.03
