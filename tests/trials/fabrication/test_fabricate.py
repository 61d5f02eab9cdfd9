"""advobj fabricate: true-scale sheets, the cube net's folding, the pre-print check and the CLI."""

import json
import re
import sys

import numpy as np
import pytest

from tests.trials.conftest import make_attack_dir
from trials.fabrication.base import FabricationError, sample_bilinear
from trials.fabrication.fabricate import (
    CHECK_LINE_MM,
    PAGES_MM,
    LayoutTweak,
    build_layout,
    draw_pages,
    load_run,
    region_raster,
)

DPI = 60  # low print resolution keeps the tests fast; the textures below are smooth at this scale


def _pattern(size: int, seed: int) -> np.ndarray:
    """(S, S, 3) float32: 8 x 8 blocks of distinct random colours plus a gradient, so every UV
    region differs from every other and from its own mirror image or rotation."""
    rng = np.random.default_rng(seed)
    blocks = rng.random((8, 8, 3))
    yy, xx = np.mgrid[0:size, 0:size] / size
    tex = 0.7 * blocks[(yy * 8).astype(int), (xx * 8).astype(int)] + 0.3 * np.stack([xx, yy, 1 - xx], -1)
    return tex.astype(np.float32)


def _run(path, mesh, size=64, seed=0):
    make_attack_dir(path, mesh=mesh, size=size)
    np.save(path / "texture.npy", _pattern(size, seed))
    return path


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("fab_runs")
    return {shape: _run(root / shape, shape) for shape in ("cube", "cylinder")}


def _layout(run_dir, tweak=LayoutTweak(), page="a4", tag=None):
    from sim.assets import build_mesh

    src = load_run(run_dir)
    mesh = build_mesh(src.mesh)
    return src, mesh, build_layout(src, mesh, src.mesh, page, DPI, tag, tweak)


# ----------------------------------------------------------------------------- sampling
def test_bilinear_sampling_follows_the_renderer_convention():
    img = np.arange(2 * 3 * 1, dtype=float).reshape(2, 3, 1)  # row 0 is v = 1
    centres = np.array([[0.5 / 3, 0.75], [2.5 / 3, 0.25]])  # texel (row 0, col 0) and (row 1, col 2)
    assert sample_bilinear(img, centres)[:, 0].tolist() == [img[0, 0, 0], img[1, 2, 0]]
    mid = sample_bilinear(img, np.array([[1.0 / 3, 0.5]]))[0, 0]  # corner of four texels
    assert mid == pytest.approx(img[:, :2, 0].mean())
    clamped = sample_bilinear(img, np.array([[0.0, 1.0]]))[0, 0]  # clamp to edge
    assert clamped == img[0, 0, 0]


def test_region_raster_prints_the_uv_box_upright_at_the_dpi(runs):
    src, mesh, layout = _layout(runs["cube"])
    reg = next(r for r in layout.pieces[0].regions if r.name == "+z")
    img = region_raster(src.texture, reg, DPI)
    assert img.shape[:2] == (round(reg.rect_mm[3] / 25.4 * DPI), round(reg.rect_mm[2] / 25.4 * DPI))
    u0, v0, u1, v1 = reg.uv_box
    corners = sample_bilinear(src.texture, np.array([[u0, v1], [u1, v0]]))  # top-left, bottom-right
    assert np.abs(img[0, 0] - corners[0]).max() < 40 and np.abs(img[-1, -1] - corners[1]).max() < 40
    assert np.abs(img[0, 0].astype(int) - img[-1, -1]).max() > 0


