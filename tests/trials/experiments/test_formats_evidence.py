"""The same attack through every format (trials.experiments.formats), end to end at a tiny budget.

A 32 px untrained checkpoint is exported by ``advobj policy export`` and attacked by ``advobj attack
run`` through the checkpoint, the .onnx and the .pt2 (2 iterations, 8 px texture), each texture
evaluated on 4 paired held-out configurations of a 3-step scene; ``evidence`` runs it as a user
would, from a clean checkout, and collects it. The checkout is a real git repository made here
(git reads it through GIT_DIR / GIT_WORK_TREE): clean for the run, with a changed file for the
refusal. The summary's figures are recomputed from the committed CSV, textures and timings with
code of the tests (csv, numpy, math: the tradeoff evidence test's Wilson, McNemar and CSV reader),
not the module's, and tampering with one episode is caught.
"""

from __future__ import annotations

import csv
import json
import shlex
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import yaml

from sim.configs import in_part, load_pool, sample_pool, save_pool
from sim.spec import default_scene, load_spec
from tests.trials.experiments.test_tradeoff_evidence import TINY_ATTACK, mcnemar_p, read_attacked, wilson
from trials.experiments import formats

EPISODES = 4
COMMITTED = (
    "episodes.csv",
    "summary.json",
    "run.json",
    "timing.json",
    "eval_set.json",
    "export.json",
    *(f"textures/{f}/{n}" for f in formats.FORMATS for n in ("texture.npy", "texture.png", "run.json")),
    *(f"attack_configs/{f}.json" for f in formats.FORMATS),
)


def _git(repo: Path, *args: str) -> str:
    cmd = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t", *args]
    return subprocess.run(cmd, check=True, capture_output=True, text=True, env={"PATH": "/usr/bin:/bin"}).stdout


def _checkout(tmp: Path, dirty: bool) -> Path:
    """A real git repository with one commit (and, when ``dirty``, a change to its tracked file)."""
    repo = tmp / ("dirty" if dirty else "clean")
    repo.mkdir()
    _git(repo, "init", "-q")
    (repo / "a.txt").write_text("a\n")
    _git(repo, "add", "a.txt")
    _git(repo, "commit", "-q", "-m", "one")
    if dirty:
        (repo / "a.txt").write_text("b\n")
    return repo


def _use_checkout(monkeypatch, repo: Path) -> None:
    monkeypatch.setenv("GIT_DIR", str(repo / ".git"))
    monkeypatch.setenv("GIT_WORK_TREE", str(repo))


