"""Built-in meshes, mesh-file loading and the UV / texture contract of sim.assets."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from sim import assets as A
from sim import textures as tx

ALL = list(A.BUILTIN_MESHES)
OBJECTS = [n for n in ALL if n != "table"]

# Expected extents (x, y, z) in m; None = checked separately.
EXPECTED_EXTENTS_M = {
    "tomato_soup_can": (0.066, 0.066, 0.101),
    "mustard_bottle": (0.096, 0.058, 0.190),
    "cube": (0.06, 0.06, 0.06),
    "cylinder": (0.066, 0.066, 0.100),
    "patch": (None, None, A.PATCH_THICKNESS_M),
}

# Texel-density bound: coefficient of variation of sqrt(3D area / UV area) over a mesh's
# (optimizable) faces. Measured: 0 for the can, cylinder, cube, patch top and table (exact
# layouts), 0.033 for the mustard bottle (lathe shear through the shoulder), 0.045 for the duck
# and dog (xatlas charts). 0.1 leaves 2x headroom; one cap chart at half the common scale
# on the cylinder gives 0.22 (see test_texel_density_metric_catches_a_misscaled_chart).
TEXEL_CV_BOUND = 0.1


@pytest.fixture(scope="module")
def meshes():
    return {name: A.build_mesh(name) for name in ALL}


def _merged(mesh):
    m = mesh.copy()
    m.merge_vertices(merge_tex=True, merge_norm=True)
    return m


def _surface_colors(mesh, n=20000, seed=0):
    """Texture colours (n, 3) uint8 at area-uniform random surface points."""
    rng = np.random.default_rng(seed)
    area = np.asarray(mesh.area_faces)
    f = rng.choice(len(area), n, p=area / area.sum())
    w = rng.dirichlet(np.ones(3), n)
    uv = (np.asarray(mesh.visual.uv)[np.asarray(mesh.faces)[f]] * w[..., None]).sum(1)
    return tx.sample_texture(np.asarray(mesh.visual.material.image.convert("RGB")), uv, wrap=True)


def _silhouette_area_by_rows(mesh):
    """Front-view (x-z) silhouette area of a lathe: per distinct ring height, the x extent of
    that ring; between rings the silhouette edge is straight (trapezoid rule). Independent of
    silhouette_area_m2's rasterisation."""
    v = np.asarray(mesh.vertices)
    z = np.unique(np.round(v[:, 2], 9))
    width = np.array([np.ptp(v[np.abs(v[:, 2] - zz) < 1e-9, 0]) for zz in z])
    return float(np.sum(0.5 * (width[1:] + width[:-1]) * np.diff(z)))


# ----------------------------------------------------------------------------- built-ins
@pytest.mark.parametrize("name", ALL)
def test_builtin_has_texture_visuals_with_uv_per_vertex_and_image(meshes, name):
    m = meshes[name]
    assert isinstance(m.visual, trimesh.visual.TextureVisuals)
    uv = np.asarray(m.visual.uv)
    assert uv.shape == (len(m.vertices), 2) and np.all(np.isfinite(uv))
    if name == "table":
        assert uv.min() >= 0.0 and uv.max() > 1.0  # tiles; the renderer uses repeat wrap
    else:
        assert uv.min() >= 0.0 and uv.max() <= 1.0
    img = m.visual.material.image
    assert isinstance(img, Image.Image) and img.size == (A.TEXTURE_SIZE, A.TEXTURE_SIZE)
    assert m.metadata["name"] == name


@pytest.mark.parametrize("name", ALL)
def test_builtin_has_no_degenerate_faces_and_is_closed_with_outward_normals(meshes, name):
    m = meshes[name]
    assert 12 <= len(m.faces) <= 3000
    assert m.area_faces.min() > 1e-7  # m^2; the smallest built-in face is ~1e-6
    merged = _merged(m)
    assert merged.is_watertight
    assert merged.is_winding_consistent
    assert merged.volume > 0  # positive signed volume: normals point out


