"""The real-trial plan: paper design counts, seeded order, stable ids, YAML round trip, clear errors."""

import re
from collections import Counter

import numpy as np
import pytest
import yaml

from trials.real.plan import (
    PlanError,
    TextureRef,
    load_plan,
    make_plan,
    plan_sha256,
    save_plan,
)

SHAPES = ["cube", "cylinder"]
CONDS = ["clean", "adv3d", "patch"]


def _refs(shapes=SHAPES):
    return {
        f"{s}/{c}": TextureRef(path=f"attacks/{s}_{c}", sha256=f"{i:064x}")
        for i, (s, c) in enumerate((s, c) for s in shapes for c in ("adv3d", "patch"))
    }


@pytest.fixture(scope="module")
def spec():
    from sim.spec import default_scene

    return default_scene()


@pytest.fixture(scope="module")
def plan(spec):
    return make_plan(spec, 0, ["A", "B"], SHAPES, CONDS, _refs(), tags=["dim"])


def test_paper_design_30_trials_per_env_shape_condition(plan):
    untagged = Counter((t.env, t.shape, t.condition) for t in plan.trials if not t.tags)
    assert set(untagged) == {(e, s, c) for e in "AB" for s in SHAPES for c in CONDS}
    assert set(untagged.values()) == {30}
    # every cell crosses each of the 5 TCP poses with each of the 6 layouts exactly once
    for e, s, c in untagged:
        pairs = {
            (t.tcp_pose, t.object_layout)
            for t in plan.trials
            if (t.env, t.shape, t.condition) == (e, s, c) and not t.tags
        }
        assert pairs == {(i, j) for i in range(5) for j in range(6)}
    tagged = Counter((t.env, t.shape, t.condition) for t in plan.trials if t.tags == ["dim"])
    assert set(tagged.values()) == {30} and len(tagged) == 12
    assert len(plan.trials) == 2 * 2 * 3 * 30 * 2
    assert [t.order for t in plan.trials] == list(range(len(plan.trials)))


def test_poses_follow_the_sim_sampler_and_see_both_objects(plan, spec):
    from sim.configs import object_local_centers, object_poses_world
    from trials.real.plan import _valid_start

    assert len(plan.tcp_poses) == 5 and len(plan.object_layouts) == 6
    lo_x, hi_x = spec.init.region_x_m
    for layout in plan.object_layouts:
        assert set(layout.objects) == {"goal", "adversarial"}
        for placement in layout.objects.values():
            assert lo_x <= placement.xy_m[0] <= hi_x and -np.pi <= placement.yaw_rad <= np.pi
    for tcp in plan.tcp_poses:
        T = tcp.T_table_tcp.T()
        assert T.shape == (4, 4) and np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3))
        for layout in plan.object_layouts:
            roles = ["goal", "adversarial"]
            xyy = [[*layout.objects[r].xy_m, layout.objects[r].yaw_rad] for r in roles]
            T_objs = object_poses_world(xyy)
            local = object_local_centers(spec)[[spec.object_index(r) for r in roles]]
            centres = np.einsum("kij,kj->ki", T_objs[:, :3, :3], local) + T_objs[:, :3, 3]
            assert _valid_start(spec, T, centres)


def test_same_seed_same_plan_other_seed_other_order(spec, plan):
    again = make_plan(spec, 0, ["A", "B"], SHAPES, CONDS, _refs(), tags=["dim"])
    assert again == plan
    other = make_plan(spec, 1, ["A", "B"], SHAPES, CONDS, _refs(), tags=["dim"])
    assert [t.trial_id for t in other.trials] != [t.trial_id for t in plan.trials]
    assert {t.trial_id for t in other.trials} == {t.trial_id for t in plan.trials}


def test_order_keeps_each_environment_together_randomized_within(spec, plan):
    envs_in_order = [t.env for t in plan.trials]
    first_env = envs_in_order[0]
    n_first = envs_in_order.count(first_env)
    assert set(envs_in_order[:n_first]) == {first_env} and first_env not in envs_in_order[n_first:]  # one switch only
    block = [t for t in plan.trials if t.env == first_env]
    # within the block the trials are shuffled across shapes, conditions and tags, not run cell by cell
    assert len({(t.shape, t.condition, tuple(t.tags)) for t in block[:12]}) > 3
    firsts = {
        make_plan(spec, seed, ["A", "B", "C"], ["cube"], ["clean"], {}, n_tcp_poses=1, n_object_layouts=2).trials[0].env
        for seed in range(8)
    }
    assert len(firsts) > 1  # the env order is drawn from the seed too


