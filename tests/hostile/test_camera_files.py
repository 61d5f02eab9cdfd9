"""Hostile camera, pose and calibration inputs: each refused in one line, exit code 2, no traceback.

Camera files in every format (ours, ROS ``camera_info``, OpenCV ``FileStorage`` YAML/JSON) nested
deeply, oversized, or claiming an impossible camera; a hand-eye file whose rotation overflows;
tag id ranges larger than the dictionary; devices and FIFOs where a file belongs. Each CLI case
runs in-process (``trials.cli.main.main`` with ``sys.argv`` patched) under an alarm, so a case that
blocks fails instead of hanging the suite.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from calibration.errors import CalibrationFileError
from calibration.intrinsics import (
    CAMERA_FILE_MAX_BYTES,
    CAMERA_FILE_MAX_DEPTH,
    FOCAL_RANGE,
    MAX_DISTORTION,
    MAX_IMAGE_PX,
    load_camera_yaml,
)
from calibration.io import nesting_depth

CASE_TIMEOUT_S = 20
ROOT = Path(__file__).resolve().parents[2]

ROS = """image_width: {w}
image_height: {h}
camera_name: cam
camera_matrix:
  rows: 3
  cols: 3
  data: [{fx}, 0, {cx}, 0, {fy}, {cy}, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: {nd}
  data: [{dist}]
"""

OPENCV = """%YAML:1.0
---
image_width: {w}
image_height: {h}
camera_matrix: !!opencv-matrix
   rows: {kr}
   cols: {kc}
   dt: d
   data: [{kdata}]
distortion_coefficients: !!opencv-matrix
   rows: 1
   cols: {nd}
   dt: d
   data: [{dist}]
"""

K9 = "500, 0, 320, 0, 500, 240, 0, 0, 1"
OURS = "width: 640\nheight: 480\nK: [[500, 0, 320], [0, 500, 240], [0, 0, 1]]\n"


def _ros(w=640, h=480, fx=500, fy=500, cx=320, cy=240, dist=(0.1, -0.2, 0, 0, 0.05), nd=None) -> str:
    return ROS.format(
        w=w, h=h, fx=fx, fy=fy, cx=cx, cy=cy, nd=len(dist) if nd is None else nd, dist=", ".join(map(str, dist))
    )


def _opencv(w=640, h=480, kr=3, kc=3, kdata=K9, dist=(0.1, -0.2, 0, 0, 0.05), nd=None) -> str:
    return OPENCV.format(
        w=w, h=h, kr=kr, kc=kc, kdata=kdata, nd=len(dist) if nd is None else nd, dist=", ".join(map(str, dist))
    )


class _Timeout(BaseException):
    pass


def _on_alarm(signum, frame):
    raise _Timeout()


def _run(monkeypatch, capsys, *argv: str) -> tuple[int | None, list[str]]:
    """``advobj *argv`` in-process: (exit code, non-empty stderr lines); fails on a traceback or a hang."""
    from trials.cli.main import main

    monkeypatch.setattr(sys, "argv", ["advobj", *argv])
    old = signal.signal(signal.SIGALRM, _on_alarm)
    signal.alarm(CASE_TIMEOUT_S)
    code = None
    try:
        main()
        code = 0
    except SystemExit as err:
        code = err.code if isinstance(err.code, int) else (0 if err.code is None else 1)
    except _Timeout:
        pytest.fail(f"advobj {' '.join(argv)}: still running after {CASE_TIMEOUT_S} s (blocked on its input)")
    except BaseException as err:  # noqa: BLE001 - an escaping exception is a traceback for the user
        pytest.fail(f"advobj {' '.join(argv)}: traceback: {type(err).__name__}: {err}")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    return code, lines


def _refused(monkeypatch, capsys, *argv: str, names: tuple[str, ...]) -> str:
    """Runs ``argv``; asserts exit 2 and one stderr line holding each of ``names``; returns the line."""
    code, lines = _run(monkeypatch, capsys, *argv)
    assert code == 2, (code, lines)
    assert len(lines) == 1, lines
    assert "Traceback" not in lines[0]
    for n in names:
        assert n in lines[0], (n, lines[0])
    return lines[0]


@pytest.fixture
def work(tmp_path, monkeypatch):
    """A scratch working directory with an ``out`` folder; asserts nothing else appears in it."""
    (tmp_path / "out").mkdir()
    monkeypatch.chdir(tmp_path)
    yield tmp_path
    assert not list((tmp_path / "out").iterdir()), "a refused input still wrote an output"


def _convert(monkeypatch, capsys, path: Path, *names: str, extra: tuple[str, ...] = ()) -> str:
    return _refused(
        monkeypatch,
        capsys,
        "calibrate",
        "convert",
        str(path),
        "--out",
        "out/cam.yaml",
        *extra,
        names=(path.name, *names),
    )


# ---------------------------------------------------------------- 1. nesting and size, before parsing


@pytest.mark.parametrize(
    "name, text",
    [
        ("deep.json", '{"camera_matrix": ' + "[" * 1000 + "]" * 1000 + "}"),
        ("deep_flow.yml", "%YAML:1.0\n---\ncamera_matrix: " + "[" * 1000 + "]" * 1000 + "\n"),
        ("deep_block.yml", "%YAML:1.0\n---\ncamera_matrix:\n" + "- " * 1000 + "1\n"),
        ("deep_indent.yaml", "".join(" " * k + f"k{k}:\n" for k in range(1000)) + " " * 1000 + "v: 1\n"),
        ("deep_ros.yaml", "image_width: 640\ncamera_matrix: " + "{a: " * 1000 + "1" + "}" * 1000 + "\n"),
    ],
)
def test_camera_file_nested_1000_deep_is_refused_before_parsing(work, monkeypatch, capsys, name, text):
    p = work / name
    p.write_text(text)
    line = _convert(monkeypatch, capsys, p, "nested")
    assert f"limit of {CAMERA_FILE_MAX_DEPTH}" in line


def test_camera_file_with_brackets_hidden_in_strings_is_refused_by_their_count(work, monkeypatch, capsys):
    # '"]"' closes nothing for a parser but would for a naive count: the total bounds it anyway.
    p = work / "hidden.json"
    p.write_text('{"camera_matrix": ' + '["]", ' * 20000 + "1" + "]" * 20000 + "}")
    _convert(monkeypatch, capsys, p, "brackets")


def test_camera_file_over_the_byte_limit_is_refused_before_reading(work, monkeypatch, capsys):
    p = work / "big.yml"
    p.write_text(_opencv() + "# " + "x" * CAMERA_FILE_MAX_BYTES + "\n")
    _convert(monkeypatch, capsys, p, "over the limit")


def test_camera_json_nested_100000_deep_fails_in_one_line_not_a_crash(tmp_path):
    """In a subprocess: OpenCV's parser used to segfault here, which would kill pytest itself."""
    p = tmp_path / "deeper.json"
    p.write_text('{"camera_matrix": ' + "[" * 100_000 + "]" * 100_000 + "}")
    code = "import sys; from trials.cli.main import main; sys.argv = sys.argv[1:]; main()"
    out = subprocess.run(
        [sys.executable, "-c", code, "advobj", "calibrate", "convert", str(p), "--out", str(tmp_path / "o.yaml")],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    assert out.returncode == 2, (out.returncode, out.stderr[-500:])  # -11 would be the segfault
    assert len(lines) == 1 and "deeper.json" in lines[0] and "nested" in lines[0], lines
    assert not (tmp_path / "o.yaml").exists()


_json_values = st.recursive(
    st.integers(-5, 5) | st.text("ab[]{}", max_size=4),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text("ab", max_size=2), inner, max_size=3),
    max_leaves=30,
)


def _depth(v) -> int:
    if isinstance(v, list):
        return 1 + max((_depth(x) for x in v), default=0)
    if isinstance(v, dict):
        return 1 + max((_depth(x) for x in v.values()), default=0)
    return 0


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_json_values, st.sampled_from([None, 2]))
def test_nesting_estimate_never_falls_below_the_real_depth(value, indent):
    import yaml

    text = json.dumps(value, indent=indent)
    assert nesting_depth(text) >= _depth(value)
    block = yaml.safe_dump(value, default_flow_style=False)
    assert nesting_depth(block) >= _depth(value) // 2  # block style: at least half (see nesting_depth)


