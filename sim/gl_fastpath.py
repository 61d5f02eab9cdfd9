"""A faster ``pyrender`` uniform upload: cached locations and direct ctypes calls.

Why: at 128x128 the llvmpipe rasteriser is quick and pyrender's Python overhead dominates a
frame. Profiling ``ReachEnv.step`` showed ~90 ``ShaderProgram.set_uniform`` calls per render,
each doing a ``glGetUniformLocation`` round trip and going through PyOpenGL's array-converting,
error-checking wrappers (~50 us per uniform): about a third of the frame time.

:func:`install` replaces ``pyrender.shader_program.ShaderProgram.set_uniform`` with a version
that

* caches each uniform's location per program object (a location never changes while the linked
  program lives; the cache is keyed by the GL program id, so a re-linked program starts afresh);
* calls the GL entry points through plain ``ctypes`` prototypes (no per-call ``glGetError``)
  for the value types pyrender actually sends (1-D float/int arrays, 2-D float matrices,
  Python floats, ints and bools);
* falls back to pyrender's own implementation for anything else, and keeps its semantics: an
  unknown uniform name (location -1) is silently ignored, as pyrender does.

It also wraps ``Renderer._bind_lighting``, which pyrender calls for every primitive although the
light uniforms of a program are the same for all primitives of one pass (uniform values are
program state and persist between draws): the second and later calls for the same program in the
same pass are skipped. Only when that is exact: no shadow maps, and no more lights than pyrender's
per-type maximum (beyond it pyrender sorts lights by distance to each node).

The rendered images are bit-identical with and without it (``tests/sim/test_gl_fastpath.py``);
``benchmarks/bench_env.py --no-fastpath`` measures the difference. Set ``ADVOBJ_GL_FASTPATH=0``
to disable it.
"""

from __future__ import annotations

import ctypes
import os

import numpy as np

__all__ = ["install", "uninstall", "installed"]

_ORIGINAL = None
_ORIGINAL_LIGHTING = None
_ORIGINAL_FORWARD = None
_FUNCS: dict | None = None

_c_int, _c_uint, _c_float, _c_ptr, _c_bool = (
    ctypes.c_int,
    ctypes.c_uint,
    ctypes.c_float,
    ctypes.c_void_p,
    ctypes.c_ubyte,
)


def _load_funcs() -> dict:
    """``name -> ctypes function`` bound to the GL library PyOpenGL itself uses."""
    from OpenGL.platform import PLATFORM  # lazy: robot_io start-up (pyrender, OpenGL)

    lib = PLATFORM.GL
    out = {}

    def proto(name, *argtypes):
        out[name] = ctypes.CFUNCTYPE(None, *argtypes)((name, lib))

    proto("glUniform1f", _c_int, _c_float)
    proto("glUniform1i", _c_int, _c_int)
    proto("glUniform1ui", _c_int, _c_uint)
    for n in (1, 2, 3, 4):
        for suffix in ("fv", "iv", "uiv"):
            proto(f"glUniform{n}{suffix}", _c_int, _c_int, _c_ptr)
    for r in (2, 3, 4):
        for c in (2, 3, 4):
            name = f"glUniformMatrix{r}fv" if r == c else f"glUniformMatrix{r}x{c}fv"
            proto(name, _c_int, _c_int, _c_bool, _c_ptr)
    out["glGetUniformLocation"] = ctypes.CFUNCTYPE(_c_int, _c_uint, ctypes.c_char_p)(("glGetUniformLocation", lib))
    return out


_VEC_SUFFIX = {"f": ("fv", np.float32), "i": ("iv", np.int32), "u": ("uiv", np.uint32)}


