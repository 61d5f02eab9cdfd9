"""The speed-vs-accuracy evidence: docs/speed-vs-accuracy.md's tables against results/tradeoff/.

The figures the doc quotes (T-ASR with its Wilson interval, the paired comparison with the baseline
of the same attack seed and its exact McNemar p, the means over attack seeds) are recomputed here
from the committed per-episode CSV with code of this file only (csv, json, math.comb), not with
the code that produced them. The same checks run on a tiny two-seed sweep collected into a
temporary folder, where tampering with one episode is shown to be caught; on the committed
results they run once ``results/tradeoff/`` exists (skipped before).
"""

from __future__ import annotations

import csv
import importlib.util
import json
import math
import re
import shlex
import shutil
from pathlib import Path
from statistics import NormalDist

import pytest

from sim.configs import load_pool, pose_id
from tests.trials.conftest import MAX_STEPS
from trials.experiments import tradeoff, tradeoff_report

ROOT = Path(__file__).resolve().parents[3]
RESULTS = ROOT / "results" / "tradeoff"
DOC = ROOT / "docs" / "speed-vs-accuracy.md"
RUNS = "Every run, paired with the baseline of its attack seed"
SETTINGS = "Per setting, over attack seeds"
#: The knobs whose rows change the attack (issue 28: at least 3 attack seeds each).
ATTACK_KNOBS = ("baseline", "iterations", "eot_envs", "rollout_steps", "sampler", "texture_size", "saliency", "pcgrad")
Z = NormalDist().inv_cdf(0.975)


# ----------------------------------------------------------------------------- independent arithmetic
def wilson(k: int, n: int) -> tuple[float, float]:
    if n == 0:
        return 0.0, 1.0
    p = k / n
    denom = 1 + Z * Z / n
    centre = (p + Z * Z / (2 * n)) / denom
    half = Z * math.sqrt(p * (1 - p) / n + Z * Z / (4 * n * n)) / denom
    return (0.0 if k == 0 else max(0.0, centre - half)), (1.0 if k == n else min(1.0, centre + half))


def mcnemar_p(b: int, c: int) -> float:
    """Two-sided exact McNemar: twice the binomial(b + c, 1/2) tail at min(b, c), at most 1."""
    n = b + c
    if n == 0:
        return 1.0
    return min(1.0, 2 * sum(math.comb(n, i) for i in range(min(b, c) + 1)) / 2**n)


def read_records(results: Path) -> dict[str, dict]:
    """rows.jsonl: the newest record per key (a torn line ignored)."""
    latest = {}
    for line in (results / "rows.jsonl").read_text().splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        latest[rec["key"]] = rec
    return latest


def read_attacked(results: Path) -> dict[str, dict[int, bool]]:
    """episodes.csv: evaluation -> configuration seed -> targeted, attacked episodes only."""
    out: dict[str, dict[int, bool]] = {}
    with open(results / "episodes.csv", newline="") as f:
        for row in csv.DictReader(f):
            if row["condition"] == "attack":
                out.setdefault(row["eval"], {})[int(row["seed"])] = row["targeted"] == "1"
    return out