# ---------------------------------------------------------------- 2. the camera mount's bounds


def _hw_yaml(work: Path, tcp_cam: str) -> Path:
    (work / "tcp_cam.yaml").write_text(tcp_cam)
    p = work / "hw.yaml"
    p.write_text(
        textwrap.dedent("""\
        camera: {type: sim}
        arm: {type: sim}
        T_tcp_cam: tcp_cam.yaml
        safety: {workspace_min_m: [-0.9, -0.9, 0.01], workspace_max_m: [0.9, 0.9, 0.9]}
        """)
    )
    return p


class _NoWorld:
    """Stands in for the sim world: the mount file is refused before anything renders."""

    def __getattr__(self, name):
        raise AssertionError(f"the world was used ({name}) before the camera mount was checked")

    def close(self):
        pass


@pytest.mark.parametrize(
    "tcp_cam, field",
    [
        ("translation_m: [0, 0, 0.1]\nrotvec_rad: [1e200, 0, 0]\n", "rotvec_rad"),
        ("translation_m: [0, 0, 0.1]\nrotvec_rad: [60, 60, 60]\n", "rotvec_rad"),
        ("translation_m: [1e6, 0, 0.1]\nrotvec_rad: [0, 0, 0]\n", "translation_m"),
        ("translation_m: [.nan, 0, 0.1]\nrotvec_rad: [0, 0, 0]\n", "translation_m"),
        ("T_tcp_cam: {translation_m: [0, 0, 0.1], rotvec_rad: [0, -.inf, 0]}\n", "rotvec_rad"),
        ("translation_m: [0, 0, 0.1]\n", "rotvec_rad"),  # required: no silent identity rotation
    ],
)
def test_hw_check_refuses_an_absurd_camera_mount_naming_file_and_field(work, monkeypatch, capsys, tcp_cam, field):
    import robot_io.config

    monkeypatch.setattr(robot_io.config, "build_world", lambda cfg: _NoWorld())
    hw = _hw_yaml(work, tcp_cam)
    _refused(monkeypatch, capsys, "hw", "check", "--config", str(hw), names=("tcp_cam.yaml", field))