def test_trial_ids_unique_and_stable(plan):
    ids = [t.trial_id for t in plan.trials]
    assert len(set(ids)) == len(ids)
    t = next(
        t
        for t in plan.trials
        if t.env == "A"
        and t.shape == "cube"
        and t.condition == "adv3d"
        and t.tcp_pose == 2
        and t.object_layout == 4
        and not t.tags
    )
    assert t.trial_id == "A-cube-adv3d-t2-o4"
    assert all(re.fullmatch(r"[AB]-(cube|cylinder)-(clean|adv3d|patch)-t[0-4]-o[0-5](-dim)?", i) for i in ids)
    assert plan.trial("A-cube-adv3d-t2-o4-dim").tags == ["dim"]


def test_texture_and_mesh_per_condition(plan):
    t = plan.trial("B-cylinder-patch-t0-o0")
    assert plan.mesh_for(t) == "patch" and plan.texture_for(t).path == "attacks/cylinder_patch"
    assert plan.texture_for(plan.trial("B-cylinder-clean-t0-o0")) is None
    assert plan.mesh_for(plan.trial("A-cube-adv3d-t0-o0")) == "cube"


def test_yaml_round_trip_with_header(plan, tmp_path):
    path = save_plan(plan, tmp_path / "plan.yaml")
    text = path.read_text()
    assert text.startswith("# advobj real-robot trial plan")
    assert "# 240 trials" not in text and f"# {len(plan.trials)} trials" in text
    assert load_plan(path) == plan
    assert len(plan_sha256(path)) == 64


def _edit(plan, tmp_path, fn):
    data = plan.model_dump(mode="json")
    fn(data)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(PlanError) as err:
        load_plan(path)
    return str(err.value)


@pytest.fixture(scope="module")
def small_plan(spec):
    return make_plan(spec, 0, ["A"], SHAPES, CONDS, _refs(), n_tcp_poses=2, n_object_layouts=3)


def test_bad_yaml_errors_name_file_and_field(small_plan, tmp_path):
    plan = small_plan
    msg = _edit(plan, tmp_path, lambda d: d["trials"][3].update(condition="stereo"))
    assert "bad.yaml" in msg and "trials.3.condition" in msg
    msg = _edit(plan, tmp_path, lambda d: d["tcp_poses"][1]["T_table_tcp"].update(rotvec_rad=[0, 0]))
    assert "tcp_poses.1.T_table_tcp.rotvec_rad" in msg
    msg = _edit(plan, tmp_path, lambda d: d.update(colour="red"))
    assert "colour" in msg
    msg = _edit(plan, tmp_path, lambda d: d["trials"][5].update(trial_id=d["trials"][4]["trial_id"]))
    assert "trials.5.trial_id" in msg and "duplicated" in msg
    msg = _edit(plan, tmp_path, lambda d: d["trials"][0].update(tcp_pose=5))
    assert "trials.0.tcp_pose" in msg and "out of range" in msg
    msg = _edit(plan, tmp_path, lambda d: d["textures"].pop("cube/patch"))
    assert "cube/patch" in msg
    msg = _edit(plan, tmp_path, lambda d: d["object_layouts"][2]["objects"].pop("goal"))
    assert "object_layouts.2.objects" in msg
    (tmp_path / "broken.yaml").write_text("seed: [1,\n")
    with pytest.raises(PlanError, match="broken.yaml: not valid YAML"):
        load_plan(tmp_path / "broken.yaml")


def test_make_plan_rejects_bad_options(spec):
    with pytest.raises(PlanError, match="unknown condition 'stereo'"):
        make_plan(spec, 0, ["A"], ["cube"], ["clean", "stereo"], {})
    with pytest.raises(PlanError, match="needs --texture cube/adv3d=RUN_DIR"):
        make_plan(spec, 0, ["A"], ["cube"], ["clean", "adv3d"], {})
    with pytest.raises(PlanError, match="--shape teapot: no object 'teapot' in the built-in scene .* no built-in mesh"):
        make_plan(spec, 0, ["A"], ["teapot"], ["clean"], {})
    with pytest.raises(PlanError, match="repeated"):
        make_plan(spec, 0, ["A", "A"], ["cube"], ["clean"], {})
    with pytest.raises(PlanError, match="letters, digits"):
        make_plan(spec, 0, ["A"], ["cube"], ["clean"], {}, tags=["dynamic lighting"])
    with pytest.raises(PlanError, match="not used"):
        make_plan(spec, 0, ["A"], ["cube"], ["clean"], _refs(["cube"]))


