"""The built-in network on two cameras (wrist + the two-camera scene's 128 px "front"): its shapes,
its files, its card, its training by DAgger, the attack's gradients through both cameras, and the
refusals; and that the one-camera network it extends is unchanged.

The policies here are untrained small CNNs at 32 px (the front camera's 128 px frames are averaged
down 4x4 inside the network); nothing is downloaded.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError
from typer.testing import CliRunner

from sim.configs import sample_pool
from sim.policies.card import CARD_NAME, ActionScaling, PolicyCard
from sim.policies.checkpoint import load_checkpoint, load_policy, save_checkpoint
from sim.policies.contract import call_policy, check_scene, policy_cameras
from sim.policies.dagger import DaggerConfig, train_dagger
from sim.policies.graph_policy import GraphPolicy
from sim.policies.interface import PolicyError
from sim.policies.onnx_policy import OnnxPolicy, export_onnx
from sim.policies.policy import PolicyArch, VisuomotorPolicy, scene_camera_px
from sim.policies.presets import resolve_preset
from sim.policies.pt2 import export_pt2, load_pt2
from sim.policies.rollout import EnvConfig, make_env, run_episodes
from sim.spec import UnknownCameraError, default_scene, load_spec

TWO_CAMERAS = "scenes/two-cameras.yaml"
S = 32


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)  # the renderer shares the CPU (tests/sim/test_policies_train.py)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def scene():
    """The two-camera scene with near starts and short episodes: the same task at a test-sized cost."""
    s = load_spec(TWO_CAMERAS)
    return s.with_updates(
        init={**s.init.model_dump(), "r_range_m": (0.25, 0.45)},
        episode={**s.episode.model_dump(), "max_steps": 6},
    )


def _arch(**kw) -> PolicyArch:
    return PolicyArch(arch="small_cnn", image_size=S, cameras=("wrist", "front"), camera_px={"front": (128, 128)}, **kw)


def _two_camera(seed: int = 0) -> VisuomotorPolicy:
    """A two-camera policy with non-trivial BN statistics and actions spread over tanh's range."""
    torch.manual_seed(seed)
    p = VisuomotorPolicy(_arch())
    p.train()
    with torch.no_grad():
        p({"wrist": torch.rand(16, 3, S, S), "front": torch.rand(16, 3, 128, 128)})
        p.mlp[-1].weight.mul_(20.0)
    return p.eval()


def _card(p) -> PolicyCard:
    return PolicyCard(arch=p.config, action=ActionScaling(max_step_m=0.02, max_step_rad=0.1))


def _frames(n: int = 32, seed: int = 1) -> dict:
    rng = np.random.default_rng(seed)
    return {
        "wrist": rng.integers(0, 256, (n, S, S, 3), dtype=np.uint8),
        "front": rng.integers(0, 256, (n, 128, 128, 3), dtype=np.uint8),
    }


# ------------------------------------------------------------------------------ the one-camera network
def test_the_default_arch_is_the_one_camera_network_as_it_was():
    a = PolicyArch(arch="small_cnn", image_size=64)
    assert a.cameras == ("wrist",) and a.camera_px == {} and a.is_one_camera
    # cards, run.json and resume hashes: the default dumps without the new fields
    assert "cameras" not in a.model_dump_json() and "camera_px" not in a.model_dump_json()
    assert PolicyArch.model_validate_json(a.model_dump_json()) == a
    torch.manual_seed(0)
    p = VisuomotorPolicy(a)
    # pinned: the parameter names and shapes of the network before cameras existed
    keys = [k for k in p.state_dict() if not k.startswith("backbone.")]
    assert keys == [
        "mean",
        "std",
        "reduce.0.weight",
        "reduce.0.bias",
        *(f"mlp.{i}.{w}" for i in (1, 3) for w in ("weight", "bias")),
    ]
    assert tuple(p.mlp[1].weight.shape) == (256, 32 * 8 * 8) and hasattr(p, "backbone") and not hasattr(p, "backbones")
    assert p.inputs.cameras == ("wrist",) and [b.name for b in p.inputs.images] == ["images"]
    x = torch.rand(2, 3, 64, 64)
    assert torch.equal(p.features(x), p.backbone((x - p.mean) / p.std))
    assert resolve_preset("quick", cameras=("wrist",)).fingerprint() == resolve_preset("quick").fingerprint()


