"""One contract for every consumer: ``advobj eval``'s rollout, the attack (pose loss, validation) and
the real-trial runner with its safety layer, for torch and ONNX policies of each contract."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from attack.optimize import AttackRun, resolve_config
from sim.configs import sample_pool
from sim.policies.onnx_policy import OnnxPolicy, export_onnx
from sim.spec import default_scene
from tests.policy_zoo import COMBOS, IDS, card_of, contract_of, tiny_policy
from tests.trials.real.trial_session_helpers import sim_hardware, small_plan
from trials.eval.conditions import Condition
from trials.eval.evaluate import rollout_condition
from trials.real.operator import AutoOperator
from trials.real.session import SessionOptions, SessionSetupError, run_session
from trials.real.store import TrialStore


def _short(spec, steps=5):
    return spec.with_updates(episode={**spec.episode.model_dump(), "max_steps": steps})


@pytest.mark.parametrize(("state", "action"), COMBOS, ids=IDS)
def test_eval_rollout_runs_every_contract_and_measures_action_errors(state, action, tmp_path):
    c = contract_of(state, action)
    torch_p = tiny_policy(c)
    onnx_p = OnnxPolicy(export_onnx(torch_p, tmp_path / "p.onnx", card_of(torch_p)))
    spec = _short(default_scene())
    configs = sample_pool(spec, 3, seed=1, part="evaluation")
    out = {}
    for name, pol in (("torch", torch_p), ("onnx", onnx_p)):
        res = {}
        rollout_condition(pol, spec, Condition("clean"), configs, 2, lambda j, r, res=res: res.__setitem__(j, r))
        out[name] = res
    assert sorted(out["torch"]) == [0, 1, 2]
    for j in range(3):
        t, o = out["torch"][j], out["onnx"][j]
        assert 1 <= t["steps"] <= 5 and t["e_trans"] == pytest.approx(0.0, abs=1e-9)  # clean: adv == clean view
        assert (t["reached"], t["steps"]) == (o["reached"], o["steps"])
        np.testing.assert_allclose(t["min_dist"], o["min_dist"], atol=1e-3)


@pytest.mark.parametrize(("state", "action"), COMBOS, ids=IDS)
def test_the_attack_optimises_every_white_box_contract(state, action):
    c = contract_of(state, action)
    spec = default_scene()
    pool = sample_pool(spec, 4, seed=3, part="attack") + sample_pool(spec, 2, seed=3, part="validation")
    cfg = resolve_config(
        "quick",
        {
            "iterations": 2,
            "num_envs": 2,
            "rollout_steps": 2,
            "texture_size": 16,
            "lr": 0.5,
            "validation_every": 1,
            "validation_episodes": 2,
            "validation_max_steps": 3,
        },
    )
    run = AttackRun(tiny_policy(c), spec, cfg, pool=pool)
    try:
        before = run.state.texture.clone()
        infos = [run.step() for _ in range(2)]
        val = run.validate()
        probe = run.probe_pose_loss()
    finally:
        run.close()
    assert all(np.isfinite(i["pose"]) and np.isfinite(i["sal"]) for i in infos)
    assert np.isfinite(run.state.history.loss_dist).all() and max(run.state.history.grad_norm) > 0
    assert not np.array_equal(before.numpy(), run.state.texture.numpy())
    assert val["episodes"] == 2 and 0.0 <= val["t_asr"] <= 1.0 and np.isfinite(val["dist_m"]) and np.isfinite(probe)


def test_the_pose_loss_of_an_absolute_action_is_measured_at_its_target():
    """An absolute target one step away at the adversarial object's centre: L_dist is ~0."""
    import torch

    from attack.losses import pose_loss
    from sim.policies.contract import to_delta

    T = torch.eye(4, dtype=torch.float64)[None]
    T[0, :3, 3] = torch.tensor([0.0, 0.0, 0.3])
    p_adv = torch.tensor([[0.01, 0.005, 0.29]], dtype=torch.float64)
    target = torch.tensor([[0.01, 0.005, 0.29, 0.0, 0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    a = to_delta(T, target, "absolute_tcp", 0.02, 0.1)
    _, parts = pose_loss(T, a, p_adv, 0.02, 0.1, 1.0)
    assert float(parts["dist"][0]) < 1e-6


def _onnx_with_card(c, path):
    p = tiny_policy(c)
    return export_onnx(p, path, card_of(p))


def _session(tmp_path, c, max_frame_age_ms=500.0):
    hw = sim_hardware(tmp_path / "hw.yaml")
    data = yaml.safe_load(hw.read_text())
    data["safety"]["max_frame_age_ms"] = max_frame_age_ms
    hw.write_text(yaml.safe_dump(data))
    plan = small_plan(tmp_path / "plan.yaml", tmp_path, n_tcp=1, max_steps=6, conditions=("clean",))
    policy = _onnx_with_card(c, tmp_path / "p.onnx")
    db = tmp_path / "t.sqlite"
    opts = SessionOptions(hardware=hw, policy=policy, plan=plan, session="s", db=db, rate_limit=False)
    run_session(opts, operator=AutoOperator(log=None))
    return TrialStore(db)


def test_the_real_runner_steps_toward_absolute_chunk_targets_as_the_sim_does_through_the_safety_layer(tmp_path):
    c = contract_of(("tcp_pose", "gripper"), ("absolute_tcp", 3, 2))
    store = _session(tmp_path, c)
    rows = store.con.execute("SELECT * FROM steps ORDER BY step").fetchall()
    assert len(rows) >= 2 and all(r["safety_status"] in ("ok", "clipped") for r in rows)
    for prev, r in zip(rows, rows[1:]):
        target = np.array([r[f"action_{i}"] for i in range(3)])
        assert abs(target[2] - 0.1) < 0.01  # the tiny policy's targets sit 10 cm above the table
        p_prev = np.array([prev[f"meas_base_{a}"] for a in ("x_m", "y_m", "z_m")])
        p_cmd = np.array([r[f"cmd_base_{a}"] for a in ("x_m", "y_m", "z_m")])
        step = p_cmd - p_prev
        # one limited step straight toward the target (table frame = base frame on sim hardware)
        assert 0 < np.linalg.norm(step) <= 0.02 * np.sqrt(3) + 1e-9
        assert np.dot(step, target - p_prev) / (np.linalg.norm(step) * np.linalg.norm(target - p_prev)) > 0.99


def test_a_chunk_that_outlives_the_safety_frame_age_limit_is_refused_before_anything_moves(tmp_path):
    c = contract_of((), ("delta_tcp", 4, 3))
    with pytest.raises(
        SessionSetupError,
        match=r"safety.max_frame_age_ms: the policy executes 3 actions per frame at 10 Hz, "
        r"so its last action is sent 2\d\d ms after its frame",
    ):
        _session(tmp_path, c, max_frame_age_ms=100.0)
    assert not (tmp_path / "t.sqlite").exists()


def test_a_policy_whose_outputs_do_not_fit_its_card_is_refused_before_any_device(tmp_path):
    from sim.policies.contract import ActionContract, PolicyContract
    from sim.policies.onnx_policy import attach_card

    p = tiny_policy(contract_of((), ("delta_tcp", 1, 1)))
    path = export_onnx(p, tmp_path / "p.onnx")
    card = card_of(p).model_copy(update={"contract": PolicyContract(action=ActionContract(chunk=4, execute=1))})
    attach_card(path, card)  # the card says chunks of 4, the graph outputs one action
    hw = sim_hardware(tmp_path / "hw.yaml")
    plan = small_plan(tmp_path / "plan.yaml", tmp_path, n_tcp=1, max_steps=3, conditions=("clean",))
    opts = SessionOptions(hardware=hw, policy=path, plan=plan, session="s", db=tmp_path / "t.sqlite", rate_limit=False)
    with pytest.raises(
        SessionSetupError, match=r"p\.onnx: .*needs outputs of shape \(1, 4, 6\) or \(1, 24\), got \(1, 6\)"
    ):
        run_session(opts, operator=AutoOperator(log=None))
    assert not (tmp_path / "t.sqlite").exists()