@pytest.mark.parametrize("name", ALL)
def test_builtin_optimizable_faces_is_a_bool_per_face(meshes, name):
    opt = meshes[name].metadata["optimizable_faces"]
    assert opt.dtype == bool and opt.shape == (len(meshes[name].faces),)
    assert opt.all() == (name != "patch")


@pytest.mark.parametrize("name", OBJECTS)
def test_builtin_origin_is_at_base_centre(meshes, name):
    lo, hi = meshes[name].bounds
    assert lo[2] == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose((lo[:2] + hi[:2]) / 2, 0.0, atol=1e-9)


def test_table_top_face_is_at_z_zero_and_centred(meshes):
    lo, hi = meshes["table"].bounds
    np.testing.assert_allclose(hi, [0.8, 0.8, 0.0], atol=1e-12)
    np.testing.assert_allclose(lo, [-0.8, -0.8, -0.03], atol=1e-12)


@pytest.mark.parametrize("name", list(EXPECTED_EXTENTS_M))
def test_builtin_extents_match_the_specified_size(meshes, name):
    ext = meshes[name].extents
    for got, want in zip(ext, EXPECTED_EXTENTS_M[name]):
        if want is not None:
            assert got == pytest.approx(want, rel=0.05)


@pytest.mark.parametrize("name", ["duck", "dog"])
def test_animals_are_10_to_15_cm(meshes, name):
    ext = meshes[name].extents
    assert ext.max() == pytest.approx(A.ANIMAL_LENGTH_M, rel=1e-6)
    assert 0.10 <= ext[2] <= 0.15


@pytest.mark.parametrize("name", ALL)
def test_texel_density_is_roughly_uniform(meshes, name):
    m = meshes[name]
    r = A.texel_density_ratio(m)[m.metadata["optimizable_faces"]]
    assert np.all(np.isfinite(r))
    assert r.std() / r.mean() < TEXEL_CV_BOUND


def test_texel_density_metric_catches_a_misscaled_chart(meshes):
    m = meshes["cylinder"].copy()
    x0, y0, x1, y1 = m.metadata["uv_islands"]["top"]
    uv = np.asarray(m.visual.uv).copy()
    inside = (uv[:, 0] >= x0) & (uv[:, 0] <= x1) & (uv[:, 1] >= y0) & (uv[:, 1] <= y1)
    uv[inside] = (uv[inside] - [x0, y0]) * 0.5 + [x0, y0]
    m.visual.uv = uv
    r = A.texel_density_ratio(m)
    assert r.std() / r.mean() > 2 * TEXEL_CV_BOUND


@pytest.mark.parametrize("name", ["tomato_soup_can", "mustard_bottle", "cylinder", "cube", "patch"])
def test_uv_side_m_is_the_surface_length_per_uv_unit(meshes, name):
    m = meshes[name]
    r = A.texel_density_ratio(m)[m.metadata["optimizable_faces"]]
    assert np.median(r) == pytest.approx(m.metadata["uv_side_m"], rel=0.01)


def test_wrap_layout_islands_do_not_overlap_and_side_is_below_caps(meshes):
    for name in ("cylinder", "tomato_soup_can", "mustard_bottle"):
        isl = meshes[name].metadata["uv_islands"]
        assert set(isl) == {"side", "top", "bottom"}
        boxes = list(isl.values())
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                a, b = boxes[i], boxes[j]
                assert a[2] <= b[0] or b[2] <= a[0] or a[3] <= b[1] or b[3] <= a[1]
        assert isl["side"][3] < min(isl["top"][1], isl["bottom"][1])


def test_cylinder_wrap_width_is_its_circumference_at_the_common_scale(meshes):
    m = meshes["cylinder"]
    u0, v0, u1, v1 = m.metadata["uv_islands"]["side"]
    # A 48-gon's perimeter is 0.07% short of the circle's.
    assert (u1 - u0) / (v1 - v0) == pytest.approx(np.pi * A.CYLINDER_DIAMETER_M / A.CYLINDER_HEIGHT_M, rel=1e-3)
    t0, s0, t1, s1 = m.metadata["uv_islands"]["top"]
    assert (t1 - t0) / (u1 - u0) == pytest.approx(1 / np.pi, rel=1e-3)  # cap diameter / circumference


