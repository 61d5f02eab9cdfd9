"""Scene rendering with pyrender (real OpenGL, headless EGL by default).

One :class:`SceneRenderer` owns one GL context and one pyrender scene. Each frame is a color pass
(RGB + depth) and, optionally, an *id pass*: a FLAT (unlit) pass in which every surface carries an
exact 24-bit code. The id buffer gives per-object visible masks and, for the adversarial object,
the index of the mesh face seen at each pixel, which the attack's differentiable texture path
needs (see ``attack/render.py``).

Multisampling is disabled: resolved MSAA samples blend neighbouring codes at silhouettes and would
corrupt the ids; it also makes the color pass and the id pass cover exactly the same pixels.

Shortcuts that keep every pixel exact (measured in ``benchmarks/bench_render_shortcuts.py``):

* frustum culling: an object whose bounding sphere lies entirely outside the view frustum is left
  out of every pass of that render (``frustum_cull=True``);
* ``render(..., isolate=k)`` draws object ``k`` alone. There are no shadows, so the shading of a
  surface point does not depend on other geometry: at the pixels where ``k`` is visible in the
  full scene (its id-pass mask) the isolated render is identical to the full one. The attack's
  measured shading passes (``HybridRenderer(shading="passes")``) read only those pixels;
* ``render(..., with_depth=False)`` skips the depth read-back (colour and ids are the same bytes).

Id codes (24-bit, ``r << 16 | g << 8 | b``):
  0                      nothing (background)
  1                      table
  2                      gripper
  OBJECT_BASE + k        scene object k (spec order)
  FACE_BASE + f          face f of the *face-coded* object (the adversarial one by default)
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass, field, replace

from sim.errors import AdvobjError

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np
import trimesh

from sim import gl_fastpath
from sim.assets import build_mesh, default_texture, region_texture, table_mesh
from sim.geometry import make_T, so3_exp
from sim.variations import table_variant_texture

__all__ = [
    "RenderError",
    "RenderOutput",
    "SceneRenderer",
    "BACKGROUND_ID",
    "TABLE_ID",
    "GRIPPER_ID",
    "OBJECT_BASE",
    "FACE_BASE",
    "gl_from_cv",
    "gripper_meshes",
    "spheres_outside_frustum",
    "frustum_normals",
    "SceneLighting",
]

BACKGROUND_ID = 0
TABLE_ID = 1
GRIPPER_ID = 2
OBJECT_BASE = 16
FACE_BASE = 1 << 16  # up to 16.7M - 65536 faces for the face-coded object

# OpenCV camera (x right, y down, z forward) -> OpenGL camera (x right, y up, z backward).
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def gl_from_cv(T_world_cvcam: np.ndarray) -> np.ndarray:
    """pyrender camera pose from an OpenCV-convention camera pose."""
    return np.asarray(T_world_cvcam) @ _CV_TO_GL


def frustum_normals(K: np.ndarray, width: int, height: int, margin_px: float = 2.0) -> np.ndarray:
    """Unit inward normals ``(4, 3)`` of the side planes of the view frustum (OpenCV camera frame).

    A point projects to edge coordinate u = fx x / z + cx + 0.5 (pixel k spans [k, k + 1]);
    'inside' is -m <= u <= W + m (same for v), i.e. n . p >= 0 for each normal n (the planes pass
    through the optical centre).
    """
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    m = float(margin_px)
    n = np.array(
        [
            [fx, 0.0, cx + 0.5 + m],
            [-fx, 0.0, width + m - cx - 0.5],
            [0.0, fy, cy + 0.5 + m],
            [0.0, -fy, height + m - cy - 0.5],
        ]
    )
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def spheres_outside_frustum(
    centers_cam: np.ndarray,
    radii: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    znear: float,
    zfar: float,
    margin_px: float = 2.0,
    normals: np.ndarray | None = None,
) -> np.ndarray:
    """Which spheres lie entirely outside the camera's view frustum: ``(N,)`` bool.

    centers_cam: (N, 3) m sphere centres in the OpenCV camera frame; radii: (N,) m; K: (3, 3)
    intrinsics at ``width x height`` px; znear, zfar: clip distances (m) along the optical axis.
    The side planes pass through the pixel grid's outer edges widened by ``margin_px`` (culling
    stays conservative: a sphere is reported outside only if no pixel can see any of it).
    ``normals``: :func:`frustum_normals` of these arguments, precomputed (per-frame callers).
    """
    c = np.asarray(centers_cam, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(radii, dtype=np.float64).reshape(-1)
    n = frustum_normals(K, width, height, margin_px) if normals is None else normals
    side = (c @ n.T < -r[:, None]).any(-1)
    return side | (c[:, 2] + r < znear) | (c[:, 2] - r > zfar)


class RenderError(AdvobjError, RuntimeError):
    """OpenGL could not be initialised or a render failed."""


_GL_HELP = (
    "No usable OpenGL for headless rendering. Install Mesa's EGL driver "
    "(Debian/Ubuntu: apt-get install libegl1 libgl1-mesa-dri) and keep PYOPENGL_PLATFORM=egl; "
    "or install OSMesa (apt-get install libosmesa6) and set PYOPENGL_PLATFORM=osmesa."
)


@dataclass
class RenderOutput:
    """One rendered frame.

    rgb: (H, W, 3) uint8; depth: (H, W) float32 m along the optical axis (0 where empty), or
    None when not read (``with_depth=False``); ids: (H, W) int32 id codes, or None when the id pass
    was skipped.
    """

    rgb: np.ndarray
    depth: np.ndarray | None
    ids: np.ndarray | None = None
    object_names: tuple[str, ...] = field(default_factory=tuple)
    face_coded: int | None = None

    def object_mask(self, k: int) -> np.ndarray:
        """Visible mask (H, W) bool of scene object ``k``."""
        if self.ids is None:
            raise RenderError("masks need the id pass (render with with_ids=True)")
        if k == self.face_coded:
            return self.ids >= FACE_BASE
        return self.ids == OBJECT_BASE + k

    @property
    def masks(self) -> dict[str, np.ndarray]:
        return {name: self.object_mask(k) for k, name in enumerate(self.object_names)}

    @property
    def face_ids(self) -> np.ndarray:
        """(H, W) int64 face index of the face-coded object, -1 elsewhere."""
        if self.ids is None:
            raise RenderError("face ids need the id pass (render with with_ids=True)")
        return np.where(self.ids >= FACE_BASE, self.ids - FACE_BASE, -1).astype(np.int64)


def _encode(code: np.ndarray) -> np.ndarray:
    code = np.asarray(code, dtype=np.int64)
    return np.stack([(code >> 16) & 255, (code >> 8) & 255, code & 255], -1).astype(np.uint8)


def _decode(rgb: np.ndarray) -> np.ndarray:
    rgb = rgb.astype(np.int32)
    return (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]


def _single_sample_framebuffer(renderer) -> None:
    """Make a pyrender ``Renderer`` allocate its 'multisample' buffers with 0 samples."""
    from OpenGL import GL  # lazy: robot_io start-up (pyrender, OpenGL)

    original = renderer._configure_main_framebuffer

    def configure():
        real = GL.glRenderbufferStorageMultisample

        def no_msaa(target, samples, fmt, w, h):
            return real(target, 0, fmt, w, h)

        import pyrender.renderer as pr  # lazy: robot_io start-up (pyrender, OpenGL)

        pr.glRenderbufferStorageMultisample = no_msaa
        try:
            original()
        finally:
            pr.glRenderbufferStorageMultisample = real

    renderer._configure_main_framebuffer = configure


def _read_color_only(renderer, scene, flags):
    """pyrender's ``Renderer._read_main_framebuffer`` without the depth buffer: the same blit and
    ``glReadPixels`` of the colour (identical bytes), no depth read-back or conversion. Returns
    ``(color, None)``; a depth-only render or macOS (which resizes) goes to pyrender's own."""

    from OpenGL.GL import (
        GL_COLOR_BUFFER_BIT,
        GL_DRAW_FRAMEBUFFER,
        GL_LINEAR,
        GL_READ_FRAMEBUFFER,
        GL_RGB,
        GL_RGBA,
        GL_UNSIGNED_BYTE,
        glBindFramebuffer,
        glBlitFramebuffer,
        glReadPixels,
    )  # lazy: robot_io start-up (pyrender, OpenGL)
    from pyrender.constants import RenderFlags  # lazy: robot_io start-up (pyrender, OpenGL)

    if flags & RenderFlags.DEPTH_ONLY or sys.platform == "darwin":
        return type(renderer)._read_main_framebuffer(renderer, scene, flags)
    width, height = renderer._main_fb_dims[0], renderer._main_fb_dims[1]
    glBindFramebuffer(GL_READ_FRAMEBUFFER, renderer._main_fb_ms)
    glBindFramebuffer(GL_DRAW_FRAMEBUFFER, renderer._main_fb)
    glBlitFramebuffer(0, 0, width, height, 0, 0, width, height, GL_COLOR_BUFFER_BIT, GL_LINEAR)
    glBindFramebuffer(GL_READ_FRAMEBUFFER, renderer._main_fb)
    c = 4 if flags & RenderFlags.RGBA else 3
    buf = glReadPixels(0, 0, width, height, GL_RGBA if c == 4 else GL_RGB, GL_UNSIGNED_BYTE)
    return np.flip(np.frombuffer(buf, dtype=np.uint8).reshape((height, width, c)), axis=0), None