def test_camera_mount_file_within_bounds_loads(tmp_path):
    from robot_io.config import load_T_tcp_cam

    f = tmp_path / "ok.yaml"
    f.write_text("translation_m: [0.01, -0.02, 0.1]\nrotvec_rad: [0, 0, 3.0]\n")
    T = load_T_tcp_cam(f)
    assert np.all(np.isfinite(T)) and np.allclose(T[:3, 3], [0.01, -0.02, 0.1])


# ---------------------------------------------------------------- 3. absurd cameras, every format


@pytest.mark.parametrize(
    "name, text, field",
    [
        ("ros_wide.yaml", _ros(w=10**12, h=750_000_000_000), "image_width"),
        ("ros_dist.yaml", _ros(dist=(1e300, 0, 0, 0, 0)), "distortion_coefficients.data.0"),
        ("ros_dist_k3.yaml", _ros(dist=(0, 0, 0, 0, -2e3)), "distortion_coefficients.data.4"),
        ("ros_fx_tiny.yaml", _ros(fx=1e-3), "camera_matrix"),
        ("ros_fy_huge.yaml", _ros(fy=1e9), "camera_matrix"),
        ("ros_dist_len.yaml", _ros(dist=(0, 0, 0)), "distortion_coefficients.data"),
        ("ros_dist_shape.yaml", _ros(nd=7, dist=(0, 0, 0, 0, 0)), "distortion_coefficients"),
        ("ros_k_shape.yaml", _ros().replace("rows: 3\n  cols: 3", "rows: 1\n  cols: 9", 1), "camera_matrix"),
        ("cv_wide.yml", _opencv(w=10**12, h=750_000_000_000), "image_width"),
        ("cv_dist.yml", _opencv(dist=(0, 1e300, 0, 0, 0)), "distortion_coefficients.1"),
        ("cv_dist_len.yml", _opencv(dist=(0, 0, 0)), "distortion_coefficients"),
        ("cv_fx.yml", _opencv(kdata="1e12, 0, 320, 0, 500, 240, 0, 0, 1"), "camera_matrix"),
        ("cv_1x9.yml", _opencv(kr=1, kc=9), "camera_matrix"),
        ("cv_short.yml", _opencv(kdata="500, 0, 320, 0, 500, 240, 0, 0"), "camera_matrix.data"),
        ("cv_huge_shape.yml", _opencv(kr=100_000, kc=100_000), "camera_matrix.data"),
        ("cv_ragged.yml", "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\n"
         "camera_matrix: [[500, 0, 320], [0, 500, 240, 0, 0, 1]]\n", "camera_matrix"),
        ("cv_words.yml", _opencv(kdata="500, 0, 320, 0, fx, 240, 0, 0, 1"), "camera_matrix.data"),
        ("cv_size.yml", _opencv(w=640.5), "image_width"),
        ("ours.yaml", OURS + "dist: [0, 0, 0, 0, 5e3]\n", "dist.4"),
        ("ours_fx.yaml", "width: 640\nheight: 480\nK: [[0.5, 0, 320], [0, 500, 240], [0, 0, 1]]\n", "K"),
        ("ours_tall.yaml", "width: 640\nheight: 100000\nK: [[500, 0, 320], [0, 500, 240], [0, 0, 1]]\n", "height"),
    ],
)  # fmt: skip
def test_absurd_camera_file_is_refused_naming_the_field(work, monkeypatch, capsys, name, text, field):
    p = work / name
    p.write_text(text)
    line = _convert(monkeypatch, capsys, p, f": {field}: ")
    with pytest.raises(CalibrationFileError) as e:
        load_camera_yaml(p)
    assert e.value.field == field, str(e.value)
    assert line.endswith(str(e.value)) or str(e.value) in line