def test_builtin_returns_independent_copies():
    a = A.build_mesh("cube")
    a.vertices = a.vertices * 2.0
    a.metadata["optimizable_faces"][:] = False
    b = A.build_mesh("cube")
    assert b.extents == pytest.approx([0.06] * 3)
    assert b.metadata["optimizable_faces"].all()


# ----------------------------------------------------------------------------- looks
def _fraction(colors, lo, hi):
    c = colors.astype(int)
    return float(np.mean(np.all((c >= lo) & (c <= hi), -1)))


def test_soup_can_is_mostly_red_and_white(meshes):
    c = _surface_colors(meshes["tomato_soup_can"])
    red = _fraction(c, (150, 0, 0), (255, 70, 70))
    white = _fraction(c, (210, 210, 200), (255, 255, 255))
    assert red > 0.25 and white > 0.25
    assert red + white > 0.6


def test_mustard_bottle_is_mostly_yellow(meshes):
    c = _surface_colors(meshes["mustard_bottle"]).astype(int)
    yellow = np.mean((c[:, 0] > 200) & (c[:, 1] > 150) & (c[:, 2] < 80))
    assert yellow > 0.7


def test_soup_can_lids_are_grey(meshes):
    m = meshes["tomato_soup_can"]
    top = np.nonzero(m.face_normals[:, 2] > 0.99)[0]
    uv = np.asarray(m.visual.uv)[m.faces[top]].mean(1)
    c = tx.sample_texture(np.asarray(m.visual.material.image), uv).astype(int)
    assert np.all(np.ptp(c, axis=-1) < 15)  # r ~ g ~ b


@pytest.mark.parametrize("name", OBJECTS + ["table", "plain"])
def test_default_texture_shape_dtype_and_matches_the_mesh_image(meshes, name):
    img = A.default_texture(name, 64)
    assert img.shape == (64, 64, 3) and img.dtype == np.uint8
    if name != "plain":
        full = A.default_texture(name)
        np.testing.assert_array_equal(full, np.asarray(meshes[name].visual.material.image))


def test_default_texture_unknown_name_raises_naming_it():
    with pytest.raises(A.AssetError, match="no_such_thing"):
        A.default_texture("no_such_thing")


def test_wood_texture_tiles_without_a_seam():
    img = tx.wood_texture(256).astype(float)
    # The jump across the tile edge is no larger than typical jumps inside the tile.
    inner = np.abs(np.diff(img, axis=1)).mean()
    edge = np.abs(img[:, 0] - img[:, -1]).mean()
    assert edge < 2.5 * inner
    # Along y the tile edge is a plank joint: it must look like the joints inside the tile.
    edge_y = np.abs(img[0] - img[-1]).mean()
    joint_y = np.abs(img[64] - img[63]).mean()  # 4 planks of 64 px
    assert 0.5 * joint_y < edge_y < 2.0 * joint_y


def test_table_uv_repeats_every_20_cm(meshes):
    m = meshes["table"]
    top = m.face_normals[:, 2] > 0.99
    v = np.unique(m.faces[top])
    duv = np.ptp(np.asarray(m.visual.uv)[v], axis=0)
    np.testing.assert_allclose(duv, np.array([1.6, 1.6]) / A.TABLE_TILE_M)


# ----------------------------------------------------------------------------- patch
def test_patch_top_area_equals_mustard_front_silhouette(meshes):
    side = A.patch_side_m()
    ref = _silhouette_area_by_rows(meshes["mustard_bottle"])
    assert side * side == pytest.approx(ref, rel=0.02)
    np.testing.assert_allclose(meshes["patch"].extents[:2], side, rtol=1e-9)


def test_silhouette_area_of_a_box_is_its_face_area():
    box = trimesh.creation.box((0.1, 0.05, 0.2))
    assert A.silhouette_area_m2(box, view_axis=1) == pytest.approx(0.1 * 0.2, rel=0.005)