def _texture(image: np.ndarray, repeat: bool):
    import pyrender  # lazy: robot_io start-up (pyrender, OpenGL)
    from OpenGL.GL import GL_CLAMP_TO_EDGE, GL_REPEAT  # lazy: robot_io start-up (pyrender, OpenGL)

    wrap = GL_REPEAT if repeat else GL_CLAMP_TO_EDGE
    sampler = pyrender.Sampler(wrapS=wrap, wrapT=wrap)
    return pyrender.Texture(source=np.ascontiguousarray(image[..., :3]), source_channels="RGB", sampler=sampler)


def _material(texture_image: np.ndarray | None, color=(1.0, 1.0, 1.0), repeat: bool = False):
    import pyrender  # lazy: robot_io start-up (pyrender, OpenGL)

    # Dielectric, fully rough: the shading is diffuse (multiplicative in the albedo) plus a
    # small albedo-independent specular term, which the attack computes per fragment
    # (attack.render.deferred_shading, from SceneRenderer.lighting) or measures (shading passes).
    kw = dict(metallicFactor=0.0, roughnessFactor=1.0, baseColorFactor=(*color, 1.0))
    if texture_image is not None:
        kw["baseColorTexture"] = _texture(texture_image, repeat)
    return pyrender.MetallicRoughnessMaterial(**kw)


