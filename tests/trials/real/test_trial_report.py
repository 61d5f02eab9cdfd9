"""Real-trial reports: Wilson cells, unknown handling, the precision line, Table IV and the CLI."""

import json
import math

import numpy as np
import pytest

from trials.real.report import (
    ReportError,
    load_sim_eval,
    normal_half_width,
    precision,
    precision_line,
    rate_cell,
    summarize_trials,
    table_iv,
    trials_for_half_width,
    wilson_half_width,
    write_trial_report,
)

Z = 1.959963984540054


def _wilson(k, n):
    """Textbook Wilson score interval, written out independently of sim.stats."""
    p = k / n
    centre = (p + Z**2 / (2 * n)) / (1 + Z**2 / n)
    half = Z / (1 + Z**2 / n) * math.sqrt(p * (1 - p) / n + Z**2 / (4 * n**2))
    return centre - half, centre + half


def _row(outcome, session="s1", env="A", shape="cube", condition="adv3d", tags=(), operator=None, sha=None, i=[0]):
    i[0] += 1
    return {
        "session": session,
        "trial_id": f"{env}-{shape}-{condition}-{i[0]}",
        "env": env,
        "shape": shape,
        "condition": condition,
        "tags": list(tags),
        "auto_outcome": outcome,
        "operator_outcome": operator,
        "final_outcome": operator if operator is not None else outcome,
        "note": "",
        "n_steps": 10,
        "stop_reason": "reached",
        "started_at": "2025-01-01T00:00:00Z",
        "duration_s": 7.0,
        "texture_sha256": sha,
    }


def test_rate_cell_matches_hand_wilson():
    rows = [_row("adversarial")] * 3 + [_row("none")] * 2 + [_row("goal")] * 5
    c = rate_cell(rows)
    assert (c["n"], c["unknown"], c["tasr"]["k"], c["asr"]["k"]) == (10, 0, 3, 5)
    assert (c["tasr"]["lo"], c["tasr"]["hi"]) == pytest.approx(_wilson(3, 10), abs=1e-12)
    assert (c["asr"]["lo"], c["asr"]["hi"]) == pytest.approx(_wilson(5, 10), abs=1e-12)


def test_rate_cell_edges_k0_kn_n0():
    none_hit = rate_cell([_row("goal")] * 5)
    assert none_hit["tasr"]["rate"] == 0 and none_hit["tasr"]["lo"] == 0.0
    assert none_hit["tasr"]["hi"] == pytest.approx(Z**2 / (5 + Z**2))  # Wilson upper bound at k = 0
    all_hit = rate_cell([_row("adversarial")] * 5)
    assert all_hit["asr"]["hi"] == 1.0 and all_hit["asr"]["lo"] == pytest.approx(5 / (5 + Z**2))
    empty = rate_cell([_row("unknown")] * 3)
    assert (empty["n"], empty["unknown"], empty["n_trials"]) == (0, 3, 3)
    assert math.isnan(empty["tasr"]["rate"]) and (empty["tasr"]["lo"], empty["tasr"]["hi"]) == (0.0, 1.0)


def test_unknown_excluded_and_operator_overrides_auto():
    rows = [
        _row("adversarial"),
        _row("goal"),
        _row("unknown"),
        _row("goal", operator="adversarial"),
        _row("adversarial", operator="unknown"),
    ]
    for r in rows:
        r.pop("final_outcome")  # derived from operator / auto when the store has not filled it
    c = rate_cell(rows)
    assert (c["n"], c["unknown"], c["tasr"]["k"], c["asr"]["k"]) == (3, 2, 2, 2)
    with pytest.raises(ReportError, match="final_outcome 'maybe'"):
        rate_cell([{**_row("goal"), "final_outcome": "maybe"}])


def test_summary_by_session_env_shape_condition_tag():
    rows = (
        [_row("adversarial", session="s1")] * 2
        + [_row("goal", session="s2", env="B", shape="cylinder")] * 3
        + [_row("none", session="s2", condition="clean", tags=["dim"])]
        + [_row("adversarial", session="s2", tags=["dim", "occluded"])]
    )
    s = summarize_trials(rows)
    assert s["sessions"] == ["s1", "s2"] and s["n_trials"] == 7
    a = s["all"]
    assert a["overall"]["n"] == 7 and a["overall"]["tasr"]["k"] == 3 and a["overall"]["asr"]["k"] == 4
    assert a["by_env"]["B"]["n"] == 3 and a["by_shape"]["cylinder"]["asr"]["k"] == 0
    assert a["by_condition"]["clean"]["asr"]["k"] == 1
    assert a["by_tag"]["dim"]["n"] == 2 and a["by_tag"]["occluded"]["n"] == 1 and a["by_tag"]["(untagged)"]["n"] == 5
    assert a["cells"]["A/cube/adv3d/dim+occluded"]["tasr"]["k"] == 1
    assert s["by_session"]["s1"]["overall"]["n"] == 2 and s["by_session"]["s2"]["by_env"]["A"]["n"] == 2


