"""advobj fabricate for an object named by its scene (issue 30, "any mesh to the cell"): a tag card
for any mesh with the tag's pose in the object frame (T_obj_tag) recorded, the registry entry made
from it, and a pre-print check that reads the card back and fails when the card and T_obj_tag
disagree. Bad input is one line naming the flag, exit 2, nothing written."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from tests.trials.real.own_mesh_helpers import box_obj_mm, own_scene, run_on_scene

DPI = 60  # fast; the card's tag is still 94 px wide at 40 mm


@pytest.fixture(scope="module")
def own(tmp_path_factory):
    d = tmp_path_factory.mktemp("own_fab")
    box_obj_mm(d / "meshes" / "my_box.obj")
    scene = own_scene(d / "my.yaml", "meshes/my_box.obj")
    return {"dir": d, "scene": scene, "run": run_on_scene(d / "run", scene, size=32)}


def _invoke(args):
    from trials.cli.main import app

    return CliRunner().invoke(app, [str(a) for a in args])


def test_the_tag_card_of_a_scene_objects_mesh_file_records_T_obj_tag_and_registers_it_by_name(own, tmp_path):
    from calibration.io import pose_to_T
    from calibration.registry import PoseModel, load_registry
    from sim.geometry import invert_T, make_T

    out = tmp_path / "fab"
    args = ["fabricate", own["run"], "--scene", own["scene"], "--shape", "my_box", "--tag-id", 7, "--tag-size-mm", 40]
    res = _invoke(args + ["--dpi", DPI, "--out", out])
    assert res.exit_code == 0, res.output
    assert "pre-print check PASSED: tag card: tag 7 read back" in res.output
    assert "in the frame of 'my_box' (T_obj_tag, in layout.json); objects.yaml registers it as object 'my_box'" in (
        res.output
    )
    for name in ("sheet.pdf", "layout.json", "objects.yaml", "print_check.png", "print_check.json", "adversarial.glb"):
        assert (out / name).is_file(), name
    layout = json.loads((out / "layout.json").read_text())
    assert layout["shape"] == "card" and layout["mm_per_uv"] is None
    (card,) = layout["pieces"]
    T_obj_tag = pose_to_T(PoseModel(**card["T_obj_tag"]))
    # The card lies on the table (z = 0 in the box's frame) with the tag to the box's -x: the tag's
    # 40 mm plus its 10 mm quiet zones, half of that block, the 8 mm gap and half the 50 mm box.
    np.testing.assert_allclose(T_obj_tag, make_T(np.eye(3), [-(0.030 + 0.008 + 0.025), 0.0, 0.0]), atol=1e-9)
    entry = load_registry(out / "objects.yaml").tags[7]
    assert entry.object == "my_box" and entry.size_m == pytest.approx(0.040)
    centre = make_T(np.eye(3), [0.0, 0.0, 0.035])  # the registry's object frame: the box's centre
    np.testing.assert_allclose(pose_to_T(entry.T_tag_object), invert_T(T_obj_tag) @ centre, atol=1e-6)
    check = json.loads((out / "print_check.json").read_text())
    assert check["passed"] and check["card"]["found"] and check["card"]["outline_on_ink"] >= 0.8
    assert abs(check["card"]["size_error_mm"]) < 0.3
    run = json.loads((out / "run.json").read_text())["config"]
    assert run["object"] == "my_box" and run["scene"] == str(own["scene"]) and len(run["mesh_sha256"]) == 64


def _card_layout(own, tag=(5, 40.0)):
    from sim.assets import build_mesh
    from sim.spec import load_spec
    from trials.fabrication.fabricate import CARD, build_layout, draw_pages
    from trials.fabrication.shapes import load_run

    obj = load_spec(own["scene"]).adversarial
    mesh = build_mesh(obj.mesh, obj.scale, **obj.mesh_kwargs())
    layout = build_layout(load_run(own["run"]), mesh, CARD, "a4", DPI, tag)
    return layout, draw_pages(layout, np.zeros((4, 4, 3), np.uint8)), mesh


@pytest.mark.parametrize(
    "mistake",
    ["shifted 5 mm along x", "tag on the other side", "tag turned half a turn", "tag 3 mm too high"],
)
def test_the_card_check_fails_when_the_card_and_T_obj_tag_disagree(own, mistake):
    from sim.geometry import make_T, rot_z
    from trials.fabrication.print_check import check_card

    layout, rasters, mesh = _card_layout(own)
    card = next(p for p in layout.pieces if p.kind == "card")
    good, _ = check_card(layout, rasters, mesh)
    assert good["failures"] == [] and good["outline_on_ink"] > 0.95 and good["origin_error_mm"] < 0.5
    T = card.fold["T_obj_tag"].copy()
    if mistake == "shifted 5 mm along x":
        T[0, 3] += 0.005
    elif mistake == "tag on the other side":
        T[0, 3] = -T[0, 3]
    elif mistake == "tag turned half a turn":
        T = T @ make_T(rot_z(np.pi), np.zeros(3))
    else:
        T[2, 3] += 0.003  # a card 3 mm off the table: the same outline, carried from a plane 3 mm higher
    bad, image = check_card(layout, rasters, mesh, T)
    if mistake == "tag 3 mm too high":  # height does not show on a flat card: the check cannot see it
        assert bad["failures"] == []
        return
    assert len(bad["failures"]) == 1 and "misses the drawn outline" in bad["failures"][0], bad
    assert image.ndim == 3 and image.shape[1] >= 600  # the overlay, large enough to look at


def test_a_card_whose_tag_cannot_be_read_fails_the_check(own):
    from trials.fabrication.print_check import check_card

    layout, rasters, mesh = _card_layout(own)
    at = layout.where("tag_card")
    ppm = rasters[0].shape[1] / layout.page_mm[0]
    blank = rasters[0].copy()
    y0, x0 = int(at.y_mm * ppm), int(at.x_mm * ppm)
    blank[y0 : y0 + int(60 * ppm), x0 : x0 + int(60 * ppm)] = 255  # the tag block, wiped
    res, image = check_card(layout, [blank], mesh)
    assert res["found"] is False and image is None
    assert res["failures"] == ["tag card: tag36h11 id 5 cannot be read from the printed page"]


def test_a_sheet_shape_named_by_a_scene_object_gets_its_net_and_a_card_under_its_name(own, tmp_path):
    from calibration.registry import load_registry

    scene = own_scene(tmp_path / "cube.yaml", "cube", name="box1", units="m")
    run = run_on_scene(tmp_path / "run", scene, size=32)
    res = _invoke(
        ["fabricate", run, "--scene", scene, "--shape", "box1", "--tag-id", 3, "--dpi", DPI, "--out", tmp_path / "o"]
    )
    assert res.exit_code == 0, res.output
    kinds = [p["kind"] for p in json.loads((tmp_path / "o" / "layout.json").read_text())["pieces"]]
    assert kinds == ["cube_net", "card"]
    check = json.loads((tmp_path / "o" / "print_check.json").read_text())
    assert check["passed"] and check["card"]["found"] and len(check["view_abs_error"]) == 8
    assert (tmp_path / "o" / "print_check.png").is_file() and (tmp_path / "o" / "print_check_card.png").is_file()
    assert load_registry(tmp_path / "o" / "objects.yaml").tags[3].object == "box1"


def _main(monkeypatch, capsys, args):
    from trials.cli.main import main

    monkeypatch.setattr(sys, "argv", ["advobj", *map(str, args)])
    with pytest.raises(SystemExit) as exc:
        main()
    return exc.value.code, capsys.readouterr().err.strip()


@pytest.mark.parametrize("case", ["unknown object", "missing mesh file", "run on another mesh", "no scene"])
def test_bad_input_is_one_line_naming_the_flag_exit_2_and_nothing_written(own, tmp_path, monkeypatch, capsys, case):
    from tests.trials.real.trial_session_helpers import attack_dir

    run, scene, shape = own["run"], own["scene"], "my_box"
    if case == "unknown object":
        shape, want = "my_bx", "--shape my_bx: no object 'my_bx' in scene "
    elif case == "missing mesh file":
        scene = own_scene(tmp_path / "gone.yaml", "meshes/gone.obj")
        want = "--shape my_box: objects.1.mesh of scene "
    elif case == "run on another mesh":
        run = attack_dir(tmp_path / "cube_run", "cube")
        want = "--shape my_box: the attack run optimised mesh 'cube', but it needs mesh "
    else:
        scene, want = None, "--shape my_box: no flat net for this shape; sheets exist for cube, cylinder; to make an"
    args = ["fabricate", run, "--shape", shape, "--tag-id", 7, "--out", tmp_path / "out"]
    code, err = _main(monkeypatch, capsys, args + (["--scene", scene] if scene else []))
    assert code == 2 and len(err.splitlines()) == 1 and want in err, err
    assert not (tmp_path / "out").exists()