def _uv_of(mesh: trimesh.Trimesh) -> np.ndarray | None:
    uv = getattr(mesh.visual, "uv", None)
    return None if uv is None else np.asarray(uv, dtype=np.float32)


def textured_pyrender_mesh(mesh: trimesh.Trimesh, texture_image: np.ndarray | None, color=None, repeat=False):
    """A pyrender mesh of ``mesh`` with smooth normals, UVs and a texture (or a flat color)."""
    import pyrender  # lazy: robot_io start-up (pyrender, OpenGL)

    uv = _uv_of(mesh)
    if texture_image is not None and uv is None:
        raise RenderError(f"mesh {mesh.metadata.get('name', '?')} has no UVs to carry a texture")
    prim = pyrender.Primitive(
        positions=np.asarray(mesh.vertices, dtype=np.float32),
        normals=np.asarray(mesh.vertex_normals, dtype=np.float32),
        texcoord_0=uv if texture_image is not None else None,
        indices=np.asarray(mesh.faces, dtype=np.uint32),
        material=_material(texture_image, color if color is not None else (1.0, 1.0, 1.0), repeat),
    )
    return pyrender.Mesh([prim])


def id_pyrender_mesh(mesh: trimesh.Trimesh, code: int | None):
    """Unlit mesh whose every pixel reads back an exact id code.

    ``code=None`` codes each face as ``FACE_BASE + face index`` (vertices unshared so the
    per-vertex color is constant over each face).
    """
    import pyrender  # lazy: robot_io start-up (pyrender, OpenGL)

    faces = np.asarray(mesh.faces)
    if code is None:
        positions = np.asarray(mesh.vertices, dtype=np.float32)[faces].reshape(-1, 3)
        codes = np.repeat(FACE_BASE + np.arange(len(faces)), 3)
        indices = np.arange(len(positions), dtype=np.uint32).reshape(-1, 3)
    else:
        positions = np.asarray(mesh.vertices, dtype=np.float32)
        codes = np.full(len(positions), code)
        indices = faces.astype(np.uint32)
    colors = np.concatenate([_encode(codes), np.full((len(codes), 1), 255, np.uint8)], -1)
    prim = pyrender.Primitive(
        positions=positions,
        color_0=colors.astype(np.float32) / 255.0,
        indices=indices,
        material=pyrender.MetallicRoughnessMaterial(baseColorFactor=(1.0, 1.0, 1.0, 1.0)),
    )
    return pyrender.Mesh([prim])


