"""The held-out split of configuration seeds into attack, validation and evaluation parts."""

from collections import Counter

import pytest
from hypothesis import given
from hypothesis import strategies as st

from sim.configs import PARTS, config_id, config_part, in_part, part_seeds, pose_id, sample_config, sample_pool
from sim.spec import default_scene


@given(st.integers(min_value=0, max_value=2**62))
def test_every_seed_belongs_to_exactly_one_part_and_always_the_same(seed):
    part = config_part(seed)
    assert part in PARTS and config_part(seed) == part


def test_shares_are_40_10_50_percent():
    counts = Counter(config_part(s) for s in range(20_000))
    assert abs(counts["attack"] / 20_000 - 0.4) < 0.02
    assert abs(counts["validation"] / 20_000 - 0.1) < 0.01
    assert abs(counts["evaluation"] / 20_000 - 0.5) < 0.02


def test_part_seeds_and_sampled_pools_stay_inside_their_part():
    for part in PARTS:
        gen = part_seeds(part, 1000)
        seeds = [next(gen) for _ in range(50)]
        assert seeds == sorted(seeds) and seeds[0] >= 1000 and {config_part(s) for s in seeds} == {part}
    spec = default_scene()
    pools = {p: sample_pool(spec, 6, seed=0, part=p) for p in PARTS}
    seen = [c.seed for cs in pools.values() for c in cs]
    assert len(seen) == len(set(seen))  # disjoint by construction
    mixed = sample_pool(spec, 30, seed=0)
    assert sorted(c.seed for p in PARTS for c in in_part(mixed, p)) == [c.seed for c in mixed]
    with pytest.raises(ValueError, match="unknown part"):
        in_part(mixed, "test")


def test_config_id_is_a_content_hash():
    spec = default_scene()
    a, b = sample_config(spec, 3), sample_config(spec, 4)
    assert config_id(a) == config_id(sample_config(spec, 3)) != config_id(b)
    moved = spec.with_updates(init={**spec.init.model_dump(), "r_range_m": (0.3, 0.5)})
    assert config_id(sample_config(moved, 3)) != config_id(a)  # same seed, other scene: another configuration


def test_pose_id_ignores_the_seed_and_sees_every_pose():
    import dataclasses

    spec = default_scene()
    a = sample_config(spec, 3)
    assert pose_id(dataclasses.replace(a, seed=99)) == pose_id(a) != pose_id(sample_config(spec, 4))
    assert pose_id(dataclasses.replace(a, phi_rad=a.phi_rad + 1e-6)) != pose_id(a)
    # -0.0 and 0.0 are the same pose
    assert pose_id(dataclasses.replace(a, theta_rad=-0.0)) == pose_id(dataclasses.replace(a, theta_rad=0.0))
