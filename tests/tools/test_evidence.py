"""The evidence tool refuses to record a result from a checkout with uncommitted changes."""

from tools import evidence


def test_a_dirty_checkout_is_refused_before_anything_runs_or_is_written(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(evidence, "_commit", lambda: "0123abc+dirty")
    ran = []
    monkeypatch.setattr(evidence.subprocess, "call", lambda *a, **k: ran.append(a) or 0)
    rc = evidence.run("table1", 10, None, tmp_path / "work", tmp_path / "results", [])
    assert rc == 2 and not ran
    assert not (tmp_path / "results").exists() and not (tmp_path / "work").exists()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "uncommitted changes" in err[0]