def test_a_distortion_of_bad_length_is_reported_under_the_distortion_field_not_the_matrix(tmp_path):
    for name, text in (("r.yaml", _ros(dist=(0, 0, 0))), ("o.yml", _opencv(dist=(0, 0, 0)))):
        (tmp_path / name).write_text(text)
        with pytest.raises(CalibrationFileError, match="expected 0, 4, 5, 8, 12 or 14") as e:
            load_camera_yaml(tmp_path / name)
        assert e.value.field.startswith("distortion_coefficients"), str(e.value)


def test_ordinary_camera_files_at_the_bounds_still_load(tmp_path):
    cases = {
        "ros.yaml": _ros(),
        "cv.yml": _opencv(),
        "cv_flat.yml": "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: [" + K9 + "]\n",
        "wide.yaml": _ros(w=MAX_IMAGE_PX, h=MAX_IMAGE_PX, fx=FOCAL_RANGE[0] * MAX_IMAGE_PX, fy=1000, cx=8000, cy=8000),
        "tele.yml": _opencv(
            kdata=f"{FOCAL_RANGE[1] * 640}, 0, 320, 0, 500, 240, 0, 0, 1", dist=(MAX_DISTORTION, 0, 0, 0)
        ),
    }
    for name, text in cases.items():
        (tmp_path / name).write_text(text)
        cam = load_camera_yaml(tmp_path / name)
        assert np.all(np.isfinite(cam.K)) and np.all(np.abs(cam.dist) <= MAX_DISTORTION), name


def test_convert_rescale_beyond_the_largest_image_is_refused_naming_the_flag(work, monkeypatch, capsys):
    p = work / "cam.yaml"
    p.write_text(_ros())
    argv = ("calibrate", "convert", str(p), "--out", "out/c.yaml", "--rescale", "1000000000000x750000000000")
    line = _refused(monkeypatch, capsys, *argv, names=("--rescale",))
    assert str(MAX_IMAGE_PX) in line


_extreme = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 1e-300, 1e300, -1e300, 5e-324, 1e3, 1e3 + 1e-9, 16384.0, 16385.0]),
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    w=st.one_of(st.integers(-5, 20000), st.sampled_from([10**12, 2**63])),
    fx=_extreme,
    cx=_extreme,
    k1=_extreme,
    fmt=st.sampled_from(["ros", "opencv"]),
)
def test_any_camera_file_loads_within_bounds_or_fails_naming_a_field(tmp_path, w, fx, cx, k1, fmt):
    def num(x):
        return ".nan" if x != x else (".inf" if x == float("inf") else "-.inf" if x == -float("inf") else repr(x))

    if fmt == "ros":
        text = _ros(w=w, h=480, fx=num(fx), cx=num(cx), dist=(num(k1), 0, 0, 0, 0))
    else:
        text = _opencv(w=w, h=480, kdata=f"{num(fx)}, 0, {num(cx)}, 0, 500, 240, 0, 0, 1", dist=(num(k1), 0, 0, 0, 0))
    p = tmp_path / f"cam.{'yaml' if fmt == 'ros' else 'yml'}"
    p.write_text(text)
    try:
        cam = load_camera_yaml(p)
    except CalibrationFileError as err:
        assert "\n" not in str(err) and str(p) in str(err) and err.field not in ("", "<file>")
        return
    assert 1 <= cam.width <= MAX_IMAGE_PX and 1 <= cam.height <= MAX_IMAGE_PX
    assert FOCAL_RANGE[0] * cam.width <= cam.K[0, 0] <= FOCAL_RANGE[1] * cam.width
    assert 0 <= cam.K[0, 2] <= cam.width and np.all(np.abs(cam.dist) <= MAX_DISTORTION)