def test_patch_top_face_owns_the_top_uv_square_and_the_rest_is_reserved(meshes):
    m = meshes["patch"]
    opt = m.metadata["optimizable_faces"]
    top = m.face_normals[:, 2] > 0.99
    np.testing.assert_array_equal(opt, top)
    u0, v0, u1, v1 = A.PATCH_TOP_UV
    uv = np.asarray(m.visual.uv)
    top_uv = uv[np.unique(m.faces[top])]
    np.testing.assert_allclose(top_uv.min(0), [u0, v0])
    np.testing.assert_allclose(top_uv.max(0), [u1, v1])
    rest = uv[m.faces[~top]].reshape(-1, 2)
    assert np.all((rest[:, 0] < u0) | (rest[:, 1] < v0))  # reserved strips only
    assert (u1 - u0) * (v1 - v0) > 0.9  # most of the texture


# ----------------------------------------------------------------------------- scale
_pos = st.floats(min_value=1e-3, max_value=1e3, allow_nan=False, allow_infinity=False)


@settings(max_examples=30, deadline=None)
@given(name=st.sampled_from(OBJECTS), scale=st.one_of(_pos, st.tuples(_pos, _pos, _pos)))
def test_scale_multiplies_extents_and_keeps_uv(meshes, name, scale):
    m = A.build_mesh(name, scale)
    base = meshes[name]
    np.testing.assert_allclose(m.extents, base.extents * np.broadcast_to(scale, (3,)), rtol=1e-9)
    np.testing.assert_array_equal(m.visual.uv, base.visual.uv)
    assert m.bounds[0][2] == pytest.approx(0.0, abs=1e-12 * max(np.max(scale), 1.0))
    assert _merged(m).volume > 0  # positive scales keep the winding outward


@pytest.mark.parametrize("scale", [0.0, -1.0, float("nan"), float("inf"), (1.0, 0.0, 1.0), (1.0, 2.0), "big"])
def test_bad_scale_raises_naming_the_source(scale):
    with pytest.raises(A.AssetError, match="cube.*scale"):
        A.build_mesh("cube", scale)


def test_unknown_builtin_name_raises_listing_the_choices():
    with pytest.raises(A.AssetError, match="tomato_soupcan.*mustard_bottle"):
        A.build_mesh("tomato_soupcan")


@pytest.mark.parametrize("size", [(0.0, 1.0), (1.0, float("nan")), (1.0,)])
def test_table_bad_size_raises_naming_the_field(size):
    with pytest.raises(A.AssetError, match="table: size_xy_m"):
        A.table_mesh(size)


# ----------------------------------------------------------------------------- files
@pytest.mark.parametrize("ext", ["obj", "ply", "stl", "glb"])
def test_mesh_file_without_uv_gets_an_atlas_and_keeps_its_origin(tmp_path, ext):
    box = trimesh.creation.box((0.1, 0.2, 0.3))
    box.apply_translation([1.0, 2.0, 3.0])
    path = tmp_path / f"box.{ext}"
    box.export(path)
    m = A.build_mesh(str(path), up_axis="z", placement="keep")  # as written: +Z up, origin kept
    uv = np.asarray(m.visual.uv)
    assert uv.shape == (len(m.vertices), 2) and uv.min() >= 0 and uv.max() <= 1
    assert len(m.faces) == 12 and m.area == pytest.approx(box.area)
    np.testing.assert_allclose(m.bounds, box.bounds, atol=1e-6)
    assert m.metadata["name"] == "box" and m.metadata["optimizable_faces"].all()
    assert A.texel_density_ratio(m).std() / A.texel_density_ratio(m).mean() < TEXEL_CV_BOUND


def test_mesh_file_recenter_puts_origin_at_base_centre(tmp_path):
    box = trimesh.creation.box((0.1, 0.2, 0.3))
    box.apply_translation([1.0, 2.0, 3.0])
    box.export(tmp_path / "box.stl")
    m = A.load_mesh_file(tmp_path / "box.stl", recenter=True)
    np.testing.assert_allclose(m.bounds, [[-0.05, -0.1, 0.0], [0.05, 0.1, 0.3]], atol=1e-6)


