"""``tools/evidence.py retable``: a recipe's committed table.md rebuilt from its committed data alone.

The committed tables are what their recipes print now for the committed summaries and rows (a table
left stale by a change in how verdicts are printed fails here); the rebuild writes table.md and
nothing else; a recipe whose table reads more than results/ holds is refused in one line.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest

from tools import evidence
from trials.experiments.recipes import RECIPES, resolve_experiment
from trials.experiments.retable import NO_REPORT_ONLY, REPORT_ONLY, TABLE_NAME, recorded_rows

RESULTS = Path(evidence.ROOT) / "results"
COMMITTED = evidence.report_only_folders(RESULTS)


def _digests(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def _copy(name: str, tmp_path: Path) -> Path:
    dst = tmp_path / "results" / name
    shutil.copytree(RESULTS / name, dst)
    return dst


def _one_refusal(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("evidence: ")
    return err[0]


def test_the_committed_recipe_runs_with_a_report_only_path_are_found():
    assert "table1" in COMMITTED
    assert all((RESULTS / n / TABLE_NAME).is_file() for n in COMMITTED)


def test_every_recipe_either_has_a_report_only_path_or_says_what_its_table_reads_beyond_results():
    assert set(REPORT_ONLY) | set(NO_REPORT_ONLY) == set(RECIPES)
    assert not set(REPORT_ONLY) & set(NO_REPORT_ONLY)


@pytest.mark.parametrize("name", COMMITTED)
def test_a_committed_table_is_what_its_recipe_prints_now_from_the_committed_data(name):
    assert evidence.retable_text(RESULTS / name) == (RESULTS / name / TABLE_NAME).read_text(), (
        f"results/{name}/{TABLE_NAME} is stale: .venv/bin/python tools/evidence.py retable {name}"
    )


def test_retable_rewrites_a_stale_table_and_no_other_file(tmp_path, capsys):
    folder = _copy("table1", tmp_path)
    table = folder / TABLE_NAME
    want = table.read_text()
    table.write_text(want.replace("inconclusive", "holds"))
    before = _digests(folder)
    assert evidence.main(["retable", "table1", "--check", "--results", str(folder.parent)]) == 1
    assert _digests(folder) == before  # --check writes nothing
    assert "stale" in capsys.readouterr().out
    assert evidence.main(["retable", "table1", "--results", str(folder.parent)]) == 0
    assert table.read_text() == want
    after = _digests(folder)
    assert {k for k in before if before[k] != after[k]} == {TABLE_NAME} and set(after) == set(before)
    assert evidence.main(["retable", "table1", "--check", "--results", str(folder.parent)]) == 0


@pytest.mark.parametrize("recipe", sorted(NO_REPORT_ONLY))
def test_a_recipe_without_a_report_only_path_is_refused_in_one_line_and_nothing_is_written(recipe, tmp_path, capsys):
    folder = tmp_path / "results" / recipe
    folder.mkdir(parents=True)
    command = f"advobj experiment {recipe} --preset quick --episodes 300 --out runs/evidence/{recipe}"
    (folder / "run.json").write_text(json.dumps({"attempts": [{"command": command, "exit_code": 0}]}))
    (folder / TABLE_NAME).write_text("stale\n")
    assert evidence.main(["retable", recipe, "--results", str(folder.parent)]) == 2
    line = _one_refusal(capsys)
    assert str(folder) in line and "no report-only path" in line and NO_REPORT_ONLY[recipe] in line
    assert (folder / TABLE_NAME).read_text() == "stale\n"


@pytest.mark.parametrize(
    "record, says",
    [
        (None, "run.json: missing"),
        ({"attempts": []}, "no successful attempt"),
        ({"attempts": [{"command": "advobj experiment table1", "exit_code": 1}]}, "no successful attempt"),
        ({"attempts": [{"command": "python -m trials.experiments.formats run", "exit_code": 0}]}, "not an 'advobj"),
        ({"attempts": [{"command": "advobj experiment table1 --episodes zero", "exit_code": 0}]}, "does not parse"),
        ({"attempts": [{"command": "advobj experiment table1 --attack-seeds 0,0", "exit_code": 0}]}, "attack seeds"),
    ],
)
def test_a_folder_that_is_not_a_readable_recipe_run_is_refused_in_one_line_naming_its_record(
    record, says, tmp_path, capsys
):
    folder = _copy("table1", tmp_path)
    (folder / "run.json").unlink()
    if record is not None:
        (folder / "run.json").write_text(json.dumps(record))
    before = _digests(folder)
    assert evidence.main(["retable", "table1", "--results", str(folder.parent)]) == 2
    line = _one_refusal(capsys)
    assert str(folder / "run.json") in line and says in line
    assert _digests(folder) == before


def test_an_evaluation_the_recipe_reads_and_the_committed_results_lack_is_named(tmp_path, capsys):
    folder = _copy("table1", tmp_path)
    summaries = json.loads((folder / "summary.json").read_text())
    gone = "table1"  # the evaluation of attack seed 0, which the recipe's table is printed from
    del summaries[gone]
    (folder / "summary.json").write_text(json.dumps(summaries))
    assert evidence.main(["retable", "table1", "--results", str(folder.parent)]) == 2
    line = _one_refusal(capsys)
    assert str(folder / "summary.json") in line and f"no evaluation {gone!r}" in line


def test_a_table2_run_without_rows_is_printed_with_the_rows_it_ran_and_named_rows_stay():
    cfg = resolve_experiment("quick")
    ran = {"table2_ns": {}, "table2_c2f": {}, "table2_c2f-seed1": {}}
    assert recorded_rows("table2", cfg, ran) == ("ns", "c2f")  # in the recipe's order, seed 0's evaluations
    named = resolve_experiment("quick", rows=("c2f", "f2c"))
    assert recorded_rows("table2", named, ran) == ("c2f", "f2c")
    assert recorded_rows("table1", cfg, ran) is None
    seeded = resolve_experiment("quick", attack_seeds=(3, 4))
    assert recorded_rows("table2", seeded, {"table2_ns-seed3": {}, "table2_ns": {}}) == ("ns",)