# ----------------------------------------------------------------------------- geometry
def _uv_to_surface(mesh, uv):
    """Surface points (N, 3) mm of UV points (N, 2), by barycentric lookup in UV space."""
    tri_uv = np.asarray(mesh.visual.uv, float)[np.asarray(mesh.faces)]  # (F, 3, 2)
    tri_xyz = np.asarray(mesh.vertices, float)[np.asarray(mesh.faces)] * 1000.0
    a, b, c = tri_uv[:, 0], tri_uv[:, 1], tri_uv[:, 2]
    out = np.full((len(uv), 3), np.nan)
    for i, p in enumerate(uv):
        v0, v1, v2 = b - a, c - a, p - a
        den = v0[:, 0] * v1[:, 1] - v0[:, 1] * v1[:, 0]
        s = (v2[:, 0] * v1[:, 1] - v2[:, 1] * v1[:, 0]) / den
        t = (v0[:, 0] * v2[:, 1] - v0[:, 1] * v2[:, 0]) / den
        hit = np.nonzero((s >= -1e-9) & (t >= -1e-9) & (s + t <= 1 + 1e-9))[0]
        if len(hit):
            f = hit[0]
            out[i] = tri_xyz[f, 0] + s[f] * (tri_xyz[f, 1] - tri_xyz[f, 0]) + t[f] * (tri_xyz[f, 2] - tri_xyz[f, 0])
    return out


def test_cube_net_folds_onto_the_cube_with_every_face_upright(runs):
    """Fold the net's tiles in 3D (printed side out) and compare, point by point, with where the
    mesh puts the UV that each paper point prints: same place, so same face, orientation, side."""
    _, mesh, layout = _layout(runs["cube"])
    net = layout.pieces[0]
    regions = {r.name: r for r in net.regions}
    assert set(net.fold["tiles"]) == set(regions) == {"+x", "-x", "+y", "-y", "+z", "-z"}
    rng = np.random.default_rng(0)
    for name, (T, (x, y, w, h)) in net.fold["tiles"].items():
        ab = rng.uniform(0.05, 0.95, (20, 2))
        paper = np.stack([x + ab[:, 0] * w, y + ab[:, 1] * h, np.zeros(20), np.ones(20)], -1)
        folded = (T @ paper.T).T[:, :3]
        u0, v0, u1, v1 = regions[name].uv_box
        uv = np.stack([u0 + ab[:, 0] * (u1 - u0), v1 - ab[:, 1] * (v1 - v0)], -1)
        np.testing.assert_allclose(folded, _uv_to_surface(mesh, uv), atol=0.05, err_msg=f"tile {name}")
        axis, sign = "xyz".index(name[1]), 1.0 if name[0] == "+" else -1.0
        assert -T[:3, 2][axis] * sign == pytest.approx(1.0), f"tile {name}: printed side must face outward"


def test_layout_is_true_scale_and_fits_the_page(runs):
    _, mesh, layout = _layout(runs["cube"], tag=(3, 30.0))
    doc = layout.to_json()
    assert doc["check_line_mm"] == CHECK_LINE_MM == 100.0
    assert next(i for i in doc["items"] if i["kind"] == "scale")["check_line_mm"] == 100.0
    net = next(p for p in doc["pieces"] if p["kind"] == "cube_net")
    edge_mm = float(mesh.extents[0]) * 1000.0
    for r in net["regions"]:
        assert r["rect_mm"][2] == pytest.approx(edge_mm) and r["rect_mm"][3] == pytest.approx(edge_mm)
        assert (r["uv_box"][2] - r["uv_box"][0]) * doc["mm_per_uv"] == pytest.approx(edge_mm)
    W, H = doc["page_mm"]
    assert sorted((W, H)) == sorted(PAGES_MM["a4"])
    for thing in doc["pieces"] + doc["items"]:
        x, y = thing["origin_mm"]
        assert x >= 8 and y >= 8 and x + thing["size_mm"][0] <= W - 8 and y + thing["size_mm"][1] <= H - 8, thing[
            "name"
        ]


def test_a_piece_too_large_for_the_page_is_named():

    from sim.assets import build_mesh
    from trials.fabrication.fabricate import RunSource

    mesh = build_mesh("cube")
    src = RunSource("run", (_pattern(16, 0) * 255).astype(np.uint8), "cube", 1.0, "0" * 64)
    with pytest.raises(FabricationError, match=r"piece 'cube_net' \(3\d\d.\d x 2\d\d.\d mm\) does not fit.*--page"):
        build_layout(src, mesh, "cube", "a4", DPI, None, LayoutTweak(scale=1.3))
    with pytest.raises(FabricationError, match="shape 'duck' has no flat net"):
        build_layout(src, mesh, "duck", "a4", DPI)


# ----------------------------------------------------------------------------- pre-print check
def _check(run_dir, tweak=LayoutTweak()):
    from trials.fabrication.print_check import check_print

    src, mesh, layout = _layout(run_dir, tweak)
    return check_print(layout, draw_pages(layout, src.texture), mesh, src.texture)


