"""A recipe's ``table.md`` rebuilt from its committed results: report only, nothing runs.

``tools/evidence.py`` collects a recipe run into ``results/<name>/``: ``run.json`` (the command),
``summary.json`` (each evaluation's summary, by evaluation name), ``episodes.csv`` (every
evaluation's rows, its name in the first column ``eval``) and ``attacks.json`` (each attack's
iterations, seconds and held-out validation), beside the ``table.md`` the run wrote. When the way a
table is printed changes (a verdict rule, a new line), :func:`committed_table` gives the table the
recipe writes now for the same data, without the run folders (``runs/``) the data came from.

It runs the recipe's own function (:data:`trials.experiments.recipes.RECIPES`) on a
:class:`~trials.experiments.recipes.Context` whose jobs are declared and never run
(:class:`ReplayGrid`, :class:`NoRun`): every evaluation the recipe reads is the committed one, laid
out in a temporary folder as the run's ``evals/<name>/`` (its summary and its rows), and every
attack's ``metrics.json`` is the committed ``attacks.json`` entry. So the text is the recipe's,
line for line, and no figure is recomputed outside the functions that print it.

Recipes whose table reads more than ``results/`` holds have no report-only path
(:data:`NO_REPORT_ONLY` says what each one reads); :func:`check_report_only` refuses them in one line.
"""

from __future__ import annotations

import csv
import json
import tempfile
from pathlib import Path

from sim.errors import AdvobjError
from trials.eval.episodes import EPISODES_NAME, SUMMARY_NAME, StorageError, read_collected
from trials.experiments.recipes import RECIPES, TABLE2_ROWS, Context, ExperimentConfig, seeded
from trials.jobs.dag import Grid, Job

__all__ = [
    "RetableError",
    "REPORT_ONLY",
    "NO_REPORT_ONLY",
    "TABLE_NAME",
    "ATTACKS_NAME",
    "ReplayGrid",
    "NoRun",
    "check_report_only",
    "recorded_rows",
    "committed_table",
]

TABLE_NAME = "table.md"
ATTACKS_NAME = "attacks.json"

#: Recipes whose table is printed from evaluation summaries, episode rows and the attacks' metrics
#: only: what ``results/<name>/`` holds.
REPORT_ONLY = ("table1", "table2", "table3", "lighting")

#: Recipes whose table reads more than ``results/`` holds, and what.
NO_REPORT_ONLY = {
    "transfer": "its table names each policy's architecture from the policy's card (policy.json), which "
    "results/ does not hold",
    "cameras": "its table names the cameras the policy reads, from the policy itself, which results/ does not hold",
    "recordings": "its table reads the recordings and the attacks' CPU records, which results/ does not hold",
}


class RetableError(AdvobjError, ValueError):
    """A results folder a table cannot be rebuilt from (its recipe has no report-only path, or a file
    it needs is missing)."""


def check_report_only(recipe: str, folder: str | Path) -> None:
    """Refuse, in one line naming ``folder``, a recipe with no report-only path."""
    if recipe in REPORT_ONLY:
        return
    why = NO_REPORT_ONLY.get(recipe, "it is not among the recipes with one (" + ", ".join(REPORT_ONLY) + ")")
    raise RetableError(
        f"{folder}: recipe {recipe!r} has no report-only path: {why}; rebuild it with tools/evidence.py run"
    )


class ReplayGrid(Grid):
    """A grid that declares jobs and checks nothing on disk: the replay's inputs (policies, scenes,
    pools) are the run's, which are not here. An evaluation the committed results lack is refused in
    one line naming ``folder`` (the recipe reads it; the run had another set of evaluations)."""

    def __init__(self, root: str | Path, folder: str | Path):
        super().__init__(root)
        self.folder = Path(folder)

    def add(self, name: str, kind: str, fn: str, out: str | Path, params=None, inputs=None, **_) -> Job:
        if kind == "eval" and not (Path(out) / SUMMARY_NAME).is_file():
            raise RetableError(
                f"{self.folder / SUMMARY_NAME}: no evaluation {Path(out).name!r}, which the recipe reads for this "
                "config; the committed run has another set of evaluations"
            )
        job = Job(name, kind, fn, str(Path(out).resolve()), dict(params or {}))
        self.jobs[name] = job
        return job


