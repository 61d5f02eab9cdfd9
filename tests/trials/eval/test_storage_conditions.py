"""Episode store (append, truncated-line recovery, config guard) and condition building."""

import numpy as np
import pytest

from tests.trials.conftest import make_attack_dir
from trials.eval.conditions import (
    CONDITIONS,
    ConditionError,
    Sources,
    build_conditions,
    condition_spec,
    load_attack_source,
)
from trials.eval.episodes import EpisodeStore, StorageError, read_rows


def _row(cond, seed):
    return {
        "condition": cond,
        "seed": seed,
        "r_m": 0.5,
        "theta_rad": 0.1,
        "phi_rad": 0.2,
        "outcome": "goal",
        "reached": 0,
        "success": True,
        "targeted": False,
        "steps": 7,
        "e_trans": 0.25,
        "e_rot": float("nan"),
        "min_dist_a": 0.05,
        "min_dist_b": 0.3,
    }


def test_store_round_trips_rows_and_knows_what_is_done(tmp_path):
    store = EpisodeStore(tmp_path, {"x": 1}, ["a", "b"])
    store.append([_row("clean", 3), _row("attack", 3)])
    again = EpisodeStore(tmp_path, {"x": 1}, ["a", "b"], resume=True)
    assert again.is_done("clean", 3) and again.is_done("attack", 3) and not again.is_done("clean", 4)
    r = again.rows[0]
    assert (
        r["success"] is True
        and r["targeted"] is False
        and r["steps"] == 7
        and r["e_trans"] == 0.25
        and np.isnan(r["e_rot"])
    )


def test_store_drops_a_truncated_last_line_left_by_a_crash(tmp_path):
    store = EpisodeStore(tmp_path, {"x": 1}, ["a", "b"])
    store.append([_row("clean", 1), _row("clean", 2)])
    with open(tmp_path / "episodes.csv", "a") as f:
        f.write("clean,3,0.5,0.1")  # crash mid-row
    again = EpisodeStore(tmp_path, {"x": 1}, ["a", "b"], resume=True)
    assert [r["seed"] for r in again.rows] == [1, 2]
    again.append([_row("clean", 3)])
    assert [r["seed"] for r in read_rows(tmp_path / "episodes.csv")] == [1, 2, 3]


def test_store_refuses_a_different_config_and_an_unrequested_resume(tmp_path):
    EpisodeStore(tmp_path, {"episodes": 10, "policy": "p"}, ["a", "b"]).append([_row("clean", 1)])
    with pytest.raises(StorageError, match="different config.*episodes"):
        EpisodeStore(tmp_path, {"episodes": 20, "policy": "p"}, ["a", "b"], resume=True)
    with pytest.raises(StorageError, match="--resume"):
        EpisodeStore(tmp_path, {"episodes": 10, "policy": "p"}, ["a", "b"], resume=False)


def test_every_condition_name_builds_with_its_sources(tmp_path):
    src = Sources(
        attack=str(make_attack_dir(tmp_path / "a")),
        patch=str(make_attack_dir(tmp_path / "p", mesh="patch")),
        shapes={s: str(make_attack_dir(tmp_path / s, mesh=s)) for s in ("dog", "duck", "cube", "cylinder")},
    )
    conds = build_conditions(list(CONDITIONS), src)
    assert [c.name for c in conds] == list(CONDITIONS)
    by = {c.name: c for c in conds}
    assert by["clean"].texture is None
    assert by["light_dim"].randomization.light == "dim" and by["bkg_varied"].randomization.background == "varied"
    assert by["noise"].randomization.noise_std > 0 and by["stereo"].stereo
    assert by["patch"].mesh == "patch" and by["shape_duck"].mesh == "duck"
    assert by["attack"].texture.dtype == np.uint8 and by["attack"].texture.shape == (16, 16, 3)


def test_condition_errors_name_the_missing_option_or_file(tmp_path, short_spec):
    with pytest.raises(ConditionError, match="unknown condition 'sunny'"):
        build_conditions(["sunny"], Sources())
    with pytest.raises(ConditionError, match="--attack DIR"):
        build_conditions(["light_bright"], Sources())
    with pytest.raises(ConditionError, match="--shape dog=DIR"):
        build_conditions(["shape_dog"], Sources())
    with pytest.raises(ConditionError, match="adversarial_mesh 'patch'"):
        build_conditions(["patch"], Sources(patch=str(make_attack_dir(tmp_path / "notpatch"))))
    with pytest.raises(ConditionError, match="texture.npy: missing"):
        load_attack_source(tmp_path)
    bad = make_attack_dir(tmp_path / "bad")
    np.save(bad / "texture.npy", np.full((4, 4, 3), 2.0, np.float32))
    with pytest.raises(ConditionError, match=r"\[0, 1\]"):
        load_attack_source(bad)


def test_condition_spec_swaps_the_adversarial_mesh_and_adds_a_stereo_baseline(tmp_path, short_spec):
    src = Sources(
        attack=str(make_attack_dir(tmp_path / "a")), shapes={"dog": str(make_attack_dir(tmp_path / "d", mesh="dog"))}
    )
    dog, stereo = build_conditions(["shape_dog", "stereo"], src)[1:]
    s = condition_spec(short_spec, dog)
    assert s.adversarial.mesh == "dog" and s.goal.mesh == short_spec.goal.mesh
    assert condition_spec(short_spec, stereo).camera.stereo_baseline_m > 0
