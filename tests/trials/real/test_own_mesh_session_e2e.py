"""CI: a real scanned mesh all the way into a (simulated) cell, by the commands a user runs.

The object is ``tests/data/meshes/scan-rabbit-mm/rabbit.stl``, a photogrammetry scan in
millimetres, named ``rabbit`` in the user's scene YAML. ``advobj fabricate --scene --shape rabbit
--tag-id 7`` makes its tag card (objects.yaml registers the card's tag under ``rabbit``),
``advobj trial plan --scene --shape rabbit`` plans it with a texture optimised on it, and
``advobj trial run`` runs the plan on sim devices whose camera draws the registry's tags (the card
beside the rabbit, tags on the goal), so the placement check and the outcome go through the
real pipeline: the AprilTag detector, the registry's bundles and the card's T_obj_tag. The sim's
ground truth (recomputed from the world after each policy loop) only checks it.
"""

from __future__ import annotations

import json

import numpy as np
import yaml
from typer.testing import CliRunner

from tests.trials.real.own_mesh_helpers import RABBIT, own_scene, run_on_scene
from tests.trials.real.trial_session_helpers import SIM_HW, straight_ahead_onnx


def _goal_tags(scene):
    """The goal's tags as a person puts them on a can (top and four sides: sim_registry's)."""
    from robot_io.cameras.sim import sim_registry
    from sim.spec import load_spec
    from sim.world import SimWorld

    with SimWorld(load_spec(scene), 32) as world:
        reg = sim_registry(world, table_tags=False)
    return {i: e for i, e in reg.tags.items() if e.object == "goal"}


def test_a_scanned_mesh_is_fabricated_planned_staged_located_and_reported(tmp_path, monkeypatch):
    from calibration.registry import ObjectRegistry, load_registry, save_registry
    from sim.outcome import NONE, object_distances, reach_outcome
    from trials.cli.main import app
    from trials.real import runner as runner_mod
    from trials.real.store import TrialStore

    cli = CliRunner()
    scene = own_scene(
        tmp_path / "rabbit.yaml",
        RABBIT,
        name="rabbit",
        scene_fields={"episode": {"max_steps": 30}, "init": {"r_range_m": [0.25, 0.5]}},
    )
    run = run_on_scene(tmp_path / "attack", scene)

    # 1. the tag card for the rabbit, its tag registered under the rabbit's name
    fab = tmp_path / "fab"
    r = cli.invoke(app, [str(a) for a in ["fabricate", run, "--scene", scene, "--shape", "rabbit", "--out", fab]] + [
        "--tag-id", "7", "--tag-size-mm", "40", "--dpi", "60"])  # fmt: skip
    assert r.exit_code == 0, r.output
    assert "pre-print check PASSED: tag card" in r.output
    card = load_registry(fab / "objects.yaml")
    assert card.objects == ("rabbit",)
    registry = tmp_path / "objects.yaml"  # the cell's registry: the goal's tags and the card's
    save_registry(registry, ObjectRegistry(tags={**_goal_tags(scene), **card.tags}))

    # 2. the plan: the rabbit by its scene name, its texture from the run on it
    plan = tmp_path / "plan.yaml"
    r = cli.invoke(app, [str(a) for a in ["trial", "plan", "--scene", scene, "--shape", "rabbit", "--out", plan]] + [
        "--texture", f"rabbit/adv3d={run}", "--condition", "clean", "--condition", "adv3d",
        "--tcp-poses", "2", "--object-poses", "1", "--seed", "3"])  # fmt: skip
    assert r.exit_code == 0, r.output
    assert "shape rabbit: scene object 'rabbit', mesh rabbit.stl (mm" in r.output

    # 3. the session on sim devices that draw the tags (480 px: the pixels a real camera has)
    hw = yaml.safe_load(SIM_HW.read_text())
    hw["sim"]["image_size"] = [480, 480]
    hw["camera"]["tags"] = True
    hw["safety"]["max_frame_age_ms"] = 5000  # a 74k-face scan rendered on a shared CPU core
    (tmp_path / "hw.yaml").write_text(yaml.safe_dump(hw))
    truth, staged = {}, {}
    original_run = runner_mod.TrialRunner.run

    def run_with_ground_truth(self, max_trials=None):
        world = self.camera.world

        def record(trial):
            c, tcp = world.object_center_array, world.T_world_tcp[:3, 3]
            k = int(reach_outcome(tcp[None], c[None], self.plan.radius_m)[0])
            margin = float(np.min(np.abs(object_distances(tcp[None], c[None])[0] - self.plan.radius_m)))
            truth[trial.trial_id] = ("none" if k == NONE else world.spec.objects[k].role, margin)
            K = world.spec.object_index("adversarial")
            staged[trial.trial_id] = (world.spec.adversarial, world.T_world_objects[K].copy(), c[K].copy())

        self.on_trial_end = record
        return original_run(self, max_trials)

    monkeypatch.setattr(runner_mod.TrialRunner, "run", run_with_ground_truth)
    db = tmp_path / "trials.sqlite"
    r = cli.invoke(app, [str(a) for a in ["trial", "run", "--hardware", tmp_path / "hw.yaml", "--policy",
        straight_ahead_onnx(tmp_path / "p.onnx"), "--plan", plan, "--session", "rabbit", "--db", db,
        "--registry", registry, "--auto-confirm", "--no-rate-limit"]])  # fmt: skip
    assert r.exit_code == 0, r.output

    with TrialStore(db, create=False) as store:
        rows = {row["trial_id"]: row for row in store.trial_rows()}
        cols, pose_rows = store.table("object_poses")
    poses = [dict(zip(cols, p)) for p in pose_rows]
    assert len(rows) == 4 and set(rows) == set(truth)
    # the session has power: from one start pose the arm reaches the goal, from the other the rabbit
    assert {r["auto_outcome"] for r in rows.values()} == {"goal", "adversarial"}
    assert {t[0] for t in truth.values()} == {"goal", "adversarial"}
    texture_sha = yaml.safe_load(plan.read_text())["textures"]["rabbit/adv3d"]["sha256"]
    for tid, row in rows.items():
        adv, T_adv, c_adv = staged[tid]
        assert adv.name == "rabbit" and adv.mesh == str(RABBIT) and adv.units == "mm"  # the scan, in its slot
        assert row["texture_sha256"] == (texture_sha if row["condition"] == "adv3d" else None)
        want, margin = truth[tid]
        if margin > 0.01:  # a tag-located centre is off by a few mm: only a near-tie may flip
            assert row["auto_outcome"] == want, (tid, row["auto_reason"])
        # placed by the tags, and located as the rabbit itself: its base centre and its centre
        (p,) = [x for x in poses if x["trial_id"] == tid and x["role"] == "adversarial" and x["phase"] == "placement"]
        assert p["found"] == 1 and p["source"] == "tags" and json.loads(p["tag_ids_json"]) == [7]
        got = np.array([p["table_x_m"], p["table_y_m"], p["table_z_m"]])
        assert np.linalg.norm(got - T_adv[:3, 3]) < 0.01
        assert np.linalg.norm(np.array([p["center_x_m"], p["center_y_m"], p["center_z_m"]]) - c_adv) < 0.01

    out = tmp_path / "report"
    r = cli.invoke(app, ["trial", "report", "--db", str(db), "--out", str(out)])
    assert r.exit_code == 0, r.output
    report = json.loads((out / "report.json").read_text())
    assert report["summary"]["all"]["by_shape"]["rabbit"]["n"] == 4
