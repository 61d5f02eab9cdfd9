"""robot_io.arms.base's connect check a UR or serial arm with a URDF runs (its tolerances, extremes),
and robot_io.check's joint readings ``advobj hw check`` prints; pure functions on the shipped UR5, no device.

On real hardware only (``-m hardware``): ``advobj hw check`` against the config named by
ADVOBJ_HW_CONFIG. Never runs in CI (the default ``-m 'not slow and not hardware'`` deselects it).
It moves nothing.
"""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from robot_io.arms.base import (
    KINEMATICS_TOL_M,
    KINEMATICS_TOL_RAD,
    check_kinematics_agree,
    kinematics_disagreement,
    tcp_from_joints,
)
from robot_io.check import format_joint, joint_readings
from robot_io.errors import HardwareConfigError
from sim.geometry import make_T, so3_exp
from tests.robot_io.fakes import Q_UR5_READY, ur5_scene_arm
from trials.cli.main import app

UR5 = ur5_scene_arm()
LO = UR5.model.limits.q_min.numpy()
HI = UR5.model.limits.q_max.numpy()

unit = st.floats(0.0, 1.0)
direction = st.tuples(*[st.floats(-1.0, 1.0)] * 3).map(np.array).filter(lambda v: np.linalg.norm(v) > 1e-3)


def _refusal(q, T, **kw) -> str:
    with pytest.raises(HardwareConfigError) as info:
        check_kinematics_agree("serial arm /dev/ttyX", UR5, q, T, **kw)
    text = str(info.value)
    assert "\n" not in text and text.startswith("serial arm /dev/ttyX: the arm's URDF kinematics disagree")
    assert text.endswith("Nothing was moved")
    return text


@settings(deadline=None, max_examples=60)
@given(
    u=st.lists(unit, min_size=6, max_size=6),
    distance=st.floats(0.0, 3.0),  # in tolerances
    angle=st.floats(0.0, 3.0),
    d=direction,
    axis=direction,
)
def test_a_reported_tcp_is_refused_iff_it_is_farther_than_a_tolerance_from_the_fk(u, distance, angle, d, axis):
    assume(abs(distance - 1.0) > 1e-6 and abs(angle - 1.0) > 1e-6)  # not on the boundary itself
    q = LO + np.array(u) * (HI - LO)  # anywhere within the limits
    # The reported TCP: the FK's, moved in its own frame by `distance` tolerances and turned by `angle`.
    dT = make_T(so3_exp(axis / np.linalg.norm(axis) * angle * KINEMATICS_TOL_RAD), d / np.linalg.norm(d))
    dT[:3, 3] *= distance * KINEMATICS_TOL_M
    T = tcp_from_joints(UR5, q) @ dT
    dp, dr = kinematics_disagreement(UR5, q, T)
    assert dp == pytest.approx(distance * KINEMATICS_TOL_M, abs=1e-9)
    assert dr == pytest.approx(angle * KINEMATICS_TOL_RAD, abs=1e-7)
    if distance > 1.0 or angle > 1.0:
        text = _refusal(q, T)
        assert f"{dp * 1000:.1f} mm and {math.degrees(dr):.2f} deg" in text
    else:
        check_kinematics_agree("serial arm /dev/ttyX", UR5, q, T)


@pytest.mark.parametrize(
    "q,T",
    [
        pytest.param([np.nan] * 6, None, id="nan_joints"),
        pytest.param([np.inf, *Q_UR5_READY[1:]], None, id="inf_joint"),
        pytest.param(Q_UR5_READY, np.full((4, 4), np.nan), id="nan_tcp"),
        pytest.param(Q_UR5_READY, "inf_translation", id="inf_translation"),
        pytest.param(Q_UR5_READY, "far_translation", id="far_translation"),
    ],
)
def test_joints_or_a_tcp_that_are_not_finite_or_far_off_are_refused_in_one_line(q, T):
    T_fk = tcp_from_joints(UR5, Q_UR5_READY)
    if T is None or isinstance(T, str):
        T_bad = T_fk.copy()
        if T == "inf_translation":
            T_bad[0, 3] = np.inf
        elif T == "far_translation":
            T_bad[0, 3] = np.finfo(np.float64).max
        T = T_bad
    dp, dr = kinematics_disagreement(UR5, q, T)
    assert not dp <= KINEMATICS_TOL_M or not dr <= KINEMATICS_TOL_RAD
    finite = np.isfinite(q).all() and np.isfinite(T).all()
    assert ("hold a NaN or an infinity" in _refusal(q, T)) == (not finite)