@pytest.mark.parametrize("ext", ["obj", "glb"])
def test_textured_mesh_file_keeps_its_uv_and_image(tmp_path, meshes, ext):
    src = meshes["cube"]
    path = tmp_path / f"cube.{ext}"
    src.export(path)
    m = A.build_mesh(path, 2.0, up_axis="z", placement="keep")
    np.testing.assert_allclose(m.visual.uv, src.visual.uv, atol=1e-6)
    np.testing.assert_allclose(m.extents, 2.0 * src.extents, rtol=1e-6)
    np.testing.assert_array_equal(
        np.asarray(m.visual.material.image.convert("RGB")), np.asarray(src.visual.material.image)
    )


def test_a_scan_in_millimetres_is_refused_in_one_line_suggesting_its_units(tmp_path):
    trimesh.creation.box((60.0, 60.0, 190.0)).export(tmp_path / "scan.stl")  # a bottle, exported in mm
    with pytest.raises(
        A.AssetError,
        match=r"scan\.stl: its longest side is 190 m .*not a plausible object \(1 cm to 60 cm\); "
        r"set `units: mm`",
    ) as e:
        A.build_mesh(tmp_path / "scan.stl")
    assert "\n" not in str(e.value)
    m = A.build_mesh(tmp_path / "scan.stl", units="mm")
    np.testing.assert_allclose(m.extents, [0.06, 0.06, 0.19], atol=1e-9)
    with pytest.raises(A.AssetError, match=r"longest side is 0.19 cm"):
        A.build_mesh(tmp_path / "scan.stl", units="mm", scale=0.01)


def test_a_gltf_file_is_y_up_by_its_spec_unless_told_otherwise(tmp_path):
    tall_along_y = trimesh.creation.box((0.05, 0.20, 0.08))  # how a +Y-up exporter writes a 20 cm tall object
    tall_along_y.export(tmp_path / "bottle.glb")
    m = A.build_mesh(tmp_path / "bottle.glb")
    np.testing.assert_allclose(m.extents, [0.05, 0.08, 0.20], atol=1e-9)  # standing: its height along +z
    assert m.bounds[0][2] == pytest.approx(0.0)
    np.testing.assert_allclose(
        A.build_mesh(tmp_path / "bottle.glb", up_axis="z").extents, [0.05, 0.20, 0.08], atol=1e-9
    )
    tall_along_y.export(tmp_path / "bottle.obj")
    np.testing.assert_allclose(
        A.build_mesh(tmp_path / "bottle.obj", up_axis="y").extents, [0.05, 0.08, 0.20], atol=1e-9
    )
    assert A.default_up_axis("x.gltf") == "y" and A.default_up_axis("x.OBJ") == "z"


def test_a_mesh_reaching_below_the_table_rests_on_its_lowest_point_and_is_recentred_with_notes(tmp_path):
    box = trimesh.creation.box((0.06, 0.06, 0.10))
    box.apply_translation([0.028, 0.0, 0.05 - 0.027])  # 2.7 cm below its origin, 2.8 cm off centre (YCB-like)
    box.export(tmp_path / "ycb.ply")
    said = []
    m = A.build_mesh(tmp_path / "ycb.ply", warn=said.append)
    np.testing.assert_allclose(m.bounds, [[-0.03, -0.03, 0.0], [0.03, 0.03, 0.10]], atol=1e-9)
    assert any("2.7 cm below its origin (below the table): rested on its lowest point" in t for t in said)
    assert any("2.8 cm from the base centre in x/y: recentred" in t for t in said)
    assert m.metadata["notes"] == said  # the mesh carries what was said
    kept = A.build_mesh(tmp_path / "ycb.ply", placement="keep", warn=said.append)
    np.testing.assert_allclose(kept.bounds, box.bounds, atol=1e-9)
    assert kept.metadata["notes"] == []


