"""The attack through several cameras: the texture rendered into every camera the policy reads, the loss through all.

A tiny two-camera policy (tests.policy_zoo.TwoCameraPolicy: wrist 32 px + the two-camera scene's
128 px "front" camera + state) is exported here to .onnx and .pt2 with LeRobot's input names and
attacked white-box from the CLI and from Python; nothing is downloaded.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch
import yaml
from typer.testing import CliRunner

from attack.losses import pose_loss
from attack.optimize import AttackRun, resolve_config
from sim.configs import sample_pool
from sim.policies.checkpoint import load_policy
from sim.policies.graph_policy import GraphPolicy
from sim.policies.onnx_policy import OnnxPolicy
from sim.spec import load_spec
from tests.policy_files import two_camera_onnx, two_camera_pt2
from tests.policy_zoo import TwoCameraPolicy, two_camera_card
from trials.cli.main import app, main

TWO_CAMERAS = "scenes/two-cameras.yaml"
TINY = {
    "iterations": 2,
    "num_envs": 2,
    "rollout_steps": 1,
    "texture_size": 8,
    "pool_size": 4,
    "validation_every": 0,
    "checkpoint_every": 1,
}


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("two-cameras")
    p = TwoCameraPolicy(seed=3)  # its wrist Grad-CAM is not all zero on these frames (seed 0's is)
    card = two_camera_card()
    return two_camera_onnx(d / "p.onnx", p, card), two_camera_pt2(d / "p.pt2", p, card)


def _iteration_grads(run) -> dict:
    """Each objective term's texture gradient summed over one iteration's frames (as attack_step)."""
    st = run.state
    run.source.start(st.iteration, st.rng)
    total: dict = {}
    while (frames := run.source.next()) is not None:
        out = run.frame_gradients(st, frames)
        assert set(out["images"]) == {"wrist", "front"}
        for k, g in out["grads"].items():
            total[k] = total.get(k, 0) + g
        run.source.advance(out["actions"].cpu().numpy())
    return total


def test_attack_run_from_the_cli_on_the_two_camera_scene_gives_the_same_texture_through_onnx_and_pt2(files, tmp_path):
    cfg = tmp_path / "attack.yaml"
    cfg.write_text(yaml.safe_dump(TINY))
    textures = []
    for f in files:
        out = tmp_path / f.suffix[1:]
        res = CliRunner().invoke(
            app,
            ["attack", "run", "--policy", str(f), "--scene", TWO_CAMERAS, "--config", str(cfg), "--out", str(out)],
        )
        assert res.exit_code == 0, res.output
        textures.append(np.load(out / "texture.npy"))
        assert (out / "gradcam_before_after.png").is_file() and (out / "rollout_strip.png").is_file()
    assert all(np.isfinite(t).all() for t in textures)
    np.testing.assert_allclose(textures[0], textures[1], atol=1e-4)


@pytest.mark.parametrize("fmt", ["onnx", "pt2"])
def test_a_two_camera_attack_on_a_scene_without_the_front_camera_is_one_line_with_exit_2(
    files, tmp_path, monkeypatch, capsys, fmt
):
    cfg = tmp_path / "attack.yaml"
    cfg.write_text(yaml.safe_dump(TINY))
    out = tmp_path / "out"
    policy = files[0] if fmt == "onnx" else files[1]
    monkeypatch.setattr(
        sys, "argv", ["advobj", "attack", "run", "--policy", str(policy), "--config", str(cfg), "--out", str(out)]
    )
    with pytest.raises(SystemExit) as exit_:
        main()
    err = capsys.readouterr().err.strip()
    assert exit_.value.code == 2 and len(err.splitlines()) == 1
    assert "unknown camera 'front'; this scene has: wrist" in err and not out.exists()


@pytest.fixture(scope="module")
def grads(files):
    spec = load_spec(TWO_CAMERAS)
    pool = sample_pool(spec, 8, seed=5, part="attack")
    cfg = resolve_config("quick", {"num_envs": 4, "rollout_steps": 1, "texture_size": 16, "validation_every": 0})
    out = {}
    for name, policy in (("onnx", OnnxPolicy(files[0])), ("pt2", load_policy(files[1]))):
        run = AttackRun(policy, spec, cfg, pool=pool)
        try:
            assert isinstance(run.policy, GraphPolicy) and run.cameras == ("wrist", "front")
            assert run.saliency_camera == "wrist" and set(run.env.renderers) == {"wrist", "front"}
            out[name] = _iteration_grads(run)
        finally:
            run.close()
    return out


def test_texture_gradients_through_two_cameras_are_finite_and_agree_between_onnx_and_pt2(grads):
    ref = grads["onnx"]
    assert set(ref) == {"pose", "saliency"}
    for term, g in ref.items():
        assert torch.isfinite(g).all() and float(g.abs().max()) > 0, term
        other = grads["pt2"][term]
        assert torch.isfinite(other).all()
        diff = float((other - g).abs().max())
        assert diff <= 1e-3 * float(g.abs().max()), f"{term}: pt2 differs by {diff:.3g}"


def test_the_pose_loss_reaches_the_texture_through_each_camera(files):
    spec = load_spec(TWO_CAMERAS)
    pool = sample_pool(spec, 8, seed=5, part="attack")
    cfg = resolve_config("quick", {"num_envs": 4, "rollout_steps": 1, "texture_size": 16, "validation_every": 0})
    run = AttackRun(load_policy(files[1]), spec, cfg, pool=pool)
    try:
        run.source.start(0, run.state.rng)
        frames = run.source.next()
        assert set(frames.views) == {"wrist", "front"} and frames.captures is frames.views["wrist"]
        ep = spec.episode
        per_camera = {}
        for cam in ("wrist", "front"):
            tex = run.state.texture.detach().clone().requires_grad_(True)
            imgs = run.render_views(frames.views, tex)
            imgs = {k: v if k == cam else v.detach() for k, v in imgs.items()}  # the texture in one camera only
            a = run.next_delta(run.call_policy(imgs, run.policy_state(frames.T_world_tcp)), frames.T_world_tcp)
            lp, _ = pose_loss(frames.T_world_tcp, a, frames.p_adv, ep.max_step_m, ep.max_step_rad, cfg.lambda_dist)
            (g,) = torch.autograd.grad(lp.sum(), tex)
            per_camera[cam] = g
        assert all(torch.isfinite(g).all() and float(g.abs().max()) > 0 for g in per_camera.values())
    finally:
        run.close()
