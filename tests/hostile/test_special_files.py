"""A FIFO, a device or a socket given on the command line is refused before any command runs."""

from __future__ import annotations

import os
import socket
import sys

import pytest

from trials.cli.main import main, special_file_argument


def _cli(monkeypatch, capsys, *argv):
    monkeypatch.setattr(sys, "argv", ["advobj", *argv])
    with pytest.raises(SystemExit) as ex:
        main()
    return ex.value.code, [line for line in capsys.readouterr().err.splitlines() if line.strip()]


def test_a_fifo_as_a_positional_file_is_one_line_and_never_opened(tmp_path, monkeypatch, capsys):
    fifo = tmp_path / "photos.yaml"
    os.mkfifo(fifo)  # no writer: opening it for reading would block forever
    code, lines = _cli(monkeypatch, capsys, "calibrate", "intrinsics", str(fifo))
    assert code == 2 and len(lines) == 1 and str(fifo) in lines[0] and "FIFO" in lines[0]


@pytest.mark.parametrize("form", ["separate", "equals"])
def test_dev_zero_as_an_option_value_names_the_flag(monkeypatch, capsys, form):
    argv = (
        ["policy", "eval", "x", "--scene", "/dev/zero"]
        if form == "separate"
        else ["policy", "eval", "x", "--scene=/dev/zero"]
    )
    code, lines = _cli(monkeypatch, capsys, *argv)
    assert code == 2 and len(lines) == 1 and "--scene" in lines[0] and "/dev/zero" in lines[0] and "device" in lines[0]


def test_a_unix_socket_is_refused_and_regular_files_and_folders_pass(tmp_path):
    sock_path = tmp_path / "s.sock"
    s = socket.socket(socket.AF_UNIX)
    try:
        s.bind(str(sock_path))
        assert "socket" in special_file_argument(["--config", str(sock_path)])
    finally:
        s.close()
    (tmp_path / "a.yaml").write_text("a: 1\n")
    assert special_file_argument([str(tmp_path / "a.yaml"), "--out", str(tmp_path), "--n", "3", "nan", ""]) is None


def test_a_sim_twin_image_over_2048_px_is_refused_before_any_world_is_built(tmp_path):
    from robot_io.config import load_hardware_config
    from sim.errors import AdvobjError

    cfg = tmp_path / "cell.yaml"
    cfg.write_text("camera: {type: sim}\narm: {type: sim}\nsim: {image_size: [8192, 8192]}\n")
    with pytest.raises(AdvobjError) as err:
        load_hardware_config(cfg)
    msg = str(err.value)
    assert "image_size" in msg and "2048" in msg and "\n" not in msg.strip()
