"""An own scanned mesh located in the (simulated) cell by tag stickers on its faces, no card.

The object is ``tests/data/meshes/ycb-mustard/006_mustard_bottle.stl`` (a YCB scan in metres),
named ``mustard`` in the user's scene YAML. A person sticks a tag on a side of the bottle that the
camera sees from a trial's start pose, measures the tag's pose on the object (``T_obj_tag``, in the
object frame the scene places it in: origin at its base centre, +z up) and writes the registry
entry as docs/fabrication.md says: ``T_tag_object = inv(T_obj_tag) @ T(centre)``, the centre being
the object's bounding-box centre that ``advobj trial plan`` records (``shape_objects.mustard.center_m``).
The plan's two start poses look at opposite sides, so there are two stickers, one per side.

The sim camera draws a tag flat at a pose on its object, depth-tested against the rendered mesh
(as it draws the card's tag). First the stickers are drawn where they physically are (from the
mesh, not from the registry) and the hand-written registry locates the bottle from each start pose
(a registry entry missing the centre's offset does not); then ``advobj trial run --registry`` runs
the plan, the camera drawing the registry's tags (which put each sticker where it physically is),
and its placement checks locate the bottle by the stickers. The sim's ground truth only checks,
within the card path's tolerance (1 cm; yaw within the plan's placement tolerance).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from tests.trials.real.own_mesh_helpers import REPO, own_scene, run_on_scene
from tests.trials.real.trial_session_helpers import SIM_HW, straight_ahead_onnx

MUSTARD = REPO / "tests" / "data" / "meshes" / "ycb-mustard" / "006_mustard_bottle.stl"
STICKER_MM = 30.0  # the tag's black square, as printed by 'calibrate tags'
STICKER_IDS = (31, 32)  # one per start pose of the plan, on the side it sees
TOLERANCE_M = 0.01  # the card path's (tests/trials/real/test_own_mesh_session_e2e.py)


def first_hit(mesh, origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Where the ray from ``origin`` along unit ``direction`` first meets the mesh (Moller-Trumbore
    over every triangle)."""
    a, b, c = (mesh.vertices[mesh.faces[:, i]] for i in range(3))
    e1, e2 = b - a, c - a
    p = np.cross(direction, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = origin - a
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    v = (q @ direction) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    assert hit.any(), "the line of sight misses the mesh"
    return origin + t[hit].min() * direction


def sticker_on_face(mesh, eye_obj: np.ndarray, center_obj: np.ndarray, size_m: float) -> np.ndarray:
    """``T_obj_tag`` of a flat sticker where the line of sight from ``eye_obj`` to ``center_obj``
    (object frame) meets the mesh: its centre on the plane fitted to the surface within the
    sticker's reach, +z out of that face, +y up the object as far as the face allows (the print
    upright on a side). One mm off the surface, as paper on a scan's bumps."""
    from sim.geometry import make_T

    d = center_obj - eye_obj
    d = d / np.linalg.norm(d)
    hit = first_hit(mesh, eye_obj, d)
    near = mesh.vertices[np.linalg.norm(mesh.vertices - hit, axis=1) < 0.6 * size_m]
    mid = near.mean(axis=0)
    normal = np.linalg.svd(near - mid)[2][2]
    normal = normal if normal @ (eye_obj - hit) > 0 else -normal
    up = np.array([0.0, 0.0, 1.0]) - normal[2] * normal
    y = up / np.linalg.norm(up)
    R = np.stack([np.cross(y, normal), y, normal], axis=1)
    origin = hit + ((mid - hit) @ normal + 0.001) * normal  # on the fitted plane, 1 mm out
    return make_T(R, origin)


def sticker_entry(T_obj_tag: np.ndarray, center_m, name: str, size_m: float, with_centre: bool = True) -> dict:
    """The registry entry as the user writes it (docs/fabrication.md): ``T_tag_object`` is the
    object's bounding-box centre seen from the tag, ``inv(T_obj_tag) @ T(centre)``
    (``with_centre=False``: the mistake of leaving the centre's offset out)."""
    from calibration.io import T_to_pose
    from sim.geometry import invert_T, make_T

    centre = np.asarray(center_m, float) if with_centre else np.zeros(3)
    pose = T_to_pose(invert_T(T_obj_tag) @ make_T(np.eye(3), centre))
    return {
        "object": name,
        "size_m": size_m,
        "T_tag_object": {"translation_m": list(pose.translation_m), "rotvec_rad": list(pose.rotvec_rad)},
    }


def physical_stickers(T_obj_tags: dict, center_m, size_m: float) -> list:
    """The stickers as the sim camera draws them where they are on the bottle, whatever the
    registry says: each at ``T_obj_tag`` in the object frame, given from the frame the camera
    draws in (the object's centre with its axes)."""
    from robot_io.cameras.sim import SimTag
    from sim.geometry import make_T

    T_centre_obj = make_T(np.eye(3), -np.asarray(center_m, float))
    return [SimTag(i, size_m, "mustard", T_centre_obj @ T) for i, T in T_obj_tags.items()]


def _goal_tags(scene):
    """The goal's tags as a person puts them on a can (top and four sides: sim_registry's)."""
    from robot_io.cameras.sim import sim_registry
    from sim.spec import load_spec
    from sim.world import SimWorld

    with SimWorld(load_spec(scene), 32) as world:
        reg = sim_registry(world, table_tags=False)
    return {i: e for i, e in reg.tags.items() if e.object == "goal"}


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    """The user's scene, attack run and plan (by the CLI), the stickers measured on the bottle for
    the plan's start poses, and their hand-written registry file."""
    from sim.assets import build_mesh
    from sim.geometry import invert_T, make_T, rot_z
    from sim.spec import load_spec
    from trials.cli.main import app
    from trials.real.plan import load_plan

    d = tmp_path_factory.mktemp("stickers")
    scene = own_scene(
        d / "mustard.yaml",
        MUSTARD,
        name="mustard",
        units="m",
        scene_fields={"episode": {"max_steps": 10}, "init": {"r_range_m": [0.25, 0.5]}},
    )
    run = run_on_scene(d / "attack", scene)
    plan = d / "plan.yaml"
    r = CliRunner().invoke(app, [str(a) for a in ["trial", "plan", "--scene", scene, "--shape", "mustard"]] + [
        "--out", str(plan), "--texture", f"mustard/adv3d={run}", "--condition", "clean", "--condition", "adv3d",
        "--tcp-poses", "2", "--object-poses", "1", "--seed", "3"])  # fmt: skip
    assert r.exit_code == 0, r.output
    doc = yaml.safe_load(plan.read_text())
    center_m = np.array(doc["shape_objects"]["mustard"]["center_m"])
    planned = load_plan(plan)

    spec = load_spec(scene)
    obj = spec.adversarial
    mesh = build_mesh(obj.mesh, obj.scale, **obj.mesh_kwargs())  # the object frame the scene places it in
    np.testing.assert_allclose(center_m, mesh.bounds.mean(axis=0), atol=1e-9)
    (layout,) = planned.object_layouts
    placed = layout.objects["adversarial"]
    T_table_obj = make_T(rot_z(placed.yaw_rad), [*placed.xy_m, 0.0])
    size_m = STICKER_MM / 1000.0
    T_obj_tags, seen_from = {}, {}
    for tag_id, tcp in zip(STICKER_IDS, planned.tcp_poses):
        T_table_cam = tcp.T_table_tcp.T() @ spec.camera.T_tcp_cam
        eye = (invert_T(T_table_obj) @ T_table_cam)[:3, 3]
        T_obj_tags[tag_id] = sticker_on_face(mesh, eye, center_m, size_m)
        seen_from[tcp.index] = tag_id
    for T in T_obj_tags.values():
        assert abs(T[2, 2]) < 0.5  # on a side of the bottle: the print stands, it does not lie
    a, b = (T[:3, 2] for T in T_obj_tags.values())
    assert a @ b < 0  # on two sides facing away from each other
    user = d / "stickers.yaml"  # the hand-written file
    stickers = {i: sticker_entry(T, center_m, "mustard", size_m) for i, T in T_obj_tags.items()}
    user.write_text(yaml.safe_dump({"tags": stickers}, sort_keys=False))
    return {
        "dir": d,
        "scene": scene,
        "spec": spec,
        "plan": plan,
        "doc": doc,
        "center_m": center_m,
        "size_m": size_m,
        "T_obj_tags": T_obj_tags,
        "seen_from": seen_from,
        "user": user,
    }


def _located_as_truth(got, world, k, tolerance_rad) -> None:
    """``got`` (a LocatedObject) is object ``k`` of ``world``: its base centre and centre within the
    card path's tolerance, its yaw within the plan's."""
    from trials.real.locate import wrap_angle, yaw_of

    T_true = world.T_world_objects[k]
    assert np.linalg.norm(got.T_table_object[:3, 3] - T_true[:3, 3]) < TOLERANCE_M, (got.T_table_object, T_true)
    assert np.linalg.norm(got.center_table_m - world.object_center_array[k]) < TOLERANCE_M
    assert abs(wrap_angle(got.yaw_rad - yaw_of(T_true))) < tolerance_rad


def test_stickers_where_they_are_on_the_mesh_locate_it_by_the_hand_written_registry_from_each_start_pose(cell):
    """The camera draws the stickers where they are on the bottle (not where the registry says), so
    the hand-written entries are what is tested: they locate the bottle from each start pose, and
    entries missing the centre's offset put it off by that offset."""
    from calibration.registry import ObjectRegistry, load_registry
    from robot_io.cameras.sim import SimCamera
    from sim.world import SimWorld
    from trials.real.locate import TagLocator, placement_issues
    from trials.real.plan import load_plan
    from trials.real.stage import SimStage

    plan = load_plan(cell["plan"])
    registry = load_registry(cell["user"])
    wrong = ObjectRegistry.model_validate(
        {
            "tags": {
                i: sticker_entry(T, cell["center_m"], "mustard", cell["size_m"], with_centre=False)
                for i, T in cell["T_obj_tags"].items()
            }
        }
    )
    tested = set()
    with SimWorld(cell["spec"], 480) as world:
        world.reset(0)
        stage = SimStage(world, plan, cell["dir"])
        camera = SimCamera(world, tags=physical_stickers(cell["T_obj_tags"], cell["center_m"], cell["size_m"]))
        for trial in [t for t in plan.trials if t.condition == "adv3d"]:
            stage.prepare(trial)
            world.set_tcp_pose(
                plan.tcp_pose(trial.tcp_pose).T_table_tcp.T()
            )  # the trial's start pose (table = world frame)
            k = world.spec.object_index("adversarial")
            with camera:
                frame = camera.read()
            locator = TagLocator(registry, camera.intrinsics, camera.T_tcp_cam, np.eye(4))
            locator.for_trial(plan, trial)
            got = locator.locate(frame, world.T_world_tcp)["adversarial"]
            assert got.tag_ids == (cell["seen_from"][trial.tcp_pose],) and got.source == "tags"
            _located_as_truth(got, world, k, plan.placement_tolerance_rad)
            layout = plan.object_layout(trial.object_layout).objects
            tol = (plan.placement_tolerance_m, plan.placement_tolerance_rad)
            assert placement_issues({"adversarial": layout["adversarial"]}, {"adversarial": got}, *tol) == []
            # the entry without the centre's offset: the bottle's base is put where its centre is
            bad = TagLocator(wrong, camera.intrinsics, camera.T_tcp_cam, np.eye(4))
            bad.for_trial(plan, trial)
            off = bad.locate(frame, world.T_world_tcp)["adversarial"]
            miss = np.linalg.norm(off.T_table_object[:3, 3] - world.T_world_objects[k][:3, 3])
            assert abs(miss - np.linalg.norm(cell["center_m"])) < TOLERANCE_M
            tested.add(trial.tcp_pose)
        stage.close()
    assert tested == set(cell["seen_from"])


def test_an_own_mesh_with_hand_registered_stickers_is_located_by_them_in_a_trial_session(cell, monkeypatch):
    from calibration.registry import ObjectRegistry, load_registry, save_registry
    from robot_io.cameras.sim import sim_tags
    from trials.cli.main import app
    from trials.real import runner as runner_mod
    from trials.real.locate import wrap_angle
    from trials.real.store import TrialStore

    d, doc = cell["dir"], cell["doc"]
    registry = d / "objects.yaml"  # the cell's registry: the goal's tags and the user's stickers
    save_registry(registry, ObjectRegistry(tags={**_goal_tags(cell["scene"]), **load_registry(cell["user"]).tags}))
    # the session's sim camera draws the registry's tags: the hand-written entries put each sticker
    # where it is on the bottle
    drawn = {t.tag_id: t.T_object_tag for t in sim_tags(load_registry(registry)) if t.tag_id in STICKER_IDS}
    for t in physical_stickers(cell["T_obj_tags"], cell["center_m"], cell["size_m"]):
        np.testing.assert_allclose(drawn[t.tag_id], t.T_object_tag, atol=1e-6)

    hw = yaml.safe_load(SIM_HW.read_text())
    hw["sim"]["image_size"] = [480, 480]  # the pixels a real camera has
    hw["camera"]["tags"] = True
    hw["safety"]["max_frame_age_ms"] = 5000  # a scanned mesh rendered on a shared CPU core
    (d / "hw.yaml").write_text(yaml.safe_dump(hw))
    truth = {}
    original_run = runner_mod.TrialRunner.run

    def run_with_ground_truth(self, max_trials=None):
        world = self.camera.world

        def record(trial):
            K = world.spec.object_index("adversarial")
            truth[trial.trial_id] = (world.T_world_objects[K].copy(), world.object_center_array[K].copy())

        self.on_trial_end = record
        return original_run(self, max_trials)

    monkeypatch.setattr(runner_mod.TrialRunner, "run", run_with_ground_truth)
    db = d / "trials.sqlite"
    r = CliRunner().invoke(app, [str(a) for a in ["trial", "run", "--hardware", d / "hw.yaml", "--policy",
        straight_ahead_onnx(d / "p.onnx"), "--plan", cell["plan"], "--session", "stickers", "--db", db,
        "--registry", registry, "--auto-confirm", "--no-rate-limit"]])  # fmt: skip
    assert r.exit_code == 0, r.output

    with TrialStore(db, create=False) as store:
        cols, pose_rows = store.table("object_poses")
        ecols, event_rows = store.table("events")
    poses = [dict(zip(cols, p)) for p in pose_rows]
    events = [dict(zip(ecols, e)) for e in event_rows]
    by_trial = {t["trial_id"]: t for t in doc["trials"]}
    placed = doc["object_layouts"][0]["objects"]["adversarial"]
    assert set(truth) == set(by_trial) and len(truth) == 4
    for tid, (T_adv, c_adv) in truth.items():
        np.testing.assert_allclose(T_adv[:2, 3], placed["xy_m"], atol=1e-6)  # placed as planned: a fair check
        (p,) = [x for x in poses if x["trial_id"] == tid and x["role"] == "adversarial" and x["phase"] == "placement"]
        assert p["found"] == 1 and p["source"] == "tags", p
        # the sticker on the side this trial's start pose sees
        assert json.loads(p["tag_ids_json"]) == [cell["seen_from"][by_trial[tid]["tcp_pose"]]]
        # located as the bottle itself: its base centre, its centre and its yaw
        got = np.array([p["table_x_m"], p["table_y_m"], p["table_z_m"]])
        assert np.linalg.norm(got - T_adv[:3, 3]) < TOLERANCE_M, (tid, got, T_adv[:3, 3])
        assert np.linalg.norm(np.array([p["center_x_m"], p["center_y_m"], p["center_z_m"]]) - c_adv) < TOLERANCE_M
        yaw = float(np.arctan2(T_adv[1, 0], T_adv[0, 0]))
        assert abs(wrap_angle(p["yaw_rad"] - yaw)) < doc["placement_tolerance_rad"], (tid, p["yaw_rad"], yaw)
    assert not [e for e in events if e["kind"] == "placement" and "adversarial" in e["reason"]], events