def test_pool_restricts_poses(spec):
    from sim.configs import sample_pool

    pool = sample_pool(spec, 40, seed=100)
    plan = make_plan(spec, 3, ["A"], ["cube"], ["clean"], {}, n_tcp_poses=2, n_object_layouts=2, pool=pool)
    layouts = {tuple(np.round(c.object_xy_yaw[spec.object_index("goal")][:2], 9)) for c in pool}
    assert all(tuple(np.round(lay.objects["goal"].xy_m, 9)) in layouts for lay in plan.object_layouts)
    with pytest.raises(PlanError, match="pool's 3 configurations"):
        make_plan(spec, 3, ["A"], ["cube"], ["clean"], {}, n_tcp_poses=5, n_object_layouts=2, pool=pool[:3])


def test_placement_sheet_pages(spec, tmp_path):
    from trials.real.sheet import ROWS_PER_PAGE, placement_sheet_pdf, sheet_page_count

    small = make_plan(
        spec,
        0,
        ["A"],
        ["cube"],
        ["clean", "patch"],
        {"cube/patch": _refs(["cube"])["cube/patch"]},
        n_tcp_poses=2,
        n_object_layouts=3,
        tags=["occluded"],
    )
    assert len(small.trials) == 2 * 2 * 3 * 2 <= ROWS_PER_PAGE
    path = tmp_path / "sheet.pdf"
    n = placement_sheet_pdf(small, path, spec)
    # 3 layout pages + 1 TCP page + 1 run-order page
    assert n == sheet_page_count(small) == 5
    assert len(re.findall(rb"/Type\s*/Page\b(?!s)", path.read_bytes())) == 5


def test_cli_plan_writes_plan_sheet_and_run_info(tmp_path):
    from typer.testing import CliRunner

    from trials.cli.main import app

    out = tmp_path / "plan.yaml"
    res = CliRunner().invoke(
        app,
        [
            "trial",
            "plan",
            "--out",
            str(out),
            "--env",
            "A",
            "--env",
            "B",
            "--shape",
            "cube",
            "--condition",
            "clean",
            "--tcp-poses",
            "2",
            "--object-poses",
            "2",
            "--seed",
            "4",
            "--sheet",
            str(tmp_path / "sheet.pdf"),
        ],
    )
    assert res.exit_code == 0, res.output
    assert "8 trials" in res.output and "env B  shape cube" in res.output
    plan = load_plan(out)
    assert plan.seed == 4 and len(plan.trials) == 8
    assert (tmp_path / "plan.run.json").is_file() and (tmp_path / "sheet.pdf").stat().st_size > 0
    res = CliRunner().invoke(app, ["trial", "plan", "--out", str(tmp_path / "other.yaml"), "--condition", "adv3d"])
    assert res.exit_code != 0 and "--texture cube/adv3d=RUN_DIR" in str(res.exception)


def test_cli_plan_never_overwrites_a_plan_unless_forced(tmp_path):
    from typer.testing import CliRunner

    from trials.cli.main import app

    out = tmp_path / "plan.yaml"
    args = [
        "trial",
        "plan",
        "--out",
        str(out),
        "--shape",
        "cube",
        "--condition",
        "clean",
        "--tcp-poses",
        "1",
        "--object-poses",
        "1",
    ]
    assert CliRunner().invoke(app, args).exit_code == 0
    before = out.read_bytes()
    res = CliRunner().invoke(app, args + ["--seed", "9"])
    assert res.exit_code != 0 and "--out" in str(res.exception) and "--force" in str(res.exception)
    assert out.read_bytes() == before
    assert CliRunner().invoke(app, args + ["--seed", "9", "--force"]).exit_code == 0 and out.read_bytes() != before
    res = CliRunner().invoke(app, ["trial", "plan", "--out", str(tmp_path)])
    assert res.exit_code != 0 and "is a directory" in str(res.exception)


