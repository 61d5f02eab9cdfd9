"""The one YAML reader: every hostile file gives one line naming the file, in the caller's error kind."""

from __future__ import annotations

import numpy as np
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
    from robot_io.config import load_hardware_config, load_T_tcp_cam
    from sim.spec import SpecError, load_scene
    from trials.real.operator import AnswersError, load_answers
    from trials.real.plan import PlanError, load_plan

    return {
        "scene": (load_scene, SpecError),
        "hardware": (load_hardware_config, HardwareConfigError),
        "plan": (load_plan, PlanError),
        "answers": (load_answers, AnswersError),
        "camera": (load_camera_yaml, CalibrationFileError),
        "T_tcp_cam": (load_T_tcp_cam, CalibrationFileError),
    }


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


def test_a_scene_texture_outside_the_scene_folder_is_refused(tmp_path):
    import yaml

    from sim.spec import SpecError, default_scene, load_scene

    outside = tmp_path / "secret.png"
    outside.write_bytes(b"\x89PNG")
    d = tmp_path / "scene"
    d.mkdir()
    doc = default_scene().model_dump(mode="json")
    for bad in ("../secret.png", str(outside)):
        doc["table"]["texture"] = bad
        (d / "scene.yaml").write_text(yaml.safe_dump(doc))
        with pytest.raises(SpecError, match=r"table.texture: texture .* lies outside the scene file's folder"):
            load_scene(d / "scene.yaml")
    (d / "wood.png").write_bytes(b"\x89PNG")
    doc["table"]["texture"] = "wood.png"
    (d / "scene.yaml").write_text(yaml.safe_dump(doc))
    assert load_scene(d / "scene.yaml").table.texture == str((d / "wood.png").resolve())


def test_an_obj_whose_mtllib_or_texture_leaves_its_folder_is_refused(tmp_path):
    from sim.assets import AssetError, load_mesh_file

    (tmp_path / "evil.mtl").write_text("newmtl m\nmap_Kd tex.png\n")
    d = tmp_path / "mesh"
    d.mkdir()
    body = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
    (d / "a.obj").write_text("mtllib ../evil.mtl\n" + body)
    with pytest.raises(AssetError, match="mtllib '../evil.mtl' lies outside the mesh's folder"):
        load_mesh_file(d / "a.obj")
    (d / "ok.mtl").write_text("newmtl m\nmap_Kd /etc/hostname\n")
    (d / "b.obj").write_text("mtllib ok.mtl\n" + body)
    with pytest.raises(AssetError, match="map_Kd '/etc/hostname' lies outside"):
        load_mesh_file(d / "b.obj")


def test_a_training_state_holding_a_pickle_is_refused_in_one_line_and_never_run(tmp_path):
    import pickle

    import torch

    from sim.policies.dagger import _State
    from sim.policies.interface import PolicyError
    from sim.policies.policy import VisuomotorPolicy

    policy = VisuomotorPolicy(arch="small_cnn", image_size=32)
    opt = torch.optim.Adam(policy.parameters())
    state = _State(tmp_path)
    state.save(policy, opt, np.zeros((1, 32, 32, 3), np.uint8), np.zeros((1, 6), np.float32), {"iteration": 1})
    marker = tmp_path / "ran"

    class Evil:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    (state.dir / "optim.pt").write_bytes(pickle.dumps(Evil()))
    with pytest.raises(PolicyError, match="cannot resume training from this state") as exc:
        state.load(policy, opt)
    assert "\n" not in str(exc.value) and not marker.exists()


def test_a_hand_eye_rotation_vector_of_1e200_is_refused_naming_the_field(tmp_path):
    from pathlib import Path

    import yaml

    from calibration.handeye import load_samples_yaml
    from calibration.io import CalibrationFileError

    doc = yaml.safe_load(
        (Path(__file__).resolve().parents[2] / "examples" / "calibration" / "handeye_samples.yaml").read_text()
    )
    doc["samples"][0]["T_base_tcp"]["rotvec_rad"] = [1e200, 0.0, 0.0]
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(CalibrationFileError, match=r"samples.0.T_base_tcp.rotvec_rad: norm must be at most 100 rad"):
        load_samples_yaml(tmp_path / "s.yaml")


def test_a_photo_of_another_size_than_the_camera_file_is_one_line_naming_it(tmp_path, monkeypatch, capsys):
    from pathlib import Path

    import imageio.v3 as iio

    from trials.cli.main import main

    root = Path(__file__).resolve().parents[2] / "examples" / "calibration"
    iio.imwrite(tmp_path / "small.png", np.zeros((240, 320, 3), np.uint8))
    monkeypatch.setattr(
        "sys.argv",
        [
            "advobj",
            "calibrate",
            "detect",
            str(tmp_path / "small.png"),
            "--camera",
            str(root / "cam.yaml"),
            "--registry",
            str(root / "objects.yaml"),
        ],
    )
    with pytest.raises(SystemExit) as exc:
        main()
    err = [l for l in capsys.readouterr().err.splitlines() if l.strip()]
    assert (
        exc.value.code == 2
        and len(err) == 1
        and "small.png" in err[0]
        and "320x240 does not match the camera file's 640x480" in err[0]
    )
    assert "same aspect ratio" in err[0]
