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