# ------------------------------------------------------------------------------ shapes
def test_two_camera_features_head_and_act_shapes():
    p = _two_camera()
    x = {"wrist": torch.rand(3, 3, S, S), "front": torch.rand(3, 3, 128, 128)}
    A = p.features(x)
    assert set(A) == {"wrist", "front"} and all(tuple(a.shape) == (3, *p.feature_shape) for a in A.values())
    assert tuple(p.head(A).shape) == (3, 6) and torch.equal(p.head(A), p(x))
    a = p.act(_frames(5))
    assert a.shape == (5, 6) and a.dtype == np.float32 and np.isfinite(a).all() and (np.abs(a) <= 1).all()
    # the contract's helpers read the plan: one input per camera, named by it
    assert policy_cameras(p) == ("wrist", "front") and p.inputs.order == ("wrist", "front")
    assert np.array_equal(call_policy(p, {**_frames(5), "other": None}, None), a)
    # a camera of its own each: separate weights, and the front camera's frame averaged down to 32 px
    assert set(p.backbones) == {"wrist", "front"} and p.backbones["wrist"] is not p.backbones["front"]
    f = x["front"]
    want = p.backbones["front"]((torch.nn.functional.avg_pool2d(f, 4) - p.mean) / p.std)
    assert torch.allclose(A["front"], want)


def test_two_camera_inputs_given_wrongly_are_one_line_naming_the_camera():
    p = _two_camera()
    with pytest.raises(PolicyError, match=r"pass \{camera: images\}"):
        p.act(_frames(2)["wrist"])
    with pytest.raises(PolicyError, match="no images of 'front'"):
        p.act({"wrist": _frames(2)["wrist"]})
    with pytest.raises(PolicyError, match=r"expects \(B, 3, 128, 128\) float in \[0, 1\] from camera 'front'"):
        p.features({"wrist": torch.rand(2, 3, S, S), "front": torch.rand(2, 3, 64, 64)})
    with pytest.raises(PolicyError, match="policy expects 128x128 px, got 96x96"):
        p.act({"wrist": _frames(2)["wrist"], "front": np.zeros((2, 96, 96, 3), np.uint8)})


@pytest.mark.parametrize(
    "kw, msg",
    [
        (dict(cameras=("wrist", "front")), "no size for camera 'front'"),
        (dict(cameras=("wrist",), camera_px={"front": (128, 128)}), "sizes of cameras it does not read"),
        (dict(cameras=("wrist", "front"), camera_px={"front": (100, 128)}), "100x128 px is not a whole multiple"),
        (dict(cameras=("wrist", "wrist")), "name each camera once"),
        (dict(cameras=()), "at least 1"),
    ],
)
def test_an_arch_whose_cameras_do_not_fit_is_refused_naming_the_field(kw, msg):
    with pytest.raises(ValidationError, match=msg):
        PolicyArch(arch="small_cnn", image_size=S, **kw)


@settings(max_examples=8, deadline=None)
@given(k_h=st.integers(1, 4), k_w=st.integers(1, 4), value=st.sampled_from([0, 255]))
def test_any_whole_multiple_camera_size_gives_the_backbones_map_and_finite_actions_at_extreme_pixels(k_h, k_w, value):
    a = PolicyArch(arch="small_cnn", image_size=S, cameras=("front", "wrist"), camera_px={"front": (S * k_h, S * k_w)})
    p = VisuomotorPolicy(a).eval()
    frames = {
        "front": np.full((2, S * k_h, S * k_w, 3), value, np.uint8),
        "wrist": np.full((2, S, S, 3), value, np.uint8),
    }
    A = p.features({k: torch.from_numpy(v).permute(0, 3, 1, 2) / 255.0 for k, v in frames.items()})
    assert tuple(A["front"].shape) == tuple(A["wrist"].shape) == (2, *p.feature_shape)
    out = p.act(frames)
    assert np.isfinite(out).all() and (np.abs(out) <= 1).all()


