"""The demo's report prints its 3D-vs-patch verdict once (trials.experiments.demo: verdicts_once and
demo_report_markdown)."""

import math

from trials.experiments.demo import verdicts_once
from trials.experiments.findings import paired_markdown


def _rows(targeted):
    """Episode rows by seed, spread over the phi and distance bins."""
    return {
        s: {"targeted": t, "phi_rad": math.radians(5 + 10 * (s % 8)), "r_m": 0.3 + 0.1 * (s % 5)}
        for s, t in enumerate(targeted)
    }


def test_the_overall_verdict_is_printed_once_and_both_bin_tables_stay():
    a = _rows([True] * 12 + [False] * 4)
    b = _rows([False] * 10 + [True] * 6)
    phi = paired_markdown("3D", "patch", a, b, "phi")
    r = paired_markdown("3D", "patch", a, b, "r")
    verdict = phi[0]
    assert verdict.startswith("**3D vs patch** (claim: ") and r[0] == verdict  # the same line, twice
    text = "\n".join(["## by phi", "", *phi, "", "## by r", "", *r])
    once = verdicts_once(text).split("\n")
    assert once.count(verdict) == 1 and once.index(verdict) < once.index("## by r")
    assert [x for x in once if x.startswith("|")] == [x for x in phi[1:] + r[1:] if x.startswith("|")]
    assert once[once.index("## by r") + 1 : once.index("## by r") + 3] == ["", r[2]]  # no double blank
    assert verdicts_once(verdicts_once(text)) == verdicts_once(text)


def _episode_rows(spec, n: int) -> list[dict]:
    """Clean, 3D-object and patch episode rows on ``n`` configurations spread over the phi and
    distance bins: clean reaches the goal, the 3D object wins on two thirds, the patch on one third."""
    goal, adv = spec.object_index("goal"), spec.object_index("adversarial")
    rows = []
    for cond, wins in (("clean", lambda s: False), ("attack", lambda s: s % 3 != 0), ("patch", lambda s: s % 3 == 0)):
        for s in range(n):
            reached = adv if wins(s) else goal
            rows.append(
                {
                    "condition": cond,
                    "seed": s,
                    "phi_rad": math.radians(5 + 10 * (s % 8)),
                    "r_m": 0.3 + 0.1 * (s % 5),
                    "reached": reached,
                    "success": reached == goal,
                    "targeted": reached == adv,
                    "steps": 10,
                    "e_trans": 0.01,
                    "e_rot": 0.1,
                }
            )
    return rows


def test_the_demo_report_page_prints_the_3d_vs_patch_verdict_once(tmp_path):
    """The demo's report.md assembled from the real pieces (the evaluation's report.md written by
    trials.eval.report, the recipe's Table I layout with its paired tests by phi and by distance):
    the overall 3D-vs-patch verdict appears once, and both bin tables, the evaluation section and
    its links (relative to the demo folder) stay."""
    from types import SimpleNamespace

    from sim.spec import default_scene
    from trials.eval.report import summarize, write_report
    from trials.experiments.demo import demo_report_markdown
    from trials.experiments.recipes import resolve_experiment, table1_markdown

    spec = default_scene()
    rows = _episode_rows(spec, 24)
    summary = summarize(rows, spec, ["clean", "attack", "patch"])
    eval_dir = tmp_path / "evals" / "demo"
    eval_dir.mkdir(parents=True)
    write_report(eval_dir, summary, rows=rows)
    ctx = SimpleNamespace(cfg=resolve_experiment("quick"))  # the Table I header reads the config only
    table = table1_markdown(summary, ctx, rows)
    page = demo_report_markdown(tmp_path, tmp_path / "policy", eval_dir, table, (eval_dir / "report.md").read_text())

    lines = page.split("\n")
    verdicts = [x for x in lines if x.startswith("**3D vs patch** (claim: ")]
    assert len(verdicts) == 1
    by_phi, by_r = (
        lines.index("## Paired T-ASR test by viewing angle phi"),
        lines.index("## Paired T-ASR test by initial distance r"),
    )
    assert by_phi < lines.index(verdicts[0]) < by_r < lines.index("## Evaluation")
    assert lines.count("# advobj demo: 3D adversarial object vs 2D patch") == 1 and "# Evaluation report" not in lines
    assert "](evals/demo/bars_by_phi.png)" in page and "[evals/demo/report.html](evals/demo/report.html)" in page
    # a verdict line the evaluation's section repeated would be dropped too: once on the whole page
    twice = demo_report_markdown(tmp_path, tmp_path / "policy", eval_dir, table, verdicts[0] + "\n\nrest")
    assert twice.count(verdicts[0]) == 1 and twice.rstrip().endswith("rest")
