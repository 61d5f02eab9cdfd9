"""Scene cameras: fixed cameras declared by the scene beside the wrist camera.

The spec refuses a camera it cannot place (no extrinsics, both pose forms, a bad or repeated name)
in one line; a scene without scene cameras is the scene it was (fingerprint, dump); a scene camera
projects objects where its id pass shows them; the env renders exactly the cameras asked for, and
the wrist camera's frames are the bytes they were before scene cameras existed.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sim.configs import spec_fingerprint
from sim.env import EnvError, ReachEnv
from sim.geometry import look_at, so3_log
from sim.render import SceneRenderer
from sim.spec import SpecError, UnknownCameraError, default_scene, load_scene, scene_from_dict
from sim.variations import Randomization
from sim.world import SimWorld

ROOT = Path(__file__).resolve().parents[2]
TWO_CAMERAS = ROOT / "scenes" / "two-cameras.yaml"

# The built-in scene's fingerprint, as the committed pools record it (results/policies/*.json).
DEFAULT_FINGERPRINT = "60e09fc80f149e90"
# sha256 of the frames, right-camera frames and masks of _wrist_digest's run, recorded with the
# env as it was before scene cameras existed (commit ebaea81).
WRIST_DIGEST = "a940cdf9f0e2ccc7ae3c4f746f550d0a5c9f95cc25848b9754db092fc99de7b5"

LOOK = {"eye_m": [0.33, -0.57, 0.51], "target_m": [0.0, 0.0, 0.05]}


def _scene(*cams, source="<dict>"):
    return scene_from_dict({**default_scene().model_dump(mode="json"), "scene_cameras": list(cams)}, source=source)


@pytest.fixture(scope="module")
def two():
    return load_scene(TWO_CAMERAS)


# ---------------------------------------------------------------------------------------------- spec


@pytest.mark.parametrize(
    "cams, field, words",
    [
        ([{"name": "front"}], "scene_cameras.0", ["no extrinsics", "t_table_cam_m", "rotvec_table_cam", "look_at"]),
        ([{"name": "front", "t_table_cam_m": [0, 0, 1]}], "scene_cameras.0", ["no extrinsics", "rotvec_table_cam"]),
        ([{"name": "front", "rotvec_table_cam": [3.1, 0, 0]}], "scene_cameras.0", ["t_table_cam_m missing"]),
        (
            [{"name": "front", "look_at": LOOK, "t_table_cam_m": [0, 0, 1], "rotvec_table_cam": [3.1, 0, 0]}],
            "scene_cameras.0",
            ["not both"],
        ),
        ([{"name": "front", "look_at": LOOK}, {"name": "front", "look_at": LOOK}], "scene_cameras", ["unique"]),
        ([{"name": "wrist", "look_at": LOOK}], "scene_cameras.0.name", ["wrist camera"]),
        ([{"name": "Front", "look_at": LOOK}], "scene_cameras.0.name", ["lower case"]),
        ([{"name": "1st", "look_at": LOOK}], "scene_cameras.0.name", ["lower case"]),
        ([{"name": "", "look_at": LOOK}], "scene_cameras.0.name", ["lower case"]),
        ([{"name": "c" * 33, "look_at": LOOK}], "scene_cameras.0.name", ["lower case"]),
        ([{"look_at": LOOK}], "scene_cameras.0.name", []),
        (
            [{"name": "front", "look_at": {"eye_m": [0.3, 0, 0.5], "target_m": [0.3, 0, 0.5]}}],
            "scene_cameras.0.look_at",
            ["1 mm apart"],
        ),
        (
            [{"name": "front", "look_at": {**LOOK, "up": [0, 0, 0]}}],
            "scene_cameras.0.look_at.up",
            ["non-zero"],
        ),
        (
            [{"name": "top", "look_at": {"eye_m": [0, 0, 1], "target_m": [0, 0, 0]}}],
            "scene_cameras.0.look_at",
            ["up lies along the view", "[0, 1, 0]"],
        ),
        (
            [{"name": "front", "look_at": {**LOOK, "eye_m": [1e5, 0, 1]}}],
            "scene_cameras.0.look_at.eye_m",
            ["100 m"],
        ),
        (
            [{"name": "front", "t_table_cam_m": [0, 0, 101], "rotvec_table_cam": [3.1, 0, 0]}],
            "scene_cameras.0.t_table_cam_m",
            ["100 m"],
        ),
        (
            [{"name": "front", "t_table_cam_m": [0, 0, 1], "rotvec_table_cam": [7.0, 0, 0]}],
            "scene_cameras.0.rotvec_table_cam",
            ["2 pi"],
        ),
        ([{"name": "front", "look_at": LOOK, "fov_deg": 179}], "scene_cameras.0.fov_deg", []),
        ([{"name": "front", "look_at": LOOK, "fx": 100.0}], "scene_cameras.0", ["fx, fy, cx, cy"]),
        ([{"name": "front", "look_at": LOOK, "znear_m": 2.0, "zfar_m": 1.0}], "scene_cameras.0", ["znear_m"]),
        ([{"name": "front", "look_at": LOOK, "zoom": 2}], "scene_cameras.0.zoom", []),
    ],
)
def test_a_camera_the_spec_cannot_place_is_one_line_naming_its_field(cams, field, words):
    with pytest.raises(SpecError) as e:
        _scene(*cams, source="cams.yaml")
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("cams.yaml: invalid scene spec: ")
    assert f" {field}: " in msg, msg
    for w in words:
        assert w in msg, msg


def test_camera_names_and_lookup(two):
    assert two.camera_names == ("wrist", "front")
    assert default_scene().camera_names == ("wrist",)
    assert two.camera_spec("wrist") is two.camera
    front = two.camera_spec("front")
    assert (front.width, front.height, front.fov_deg) == (128, 128, 60)
    with pytest.raises(UnknownCameraError) as e:
        two.camera_spec("top")
    assert str(e.value) == "unknown camera 'top'; this scene has: wrist, front"
    # What a renderer of the camera is built from: its intrinsics in the camera slot.
    view = two.for_camera("front")
    assert np.array_equal(view.camera.K(), front.K()) and view.objects == two.objects
    assert two.for_camera("wrist") is two


def test_without_scene_cameras_a_scene_is_the_scene_it_was(two):
    d = default_scene()
    assert spec_fingerprint(d) == DEFAULT_FINGERPRINT
    # Cameras do not change configurations: the two-camera scene reads the built-in scene's pools.
    assert spec_fingerprint(two) == DEFAULT_FINGERPRINT
    # The dump (run records, evaluation config hashes) has no new key.
    assert "scene_cameras" not in d.model_dump() and "scene_cameras" not in d.model_dump(mode="json")
    assert "scene_cameras" in two.model_dump()
    assert scene_from_dict(json.loads(json.dumps(two.model_dump(mode="json")))) == two


def test_both_pose_forms_give_the_same_pose():
    T = look_at(np.array(LOOK["eye_m"]), np.array(LOOK["target_m"]))
    explicit = {"t_table_cam_m": T[:3, 3].tolist(), "rotvec_table_cam": so3_log(T[:3, :3]).tolist()}
    a = _scene({"name": "a", "look_at": LOOK}, {"name": "b", **explicit})
    Ta, Tb = a.camera_spec("a").T_table_cam, a.camera_spec("b").T_table_cam
    np.testing.assert_allclose(Ta, Tb, atol=1e-12)
    # OpenCV axes: +z looks at the target, +y (image down) points down the table's +z.
    np.testing.assert_allclose(Ta[:3, 2], (T[:3, 3] - [0, 0, 0.05]) / -np.linalg.norm(T[:3, 3] - [0, 0, 0.05]))
    assert Ta[2, 1] < 0


coord = st.floats(-100.0, 100.0, allow_nan=False)
point = st.tuples(coord, coord, coord)


@settings(max_examples=300, deadline=None)
@given(
    point,
    point,
    st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)),
    st.floats(1.0, 179.0),
    st.integers(1, 4096),
)
def test_any_accepted_camera_has_a_finite_rigid_pose_and_finite_intrinsics(eye, target, up, fov, size):
    cam = {"name": "c", "width": size, "height": size, "fov_deg": fov, "look_at": {"eye_m": eye, "target_m": target}}
    cam["look_at"]["up"] = up
    try:
        spec = _scene(cam)
    except SpecError as e:
        assert "\n" not in str(e)
        view = np.subtract(target, eye)
        parallel = np.linalg.norm(np.cross(view, up)) <= 1e-6 * np.linalg.norm(view) * math.hypot(*up) * 1.01
        assert math.dist(eye, target) < 1e-3 or math.hypot(*up) < 1e-6 or parallel or not 1 < fov < 179, str(e)
        return
    T = spec.camera_spec("c").T_table_cam
    K = spec.camera_spec("c").K()
    assert np.isfinite(T).all() and np.isfinite(K).all() and K[0, 0] > 0
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
    assert np.linalg.det(T[:3, :3]) > 0


@settings(max_examples=200, deadline=None)
@given(point, st.tuples(*[st.floats(-2 * math.pi / math.sqrt(3), 2 * math.pi / math.sqrt(3))] * 3))
def test_explicit_poses_are_finite_and_rigid(t, rotvec):
    spec = _scene({"name": "c", "t_table_cam_m": t, "rotvec_table_cam": rotvec})
    T = spec.camera_spec("c").T_table_cam
    assert np.isfinite(T).all()
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)


# ---------------------------------------------------------------------------------------------- world


def _project(K, T_world_cam, p_world):
    T_cam_world = np.linalg.inv(T_world_cam)
    p = T_cam_world[:3, :3] @ p_world + T_cam_world[:3, 3]
    uv = K @ (p / p[2])
    return p[2], uv[:2]


def test_a_scene_camera_projects_each_object_centre_into_its_mask(two):
    with SimWorld(two, seed=0) as w:
        checked = 0
        for seed in range(8):
            w.reset(seed)
            out = w.render(camera="front")
            T = w.camera_pose("front")
            np.testing.assert_array_equal(T, two.camera_spec("front").T_table_cam)
            assert out.rgb.shape == (128, 128, 3)
            for k, c in enumerate(w.object_center_array):
                z, (u, v) = _project(w.intrinsics("front"), T, c)
                iu, iv = int(round(u)), int(round(v))
                mask = out.object_mask(k)
                assert mask.any() and 0 < z < 2.0, (seed, k)
                if out.depth[iv, iu] >= z - 0.1:  # nothing stands in front of the centre
                    ys, xs = np.nonzero(mask)
                    assert np.min(np.hypot(xs - u, ys - v)) <= 2.0, (seed, k)
                    checked += 1
        assert checked >= 12


def test_the_two_camera_scenes_front_camera_sees_both_objects_in_the_first_200_configurations(two):
    # What scenes/two-cameras.yaml and the docs say of it.
    with SimWorld(two, image_size=16, seed=0) as w:
        unseen = []
        for seed in range(200):
            w.reset(seed)
            masks = w.render(camera="front").masks
            unseen += [(seed, name) for name, m in masks.items() if not m.any()]
    assert unseen == []


def test_a_camera_looking_straight_down_sees_the_table_centre_at_the_principal_point():
    # Camera 1 m above the table, rotated pi about +x: +z (optical axis) down, +y (image down) along -y.
    spec = _scene({"name": "top", "width": 64, "height": 48, "fov_deg": 60, "t_table_cam_m": [0.1, 0.0, 1.0],
                   "rotvec_table_cam": [math.pi, 0, 0]})  # fmt: skip
    with SimWorld(spec, seed=0) as w:
        T, K = w.camera_pose("top"), w.intrinsics("top")
        z, (u, v) = _project(K, T, np.array([0.1, 0.0, 0.0]))
        assert z == pytest.approx(1.0) and (u, v) == pytest.approx(((64 - 1) / 2, (48 - 1) / 2))
        # A point at +x lands right of centre, +y above it (image rows grow along table -y).
        _, (u2, v2) = _project(K, T, np.array([0.2, 0.1, 0.0]))
        assert u2 > u and v2 < v
        out = w.render(camera="top")
        assert out.rgb.shape == (48, 64, 3) and out.depth[24, 32] == pytest.approx(1.0, abs=1e-3)


def test_world_camera_pose_keeps_the_wrist_calls(two):
    with SimWorld(two, image_size=32, seed=1) as w:
        T_tcp = w.T_world_tcp
        np.testing.assert_array_equal(w.camera_pose(), T_tcp @ two.camera.T_tcp_cam)
        np.testing.assert_array_equal(w.camera_pose("wrist"), w.camera_pose())
        np.testing.assert_array_equal(w.camera_pose(T_world_tcp=np.eye(4)), two.camera.T_tcp_cam)
        with pytest.raises(TypeError):
            w.camera_pose(np.eye(4))
        with pytest.raises(ValueError, match="fixed scene camera"):
            w.camera_pose("front", right=True)
        with pytest.raises(UnknownCameraError, match="this scene has: wrist, front"):
            w.camera_pose("top")
        # The scene camera renders at its own size, whatever the wrist camera's.
        assert w.render().rgb.shape == (32, 32, 3) and w.render(camera="front").rgb.shape == (128, 128, 3)


# ---------------------------------------------------------------------------------------------- env


def _wrist_digest(spec, cameras=None) -> str:
    spec = spec.with_updates(camera={**spec.camera.model_dump(), "stereo_baseline_m": 0.06})
    kw = {} if cameras is None else {"cameras": cameras}
    h = hashlib.sha256()
    with ReachEnv(
        spec,
        num_envs=2,
        image_size=64,
        seed=5,
        randomization=Randomization("random", "varied", 0.02),
        render_masks=True,
        stereo=True,
        **kw,
    ) as env:
        obs, info = env.reset(seed=11)
        frames = [obs]
        for _ in range(4):
            obs, _, _, _, info = env.step(env.expert_actions())
            frames.append(obs)
            h.update(info["rgb_right"].tobytes())
            for m in info["masks"]:
                for k in sorted(m):
                    h.update(np.packbits(m[k]).tobytes())
            np.testing.assert_array_equal(info["images"]["wrist"], obs)
        for f in frames:
            h.update(f.tobytes())
    return h.hexdigest()


def test_the_wrist_cameras_frames_are_the_bytes_they_were(two):
    # Light, backdrop and sensor noise randomised, masks and the stereo pair on: every stream the
    # wrist camera draws from. A scene camera rendered beside it changes none of its bytes.
    assert _wrist_digest(default_scene()) == WRIST_DIGEST
    assert _wrist_digest(two, ("wrist", "front")) == WRIST_DIGEST


class _Calls:
    def __init__(self, monkeypatch):
        self.by = []
        real = SceneRenderer.render

        def render(r, *a, **kw):
            self.by.append(r)
            return real(r, *a, **kw)

        monkeypatch.setattr(SceneRenderer, "render", render)


@pytest.mark.parametrize("cameras", [("wrist",), ("front",), ("front", "wrist")])
def test_the_env_renders_exactly_the_cameras_asked_for(two, monkeypatch, cameras):
    calls = _Calls(monkeypatch)
    with ReachEnv(two, num_envs=2, image_size=48, render_masks=True, cameras=cameras) as env:
        assert set(env.renderers) == {"wrist", *cameras}  # no renderer for a camera nobody reads
        obs, info = env.reset(seed=3)
        calls.by.clear()
        obs, _, _, _, info = env.step(np.zeros((2, 6)))
        assert sorted(id(r) for r in calls.by) == sorted(id(env.renderers[c]) for c in cameras for _ in range(2))
        assert set(info["images"]) == set(cameras) == set(info["camera_masks"])
        for c in cameras:
            shape = (2, 48, 48, 3) if c == "wrist" else (2, 128, 128, 3)
            assert info["images"][c].shape == shape and info["images"][c].dtype == np.uint8
            assert all(set(m) == {"tomato_soup_can", "mustard_bottle"} for m in info["camera_masks"][c])
        # obs is the wrist camera's when it is asked for, else the first camera's.
        np.testing.assert_array_equal(obs, info["images"]["wrist" if "wrist" in cameras else cameras[0]])
        if "front" in cameras:  # both objects stand in the front camera's view
            assert all(m.any() for ms in info["camera_masks"]["front"] for m in ms.values())
            assert info["images"]["front"].std() > 10


def test_the_env_refuses_cameras_it_cannot_render_in_one_line(two):
    with pytest.raises(UnknownCameraError) as e:
        ReachEnv(two, cameras=("wrist", "top"))
    assert str(e.value) == "unknown camera 'top'; this scene has: wrist, front"
    with pytest.raises(UnknownCameraError, match="this scene has: wrist$"):
        ReachEnv(default_scene(), cameras=("front",))
    for bad in [(), ("front", "front")]:
        with pytest.raises(EnvError, match="once"):
            ReachEnv(two, cameras=bad)
    stereo = two.with_updates(camera={**two.camera.model_dump(), "stereo_baseline_m": 0.06})
    with pytest.raises(EnvError, match="stereo"):
        ReachEnv(stereo, stereo=True, cameras=("front",))


def test_the_gym_env_observes_a_dict_of_cameras(two):
    from gymnasium import spaces

    from sim.gym_env import ReachGymEnv

    env = ReachGymEnv(two, image_size=32, cameras=("wrist", "front"), render_mode="rgb_array")
    try:
        assert isinstance(env.observation_space, spaces.Dict)
        obs, info = env.reset(seed=4)
        assert env.observation_space.contains(obs) and "images" not in info
        assert obs["wrist"].shape == (32, 32, 3) and obs["front"].shape == (128, 128, 3)
        obs, *_ = env.step(np.zeros(6, np.float32))
        assert env.observation_space.contains(obs)
        np.testing.assert_array_equal(env.render(), obs["wrist"])
    finally:
        env.close()
    one = ReachGymEnv(two, cameras=("front",))
    try:
        assert one.observation_space.shape == (128, 128, 3)
        assert one.observation_space.contains(one.reset(seed=0)[0])
    finally:
        one.close()
