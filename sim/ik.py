"""Inverse kinematics on the torch FK, and an arm as a scene places it.

* :func:`solve_ik`: damped least squares (DLS) on :meth:`sim.kinematics.ArmModel.fk_jacobian`,
  batched, in float64 or float32 on the model's device. Each iteration takes
  ``dq = J^T (J J^T + damping^2 I)^-1 e`` for the pose error ``e = (p_target - p, log(R_target R^T))``
  (base frame, m and rad), scales ``dq`` down as a whole to at most :data:`MAX_IK_STEP` per joint,
  and clips ``q`` to the joint's position limits, so every iterate (and the answer) lies within
  them. It stops when every row is within ``tol_m`` and ``tol_rad`` or after ``max_iters``
  iterations, and returns the best iterate of each row with its errors and a ``converged`` flag:
  a pose it could not reach is reported (:attr:`IkResult.converged`, :meth:`IkResult.require`),
  never handed back as a solution. The damping keeps the step finite at singular configurations
  (a stretched or folded arm, aligned wrist axes): no NaN comes out of a finite input.
* :class:`SceneArm`: a URDF arm where a scene puts it (:class:`sim.spec.ArmModelConfig`): its base
  in the table frame, the TCP in the tool link's frame, the control period that turns joint
  velocity limits into a per-step bound. :meth:`SceneArm.tcp_pose` is ``T_world_tcp = T_world_base
  FK(q) T_tool_tcp`` (differentiable), :meth:`SceneArm.limit_step` the one rule that enforces the
  joint limits on a commanded target, :meth:`SceneArm.solve_start` the IK of a start pose from the
  arm's home configuration (then from fixed pseudo-random restarts).

Frames and units follow :mod:`sim.geometry`: ``T_a_b`` maps points in frame ``b`` into frame ``a``;
metres, radians (a prismatic joint's position in metres).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from sim.kinematics import ArmModel, KinematicsError

__all__ = [
    "IkError",
    "IkResult",
    "TOL_M",
    "TOL_RAD",
    "MAX_ITERS",
    "DAMPING",
    "MAX_IK_STEP",
    "START_RESTARTS",
    "START_TOL_M",
    "START_TOL_RAD",
    "rotvec",
    "solve_ik",
    "SceneArm",
]

#: Default position tolerance of :func:`solve_ik` (m): the tool origin within 0.1 mm of the target.
TOL_M = 1e-4
#: Default rotation tolerance of :func:`solve_ik` (rad, geodesic angle).
TOL_RAD = 1e-3
#: Default iteration cap of :func:`solve_ik`.
MAX_ITERS = 100
#: Default DLS damping (m or rad): the step's size in a direction of the pose the arm cannot move
#: in (a singular value ``s`` of ``J`` is answered with ``s / (s^2 + damping^2)``, at most
#: ``1 / (2 damping)``).
DAMPING = 0.02
#: At most this change of any joint (rad or m) in one IK iteration; the step is scaled as a whole.
MAX_IK_STEP = 0.5
#: Seeds :meth:`SceneArm.solve_start` tries after the home configuration (fixed, pseudo-random).
START_RESTARTS = 16
#: A start pose (:meth:`SceneArm.solve_start`) the IK leaves short of :data:`TOL_M` / :data:`TOL_RAD`
#: is still a start when its best iterate is this close (:meth:`IkResult.start_reached`): the arm then
#: starts at FK of those joints, a few mm from the pose asked for. Of 4,140 start poses of
#: scenes/panda-joint.yaml (evaluation seeds 0-1999, 30 DAgger iterations' seeds, 700 of the split's
#: attack and validation parts) one missed, seed 10050039, by 3.5 mm and 0.0008 rad.
START_TOL_M, START_TOL_RAD = 0.005, 0.01


class IkError(KinematicsError):
    """A pose the IK did not reach within its tolerance; one line naming the row and the errors."""


def rotvec(R: torch.Tensor) -> torch.Tensor:
    """Axis-angle ``(..., 3)`` rad of rotation matrices ``R: (..., 3, 3)`` (torch, differentiable).

    The atan2 form with the sine's norm floored, so the value and its gradient are finite at the
    identity. Near pi the axis is less accurate than :func:`sim.geometry.so3_log` (numpy), which
    the execution uses; the angle (the norm) is accurate everywhere.
    """
    vee = 0.5 * torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    cos = ((R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0) / 2.0).clamp(-1.0, 1.0)
    sin = torch.sqrt((vee * vee).sum(-1).clamp_min(1e-12))
    theta = torch.atan2(sin, cos)
    return vee * (theta / sin)[..., None]


def _angle(R: torch.Tensor) -> torch.Tensor:
    """Geodesic angle ``(...,)`` rad of ``R`` (atan2: accurate at 0 and at pi)."""
    vee = 0.5 * torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    cos = (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0) / 2.0
    return torch.atan2(torch.linalg.vector_norm(vee, dim=-1), cos)


@dataclass(frozen=True, eq=False)
class IkResult:
    """What :func:`solve_ik` found, per row of the batch.

    ``q (B, n)``: the best iterate (within the position limits); ``converged (B,)`` bool: it is within
    both tolerances; ``pos_err_m (B,)`` and ``rot_err_rad (B,)``: its pose errors; ``iterations``:
    the iterations run (the batch stops together).
    """

    q: torch.Tensor
    converged: torch.Tensor
    pos_err_m: torch.Tensor
    rot_err_rad: torch.Tensor
    iterations: int

    def start_reached(self) -> torch.Tensor:
        """``(B,)`` bool: converged, or within :data:`START_TOL_M` / :data:`START_TOL_RAD` (a start
        pose's rule: the simulator's, the real runner's and the sim arm's positioning moves)."""
        return self.converged | ((self.pos_err_m <= START_TOL_M) & (self.rot_err_rad <= START_TOL_RAD))

    def require(self, what: str = "pose") -> torch.Tensor:
        """``q`` when every row converged, else an :class:`IkError` naming the first row that did not."""
        bad = (~self.converged).nonzero()
        if len(bad):
            i = int(bad[0, 0])
            raise IkError(
                f"{what}[{i}]: the arm does not reach it within its joint limits (best: "
                f"{float(self.pos_err_m[i]):.3g} m and {float(self.rot_err_rad[i]):.3g} rad away after "
                f"{self.iterations} iterations; "
                f"{int(bad.shape[0])} of {len(self.converged)} unreached)",
                "q",
            )
        return self.q


def _as_like(x, like: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(x, dtype=like.dtype, device=like.device)


def solve_ik(
    arm: ArmModel,
    T_base_tool: torch.Tensor,
    q0: torch.Tensor,
    *,
    tol_m: float = TOL_M,
    tol_rad: float = TOL_RAD,
    max_iters: int = MAX_ITERS,
    damping: float = DAMPING,
) -> IkResult:
    """Joint positions ``q (B, n)`` putting the tool link at ``T_base_tool (B, 4, 4)``, from ``q0 (B, n)``.

    Damped least squares (module docstring), every iterate clipped to the joint limits. ``q0`` is
    checked like any input from outside (:meth:`ArmModel.check_q`, a tolerance of 1e-9 beyond the
    limits), ``T_base_tool`` must be finite and of ``q0``'s dtype and device; a wrong shape is a
    :class:`sim.kinematics.KinematicsError`. Rows that converge stop moving; the answer of a row that
    did not is its best iterate, flagged in :attr:`IkResult.converged`.
    """
    if not (tol_m > 0 and tol_rad > 0 and damping > 0 and max_iters >= 0):
        raise KinematicsError(
            f"solve_ik: tol_m, tol_rad and damping must be > 0 and max_iters >= 0, got {tol_m}, {tol_rad}, "
            f"{damping}, {max_iters}"
        )
    q0 = arm.check_q(q0, tol=1e-9, what="q0")
    if not isinstance(T_base_tool, torch.Tensor) or tuple(T_base_tool.shape) != (*q0.shape[:-1], 4, 4):
        shape = tuple(T_base_tool.shape) if isinstance(T_base_tool, torch.Tensor) else type(T_base_tool).__name__
        raise KinematicsError(f"T_base_tool: expected a tensor of shape {(*q0.shape[:-1], 4, 4)}, got {shape}", "q")
    if T_base_tool.dtype != q0.dtype or T_base_tool.device != q0.device:
        raise KinematicsError(
            f"T_base_tool is {T_base_tool.dtype} on {T_base_tool.device}, q0 {q0.dtype} on {q0.device}", "q"
        )
    if not torch.isfinite(T_base_tool).all():
        raise KinematicsError("T_base_tool: a target pose is not finite", "q")
    lo, hi = arm.limits.q_min.to(q0.dtype), arm.limits.q_max.to(q0.dtype)
    p_t, R_t = T_base_tool[..., :3, 3], T_base_tool[..., :3, :3]
    eye = torch.eye(6, dtype=q0.dtype, device=q0.device)
    q = torch.maximum(torch.minimum(q0, hi), lo)
    best_q = q.clone()
    best_score = torch.full(q.shape[:-1], float("inf"), dtype=q.dtype, device=q.device)
    best_p = best_score.clone()
    best_r = best_score.clone()
    it = 0
    while True:
        T, J = arm.fk_jacobian(q)
        R = T[..., :3, :3]
        dR = R_t @ R.transpose(-1, -2)
        e = torch.cat([p_t - T[..., :3, 3], rotvec(dR)], -1)
        err_p = torch.linalg.vector_norm(e[..., :3], dim=-1)
        err_r = _angle(dR)
        score = torch.maximum(err_p / tol_m, err_r / tol_rad)
        score = torch.where(torch.isfinite(score), score, torch.full_like(score, float("inf")))
        better = score < best_score
        best_q = torch.where(better[..., None], q, best_q)
        best_p = torch.where(better, err_p, best_p)
        best_r = torch.where(better, err_r, best_r)
        best_score = torch.where(better, score, best_score)
        done = best_score <= 1.0
        if bool(done.all()) or it >= max_iters:
            break
        A = J @ J.transpose(-1, -2) + (damping * damping) * eye
        dq = (J.transpose(-1, -2) @ torch.linalg.solve(A, e.unsqueeze(-1))).squeeze(-1)
        scale = (dq.abs().amax(-1, keepdim=True) / MAX_IK_STEP).clamp_min(1.0)
        dq = torch.where(done[..., None], torch.zeros_like(dq), dq / scale)
        q = torch.maximum(torch.minimum(q + dq, hi), lo)
        it += 1
    return IkResult(best_q, best_score <= 1.0, best_p, best_r, it)


@dataclass(frozen=True, eq=False)
class SceneArm:
    """A URDF arm placed in a scene: build it with :meth:`sim.spec.ArmModelConfig.scene_arm`.

    ``model``: the chain (:class:`sim.kinematics.ArmModel`); ``T_world_base (4, 4)``: its base link
    in the table (world) frame; ``T_tool_tcp (4, 4)``: the TCP in the tool link's frame;
    ``control_period_s``: one env step, so a joint moves at most ``qd_max * control_period_s`` per
    step (:meth:`limit_step`); ``q_home (n,)``: the first IK seed of a start pose.
    """

    model: ArmModel
    T_world_base: np.ndarray
    T_tool_tcp: np.ndarray
    control_period_s: float
    q_home: np.ndarray

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self.model.joint_names

    @property
    def units(self) -> tuple[str, ...]:
        return self.model.units

    @property
    def n_joints(self) -> int:
        return self.model.n_joints

    @property
    def device(self) -> torch.device:
        return self.model.device

    def step_max(self, like: torch.Tensor) -> torch.Tensor:
        """``(n,)`` the most each joint moves in one step (its unit): ``qd_max * control_period_s``."""
        return self.model.limits.qd_max.to(like.dtype) * self.control_period_s

    def tcp_pose(self, q: torch.Tensor) -> torch.Tensor:
        """``T_world_tcp (..., 4, 4) = T_world_base FK(q) T_tool_tcp`` for ``q (..., n)``, in ``q``'s
        dtype, differentiable in ``q``."""
        T = self.model.fk(q)
        return _as_like(self.T_world_base, q) @ T @ _as_like(self.T_tool_tcp, q)

    def limit_step(self, q: torch.Tensor, q_target: torch.Tensor) -> torch.Tensor:
        """The joint positions one step reaches from ``q (..., n)`` when ``q_target (..., n)`` is commanded.

        The target is clipped to the position limits, then the motion ``q_target - q`` is scaled down
        as a whole (its direction in joint space kept) until every joint moves at most
        :meth:`step_max`. So the answer lies within the position limits when ``q`` does, and no joint
        exceeds its velocity limit over the control period. Differentiable in ``q_target`` (zero
        gradient in a joint clipped at a position limit).
        """
        lo, hi = self.model.limits.q_min.to(q.dtype), self.model.limits.q_max.to(q.dtype)
        dq = torch.maximum(torch.minimum(q_target, hi), lo) - q
        scale = (dq.abs() / self.step_max(q)).amax(-1, keepdim=True).clamp_min(1.0)
        # clipped again: q + (limit - q) can round one ulp past the limit
        return torch.maximum(torch.minimum(q + dq / scale, hi), lo)

    def ik(self, T_world_tcp: torch.Tensor, q0: torch.Tensor, **kw) -> IkResult:
        """:func:`solve_ik` for TCP poses ``T_world_tcp (B, 4, 4)`` in the table frame, from ``q0 (B, n)``."""
        T_base_tool = (
            _as_like(np.linalg.inv(self.T_world_base), q0) @ T_world_tcp @ _as_like(np.linalg.inv(self.T_tool_tcp), q0)
        )
        return solve_ik(self.model, T_base_tool, q0, **kw)

    def solve_start(self, T_world_tcp: torch.Tensor, restarts: int = START_RESTARTS, **kw) -> IkResult:
        """The IK of start poses ``T_world_tcp (B, 4, 4)``: from :attr:`q_home`, then, for the poses it
        leaves unreached, from ``restarts`` fixed pseudo-random configurations within the limits
        (the same ones at every call, so a start's joints are a function of its pose). Each pose
        takes the first seed that converges; unreached ones keep their best iterate, flagged."""
        like = T_world_tcp
        B, n = T_world_tcp.shape[0], self.n_joints
        home = _as_like(self.q_home, like).expand(B, n).contiguous()
        res = self.ik(T_world_tcp, home, **kw)
        miss = (~res.converged).nonzero()[:, 0]
        if len(miss) == 0 or restarts <= 0:
            return res
        gen = torch.Generator().manual_seed(0x1C)
        lo, hi = self.model.limits.q_min.cpu(), self.model.limits.q_max.cpu()
        u = torch.rand(restarts, n, generator=gen, dtype=torch.float64)
        seeds = _as_like(lo + (0.1 + 0.8 * u) * (hi - lo), like)  # (S, n), away from the limits
        m = len(miss)
        T_rep = T_world_tcp[miss].repeat_interleave(restarts, 0)
        q_rep = seeds.repeat(m, 1)
        more = self.ik(T_rep, q_rep, **kw)
        ok = more.converged.view(m, restarts)
        first = torch.where(ok.any(1), ok.to(torch.int64).argmax(1), (more.pos_err_m.view(m, restarts)).argmin(1))
        pick = torch.arange(m, device=first.device) * restarts + first
        q, conv = res.q.clone(), res.converged.clone()
        pos, rot = res.pos_err_m.clone(), res.rot_err_rad.clone()
        take = ok.any(1) | (more.pos_err_m[pick] < pos[miss])
        rows = miss[take]
        q[rows], conv[rows] = more.q[pick[take]], more.converged[pick[take]]
        pos[rows], rot[rows] = more.pos_err_m[pick[take]], more.rot_err_rad[pick[take]]
        return IkResult(q, conv, pos, rot, max(res.iterations, more.iterations))