@pytest.fixture(scope="module")
def inputs(tmp_path_factory, tiny_policy_dir):
    """A 3-step scene, a pool of it (34 attack-part and 6 evaluation-part configurations) and the
    attack's overrides."""
    d = tmp_path_factory.mktemp("formats-inputs")
    doc = default_scene().model_dump(mode="json")
    doc["episode"]["max_steps"] = 3
    (d / "scene.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    spec = load_spec(d / "scene.yaml")
    pool = sample_pool(spec, 34, seed=0, part="attack") + sample_pool(spec, 6, seed=0, part="evaluation")
    save_pool(d / "pool.json", spec, pool)
    (d / "attack.yaml").write_text(yaml.safe_dump(TINY_ATTACK))
    return {"policy": tiny_policy_dir, "pool": d / "pool.json", "scene": d / "scene.yaml", "config": d / "attack.yaml"}


def _argv(inputs: dict, out: Path, episodes: int = EPISODES) -> list[str]:
    argv = ["--out", str(out), "--episodes", str(episodes), "--num-envs", "4"]
    for k in ("policy", "pool", "scene", "config"):
        argv += [f"--{k}", str(inputs[k])]
    return argv


@pytest.fixture(scope="module")
def evidence_run(tmp_path_factory, inputs):
    """``evidence`` from a clean checkout at a tiny budget: (run folder, results folder, git HEAD)."""
    d = tmp_path_factory.mktemp("formats-evidence")
    repo = _checkout(d, dirty=False)
    with pytest.MonkeyPatch.context() as mp:
        _use_checkout(mp, repo)
        rc = formats.evidence(_argv(inputs, d / "run"), d / "results", min_episodes=EPISODES)
    assert rc == 0
    return d / "run", d / "results", _git(repo, "rev-parse", "HEAD").strip()


# ----------------------------------------------------------------------------- independent arithmetic
def check_summary(results: Path) -> None:
    """Every figure of summary.json recomputed from episodes.csv (format -> seed -> targeted: the
    ``eval`` column names the format), the textures and timing.json."""
    summary = json.loads((results / "summary.json").read_text())
    attacked, timing = read_attacked(results), json.loads((results / "timing.json").read_text())
    textures = {f: np.load(results / "textures" / f / "texture.npy", allow_pickle=False) for f in formats.FORMATS}
    assert set(attacked) == set(summary["formats"]) == set(formats.FORMATS)
    ref = attacked["checkpoint"]
    for fmt, row in summary["formats"].items():
        got = attacked[fmt]
        k, n = sum(got.values()), len(got)
        assert (row["tasr"]["k"], row["tasr"]["n"]) == (k, n), fmt
        assert (row["tasr"]["lo"], row["tasr"]["hi"]) == pytest.approx(wilson(k, n), abs=1e-12), fmt
        for name, field in (("wall", "wall_s"), ("cpu", "cpu_s"), ("per_iteration", "seconds_per_iteration")):
            assert row["ratio_to_checkpoint"][name] == pytest.approx(
                timing[fmt][field] / timing["checkpoint"][field]
            ), (fmt, name)
        assert row["attack"] == timing[fmt]
        if fmt == "checkpoint":
            continue
        assert set(got) == set(ref), f"{fmt}: not paired with the checkpoint"
        b = sum(ref[s] and not got[s] for s in ref)
        c = sum(got[s] and not ref[s] for s in ref)
        t = row["mcnemar_vs_checkpoint"]
        assert (t["b"], t["c"], t["n_pairs"]) == (b, c, len(ref)), fmt
        assert t["p_value"] == pytest.approx(mcnemar_p(b, c)), fmt
        assert row["tasr_difference_pp"] == pytest.approx(100.0 * (c - b) / len(ref)), fmt
        diff = np.abs(textures[fmt].astype(np.float64) - textures["checkpoint"].astype(np.float64))
        u8 = {f: np.clip(np.rint(t.astype(np.float64) * 255), 0, 255).astype(int) for f, t in textures.items()}
        tex = row["texture_vs_checkpoint"]
        assert tex["max_abs"] == pytest.approx(float(diff.max()), abs=1e-12), fmt
        assert tex["max_levels_8bit"] == int(np.abs(u8[fmt] - u8["checkpoint"]).max()), fmt
        agrees = float(diff.max()) <= summary["texture_atol"]
        assert tex["agrees"] == agrees, fmt
        holds = "texture agrees" if agrees else ("T-ASR not different" if mcnemar_p(b, c) >= 0.05 else None)
        assert row["criterion"] == (holds or "T-ASR different"), fmt


# ----------------------------------------------------------------------------- refusals
def test_evidence_refuses_a_checkout_with_uncommitted_changes_before_running_anything(
    tmp_path, inputs, monkeypatch, capsys
):
    _use_checkout(monkeypatch, _checkout(tmp_path, dirty=True))
    argv = _argv(inputs, tmp_path / "run")
    assert formats.evidence(argv, tmp_path / "results", min_episodes=EPISODES) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "uncommitted changes" in err and "+dirty" in err
    assert not (tmp_path / "results").exists() and not (tmp_path / "run").exists()


def test_evidence_refuses_fewer_than_300_episodes(tmp_path, inputs, monkeypatch, capsys):
    _use_checkout(monkeypatch, _checkout(tmp_path, dirty=False))
    assert formats.evidence(_argv(inputs, tmp_path / "run", episodes=100), tmp_path / "results") == 2
    assert "--episodes 100 < 300" in capsys.readouterr().err
    assert not (tmp_path / "results").exists() and not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    "flag, value, words",
    [
        ("--policy", "nope", "--policy: "),
        ("--pool", "nope.json", "--pool: "),
        ("--config", "nope.yaml", "--config: "),
        ("--scene", "nope.yaml", "--scene: "),
    ],
)
def test_a_bad_input_is_one_line_naming_its_flag_and_nothing_is_written(tmp_path, inputs, capsys, flag, value, words):
    argv = _argv(inputs, tmp_path / "run")
    argv[argv.index(flag) + 1] = str(tmp_path / value)
    assert formats.main(["run", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and words in err and value in err, err
    assert not (tmp_path / "run").exists()


def test_a_pool_of_another_scene_and_an_unknown_preset_are_one_line(tmp_path, inputs, capsys):
    save_pool(tmp_path / "other.json", default_scene(), sample_pool(default_scene(), 4, seed=0))  # 60 steps, not 3
    for extra, words in (
        (["--pool", str(tmp_path / "other.json")], "--pool: "),
        (["--preset", "nope"], "--preset: unknown preset 'nope'"),
    ):
        argv = _argv(inputs, tmp_path / "run")
        if extra[0] in argv:
            argv[argv.index(extra[0]) + 1] = extra[1]
        else:
            argv += extra
        assert formats.main(["run", *argv]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and words in err, err
    assert not (tmp_path / "run").exists()


def test_an_attack_config_that_is_not_an_attack_config_is_one_line(tmp_path, inputs, capsys):
    (tmp_path / "bad.yaml").write_text("iterations: 0\n")
    argv = _argv({**inputs, "config": tmp_path / "bad.yaml"}, tmp_path / "run")
    assert formats.main(["run", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--config: " in err and "iterations" in err, err
    assert not (tmp_path / "run").exists()


def test_the_documented_commands_parse():
    lines = [ln.strip() for ln in formats.__doc__.split("::", 1)[1].splitlines() if ln.strip()]
    joined = " ".join(ln.rstrip("\\").strip() for ln in lines[:2])
    commands = [joined, lines[2]]
    for text in commands:
        argv = shlex.split(text, comments=True)
        assert argv[:3] == ["python", "-m", "trials.experiments.formats"], text
        formats.parser().parse_args(argv[3:])  # SystemExit on an unknown option
    assert shlex.split(commands[0])[3] == "evidence" and "--episodes" in commands[0]


# ----------------------------------------------------------------------------- end to end
def test_the_evidence_is_collected_with_its_record_and_no_machine_path(evidence_run):
    run, results, head = evidence_run
    for name in COMMITTED:
        assert (results / name).is_file(), name
    record = json.loads((results / "run.json").read_text())
    (attempt,) = record["attempts"]
    assert attempt["command"].startswith("python -m trials.experiments.formats run --policy ")
    assert attempt["commit"] == head and attempt["exit_code"] == 0 and attempt["machine"]["cpus"] >= 1
    assert attempt["wall_s"] > 0 and attempt["cpu_s"] > 0
    assert record["episodes_rows"] == 3 * 2 * EPISODES  # 3 formats x (clean, attack) x episodes
    assert record["jobs_cpu_s"] > 0 and record["attack_commits"] == [head]
    for name in COMMITTED:
        if not name.endswith((".npy", ".png")):
            text = (results / name).read_text()
            assert str(run.parent) not in text and "/tmp/" not in text, name  # no machine path is committed


def test_the_three_attacks_ran_from_the_command_line_with_the_same_config_and_configurations(evidence_run):
    run, results, _ = evidence_run
    summary = json.loads((results / "summary.json").read_text())
    assert summary["same_attack_config"] and summary["same_attack_configurations"]
    for fmt in formats.FORMATS:
        t = summary["formats"][fmt]["attack"]
        assert t["command"].startswith("advobj attack run --policy ") and t["iterations"] == TINY_ATTACK["iterations"]
        assert t["wall_s"] > 0 and t["cpu_s"] > 0 and t["loop_s"] > 0
        cfg = json.loads((results / "textures" / fmt / "run.json").read_text())["config"]["attack"]
        assert {k: cfg[k] for k in TINY_ATTACK} == TINY_ATTACK and cfg["seed"] == 0
    files = {"onnx": "policy.onnx", "pt2": "policy.pt2"}
    for fmt, name in files.items():
        assert f"/export/{name} --preset quick " in summary["formats"][fmt]["attack"]["command"], fmt
    export = json.loads((results / "export.json").read_text())
    assert export["command"].startswith("advobj policy export ") and len(export["stdout"]) == 2


def test_every_texture_is_evaluated_on_the_same_held_out_configurations(evidence_run, inputs):
    _, results, _ = evidence_run
    attacked = read_attacked(results)
    fixed = [c.seed for c in load_pool(results / "eval_set.json")]
    expected = [c.seed for c in in_part(load_pool(inputs["pool"]), "evaluation")][:EPISODES]
    assert fixed == expected
    assert all(sorted(attacked[f]) == sorted(fixed) for f in formats.FORMATS)
    summary = json.loads((results / "summary.json").read_text())
    for f in formats.FORMATS:
        assert summary["evaluations"][f]["overlap"]["attack"] == 0  # held out from what the attack saw


def test_the_summary_is_recomputed_from_the_committed_files(evidence_run):
    _, results, _ = evidence_run
    check_summary(results)
    summary = json.loads((results / "summary.json").read_text())
    # the same attack, seeds and configurations: through both files the texture is the checkpoint's
    for fmt in ("onnx", "pt2"):
        assert summary["formats"][fmt]["texture_vs_checkpoint"]["max_levels_8bit"] == 0, fmt


def test_a_changed_episode_no_longer_matches_the_summary(evidence_run, tmp_path):
    _, results, _ = evidence_run
    bad = tmp_path / "tampered"
    shutil.copytree(results, bad)
    with open(bad / "episodes.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    i = next(j for j, r in enumerate(rows) if r["eval"] == "onnx" and r["condition"] == "attack")
    rows[i]["targeted"] = "0" if rows[i]["targeted"] == "1" else "1"
    with open(bad / "episodes.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    with pytest.raises(AssertionError):
        check_summary(bad)


def test_a_run_folder_of_other_settings_is_refused_and_collect_again_is_the_same(
    evidence_run, inputs, tmp_path, capsys
):
    run, results, _ = evidence_run
    argv = _argv(inputs, run, episodes=EPISODES + 1)
    assert formats.main(["run", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert "holds a run with other settings" in err and len(err.splitlines()) == 1
    again = formats.collect(run, tmp_path / "again")
    for name in ("episodes.csv", "timing.json", "eval_set.json"):
        assert (again / name).read_bytes() == (results / name).read_bytes(), name
    a, b = (json.loads((d / "summary.json").read_text()) for d in (results, again))
    assert a == b


def test_the_child_commands_name_the_module_not_main_so_python_m_runs_them(evidence_run):
    # Run as ``python -m trials.experiments.formats``, the module's __name__ is "__main__": a child
    # command or a job function spelled from it would not import.
    import subprocess
    import sys

    assert formats.MODULE == formats.__name__
    run, results, _ = evidence_run
    record = json.loads((results / "run.json").read_text())
    assert all(a["command"].startswith(f"python -m {formats.MODULE} run ") for a in record["attempts"])
    assert not [p for p in run.rglob("*.json") if "__main__" in p.read_text(errors="replace")]
    got = subprocess.run([sys.executable, "-m", formats.MODULE, "run", "--help"], capture_output=True, text=True)
    assert got.returncode == 0 and "--policy" in got.stdout, got.stderr
