"""The one YAML reader: every hostile file gives one line naming the file, in the caller's error kind."""

from __future__ import annotations

import pytest

from calibration.errors import CalibrationFileError
from robot_io.errors import HardwareConfigError
from sim.configio import ConfigError, read_yaml

HOSTILE = {
    "binary": bytes(range(256)) * 8,
    "nul": b"a: 1\n\x00\x00\x00",
    "latin1": "name: caf\xe9\n".encode("latin-1"),
    "malformed": b"a: [1, 2\nb: }\n",
    "deep_flow": b"a: " + b"[" * 5000 + b"]" * 5000 + b"\n",
    "deep_block": "".join(f"{'  ' * i}k:\n" for i in range(990)).encode() + b"  " * 990 + b"v\n",
    "empty": b"",
    "list": b"- 1\n- 2\n",
    "scalar": b"42\n",
}


def _loaders():
    from calibration.intrinsics import load_camera_yaml
    from robot_io.config import load_T_tcp_cam, load_hardware_config
    from sim.spec import SpecError, load_scene
    from trials.real.operator import AnswersError, load_answers
    from trials.real.plan import PlanError, load_plan

    return {"scene": (load_scene, SpecError), "hardware": (load_hardware_config, HardwareConfigError),
            "plan": (load_plan, PlanError), "answers": (load_answers, AnswersError),
            "camera": (load_camera_yaml, CalibrationFileError), "T_tcp_cam": (load_T_tcp_cam, CalibrationFileError)}


@pytest.mark.parametrize("loader", sorted(_loaders()))
@pytest.mark.parametrize("kind", sorted(HOSTILE) + ["missing", "directory"])
def test_every_loader_refuses_hostile_files_in_one_line(tmp_path, loader, kind):
    load, error = _loaders()[loader]
    if kind == "missing":
        path = tmp_path / "absent.yaml"
    elif kind == "directory":
        path = tmp_path / "dir.yaml"
        path.mkdir()
    else:
        path = tmp_path / f"{kind}.yaml"
        path.write_bytes(HOSTILE[kind])
    if loader == "answers" and kind in ("list", "empty"):
        pytest.skip("an answers file may be a list; an empty one is refused by its own check")
    with pytest.raises(error) as info:
        load(path)
    msg = str(info.value)
    assert str(path) in msg and "\n" not in msg and len(msg) < 300, msg


def test_read_yaml_names_the_kind_of_file(tmp_path):
    p = tmp_path / "x.yaml"
    p.write_bytes(b"\xff\xfe")
    with pytest.raises(ConfigError, match=r"x\.yaml: not a widget config: not UTF-8"):
        read_yaml(p, "widget config")
    p.write_text("a: 1\n")
    assert read_yaml(p, "widget config") == {"a": 1}