@pytest.mark.parametrize("shape", ["cube", "cylinder"])
def test_print_back_check_passes_for_a_correct_sheet(runs, shape):
    r = _check(runs[shape])
    assert r.passed, r.message()
    assert r.unread_texels == 0
    assert max(abs(s["error_mm"]) for s in r.scale) < 0.05
    # Tighter than the pass threshold: a correct sheet reads back close to the texture.
    assert r.mean_mae < r.max_mean / 2


@pytest.mark.parametrize(
    "shape, tweak, named",
    [
        ("cube", LayoutTweak(transform={"+x": "mirror"}), "tile +x"),
        ("cube", LayoutTweak(transform={"+z": "rot90"}), "tile +z"),
        ("cube", LayoutTweak(scale=0.97), "tile -y width printed 58.20 mm"),
        ("cylinder", LayoutTweak(swap=("top", "bottom")), "cap_"),
        ("cylinder", LayoutTweak(transform={"side": "mirror"}), "piece side"),
    ],
)
def test_print_back_check_catches_layout_mistakes(runs, shape, tweak, named):
    r = _check(runs[shape], tweak)
    assert not r.passed
    assert named in r.message()


# ----------------------------------------------------------------------------- CLI
def _invoke(args):
    from typer.testing import CliRunner

    from trials.cli.main import app

    return CliRunner().invoke(app, [str(a) for a in args])


def test_cli_writes_sheet_meshes_check_and_tag_registry(runs, tmp_path):
    from calibration.registry import load_registry

    out = tmp_path / "fab"
    res = _invoke(["fabricate", runs["cylinder"], "--out", out, "--dpi", DPI, "--tag-id", 7, "--tag-size-mm", 25])
    assert res.exit_code == 0, res.output
    assert "check PASSED" in res.output
    for name in (
        "sheet.pdf",
        "layout.json",
        "adversarial.glb",
        "adversarial_obj/adversarial.obj",
        "print_check.png",
        "print_check.json",
        "run.json",
        "objects.yaml",
    ):
        assert (out / name).is_file(), name
    layout = json.loads((out / "layout.json").read_text())
    pdf = (out / "sheet.pdf").read_bytes()
    boxes = re.findall(rb"/MediaBox \[\s*0 0 ([\d.]+) ([\d.]+)\s*\]", pdf)
    assert len(boxes) == layout["pages"] >= 1
    for w_pt, h_pt in boxes:
        assert [float(w_pt) * 25.4 / 72, float(h_pt) * 25.4 / 72] == pytest.approx(layout["page_mm"], abs=0.01)
    assert json.loads((out / "print_check.json").read_text())["passed"] is True
    assert json.loads((out / "run.json").read_text())["config"]["dpi"] == DPI
    reg = load_registry(out / "objects.yaml")
    entry = reg.tags[7]
    assert entry.object == "adversarial" and entry.size_m == pytest.approx(0.025)
    # The object's centre sits beside the tag (+x), half the cylinder's height above the card.
    t = np.asarray(entry.T_tag_object.translation_m)
    card = next(p for p in layout["pieces"] if p["kind"] == "card")
    assert t[0] > 0.0125 and t[0] + 0.033 < card["size_mm"][0] / 1000 and t[1] == 0.0 and t[2] == pytest.approx(0.05)


def test_cli_mesh_without_a_net_gets_meshes_only(tmp_path):
    run = make_attack_dir(tmp_path / "run", mesh=None, size=16)  # None: the scene's mustard bottle
    res = _invoke(["fabricate", run, "--out", tmp_path / "out", "--dpi", DPI])
    assert res.exit_code == 0, res.output
    assert "no flat net" in res.output and "mustard_bottle" in res.output
    assert (tmp_path / "out" / "adversarial.glb").is_file() and not (tmp_path / "out" / "sheet.pdf").exists()
    assert "light_randomization" not in res.output  # the run does not say: nothing to warn about
    # A texture optimised under the fixed light is printed, with a warning that says what to do.
    doc = json.loads((run / "run.json").read_text())
    doc["config"]["attack"]["light_randomization"] = False
    (run / "run.json").write_text(json.dumps(doc))
    res = _invoke(["fabricate", run, "--out", tmp_path / "out2", "--dpi", DPI])
    assert res.exit_code == 0 and "warning: this texture was optimised under the scene's fixed light" in res.output
    assert json.loads((tmp_path / "out2" / "run.json").read_text())["config"]["light_randomization"] is False


