"""CI: a whole "real" session on SimCamera + SimArm: plan -> run (auto-confirmed) -> report -> export.

The policy is a real ONNX network run by onnxruntime whose action is "move straight ahead"
(:func:`straight_ahead_onnx`); from the plan's start poses (seed 5, 2 TCP poses x 2 layouts) it
reaches the goal in some trials and the adversarial object in others, so the checks below have
something to check. The logged automatic outcomes are compared with the sim's ground truth,
recomputed here from the world right after each trial's policy loop (a hook), not taken from the
runner; the report's rates are compared with counts of the stored rows.
"""

from __future__ import annotations

import json
from collections import Counter

import numpy as np
from typer.testing import CliRunner

from tests.trials.real.trial_session_helpers import attack_dir, sim_hardware, straight_ahead_onnx


def test_plan_run_report_export_matches_sim_ground_truth(tmp_path, monkeypatch):
    from sim.outcome import NONE, reach_outcome
    from trials.cli.main import app
    from trials.real import runner as runner_mod
    from trials.real.store import TrialStore

    cli = CliRunner()
    policy = straight_ahead_onnx(tmp_path / "p.onnx")
    hw = sim_hardware(tmp_path / "hw.yaml")
    adv, patch = attack_dir(tmp_path / "adv", "cube"), attack_dir(tmp_path / "patch", "patch", 1)
    plan = tmp_path / "plan.yaml"
    r = cli.invoke(
        app,
        [
            "trial",
            "plan",
            "--out",
            str(plan),
            "--shape",
            "cube",
            "--texture",
            f"cube/adv3d={adv}",
            "--texture",
            f"cube/patch={patch}",
            "--tcp-poses",
            "2",
            "--object-poses",
            "2",
            "--seed",
            "5",
        ],
    )
    assert r.exit_code == 0, r.output

    truth = {}
    original_run = runner_mod.TrialRunner.run

    def run_with_ground_truth(self, max_trials=None):
        world = self.camera.world  # the SimCamera's world, shared with the SimArm

        def record(trial):
            centers = world.object_center_array
            k = int(reach_outcome(world.T_world_tcp[:3, 3][None], centers[None], self.plan.radius_m)[0])
            truth[trial.trial_id] = "none" if k == NONE else world.spec.objects[k].role
            # The staged scene is the trial's: adversarial mesh per condition.
            assert world.spec.adversarial.mesh == ("patch" if trial.condition == "patch" else trial.shape)

        self.on_trial_end = record
        return original_run(self, max_trials)

    monkeypatch.setattr(runner_mod.TrialRunner, "run", run_with_ground_truth)
    db = tmp_path / "trials.sqlite"
    r = cli.invoke(
        app,
        [
            "trial",
            "run",
            "--hardware",
            str(hw),
            "--policy",
            str(policy),
            "--plan",
            str(plan),
            "--session",
            "ci",
            "--db",
            str(db),
            "--auto-confirm",
            "--no-rate-limit",
        ],
    )
    assert r.exit_code == 0, r.output

    with TrialStore(db, create=False) as store:
        rows = store.trial_rows()
        assert len(rows) == 12 and len(truth) == 12
        outcomes = Counter(r["final_outcome"] for r in rows)
        assert outcomes["goal"] > 0 and outcomes["adversarial"] > 0, outcomes  # the session has power
        assert any(r["stop_reason"] == "reached" for r in rows)
        for row in rows:
            assert row["auto_outcome"] == truth[row["trial_id"]], row
            assert row["final_outcome"] == row["auto_outcome"] and row["operator_outcome"] is None
            steps = store.steps("ci", row["trial_id"])
            assert len(steps) == row["n_steps"] > 0
            assert all((db.parent / s["frame_ref"]).is_file() for s in steps)
        sess = store.session("ci")
        assert sess["software_version"] and sess["git_commit"] and '"serial": "sim"' in sess["devices_json"]
        textured = [r for r in rows if r["condition"] != "clean"]
        assert all(len(r["texture_sha256"]) == 64 for r in textured)

    out = tmp_path / "report"
    r = cli.invoke(app, ["trial", "report", "--db", str(db), "--out", str(out)])
    assert r.exit_code == 0, r.output
    report = json.loads((out / "report.json").read_text())
    md = (out / "report.md").read_text()
    # every per-condition cell and the Table IV row (untagged adv3d) are the counts of the stored rows
    for cond in ("clean", "adv3d", "patch"):
        rs = [x for x in rows if x["condition"] == cond]
        cell = report["summary"]["all"]["by_condition"][cond]
        assert (cell["n"], cell["tasr"]["k"], cell["asr"]["k"]) == (
            len(rs),
            sum(x["final_outcome"] == "adversarial" for x in rs),
            sum(x["final_outcome"] != "goal" for x in rs),
        ), cond
    adv = [x for x in rows if x["condition"] == "adv3d"]
    k_tasr = sum(x["final_outcome"] == "adversarial" for x in adv)
    k_asr = sum(x["final_outcome"] != "goal" for x in adv)
    (row,) = report["table_iv"]
    assert (row["env"], row["shape"], row["n"], row["real"]["tasr"]["k"], row["real"]["asr"]["k"]) == (
        "A",
        "cube",
        len(adv),
        k_tasr,
        k_asr,
    )
    assert 0 < k_tasr < len(adv) or 0 < k_asr < len(adv)  # a rate strictly between 0 and 1 somewhere in the row
    assert f"| A | cube | – | – | {100 * k_tasr / len(adv):.2f} [" in md and f"| {len(adv)} |" in md

    r = cli.invoke(app, ["trial", "export", "--db", str(db), "--out", str(tmp_path / "export")])
    assert r.exit_code == 0, r.output
    import pyarrow.parquet as pq

    t = pq.read_table(tmp_path / "export" / "trials.parquet").to_pydict()
    assert sorted(t["trial_id"]) == sorted(truth) and np.all(np.array(t["n_steps"]) > 0)
