"""Outcomes that are observed through the tags, not assumed: a sim cell whose camera draws the
registry's tag36h11 tags, so the session runs the real pipeline (AprilTag 3 detector, bundles, the
calibrated chain) and the simulator's ground truth is only used to check it.

The policy always moves straight ahead (a real ONNX network, whatever the image), so the arm's
path does not depend on where the objects stand: a first session learns where a trial ends, and
the scenarios then move or hide an object relative to that.
"""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from tests.trials.real.trial_session_helpers import SIM_HW, small_plan, straight_ahead_onnx

TRIAL = "A-cube-adv3d-t0-o0"  # ends at max_steps, reaching nothing


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    d = tmp_path_factory.mktemp("tagged_cell")
    data = yaml.safe_load(SIM_HW.read_text())
    data["sim"]["image_size"] = [480, 480]  # tags of 4.5 cm need the pixels a real camera has
    data["camera"]["tags"] = True
    (d / "hw.yaml").write_text(yaml.safe_dump(data))
    return {
        "dir": d,
        "hw": d / "hw.yaml",
        "policy": straight_ahead_onnx(d / "p.onnx"),
        "plan": small_plan(d / "plan.yaml", d / "tex", n_tcp=2, n_layouts=2, max_steps=30, seed=5),
    }


def _run(cell, session, operator=None, on_ready=None, max_trials=1):
    from trials.real.operator import AutoOperator
    from trials.real.session import SessionOptions, run_session

    db = cell["dir"] / f"{session}.sqlite"
    opts = SessionOptions(
        hardware=cell["hw"],
        policy=cell["policy"],
        plan=cell["plan"],
        session=session,
        db=db,
        rate_limit=False,
        max_trials=max_trials,
    )
    run_session(opts, operator=operator or AutoOperator(None), on_ready=on_ready, log=lambda _t: None)
    return db


def _rows(db, table):
    from trials.real.store import TrialStore

    with TrialStore(db, create=False) as st:
        if table == "trials":
            return {r["trial_id"]: r for r in st.trial_rows()}
        cols, rows = st.table(table)
        return [dict(zip(cols, r)) for r in rows]


def _truth_hook(truth):
    from sim.outcome import NONE, object_distances, reach_outcome

    def ready(runner, world):
        def record(trial):
            c = world.object_center_array
            tcp = world.T_world_tcp[:3, 3]
            k = int(reach_outcome(tcp[None], c[None], runner.plan.radius_m)[0])
            d = object_distances(tcp[None], c[None])[0]
            truth[trial.trial_id] = (
                "none" if k == NONE else world.spec.objects[k].role,
                float(np.min(np.abs(d - runner.plan.radius_m))),
            )

        runner.on_trial_end = record
        assert runner.locator.source == "tags" and runner.camera.tags == []  # tagged when the first scene is staged

    return ready


def test_outcomes_seen_through_the_tags_match_the_sim_ground_truth(cell):
    truth = {}
    db = _run(cell, "seen", on_ready=_truth_hook(truth), max_trials=4)
    rows = _rows(db, "trials")
    assert len(rows) == 4
    for tid, r in rows.items():
        want, margin = truth[tid]
        if margin > 0.01:  # a tag-located centre is off by a few mm: only a near-tie may flip
            assert r["auto_outcome"] == want, (tid, r["auto_reason"])
    poses = [p for p in _rows(db, "object_poses") if p["phase"] == "final"]
    assert poses and all(p["found"] == 1 and p["source"] == "tags" for p in poses)
    # Occlusion measure: the share of the expected tag area that was seen (a bundle's back tags are not expected).
    assert all(0.0 < p["visible_fraction"] <= 1.0 for p in poses if p["visible_fraction"] is not None)
    assert sum(p["visible_fraction"] is not None for p in poses) >= len(poses) // 2
    assert all(0.05 < r["light_level"] < 0.95 for r in rows.values())  # the lighting scenarios' measure, per trial
    assert list((cell["dir"] / "frames" / "seen").glob("sim_registry_*.yaml"))  # each staged object tagged, on record


@pytest.fixture(scope="module")
def end_of_trial(cell):
    """Where TRIAL's TCP ends and where its objects stand, from a session with nothing changed."""
    db = _run(cell, "baseline")
    r = _rows(db, "trials")[TRIAL]
    assert r["auto_outcome"] == "none" and r["stop_reason"] == "max_steps"
    return np.array([r["tcp_final_x_m"], r["tcp_final_y_m"], r["tcp_final_z_m"]])


