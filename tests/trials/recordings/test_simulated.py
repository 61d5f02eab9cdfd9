"""``advobj record sim`` (trials.recordings.simulated): closed-loop clean episodes of a policy written
as a recording, with the adversarial object hidden, from attack-part configurations only."""

from __future__ import annotations

import hashlib
import json
import sys

import numpy as np
import pytest

from sim.action import next_tcp_pose
from sim.configs import config_part, sample_config, sample_pool
from sim.policies.checkpoint import load_policy
from sim.recording import read_recording
from sim.spec import WRIST, default_scene
from sim.world import SimWorld
from trials.cli.main import main
from trials.recordings.simulated import (
    SHIFTED_LIGHTING,
    SHIFTED_TABLE_RGB,
    STEP_S,
    RecordSimError,
    SimRecordJob,
    attack_configs,
    check_attack_part,
    check_held_out,
    first_episodes,
    record_episodes,
    recorded_seeds,
    run_record_sim,
    shifted_cell,
)

STEPS = 4


@pytest.fixture(scope="module")
def spec():
    s = default_scene()
    return s.with_updates(episode={**s.episode.model_dump(), "max_steps": STEPS})


@pytest.fixture(scope="module")
def recorded(tiny_policy_dir, tmp_path_factory):
    d = tmp_path_factory.mktemp("rec") / "rec"
    job = SimRecordJob(policy=tiny_policy_dir, out=d, episodes=5, max_steps=STEPS, num_envs=2, seed=3)
    return run_record_sim(job)


def _render(spec, config, T_world_tcp, size, hidden=True) -> np.ndarray:
    with SimWorld(spec, image_size=size, seed=0) as world:
        world.camera_renderer(WRIST).set_object_visible(spec.object_index("adversarial"), not hidden)
        world.reset(config=config)
        world.set_tcp_pose(T_world_tcp)
        return world.render(with_ids=False).rgb


def test_each_episode_is_the_policys_closed_loop_from_an_attack_part_configuration(recorded, spec, tiny_policy_dir):
    rec = recorded
    policy = load_policy(tiny_policy_dir)
    seeds = recorded_seeds(rec)
    assert seeds == tuple(c.seed for c in attack_configs(spec, 5, 3)) and all(s >= 3 for s in seeds)
    assert all(config_part(s) == "attack" for s in seeds)
    assert [e.id for e in rec.episodes] == [f"config_{s:07d}" for s in seeds]
    assert np.array_equal(rec.T_table_base, np.eye(4)) and rec.sync_tolerance_s == 0.0 and rec.gripper is None
    ep = spec.episode
    for e, seed in zip(rec.episodes, seeds):
        steps = list(rec.frames(e.id))
        assert 1 <= len(steps) <= STEPS
        assert [s.t_s for s in steps] == [k * STEP_S for k in range(len(steps))]
        assert np.allclose(steps[0].T_base_tcp, sample_config(spec, seed).T_world_tcp_array)
        # closed loop: each next pose is where the policy's action on the recorded frame moved the TCP
        for a, b in zip(steps, steps[1:]):
            action = np.clip(policy.act(a.images[WRIST][None]), -1.0, 1.0)
            want = next_tcp_pose(a.T_base_tcp[None], action, ep.max_step_m, ep.max_step_rad)[0]
            want[2, 3] = max(want[2, 3], ep.min_tcp_height_m)
            assert np.allclose(b.T_base_tcp, want, atol=1e-5)


def test_the_frames_are_the_cells_renders_without_the_adversarial_object(recorded, spec):
    rec = recorded
    cam = rec.camera(WRIST)
    assert cam.mount == "tcp" and np.allclose(cam.T_tcp_cam, spec.camera.T_tcp_cam) and cam.dist.size == 0
    assert (cam.width, cam.height) == (32, 32)
    shown = 0
    for e, seed in zip(rec.episodes, recorded_seeds(rec)):
        config = sample_config(spec, seed)
        last = e.n_frames - 1
        step = list(rec.frames(e.id))[last]
        hidden = _render(spec, config, step.T_base_tcp, 32)
        assert np.array_equal(step.images[WRIST], hidden)
        shown += not np.array_equal(hidden, _render(spec, config, step.T_base_tcp, 32, hidden=False))
    assert shown >= 1  # the object would have been in view: hiding it changed what was recorded


def test_a_configuration_outside_the_attack_part_is_refused_before_any_rollout(spec, tiny_policy_dir):
    policy = load_policy(tiny_policy_dir)
    for part in ("evaluation", "validation"):
        configs = attack_configs(spec, 2, 0) + sample_pool(spec, 1, seed=0, part=part)
        with pytest.raises(RecordSimError, match=f"belongs to the {part} part of the split") as err:
            record_episodes(policy, spec, configs)
        assert "\n" not in str(err.value)
    check_attack_part(attack_configs(spec, 3, 0))  # the attack part alone passes


def test_the_held_out_check_fails_when_an_evaluation_shares_a_configuration(recorded):
    seeds = recorded_seeds(recorded)
    held_out = [c.seed for c in sample_pool(default_scene(), 6, seed=0, part="evaluation")]
    assert check_held_out(recorded, held_out) == 6
    with pytest.raises(RecordSimError, match=f"seed {seeds[1]} first.*held-out configurations only"):
        check_held_out(recorded, held_out + [seeds[1]])


