"""The benign arm (the attacked mesh with the attack's own unoptimised start texture), the attacked
mesh in every arm but clean, and the headline: attack vs benign, paired."""

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from attack.artifact import AttackArtifact, texture_to_uint8, write_config_record
from attack.optimize import AttackRun, resolve_config
from sim.configs import load_pool, sample_pool
from sim.policies.checkpoint import load_policy
from sim.spec import default_scene
from tests.trials.conftest import MAX_STEPS
from trials.eval.conditions import (
    CONDITIONS,
    ConditionError,
    Sources,
    build_conditions,
    load_attack_source,
    start_source,
    with_benign,
)
from trials.eval.evaluate import load_eval_config, rollout_condition, run_eval
from trials.eval.metrics import mcnemar_exact
from trials.eval.report import format_headline, paired_tests, summarize

ATTACK = {"iterations": 1, "num_envs": 1, "rollout_steps": 1, "texture_size": 16, "validation_every": 0}


def _run_dir(path, cfg, texture=None):
    """A texture folder as an attack run writes it: the run's whole config under config.attack, and the
    record of the attack-part configurations it drew from."""
    tex = np.random.default_rng(1).random((cfg.texture_size,) * 2 + (3,)) if texture is None else texture
    AttackArtifact(tex.astype(np.float32), {"job": "attack", "attack": cfg.model_dump()}, cfg.seed).save(path)
    write_config_record(path, sample_pool(default_scene(), 2, part="attack"), [])
    return path


@pytest.mark.parametrize(
    "extra",
    [
        {},  # the scene's own mustard bottle, its own texture resized
        {"adversarial_mesh": "cube"},
        {"adversarial_mesh": "cube", "init_texture": "random", "seed": 7},
        {"init_texture": "gray"},
    ],
)
def test_the_benign_texture_is_the_one_the_attack_itself_starts_from(tmp_path, tiny_policy_dir, extra):
    spec = default_scene()
    cfg = resolve_config("quick", {**ATTACK, **extra})
    run = AttackRun(load_policy(tiny_policy_dir), spec, cfg, pool=sample_pool(spec, 2, part="attack"))
    try:
        started = texture_to_uint8(run.state.texture)
    finally:
        run.close()
    src = start_source(_run_dir(tmp_path / "run", cfg), spec)
    assert np.array_equal(src.texture, started)
    assert src.mesh == extra.get("adversarial_mesh") and src.start == cfg.init_texture
    assert src.trained_on == frozenset()  # made from no configuration: its overlap with any evaluation is 0
    # and it is not the optimised texture of the folder
    assert not np.array_equal(src.texture, load_attack_source(tmp_path / "run").texture)


def test_a_run_record_without_the_start_fields_takes_the_attack_configs_defaults(tmp_path):
    AttackArtifact(np.zeros((8, 8, 3), np.float32), {"attack": {"adversarial_mesh": "cube"}}).save(tmp_path / "r")
    src = start_source(tmp_path / "r", default_scene())
    default = resolve_config("quick", {"texture_size": 256})  # the AttackConfig default size and init
    assert src.texture.shape == (default.texture_size, default.texture_size, 3) and src.start == "benign"


def test_the_benign_arm_is_refused_in_one_line_without_a_run_or_with_a_bad_record(tmp_path):
    with pytest.raises(ConditionError, match=r"^condition 'benign' needs an attack run directory: pass --attack DIR$"):
        build_conditions(["benign"], Sources())
    AttackArtifact(np.zeros((8, 8, 3), np.float32), {"attack": {"init_texture": "plaid"}}).save(tmp_path / "bad")
    with pytest.raises(ConditionError, match=r"bad/run\.json: invalid attack config: init_texture") as err:
        build_conditions(["benign"], Sources(attack=str(tmp_path / "bad")))
    assert "\n" not in str(err.value)