def _fast_set_uniform(self, name, value, unsigned=False):
    f = _FUNCS
    pid = self._program_id
    cache = self.__dict__.get("_advobj_uniform_locs")
    if cache is None or cache[0] != pid:
        cache = (pid, {})
        self._advobj_uniform_locs = cache
    locs = cache[1]
    loc = locs.get(name)
    if loc is None:
        loc = f["glGetUniformLocation"](pid, name.encode())
        locs[name] = loc
    if loc == -1:
        return  # pyrender ignores unknown uniforms (its ValueError is swallowed)
    if type(value) is np.ndarray:
        if value.ndim == 1 and 1 <= value.shape[0] <= 4:
            if np.issubdtype(value.dtype, np.unsignedinteger) or unsigned:
                kind = "u"
            elif np.issubdtype(value.dtype, np.integer):
                kind = "i"
            else:
                kind = "f"
            suffix, dtype = _VEC_SUFFIX[kind]
            arr = np.ascontiguousarray(value, dtype=dtype)
            f[f"glUniform{arr.shape[0]}{suffix}"](loc, 1, arr.ctypes.data)
            return
        if value.ndim == 2 and value.shape[0] in (2, 3, 4) and value.shape[1] in (2, 3, 4):
            r, c = value.shape
            name_fn = f"glUniformMatrix{r}fv" if r == c else f"glUniformMatrix{r}x{c}fv"
            arr = np.ascontiguousarray(value, dtype=np.float32)
            f[name_fn](loc, 1, 1, arr.ctypes.data)  # transpose = GL_TRUE, as pyrender passes
            return
    elif isinstance(value, float):
        f["glUniform1f"](loc, value)
        return
    elif isinstance(value, int):  # bool is an int: pyrender's int branch handles it too
        (f["glUniform1ui"] if unsigned else f["glUniform1i"])(loc, int(value))
        return
    _ORIGINAL(self, name, value, unsigned)


def _counting_forward_pass(self, scene, flags, seg_node_map=None):
    self._advobj_pass = getattr(self, "_advobj_pass", 0) + 1
    self._advobj_lit = set()
    return _ORIGINAL_FORWARD(self, scene, flags, seg_node_map)


def _lighting_once_per_pass(self, scene, program, node, flags):
    from pyrender.constants import MAX_N_LIGHTS, RenderFlags  # lazy: robot_io start-up (pyrender, OpenGL)

    lit = getattr(self, "_advobj_lit", None)
    exact = (
        lit is not None
        and not flags & (RenderFlags.SHADOWS_DIRECTIONAL | RenderFlags.SHADOWS_SPOT | RenderFlags.SHADOWS_POINT)
        and len(scene.directional_light_nodes) <= MAX_N_LIGHTS
        and len(scene.spot_light_nodes) <= MAX_N_LIGHTS
        and len(scene.point_light_nodes) <= MAX_N_LIGHTS
    )
    if exact:
        key = (id(program), program._program_id)
        if key in lit:
            return
        lit.add(key)
    _ORIGINAL_LIGHTING(self, scene, program, node, flags)


def install() -> bool:
    """Patch pyrender (idempotent). Returns whether the fast path is active."""
    global _ORIGINAL, _ORIGINAL_LIGHTING, _ORIGINAL_FORWARD, _FUNCS
    if os.environ.get("ADVOBJ_GL_FASTPATH", "1") == "0":
        return False
    from pyrender.renderer import Renderer  # lazy: robot_io start-up (pyrender, OpenGL)
    from pyrender.shader_program import ShaderProgram  # lazy: robot_io start-up (pyrender, OpenGL)

    if _ORIGINAL is not None:
        return True
    try:
        funcs = _load_funcs()
    except (AttributeError, OSError, TypeError):
        return False  # unusual GL platform: keep pyrender's own path
    _FUNCS = funcs
    _ORIGINAL = ShaderProgram.set_uniform
    ShaderProgram.set_uniform = _fast_set_uniform
    _ORIGINAL_LIGHTING, _ORIGINAL_FORWARD = Renderer._bind_lighting, Renderer._forward_pass
    Renderer._bind_lighting = _lighting_once_per_pass
    Renderer._forward_pass = _counting_forward_pass
    return True


def uninstall() -> None:
    """Restore pyrender's own ``set_uniform`` and lighting binding (used by the equivalence test and the benchmark)."""
    global _ORIGINAL, _ORIGINAL_LIGHTING, _ORIGINAL_FORWARD
    if _ORIGINAL is None:
        return
    from pyrender.renderer import Renderer  # lazy: robot_io start-up (pyrender, OpenGL)
    from pyrender.shader_program import ShaderProgram  # lazy: robot_io start-up (pyrender, OpenGL)

    ShaderProgram.set_uniform = _ORIGINAL
    Renderer._bind_lighting, Renderer._forward_pass = _ORIGINAL_LIGHTING, _ORIGINAL_FORWARD
    _ORIGINAL = _ORIGINAL_LIGHTING = _ORIGINAL_FORWARD = None


def installed() -> bool:
    return _ORIGINAL is not None
