"""Episode store (append, truncated-line recovery, config guard) and condition building."""

import json

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
from trials.eval.episodes import (
    EpisodeStore,
    StorageError,
    collect_evals,
    has_manifest,
    has_rows,
    read_manifest,
    read_rows,
    write_summary,
)


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


def test_rows_read_from_the_eval_folder_or_its_csv_alike_and_its_manifest_through_the_store(tmp_path):
    assert read_rows(tmp_path) == [] and not has_rows(tmp_path) and not has_manifest(tmp_path)
    with pytest.raises(StorageError, match="manifest.json: missing"):
        read_manifest(tmp_path)
    EpisodeStore(tmp_path, {"x": 1}, ["a", "b"]).append([_row("clean", 1)])
    assert has_rows(tmp_path) and has_manifest(tmp_path) and read_manifest(tmp_path)["config"] == {"x": 1}
    assert read_rows(tmp_path)[0]["seed"] == 1 and str(read_rows(tmp_path)) == str(read_rows(tmp_path / "episodes.csv"))
    (tmp_path / "manifest.json").write_text("[1]")
    with pytest.raises(StorageError, match="manifest.json: not an eval manifest"):
        read_manifest(tmp_path)


def test_collected_evals_keep_each_rows_bytes_with_the_evals_name_first(tmp_path):
    dirs = []
    for name, seeds in (("b-eval", (1, 2)), ("a-eval", (3,)), ("not-run", ())):
        d = tmp_path / "evals" / name
        dirs.append(d)
        if not seeds:
            d.mkdir(parents=True)
            continue
        EpisodeStore(d, {"overlap": {"attack": 0}, "name": name}, ["a", "b"]).append([_row("clean", s) for s in seeds])
        write_summary(d, {"conditions": {"clean": {"n": len(seeds)}}})
    assert collect_evals(tmp_path / "out", dirs) == 3
    stored = {d.name: (d / "episodes.csv").read_text().splitlines() for d in dirs[:2]}
    lines = (tmp_path / "out" / "episodes.csv").read_text().splitlines()
    assert lines[0] == "eval," + stored["b-eval"][0]
    assert lines[1:] == [f"{n},{line}" for n in ("b-eval", "a-eval") for line in stored[n][1:]]
    rows = read_rows(tmp_path / "out")
    assert [(r["eval"], r["seed"]) for r in rows] == [("b-eval", 1), ("b-eval", 2), ("a-eval", 3)]
    summaries = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summaries == {
        n: {"conditions": {"clean": {"n": k}}, "overlap": {"attack": 0}} for n, k in (("b-eval", 2), ("a-eval", 1))
    }


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


def test_collected_summaries_name_paths_relative_to_the_checkout(tmp_path):
    d = tmp_path / "evals" / "e"
    EpisodeStore(d, {"overlap": {"attack": 0}, "name": "e"}, ["a", "b"]).append([_row("clean", 1)])
    inside = str(tmp_path.resolve() / "runs" / "policy")
    write_summary(d, {"conditions": {"clean": {"n": 1}}, "policy": inside, "other": "/elsewhere/policy"})
    collect_evals(tmp_path / "out", [d], relative_to=tmp_path)
    s = json.loads((tmp_path / "out" / "summary.json").read_text())["e"]
    assert s["policy"] == "runs/policy" and s["other"] == "/elsewhere/policy"