# ---------------------------------------------------------------- 4. unbounded inputs


def test_tag_ids_beyond_the_dictionary_are_refused_before_expanding(work, monkeypatch, capsys):
    tracemalloc.start()
    try:
        _refused(
            monkeypatch, capsys, "calibrate", "tags", "--ids", "0-100000000", "--out", "out/t.pdf", names=("--ids",)
        )
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 20 * 2**20, f"{peak / 2**20:.0f} MiB for a refused --ids"


@pytest.mark.parametrize("ids", ["0-586,0-586", "587", "5-2", "-3", "0-99999999999999999999", ""])
def test_tag_ids_out_of_range_or_too_many_name_the_flag(work, monkeypatch, capsys, ids):
    _refused(monkeypatch, capsys, "calibrate", "tags", "--ids", ids, "--out", "out/t.pdf", names=("--ids",))


def test_tag_id_ranges_parse_only_within_the_dictionary():
    from calibration.printables import TAG36H11_IDS, parse_id_ranges

    assert parse_id_ranges("0-2, 586") == [0, 1, 2, 586]
    assert len(parse_id_ranges(f"0-{TAG36H11_IDS - 1}")) == TAG36H11_IDS
    with pytest.raises(ValueError, match="ids: .*0..49"):
        parse_id_ranges("0-50", n_ids=50)


@pytest.fixture
def fifo(work):
    p = work / "pipe.yaml"
    os.mkfifo(p)
    return p


def _special(kind: str, fifo: Path) -> str:
    return str(fifo) if kind == "fifo" else "/dev/zero"


@pytest.mark.skipif(not Path("/dev/zero").exists(), reason="needs /dev/zero")
@pytest.mark.parametrize("kind", ["fifo", "devzero"])
@pytest.mark.parametrize(
    "argv, flag",
    [
        (["calibrate", "convert", "{x}", "--out", "out/c.yaml"], None),
        (["calibrate", "detect", "{ok_image}", "--camera", "{x}"], "--camera"),
        (["calibrate", "detect", "{x}", "--camera", "{ok_camera}"], None),
        (["calibrate", "detect", "{ok_image}", "--camera", "{ok_camera}", "--registry", "{x}"], "--registry"),
        (["calibrate", "intrinsics", "{x}", "--out", "out/c.yaml"], None),
        (["calibrate", "intrinsics", "{ok_image}", "--board", "{x}", "--out", "out/c.yaml"], "--board"),
        (["calibrate", "handeye", "{x}", "--out", "out/h.yaml"], None),
        (["hw", "check", "--config", "{x}"], "--config"),
    ],
)
def test_a_device_or_fifo_given_for_a_file_is_refused_without_blocking(
    work, monkeypatch, capsys, fifo, kind, argv, flag
):
    x = _special(kind, fifo)
    (work / "ok.yaml").write_text(_ros())
    import cv2

    cv2.imwrite(str(work / "ok.png"), np.zeros((480, 640, 3), np.uint8))
    args = [a.format(x=x, ok_image=work / "ok.png", ok_camera=work / "ok.yaml") for a in argv]
    line = _refused(monkeypatch, capsys, *args, names=(x,))
    assert "regular file" in line


