"""sim.ik: damped least squares IK on the torch FK, and an arm as a scene places it.

Round trips on both shipped arms: poses made by FK from random joint vectors within the limits are
solved back (the answer's own FK is checked, not its joints: a redundant arm reaches a pose in many
ways), every iterate stays within the limits, an unreachable pose is reported rather than solved,
and neither the limits nor singular configurations give a NaN.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sim.ik import TOL_M, TOL_RAD, IkError, IkResult, SceneArm, rotvec, solve_ik
from sim.kinematics import SHIPPED_ARMS, KinematicsError, shipped_arm
from sim.spec import ArmModelConfig

ARMS = sorted(SHIPPED_ARMS)
DEVICES = [
    "cpu",
    pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device here")),
]


def _uniform_q(arm, n: int, seed: int, margin: float = 0.0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    lo, hi = arm.limits.q_min, arm.limits.q_max
    u = margin + (1 - 2 * margin) * torch.rand(n, arm.n_joints, generator=g, dtype=torch.float64)
    return lo + u * (hi - lo)


def _pose_errors(arm, q: torch.Tensor, T_target: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and geodesic rotation (rad) errors of FK(q) against the targets, in numpy float64."""
    T = arm.fk(q).numpy()
    Tt = T_target.numpy()
    dp = np.linalg.norm(T[:, :3, 3] - Tt[:, :3, 3], axis=-1)
    R = np.swapaxes(T[:, :3, :3], -1, -2) @ Tt[:, :3, :3]
    v = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], -1)
    return dp, np.arctan2(np.linalg.norm(v, axis=-1) / 2, (np.trace(R, axis1=-2, axis2=-1) - 1) / 2)


def _within_limits(arm, q: torch.Tensor) -> bool:
    return bool(((q >= arm.limits.q_min) & (q <= arm.limits.q_max)).all())


@pytest.mark.parametrize("name", ARMS)
def test_fk_jacobian_matches_finite_differences_of_the_fk(name):
    arm = shipped_arm(name)
    q = _uniform_q(arm, 8, seed=1)
    T, J = arm.fk_jacobian(q)
    assert torch.equal(T, arm.fk(q))  # the same walk: the pose is FK's, bit for bit
    eps = 1e-6
    for k in range(arm.n_joints):
        dq = torch.zeros_like(q)
        dq[:, k] = eps
        Tp, Tm = arm.fk(q + dq), arm.fk(q - dq)
        v = (Tp[:, :3, 3] - Tm[:, :3, 3]) / (2 * eps)
        # angular velocity: the vee of dR R^T
        W = (Tp[:, :3, :3] - Tm[:, :3, :3]) / (2 * eps) @ T[:, :3, :3].transpose(-1, -2)
        w = torch.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], -1)
        torch.testing.assert_close(J[:, :3, k], v, atol=1e-8, rtol=0)
        torch.testing.assert_close(J[:, 3:, k], w, atol=1e-8, rtol=0)


@pytest.mark.parametrize("name", ARMS)
def test_fk_round_trips_from_a_nearby_seed_on_random_poses_within_tolerance(name):
    arm = shipped_arm(name)
    q_true = _uniform_q(arm, 400, seed=2, margin=0.02)
    T = arm.fk(q_true)
    g = torch.Generator().manual_seed(3)
    q0 = (q_true + (torch.rand(q_true.shape, generator=g, dtype=torch.float64) - 0.5) * 0.4).clamp(
        arm.limits.q_min, arm.limits.q_max
    )
    res = solve_ik(arm, T, q0)
    ok = res.converged.numpy()
    # a seed may be walled off from its pose by a joint limit (every iterate is clipped): rare, and reported
    assert isinstance(res, IkResult) and ok.mean() >= 0.99, f"{int((~ok).sum())} of 400 not reached"
    dp, dr = _pose_errors(arm, res.q, T)
    assert dp[ok].max() <= TOL_M and dr[ok].max() <= TOL_RAD  # checked on the answer's own FK, independently
    assert ((dp[~ok] > TOL_M) | (dr[~ok] > TOL_RAD)).all()
    np.testing.assert_allclose(dp, res.pos_err_m.numpy(), atol=1e-12)
    assert _within_limits(arm, res.q)