def test_loading_a_mesh_file_warns_about_nothing_it_was_configured_to_do(tmp_path):
    """A mesh exported around its centre (Blender's way) is rested on the table by placement auto, the
    documented default: a note on the mesh, not a UserWarning printed by every command that loads it."""
    trimesh.creation.box((0.06, 0.06, 0.10)).export(tmp_path / "centred.obj")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # any warning fails the test
        m = A.build_mesh(tmp_path / "centred.obj")
    assert m.bounds[0][2] == pytest.approx(0.0, abs=1e-9)
    assert len(m.metadata["notes"]) == 1 and "5.0 cm below its origin" in m.metadata["notes"][0]


def test_the_scene_notes_name_each_file_objects_notes_and_skip_built_ins(tmp_path):
    from sim.spec import default_scene, scene_from_dict

    trimesh.creation.box((0.06, 0.06, 0.10)).export(tmp_path / "centred.obj")
    assert A.scene_mesh_notes(default_scene()) == []
    d = default_scene().model_dump(mode="json")
    adv = next(o for o in d["objects"] if o["role"] == "adversarial")
    adv["mesh"] = str(tmp_path / "centred.obj")
    notes = A.scene_mesh_notes(scene_from_dict(d))
    assert len(notes) == 1 and notes[0].startswith(f"{adv['name']}: {tmp_path / 'centred.obj'}: the mesh reaches")
    adv["placement"] = "keep"  # the file's frame kept: nothing changed, nothing to say
    assert A.scene_mesh_notes(scene_from_dict(d)) == []


def test_a_scene_object_carries_units_up_axis_and_placement(tmp_path):
    from sim.spec import default_scene, scene_from_dict

    trimesh.creation.box((60.0, 40.0, 120.0)).export(tmp_path / "box_mm.stl")
    d = default_scene().model_dump(mode="json")
    adv = next(o for o in d["objects"] if o["role"] == "adversarial")
    adv.update(mesh=str(tmp_path / "box_mm.stl"), units="mm")
    spec = scene_from_dict(d)
    from sim.configs import object_local_centers

    k = spec.object_index("adversarial")
    assert object_local_centers(spec)[k] == pytest.approx([0.0, 0.0, 0.06])
    adv["units"] = "inch"
    with pytest.raises(Exception, match="units"):
        scene_from_dict(d)


def test_multi_part_file_is_concatenated(tmp_path):
    scene = trimesh.Scene([trimesh.creation.box((0.1, 0.1, 0.1)), trimesh.creation.icosphere(1, radius=0.05)])
    scene.export(tmp_path / "two.glb")
    m = A.load_mesh_file(tmp_path / "two.glb")
    assert len(m.faces) == 12 + 80


def test_vertex_colours_are_baked_into_the_atlas(tmp_path):
    box = trimesh.creation.box((0.1, 0.1, 0.1))
    box.visual.vertex_colors = np.tile([200, 30, 40, 255], (len(box.vertices), 1))
    box.export(tmp_path / "red.ply")
    m = A.load_mesh_file(tmp_path / "red.ply")
    c = _surface_colors(m, 2000).astype(int)
    assert np.all(np.abs(c - [200, 30, 40]) <= 2)


def test_tiled_uv_is_reatlased_and_the_texture_resampled(tmp_path):
    # A quad whose UVs run to 4 over a 2-colour checker: after loading, UVs are in [0, 1] and
    # the surface still shows both colours in equal parts.
    checker = np.zeros((64, 64, 3), np.uint8)
    checker[:32, :32] = checker[32:, 32:] = 255
    quad = trimesh.Trimesh(
        vertices=[[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]],
        faces=[[0, 1, 2], [0, 2, 3]],
        visual=trimesh.visual.TextureVisuals(uv=[[0, 0], [4, 0], [4, 4], [0, 4]], image=Image.fromarray(checker)),
        process=False,
    )
    quad.export(tmp_path / "tiled.glb")
    m = A.load_mesh_file(tmp_path / "tiled.glb")
    assert np.asarray(m.visual.uv).min() >= 0 and np.asarray(m.visual.uv).max() <= 1
    white = np.mean(_surface_colors(m, 4000)[:, 0] > 127)
    assert white == pytest.approx(0.5, abs=0.08)


