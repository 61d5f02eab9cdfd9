"""sim.poses: the one pose entry and rigid-transform check that recordings and calibration files share."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

import calibration.io as cio
from sim import recording
from sim.geometry import make_T, so3_exp
from sim.poses import MAX_ROTVEC_RAD, MAX_TRANSLATION_M, Pose, check_T

finite = st.floats(-1e3, 1e3, allow_nan=False)
vec3 = st.tuples(finite, finite, finite)
small_rotvec = st.tuples(*[st.floats(-1.8, 1.8, allow_nan=False)] * 3)


def _T(rotvec, t) -> np.ndarray:
    return make_T(so3_exp(np.asarray(rotvec, float)), np.asarray(t, float))


def test_calibration_and_recordings_use_this_one_implementation():
    assert cio.check_T is check_T
    assert issubclass(cio.PoseModel, Pose) and recording.Pose is Pose


@settings(max_examples=100, deadline=None)
@given(rotvec=small_rotvec, t=vec3)
def test_a_rigid_transform_passes_and_its_entry_gives_it_back(rotvec, t):
    T = _T(rotvec, t)
    assert check_T(T, "T", single=True, max_translation_m=MAX_TRANSLATION_M) is not None
    np.testing.assert_allclose(Pose.of(T).T, T, rtol=0, atol=1e-9)
    np.testing.assert_allclose(cio.T_to_pose(T).T, T, rtol=0, atol=1e-9)


@pytest.mark.parametrize(
    "T, message",
    [
        ("four", "not a 4x4 array of numbers"),
        ({"R": 1}, "not a 4x4 array of numbers"),
        (np.eye(3), r"expected shape \(4, 4\)"),
        (np.eye(4)[None], r"expected shape \(4, 4\)"),
        (np.diag([1.0, 1.0, -1.0, 1.0]), "the rotation part is not a proper rotation matrix"),
        (np.diag([2.0, 1.0, 1.0, 1.0]), "the rotation part is not a proper rotation matrix"),
        (_T((0, 0, 0), (1e300, 0, 0)), "each translation component must lie within \\+-1000 m"),
        (_T((0, 0, 0), (0, 0, 1000.001)), "each translation component must lie within \\+-1000 m"),
    ],
)
def test_what_is_no_rigid_transform_is_one_line_naming_it(T, message):
    with pytest.raises(ValueError, match=f"^camera 'w': T_tcp_cam: {message}") as err:
        check_T(T, "camera 'w': T_tcp_cam", single=True, max_translation_m=MAX_TRANSLATION_M)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("at", [(0, 0), (0, 3), (3, 3)])
def test_nan_or_inf_anywhere_is_refused(bad, at):
    T = np.eye(4)
    T[at] = bad
    with pytest.raises(ValueError, match="T: contains NaN or inf"):
        check_T(T, "T")


def test_the_last_row_must_be_homogeneous():
    T = np.eye(4)
    T[3, 0] = 1e-3
    with pytest.raises(ValueError, match=r"T: the last row must be \[0, 0, 0, 1\]"):
        check_T(T, "T")
    T[3, 0] = 1e-7  # within the tolerance
    check_T(T, "T")


def test_huge_finite_entries_are_refused_without_an_overflow_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for huge in (1e200, np.finfo(np.float64).max):
            with pytest.raises(ValueError, match="not a proper rotation"):
                check_T(np.diag([huge, 1.0, 1.0, 1.0]), "T")


def test_a_batch_is_checked_whole_and_an_empty_one_passes():
    batch = np.stack([np.eye(4), _T((0.1, 0.2, 0.3), (1, 2, 3))])
    assert check_T(batch, "T_base_tcp").shape == (2, 4, 4)
    batch[1, 0, 0] = -1.0
    with pytest.raises(ValueError, match="T_base_tcp: the rotation part"):
        check_T(batch, "T_base_tcp")
    assert check_T(np.zeros((0, 4, 4)), "T").shape == (0, 4, 4)
    with pytest.raises(ValueError, match=r"expected shape \(\.\.\., 4, 4\)"):
        check_T(np.eye(3), "T")


def test_the_translation_bound_is_only_asked_for_when_given():
    far = _T((0, 0, 0), (5000.0, 0, 0))
    assert check_T(far, "T") is not None
    with pytest.raises(ValueError, match="within \\+-10 m"):
        check_T(far, "T", max_translation_m=10.0)


def test_the_entry_holds_its_bounds_at_their_edges():
    edge = math.nextafter(MAX_TRANSLATION_M, math.inf)
    Pose(translation_m=(MAX_TRANSLATION_M, -MAX_TRANSLATION_M, 0.0), rotvec_rad=(MAX_ROTVEC_RAD, 0.0, 0.0))
    with pytest.raises(ValidationError, match="each component must lie within"):
        Pose(translation_m=(0.0, edge, 0.0), rotvec_rad=(0.0, 0.0, 0.0))
    with pytest.raises(ValidationError, match="norm must be at most 100 rad"):
        Pose(translation_m=(0.0, 0.0, 0.0), rotvec_rad=(60.0, 60.0, 60.0))
    with pytest.raises(ValidationError, match="finite"):
        Pose(translation_m=(math.nan, 0.0, 0.0), rotvec_rad=(0.0, 0.0, 0.0))
    with pytest.raises(ValidationError, match="rotvec_rad"):
        Pose(translation_m=(0.0, 0.0, 0.0))  # both fields required
    with pytest.raises(ValidationError, match="extra"):
        Pose(translation_m=(0.0, 0.0, 0.0), rotvec_rad=(0.0, 0.0, 0.0), quat=(0, 0, 0, 1))


def test_the_calibration_entry_defaults_to_the_identity_and_keeps_the_bounds():
    np.testing.assert_array_equal(cio.PoseModel().T, np.eye(4))
    with pytest.raises(ValidationError, match="each component must lie within"):
        cio.PoseModel(translation_m=(1e4, 0.0, 0.0))
    with pytest.raises(ValidationError, match="norm must be at most"):
        cio.PoseModel(rotvec_rad=(1e200, 0.0, 0.0))
    with pytest.raises(ValueError, match=r"^T: expected shape \(4, 4\)"):
        cio.T_to_pose(np.stack([np.eye(4)] * 2))