@pytest.mark.parametrize("name", ARMS)
def test_far_random_poses_are_reached_or_reported_never_handed_back_wrong(name):
    # From the middle of the limits, random poses of the whole workspace: many converge, and every
    # one flagged converged is within tolerance by its own FK; the rest report their true errors.
    arm = shipped_arm(name)
    q_true = _uniform_q(arm, 300, seed=4)
    T = arm.fk(q_true)
    home = ((arm.limits.q_min + arm.limits.q_max) / 2).expand(300, -1).contiguous()
    res = solve_ik(arm, T, home, max_iters=150)
    dp, dr = _pose_errors(arm, res.q, T)
    ok = res.converged.numpy()
    assert ok.mean() > 0.5
    assert (dp[ok] <= TOL_M).all() and (dr[ok] <= TOL_RAD).all()
    assert ((dp[~ok] > TOL_M) | (dr[~ok] > TOL_RAD)).all()
    np.testing.assert_allclose(dr, res.rot_err_rad.numpy(), atol=1e-9)
    assert _within_limits(arm, res.q)


@pytest.mark.parametrize("name", ARMS)
def test_an_unreachable_pose_is_reported_in_one_line_and_its_best_iterate_stays_within_limits(name):
    arm = shipped_arm(name)
    T = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    T[0, :3, 3] = torch.tensor([3.0, 0.0, 0.5])  # 3 m away: beyond any arm here
    T[1] = arm.fk(_uniform_q(arm, 1, seed=5))[0]
    home = ((arm.limits.q_min + arm.limits.q_max) / 2).expand(2, -1).contiguous()
    res = solve_ik(arm, T, home)
    assert res.converged.tolist() == [False, True]
    assert res.pos_err_m[0] > 1.0 and res.iterations == 100
    assert torch.isfinite(res.q).all() and _within_limits(arm, res.q)
    with pytest.raises(IkError, match=r"^start\[0\]: the arm does not reach it within its joint limits") as err:
        res.require("start")
    assert "\n" not in str(err.value) and "1 of 2 unreached" in str(err.value)
    assert torch.equal(solve_ik(arm, T[1:], home[1:]).require(), solve_ik(arm, T[1:], home[1:]).q)


def _singular_or_limit_q(name: str, data) -> torch.Tensor:
    arm = shipped_arm(name)
    lo, hi = arm.limits.q_min.numpy(), arm.limits.q_max.numpy()
    q = []
    for k in range(arm.n_joints):
        q.append(
            data.draw(
                st.one_of(
                    st.sampled_from([lo[k], hi[k], 0.0 if lo[k] <= 0.0 <= hi[k] else lo[k]]),
                    st.floats(lo[k], hi[k], allow_nan=False),
                )
            )
        )
    return torch.tensor([q], dtype=torch.float64)


@pytest.mark.parametrize("name", ARMS)
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_limits_and_singular_configurations_never_give_nan(name, data):
    # Seeds and targets at the limits' ends and at 0 (UR5: a stretched elbow and aligned wrist axes
    # are singular; Panda: joint 4 at its upper limit 0 stretches the arm), targets anywhere,
    # unreachable ones included: every answer is finite, within the limits, with finite errors.
    arm = shipped_arm(name)
    q0 = _singular_or_limit_q(name, data)
    q_t = _singular_or_limit_q(name, data)
    T = arm.fk(q_t)
    shift = data.draw(st.sampled_from([0.0, 0.05, 5.0]))
    T[:, 0, 3] += shift
    res = solve_ik(arm, T, q0, max_iters=30)
    assert torch.isfinite(res.q).all() and torch.isfinite(res.pos_err_m).all() and torch.isfinite(res.rot_err_rad).all()
    assert _within_limits(arm, res.q)
    if shift == 5.0:
        assert not res.converged.any()
    T0, J = arm.fk_jacobian(q0)
    assert torch.isfinite(J).all() and torch.isfinite(T0).all()


def test_rotvec_is_the_rotation_angle_and_finite_with_a_finite_gradient_at_the_identity():
    R = torch.eye(3, dtype=torch.float64, requires_grad=True)
    v = rotvec(R)
    v.sum().backward()
    assert torch.equal(v.detach(), torch.zeros(3, dtype=torch.float64)) and torch.isfinite(R.grad).all()
    from sim.geometry import so3_exp

    for angle in (1e-9, 0.3, 2.0, math.pi - 1e-3):
        w = torch.tensor([0.0, 0.6, 0.8], dtype=torch.float64) * angle
        torch.testing.assert_close(rotvec(so3_exp(w)), w, atol=1e-6, rtol=0)


def test_a_bad_seed_target_or_setting_is_one_clear_error():
    arm = shipped_arm("panda")
    q = ((arm.limits.q_min + arm.limits.q_max) / 2)[None]
    T = arm.fk(q)
    with pytest.raises(KinematicsError, match="a joint vector of length 6"):
        solve_ik(arm, T, q[:, :6])
    with pytest.raises(KinematicsError, match=r"q0\[0\]: joint 'panda_joint1' is nan"):
        solve_ik(arm, T, torch.full_like(q, float("nan")))
    with pytest.raises(KinematicsError, match="outside its limits"):
        solve_ik(arm, T, q + 10.0)
    bad = T.clone()
    bad[0, 0, 3] = float("inf")
    with pytest.raises(KinematicsError, match="not finite"):
        solve_ik(arm, bad, q)
    with pytest.raises(KinematicsError, match="expected a tensor of shape"):
        solve_ik(arm, T[0], q)
    with pytest.raises(KinematicsError, match="must be > 0"):
        solve_ik(arm, T, q, tol_m=0.0)
    with pytest.raises(KinematicsError, match="float32"):
        solve_ik(arm, T.float(), q)