def gripper_meshes(gripper) -> list[trimesh.Trimesh]:
    """Panda-like gripper geometry in the TCP frame: palm plus two fingers ending at the TCP.

    ``gripper``: a :class:`sim.spec.GripperSpec`. The fingers extend along +z (approach) and are
    separated along x; the finger tips sit at z = 0 (the TCP).
    """
    L, w, t = gripper.finger_length_m, gripper.finger_width_m, gripper.finger_thickness_m
    px, py, pz = gripper.palm_size_m
    half_open = gripper.opening_m / 2.0
    parts = []
    for sx in (-1.0, 1.0):
        f = trimesh.creation.box((t, w, L))
        f.apply_translation((sx * (half_open + t / 2.0), 0.0, -L / 2.0))
        parts.append(f)
    palm = trimesh.creation.box((px, py, pz))
    palm.apply_translation((0.0, 0.0, -L - pz / 2.0))
    parts.append(palm)
    return parts


def _light_pose(direction) -> np.ndarray:
    d = np.asarray(direction, dtype=np.float64)
    z = -d / np.linalg.norm(d)  # pyrender lights shine along their node's -z
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_T(np.stack([x, y, z], -1), np.zeros(3))


@dataclass(frozen=True)
class SceneLighting:
    """What pyrender's ``mesh.frag`` needs, besides the albedo, to shade one object's fragments.

    Read from the live scene by :meth:`SceneRenderer.lighting` (the uniforms pyrender binds), so
    randomised lights and appearances are the ones the colour pass used. Frame: whatever the
    arrays are expressed in (world from the renderer; :meth:`in_frame` moves them).

    ambient: (3,); directional: ``dir (Nd, 3)`` the direction light travels, ``rad (Nd, 3)``
    intensity * color; point: ``pos (Np, 3)``, ``rad (Np, 3)``; spot: ``pos (Ns, 3)``,
    ``dir (Ns, 3)``, ``rad (Ns, 3)``, ``scale (Ns,)``, ``offset (Ns,)`` (pyrender's
    light_angle_scale/offset); roughness: the material's, clamped as the shader does;
    emissive: (3,) the albedo-independent emissive term (pyrender adds emissive_factor squared).
    """

    ambient: np.ndarray
    dir_dir: np.ndarray
    dir_rad: np.ndarray
    point_pos: np.ndarray
    point_rad: np.ndarray
    spot_pos: np.ndarray
    spot_dir: np.ndarray
    spot_rad: np.ndarray
    spot_scale: np.ndarray
    spot_offset: np.ndarray
    roughness: float
    emissive: np.ndarray

    def in_frame(self, T_frame_world: np.ndarray) -> "SceneLighting":
        """The same lights expressed in another frame (``T_frame_world: (4, 4)``, rigid)."""

        T = np.asarray(T_frame_world, dtype=np.float64)
        R, t = T[:3, :3], T[:3, 3]
        return replace(
            self,
            dir_dir=self.dir_dir @ R.T,
            point_pos=self.point_pos @ R.T + t,
            spot_pos=self.spot_pos @ R.T + t,
            spot_dir=self.spot_dir @ R.T,
        )


@dataclass
class _ObjectNodes:
    color: object
    ids: object
    mesh: trimesh.Trimesh
    texture: np.ndarray | None  # the object's own look, restored by set_object_texture(k, None)
    flat_color: tuple | None
    variants: dict = field(default_factory=dict)