def _main(monkeypatch, capsys, args):
    from trials.cli.main import main

    monkeypatch.setattr(sys, "argv", ["advobj", *map(str, args)])
    with pytest.raises(SystemExit) as exc:
        main()
    return exc.value.code, capsys.readouterr().err


def test_cli_errors_name_the_file_or_shape(monkeypatch, capsys, tmp_path, runs):
    empty = tmp_path / "empty_run"
    empty.mkdir()
    code, err = _main(monkeypatch, capsys, ["fabricate", empty, "--out", tmp_path / "o1"])
    assert code == 2 and "texture.npy: missing" in err

    mustard = make_attack_dir(tmp_path / "mustard", mesh="mustard_bottle", size=16)
    code, err = _main(monkeypatch, capsys, ["fabricate", mustard, "--out", tmp_path / "o2", "--shape", "cube"])
    assert code == 2 and "'mustard_bottle'" in err and "'cube'" in err

    code, err = _main(monkeypatch, capsys, ["fabricate", mustard, "--out", tmp_path / "o3", "--shape", "duck"])
    assert code == 2 and "--shape duck: no flat net" in err

    code, err = _main(
        monkeypatch, capsys, ["fabricate", runs["cube"], "--out", tmp_path / "o4", "--page", "b5", "--no-check"]
    )
    assert code == 2 and "--page: 'b5'" in err and not (tmp_path / "o4").exists()  # refused before writing


def test_bad_dpi_is_refused_before_anything_is_written(tmp_path, monkeypatch, capsys):
    code, err = _main(monkeypatch, capsys, ["fabricate", tmp_path / "no_run", "--out", tmp_path / "o", "--dpi", "0"])
    assert code == 2 and "--dpi" in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "o").exists()
    from trials.fabrication.fabricate import fabricate

    with pytest.raises(FabricationError, match="--dpi"):
        fabricate(tmp_path / "no_run", tmp_path / "o", dpi=0)
    assert not (tmp_path / "o").exists()


def test_exports_follow_their_formats_glb_y_up_and_obj_says_its_units(tmp_path):
    import trimesh

    import sim.assets as A

    run = make_attack_dir(tmp_path / "run", mesh=None, size=16)  # the mustard bottle: 19 cm tall
    res = _invoke(["fabricate", run, "--out", tmp_path / "out", "--dpi", DPI, "--units", "mm"])
    assert res.exit_code == 0, res.output
    raw = trimesh.load(tmp_path / "out" / "adversarial.glb", force="mesh")
    assert raw.extents[1] == pytest.approx(0.19, abs=0.002) and raw.bounds[0][1] == pytest.approx(
        0.0, abs=1e-6
    )  # +Y up
    back = A.build_mesh(tmp_path / "out" / "adversarial.glb", placement="keep")  # read as glTF: standing again
    np.testing.assert_allclose(back.bounds, A.build_mesh("mustard_bottle").bounds, atol=1e-5)
    obj = tmp_path / "out" / "adversarial_obj" / "adversarial.obj"
    assert obj.read_text().splitlines()[0] == "# advobj: units mm, +Z up (in a scene YAML: units: mm)"
    np.testing.assert_allclose(A.build_mesh(obj, units="mm", placement="keep").bounds, back.bounds, atol=1e-5)


def test_tag_id_on_a_mesh_without_a_net_gets_the_tag_card_alone_and_a_bad_id_writes_nothing(tmp_path):
    from calibration.registry import load_registry

    run = make_attack_dir(tmp_path / "run", mesh=None, size=16)  # the scene's mustard bottle: no net
    res = _invoke(["fabricate", run, "--out", tmp_path / "out", "--dpi", DPI, "--tag-id", 5])
    assert res.exit_code == 0, res.output
    assert "pre-print check PASSED: tag card: tag 5 read back" in res.output
    layout = json.loads((tmp_path / "out" / "layout.json").read_text())
    assert layout["shape"] == "card" and [p["kind"] for p in layout["pieces"]] == ["card"]
    assert load_registry(tmp_path / "out" / "objects.yaml").tags[5].object == "adversarial"
    res = _invoke(["fabricate", run, "--out", tmp_path / "bad", "--dpi", DPI, "--tag-id", 587])
    assert res.exit_code != 0 and "--tag-id: tag36h11 has ids 0..586, got 587" in str(res.exception)
    assert not (tmp_path / "bad").exists()