def test_precision_numbers():
    assert trials_for_half_width(0.5, 0.05) == 385  # ceil(1.96^2 * 0.25 / 0.0025) = ceil(384.15)
    assert trials_for_half_width(0.6, 0.05) == math.ceil(Z**2 * 0.24 / 0.0025) == 369
    assert normal_half_width(0.5, 30) == pytest.approx(Z * math.sqrt(0.25 / 30)) == pytest.approx(0.1789, abs=1e-4)
    lo, hi = _wilson(15, 30)
    assert wilson_half_width(15, 30) == pytest.approx((hi - lo) / 2) == pytest.approx(0.1685, abs=1e-4)
    line = precision_line(precision(15, 30))
    assert "385 trials at the worst case" in line and "±17.9 %" in line and "±16.8 %" in line
    zero = precision(0, 30)
    assert zero["trials_needed_observed"] is None and "385" in precision_line(zero)
    assert "no rated trials" in precision_line(precision(0, 0))


def _sim_dir(tmp_path, name, conditions, sources, adv_mesh="mustard_bottle"):
    d = tmp_path / name
    d.mkdir()
    rate = lambda k, n: {"k": k, "n": n, "rate": k / n, "lo": 0.0, "hi": 1.0, "confidence": 0.95}  # noqa: E731
    (d / "summary.json").write_text(
        json.dumps(
            {
                "conditions": {
                    c: {"n": n, "tasr": rate(k1, n), "asr": rate(k2, n)} for c, (k1, k2, n) in conditions.items()
                }
            }
        )
    )
    conds = [
        {
            "name": c,
            "source": None if sources.get(c) is None else {"path": "x", "mesh": sources[c][1], "sha256": sources[c][0]},
        }
        for c in conditions
    ]
    (d / "run.json").write_text(
        json.dumps({"config": {"conditions": conds, "scene": {"objects": [{"role": "adversarial", "mesh": adv_mesh}]}}})
    )
    return d


def test_table_iv_with_and_without_sim(tmp_path):
    sha = "a" * 64
    rows = (
        [_row("adversarial", shape="cube", sha=sha)] * 6
        + [_row("goal", shape="cube", sha=sha)] * 4
        + [_row("unknown", shape="cube", sha=sha)]
        + [_row("none", shape="cylinder")] * 2
        + [_row("adversarial", env="B", shape="cube", sha="b" * 64)] * 2
        + [_row("adversarial", shape="cube", condition="clean")]
        + [_row("adversarial", shape="cube", tags=["dim"], sha=sha)]
    )
    bare = table_iv(rows)
    assert [(r["env"], r["shape"], r["n"]) for r in bare] == [("A", "cube", 10), ("A", "cylinder", 2), ("B", "cube", 2)]
    assert bare[0]["real"]["tasr"]["k"] == 6 and bare[0]["sim"]["tasr"] is None
    assert "no sim eval given" in bare[0]["note"] and "1 unknown excluded" in bare[0]["note"]

    cube = load_sim_eval(
        _sim_dir(
            tmp_path,
            "cube",
            {"clean": (0, 0, 50), "attack": (36, 40, 50), "shape_cube": (30, 35, 50)},
            {"attack": (sha, "cube"), "shape_cube": ("c" * 64, "cube")},
        )
    )
    cyl = load_sim_eval(
        _sim_dir(tmp_path, "cyl", {"shape_cylinder": (38, 42, 50)}, {"shape_cylinder": ("d" * 64, "cylinder")})
    )
    t = table_iv(rows, {"cube": cube, "cylinder": cyl})
    assert (
        t[0]["sim"]["condition"] == "attack"
        and t[0]["sim"]["status"] == "sha256 match"
        and t[0]["sim"]["tasr"]["k"] == 36
    )
    # cylinder trials recorded no texture and no plan was given: same shape, texture not verified
    assert t[1]["sim"]["condition"] == "shape_cylinder" and "not matched" in t[1]["note"]
    # env B used another texture: no sim numbers rather than the wrong ones
    assert t[2]["sim"]["tasr"] is None and "sim texture differs" in t[2]["note"]
    # the plan's sha256 stands in when trials did not record one; an env-specific eval wins
    t = table_iv(rows, {"cylinder": cyl, "A/cylinder": cyl}, {"cylinder/adv3d": "d" * 64})
    assert t[1]["sim"]["status"] == "sha256 match"
    with pytest.raises(ReportError, match="summary.json: missing"):
        load_sim_eval(tmp_path / "nowhere")