# ------------------------------------------------------------------------------ card, checkpoint, files
@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    d = tmp_path_factory.mktemp("two-camera")
    p = _two_camera()
    card = save_checkpoint(d / "ck", p, _card(p))
    return p, d / "ck", export_onnx(p, d / "p.onnx", card=card), export_pt2(p, d / "p.pt2", card=card)


def test_the_card_records_the_cameras_and_the_checkpoint_round_trips(exported):
    p, ck, *_ = exported
    doc = json.loads((ck / CARD_NAME).read_text())
    assert doc["arch"]["cameras"] == ["wrist", "front"] and doc["arch"]["camera_px"] == {"front": [128, 128]}
    q, card = load_checkpoint(ck)
    assert card.arch == p.config and q.cameras == ("wrist", "front")
    x = _frames(4)
    assert np.array_equal(p.act(x), q.act(x))


def test_onnx_and_pt2_name_one_image_input_per_camera_and_load_back_to_the_same_actions(exported):
    p, ck, onnx_path, pt2_path = exported
    x, ref = _frames(32), p.act(_frames(32))
    onnx = OnnxPolicy(onnx_path)
    assert [i.name for i in onnx.session.get_inputs()] == ["wrist", "front"]
    assert onnx.inputs.cameras == ("wrist", "front") and set(onnx.card.inputs) == {"wrist", "front"}
    assert set(onnx.card.feature_map) == {"wrist", "front"} and onnx.card.arch.cameras == ("wrist", "front")
    np.testing.assert_allclose(onnx.act(x), ref, atol=1e-5)
    pt2 = load_pt2(pt2_path)
    assert pt2.cameras == ("wrist", "front") and set(pt2.feature_map) == {"wrist", "front"}
    np.testing.assert_allclose(pt2.act(x), ref, atol=1e-5)
    # load_policy with the two-camera scene: the .onnx converted white-box (checked against onnxruntime)
    white = load_policy(onnx_path, white_box=True, spec=load_spec(TWO_CAMERAS))
    assert isinstance(white, GraphPolicy) and white.cameras == ("wrist", "front")
    np.testing.assert_allclose(white.act(x), ref, atol=1e-5)
    # each camera's feature map is the checkpoint's
    views = {k: torch.from_numpy(v[:4]).permute(0, 3, 1, 2) / 255.0 for k, v in x.items()}
    with torch.no_grad():
        for cam, A in p.features(views).items():
            torch.testing.assert_close(pt2.features(views)[cam], A, atol=1e-5, rtol=1e-5)


def test_the_policy_export_command_writes_both_files_of_a_two_camera_checkpoint(exported, tmp_path):
    from trials.cli.main import app

    _, ck, *_ = exported
    res = CliRunner().invoke(
        app, ["policy", "export", str(ck), "--onnx", str(tmp_path / "a.onnx"), "--pt2", str(tmp_path / "a.pt2")]
    )
    assert res.exit_code == 0, res.output
    assert "inputs wrist (B, 3, 32, 32), front (B, 3, 128, 128)" in res.output
    assert "max |onnx - torch|" in res.output and "max |pt2 - torch|" in res.output


@pytest.mark.parametrize("fmt", ["checkpoint", "onnx", "pt2"])
def test_a_two_camera_policy_on_a_scene_without_the_front_camera_is_one_line(exported, fmt):
    _, ck, onnx_path, pt2_path = exported
    path = {"checkpoint": ck, "onnx": onnx_path, "pt2": pt2_path}[fmt]
    with pytest.raises(UnknownCameraError, match="unknown camera 'front'; this scene has: wrist") as err:
        load_policy(path, spec=default_scene())
    assert "\n" not in str(err.value)