def test_benign_joins_attack_once_and_nothing_else():
    assert with_benign(["attack"]) == ["benign", "attack"]
    assert with_benign(["patch", "attack", "noise"]) == ["patch", "benign", "attack", "noise"]
    assert with_benign(["attack", "benign"]) == ["attack", "benign"]  # asked for: where it was asked
    assert with_benign(["light_dim", "patch"]) == ["light_dim", "patch"]
    assert "benign" in CONDITIONS  # one registry of conditions


def test_every_arm_but_clean_shows_the_attacked_cube(tmp_path, tiny_policy_dir, short_spec, pool_file):
    """An attack run on the cube in the mustard-bottle scene: benign, attack and a variation all render
    the cube (their clean views of the same state are the cube's own look, pixel for pixel); only the
    clean arm shows the mustard bottle."""
    cube = _run_dir(tmp_path / "cube", resolve_config("quick", {**ATTACK, "adversarial_mesh": "cube"}))
    conds = build_conditions(["benign", "attack", "light_dim"], Sources(attack=str(cube), scene=short_spec))
    assert [(c.name, c.mesh) for c in conds] == [
        ("clean", None),
        ("benign", "cube"),
        ("attack", "cube"),
        ("light_dim", "cube"),
    ]
    policy = load_policy(tiny_policy_dir)
    configs = load_pool(pool_file, short_spec)[:3]
    first = {}
    for cond in conds[:3]:
        views = {}

        def on_frame(j, step, adv, clean, views=views):
            if step == 0:
                views[configs[j].seed] = (adv.copy(), clean.copy())

        rollout_condition(policy, short_spec, cond, configs, 3, lambda j, r: None, on_frame)
        first[cond.name] = views
    seeds = sorted(first["clean"])
    assert seeds == sorted(c.seed for c in configs)
    for s in seeds:
        assert np.array_equal(first["benign"][s][1], first["attack"][s][1])  # the same cube, its own look
    assert any(not np.array_equal(first["benign"][s][1], first["clean"][s][1]) for s in seeds)  # not the bottle
    assert any(not np.array_equal(first["benign"][s][0], first["attack"][s][0]) for s in seeds)  # other textures


def test_the_headline_is_attack_vs_benign_and_adding_benign_changes_no_other_arm(
    tmp_path, tiny_policy_dir, short_spec, pool_file
):
    cube = _run_dir(tmp_path / "cube", resolve_config("quick", {**ATTACK, "adversarial_mesh": "cube"}))
    common = dict(
        policy=str(tiny_policy_dir),
        episodes=3,
        max_steps=MAX_STEPS,
        num_envs=3,
        pool=str(pool_file),
        attack=str(cube),
        gifs=0,
    )
    plain = run_eval(load_eval_config(conditions=("attack",), **common), tmp_path / "plain", progress=False)
    names = tuple(with_benign(["attack", "light_dim"]))
    full = run_eval(load_eval_config(conditions=names, **common), tmp_path / "full", progress=False)

    # The evaluation without benign keeps its records: no headline, the same rows and condition records.
    assert "headline" not in plain
    rows = {n: (tmp_path / n / "episodes.csv").read_text().splitlines() for n in ("plain", "full")}
    assert rows["plain"][0] == rows["full"][0]
    assert sorted(rows["plain"][1:]) == sorted(r for r in rows["full"][1:] if r.split(",")[0] in ("clean", "attack"))
    manifests = {n: json.loads((tmp_path / n / "manifest.json").read_text())["config"] for n in ("plain", "full")}
    by_name = {n: {c["name"]: c for c in m["conditions"]} for n, m in manifests.items()}
    assert (
        by_name["plain"]["attack"] == by_name["full"]["attack"]
        and by_name["plain"]["clean"] == by_name["full"]["clean"]
    )
    assert "start_texture" not in by_name["full"]["attack"]["source"]
    assert by_name["full"]["benign"]["source"]["start_texture"] == "benign"
    assert plain["conditions"]["attack"]["vs_clean"] == full["conditions"]["attack"]["vs_clean"]

    # The headline: McNemar's exact test of attack against benign on the episodes' own outcomes.
    episodes = [line.split(",") for line in rows["full"][1:]]
    col = rows["full"][0].split(",").index("targeted")
    hit = {(e[0], int(e[1])): e[col] == "True" for e in episodes}
    seeds = sorted({int(e[1]) for e in episodes})
    b = sum(hit[("attack", s)] and not hit[("benign", s)] for s in seeds)
    c = sum(hit[("benign", s)] and not hit[("attack", s)] for s in seeds)
    h = full["headline"]
    assert (h["condition"], h["control"]) == ("attack", "benign")
    assert h["tasr"] == mcnemar_exact(b, c, len(seeds)).to_dict()
    assert h["tasr"]["n_pairs"] == 3

    report = (tmp_path / "full" / "report.md").read_text()
    assert (
        "adversarial object `cube` (the attacked mesh, in place of the scene's `mustard_bottle` in every arm but "
        "`clean`)" in report
    )
    assert f"**Headline: {format_headline(full)}.**" in report
    assert report.index("**Headline:") < report.index("| condition | n |")  # above the tables
    assert "textures/benign.png" in report and (tmp_path / "full" / "textures" / "benign.png").is_file()
    plain_report = (tmp_path / "plain" / "report.md").read_text()
    assert "No `benign` arm (`cube` with the attack's unoptimised start texture)" in plain_report


