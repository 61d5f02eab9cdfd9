"""Policy files the attack cannot go through are one line on stderr, exit 2, and nothing written.

The CLI runs in-process (``trials.cli.main.main`` with ``sys.argv`` patched), as a user would call
``advobj attack run --policy FILE`` or ``advobj policy eval FILE``; the files are real ONNX graphs
run by onnxruntime and real .pt2 archives (tests/policy_files.py).
"""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path

import pytest

from tests.policy_files import garbage_pt2, mismatched_onnx, other_torch_pt2, truncated_pt2, unsupported_op_onnx

BAD = {
    "unsupported_op.onnx": (unsupported_op_onnx, "operator 'Shrink'"),
    "mismatch.onnx": (mismatched_onnx, "output 'actions' of the torch conversion differs from onnxruntime by up to"),
    "garbage.pt2": (garbage_pt2, "not a torch.export archive"),
    "truncated.pt2": (truncated_pt2, "not a torch.export archive"),
    "other_torch.pt2": (other_torch_pt2, "exported by an incompatible torch"),
}


def _snapshot(root: Path) -> dict:
    out = {}
    for d, _, files in os.walk(root):
        for f in files:
            p = Path(d) / f
            out[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def _run(argv, tmp_path, monkeypatch, capsys):
    from trials.cli.main import main

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["advobj", *argv])
    with pytest.raises(SystemExit) as ex:
        main()
    return ex.value.code, [line for line in capsys.readouterr().err.splitlines() if line.strip()]


@pytest.mark.parametrize("name", sorted(BAD))
def test_attack_run_on_a_bad_policy_file_is_one_line_exit_2_and_writes_nothing(name, tmp_path, monkeypatch, capsys):
    build, expected = BAD[name]
    path = build(tmp_path / name)
    before = _snapshot(tmp_path)
    code, lines = _run(["attack", "run", "--policy", str(path), "--out", "atk"], tmp_path, monkeypatch, capsys)
    assert code == 2, lines
    assert len(lines) == 1 and expected in lines[0] and str(path) in lines[0], lines
    assert "Traceback" not in lines[0]
    assert _snapshot(tmp_path) == before and not (tmp_path / "atk").exists()


@pytest.mark.parametrize("name", [n for n in sorted(BAD) if n.endswith(".pt2")])
def test_policy_eval_of_a_bad_pt2_is_one_line_exit_2(name, tmp_path, monkeypatch, capsys):
    build, expected = BAD[name]
    path = build(tmp_path / name)
    before = _snapshot(tmp_path)
    argv = ["policy", "eval", str(path), "--episodes", "2", "--out", "ev"]
    code, lines = _run(argv, tmp_path, monkeypatch, capsys)
    assert code == 2 and len(lines) == 1 and expected in lines[0], lines
    assert _snapshot(tmp_path) == before


def test_policy_export_without_a_target_file_is_one_line(tmp_path, monkeypatch, capsys):
    code, lines = _run(["policy", "export", str(tmp_path)], tmp_path, monkeypatch, capsys)
    assert code == 2 and len(lines) == 1 and "--pt2" in lines[0], lines


@pytest.mark.parametrize("name", ["unsupported_op.onnx", "mismatch.onnx"])
def test_a_bad_onnx_with_a_short_pool_is_refused_before_the_pool_is_topped_up(name, tmp_path, monkeypatch, capsys):
    """With a --pool too small for the attack, the job would build more configurations into its output
    folder; the conversion is checked first, so nothing is written."""
    from sim.configs import sample_pool, save_pool
    from sim.spec import default_scene

    build, expected = BAD[name]
    path = build(tmp_path / name)
    save_pool(tmp_path / "short_pool.json", default_scene(), sample_pool(default_scene(), 2, part="attack"))
    before = _snapshot(tmp_path)
    argv = ["attack", "run", "--policy", str(path), "--pool", "short_pool.json", "--out", "atk"]
    code, lines = _run(argv, tmp_path, monkeypatch, capsys)
    assert code == 2 and len(lines) == 1 and expected in lines[0], lines
    assert _snapshot(tmp_path) == before and not (tmp_path / "atk").exists()