# ------------------------------------------------------------------------------ the attack through both cameras
def test_the_attack_texture_gradient_flows_through_each_cameras_render(exported):
    from attack.losses import pose_loss
    from attack.optimize import AttackRun, resolve_config

    spec = load_spec(TWO_CAMERAS)
    pool = sample_pool(spec, 8, seed=5, part="attack")
    cfg = resolve_config("quick", {"num_envs": 4, "rollout_steps": 1, "texture_size": 16, "validation_every": 0})
    run = AttackRun(load_checkpoint(exported[1])[0], spec, cfg, pool=pool)
    try:
        assert run.cameras == ("wrist", "front") and run.saliency_camera == "wrist"
        run.source.start(0, run.state.rng)
        frames = run.source.next()
        ep = spec.episode
        for cam in ("wrist", "front"):
            tex = run.state.texture.detach().clone().requires_grad_(True)
            imgs = run.render_views(frames.views, tex)
            imgs = {k: v if k == cam else v.detach() for k, v in imgs.items()}  # the texture in one camera only
            a = run.next_delta(run.call_policy(imgs, run.policy_state(frames.T_world_tcp)), frames.T_world_tcp)
            lp, _ = pose_loss(frames.T_world_tcp, a, frames.p_adv, ep.max_step_m, ep.max_step_rad, cfg.lambda_dist)
            (g,) = torch.autograd.grad(lp.sum(), tex)
            assert torch.isfinite(g).all() and float(g.abs().max()) > 0, cam
        # the whole objective (pose and saliency terms) through the run's own step
        run.source.start(0, run.state.rng)
        out = run.frame_gradients(run.state, run.source.next())
        assert set(out["images"]) == {"wrist", "front"} and set(out["grads"]) == {"pose", "saliency"}
        assert all(torch.isfinite(g).all() for g in out["grads"].values())
    finally:
        run.close()


# ------------------------------------------------------------------------------ DAgger and training
def test_dagger_trains_a_two_camera_policy_for_one_iteration_and_resumes(scene, tmp_path):
    env_cfg = EnvConfig(image_size=S, light="random", background="mixed", noise_std=0.02)
    env = make_env(scene, env_cfg, num_envs=4, cameras=("wrist", "front"))
    cfg = DaggerConfig(iterations=1, episodes_per_iter=4, num_envs=4, grad_steps_per_iter=2, batch_size=4)
    quiet = dict(progress=False, log=lambda *_: None)
    try:
        torch.manual_seed(0)
        train_dagger(VisuomotorPolicy(_arch()), env, cfg, env_cfg, tmp_path, fingerprint="two", **quiet)
        with np.load(tmp_path / "train_state" / "data.npz", allow_pickle=False) as d:
            # the wrist camera's frames where they always were, the front camera's beside them, one per state
            assert sorted(d.files) == ["actions", "images", "images.front"]
            n = len(d["actions"])
            assert n > 0 and d["images"].shape == (n, S, S, 3) and d["images.front"].shape == (n, 128, 128, 3)
        resumed = VisuomotorPolicy(_arch())
        prog = train_dagger(
            resumed, env, cfg.model_copy(update={"iterations": 2}), env_cfg, tmp_path, fingerprint="two", **quiet
        )
        assert [h["iteration"] for h in prog["history"]] == [0, 1] and prog["history"][1]["frames"] > n
        assert np.isfinite(prog["history"][1]["loss"])
        # a one-camera run's state is not this run's: refused before its data are read
        with pytest.raises(PolicyError, match="different config"):
            train_dagger(resumed, env, cfg, env_cfg, tmp_path, fingerprint="one", **quiet)
        # the env must render every camera the policy reads
        wrist_only = make_env(scene, env_cfg, num_envs=4)
        try:
            with pytest.raises(PolicyError, match=r"make it with cameras=\('wrist', 'front'\)"):
                train_dagger(VisuomotorPolicy(_arch()), wrist_only, cfg, env_cfg, tmp_path / "b", **quiet)
        finally:
            wrist_only.close()
    finally:
        env.close()