@pytest.mark.skipif(not Path("/dev/zero").exists(), reason="needs /dev/zero")
@pytest.mark.parametrize("kind", ["fifo", "devzero"])
def test_every_reader_refuses_a_device_or_fifo_itself_naming_the_file(work, fifo, kind):
    """The loaders check on their own: a file named inside another file never passes the command line."""
    from calibration.handeye import load_samples_yaml
    from calibration.intrinsics import camera_file_format, load_board_yaml
    from calibration.io import read_image, read_yaml
    from calibration.registry import load_registry
    from robot_io.config import load_hardware_config, load_T_tcp_cam
    from sim.errors import AdvobjError

    x = _special(kind, fifo)
    readers = (
        load_camera_yaml,
        camera_file_format,
        load_board_yaml,
        read_image,
        read_yaml,
        load_registry,
        load_samples_yaml,
        load_hardware_config,
        load_T_tcp_cam,
    )
    old = signal.signal(signal.SIGALRM, _on_alarm)
    try:
        for reader in readers:
            signal.alarm(CASE_TIMEOUT_S)
            try:
                with pytest.raises(AdvobjError, match="regular file") as e:
                    reader(x)
            except _Timeout:
                pytest.fail(f"{reader.__name__}({x}) blocked")
            finally:
                signal.alarm(0)
            assert x in str(e.value) and "\n" not in str(e.value), (reader.__name__, str(e.value))
    finally:
        signal.signal(signal.SIGALRM, old)


@pytest.mark.parametrize("field", ["T_tcp_cam", "sim.scene", "camera.path", "camera.intrinsics"])
def test_a_fifo_named_inside_the_hardware_config_is_refused_without_blocking(work, monkeypatch, capsys, fifo, field):
    cfg = {
        "camera": {"type": "sim"},
        "arm": {"type": "sim"},
        "safety": {"workspace_min_m": [-0.9, -0.9, 0.01], "workspace_max_m": [0.9, 0.9, 0.9]},
    }
    if field == "T_tcp_cam":
        cfg["T_tcp_cam"] = str(fifo)
    elif field == "sim.scene":
        cfg["sim"] = {"scene": str(fifo)}
    else:  # a replay camera and a serial arm: no sim world at all
        cfg["arm"] = {"type": "serial", "port": "/dev/null"}
        frames = work / "frames"
        frames.mkdir()
        cfg["camera"] = {"type": "replay", "path": str(fifo) if field == "camera.path" else str(frames)}
        if field == "camera.intrinsics":
            cfg["camera"]["intrinsics"] = str(fifo)
    if field == "T_tcp_cam":  # sim.scene is refused by build_world itself, before any rendering
        import robot_io.config

        monkeypatch.setattr(robot_io.config, "build_world", lambda c: _NoWorld())
    hw = work / "hw.yaml"
    hw.write_text(json.dumps(cfg))
    _refused(monkeypatch, capsys, "hw", "check", "--config", str(hw), "--frames", "2", names=(fifo.name,))


@pytest.mark.parametrize("device", ["/dev/zero", "/dev/null", "fifo", "dir"])
def test_an_opencv_camera_device_that_is_no_video4linux_node_is_refused(work, fifo, device):
    from robot_io.cameras.opencv import resolve_device
    from robot_io.errors import CameraLostError

    if device.startswith("/dev/") and not Path(device).exists():
        pytest.skip(f"needs {device}")
    path = {"fifo": str(fifo), "dir": str(work)}.get(device, device)
    with pytest.raises(CameraLostError, match="not a video4linux camera|no video4linux camera") as e:
        resolve_device(path)
    assert path in str(e.value) and "\n" not in str(e.value)


@pytest.mark.skipif(not Path("/dev/zero").exists(), reason="needs /dev/zero")
def test_hw_check_with_dev_zero_as_the_opencv_camera_fails_in_one_line(work, monkeypatch, capsys):
    hw = work / "hw.yaml"
    hw.write_text(
        "camera: {type: opencv, device: /dev/zero}\narm: {type: serial, port: /dev/null}\n"
        "safety: {workspace_min_m: [-0.9, -0.9, 0.01], workspace_max_m: [0.9, 0.9, 0.9]}\n"
    )
    _refused(monkeypatch, capsys, "hw", "check", "--config", str(hw), names=("/dev/zero", "video4linux"))


def test_a_directory_given_as_a_camera_file_is_one_error_naming_it(tmp_path):
    with pytest.raises(CalibrationFileError, match="is a directory") as e:
        load_camera_yaml(tmp_path)
    assert str(tmp_path) in str(e.value) and "\n" not in str(e.value)