def tables(block: str) -> dict[str, list[dict]]:
    """``### heading`` -> the rows (header -> cell) of the table under it."""
    out: dict[str, list[dict]] = {}
    heading, header = None, None
    for line in block.splitlines():
        if line.startswith("### "):
            heading, header = line[4:].strip(), None
        elif heading and line.startswith("|"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if header is None:
                header, out[heading] = cells, []
            elif not set(line.strip()) <= set("|-"):
                out[heading].append(dict(zip(header, cells)))
    return out


def generated_block(text: str) -> str:
    start, end = tradeoff_report.START, tradeoff_report.END
    assert text.count(start) == 1 and text.count(end) == 1, "the doc must hold the generated block's markers once"
    return text.split(start, 1)[1].split(end, 1)[0]


def _seed(rec: dict) -> int:
    return rec.get("attack_seed") or 0


def check_figures(results: Path, block: str) -> int:
    """Every quoted figure of the runs and per-setting tables, recomputed from episodes.csv; returns
    how many runs were checked."""
    recs, attacked, tabs = read_records(results), read_attacked(results), tables(block)
    runs = {r["row"]: r for r in tabs[RUNS]}
    reported = {
        k: r for k, r in recs.items() if r.get("status") == "ok" and r["kind"] in ("attack", "snapshot", "episodes")
    }
    assert set(runs) == set(reported), "the runs table lists other rows than rows.jsonl reports"
    rates, paired = {}, {}
    for key, rec in reported.items():
        got, row = attacked[rec["eval_name"]], runs[key]
        k, n = sum(got.values()), len(got)
        lo, hi = wilson(k, n)
        rate = k / n
        assert (rec["tasr"]["k"], rec["tasr"]["n"]) == (k, n), f"{key}: rows.jsonl disagrees with its episodes"
        assert row["episodes"] == str(n) and row["T-ASR k/n"] == f"{k}/{n}", key
        assert row["T-ASR % [95% CI]"] == f"{100 * rate:.1f} [{100 * lo:.1f}, {100 * hi:.1f}]", key
        rates[key] = 100 * rate
        if rec["knob"] == "baseline" or rec["policy"] != "ref":
            assert row["pairs"] in ("baseline", "not paired"), key
            continue
        (base,) = [b for b in reported.values() if b["knob"] == "baseline" and _seed(b) == _seed(rec)]
        ref = attacked[base["eval_name"]]
        common = sorted(set(ref) & set(got))
        b = sum(ref[s] and not got[s] for s in common)
        c = sum(got[s] and not ref[s] for s in common)
        d, p = 100.0 * (c - b) / len(common), mcnemar_p(b, c)
        cells = (row["pairs"], row["baseline only"], row["row only"], row["diff pp"], row["McNemar p"])
        assert cells == (str(len(common)), str(b), str(c), f"{d:+.1f}", f"{p:.3g}"), key
        paired[key] = (d, p, b, c)
    settings = {r["setting"]: r for r in tabs[SETTINGS]}
    groups: dict[str, list[str]] = {}
    for key in reported:
        groups.setdefault(key.split("@")[0], []).append(key)
    assert set(settings) == set(groups)
    for name, keys in groups.items():
        row, rs = settings[name], [rates[k] for k in keys]
        assert set(row["attack seeds"].split(", ")) == {str(reported[k].get("attack_seed")) for k in keys}, name
        assert row["mean T-ASR %"] == f"{sum(rs) / len(rs):.1f}", name
        assert (row["min T-ASR %"], row["max T-ASR %"]) == (f"{min(rs):.1f}", f"{max(rs):.1f}"), name
        ps = [paired[k] for k in keys if k in paired]
        if ps:
            up = sum(p < 0.05 and c > b for _, p, b, c in ps)
            down = sum(p < 0.05 and c < b for _, p, b, c in ps)
            assert row["mean diff vs baseline pp"] == f"{sum(d for d, *_ in ps) / len(ps):+.1f}", name
            assert row["McNemar p < 0.05: row higher / lower / runs"] == f"{up} / {down} / {len(ps)}", name
    return len(reported)


def _configs(path: Path) -> list[dict]:
    return json.loads(path.read_text())["configs"]


def check_requirements(results: Path, min_n: int = 300, min_seeds: int = 3, provenance: bool = True) -> None:
    """What issue 28 asks of the committed sweep: every row of a policy evaluated on that policy's
    one fixed set (the same configurations, so paired), n >= min_n, >= min_seeds attack seeds for
    every setting that changes the attack (the same seeds as the baseline's), no evaluation
    configuration among an attack's, wall beside CPU time, and the evidence record."""
    recs, attacked = read_records(results), read_attacked(results)
    ok = {k: r for k, r in recs.items() if r.get("status") == "ok"}
    fixed = {f.stem: [c["seed"] for c in _configs(f)] for f in (results / "eval_sets").glob("*.json")}
    n = min(r["episodes"] for r in ok.values() if r["knob"] == "baseline")
    assert n >= min_n, f"baseline rows evaluated on {n} < {min_n} episodes"
    for key, r in ok.items():
        if r["kind"] == "deployment":
            continue
        m = int(r["value"]) if r["kind"] == "episodes" else n
        assert set(attacked[r["eval_name"]]) == set(fixed[r["policy"]][:m]), f"{key}: not on the fixed set"
        for f in ("attack_wall_s", "attack_cpu_s", "eval_wall_s", "eval_cpu_s", "row_wall_s", "row_cpu_s"):
            assert isinstance(r.get(f), (int, float)), f"{key}: no {f}"
    seeds: dict[str, set] = {}
    for r in ok.values():
        if r["knob"] in ATTACK_KNOBS and r["policy"] == "ref":
            seeds.setdefault(r["name"], set()).add(_seed(r))
    (base,) = [s for name, s in seeds.items() if name.startswith("baseline=")]
    assert len(base) >= min_seeds, f"the baseline ran under {len(base)} attack seeds"
    assert all(s == base for s in seeds.values()), {k: sorted(v) for k, v in seeds.items() if v != base}
    evaluated = {c.seed for f in (results / "eval_sets").glob("*.json") for c in load_pool(f)}
    poses = {pose_id(c) for f in (results / "eval_sets").glob("*.json") for c in load_pool(f)}
    records = sorted((results / "attack_configs").glob("*.json"))
    assert records, "no attack configuration records"
    for f in records:
        doc = json.loads(f.read_text())
        entries = [e for part in ("attack", "validation") for e in doc.get(part, [])]
        assert not {e["seed"] for e in entries} & evaluated, f"{f.name}: attacked on an evaluation configuration"
        assert not {e["pose"] for e in entries} & poses, f"{f.name}: attacked on an evaluation pose"
    if provenance:
        run = json.loads((results / "run.json").read_text())
        assert run["attempts"] and run["attempts"][-1]["exit_code"] == 0
        for a in run["attempts"]:
            assert a["command"].startswith("python -m trials.experiments.tradeoff sweep ")
            assert a["commit"] and not a["commit"].endswith("+dirty") and a["machine"]["cpus"]
            assert a["wall_s"] > 0 and a["cpu_s"] > 0
        assert all(not str(r["git_commit"]).endswith("+dirty") for r in ok.values())


# ----------------------------------------------------------------------------- the doc and the committed results
def test_the_doc_block_is_generated_from_the_committed_results():
    assert DOC.read_text() == tradeoff_report.expected_doc(), (
        "docs/speed-vs-accuracy.md is stale; regenerate with: python -m trials.experiments.tradeoff_report"
    )


def test_without_committed_results_the_doc_quotes_no_sweep_figure():
    if (RESULTS / "rows.jsonl").is_file():
        pytest.skip("results/tradeoff/ is committed: its figures are checked below")
    block = generated_block(DOC.read_text())
    assert "Not run and committed yet" in block and not re.search(r"\d+(\.\d+)? ?%", block)


@pytest.mark.skipif(not (RESULTS / "rows.jsonl").is_file(), reason="results/tradeoff/ not committed yet")
def test_the_committed_figures_recomputed_from_the_episodes():
    assert check_figures(RESULTS, generated_block(DOC.read_text())) > 0


@pytest.mark.skipif(not (RESULTS / "rows.jsonl").is_file(), reason="results/tradeoff/ not committed yet")
def test_the_committed_sweep_is_what_issue_28_asks_for():
    check_requirements(RESULTS)


def _module_commands(path: Path, module: str) -> list[list[str]]:
    """``python -m <module> ...`` lines of the shell blocks of ``path`` (continuations joined)."""
    out, fenced, pending = [], False, ""
    for raw in path.read_text().splitlines():
        if raw.strip().startswith("```"):
            fenced, pending = not fenced, ""
            continue
        if not fenced:
            continue
        line = (pending + " " + raw.strip()).strip()
        if line.endswith("\\"):
            pending = line[:-1]
            continue
        pending = ""
        argv = shlex.split(line, comments=True)
        if argv[:3] == ["python", "-m", module]:
            out.append(argv[3:])
    return out


def test_the_documented_sweep_commands_parse():
    docs = [DOC, ROOT / "docs" / "real-trials.md"]
    sweep = [a for d in docs for a in _module_commands(d, "trials.experiments.tradeoff")]
    assert any(a[:1] == ["evidence"] for a in sweep) and any(a[:1] == ["collect"] for a in sweep)
    for argv in sweep:
        tradeoff.parser().parse_args(argv)  # SystemExit on an unknown option or a bad value
    report = [a for d in docs for a in _module_commands(d, "trials.experiments.tradeoff_report")]
    assert report and all(set(a) <= {"--check"} for a in report)


def test_evidence_refuses_what_is_not_evidence_before_running_anything(tmp_path, capsys):
    argv = ["--policy", "p", "--out", str(tmp_path / "o"), "--quick-check", "--episodes", "100"]
    assert tradeoff.evidence(argv, tmp_path / "r") == 2
    err = capsys.readouterr().err
    assert "--quick-check" in err and "--episodes 100 < 300" in err and "--attack-seeds" in err
    assert not (tmp_path / "r").exists() and not (tmp_path / "o").exists()


# ----------------------------------------------------------------------------- a tiny sweep, end to end
TINY_ATTACK = {
    "iterations": 2,
    "num_envs": 1,
    "rollout_steps": 1,
    "texture_size": 8,
    "checkpoint_every": 1000,
    "validation_every": 0,
}


def test_a_tiny_two_seed_sweep_is_collected_rendered_and_recomputed(tmp_path, tiny_policy_dir, mixed_pool_file):
    cfg = tradeoff.load_tradeoff_config(
        policy=str(tiny_policy_dir),
        pool=str(mixed_pool_file),
        attack_overrides=TINY_ATTACK,
        snapshots=(1,),
        episodes=4,
        big_episodes=2,
        attack_seeds=(0, 1),
        max_steps=MAX_STEPS,
        eval_num_envs=2,
        deploy_episodes=2,
        latency_reps=2,
    )
    out = tmp_path / "sweep"
    rows = ["baseline", "eot_envs", "eval_episodes"]
    res = {r["key"]: r for r in tradeoff.run_sweep(cfg, out, rows, progress=False, log=lambda m: None, isolate=False)}
    assert set(res) == {"baseline=quick", "baseline=quick@seed1", "eot_envs=2", "eot_envs=2@seed1", "eval_episodes=2"}
    assert all(r["status"] == "ok" for r in res.values()), {k: r.get("traceback") for k, r in res.items()}
    assert [res[k]["attack_config"]["seed"] for k in ("baseline=quick", "baseline=quick@seed1")] == [0, 1]
    assert res["eot_envs=2@seed1"]["attack_config"]["seed"] == 1 and res["eval_episodes=2"]["episodes"] == 2
    # the fixed set was built once, before the rows, and timed
    meta = json.loads((out / "eval_sets" / "ref.json").read_text())["meta"]
    assert meta["first"] == 4 and meta["build_cpu_s"] >= 0

    results = tradeoff.collect(out, tmp_path / "results")
    for name in ("rows.jsonl", "episodes.csv", "summary.json", "sweep.json", "machine.json", "report.md", "run.json"):
        assert (results / name).is_file(), name
    assert (results / "eval_sets" / "ref.json").is_file() and len(list((results / "attack_configs").iterdir())) == 4
    assert len(list((results / "textures").glob("*.png"))) == 4
    for name in ("rows.jsonl", "sweep.json", "summary.json", "eval_sets/ref.json"):
        text = (results / name).read_text()
        assert str(tmp_path) not in text and "traceback" not in text, name  # no machine path is committed
    run = json.loads((results / "run.json").read_text())
    assert run["episodes_rows"] == 2 * (4 * 4 + 2) and run["rows_ok"] == 5 and run["rows_cpu_s"] > 0

    block = tradeoff_report.doc_block(results)
    assert check_figures(results, block) == 5
    check_requirements(results, min_n=4, min_seeds=2, provenance=False)
    doc = tmp_path / "doc.md"
    doc.write_text(f"# x\n\n{tradeoff_report.START}\nold\n{tradeoff_report.END}\n\ntail\n")
    assert tradeoff_report.main(["--results", str(results), "--doc", str(doc), "--check"]) == 1
    assert tradeoff_report.main(["--results", str(results), "--doc", str(doc)]) == 0
    assert tradeoff_report.main(["--results", str(results), "--doc", str(doc), "--check"]) == 0
    assert doc.read_text().endswith("\n\ntail\n") and check_figures(results, generated_block(doc.read_text())) == 5

    # one attacked episode flipped in the CSV: the doc no longer matches the data, and the check says so
    bad = tmp_path / "tampered"
    shutil.copytree(results, bad)
    lines = (bad / "episodes.csv").read_text().splitlines()
    header = lines[0].split(",")
    i = next(j for j, line in enumerate(lines) if line.split(",")[header.index("condition")] == "attack")
    cells = lines[i].split(",")
    cells[header.index("targeted")] = "0" if cells[header.index("targeted")] == "1" else "1"
    lines[i] = ",".join(cells)
    (bad / "episodes.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(AssertionError):
        check_figures(bad, block)
    # and a run evaluated on other configurations is not paired with the others
    shutil.copytree(results, tmp_path / "unpaired")
    doc_set = json.loads((tmp_path / "unpaired" / "eval_sets" / "ref.json").read_text())
    doc_set["configs"] = doc_set["configs"][1:] + doc_set["configs"][:1]
    doc_set["configs"][0]["seed"] = 10**6
    (tmp_path / "unpaired" / "eval_sets" / "ref.json").write_text(json.dumps(doc_set))
    with pytest.raises(AssertionError, match="not on the fixed set"):
        check_requirements(tmp_path / "unpaired", min_n=4, min_seeds=2, provenance=False)


# ----------------------------------------------------------------------------- --workers
@pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="ray not installed")
def test_workers_runs_the_rows_on_a_local_ray_of_that_many_cpus_and_refuses_less_than_one(capsys):
    from trials.jobs.dag import RayExecutor

    base = ["sweep", "--policy", "p", "--out", "o"]
    assert tradeoff.sweep_executor(tradeoff.parser().parse_args(base)) is None  # default: one row at a time
    ex = tradeoff.sweep_executor(tradeoff.parser().parse_args(base + ["--workers", "1"]))
    assert isinstance(ex, RayExecutor) and ex.workers == 1  # (at most the machine's CPUs)
    for bad in ("0", "-1", "two"):
        with pytest.raises(SystemExit) as e:
            tradeoff.parser().parse_args(base + ["--workers", bad])
        assert e.value.code == 2
        assert "--workers" in capsys.readouterr().err
    # evidence passes it on to the sweep it records
    ev = tradeoff.parser().parse_args(["evidence", "--policy", "p", "--out", "o", "--workers", "2"])
    assert ev.workers == 2


def test_each_row_records_how_it_ran_and_each_invocation_its_executor(tmp_path, monkeypatch):
    """A row's wall time depends on whether another row ran beside it (--workers): the record says so."""
    from dataclasses import asdict

    monkeypatch.setattr(tradeoff, "_measure_row", lambda cfg, row, out: {"key": row.key, "status": "ok", "note": ""})
    cfg = tradeoff.load_tradeoff_config(policy="p")
    row = tradeoff.Row("deployment", "torch-fp32", "deployment", "ref")
    for mode in ("worker", "inline"):
        tradeoff.job_row(tmp_path / mode, {}, cfg.model_dump(mode="json"), asdict(row), str(tmp_path), mode)
        assert json.loads((tmp_path / mode / "result.json").read_text())["runner"] == mode
    # an invocation with nothing to run still records its executor
    out = tmp_path / "sweep"
    done = [
        {"key": r.key, "status": "ok", "settings_hash": tradeoff._settings_hash(cfg)} for r in tradeoff.build_rows(cfg)
    ]
    monkeypatch.setattr(tradeoff, "read_results", lambda o: done)
    tradeoff.run_sweep(cfg, out, progress=False, log=lambda m: None)
    run = json.loads((out / "machine.json").read_text())["runs"][-1]
    assert run["executor"] == "serial" and run["workers"] == 1