@pytest.mark.parametrize("device", DEVICES)
def test_ik_runs_in_float32_and_on_the_models_device(device):
    arm = shipped_arm("ur5", device=device)
    q_true = _uniform_q(arm.to("cpu"), 16, seed=6, margin=0.05).to(device)
    q0 = (q_true + 0.1).clamp(arm.limits.q_min, arm.limits.q_max)
    T = arm.fk(q_true)
    res = solve_ik(arm, T.float(), q0.float(), tol_m=1e-3, tol_rad=1e-2)
    assert res.q.dtype == torch.float32 and res.q.device.type == torch.device(device).type
    assert res.converged.all()


def _scene_arm(name: str = "panda", **kw) -> SceneArm:
    base, tool = SHIPPED_ARMS[name]
    return ArmModelConfig(urdf=name, base_link=base, tool_link=tool, **kw).scene_arm()


def test_the_scene_arm_places_fk_between_its_base_and_tcp_transforms():
    arm = _scene_arm(t_table_base_m=(-0.5, 0.1, 0.02), rotvec_table_base=(0, 0, 0.7), t_tool_tcp_m=(0, 0, 0.1))
    q = _uniform_q(arm.model, 5, seed=7)
    want = torch.from_numpy(arm.T_world_base) @ arm.model.fk(q) @ torch.from_numpy(arm.T_tool_tcp)
    torch.testing.assert_close(arm.tcp_pose(q), want, atol=1e-15, rtol=0)
    res = arm.ik(want, (q + 0.05).clamp(arm.model.limits.q_min, arm.model.limits.q_max))
    assert res.converged.all()
    torch.testing.assert_close(arm.tcp_pose(res.q)[:, :3, 3], want[:, :3, 3], atol=TOL_M, rtol=0)
    np.testing.assert_allclose(arm.q_home, (arm.model.chain.q_min + arm.model.chain.q_max) / 2)


def test_solve_start_tries_restarts_and_is_a_function_of_the_pose():
    arm = _scene_arm()
    q_true = _uniform_q(arm.model, 24, seed=8, margin=0.05)
    T = arm.tcp_pose(q_true)
    first = arm.solve_start(T)
    again = arm.solve_start(T)
    assert torch.equal(first.q, again.q) and torch.equal(first.converged, again.converged)
    home_only = arm.ik(T, torch.from_numpy(arm.q_home).expand(24, -1).contiguous())
    # the restarts reach every pose the home seed reaches, and more
    assert (first.converged >= home_only.converged).all() and first.converged.sum() > home_only.converged.sum()
    dp, _ = _pose_errors(arm.model, first.q, torch.linalg.inv(torch.from_numpy(arm.T_world_base)) @ T)
    assert (dp[first.converged.numpy()] <= TOL_M).all()


@settings(max_examples=200, deadline=None)
@given(
    u=st.lists(st.floats(0.0, 1.0), min_size=7, max_size=7),
    target=st.lists(st.floats(-1e6, 1e6, allow_nan=False), min_size=7, max_size=7),
    period=st.floats(1e-3, 10.0),
)
def test_limit_step_keeps_every_joint_within_its_position_and_velocity_limits(u, target, period):
    arm = _scene_arm(control_period_s=period)
    lo, hi = arm.model.limits.q_min, arm.model.limits.q_max
    q = (lo + torch.tensor(u, dtype=torch.float64) * (hi - lo))[None]
    t = torch.tensor([target], dtype=torch.float64)
    q_next = arm.limit_step(q, t)
    step = arm.model.limits.qd_max * period
    assert _within_limits(arm.model, q_next)
    assert ((q_next - q).abs() <= step * (1 + 1e-12)).all()
    # the direction toward the clipped target is kept
    d_want = torch.maximum(torch.minimum(t, hi), lo) - q
    d_got = q_next - q
    cross = d_want[0, :, None] * d_got[0, None, :] - d_got[0, :, None] * d_want[0, None, :]
    assert cross.abs().max() <= 1e-9 * max(1.0, float(d_want.abs().max()) ** 2)
    if (d_want.abs() <= step).all():  # within one step: reached exactly
        torch.testing.assert_close(q_next, q + d_want, atol=1e-12, rtol=0)