def test_the_optimised_texel_size_is_said_honestly(tmp_path):
    import sim.assets as A
    from trials.fabrication.fabricate import optimised_texel_size_mm

    cube = A.build_mesh("cube")  # 6 cm cube, its net on the unit UV square
    d = optimised_texel_size_mm(cube, 64, 64)
    side_mm = A.texel_density_ratio(cube)[0] * 1000 / 64
    assert d["median"] == pytest.approx(side_mm, rel=0.05) and d["p10"] <= d["median"] <= d["p90"]
    assert optimised_texel_size_mm(cube, 128, 128)["median"] == pytest.approx(d["median"] / 2, rel=1e-6)
    run = make_attack_dir(tmp_path / "run", mesh=None, size=16)
    res = _invoke(["fabricate", run, "--out", tmp_path / "out", "--dpi", DPI])
    assert res.exit_code == 0 and "the optimised texture is 16 x 16 texels; on the object one texel spans" in res.output


def test_a_user_mesh_keeps_its_own_texture_outside_the_attack_region_in_print(tmp_path):
    from pathlib import Path

    from PIL import Image

    import sim.assets as A
    from attack.artifact import AttackArtifact
    from sim.assets import region_texture as print_texture
    from sim.spec import default_scene

    duck = Path(__file__).resolve().parents[3] / "tests" / "data" / "meshes" / "pybullet-duck" / "duck.obj"
    a = np.zeros((64, 64), np.uint8)
    a[:, :32] = 255
    Image.fromarray(a).save(tmp_path / "left.png")
    kw = {"up_axis": "y", "scale": 0.05, "attack_region": str(tmp_path / "left.png")}
    mesh = A.build_mesh(duck, warn=lambda _t: None, **kw)
    own = np.asarray(mesh.visual.material.image.convert("RGB"))
    attack = np.zeros((16, 16, 3), np.uint8)
    attack[..., 2] = 255  # all blue: easy to tell from the yellow duck
    out = print_texture(mesh, attack)
    assert out.shape == own.shape == (512, 512, 3)
    # the right half of UV space holds no optimised face: the duck's own texels, untouched
    np.testing.assert_array_equal(out[:, 300:], own[:, 300:])
    # where an optimised face lies, the attack's texels
    uv = np.asarray(mesh.visual.uv)[np.asarray(mesh.faces)[mesh.metadata["optimizable_faces"]]].mean(1)
    rows, cols = ((1 - uv[:, 1]) * 512).astype(int), (uv[:, 0] * 512).astype(int)
    assert (out[rows, cols] == [0, 0, 255]).all()
    assert print_texture(A.build_mesh("cube"), attack) is attack  # every face optimised: the attack's texture as it is
    # end to end: fabricate reads the region from the run's scene and prints the composite
    spec = default_scene()
    objs = [{**o.with_mesh(str(duck)), **kw} if o.role == "adversarial" else o.model_dump() for o in spec.objects]
    scene = spec.with_updates(objects=objs).model_dump(mode="json")
    tex = np.zeros((16, 16, 3), np.float32)
    tex[..., 2] = 1.0
    AttackArtifact(tex, {"attack": {"adversarial_mesh": None}, "scene": scene}).save(tmp_path / "run")
    res = _invoke(["fabricate", tmp_path / "run", "--out", tmp_path / "out", "--dpi", DPI])
    assert res.exit_code == 0, res.output
    assert "keep the mesh's own texture, written at 512 x 512 texels" in res.output
    png = next((tmp_path / "out" / "adversarial_obj").glob("*.png"))
    np.testing.assert_array_equal(np.asarray(Image.open(png).convert("RGB"))[:, 300:], own[:, 300:])
