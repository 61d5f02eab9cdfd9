"""The fast uniform path changes speed only: images are bit-identical with and without it."""

import numpy as np

from sim import gl_fastpath
from sim.geometry import look_at
from sim.render import SceneRenderer
from sim.spec import LightingSpec, LightSpec, default_scene


def _views():
    rng = np.random.default_rng(3)
    for _ in range(4):
        eye = np.array([rng.uniform(-0.4, 0.4), rng.uniform(-0.4, 0.4), rng.uniform(0.15, 0.6)])
        yield look_at(eye, np.array([0.0, 0.0, 0.05]))


def _render_all(fast: bool, monkeypatch):
    if fast:
        monkeypatch.delenv("ADVOBJ_GL_FASTPATH", raising=False)
        assert gl_fastpath.install()
    else:
        gl_fastpath.uninstall()
        monkeypatch.setenv("ADVOBJ_GL_FASTPATH", "0")  # SceneRenderer() must not re-install it
    # A fresh renderer per mode: its shader programs (and location caches) start empty.
    with SceneRenderer(default_scene(), 96, 96) as r:
        T = np.stack([np.eye(4)] * len(r.object_names))
        T[:, 0, 3] = np.linspace(-0.15, 0.15, len(T))  # side by side, all in view
        r.set_state(T, np.eye(4) @ look_at(np.array([0.0, -0.2, 0.3]), np.zeros(3)))
        assert gl_fastpath.installed() == fast
        outs = []
        for i, T in enumerate(_views()):
            # Lights change between renders: a light binding wrongly skipped would show.
            lights = [
                LightSpec(intensity=1.0 + i, direction=(0.3 - 0.2 * i, 0.2, -1.0)),
                LightSpec(type="point", intensity=2.0 * i, color=(1.0, 0.8, 0.6), position_m=(0.2, -0.1, 0.8)),
            ]
            r.set_lights(LightingSpec(ambient=(0.1 * i, 0.2, 0.3), lights=lights[: 1 + i % 2]))
            outs.append(r.render(T, with_ids=True))
        return outs


def test_fast_uniform_path_renders_bit_identical_color_ids_and_depth(monkeypatch):
    try:
        slow = _render_all(False, monkeypatch)
        fast = _render_all(True, monkeypatch)
    finally:
        monkeypatch.delenv("ADVOBJ_GL_FASTPATH", raising=False)
        gl_fastpath.install()
    assert gl_fastpath.installed()
    for a, b in zip(slow, fast):
        assert a.rgb.std() > 0  # the views see something, so equality means something
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_array_equal(a.ids, b.ids)
        np.testing.assert_array_equal(a.depth, b.depth)


def test_fast_uniform_path_ignores_unknown_uniforms_like_pyrender():
    from pyrender.shader_program import ShaderProgram

    gl_fastpath.install()
    with SceneRenderer(default_scene(), 32, 32) as r:
        r.render(look_at(np.array([0.3, 0.0, 0.4]), np.zeros(3)), with_ids=False)
        program = next(iter(r._renderer._renderer._program_cache._program_cache.values()))
        program._bind()
        ShaderProgram.set_uniform(program, "no_such_uniform", np.ones(3))  # must not raise
        ShaderProgram.set_uniform(program, "no_such_uniform", 1.0)


def test_fast_uniform_path_can_be_switched_off_by_environment(monkeypatch):
    gl_fastpath.uninstall()
    try:
        monkeypatch.setenv("ADVOBJ_GL_FASTPATH", "0")
        assert gl_fastpath.install() is False
        assert not gl_fastpath.installed()
    finally:
        monkeypatch.delenv("ADVOBJ_GL_FASTPATH")
        assert gl_fastpath.install()