def test_some_degenerate_faces_are_removed_with_a_note(tmp_path):
    p = tmp_path / "some.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 4\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        m = A.load_mesh_file(p)
    assert len(m.faces) == 1 and m.area == pytest.approx(0.5)
    assert len(m.metadata["notes"]) == 1 and re.search(
        r"some\.obj: removed 1 degenerate face\(s\) of 2", m.metadata["notes"][0]
    )


def _bad_files(tmp_path):
    garbage = bytes(range(256)) * 8
    files = {
        "garbage.obj": garbage,
        "garbage.stl": garbage,
        "garbage.glb": garbage,
        "garbage.ply": garbage,
        "notes.xyzw": b"hello",
        "empty.obj": b"# no geometry\n",
        "nan.obj": b"v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
        "inf.obj": b"v inf 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
        "flat.obj": b"v 0 0 0\nv 1 0 0\nv 2 0 0\nv 3 0 0\nf 1 2 3\nf 2 3 4\n",
        "points.ply": b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
        b"property float z\nend_header\n0 0 0\n1 1 1\n",
    }
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    return list(files)


BAD = [
    "garbage.obj",
    "garbage.stl",
    "garbage.glb",
    "garbage.ply",
    "notes.xyzw",
    "empty.obj",
    "nan.obj",
    "inf.obj",
    "flat.obj",
    "points.ply",
]


@pytest.mark.parametrize("name", BAD)
def test_bad_mesh_file_raises_asset_error_naming_it(tmp_path, name):
    assert name in _bad_files(tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(A.AssetError, match=name.replace(".", r"\.")):
            A.build_mesh(str(tmp_path / name))


def test_missing_mesh_file_raises_naming_it(tmp_path):
    with pytest.raises(A.AssetError, match="nowhere.obj.*not found"):
        A.build_mesh(tmp_path / "nowhere.obj")


def test_asset_error_is_a_value_error_and_an_advobj_error():
    from sim.errors import AdvobjError

    assert issubclass(A.AssetError, ValueError) and issubclass(A.AssetError, AdvobjError)


# ----------------------------------------------------------------------------- baking
def test_rasterize_uv_barycentrics_reproduce_the_texel_centre():
    uv = np.array([[0.1, 0.1], [0.9, 0.2], [0.3, 0.95]])
    face_id, bary = tx.rasterize_uv(uv, np.array([[0, 1, 2]]), 64)
    inside = face_id == 0
    assert 0.3 < inside.mean() < 0.4  # triangle area 0.2925 plus its outline
    rows, cols = np.nonzero(inside)
    p = (bary[rows, cols, :, None] * uv[None]).sum(1)
    centre = np.stack([(cols + 0.5) / 64, 1 - (rows + 0.5) / 64], -1)
    interior = np.all(bary[rows, cols] > 0.02, -1)  # clamping moves only outline texels
    np.testing.assert_allclose(p[interior], centre[interior], atol=1e-9)
    np.testing.assert_allclose(bary[inside].sum(-1), 1.0)


def test_bake_texture_on_tiny_and_sliver_faces_stays_finite():
    # Faces far below one texel and a needle-thin sliver: no division blow-up, colours valid.
    v = np.array([[0, 0, 0], [1e-9, 0, 0], [0, 1e-9, 0], [0, 0, 0], [1, 0, 0], [0.5, 1e-12, 0]], float)
    uv = np.array([[0.5, 0.5], [0.5 + 1e-9, 0.5], [0.5, 0.5 + 1e-9], [0.0, 0.0], [1.0, 0.0], [0.5, 1e-12]])
    img = tx.bake_texture(v, np.array([[0, 1, 2], [3, 4, 5]]), uv, lambda p, n, t: np.ones((len(p), 3)) * 0.25, 32)
    assert img.dtype == np.uint8 and np.all(np.isfinite(img))
    assert (img == 64).all(-1).any()
