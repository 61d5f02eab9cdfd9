"""Property: no sequence of random or hostile actions makes the safety layer send a command outside its limits.

100 hypothesis examples x 100 actions = 10,000 actions per run, through :class:`SafeArm` over a
pure-math arm (no rendering, no I/O). Drawing every float through hypothesis costs ~2 ms per
action, so each example draws a few hostile actions directly and a seed for numpy to generate
the rest from the same menu (small, huge, NaN/Inf, far away, non-rigid, oscillating, stale).
The injected clock advances by irregular amounts (a whole period, nothing at all, bursts far
faster than the loop, long pauses), and every command is checked against the time that
actually passed since the previous one.
"""

from __future__ import annotations

import math

import numpy as np
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from robot_io.poses import is_valid_pose, pose_from_vec, pose_step
from robot_io.safety import SafeArm, SafetyLimits
from tests.robot_io.fakes import RecordingArm, make_pose

LIMITS = SafetyLimits(
    workspace_min_m=(0.2, -0.3, 0.05),
    workspace_max_m=(0.7, 0.3, 0.5),
    max_step_m=0.01,
    max_step_rad=0.05,
    max_speed_mps=0.15,
    max_speed_radps=0.8,
    max_accel_mps2=1.0,
    control_period_s=1 / 30,
    max_frame_age_ms=100.0,
    max_trial_s=1e6,
    positioning_speed_mps=0.05,
)
TOL = 1e-9

hostile_float = st.one_of(
    st.floats(-0.05, 0.05),
    st.floats(-1e9, 1e9),
    st.sampled_from([math.nan, math.inf, -math.inf, 1e308, -1e308, 0.0]),
)
delta = st.tuples(*[hostile_float] * 6).map(lambda v: ("delta", np.array(v)))
far_pose = st.tuples(
    st.floats(-5, 5), st.floats(-5, 5), st.floats(-5, 5), st.floats(-10, 10), st.floats(-10, 10), st.floats(-10, 10)
).map(lambda v: ("pose", pose_from_vec(v)))
garbage_matrix = st.lists(hostile_float, min_size=16, max_size=16).map(lambda v: ("pose", np.array(v).reshape(4, 4)))
oscillation = st.floats(0.0, 10.0).map(lambda a: ("osc", a))
stale = st.floats(100.5, 1e6).map(lambda age_ms: ("stale", age_ms))
action = st.one_of(delta, far_pose, garbage_matrix, oscillation, stale)


ACTIONS_PER_EXAMPLE = 100
P = LIMITS.control_period_s
# Time between two actions: on time, simultaneous, a tight loop (as fast as possible), jitter, stalls.
DT_MENU_S = np.array([P, 0.0, 1e-4, 1e-3, P / 3, 0.9 * P, 2 * P, 1.0])


def numpy_actions(seed: int, n: int) -> list[tuple[str, object]]:
    rng = np.random.default_rng(seed)
    out = []
    for kind in rng.integers(0, 7, size=n):
        if kind == 0:
            out.append(("delta", rng.normal(scale=0.03, size=6)))
        elif kind == 1:
            out.append(("delta", rng.normal(scale=10.0 ** rng.uniform(0, 300), size=6)))
        elif kind == 2:
            d = rng.normal(scale=0.01, size=6)
            d[rng.integers(0, 6)] = rng.choice([np.nan, np.inf, -np.inf])
            out.append(("delta", d))
        elif kind == 3:
            out.append(("pose", pose_from_vec(np.concatenate([rng.uniform(-5, 5, 3), rng.uniform(-10, 10, 3)]))))
        elif kind == 4:
            out.append(("pose", rng.normal(scale=10.0 ** rng.uniform(-3, 3), size=(4, 4))))
        elif kind == 5:
            out.append(("osc", float(rng.uniform(0, 10))))
        else:
            out.append(("stale", float(rng.uniform(100.5, 1e6))))
    return out


def numpy_dts(seed: int, n: int) -> np.ndarray:
    return np.random.default_rng([seed, 1]).choice(DT_MENU_S, size=n)


# No shrink phase: a failure prints its (reproducible, derandomized) example at once.
@settings(
    max_examples=100,
    deadline=None,
    derandomize=True,
    database=None,
    phases=[Phase.explicit, Phase.generate],
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.large_base_example],
)
@given(
    st.integers(0, 2**32 - 1),
    st.lists(action, min_size=0, max_size=5),
    st.tuples(st.floats(0.2, 0.7), st.floats(-0.3, 0.3), st.floats(0.05, 0.5)),
)
def test_hostile_actions_never_produce_a_command_outside_the_limits(seed, drawn, start):
    actions = numpy_actions(seed, ACTIONS_PER_EXAMPLE - len(drawn))
    for i, a in enumerate(drawn):  # spread the hypothesis-drawn actions through the sequence
        actions.insert((i * 37) % (len(actions) + 1), a)
    assert len(actions) == ACTIONS_PER_EXAMPLE
    t = [0.0]
    arm = RecordingArm(make_pose(*start))
    safe = SafeArm(arm, LIMITS, clock=lambda: t[0])
    sign = 1.0
    sent_at_s = []  # clock time of every command the arm received
    with safe:
        for (kind, value), dt in zip(actions, numpy_dts(seed, len(actions))):
            t[0] += dt
            n_before, stops_before = len(arm.servos), arm.stops
            if kind == "delta":
                res = safe.step_delta(value, t[0])
            elif kind == "pose":
                res = safe.step(value, t[0])
            elif kind == "osc":  # full-amplitude reversal every step
                sign = -sign
                res = safe.step_delta([sign * value, -sign * value, sign * value, sign * value, 0.0, 0.0], t[0])
            else:
                res = safe.step_delta(np.zeros(6), t[0] - value / 1000.0)
            if (
                kind == "stale"
                or (kind == "delta" and not np.isfinite(value).all())
                or (kind == "pose" and not is_valid_pose(value))
            ):
                assert res.status == "refused" and len(arm.servos) == n_before and arm.stops == stops_before + 1
            sent_at_s += [t[0]] * (len(arm.servos) - n_before)
    kicks_expected = len(actions)
    assert arm.kicks >= kicks_expected  # the watchdog is kicked on every step, refused or not
    prev_s, path_m, path_rad = None, 0.0, 0.0
    for (T_before, T_cmd, duration), t_s in zip(arm.servos, sent_at_s):
        assert is_valid_pose(T_cmd)
        assert duration == P
        p = T_cmd[:3, 3]
        assert (p >= np.array(LIMITS.workspace_min_m) - TOL).all() and (
            p <= np.array(LIMITS.workspace_max_m) + TOL
        ).all()
        dp, dr = pose_step(T_before, T_cmd)
        assert dp <= LIMITS.step_cap_m + TOL
        assert dr <= LIMITS.step_cap_rad + 1e-7
        # Real speed: a command covers at most one period, and no more than the time since the last one.
        window_s = P if prev_s is None else min(P, t_s - prev_s)
        assert dp <= LIMITS.max_speed_mps * window_s + TOL, (
            f"{dp * 1000:.2f} mm {window_s * 1000:.2f} ms after the last command"
        )
        assert dr <= LIMITS.max_speed_radps * window_s + 1e-7
        prev_s, path_m, path_rad = t_s, path_m + dp, path_rad + dr
    if sent_at_s:  # over the whole run: the path length fits the elapsed time (plus the first command's period)
        span_s = sent_at_s[-1] - sent_at_s[0] + P
        assert path_m <= LIMITS.max_speed_mps * span_s + 1e-6 and path_rad <= LIMITS.max_speed_radps * span_s + 1e-6
