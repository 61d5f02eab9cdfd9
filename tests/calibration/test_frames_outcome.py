"""Frame chain, registry, and the real-world reach outcome (with unknown), end to end on a rendered scene."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from calibration import synthetic as S
from calibration.apriltag import detect_tags
from calibration.errors import CalibrationFileError
from calibration.frames import FrameChain, T_base_object, T_table_base
from calibration.outcome import NONE, UNKNOWN, measure_reach, real_reach_outcome
from calibration.registry import TABLE, ObjectRegistry, load_registry, locate_objects, save_registry
from sim.geometry import invert_T, look_at, make_T, rot_z, so3_exp, transform_points
from sim.outcome import reach_outcome

from .conftest import H, W

EXAMPLE = __import__("pathlib").Path(__file__).resolve().parents[2] / "examples" / "calibration" / "objects.yaml"


def test_example_registry_loads():
    reg = load_registry(EXAMPLE)
    assert reg.objects[0] == TABLE and set(reg.objects) >= {"goal", "adversarial", "distractor"}
    assert reg.tag_size(2) == 0.04 and reg.tag_size(99) is None
    c = reg.corners_in_object(2)  # tag on the lid, object centre 5 cm below: corners at z = +0.05
    assert np.allclose(c[:, 2], 0.05)


def test_registry_round_trip(tmp_path):
    reg = load_registry(EXAMPLE)
    assert load_registry(save_registry(tmp_path / "r.yaml", reg)) == reg


@pytest.mark.parametrize(
    "text, field",
    [
        ("tags:\n  900: {object: a, size_m: 0.04}\n", "tags"),
        ("tags:\n  1: {object: a, size_m: -0.04}\n", "tags.1.size_m"),
        (
            "tags:\n  1: {object: a, size_m: 0.04, T_tag_object: {translation_m: [0, 0]}}\n",
            "tags.1.T_tag_object.translation_m",
        ),
        ("tags:\n  1: {object: a, size_m: 0.04, colour: red}\n", "tags.1.colour"),
        ("tag:\n  1: {object: a, size_m: 0.04}\n", "tags"),
    ],
)
def test_corrupt_registry_names_file_and_field(tmp_path, text, field):
    p = tmp_path / "objects.yaml"
    p.write_text(text)
    with pytest.raises(CalibrationFileError) as e:
        load_registry(p)
    assert str(p) in str(e.value) and e.value.field.startswith(field)


def test_chain_composes_in_parent_child_order():
    rng = np.random.default_rng(0)
    Ts = [make_T(so3_exp(rng.normal(size=3)), rng.normal(size=3)) for _ in range(4)]
    T = T_base_object(*Ts)
    p = rng.normal(size=(5, 3))
    expect = p
    for t in reversed(Ts):
        expect = transform_points(t, expect)
    assert np.allclose(transform_points(T, p), expect)
    assert np.allclose(T_table_base(Ts[0], Ts[1], Ts[2]) @ Ts[0] @ Ts[1] @ Ts[2], np.eye(4))


def test_frame_chain_validates_and_maps_points():
    with pytest.raises(ValueError, match="T_tcp_cam"):
        FrameChain(np.eye(3))
    chain = FrameChain(make_T(np.eye(3), [0, 0, 0.1]))
    with pytest.raises(ValueError, match="T_base_table"):
        chain.points_to_table(np.zeros(3))
    T_base_tcp = make_T(np.eye(3), [0.4, 0, 0.3])
    assert np.allclose(chain.points_to_base(T_base_tcp, [0, 0, 0.2]), [0.4, 0, 0.6])
    t = chain.with_table(T_base_tcp, make_T(np.eye(3), [0, 0, 0.6]))
    assert np.allclose(t.points_to_table([0.4, 0, 1.0]), [0, 0, 0])


@settings(max_examples=80, deadline=None)
@given(
    tcp=arrays(np.float64, (4, 3), elements=st.floats(-0.3, 0.3)),
    obj=arrays(np.float64, (4, 3, 3), elements=st.floats(-0.3, 0.3)),
    radius=st.floats(0.0, 0.3),
)
def test_real_outcome_equals_the_sim_criterion_when_everything_is_seen(tcp, obj, radius):
    assert np.array_equal(real_reach_outcome(tcp, obj, radius), reach_outcome(tcp, obj, radius))


@settings(max_examples=60, deadline=None)
@given(
    tcp=arrays(np.float64, (1, 3), elements=st.floats(-0.3, 0.3)),
    obj=arrays(np.float64, (1, 3, 3), elements=st.floats(-0.3, 0.3)),
    missing=st.integers(0, 2),
)
def test_any_undetected_object_makes_the_outcome_unknown(tcp, obj, missing):
    obj = obj.copy()
    obj[0, missing] = np.nan
    assert real_reach_outcome(tcp, obj, 0.1)[0] == UNKNOWN


def test_ambiguous_positions_are_unknown_only_when_they_change_the_outcome():
    tcp = np.zeros((1, 3))
    obj = np.array([[[0.05, 0, 0], [0.5, 0, 0]]])
    alts = np.full((1, 2, 1, 3), np.nan)
    alts[0, 1, 0] = [0.45, 0, 0]  # far either way: still object 0
    assert real_reach_outcome(tcp, obj, 0.1, alts)[0] == 0
    alts[0, 1, 0] = [0.02, 0, 0]  # the other reading would be closer: unknown
    assert real_reach_outcome(tcp, obj, 0.1, alts)[0] == UNKNOWN
    assert real_reach_outcome(tcp, np.array([[[0.5, 0, 0]]]), 0.1)[0] == NONE


def test_measure_reach_names_the_result_and_why():
    r = measure_reach([0, 0, 0.0], {"goal": [0.06, 0, 0], "adversarial": [0.3, 0, 0]}, ["goal", "adversarial"], 0.10)
    assert r.reached == "goal" and r.index == 0 and r.distances_m["goal"] == pytest.approx(0.06)
    r = measure_reach([0, 0, 0.0], {"goal": [0.06, 0, 0]}, ["goal", "adversarial"], 0.10)
    assert r.reached == "unknown" and r.missing == ("adversarial",) and "adversarial" in r.reason
    r = measure_reach([0, 0, 0.0], {"goal": [0.2, 0, 0], "adversarial": [0.3, 0, 0]}, ["goal", "adversarial"], 0.10)
    assert r.reached == "none"


def test_shape_errors_name_the_argument():
    with pytest.raises(ValueError, match="object_pos"):
        real_reach_outcome(np.zeros((2, 3)), np.zeros((3, 1, 3)), 0.1)


# ---- end to end: a rendered table scene seen from the wrist camera ----------------------------

X = make_T(so3_exp([0.0, 0.0, np.pi / 2]), [0.0, -0.06, 0.04])  # T_tcp_cam
T_BASE_TABLE = make_T(rot_z(0.2), [0.45, -0.1, -0.02])  # table top 2 cm below the base origin


def _scene(registry, hide=()):
    """Render every registered tag lying face-up on the table; returns (image, T_base_tcp, true centres (base))."""
    K = S.default_K(W, H)
    objects_table = {"goal": [0.05, 0.08, 0.05], "adversarial": [-0.08, 0.02, 0.04], "distractor": [0.1, -0.09, 0.03]}
    T_table_obj = {TABLE: np.eye(4), **{n: make_T(rot_z(0.3 * i), p) for i, (n, p) in enumerate(objects_table.items())}}
    eye_table = np.array([0.02, -0.05, 0.42])
    T_table_cam = look_at(eye_table, [0.0, 0.0, 0.0], up=(0.0, 1.0, 0.0))
    T_base_cam = T_BASE_TABLE @ T_table_cam
    T_base_tcp = T_base_cam @ invert_T(X)
    planes = []
    for tag_id, e in registry.tags.items():
        if e.object in hide or e.object not in T_table_obj:
            continue
        T_table_tag = T_table_obj[e.object] @ invert_T(e.T_tag_object.T)
        planes.append(S.tag_plane(tag_id, e.size_m, invert_T(T_table_cam) @ T_table_tag, margin=0.3))
    img = S.degrade(S.render_planes(planes, K, W, H), 0.7, 2.0, seed=1)
    centres = {n: (T_BASE_TABLE @ T)[:3, 3] for n, T in T_table_obj.items() if n != TABLE}
    return img, T_base_tcp, centres


def _measure(registry, img, T_base_tcp, cam):
    dets = detect_tags(img, cam, registry.tag_size)
    obs = locate_objects(dets, registry, cam)
    chain = FrameChain(X)
    pos = {n: chain.points_to_base(T_base_tcp, o.positions_cam_m()) for n, o in obs.items() if n != TABLE}
    return obs, pos, chain


def test_object_centres_in_the_base_frame_from_tags_through_the_chain(cam):
    reg = load_registry(EXAMPLE)
    img, T_base_tcp, centres = _scene(reg)
    obs, pos, chain = _measure(reg, img, T_base_tcp, cam)
    assert set(obs) == {TABLE, "goal", "adversarial", "distractor"}
    assert obs[TABLE].tag_ids == (0, 1) and not obs[TABLE].ambiguous  # two table tags: a bundle
    for n, c in centres.items():
        assert np.linalg.norm(pos[n][0] - c) < 0.005, n
    # The table frame recovered from the table tags matches the truth.
    T_base_table = chain.to_base(T_base_tcp, obs[TABLE].T_cam_object)
    assert np.linalg.norm(T_base_table[:3, 3] - T_BASE_TABLE[:3, 3]) < 0.003


def test_reach_outcome_from_a_rendered_scene_and_unknown_when_an_object_is_hidden(cam):
    reg = load_registry(EXAMPLE)
    names = ["goal", "adversarial", "distractor"]
    img, T_base_tcp, centres = _scene(reg)
    _, pos, _ = _measure(reg, img, T_base_tcp, cam)
    tcp = centres["goal"] + [0.0, 0.0, 0.07]  # the gripper ends 7 cm above the goal's centre
    assert measure_reach(tcp, pos, names, 0.10).reached == "goal"
    img, T_base_tcp, _ = _scene(reg, hide=("distractor",))
    _, pos, _ = _measure(reg, img, T_base_tcp, cam)
    r = measure_reach(tcp, pos, names, 0.10)
    assert r.reached == "unknown" and r.missing == ("distractor",)


def test_registry_requires_known_tag_ids():
    with pytest.raises(ValueError):
        ObjectRegistry(tags={-1: {"object": "a", "size_m": 0.04}})