class NoRun:
    """An executor that runs nothing: every job the replay declares is finished in the committed results."""

    def run(self, grid: Grid) -> dict:
        return {}


def recorded_rows(recipe: str, cfg: ExperimentConfig, summaries: dict) -> tuple[str, ...] | None:
    """The Table II rows of a ``table2`` run made without ``--rows``: the rows of its time, those
    with an evaluation in ``summaries`` (the recipe's list of rows has grown since; a run asked for
    all of them). ``cfg.rows`` as it is for any other recipe or a run that named its rows."""
    if recipe != "table2" or cfg.rows is not None:
        return cfg.rows
    first = cfg.attack_seeds[0]
    return tuple(key for key, *_ in TABLE2_ROWS if seeded(f"table2_{key}", first) in summaries)


def _lay_out(folder: Path, summaries: dict, root: Path) -> None:
    """The committed evaluations as the run's ``root/evals/<name>/`` folders (summary and rows, the
    rows as stored, without the ``eval`` column), and each attack of ``attacks.json`` as
    ``root/attacks/<name>/metrics.json``."""
    rows: dict[str, list[dict]] = {}
    with open(folder / EPISODES_NAME, newline="") as f:
        reader = csv.DictReader(f)
        if not reader.fieldnames or reader.fieldnames[0] != "eval":
            raise RetableError(f"{folder / EPISODES_NAME}: not a collection of evaluations (no first column 'eval')")
        fields = reader.fieldnames[1:]
        for r in reader:
            rows.setdefault(r.pop("eval"), []).append(r)
    for name, summary in summaries.items():
        d = root / "evals" / name
        d.mkdir(parents=True)
        (d / SUMMARY_NAME).write_text(json.dumps(summary))
        with open(d / EPISODES_NAME, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=fields)
            w.writeheader()
            w.writerows(rows.get(name, []))
    attacks = folder / ATTACKS_NAME
    for name, m in (json.loads(attacks.read_text()) if attacks.is_file() else {}).items():
        d = root / "attacks" / name
        d.mkdir(parents=True)
        # attack.outputs writes seconds_per_iteration as seconds over the iterations of the run's
        # history (one entry per iteration); attacks.json keeps the seconds and the iterations.
        try:
            metrics = {**m, "seconds_per_iteration": float(m["seconds"]) / max(1, int(m["iterations"]))}
        except (KeyError, TypeError, ValueError):
            raise RetableError(f"{attacks}: attack {name!r} has no seconds or iterations") from None
        (d / "metrics.json").write_text(json.dumps(metrics))


def committed_table(
    folder: str | Path,
    recipe: str,
    cfg: ExperimentConfig,
    policy: str | Path | None = None,
    targets: dict | None = None,
    scene: str | None = None,
) -> str:
    """The ``table.md`` recipe ``recipe`` writes now for the committed results in ``folder``
    (``results/<name>/``), run with ``cfg``, ``policy``, ``targets`` and ``scene`` as its recorded
    command gave them. Nothing runs and nothing in ``folder`` is written; one :class:`RetableError`
    line when the recipe has no report-only path or a file it needs is missing or malformed."""
    folder = Path(folder)
    check_report_only(recipe, folder)
    for need in (SUMMARY_NAME, EPISODES_NAME):
        if not (folder / need).is_file():
            raise RetableError(f"{folder / need}: missing; is {folder} a recipe's collected results?")
    try:
        summaries = read_collected(folder)
    except StorageError as err:
        raise RetableError(str(err)) from None
    cfg = cfg.model_copy(update={"rows": recorded_rows(recipe, cfg, summaries)})
    with tempfile.TemporaryDirectory(prefix="retable-") as tmp:
        root = Path(tmp)
        _lay_out(folder, summaries, root)
        ctx = Context(
            cfg,
            root,
            None if policy is None else Path(policy),
            {k: Path(v) for k, v in (targets or {}).items()},
            scene,
            progress=False,
            log=lambda _msg: None,
            executor=NoRun(),
            grid=ReplayGrid(root, folder),
        )
        try:
            return RECIPES[recipe].run(ctx)
        except FileNotFoundError as err:  # an attack's metrics the recipe reads (lighting)
            name = Path(err.filename or "?").parent.name
            raise RetableError(f"{folder / ATTACKS_NAME}: no attack {name!r}, which the recipe reads") from None