def test_the_refusal_names_the_kinematics_fields_and_the_drivers_hint():
    T = tcp_from_joints(UR5, Q_UR5_READY)
    T[2, 3] += 2 * KINEMATICS_TOL_M
    text = _refusal(Q_UR5_READY, T, hint="a hint for this arm")
    for field in ("urdf", "t_base_link_m", "rotvec_base_link", "t_tool_tcp_m", "rotvec_tool_tcp"):
        assert field in text
    assert "; a hint for this arm. Nothing was moved" in text
    assert f"tolerance {KINEMATICS_TOL_M * 1000:g} mm, {math.degrees(KINEMATICS_TOL_RAD):.2f} deg" in text


def test_tighter_tolerances_refuse_what_the_defaults_accept():
    T = tcp_from_joints(UR5, Q_UR5_READY)
    T[2, 3] += KINEMATICS_TOL_M / 2
    check_kinematics_agree("x", UR5, Q_UR5_READY, T)
    with pytest.raises(HardwareConfigError):
        check_kinematics_agree("x", UR5, Q_UR5_READY, T, tol_m=KINEMATICS_TOL_M / 4)


# ---------------------------------------------------------------------------- joint readings


@given(q=st.lists(st.floats(-1e6, 1e6), min_size=6, max_size=6))
def test_each_reading_is_its_joint_between_its_limits_and_one_line(q):
    readings = joint_readings(UR5, q)
    assert [r.name for r in readings] == list(UR5.joint_names) and [r.unit for r in readings] == list(UR5.units)
    for r, x, lo, hi in zip(readings, q, LO, HI):
        assert r.value == x and (r.lower, r.upper) == (lo, hi)
        assert r.above_lower == x - lo and r.below_upper == hi - x
        assert r.inside == (lo <= x <= hi)
        line = format_joint(r)
        assert "\n" not in line and line.startswith(f"{r.name} = ") and f" {r.unit}" in line
        assert ("OUTSIDE" in line) == (not r.inside)


def test_a_joint_at_a_limit_is_inside_and_one_past_it_says_by_how_much_and_which_side():
    k = int(np.argmin(HI - LO))  # the joint with the narrowest range (the elbow)
    gap = 0.125
    at_lower = joint_readings(UR5, np.where(np.arange(6) == k, LO, Q_UR5_READY))[k]
    assert at_lower.inside and at_lower.above_lower == 0
    assert format_joint(at_lower).endswith(f": {0:.4f} above the lower, {HI[k] - LO[k]:.4f} below the upper")
    below = joint_readings(UR5, np.where(np.arange(6) == k, LO - gap, Q_UR5_READY))[k]
    assert format_joint(below).endswith(f": OUTSIDE them, {gap:.4f} rad below the lower")
    above = joint_readings(UR5, np.where(np.arange(6) == k, HI + gap, Q_UR5_READY))[k]
    assert format_joint(above).endswith(f": OUTSIDE them, {gap:.4f} rad above the upper")


@pytest.mark.parametrize("x", [np.nan, np.inf, -np.inf])
def test_a_joint_that_reads_no_finite_number_is_outside_and_says_so(x):
    r = joint_readings(UR5, [x, *Q_UR5_READY[1:]])[0]
    assert not r.inside and format_joint(r).endswith(": OUTSIDE them, not a finite number")


def test_readings_pad_names_so_a_list_lines_up():
    readings = joint_readings(UR5, Q_UR5_READY)
    width = max(len(r.name) for r in readings)
    assert len({format_joint(r, width).index(" = ") for r in readings}) == 1


@pytest.mark.parametrize("q", [np.zeros(5), np.zeros(7), np.zeros((2, 6))])
def test_readings_of_the_wrong_number_of_joints_are_refused_naming_them(q):
    with pytest.raises(ValueError, match="6 joint positions expected .*shoulder_pan_joint"):
        joint_readings(UR5, q)


# ---------------------------------------------------------------------------- real hardware


@pytest.mark.hardware
def test_hw_check_on_the_lab_config_reports_a_healthy_camera_and_arm():
    path = os.environ.get("ADVOBJ_HW_CONFIG")
    if not path:
        pytest.skip("set ADVOBJ_HW_CONFIG to the cell's hardware YAML")
    result = CliRunner().invoke(app, ["hw", "check", "--config", path, "--frames", "90"])
    assert result.exit_code == 0, result.output
    assert "fault: none" in result.output and "nothing moved" in result.output
