"""Policy files that claim absurd shapes are refused in one line naming the file, before any work."""

from __future__ import annotations

import sys

import onnx
import pytest
from onnx import TensorProto, helper

from sim.policies.interface import IMAGE_SIZE_MAX_PX, IMAGE_SIZE_MIN_PX, PolicyError
from sim.policies.onnx_policy import OnnxPolicy


def _graph_of_size(path, size: int) -> None:
    """A valid ONNX policy (image -> 6 actions) whose image input is fixed at ``size`` px."""
    image = helper.make_tensor_value_info("image", TensorProto.FLOAT, ["B", 3, size, size])
    action = helper.make_tensor_value_info("action", TensorProto.FLOAT, ["B", 6])
    nodes = [
        helper.make_node("GlobalAveragePool", ["image"], ["pooled"]),
        helper.make_node("Flatten", ["pooled"], ["flat"]),
        helper.make_node("Concat", ["flat", "flat"], ["action"], axis=1),
    ]
    model = helper.make_model(
        helper.make_graph(nodes, "g", [image], [action]), opset_imports=[helper.make_opsetid("", 17)]
    )
    onnx.checker.check_model(model)
    onnx.save(model, str(path))


@pytest.mark.parametrize("size", [1, IMAGE_SIZE_MIN_PX - 1, IMAGE_SIZE_MAX_PX + 1, 1 << 20])
def test_an_onnx_input_size_outside_the_render_range_is_one_error_naming_the_file(tmp_path, size):
    path = tmp_path / "absurd.onnx"
    _graph_of_size(path, size)
    with pytest.raises(PolicyError) as err:
        OnnxPolicy(path)
    msg = str(err.value)
    assert str(path) in msg and f"{size} px" in msg and "EnvConfig" not in msg and "\n" not in msg


def test_an_onnx_input_size_inside_the_range_loads(tmp_path):
    path = tmp_path / "ok.onnx"
    _graph_of_size(path, IMAGE_SIZE_MIN_PX)
    assert OnnxPolicy(path).image_size == IMAGE_SIZE_MIN_PX


def test_policy_eval_of_an_absurd_onnx_exits_2_with_one_line_naming_the_file(tmp_path, monkeypatch, capsys):
    from trials.cli.main import main

    path = tmp_path / "absurd.onnx"
    _graph_of_size(path, 100_000)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["advobj", "policy", "eval", str(path), "--episodes", "2", "--out", "o"])
    with pytest.raises(SystemExit) as ex:
        main()
    err = capsys.readouterr().err.strip()
    assert ex.value.code == 2
    assert len(err.splitlines()) == 1 and str(path) in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_a_policy_card_nested_100000_deep_is_one_error_naming_the_file(tmp_path):
    from sim.policies.card import CARD_NAME, load_card

    d = tmp_path / "ckpt"
    d.mkdir()
    (d / CARD_NAME).write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(PolicyError, match="nested too deeply") as err:
        load_card(d)
    assert str(d / CARD_NAME) in str(err.value)