def test_train_policy_with_two_cameras_writes_a_card_that_loads_and_runs_in_the_two_camera_scene(scene, tmp_path):
    from sim.policies.train import train_policy

    cfg = resolve_preset(
        "ci",
        cameras=("wrist", "front"),
        spec=scene,
        dagger={"iterations": 1, "episodes_per_iter": 4, "num_envs": 4, "grad_steps_per_iter": 2, "batch_size": 4},
        final_eval_episodes=2,
        policy={"image_size": S},
        env={"image_size": S},
    )
    assert cfg.policy.cameras == ("wrist", "front") and cfg.policy.camera_px == {"front": (128, 128)}
    assert cfg.fingerprint() != resolve_preset("ci", policy={"image_size": S}, env={"image_size": S}).fingerprint()
    card = train_policy(cfg, tmp_path, scene, progress=False, log=lambda *_: None)
    assert card.arch.cameras == ("wrist", "front") and card.clean_success.n == 2
    policy, loaded = load_checkpoint(tmp_path)
    assert loaded.arch == card.arch and json.loads((tmp_path / "run.json").read_text())["config"]["policy"][
        "cameras"
    ] == [
        "wrist",
        "front",
    ]
    check_scene(policy, scene)
    env = make_env(scene, EnvConfig(image_size=S), num_envs=2, cameras=policy.cameras)
    try:
        res = run_episodes(env, policy, [0, 1])
    finally:
        env.close()
    assert len(res.success) == 2


def test_presets_size_the_scene_cameras_from_the_scene_and_refuse_what_they_cannot_train(scene):
    assert scene_camera_px(scene, ("wrist", "front")) == {"front": (128, 128)}
    with pytest.raises(UnknownCameraError, match="unknown camera 'side'; this scene has: wrist, front"):
        resolve_preset("quick", cameras=("wrist", "side"), spec=scene)
    with pytest.raises(ValueError, match="pass the scene"):
        resolve_preset("quick", cameras=("wrist", "front"))
    with pytest.raises(ValueError, match="PPO trains the wrist camera alone"):
        resolve_preset("quick", method="ppo", cameras=("wrist", "front"), spec=scene)
    with pytest.raises(ValueError, match="not a whole multiple of image_size"):
        resolve_preset(
            "quick", cameras=("wrist", "front"), spec=scene, policy={"image_size": 48}, env={"image_size": 48}
        )


# ------------------------------------------------------------------------------ the command line
def _cli(monkeypatch, capsys, *args) -> tuple[int, str]:
    from trials.cli.main import main

    monkeypatch.setattr(sys, "argv", ["advobj", *args])
    with pytest.raises(SystemExit) as exit_:
        main()
    return exit_.value.code, capsys.readouterr().err.strip()


def test_training_a_two_camera_policy_on_a_scene_without_that_camera_is_one_line_and_writes_nothing(
    tmp_path, monkeypatch, capsys
):
    out = tmp_path / "out"
    code, err = _cli(
        monkeypatch, capsys, "policy", "train", "--preset", "ci", "--cameras", "wrist,front", "--out", str(out)
    )
    assert code == 2 and len(err.splitlines()) == 1
    assert "--cameras" in err and "unknown camera 'front'; this scene has: wrist" in err
    assert not out.exists()
    code, err = _cli(
        monkeypatch,
        capsys,
        *("policy", "train", "--preset", "ci", "--method", "ppo", "--cameras", "wrist,front"),
        *("--scene", TWO_CAMERAS, "--out", str(out)),
    )
    assert code == 2 and len(err.splitlines()) == 1 and "PPO trains the wrist camera alone" in err
    assert not out.exists()