def test_an_object_moved_mid_trial_is_judged_where_it_is(cell, end_of_trial):
    from sim.configs import object_poses_world

    target = end_of_trial[:2] + [0.0, 0.0]
    seen = {}

    def ready(runner, world):
        def move(trial, k):
            if k == 8:  # the operator (or the object's own motion) puts it in the arm's way
                K = world.spec.object_index("adversarial")
                T = world.T_world_objects.copy()
                T[K] = object_poses_world([[target[0], target[1], 0.3]])[0]
                world.T_world_objects = T
                seen["center"] = world.object_center_array[K].copy()

        runner.on_step = move

    db = _run(cell, "moved", on_ready=ready)
    r = _rows(db, "trials")[TRIAL]
    assert r["auto_outcome"] == "adversarial" and r["stop_reason"] == "reached", r["auto_reason"]
    events = [e for e in _rows(db, "events") if e["trial_id"] == TRIAL and e["kind"] == "track"]
    assert (
        len(events) == 1 and events[0]["reason"].startswith("adversarial moved") and "by step 8" in events[0]["reason"]
    )
    final = {p["role"]: p for p in _rows(db, "object_poses") if p["trial_id"] == TRIAL and p["phase"] == "final"}
    got = np.array([final["adversarial"][f"center_{a}_m"] for a in "xyz"])
    assert np.linalg.norm(got - seen["center"]) < 0.01  # located by its tags at its new place
    placed = {p["role"]: p for p in _rows(db, "object_poses") if p["trial_id"] == TRIAL and p["phase"] == "placement"}
    old = np.array([placed["adversarial"][f"center_{a}_m"] for a in "xyz"])
    assert np.linalg.norm(old - end_of_trial) > 0.1  # judged at its placement it would have been 'none'


@pytest.mark.parametrize("answer", [None, "adversarial"])
def test_an_object_hidden_at_the_end_gives_unknown_and_the_operator_decides(cell, end_of_trial, answer):
    from trials.real.operator import Decision, ScriptedOperator

    def ready(runner, world):
        runner.on_trial_end = lambda trial: runner.camera.hidden.add("adversarial")  # a hand over its tags

    operator = ScriptedOperator({TRIAL: Decision(answer)} if answer else {}, log=None)
    db = _run(cell, f"hidden-{answer}", operator=operator, on_ready=ready)
    r = _rows(db, "trials")[TRIAL]
    assert r["auto_outcome"] == "unknown"
    assert "not detected: adversarial" in r["auto_reason"] and "adversarial last seen at step" in r["auto_reason"]
    assert r["final_outcome"] == (answer or "unknown") and r["operator_outcome"] == answer
    looks = [e for e in _rows(db, "events") if e["trial_id"] == TRIAL and e["kind"] == "outcome"]
    assert looks and "from the start pose: none of them" in looks[0]["reason"]
    final = {p["role"]: p for p in _rows(db, "object_poses") if p["trial_id"] == TRIAL and p["phase"] == "final"}
    assert final["adversarial"]["found"] == 0 and final["goal"]["found"] == 1


def test_a_fault_mid_trial_is_committed_and_the_arm_does_not_move_again(cell):
    from robot_io.arms.base import Fault

    moves = []

    def ready(runner, world):
        driver = runner.arm._SafeArm__arm  # the sim driver behind the safety layer (the vendor-SDK boundary's twin)

        def fault(trial, k):
            if k == 3:
                driver.inject_fault(Fault("protective_stop", "simulated protective stop", "clear it on the pendant"))

        runner.on_step = fault
        real_move = runner.arm.move_to
        runner.arm.move_to = lambda T, *a, **kw: (moves.append(T), real_move(T, *a, **kw))[1]

    db = _run(cell, "fault", on_ready=ready)
    r = _rows(db, "trials")[TRIAL]
    assert r["stop_reason"].startswith("fault:")
    assert len(moves) == 1  # the positioning move only: no look-again after the fault
    looks = [e for e in _rows(db, "events") if e["trial_id"] == TRIAL and e["kind"] == "outcome"]
    assert all(e["action"] != "look_again" for e in looks)
    assert r["auto_outcome"] in ("unknown", "none", "goal", "adversarial")