class SceneRenderer:
    """Renders a :class:`sim.spec.SceneSpec` from arbitrary OpenCV camera poses.

    Args:
        spec: the scene.
        width, height: image size in px (defaults to the spec camera's).
        meshes: optional pre-built trimesh per object (default: built from the spec).
        face_coded: index of the object whose faces are id-coded (default: the adversarial one).
        frustum_cull: leave objects entirely outside the view out of each render (exact: the
            images are pixel-identical; :attr:`culled` lists the objects skipped last render).
    """

    def __init__(
        self,
        spec,
        width: int | None = None,
        height: int | None = None,
        meshes=None,
        face_coded=None,
        frustum_cull: bool = True,
    ):
        try:
            import pyrender  # lazy: robot_io start-up (pyrender, OpenGL)
        except Exception as err:  # ImportError, or PyOpenGL failing to find the platform library
            raise RenderError(f"{_GL_HELP} (import failed: {err})") from None

        self.spec = spec
        self.width = int(width or spec.camera.width)
        self.height = int(height or spec.camera.height)
        self.K = spec.camera.K(self.width, self.height)
        self.object_names = tuple(o.name for o in spec.objects)
        self.face_coded = spec.object_index("adversarial") if face_coded is None else face_coded
        try:
            self._renderer = pyrender.OffscreenRenderer(self.width, self.height)
        except Exception as err:
            raise RenderError(f"{_GL_HELP} (context creation failed: {type(err).__name__}: {err})") from None
        _single_sample_framebuffer(self._renderer._renderer)

        gl_fastpath.install()  # bit-identical images, less Python per uniform (see the module)

        self.scene = pyrender.Scene(bg_color=(*spec.background, 1.0), ambient_light=spec.lighting.ambient)
        self._light_nodes = []
        self.set_lights(spec.lighting)

        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        # pyrender measures the principal point from the image edge, OpenCV from the first
        # pixel centre: shift by half a pixel.
        cam = pyrender.IntrinsicsCamera(fx, fy, cx + 0.5, cy + 0.5, znear=spec.camera.znear_m, zfar=spec.camera.zfar_m)
        self._camera_node = self.scene.add(cam, pose=np.eye(4))

        # Table: a tiled texture (repeat wrap) on a box whose top is z = 0.
        self._table_mesh = table_mesh(tuple(spec.table.size_m), spec.table.thickness_m)
        self._table = self._add_static(
            self._table_mesh, spec.table.texture, TABLE_ID, repeat=True, default_name="table"
        )

        # Gripper: children of a TCP node so one pose update moves all parts.
        self._tcp_node = pyrender.Node(name="tcp", matrix=np.eye(4))
        self.scene.add_node(self._tcp_node)
        self._gripper_nodes = []
        # One merged mesh (one draw call per pass instead of three): the parts share one colour
        # and one id code, and pyrender's per-draw overhead dominates small frames.
        for part in [trimesh.util.concatenate(gripper_meshes(spec.gripper))]:
            c = pyrender.Node(mesh=textured_pyrender_mesh(part, None, spec.gripper.color))
            i = pyrender.Node(mesh=id_pyrender_mesh(part, GRIPPER_ID))
            self.scene.add_node(c, parent_node=self._tcp_node)
            self.scene.add_node(i, parent_node=self._tcp_node)
            self._gripper_nodes.append((c, i))

        self._objects: list[_ObjectNodes] = []
        for k, ospec in enumerate(spec.objects):
            mesh = meshes[k] if meshes is not None else build_mesh(ospec.mesh, ospec.scale, **ospec.mesh_kwargs())
            tex = self._resolve_texture(ospec.texture, mesh, default_texture)
            color = tuple(ospec.texture) if isinstance(ospec.texture, tuple) else None
            cnode = self.scene.add(textured_pyrender_mesh(mesh, tex, color), pose=np.eye(4))
            code = None if k == self.face_coded else OBJECT_BASE + k
            inode = self.scene.add(id_pyrender_mesh(mesh, code), pose=np.eye(4))
            self._objects.append(_ObjectNodes(cnode, inode, mesh, tex, color))
        self._hidden: set[int] = set()
        self._gripper_visible = True
        self.frustum_cull = bool(frustum_cull)
        self.culled: tuple[int, ...] = ()
        # Bounding spheres in the object frames: bounding-box centre, farthest vertex.
        self._sphere_c = np.array([(o.mesh.bounds[0] + o.mesh.bounds[1]) / 2.0 for o in self._objects]).reshape(-1, 3)
        self._sphere_r = np.array(
            [
                np.linalg.norm(np.asarray(o.mesh.vertices) - c, axis=-1).max()
                for o, c in zip(self._objects, self._sphere_c)
            ]
        )
        self._T_world_objects = np.tile(np.eye(4), (len(self._objects), 1, 1))
        self._frustum_normals = frustum_normals(self.K, self.width, self.height)

    # ------------------------------------------------------------------ building
    @staticmethod
    def _resolve_texture(texture, mesh, default_texture):
        """Image for a spec texture field: None -> the mesh's own look, str -> image file."""
        if isinstance(texture, tuple):
            return None
        if texture is None or texture == "default":
            img = getattr(getattr(mesh.visual, "material", None), "image", None)
            if img is not None:
                return np.asarray(img.convert("RGB"))
            return default_texture(mesh.metadata.get("name", "plain"))
        import imageio.v3 as iio  # lazy: robot_io start-up (imageio)

        try:
            img = iio.imread(texture)
        except Exception as err:
            raise RenderError(f"{texture}: cannot read texture image ({err})") from None
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, -1)
        return np.ascontiguousarray(img[..., :3]).astype(np.uint8)

    def _add_static(self, mesh, texture, code, repeat, default_name):

        tex = self._resolve_texture(texture, mesh, lambda _n: default_texture(default_name))
        if tex is None:  # a flat color: a tiny image keeps one code path for texture swaps
            tex = np.full((4, 4, 3), np.round(np.asarray(texture) * 255), np.uint8)
        self._table_texture = tex
        c = self.scene.add(textured_pyrender_mesh(mesh, tex, None, repeat=repeat), pose=np.eye(4))
        i = self.scene.add(id_pyrender_mesh(mesh, code), pose=np.eye(4))
        return c, i

    def set_lights(self, lighting) -> None:
        """Replace ambient and lights with a :class:`sim.spec.LightingSpec`."""
        import pyrender  # lazy: robot_io start-up (pyrender, OpenGL)

        for n in self._light_nodes:
            self.scene.remove_node(n)
        self._light_nodes = []
        self.scene.ambient_light = np.asarray(lighting.ambient, dtype=np.float64)
        for light in lighting.lights:
            if light.type == "directional":
                node = self.scene.add(
                    pyrender.DirectionalLight(color=light.color, intensity=light.intensity),
                    pose=_light_pose(light.direction),
                )
            else:
                node = self.scene.add(
                    pyrender.PointLight(color=light.color, intensity=light.intensity),
                    pose=make_T(np.eye(3), light.position_m),
                )
            self._light_nodes.append(node)

    def set_table_texture(self, image: np.ndarray) -> None:
        """Swap the table's texture (used by background variation)."""
        self._table[0].mesh = textured_pyrender_mesh(self._table_mesh, image, repeat=True)

    def set_background(self, rgb) -> None:
        self.scene.bg_color = np.array([*rgb, 1.0])

    def apply_appearance(self, appearance) -> None:
        """Apply a :class:`sim.variations.Appearance` (lights, table, backdrop); no-op if current."""
        if appearance == getattr(self, "_appearance", None):
            return

        self.set_lights(appearance.lighting)
        self.set_background(appearance.background if appearance.background is not None else self.spec.background)
        if appearance.table_variant != getattr(getattr(self, "_appearance", None), "table_variant", -1):
            tex = (
                self._table_texture if appearance.table_variant < 0 else table_variant_texture(appearance.table_variant)
            )
            self.set_table_texture(tex)
        self._appearance = appearance

    def object_mesh(self, k: int) -> trimesh.Trimesh:
        return self._objects[k].mesh

    def set_object_texture(self, k: int, image: np.ndarray | None) -> None:
        """Re-texture object ``k`` (e.g. with an optimised texture); ``None`` restores its own look."""
        obj = self._objects[k]
        if image is None:
            image, color = obj.texture, obj.flat_color
        else:
            image, color = (
                region_texture(obj.mesh, np.ascontiguousarray(np.asarray(image, dtype=np.uint8)[..., :3])),
                None,
            )
        obj.color.mesh = textured_pyrender_mesh(obj.mesh, image, color)

    def add_variant(self, k: int, variant: str, image: np.ndarray | None, color=(1.0, 1.0, 1.0)) -> None:
        """Register an alternative look of object ``k`` selectable per render (e.g. white albedo)."""
        import pyrender  # lazy: robot_io start-up (pyrender, OpenGL)

        mesh = self._objects[k].mesh
        if image is not None:
            image = region_texture(mesh, np.ascontiguousarray(np.asarray(image, dtype=np.uint8)[..., :3]))
        # Placed where the object is now (set_state moves it with the object from then on).
        node = pyrender.Node(mesh=textured_pyrender_mesh(mesh, image, color), matrix=self._T_world_objects[k].copy())
        self.scene.add_node(node)
        self._objects[k].variants[variant] = node

    def lighting(self, k: int) -> SceneLighting | None:
        """The lights, ambient and material terms pyrender shades object ``k``'s colour mesh with,
        in the world frame, or ``None`` when its shader output is not ``albedo * D + S`` with
        ``D``, ``S`` independent of the albedo as :class:`SceneLighting` describes (a metallic
        material, a normal/occlusion/emissive/metallic-roughness texture, or more lights of a type
        than pyrender binds, when it picks the nearest per object). This renderer never builds
        such materials; the check keeps a caller from silently shading another model.
        """
        import pyrender  # lazy: robot_io start-up (pyrender, OpenGL)
        from pyrender.constants import MAX_N_LIGHTS  # lazy: robot_io start-up (pyrender, OpenGL)

        scene = self.scene
        if any(
            len(nodes) > MAX_N_LIGHTS
            for nodes in (scene.directional_light_nodes, scene.point_light_nodes, scene.spot_light_nodes)
        ):
            return None
        emissive = np.zeros(3)
        roughness = None
        for prim in self._objects[k].color.mesh.primitives:
            m = prim.material
            if not isinstance(m, pyrender.MetallicRoughnessMaterial) or prim.color_0 is not None:
                return None
            if any(
                t is not None
                for t in (m.normalTexture, m.occlusionTexture, m.emissiveTexture, m.metallicRoughnessTexture)
            ):
                return None
            metallic = 1.0 if m.metallicFactor is None else float(m.metallicFactor)
            r = 1.0 if m.roughnessFactor is None else float(m.roughnessFactor)
            r = min(max(r, 0.04), 1.0)  # mesh.frag's clamp(roughness, min_roughness, 1.0)
            if min(max(metallic, 0.0), 1.0) != 0.0 or (roughness is not None and r != roughness):
                return None
            roughness = r
            emissive = np.asarray(m.emissiveFactor, dtype=np.float64) ** 2
        groups = {"d": ([], []), "p": ([], []), "s": ([], [], [], [], [])}
        for node in scene.light_nodes:  # as Renderer._bind_lighting: direction = -z, position = t
            light, pose = node.light, scene.get_pose(node)
            rad = float(light.intensity) * np.asarray(light.color, dtype=np.float64)
            if isinstance(light, pyrender.PointLight):
                groups["p"][0].append(pose[:3, 3])
                groups["p"][1].append(rad)
            elif isinstance(light, pyrender.SpotLight):
                scale = 1.0 / max(0.001, np.cos(light.innerConeAngle) - np.cos(light.outerConeAngle))
                for lst, val in zip(
                    groups["s"], (pose[:3, 3], -pose[:3, 2], rad, scale, -np.cos(light.outerConeAngle) * scale)
                ):
                    lst.append(val)
            else:
                groups["d"][0].append(-pose[:3, 2])
                groups["d"][1].append(rad)

        def arr(lst, shape=(0, 3)):
            return np.asarray(lst, dtype=np.float64).reshape((-1, *shape[1:]))

        sp = groups["s"]
        return SceneLighting(
            ambient=np.asarray(scene.ambient_light, dtype=np.float64).reshape(3),
            dir_dir=arr(groups["d"][0]),
            dir_rad=arr(groups["d"][1]),
            point_pos=arr(groups["p"][0]),
            point_rad=arr(groups["p"][1]),
            spot_pos=arr(sp[0]),
            spot_dir=arr(sp[1]),
            spot_rad=arr(sp[2]),
            spot_scale=arr(sp[3], (0,)),
            spot_offset=arr(sp[4], (0,)),
            roughness=1.0 if roughness is None else roughness,
            emissive=emissive,
        )

    # ------------------------------------------------------------------ state
    def set_state(self, T_world_objects: np.ndarray, T_world_tcp: np.ndarray | None) -> None:
        """Place objects (``T_world_objects: (K, 4, 4)``) and the gripper (``None`` hides it)."""
        self._T_world_objects = np.array(T_world_objects, dtype=np.float64).reshape(-1, 4, 4)
        for obj, T in zip(self._objects, T_world_objects):
            self.scene.set_pose(obj.color, T)
            self.scene.set_pose(obj.ids, T)
            for v in obj.variants.values():
                self.scene.set_pose(v, T)
        self._gripper_visible = T_world_tcp is not None
        if self._gripper_visible:
            self.scene.set_pose(self._tcp_node, np.asarray(T_world_tcp, dtype=np.float64))

    def set_object_visible(self, k: int, visible: bool) -> None:
        """Show or hide object ``k`` in every pass (e.g. an object removed from a condition)."""
        (self._hidden.discard if visible else self._hidden.add)(k)

    # ------------------------------------------------------------------ rendering
    def _culled(self, T_world_cam: np.ndarray) -> tuple[int, ...]:
        """Objects whose bounding sphere is entirely outside the view from ``T_world_cam``."""
        if not self.frustum_cull or not self._objects:
            return ()
        T = self._T_world_objects
        centers_world = np.einsum("kij,kj->ki", T[:, :3, :3], self._sphere_c) + T[:, :3, 3]
        T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
        R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
        centers_cam = (centers_world - t) @ R  # R^T (p - t), row-wise
        cam = self.spec.camera
        out = spheres_outside_frustum(
            centers_cam,
            self._sphere_r,
            self.K,
            self.width,
            self.height,
            cam.znear_m,
            cam.zfar_m,
            normals=self._frustum_normals,
        )
        return tuple(int(k) for k in np.flatnonzero(out))

    def _set_pass(self, color_pass: bool, variants: dict, isolate: int | None = None) -> None:
        """Node visibility for one pass: color meshes (with variants swapped in) or id meshes."""
        scene = isolate is None
        self._table[0].mesh.is_visible = color_pass and scene
        self._table[1].mesh.is_visible = (not color_pass) and scene
        for c, i in self._gripper_nodes:
            c.mesh.is_visible = color_pass and self._gripper_visible and scene
            i.mesh.is_visible = (not color_pass) and self._gripper_visible and scene
        for k, obj in enumerate(self._objects):
            shown = k not in self._hidden and k not in self.culled and (scene or k == isolate)
            chosen = variants.get(k)
            obj.color.mesh.is_visible = color_pass and shown and chosen is None
            obj.ids.mesh.is_visible = (not color_pass) and shown
            for name, node in obj.variants.items():
                node.mesh.is_visible = color_pass and shown and chosen == name

    def render(
        self,
        T_world_cam: np.ndarray,
        with_ids: bool = True,
        with_color: bool = True,
        variants=None,
        isolate: int | None = None,
        with_depth: bool = True,
    ) -> RenderOutput:
        """Render from an OpenCV camera pose ``T_world_cam: (4, 4)``.

        ``variants``: ``{object index: variant name}`` swaps in looks registered with
        :meth:`add_variant` for this color pass only.
        ``isolate``: draw only object ``isolate`` (no table, gripper or other objects). Its pixels
        equal the full render's only where it is visible in the full scene (use them under its
        id-pass mask); elsewhere they show what the other geometry would have hidden.
        ``with_depth=False``: no depth read-back in any pass (``depth`` is None; the colour and
        ids are the same bytes), for callers that do not use it.
        """
        import pyrender  # lazy: robot_io start-up (pyrender, OpenGL)

        variants = dict(variants or {})
        for k, name in variants.items():
            if name not in self._objects[k].variants:
                raise RenderError(f"object {self.object_names[k]} has no variant {name!r}")
        if isolate is not None and not 0 <= isolate < len(self._objects):
            raise RenderError(f"isolate: no object {isolate} (the scene has {len(self._objects)})")
        self.scene.set_pose(self._camera_node, gl_from_cv(T_world_cam))
        self.culled = self._culled(T_world_cam)
        rgb = depth = ids = None
        gl = self._renderer._renderer
        if not with_depth:  # an instance attribute shadows the method for these passes only
            gl._read_main_framebuffer = lambda scene, flags: _read_color_only(gl, scene, flags)
        try:
            if with_color:
                self._set_pass(True, variants, isolate)
                rgb, depth = self._renderer.render(self.scene)
            if with_ids:
                self._set_pass(False, {}, isolate)
                bg = self.scene.bg_color.copy()
                self.scene.bg_color = np.array([0.0, 0.0, 0.0, 1.0])  # code 0 = nothing hit
                try:
                    flat, d2 = self._renderer.render(self.scene, flags=pyrender.RenderFlags.FLAT)
                finally:
                    self.scene.bg_color = bg
                ids = _decode(flat)
                depth = d2 if depth is None else depth
        finally:
            if not with_depth:
                del gl._read_main_framebuffer
        if rgb is None:
            rgb = np.zeros((self.height, self.width, 3), np.uint8)
        depth = None if depth is None else depth.astype(np.float32)
        return RenderOutput(np.ascontiguousarray(rgb), depth, ids, self.object_names, self.face_coded)

    def close(self) -> None:
        """Free this renderer's GL resources (other renderers keep working)."""
        r = getattr(self, "_renderer", None)
        if r is None:
            return
        self._renderer = None
        platform = r._platform
        platform.make_current()
        r._renderer.delete()
        if getattr(platform, "_egl_context", None) is not None:
            # pyrender's own delete() calls eglTerminate, which destroys every context on the
            # shared EGL display, i.e. every other live renderer: destroy only ours.
            from OpenGL import EGL  # lazy: robot_io start-up (pyrender, OpenGL)

            EGL.eglMakeCurrent(platform._egl_display, EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, EGL.EGL_NO_CONTEXT)
            EGL.eglDestroyContext(platform._egl_display, platform._egl_context)
            # The platform's __del__ would eglTerminate the display it still names.
            platform._egl_context = None
            platform._egl_display = None
        else:
            platform.delete_context()
        # OffscreenRenderer.__del__ would run pyrender's delete() (and eglTerminate) again;
        # without a platform it fails inside its own try/except and does nothing.
        r._platform = None
        r._renderer = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass


def object_pose(x_m: float, y_m: float, yaw_rad: float) -> np.ndarray:
    """``T_world_object`` for an object standing on the table at (x, y) with yaw about +z."""
    return make_T(so3_exp(np.array([0.0, 0.0, yaw_rad])), np.array([x_m, y_m, 0.0]))
