"""The placement sheet of a plan whose starts are given as joints (issue 31, item 5): their TCP is
the forward kinematics on the scene's arm, as the session takes it, and a joints-only start on a
scene without an arm is refused in one line naming it and a trial, before any page is written."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from sim.geometry import so3_log
from sim.spec import load_spec
from tests.trials.real.trial_session_helpers import REPO, small_plan
from trials.real.plan import load_plan
from trials.real.runner import StartError
from trials.real.sheet import placement_sheet_pdf, sheet_page_count, start_poses, tcp_page_rows

PANDA_SCENE = REPO / "scenes" / "panda-joint.yaml"


@pytest.fixture(scope="module")
def spec():
    return load_spec(PANDA_SCENE)


@pytest.fixture(scope="module")
def arm(spec):
    return spec.arm.scene_arm()


def _fk(arm, q) -> np.ndarray:
    return arm.tcp_pose(torch.as_tensor(np.asarray(q, dtype=np.float64))).numpy()


def _plan_with_joint_starts(tmp_path, arm, scene=PANDA_SCENE, n_tcp: int = 3):
    """The small plan on ``scene`` with start 0 given as joints only, start 1 both ways, the others TCP
    poses. On the arm's scene the joints are its IK of the drawn poses (start 0's moved a little), so
    start 1's agree with its pose; on another scene they are the arm's home joints."""
    plan = load_plan(small_plan(tmp_path / "plan.yaml", tmp_path, n_tcp=n_tcp, conditions=("clean",), scene=scene))
    first, second, *rest = plan.tcp_poses
    if scene == PANDA_SCENE:
        res = arm.solve_start(torch.as_tensor(np.stack([first.T_table_tcp.T(), second.T_table_tcp.T()])))
        assert bool(res.converged.all())
        q0, q1 = res.q.numpy()
        q0[0] += 0.05
    else:
        q0 = q1 = np.asarray(arm.q_home, dtype=np.float64)
    starts = [
        first.model_copy(update={"T_table_tcp": None, "joint_positions": tuple(q0)}),
        second.model_copy(update={"joint_positions": tuple(q1)}),
        *rest,
    ]
    return plan.model_copy(update={"tcp_poses": starts})


def test_a_joint_start_is_drawn_at_the_tcp_its_joints_put_on_the_scenes_arm(spec, arm, tmp_path):
    plan = _plan_with_joint_starts(tmp_path, arm)
    poses = start_poses(plan, spec)
    joints_only, both, tcp_only = plan.tcp_poses[0], plan.tcp_poses[1], plan.tcp_poses[2]
    np.testing.assert_allclose(poses[0], _fk(arm, joints_only.joint_positions), rtol=0, atol=1e-12)
    np.testing.assert_allclose(poses[1], _fk(arm, both.joint_positions), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(poses[2], tcp_only.T_table_tcp.T())  # a TCP start is its pose, as before

    rows = tcp_page_rows(plan, poses)
    by_start = {int(m[1]): r for r in rows if (m := re.match(r"^t(\d+)", r))}
    for k, mark in ((0, "J"), (1, "J"), (2, " ")):
        cells = by_start[k].split()
        assert by_start[k][5] == mark
        xyz = [float(v) for v in (cells[2:5] if mark == "J" else cells[1:4])]
        np.testing.assert_allclose(xyz, 100 * poses[k][:3, 3], rtol=0, atol=0.05)  # cm, one decimal
    rv = np.degrees(so3_log(poses[0][:3, :3]))
    assert f"({rv[0]:7.1f}, {rv[1]:7.1f}, {rv[2]:7.1f})" in by_start[0]
    assert any(r.startswith("J: a start given as joint positions") for r in rows)

    path = tmp_path / "sheet.pdf"
    n = placement_sheet_pdf(plan, path, spec)
    assert n == sheet_page_count(plan) == len(re.findall(rb"/Type\s*/Page\b(?!s)", path.read_bytes()))


def test_a_joint_start_no_trial_uses_is_listed_with_its_joints(spec, arm, tmp_path):
    plan = _plan_with_joint_starts(tmp_path, arm)
    unused = plan.tcp_poses[0].model_copy(update={"index": len(plan.tcp_poses)})
    plan = plan.model_copy(update={"tcp_poses": [*plan.tcp_poses, unused]})
    poses = start_poses(plan, spec)
    assert poses[unused.index] is None
    (row,) = [r for r in tcp_page_rows(plan, poses) if r.startswith(f"t{unused.index} ")]
    assert "(no trial starts here)" in row and f"{unused.joint_positions[0]:.3f}" in row


def test_a_joints_only_start_on_a_scene_without_an_arm_is_refused_naming_it_and_a_trial(arm, tmp_path):
    builtin = load_spec(None)
    assert builtin.arm is None
    plan = _plan_with_joint_starts(tmp_path, arm, scene=None)
    (trial,) = [t.trial_id for t in plan.trials if t.tcp_pose == 0]
    path = tmp_path / "sheet.pdf"
    with pytest.raises(
        StartError, match=rf"^trial plan: tcp_poses\.0 \(trial {trial}\): a start given as joint_positions only, "
    ) as err:
        placement_sheet_pdf(plan, path, builtin)
    assert f"scene {builtin.name!r} has no arm" in str(err.value) and "\n" not in str(err.value)
    assert not path.exists()
    # a start given both ways is drawn at its TCP pose without an arm (the session's arm checks the joints)
    both = plan.tcp_poses[1]
    plan = plan.model_copy(update={"tcp_poses": [both.model_copy(update={"index": 0}), *plan.tcp_poses[1:]]})
    poses = start_poses(plan, builtin)
    for k in (0, 1):
        np.testing.assert_array_equal(poses[k], both.T_table_tcp.T())