def _rows(events_a, events_b, spec):
    goal, adv = spec.object_index("goal"), spec.object_index("adversarial")
    rows = []
    for cond, events in (("clean", [False] * len(events_a)), ("benign", events_b), ("attack", events_a)):
        for seed, hit in enumerate(events):
            reached = adv if hit else goal
            rows.append(
                {
                    "condition": cond,
                    "seed": seed,
                    "r_m": 0.5,
                    "phi_rad": 0.3,
                    "reached": reached,
                    "success": reached == goal,
                    "targeted": hit,
                    "steps": 5,
                    "e_trans": 0.0,
                    "e_rot": 0.0,
                }
            )
    return rows


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.booleans(), st.booleans()), min_size=0, max_size=40))
def test_the_headline_counts_the_discordant_configurations_and_is_the_pairwise_test_mirrored(pairs):
    spec = default_scene()
    a, b = [x for x, _ in pairs], [y for _, y in pairs]
    s = summarize(_rows(a, b, spec), spec, ["clean", "benign", "attack"])
    h = s["headline"]["tasr"]
    only_a = sum(x and not y for x, y in pairs)
    only_b = sum(y and not x for x, y in pairs)
    assert (h["b"], h["c"], h["n_pairs"]) == (only_a, only_b, len(pairs))
    assert 0.0 <= h["p_value"] <= 1.0 and (only_a + only_b > 0 or h["p_value"] == 1.0)
    mirrored = s["paired"]["benign vs attack"]["tasr"]  # one implementation: the same test, arms swapped
    assert (mirrored["b"], mirrored["c"], mirrored["p_value"]) == (h["c"], h["b"], h["p_value"])
    arm = {c: [r for r in _rows(a, b, spec) if r["condition"] == c] for c in ("attack", "benign")}
    assert s["headline"] == {"condition": "attack", "control": "benign", **paired_tests(arm["attack"], arm["benign"])}


def test_the_headline_pairs_only_the_configurations_both_arms_ran():
    spec = default_scene()
    rows = _rows([True, True, False], [False, True, False], spec)
    rows = [r for r in rows if not (r["condition"] == "benign" and r["seed"] == 0)]  # benign lacks seed 0
    h = summarize(rows, spec, ["clean", "benign", "attack"])["headline"]["tasr"]
    assert (h["b"], h["c"], h["n_pairs"]) == (0, 0, 2) and h["p_value"] == 1.0