def test_the_first_episodes_are_copied_frame_for_frame(recorded, tmp_path):
    part = first_episodes(recorded.path, tmp_path / "first2", 2)
    assert [e.id for e in part.episodes] == [e.id for e in recorded.episodes[:2]]
    assert recorded_seeds(part) == recorded_seeds(recorded)[:2]
    for e in part.episodes:
        for a, b in zip(part.frames(e.id), recorded.frames(e.id)):
            assert a.t_s == b.t_s and np.allclose(a.T_base_tcp, b.T_base_tcp, rtol=0, atol=1e-12)  # rotvec round trip
            assert np.array_equal(a.images[WRIST], b.images[WRIST])
    with pytest.raises(RecordSimError, match="holds 5 episodes, not the first 6"):
        first_episodes(recorded.path, tmp_path / "too-many", 6)
    assert not (tmp_path / "too-many").exists()


def test_the_shifted_cell_changes_the_light_and_the_table_and_nothing_else(spec, tiny_policy_dir, tmp_path):
    moved = shifted_cell(spec)
    assert moved.lighting == SHIFTED_LIGHTING and moved.table.texture == SHIFTED_TABLE_RGB
    same = lambda s: s.model_dump(exclude={"lighting", "table"})  # noqa: E731
    assert same(moved) == same(spec) and moved.table.size_m == spec.table.size_m
    job = dict(policy=tiny_policy_dir, episodes=1, max_steps=1, num_envs=1)
    a = run_record_sim(SimRecordJob(out=tmp_path / "a", **job))
    b = run_record_sim(SimRecordJob(out=tmp_path / "b", cell="shifted", **job))
    (e,) = a.episodes
    assert b.source["cell"] == "shifted" and a.source["cell"] == "nominal"
    fa, fb = next(a.frames(e.id)), next(b.frames(e.id))
    assert np.array_equal(fa.T_base_tcp, fb.T_base_tcp)  # the same start, another look
    assert np.abs(fa.images[WRIST].astype(int) - fb.images[WRIST].astype(int)).mean() > 10


def _run(monkeypatch, capsys, argv):
    monkeypatch.setattr(sys, "argv", ["advobj", *argv])
    with pytest.raises(SystemExit) as exit_:
        main()
    out = capsys.readouterr()
    return exit_.value.code, out.out, [line for line in out.err.splitlines() if line.strip()]


def test_record_sim_from_the_command_line(monkeypatch, capsys, tiny_policy_dir, tmp_path):
    argv = ["record", "sim", "--policy", str(tiny_policy_dir), "--episodes", "2", "--max-steps", "2"]
    code, out, err = _run(monkeypatch, capsys, [*argv, "--out", str(tmp_path / "rec"), "--seed", "5"])
    assert code == 0, err
    rec = read_recording(tmp_path / "rec")
    assert "recording: 2 episodes" in out and f"in {rec.path}" in out
    assert rec.source["from"] == "sim" and all(s >= 5 for s in recorded_seeds(rec))


def _tree(root):
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in root.rglob("*") if p.is_file()
    }


@pytest.mark.parametrize(
    "bad, expect",
    [
        (["--episodes", "0"], "--episodes: Input should be greater than or equal to 1"),
        (["--cell", "mars"], "--cell: Input should be 'nominal' or 'shifted'"),
        (["--num-envs", "0"], "--num-envs: Input should be greater than or equal to 1"),
        (["--out", "{tmp}/full"], "not empty; a recording is written into a new or empty folder"),
        (["--scene", "{tmp}/none.yaml"], "none.yaml"),
    ],
)
def test_a_bad_input_is_one_line_exit_2_and_writes_nothing(monkeypatch, capsys, tiny_policy_dir, tmp_path, bad, expect):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "mine.txt").write_text("keep")
    argv = ["record", "sim", "--policy", str(tiny_policy_dir), "--episodes", "1", "--out", str(tmp_path / "rec")]
    argv += [a.replace("{tmp}", str(tmp_path)) for a in bad]
    before = _tree(tmp_path)
    monkeypatch.chdir(tmp_path)
    code, _, err = _run(monkeypatch, capsys, argv)
    assert code == 2 and len(err) == 1 and "Traceback" not in err[0], err
    assert expect in err[0], err[0]
    assert _tree(tmp_path) == before and not (tmp_path / "rec").exists()


def test_the_job_refuses_a_bad_field_naming_its_flag():
    with pytest.raises(RecordSimError, match=r"^--max-steps: "):
        SimRecordJob(policy="p", out="o", episodes=1, max_steps=0)
    with pytest.raises(RecordSimError, match=r"^--seed: "):
        SimRecordJob(policy="p", out="o", episodes=1, seed=-1)


def test_record_sim_draws_fresh_configurations_for_another_seed(spec):
    a, b = attack_configs(spec, 4, 0), attack_configs(spec, 4, 1000)
    assert not {c.seed for c in a} & {c.seed for c in b}
    assert json.dumps([c.to_dict() for c in a]) == json.dumps([c.to_dict() for c in attack_configs(spec, 4, 0)])