def test_plan_with_a_cells_hardware_draws_start_poses_inside_its_workspace_box(spec):
    from pathlib import Path

    from robot_io.config import load_hardware_config

    hw = load_hardware_config(Path(__file__).resolve().parents[3] / "examples" / "hardware" / "ur_v4l2.yaml")
    lo, hi = np.array(hw.safety.workspace_min_m), np.array(hw.safety.workspace_max_m)
    free = make_plan(spec, 0, ["A"], ["cube"], ["clean"], {}, n_tcp_poses=4, n_object_layouts=2)
    inside = lambda p: bool(np.all(p.T_table_tcp.T()[:3, 3] >= lo) and np.all(p.T_table_tcp.T()[:3, 3] <= hi))  # noqa: E731
    boxed = make_plan(
        spec, 0, ["A"], ["cube"], ["clean"], {}, n_tcp_poses=4, n_object_layouts=2, workspace=(lo, hi, np.eye(4))
    )
    assert not all(inside(p) for p in free.tcp_poses)  # the sampler alone ignores the cell
    assert all(inside(p) for p in boxed.tcp_poses) and len(boxed.tcp_poses) == 4
    shifted = np.eye(4)
    shifted[0, 3] = 0.5  # the table origin 0.5 m in front of the base
    moved = make_plan(
        spec, 0, ["A"], ["cube"], ["clean"], {}, n_tcp_poses=4, n_object_layouts=2, workspace=(lo, hi, shifted)
    )
    assert all(
        np.all((shifted @ p.T_table_tcp.T())[:3, 3] >= lo) and np.all((shifted @ p.T_table_tcp.T())[:3, 3] <= hi)
        for p in moved.tcp_poses
    )


def test_plan_refuses_a_workspace_no_start_pose_fits_in_one_line(spec, tmp_path, monkeypatch, capsys):
    from pathlib import Path

    from trials.cli.main import main

    data = yaml.safe_load((Path(__file__).resolve().parents[3] / "examples" / "hardware" / "sim.yaml").read_text())
    data["safety"]["workspace_min_m"], data["safety"]["workspace_max_m"] = [0.0, 0.0, 0.01], [0.05, 0.05, 0.05]
    (tmp_path / "hw.yaml").write_text(yaml.safe_dump(data))
    monkeypatch.setattr(
        "sys.argv",
        [
            "advobj",
            "trial",
            "plan",
            "--out",
            str(tmp_path / "p.yaml"),
            "--shape",
            "cube",
            "--condition",
            "clean",
            "--tcp-poses",
            "2",
            "--object-poses",
            "1",
            "--hardware",
            str(tmp_path / "hw.yaml"),
        ],
    )
    with pytest.raises(SystemExit) as exc:
        main()
    err = [l for l in capsys.readouterr().err.splitlines() if l.strip()]
    assert exc.value.code == 2 and len(err) == 1
    assert (
        "--hardware: found 0/2 start TCP poses inside the workspace box [0, 0, 0.01] .. [0.05, 0.05, 0.05] m" in err[0]
    )
    assert re.search(r"spanning x -?\d\.\d+\.\.-?\d\.\d+, y .*, z \d\.\d+\.\.\d\.\d+ m", err[0])
    assert not (tmp_path / "p.yaml").exists()


def test_a_plan_outside_the_cells_box_is_refused_once_not_twice(tmp_path, monkeypatch, capsys):
    from pathlib import Path

    from tests.trials.real.trial_session_helpers import tiny_onnx
    from trials.cli.main import main

    root = Path(__file__).resolve().parents[3]
    data = yaml.safe_load((root / "examples" / "hardware" / "sim.yaml").read_text())
    data["safety"]["workspace_max_m"] = [0.9, 0.9, 0.05]
    data["sim"]["image_size"] = [32, 32]
    (tmp_path / "hw.yaml").write_text(yaml.safe_dump(data))
    monkeypatch.setattr(
        "sys.argv",
        [
            "advobj",
            "trial",
            "plan",
            "--out",
            str(tmp_path / "p.yaml"),
            "--shape",
            "cube",
            "--condition",
            "clean",
            "--tcp-poses",
            "1",
            "--object-poses",
            "1",
        ],
    )
    try:
        main()
    except SystemExit as exc:
        assert exc.code in (0, None)
    capsys.readouterr()
    monkeypatch.setattr(
        "sys.argv",
        [
            "advobj",
            "trial",
            "run",
            "--hardware",
            str(tmp_path / "hw.yaml"),
            "--policy",
            str(tiny_onnx(tmp_path / "p.onnx")),
            "--plan",
            str(tmp_path / "p.yaml"),
            "--session",
            "s",
            "--db",
            str(tmp_path / "t.sqlite"),
            "--auto-confirm",
            "--no-rate-limit",
        ],
    )
    with pytest.raises(SystemExit) as exc:
        main()
    cap = capsys.readouterr()
    both = cap.out + cap.err
    assert exc.value.code == 2 and both.count("initial TCP poses outside the safety workspace box") == 1
