"""From the CLI alone: export a checkpoint to .onnx and .pt2, then attack each file white-box.

No Python is written by the user: ``advobj policy export`` writes both files with the card inside,
and ``advobj attack run --policy FILE`` converts the ONNX file (checked against onnxruntime) or
loads the ExportedProgram, and runs the same attack as on the checkpoint.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from trials.cli.main import app

TINY = {
    "iterations": 1,
    "num_envs": 2,
    "rollout_steps": 1,
    "texture_size": 8,
    "pool_size": 4,
    "validation_every": 0,
    "checkpoint_every": 1,
}


@pytest.fixture(scope="module")
def files(tiny_policy_dir, tmp_path_factory):
    d = tmp_path_factory.mktemp("export")
    res = CliRunner().invoke(
        app, ["policy", "export", str(tiny_policy_dir), "--onnx", str(d / "p.onnx"), "--pt2", str(d / "p.pt2")]
    )
    assert res.exit_code == 0, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 2 and "max |onnx - torch|" in lines[0] and "max |pt2 - torch|" in lines[1]
    return d / "p.onnx", d / "p.pt2"


def test_policy_export_writes_both_files_and_refuses_a_wrong_suffix(files, tiny_policy_dir, tmp_path):
    onnx_path, pt2_path = files
    assert onnx_path.stat().st_size > 0 and pt2_path.stat().st_size > 0
    res = CliRunner().invoke(app, ["policy", "export", str(tiny_policy_dir), "--pt2", str(tmp_path / "p.onnx")])
    assert res.exit_code == 2 and not (tmp_path / "p.onnx").exists()


def _attack(policy, out, cfg):
    res = CliRunner().invoke(app, ["attack", "run", "--policy", str(policy), "--config", str(cfg), "--out", str(out)])
    assert res.exit_code == 0, res.output
    return np.load(out / "texture.npy"), json.loads((out / "metrics.json").read_text())


def test_attack_run_on_each_file_gives_the_checkpoints_texture(files, tiny_policy_dir, tmp_path):
    cfg = tmp_path / "attack.yaml"
    cfg.write_text(yaml.safe_dump(TINY))
    ref, _ = _attack(tiny_policy_dir, tmp_path / "ckpt", cfg)
    for f in files:
        tex, metrics = _attack(f, tmp_path / f.suffix[1:], cfg)
        assert np.isfinite(tex).all()
        np.testing.assert_allclose(tex, ref, atol=1e-4)  # same seeds, same gradients to float tolerance
        assert json.loads((tmp_path / f.suffix[1:] / "run.json").read_text())["config"]["policy"] == str(f)


def test_a_joint_space_checkpoint_exports_to_both_files_checked_on_random_states_too(tmp_path):
    """The export's check fed images only, so a policy reading joint positions failed it (state: no
    state given) and could not be exported from the CLI."""
    from pathlib import Path

    from sim.policies.checkpoint import save_checkpoint
    from sim.policies.onnx_policy import OnnxPolicy
    from sim.policies.pt2 import load_pt2
    from sim.spec import load_spec
    from tests.attack.test_joint_attack import joint_policy
    from tests.policy_zoo import card_of

    spec = load_spec(Path(__file__).resolve().parents[3] / "scenes" / "panda-joint.yaml")
    policy = joint_policy(spec)
    save_checkpoint(tmp_path / "ck", policy, card_of(policy))
    files = ["--onnx", str(tmp_path / "j.onnx"), "--pt2", str(tmp_path / "j.pt2")]
    res = CliRunner().invoke(app, ["policy", "export", str(tmp_path / "ck"), *files])
    assert res.exit_code == 0, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 2 and all("state (B, 7), output actions (B, 7)" in line for line in lines), lines
    assert all("on 32 random images and states" in line for line in lines), lines
    # the files act as the checkpoint does on the same images and joint states
    rng = np.random.default_rng(1)
    x = rng.random((4, 3, 32, 32), dtype=np.float32)
    q = rng.uniform(-1, 1, (4, 7)).astype(np.float32)
    want = policy.act(x, q)
    for got in (OnnxPolicy(tmp_path / "j.onnx").act(x, q), load_pt2(tmp_path / "j.pt2").act(x, q)):
        assert got.shape == (4, 7) and np.abs(got - want).max() < 1e-4
