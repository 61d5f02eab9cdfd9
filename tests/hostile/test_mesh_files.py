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
