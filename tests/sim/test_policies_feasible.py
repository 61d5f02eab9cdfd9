"""The task-feasible pool builder (``sim.policies.pool.build_feasible``) and its rollout core.

The expected seeds and outcomes were recorded with the builder as it was in ``trials.eval.evaluate``
(rolling candidates out through the evaluation's clean condition), before it moved into ``sim``:
the move changes no pool. The policies are tiny untrained CNNs pushed forward along the approach
axis, so which candidates reach the goal depends on what they see; the scene takes long steps so
an episode is at most 12 of them.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sim.configs import sample_config, sample_pool
from sim.policies.paired import rollout_paired
from sim.policies.pool import build_feasible
from sim.spec import default_scene
from tests.policy_zoo import contract_of, tiny_policy


def _forward_policy(state, action):
    p = tiny_policy(contract_of(state, action), seed=0)
    with torch.no_grad():
        p.mlp[-1].weight.mul_(3.0)
        p.mlp[-1].bias.copy_(torch.tensor([0.0, 0.0, 2.0, 0.0, 0.0, 0.0] * action[1]))
    return p.eval()


@pytest.fixture(scope="module")
def policies():
    return {
        "image": _forward_policy((), ("delta_tcp", 1, 1)),
        "state-chunked": _forward_policy(("tcp_pose", "gripper"), ("delta_tcp", 4, 2)),
    }


@pytest.fixture(scope="module")
def scenes():
    base = default_scene()
    fast = base.with_updates(episode={**base.episode.model_dump(), "max_steps": 12, "max_step_m": 0.07})
    # A scene with a stereo pair: the clean condition still acts on the left camera alone.
    stereo = fast.with_updates(camera={**fast.camera.model_dump(), "stereo_baseline_m": 0.06})
    return {"mono": fast, "stereo": stereo}


@pytest.mark.parametrize(
    ("policy", "scene", "part", "n", "start", "num_envs", "exclude", "max_candidates", "seeds", "tried"),
    [
        ("image", "mono", "evaluation", 6, 0, 4, (), 16, [7, 11, 13, 26], 16),
        ("image", "stereo", "evaluation", 6, 0, 4, (), 16, [7, 11, 13, 26], 16),
        ("state-chunked", "mono", "evaluation", 6, 0, 4, (), 16, [19, 21, 23, 26], 16),
        ("image", "mono", "attack", 4, 2, 3, (3, 17), 10, [5], 10),
    ],
    ids=["image-mono", "image-stereo-scene", "state-chunked", "attack-part-excluding"],
)
def test_the_feasible_pool_is_the_one_the_evaluation_built(
    policies, scenes, policy, scene, part, n, start, num_envs, exclude, max_candidates, seeds, tried
):
    spec = scenes[scene]
    got, n_tried = build_feasible(
        policies[policy],
        spec,
        part,
        n,
        start,
        num_envs,
        exclude=exclude,
        max_candidates=max_candidates,
        progress=False,
    )
    assert [c.seed for c in got] == seeds and n_tried == tried
    assert got == [sample_config(spec, s) for s in seeds]


@pytest.mark.parametrize("scene", ["mono", "stereo"])
def test_the_clean_rollout_core_gives_the_evaluations_clean_outcomes(policies, scenes, scene):
    """Five clean episodes two at a time (the last one alone in a batch padded to two): the
    outcomes ``advobj eval``'s clean arm recorded for them. With a stereo pair in the scene too:
    the clean condition looks through the left camera only (the two views' mean action would move
    every closest approach by 0.04 to 0.5 mm)."""
    spec = scenes[scene]
    res = {}
    configs = sample_pool(spec, 5, seed=3, part="evaluation")
    rollout_paired(policies["image"], spec, configs, 2, lambda j, _slot, r: res.__setitem__(j, r))
    assert [res[j]["reached"] for j in range(5)] == [0, 1, 0, -1, 0]
    assert [res[j]["steps"] for j in range(5)] == [9, 4, 6, 12, 9]
    np.testing.assert_allclose(
        [res[j]["min_dist"] for j in range(5)],
        [
            [0.09666382776046561, 0.14469915797989547],
            [0.2207005517725472, 0.09388257584846628],
            [0.09418243324755148, 0.20287058151122994],
            [0.14553693730837122, 0.20502429972542807],
            [0.07992619360455906, 0.18391389433538666],
        ],
        atol=1e-6,
    )


def test_no_candidate_is_rolled_out_for_nothing_wanted(policies, scenes):
    assert build_feasible(policies["image"], scenes["mono"], "evaluation", 0, progress=False) == ([], 0)
