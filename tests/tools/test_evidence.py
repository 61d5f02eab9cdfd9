"""The evidence tool refuses to record a result from a checkout with uncommitted changes, and records every attempt."""

import json
from pathlib import Path

from tools import evidence
from trials.experiments import record


def test_a_dirty_checkout_is_refused_before_anything_runs_or_is_written(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(record, "git_commit", lambda: "0123abc+dirty")
    ran = []
    monkeypatch.setattr(evidence, "run_attempt", lambda *a, **k: ran.append(a) or {"exit_code": 0})
    rc = evidence.run("table1", 10, None, tmp_path / "work", tmp_path / "results", [])
    assert rc == 2 and not ran
    assert not (tmp_path / "results").exists() and not (tmp_path / "work").exists()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "uncommitted changes" in err[0]


def test_a_failed_run_is_recorded_as_an_attempt_with_its_command_machine_and_times(tmp_path, monkeypatch):
    monkeypatch.setattr(record, "git_commit", lambda: "0123abc")
    calls = []
    monkeypatch.setattr(record.subprocess, "call", lambda argv, **k: calls.append(argv) or 3)
    rc = evidence.run("table1", 10, None, tmp_path / "work", tmp_path / "results", ["--workers", "2"])
    assert rc == 3 and len(calls) == 1 and calls[0][1:3] == ["experiment", "table1"]
    (attempt,) = record.read_record(tmp_path / "results" / "table1")["attempts"]
    assert attempt["command"].startswith("advobj experiment table1 --preset quick --episodes 10 --out ")
    assert attempt["command"].endswith("--workers 2") and attempt["commit"] == "0123abc"
    assert attempt["exit_code"] == 3 and attempt["wall_s"] >= 0 and attempt["cpu_s"] >= 0
    assert attempt["machine"]["cpus"] >= 1 and "load_avg_start" in attempt["machine"]
    assert not (tmp_path / "results" / "table1" / "episodes.csv").exists()  # a failed run is not collected


def _absolute_paths(doc):
    """The string values of a JSON document that are absolute paths."""
    if isinstance(doc, dict):
        for v in doc.values():
            yield from _absolute_paths(v)
    elif isinstance(doc, list):
        for v in doc:
            yield from _absolute_paths(v)
    elif isinstance(doc, str) and (doc.startswith("/") or (len(doc) > 2 and doc[1:3] == ":\\")):
        yield doc


def test_no_committed_result_names_an_absolute_path():
    """A committed record names files relative to the repository (or its own folder), never by a
    machine's absolute path: every string value of every JSON and JSON-lines file under results/."""
    results = Path(__file__).resolve().parents[2] / "results"
    found = []
    for f in sorted(results.rglob("*.json")) + sorted(results.rglob("*.jsonl")):
        docs = [f.read_text()] if f.suffix == ".json" else f.read_text().splitlines()
        for text in docs:
            found += [(f.relative_to(results).as_posix(), s) for s in _absolute_paths(json.loads(text))]
    assert found == []
    # the check sees one
    assert list(_absolute_paths({"meta": {"pool": [str(results / "x.json")]}})) == [str(results / "x.json")]
