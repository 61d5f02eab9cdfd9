"""Hostile mesh input: the UV atlas cache, OBJ/MTL references, malformed and oversized mesh files.

Every refusal is one line naming the file; nothing outside the mesh's folder or the cache entry is
read or written, and nothing blocks or inflates without bound.
"""

from __future__ import annotations

import io
import os
import stat
import threading
import tracemalloc
import warnings
import zipfile

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

import sim.assets as A

BODY = "v 0 0 0\nv 0.05 0 0\nv 0 0.05 0\nv 0 0 0.05\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


# ============================================================================ UV atlas cache
@pytest.fixture
def cache(tmp_path, monkeypatch):
    """A fresh, empty disk cache and no in-memory atlases; returns the cache's uv folder."""
    monkeypatch.setenv("ADVOBJ_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(A, "_ATLAS_MEMO", {})
    return tmp_path / "cache" / "uv"


@pytest.fixture(scope="module")
def sphere():
    """A small mesh, its atlas cache key and its atlas as the cache stores it (vmap, idx, uv)."""
    import xatlas

    m = trimesh.creation.icosphere(subdivisions=2, radius=0.05)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    vmap, idx, uv = xatlas.parametrize(np.float32(v), np.uint32(f))
    hit = (np.int64(vmap), np.int64(idx), np.clip(np.float64(uv), 0.0, 1.0))
    return v, f, A._atlas_key(np.float32(v), np.uint32(f)), hit


def _no_rebuild(monkeypatch):
    import xatlas

    def refuse(*_a):
        raise AssertionError("the atlas was rebuilt, not read from the cache")

    monkeypatch.setattr(xatlas, "parametrize", refuse)


def _fresh_command(monkeypatch):
    monkeypatch.setattr(A, "_ATLAS_MEMO", {})


def test_atlas_cache_round_trips_through_a_regular_entry(cache, sphere, monkeypatch):
    v, f, key, hit = sphere
    first = A._atlas(v, f)
    entry = cache / f"{key}.npz"
    assert stat.S_ISREG(os.lstat(entry).st_mode)
    _fresh_command(monkeypatch)
    _no_rebuild(monkeypatch)
    for a, b in zip(first, A._atlas(v, f)):
        np.testing.assert_array_equal(a, b)


def test_planted_symlinks_for_temporaries_and_the_entry_leave_their_targets_unchanged(cache, sphere, tmp_path):
    v, f, key, hit = sphere
    cache.mkdir(parents=True)
    victims = []
    pid = os.getpid()
    for k, p in enumerate(range(pid - 64, pid + 64)):  # the names a pid-based temporary would take
        victim = tmp_path / f"victim{k}"
        victim.write_bytes(b"precious")
        os.symlink(victim, cache / f".{key}.{p}.npz")
        victims.append(victim)
    entry_victim = tmp_path / "entry_victim"
    entry_victim.write_bytes(b"precious")
    os.symlink(entry_victim, cache / f"{key}.npz")
    with pytest.warns(UserWarning, match="not a regular file: replaced"):
        A._atlas(v, f)
    assert all(p.read_bytes() == b"precious" for p in [*victims, entry_victim])
    assert stat.S_ISREG(os.lstat(cache / f"{key}.npz").st_mode)
    assert not [p for p in cache.iterdir() if p.name.endswith(".tmp")]  # no temporary left behind


def test_a_symlinked_entry_is_never_read_even_when_it_points_at_a_valid_atlas(cache, sphere, tmp_path, monkeypatch):
    v, f, key, hit = sphere
    A._atlas(v, f)
    entry = cache / f"{key}.npz"
    elsewhere = tmp_path / "elsewhere.npz"
    os.replace(entry, elsewhere)
    os.symlink(elsewhere, entry)
    assert A._read_atlas_entry(entry, key, len(v), len(f)) is None
    assert A._read_atlas_entry(elsewhere, key, len(v), len(f)) is not None


def test_a_fifo_as_the_cache_entry_does_not_block_and_is_replaced(cache, sphere):
    v, f, key, hit = sphere
    cache.mkdir(parents=True)
    os.mkfifo(cache / f"{key}.npz")
    done = threading.Event()

    def run():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            A._atlas(v, f)
        done.set()

    threading.Thread(target=run, daemon=True).start()
    assert done.wait(20), "reading a FIFO cache entry blocked"
    assert stat.S_ISREG(os.lstat(cache / f"{key}.npz").st_mode)


def _npy_header(shape, dtype) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": np.dtype(dtype).str, "fortran_order": False, "shape": shape})
    return buf.getvalue()


def _entry_members(key, v, f):
    """Valid-looking small members key/vmap/idx as npy bytes."""
    n = 3 * len(f)
    out = {}
    for name, arr in (
        ("key", np.frombuffer(key.encode(), np.uint8)),
        ("vmap", np.zeros(n, np.int64)),
        ("idx", np.arange(3 * len(f), dtype=np.int64).reshape(-1, 3)),
    ):
        buf = io.BytesIO()
        np.save(buf, arr)
        out[f"{name}.npy"] = buf.getvalue()
    return out


BOMB_PEAK_CAP = 8 << 20  # bytes of Python/numpy allocations while reading a bomb entry


def test_a_deflate_bomb_entry_is_refused_before_it_is_inflated(cache, sphere):
    v, f, key, hit = sphere
    cache.mkdir(parents=True)
    entry = cache / f"{key}.npz"
    inflated = 32 << 20  # 32 MiB of zeros deflate to ~32 KB, inside the file-size cap for this mesh
    with zipfile.ZipFile(entry, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in _entry_members(key, v, f).items():
            z.writestr(name, data)
        with z.open("uv.npy", "w", force_zip64=True) as w:
            w.write(_npy_header((inflated // 16, 2), np.float64))
            zeros = bytes(1 << 20)
            for _ in range(inflated >> 20):
                w.write(zeros)
    assert entry.stat().st_size < 100_000
    tracemalloc.start()
    try:
        got = A._read_atlas_entry(entry, key, len(v), len(f))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert got is None and peak < BOMB_PEAK_CAP


def test_an_entry_whose_npy_header_claims_a_huge_shape_is_refused_without_allocating_it(cache, sphere):
    v, f, key, hit = sphere
    cache.mkdir(parents=True)
    entry = cache / f"{key}.npz"
    with zipfile.ZipFile(entry, "w", zipfile.ZIP_STORED) as z:
        for name, data in _entry_members(key, v, f).items():
            z.writestr(name, data)
        z.writestr("uv.npy", _npy_header((1 << 30, 2), np.float64) + bytes(64))  # claims 16 GiB
    tracemalloc.start()
    try:
        got = A._read_atlas_entry(entry, key, len(v), len(f))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert got is None and peak < BOMB_PEAK_CAP


def test_an_oversized_entry_file_is_refused_by_its_size(cache, sphere):
    v, f, key, hit = sphere
    cache.mkdir(parents=True)
    entry = cache / f"{key}.npz"
    with open(entry, "wb") as out:
        out.truncate(1 << 30)  # sparse: 1 GiB on paper, nothing on disk
    assert A._read_atlas_entry(entry, key, len(v), len(f)) is None


def _tampered(hit, what):
    vmap, idx, uv = (a.copy() for a in hit)
    if what == "nan_uv":
        uv[0, 0] = np.nan
    elif what == "uv_above_one":
        uv[1, 1] = 1.5
    elif what == "negative_uv":
        uv[2, 0] = -0.25
    elif what == "vmap_out_of_range":
        vmap[0] = 10**9
    elif what == "idx_out_of_range":
        idx[0, 0] = len(vmap)
    elif what == "wrong_idx_shape":
        idx = idx[:-1]
    elif what == "uv_rows_differ_from_vmap":
        uv = uv[:-1]
    elif what == "float32_uv":
        uv = uv.astype(np.float32)
    return vmap, idx, uv


TAMPERINGS = [
    "nan_uv",
    "uv_above_one",
    "negative_uv",
    "vmap_out_of_range",
    "idx_out_of_range",
    "wrong_idx_shape",
    "uv_rows_differ_from_vmap",
    "float32_uv",
]


@pytest.mark.parametrize("what", TAMPERINGS)
def test_a_tampered_entry_is_refused_and_rebuilt(cache, sphere, monkeypatch, what):
    v, f, key, hit = sphere
    good = A._atlas(v, f)
    A._write_atlas_entry(cache, key, _tampered(hit, what))
    assert A._read_atlas_entry(cache / f"{key}.npz", key, len(v), len(f)) is None
    _fresh_command(monkeypatch)
    for a, b in zip(good, A._atlas(v, f)):  # dropped and rebuilt: the same atlas as before
        np.testing.assert_array_equal(a, b)
    assert A._read_atlas_entry(cache / f"{key}.npz", key, len(v), len(f)) is not None


def test_an_entry_recording_another_key_is_refused(cache, sphere):
    v, f, key, hit = sphere
    other = "0" * 64
    A._write_atlas_entry(cache, other, hit)  # another mesh's name, this atlas
    os.replace(cache / f"{other}.npz", cache / f"{key}.npz")  # ... moved under this mesh's name
    assert A._read_atlas_entry(cache / f"{key}.npz", key, len(v), len(f)) is None
    assert A._read_atlas_entry(cache / f"{key}.npz", other, len(v), len(f)) is not None


@settings(max_examples=40, deadline=None)
@given(x=st.floats(allow_nan=True, allow_infinity=True, width=64))
def test_a_cached_uv_is_accepted_exactly_when_it_lies_in_the_unit_square(tmp_path_factory, sphere, x):
    v, f, key, hit = sphere
    folder = tmp_path_factory.mktemp("uv")
    vmap, idx, uv = (a.copy() for a in hit)
    uv[3, 1] = x
    A._write_atlas_entry(folder, key, (vmap, idx, uv))
    got = A._read_atlas_entry(folder / f"{key}.npz", key, len(v), len(f))
    assert (got is not None) == (0.0 <= x <= 1.0)


# ============================================================================ OBJ / MTL references
def _png(path, color=(200, 30, 30)):
    from PIL import Image

    Image.new("RGB", (8, 8), color).save(path)
    return path


@pytest.fixture
def folders(tmp_path):
    """``tmp_path/mesh`` (the mesh's folder) beside a secret image and an outside material library."""
    _png(tmp_path / "secret.png")
    (tmp_path / "evil.mtl").write_text("newmtl m\nmap_Kd secret.png\n")
    d = tmp_path / "mesh"
    d.mkdir()
    return d


BYPASSES = {
    "tab_before_map_name": ("mtllib a.mtl\n", "newmtl m\nmap_Kd\t../secret.png\n", r"map_Kd '\.\./secret\.png'"),
    "leading_space_before_mtllib": (" mtllib ../evil.mtl\n", None, r"mtllib '\.\./evil\.mtl'"),
    "leading_tab_before_mtllib": ("\tmtllib ../evil.mtl\n", None, r"mtllib '\.\./evil\.mtl'"),
    "two_libraries_on_one_line": ("mtllib a.mtl ../evil.mtl\n", "newmtl m\n", r"mtllib '\.\./evil\.mtl'"),
    "uppercase_keyword": ("MTLLIB ../evil.mtl\n", None, r"mtllib '\.\./evil\.mtl'"),
    "mtllib_in_a_comment": ("# mtllib ../evil.mtl\n", None, r"mtllib '\.\./evil\.mtl'"),  # trimesh reads it
    "continued_mtllib_line": ("mtllib \\\n../evil.mtl\n", None, r"mtllib '\.\./evil\.mtl'"),
    "continued_keyword": ("mtl\\\nlib ../evil.mtl\n", None, r"mtllib '\.\./evil\.mtl'"),
    "crlf_lines": ("mtllib a.mtl\r\n", "newmtl m\r\nmap_Kd ../secret.png\r\n", r"map_Kd '\.\./secret\.png'"),
    "scale_option": ("mtllib a.mtl\n", "newmtl m\nmap_Kd -s 1 1 1 ../secret.png\n", r"'\.\./secret\.png'"),
    "many_options": (
        "mtllib a.mtl\n",
        "newmtl m\nmap_Kd -blendu on -o 0 0 -mm 0 1 -clamp on ../secret.png\n",
        r"'\.\./secret\.png'",
    ),
    "bump_with_multiplier": ("mtllib a.mtl\n", "newmtl m\nbump -bm 0.5 ../secret.png\n", r"bump '\.\./secret\.png'"),
    "disp": ("mtllib a.mtl\n", "newmtl m\ndisp ../secret.png\n", r"disp '\.\./secret\.png'"),
    "decal": ("mtllib a.mtl\n", "newmtl m\ndecal ../secret.png\n", r"decal '\.\./secret\.png'"),
    "refl_with_type": ("mtllib a.mtl\n", "newmtl m\nrefl -type sphere ../secret.png\n", r"refl '\.\./secret\.png'"),
    "map_bump_mixed_case": ("mtllib a.mtl\n", "newmtl m\nMap_Bump ../secret.png\n", r"'\.\./secret\.png'"),
    "leading_space_before_map": ("mtllib a.mtl\n", "newmtl m\n  map_Kd ../secret.png\n", r"'\.\./secret\.png'"),
    "continued_map_line": ("mtllib a.mtl\n", "newmtl m\nmap_Kd \\\n../secret.png\n", r"'\.\./secret\.png'"),
    "absolute_image_path": ("mtllib a.mtl\n", "newmtl m\nmap_Kd {secret}\n", r"map_Kd '.*secret\.png'"),
    "dotdot_through_a_subfolder": ("mtllib a.mtl\n", "newmtl m\nmap_Kd sub/../../secret.png\n", r"secret\.png'"),
    "name_with_spaces_after_options": (
        "mtllib a.mtl\n",
        "newmtl m\nmap_Kd -s 1 1 1 ../my secret.png\n",
        r"'\.\./my",  # the first word already leaves; the whole name would too
    ),
}


@pytest.mark.parametrize("case", list(BYPASSES))
def test_an_obj_reference_leaving_the_mesh_folder_is_refused_in_one_line(folders, case):
    obj_head, mtl, match = BYPASSES[case]
    (folders / "sub").mkdir()
    if mtl is not None:
        (folders / "a.mtl").write_text(mtl.format(secret=folders.parent / "secret.png"), newline="")
    (folders / "a.obj").write_text(obj_head + BODY, newline="")
    with pytest.raises(A.AssetError, match=match + r".* lies outside the mesh's folder") as e:
        A.load_mesh_file(folders / "a.obj")
    assert "\n" not in str(e.value) and "a.obj" in str(e.value)


def _must_not_block(fn, seconds=20):
    """``fn()``'s exception (or None), failing the test if it runs longer than ``seconds``."""
    out = {}

    def run():
        try:
            fn()
        except BaseException as err:  # noqa: BLE001 - handed back to the test
            out["err"] = err
        out["done"] = True

    threading.Thread(target=run, daemon=True).start()
    t = threading.Event()
    for _ in range(seconds * 10):
        if out.get("done"):
            break
        t.wait(0.1)
    assert out.get("done"), "the load blocked"
    return out.get("err")


@pytest.mark.parametrize("which", ["mtllib", "map_Kd", "the_mesh_file"])
def test_a_fifo_named_by_an_obj_is_refused_without_blocking(folders, which):
    os.mkfifo(folders / "pipe")
    if which == "mtllib":
        (folders / "a.obj").write_text("mtllib pipe\n" + BODY)
    elif which == "map_Kd":
        (folders / "a.mtl").write_text("newmtl m\nmap_Kd pipe\n")
        (folders / "a.obj").write_text("mtllib a.mtl\n" + BODY)
    target = folders / ("pipe.obj" if which == "the_mesh_file" else "a.obj")
    if which == "the_mesh_file":
        os.rename(folders / "pipe", target)
    err = _must_not_block(lambda: A.load_mesh_file(target))
    assert isinstance(err, A.AssetError) and "not a regular file" in str(err) and "\n" not in str(err)


@pytest.mark.parametrize("what", ["mtl", "image"])
def test_a_symlink_beside_the_mesh_pointing_outside_is_refused(folders, what):
    if what == "mtl":
        os.symlink(folders.parent / "evil.mtl", folders / "a.mtl")
        match = r"mtllib 'a\.mtl' lies outside"
    else:
        os.symlink(folders.parent / "secret.png", folders / "tex.png")
        (folders / "a.mtl").write_text("newmtl m\nmap_Kd tex.png\n")
        match = r"map_Kd 'tex\.png' lies outside"
    (folders / "a.obj").write_text("mtllib a.mtl\n" + BODY)
    with pytest.raises(A.AssetError, match=match):
        A.load_mesh_file(folders / "a.obj")


def test_a_textured_obj_with_its_texture_beside_it_still_loads_the_texture(folders):
    _png(folders / "my tex.png", (10, 200, 10))
    # trimesh reads the whole rest of a map_Kd line as the name; options on other statements are fine
    (folders / "a.mtl").write_text("newmtl m\nKd 1 1 1\nmap_Kd my tex.png\nbump -bm 1 -s 1 1 1 my tex.png\n")
    (folders / "a.obj").write_text(
        "mtllib a.mtl\nv 0 0 0\nv 0.05 0 0\nv 0 0.05 0\nvt 0 0\nvt 1 0\nvt 0 1\nusemtl m\nf 1/1 2/2 3/3\n"
    )
    m = A.load_mesh_file(folders / "a.obj")
    img = np.asarray(m.visual.material.image.convert("RGB"))
    assert m.metadata["uv_source"] == "file" and img.shape == (8, 8, 3) and tuple(img[0, 0]) == (10, 200, 10)


def test_a_gltf_buffer_outside_the_mesh_folder_is_refused_by_the_loader_gate(folders):
    import json

    files = trimesh.exchange.gltf.export_gltf(trimesh.creation.box((0.05, 0.05, 0.05)))
    doc = json.loads(files["model.gltf"])
    for k, buffer in enumerate(doc["buffers"]):
        (folders.parent / f"outside{k}.bin").write_bytes(files[buffer["uri"]])
        buffer["uri"] = f"../outside{k}.bin"
    (folders / "a.gltf").write_text(json.dumps(doc))
    with pytest.raises(A.AssetError, match=r"a\.gltf: reference '\.\./outside\d\.bin' lies outside"):
        A.load_mesh_file(folders / "a.gltf")


def test_the_trimesh_pin_covers_the_installed_parser():
    import importlib.metadata
    import tomllib
    from pathlib import Path

    from packaging.requirements import Requirement

    doc = tomllib.loads((Path(__file__).parents[2] / "pyproject.toml").read_text())
    (req,) = [Requirement(d) for d in doc["project"]["dependencies"] if d.startswith("trimesh")]
    assert req.specifier.contains(importlib.metadata.version("trimesh"))
    assert any(s.operator == "<" for s in req.specifier)  # an upper bound: a new parser is checked first


# ============================================================================ malformed vertices
@pytest.mark.parametrize(
    "text,line",
    [
        ("v 0 0 0\nv 0 1\nv 0 1 0\nf 1 2 3\n", 2),
        ("v 0 1\nv 1 0\nv 0 0\nf 1 2 3\n", 1),
        ("v 0 0 0\nv 1\nv 0 1 0\nv 1 1 1\nf 1 2 3\n", 2),
        ("v 0 0 0\nv 0.05 0\nv 0 0.05 0 1\nf 1 2 3\n", 2),  # 9 numbers in all: would reshape silently
    ],
)
def test_a_truncated_vertex_line_is_one_line_naming_the_file_and_line(tmp_path, text, line):
    (tmp_path / "short.obj").write_text(text)
    with pytest.raises(A.AssetError, match=rf"short\.obj: line {line}: a vertex needs x y z") as e:
        A.build_mesh(tmp_path / "short.obj")
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("bad", ["nan", "inf", "-inf", "NaN", "1e999"])
def test_a_non_finite_vertex_is_one_line_naming_the_file_and_line(tmp_path, bad):
    (tmp_path / "nf.obj").write_text(f"v 0 0 0\nv 0.05 0 0\nv 0 {bad} 0\nf 1 2 3\n")
    with pytest.raises(A.AssetError, match=r"nf\.obj: 1 vertices are not finite \(NaN/inf\), the first on line 3"):
        A.build_mesh(tmp_path / "nf.obj")


@settings(max_examples=40, deadline=None)
@given(x=st.floats(allow_nan=True, allow_infinity=True, width=64))
def test_any_vertex_coordinate_loads_or_is_one_clear_error(tmp_path_factory, x):
    d = tmp_path_factory.mktemp("v")
    (d / "x.obj").write_text(f"v 0 0 0\nv 0.05 0 0\nv 0 0.05 0\nv {x!r} 0.02 0.03\nf 1 2 3\nf 1 2 4\n")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            m = A.build_mesh(d / "x.obj")
        except A.AssetError as e:
            assert "x.obj" in str(e) and "\n" not in str(e)
        else:
            assert np.all(np.isfinite(m.vertices)) and np.all((m.visual.uv >= 0) & (m.visual.uv <= 1))


# ============================================================================ size and face caps
@pytest.fixture
def tiny_caps(monkeypatch):
    """Caps of 10 faces and 4 KiB, and a trimesh that must not be asked to parse anything."""
    monkeypatch.setattr(A, "MAX_MESH_FACES", 10)
    monkeypatch.setattr(A, "MAX_MESH_FILE_BYTES", 4096)

    def refuse(*_a, **_k):
        raise AssertionError("trimesh parsed a file over the cap")

    monkeypatch.setattr(A.trimesh, "load", refuse)


def _fan(n_vertices: int) -> str:
    return "".join(f"v {np.cos(a) * 0.03:.4f} {np.sin(a) * 0.03:.4f} 0\n" for a in np.linspace(0, 6, n_vertices))


@pytest.mark.parametrize(
    "faces,count",
    [
        ("".join(f"f 1 {k} {k + 1}\n" for k in range(2, 14)), 11),  # 12 triangles: stops past the cap
        ("f " + " ".join(str(k) for k in range(1, 15)) + "\n", 12),  # one 14-gon: 12 triangles
        ("f 1 2 3 4 5 6 \\\n7 8 9 10 11 12 13 14\n", 12),  # a continued polygon
        ("".join(f"\tf 1 {k} {k + 1}\n" for k in range(2, 14)), 11),  # leading whitespace
    ],
)
def test_an_obj_over_the_face_cap_is_refused_before_parsing(tmp_path, tiny_caps, faces, count):
    (tmp_path / "big.obj").write_text(_fan(14) + faces)
    with pytest.raises(A.AssetError, match=rf"big\.obj: at least {count} faces, more than the 10 advobj loads"):
        A.load_mesh_file(tmp_path / "big.obj")


def test_a_mesh_file_over_the_size_cap_is_refused_by_its_size(tmp_path, tiny_caps):
    with open(tmp_path / "huge.stl", "wb") as f:
        f.truncate(1 << 30)  # sparse
    with pytest.raises(A.AssetError, match=r"huge\.stl: 1,073,741,824 bytes, more than the 4,096 advobj reads"):
        A.load_mesh_file(tmp_path / "huge.stl")


def _headers():
    import json
    import struct

    gltf = {
        "asset": {"version": "2.0"},
        "accessors": [{"count": 3_000_000}, {"count": 33}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 1}, "indices": 0}]}],
    }
    js = json.dumps(gltf).encode()
    js += b" " * (-len(js) % 4)
    glb = struct.pack("<4sII", b"glTF", 2, 20 + len(js)) + struct.pack("<II", len(js), 0x4E4F534A) + js
    return {
        "claims.stl": (b"\0" * 80 + struct.pack("<I", 10**9), "1,000,000,000"),
        "claims.ply": (
            b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nelement face 123456\nend_header\n",
            "123,456",
        ),
        "claims.off": (b"OFF\n# a comment\n3 99999 0\n", "99,999"),
        "claims.glb": (glb, "1,000,000"),
        "claims.gltf": (json.dumps(gltf).encode(), "1,000,000"),
    }


@pytest.mark.parametrize("name", list(_headers()))
def test_a_binary_or_headed_file_declaring_too_many_faces_is_refused_from_its_header(tmp_path, tiny_caps, name):
    data, shown = _headers()[name]
    (tmp_path / name).write_bytes(data)
    with pytest.raises(A.AssetError, match=rf"{name}: {shown} faces, more than the 10 advobj loads"):
        A.load_mesh_file(tmp_path / name)


def test_a_mesh_under_the_caps_still_loads(tmp_path, monkeypatch):
    monkeypatch.setattr(A, "MAX_MESH_FACES", 4)
    (tmp_path / "ok.obj").write_text(BODY)
    assert len(A.load_mesh_file(tmp_path / "ok.obj").faces) == 4


@pytest.mark.slow
def test_an_obj_just_over_the_default_face_cap_is_refused_before_parsing(tmp_path, monkeypatch):
    monkeypatch.setattr(A.trimesh, "load", lambda *_a, **_k: pytest.fail("trimesh parsed a file over the cap"))
    with open(tmp_path / "big.obj", "w") as f:
        f.write("v 0 0 0\nv 0.05 0 0\nv 0 0.05 0\n")
        f.write("f 1 2 3\n" * (A.MAX_MESH_FACES + 1))
    with pytest.raises(A.AssetError, match=r"big\.obj: at least 2,000,001 faces, more than the 2,000,000"):
        A.load_mesh_file(tmp_path / "big.obj")