def test_write_report_md_and_json(tmp_path):
    rows = [_row("adversarial")] * 18 + [_row("none")] * 4 + [_row("goal")] * 8
    s = summarize_trials(rows)
    md, js = write_trial_report(tmp_path / "r", s, table_iv(rows))
    text = md.read_text()
    assert "| Env | Shape | Sim T-ASR | Sim ASR | Real T-ASR | Real ASR | n | Note |" in text
    assert "| A | cube | – | – | 60.00 [" in text and "| 30 |" in text
    assert "Precision (A/cube" in text and "369 trials at the observed 60.0 %" in text and "385" in text
    doc = json.loads(js.read_text())
    assert doc["table_iv"][0]["real"]["tasr"]["k"] == 18 and doc["precision"]["n"] == 30
    # NaN rates (n = 0) become null: report.json stays strict JSON
    md, js = write_trial_report(tmp_path / "e", summarize_trials([_row("unknown")]), [])
    assert "NaN" not in js.read_text() and "no untagged adv3d trials" in md.read_text()


def _record(i, outcome, condition="adv3d", tags=(), operator=None, sha=None):
    from trials.real.store import TrialRecord

    return TrialRecord(
        trial_id=f"A-cube-{condition}-t{i}-o0",
        plan_order=i,
        env="A",
        shape="cube",
        condition=condition,
        tcp_pose=0,
        object_layout=0,
        tags=list(tags),
        texture_sha256=sha,
        started_at="2025-01-01T00:00:00Z",
        duration_s=5.0,
        stop_reason="reached",
        auto_outcome=outcome,
        auto_reason="test",
        distances_m={},
        operator_outcome=operator,
        note="",
        placement_checks=1,
        placement_skipped=False,
        T_table_tcp_final=np.eye(4),
        frames_dir="frames",
    )


def test_cli_report_end_to_end(tmp_path):
    from typer.testing import CliRunner

    from trials.cli.main import app
    from trials.real.store import SessionInfo, TrialStore

    sha = "e" * 64
    db = tmp_path / "trials.sqlite"
    with TrialStore(db) as store:
        for name, outcomes in (
            ("day1", ["adversarial", "adversarial", "goal", "unknown"]),
            ("day2", ["none", "goal", "adversarial"]),
        ):
            sid = store.open_session(
                SessionInfo(
                    name=name,
                    plan_sha256="p",
                    plan_text="",
                    hardware_text="",
                    policy_path="pol",
                    policy_sha256="q",
                    software_version="0",
                    git_commit="g",
                    devices={},
                    calibration={},
                )
            )
            for i, o in enumerate(outcomes):
                store.commit_trial(sid, _record(i, o, sha=sha, operator="goal" if (name, i) == ("day2", 1) else None))
    sim = _sim_dir(tmp_path, "sim_cube", {"attack": (40, 45, 50)}, {"attack": (sha, None)}, adv_mesh="cube")
    out = tmp_path / "report"
    res = CliRunner().invoke(app, ["trial", "report", "--db", str(db), "--sim", f"cube={sim}", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "| A | cube | 80.00 | 90.00 | 50.00 [" in res.output  # 3 of 6 rated trials hit the adversary
    doc = json.loads((out / "report.json").read_text())
    assert doc["summary"]["sessions"] == ["day1", "day2"] and doc["summary"]["all"]["overall"]["unknown"] == 1
    assert doc["summary"]["by_session"]["day1"]["overall"]["tasr"]["k"] == 2
    assert (out / "report.md").is_file() and (out / "run.json").is_file()
    res = CliRunner().invoke(
        app, ["trial", "report", "--db", str(db), "--session", "day2", "--out", str(tmp_path / "r2")]
    )
    assert res.exit_code == 0 and json.loads((tmp_path / "r2" / "report.json").read_text())["summary"]["n_trials"] == 3
    res = CliRunner().invoke(
        app, ["trial", "report", "--db", str(db), "--session", "day9", "--out", str(tmp_path / "r3")]
    )
    assert res.exit_code != 0 and "no session day9" in str(res.exception)
