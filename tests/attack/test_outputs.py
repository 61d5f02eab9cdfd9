"""Exported adversarial meshes re-render in pyrender exactly as the optimised texture."""

import numpy as np

from attack.outputs import export_meshes
from sim.configs import object_poses_world
from sim.geometry import look_at
from sim.render import SceneRenderer
from sim.spec import default_scene


def _render(spec, T, texture=None):
    r = SceneRenderer(spec, 96, 96)
    adv = r.face_coded
    nominal = [(o.pose.x_m, o.pose.y_m, np.radians(o.pose.yaw_deg)) for o in spec.objects]
    r.set_state(object_poses_world(nominal), None)
    if texture is not None:
        r.set_object_texture(adv, texture)
    out = r.render(T)
    r.close()
    assert out.object_mask(adv).sum() > 500  # the object fills a good part of the view
    return out.rgb


def test_glb_and_obj_exports_re_render_as_optimised(tmp_path):
    spec = default_scene()
    base = SceneRenderer(spec, 96, 96)
    adv = base.face_coded
    mesh = base.object_mesh(adv)
    base.close()
    tex = (np.random.default_rng(0).random((64, 64, 3)) * 255).astype(np.uint8)
    paths = export_meshes(tmp_path, mesh, tex)
    c = np.array([spec.objects[adv].pose.x_m, spec.objects[adv].pose.y_m, 0.1])
    T = look_at(c + np.array([0.25, 0.1, 0.15]), c)
    want = _render(spec, T, tex)
    for kind in ("glb", "obj"):
        objs = [o.model_dump() for o in spec.objects]
        objs[adv]["mesh"] = str(paths[kind])
        got = _render(spec.with_updates(objects=objs), T)
        # Same pixels up to rounding of re-read vertex/UV floats at a few texel boundaries.
        diff = np.abs(got.astype(int) - want.astype(int))
        assert np.mean(diff) < 0.5 and np.percentile(diff, 99) <= 8, (kind, diff.mean())


def test_the_end_of_run_summary_puts_the_held_out_t_asr_first_and_explains_the_pose_loss():
    from attack.outputs import summary_lines

    m = {
        "iterations": 120,
        "seconds": 30.0,
        "initial_loss_pose": 0.136,
        "final_loss_pose": 0.209,
        "validation": {"t_asr": [0.0, 0.31, 0.62], "best": {"iteration": 120, "t_asr": 0.62, "episodes": 16}},
    }
    lines = summary_lines(m)
    assert "validation T-ASR (n = 16): 0.00 at the start -> 0.62 at the end; best 0.62 at iteration 120" in lines[1]
    assert lines[2].startswith("pose loss 0.136 -> 0.209") and "not comparable across iterations" in lines[2]
    off = summary_lines({**m, "validation": None})
    assert "validation: off" in off[1]


def test_write_outputs_leaves_a_folder_eval_and_fabricate_read_and_keeps_a_jobs_run_record(tmp_path):
    """The Python API (AttackRun, run_attack, write_outputs) writes run.json and configs.json beside the
    texture, as 'advobj attack run' does: the folder is a valid texture source with its mesh and the
    configurations it was optimised and validated on. A run.json recording this run's config (the job's,
    written before the run) is kept; one recording another config is replaced."""
    import json

    import torch

    from attack.artifact import AttackArtifact
    from attack.optimize import AttackRun, resolve_config, run_attack
    from attack.outputs import write_outputs
    from sim.configs import config_id, sample_pool
    from sim.policies.policy import VisuomotorPolicy

    spec = default_scene()
    cfg = resolve_config(
        "ci",
        {"iterations": 2, "num_envs": 1, "validation_every": 1, "validation_episodes": 2, "adversarial_mesh": "cube"},
    )
    pool = sample_pool(spec, 3, seed=0, part="attack") + sample_pool(spec, 2, seed=0, part="validation")
    torch.manual_seed(0)
    out = tmp_path / "mine"
    (out).mkdir()
    (out / "run.json").write_text(json.dumps({"config": {"attack": {"iterations": 99}}}))  # a stale record
    run = AttackRun(VisuomotorPolicy(arch="small_cnn", image_size=32), spec, cfg, pool=pool, out_dir=out)
    try:
        before = run.state.texture.clone()
        run_attack(run, progress=False)
        write_outputs(run, out, before)
        art = AttackArtifact.load(out)
        assert art.mesh == "cube" and art.attack_config == cfg.model_dump() and art.seed == cfg.seed
        assert art.trained_on >= {config_id(c) for c in pool}  # every configuration drawn from or validated on
        assert art.scene["objects"][spec.object_index("adversarial")]["mesh"] == "cube"
        job = {"config": {"job": "attack", "preset": "ci", "attack": cfg.model_dump()}, "seed": cfg.seed}
        (out / "run.json").write_text(json.dumps(job))
        write_outputs(run, out, before)
        assert json.loads((out / "run.json").read_text()) == job  # the job's record, kept
    finally:
        run.close()
