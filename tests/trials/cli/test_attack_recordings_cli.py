"""``advobj attack run --recordings DIR`` from the command line (``trials.cli.main.main`` in-process):
a tiny attack on a recording written from the simulator writes the texture folder ``advobj attack
run`` always writes, with the recording's manifest hash and episode split in ``run.json``, and never
builds a simulator env; each bad recording is one line with exit code 2, writing nothing."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from sim.geometry import make_T, so3_exp
from sim.spec import default_scene
from tests.attack.recordings_helpers import sim_recording
from tests.trials.cli.test_record_import import _run, _tree  # the CLI run and tree snapshot of record import

TINY = {
    "iterations": 2,
    "num_envs": 1,
    "rollout_steps": 2,
    "texture_size": 8,
    "checkpoint_every": 1,
    "validation_every": 1,
    "validation_episodes": 2,
}


def _args(policy, recordings, out, config, *more) -> list[str]:
    return [
        "attack",
        "run",
        "--policy",
        str(policy),
        "--preset",
        "quick",
        "--config",
        str(config),
        "--recordings",
        str(recordings),
        "--out",
        str(out),
        *more,
    ]


@pytest.fixture()
def config(tmp_path):
    path = tmp_path / "attack.yaml"
    path.write_text(yaml.safe_dump(TINY))
    return path


def test_an_attack_on_recordings_writes_the_texture_folder_and_what_it_ran_on(
    monkeypatch, capsys, tmp_path, tiny_policy_dir, config
):
    import attack.optimize
    import sim.env

    def refuse(*_a, **_k):
        raise AssertionError("the recordings attack built a simulator env")

    monkeypatch.setattr(sim.env.ReachEnv, "__init__", refuse)
    monkeypatch.setattr(attack.optimize, "ReachEnv", refuse)
    rec = sim_recording(tmp_path / "rec", default_scene(), size=32, episodes=3, steps=2)
    code, out, err = _run(monkeypatch, capsys, _args(tiny_policy_dir, rec.path, tmp_path / "atk", config))
    assert code == 0, err
    atk = tmp_path / "atk"
    for name in ("texture.png", "texture.npy", "run.json", "configs.json", "metrics.json", "best", "checkpoint"):
        assert (atk / name).exists(), name
    ran = json.loads((atk / "run.json").read_text())["config"]
    want = hashlib.sha256((rec.path / "recording.json").read_bytes()).hexdigest()
    assert ran["recordings"]["manifest_sha256"] == want
    assert ran["recordings"]["training_episodes"] == ["ep0", "ep1"]
    assert ran["recordings"]["held_out_episodes"] == ["ep2"]
    assert ran["attack"]["recordings"] == str(rec.path) and ran["pool"] is None
    metrics = json.loads((atk / "metrics.json").read_text())
    assert metrics["validation"]["measure"].startswith("toward fraction")
    assert "held-out validation toward fraction" in out


def _looking_away(tmp_path):
    upside_down = make_T(so3_exp(np.array([math.pi, 0.0, 0.0])), np.array([0.0, 0.0, 1.0]))
    rec = sim_recording(tmp_path / "rec", default_scene(), size=32, episodes=3, steps=1, T_table_base=upside_down)
    return rec.path, [], "frames with no table visible: no frame of the training episodes shows the region"


def _no_wrist_camera(tmp_path):
    rec = sim_recording(tmp_path / "rec", default_scene(), size=32, episodes=3, steps=1, names={"wrist": "hand"})
    return rec.path, [], "the policy reads camera 'wrist', which the recording does not have (it has hand)"


def _front_policy(tmp_path, front_wh):
    """A wrist + front policy reading front at 32 x 64 px (H x W) and its scene (front at that size),
    and a recording of the same cell whose front camera is ``front_wh`` px."""
    from sim.policies.card import ActionScaling, PolicyCard
    from sim.policies.checkpoint import save_checkpoint
    from sim.policies.policy import VisuomotorPolicy

    def scene(w, h):
        d = default_scene().model_dump(mode="json")
        look = {"eye_m": [0.33, -0.57, 0.51], "target_m": [0.0, 0.0, 0.05]}
        d["scene_cameras"] = [{"name": "front", "width": w, "height": h, "fov_deg": 60, "look_at": look}]
        return d

    from sim.spec import scene_from_dict

    (tmp_path / "scene.yaml").write_text(yaml.safe_dump(scene(64, 32)))
    torch.manual_seed(0)
    p = VisuomotorPolicy(arch="small_cnn", image_size=32, cameras=("wrist", "front"), camera_px={"front": (32, 64)})
    d = tmp_path / "policy"
    save_checkpoint(d, p, PolicyCard(arch=p.config, action=ActionScaling(max_step_m=0.02, max_step_rad=0.1)))
    spec = scene_from_dict(scene(*front_wh))
    rec = sim_recording(tmp_path / "rec", spec, size=32, episodes=3, steps=1, cameras=("wrist", "front"))
    return d, rec.path


def _wrong_size(tmp_path):
    policy, rec = _front_policy(tmp_path, (64, 64))
    more = ["--scene", str(tmp_path / "scene.yaml")]
    return rec, more, "camera front: frames of 64x64 px, the policy reads 64x32 px from it", policy


def _pool_too(tmp_path):
    rec = sim_recording(tmp_path / "rec", default_scene(), size=32, episodes=3, steps=1)
    (tmp_path / "pool.json").write_text("{}")
    return rec.path, ["--pool", str(tmp_path / "pool.json")], "--pool: an attack on --recordings draws no simulator"


def _one_episode(tmp_path):
    rec = sim_recording(tmp_path / "rec", default_scene(), size=32, episodes=1, steps=1)
    return rec.path, [], "1 episode; validation holds whole episodes out, so it needs at least 2"


@pytest.mark.parametrize("bad", [_looking_away, _no_wrist_camera, _wrong_size, _pool_too, _one_episode])
def test_a_bad_recording_is_one_line_exit_2_and_writes_nothing(
    monkeypatch, capsys, tmp_path, tiny_policy_dir, config, bad
):
    made = bad(tmp_path)
    rec, more, expect = made[:3]
    policy = made[3] if len(made) > 3 else tiny_policy_dir
    before = _tree(tmp_path), _tree(Path(policy))
    monkeypatch.chdir(tmp_path)
    code, _, err = _run(monkeypatch, capsys, _args(policy, rec, tmp_path / "atk", config, *more))
    assert code == 2
    assert len(err) == 1 and err[0].startswith("error: ") and "Traceback" not in err[0], err
    assert expect in err[0], err[0]
    assert not (tmp_path / "atk").exists()
    assert (_tree(tmp_path), _tree(Path(policy))) == before  # nothing written, in --out or anywhere
