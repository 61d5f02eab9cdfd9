"""The evaluation's report.html (trials.eval.report through sim.htmlreport): the bar charts (n on
every bar, 0 % drawn, empty bins empty), the rollout shown (the attack reached the adversarial
object and clean did not, or a line saying there is none), and the page in a real Chromium."""

from __future__ import annotations

import shutil

import matplotlib.pyplot as plt
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from matplotlib.collections import LineCollection
from matplotlib.patches import Rectangle

from sim.htmlreport import REPORT_HTML
from sim.stats import proportion
from tests.sim.browser_helpers import assert_renders_cleanly, needs_chromium, outline, render_in_chromium
from tests.trials.conftest import MAX_STEPS
from trials.eval.episodes import read_rows, read_summary
from trials.eval.evaluate import load_eval_config, run_eval
from trials.eval.report import pick_rollout, rate_bars_figure, write_report


def _cell(k, n):
    return {"n": n, "tasr": proportion(k, n).to_dict(), "asr": proportion(n - k, n).to_dict()}


def test_bars_show_n_on_every_bar_draw_zero_and_leave_empty_bins_empty():
    labels = ["0-10", "10-20", "20-30"]
    series = {
        "clean": {"0-10": _cell(0, 5), "10-20": _cell(2, 4), "20-30": _cell(0, 0)},
        "attack": {"10-20": _cell(4, 4)},
    }
    fig = rate_bars_figure(labels, series, "phi", "deg")
    try:
        ax = fig.axes[0]  # T-ASR
        texts = sorted((round(t.get_position()[0], 3), t.get_text()) for t in ax.texts)
        w = 0.8 / 2
        # clean at x - w/2, attack at x + w/2: n on the 3 non-empty bars, "n=0" on the 3 empty bins
        assert texts == sorted(
            [
                (round(0 - w / 2, 3), "n=5"),
                (round(0 + w / 2, 3), "n=0"),
                (round(1 - w / 2, 3), "n=4"),
                (round(1 + w / 2, 3), "n=4"),
                (round(2 - w / 2, 3), "n=0"),
                (round(2 + w / 2, 3), "n=0"),
            ]
        )
        bars = [p for p in ax.patches if isinstance(p, Rectangle)]
        heights = sorted((round(b.get_x() + b.get_width() / 2, 3), round(b.get_height(), 6)) for b in bars)
        # no bar at an empty bin (none full-height any more); the 0 % bin is a zero-height bar ...
        assert heights == [(round(0 - w / 2, 3), 0.0), (round(1 - w / 2, 3), 50.0), (round(1 + w / 2, 3), 100.0)]
        # ... drawn as a thick line at 0 in its series' colour
        zero = [c for c in ax.collections if isinstance(c, LineCollection) and c.get_linewidth()[0] >= 3]
        assert len(zero) == 1 and np.allclose(zero[0].get_segments()[0][:, 1], 0)
        (legend,) = fig.legends
        assert [t.get_text() for t in legend.get_texts()] == ["clean", "attack"]
        assert legend.get_texts()[0].get_fontsize() >= 10
    finally:
        plt.close(fig)


def _rows(outcomes):
    """Episode rows from ``{seed: (attack_outcome, clean_outcome)}``."""
    rows = []
    for seed, pair in outcomes.items():
        for cond, out in zip(("attack", "clean"), pair):
            rows.append(
                {
                    "condition": cond,
                    "seed": seed,
                    "outcome": out,
                    "success": out == "goal",
                    "targeted": out == "adversarial",
                }
            )
    return rows


OUTCOME = st.sampled_from(["goal", "adversarial", "none"])


@settings(max_examples=200, deadline=None)
@given(st.dictionaries(st.integers(0, 30), st.tuples(OUTCOME, OUTCOME), min_size=1), st.data())
def test_the_rollout_shown_is_one_where_the_attack_won_and_clean_did_not(outcomes, data):
    recorded = data.draw(st.lists(st.sampled_from(sorted(outcomes)), unique=True))
    seed, why = pick_rollout(_rows(outcomes), "attack", recorded)
    wins = sorted(s for s in recorded if outcomes[s][0] == "adversarial" and outcomes[s][1] != "adversarial")
    best = [s for s in wins if outcomes[s][1] == "goal"]
    if not wins:
        assert seed is None and f"none of the {len(recorded)} recorded configurations" in why
        anywhere = [s for s, (a, c) in outcomes.items() if a == "adversarial" and c != "adversarial"]
        assert ("larger `--gifs`" in why) == bool(anywhere)
    else:
        assert seed == (best or wins)[0] and f"configuration {seed}: `attack` reached the adversarial object" in why


@pytest.fixture(scope="module")
def tiny_eval(tmp_path_factory, tiny_policy_dir, pool_file, attack_dir):
    """A real evaluation (clean and attack, 4 configurations, 2 recorded as GIFs), run once here."""
    out = tmp_path_factory.mktemp("eval") / "ev"
    cfg = load_eval_config(
        policy=str(tiny_policy_dir),
        conditions=("attack",),
        episodes=4,
        max_steps=MAX_STEPS,
        num_envs=2,
        pool=str(pool_file),
        attack=str(attack_dir),
        gifs=2,
    )
    run_eval(cfg, out, progress=False)
    return out


def test_a_real_evaluation_writes_its_page_beside_the_markdown(tiny_eval):
    tmp_path = tiny_eval
    assert (tmp_path / "report.md").is_file()
    page = (tmp_path / REPORT_HTML).read_text()
    o = outline(page)
    assert o.headings["h1"] == ["Evaluation report"]
    assert o.headings["h2"] == [
        "Summary",
        "Paired tests between arms",
        "T-ASR and ASR by viewing angle phi (deg)",
        "T-ASR and ASR by initial distance (cm)",
        "Rollouts: clean (left) and the arm (right) from the same configuration",
        "Textures",
        "Metric definitions",
    ]
    kinds = [i["src"].split(";")[0] for i in o.images]
    assert kinds.count("data:image/png") == 2 + 1 and kinds.count("data:image/gif") == 1  # bars, texture; GIF
    assert "attack vs clean" in o.text and "n on every bar" in o.text
    seed, _ = pick_rollout(read_rows(tmp_path), "attack", _recorded(tmp_path))
    if seed is None:  # an untrained policy: most likely, and then said in a line
        assert "attack: none of the 2 recorded configurations" in o.text
    else:
        assert f"configuration {seed}: attack reached the adversarial object" in o.text


def _recorded(eval_dir) -> list[int]:
    return sorted(int(p.stem.split("_seed")[1]) for p in (eval_dir / "gifs").glob("clean_seed*.gif"))


def test_the_page_shows_the_configuration_where_the_attack_won(tmp_path, tiny_eval):
    """With an episode table where the attack reached the adversarial object from the second recorded
    configuration only, that configuration's GIF is the one shown, and the Markdown lists it first."""
    tmp_path = shutil.copytree(tiny_eval, tmp_path / "ev")
    rows = read_rows(tmp_path)
    first, second = _recorded(tmp_path)
    for r in rows:
        won = r["condition"] == "attack" and r["seed"] == second
        r.update(targeted=won, outcome="adversarial" if won else "goal", success=not won)
    write_report(tmp_path, read_summary(tmp_path), rows=rows)
    o = outline((tmp_path / REPORT_HTML).read_text())
    assert f"configuration {second}: attack reached the adversarial object, clean reached the goal" in o.text
    gif = [i for i in o.images if i["src"].startswith("data:image/gif")]
    assert len(gif) == 1 and f"configuration {second}" in gif[0]["alt"]
    md = (tmp_path / "report.md").read_text()
    assert md.index(f"compare_clean_vs_attack_seed{second}") < md.index(f"compare_clean_vs_attack_seed{first}")


@needs_chromium
def test_chromium_renders_the_evaluation_page_without_console_messages(tmp_path, tiny_eval):
    r = render_in_chromium(tiny_eval / REPORT_HTML, tmp_path / "chromium", 1280, 2400)
    assert_renders_cleanly(r)
    assert r.outline.headings["h2"][:2] == ["Summary", "Paired tests between arms"]
    assert r.outline.tables >= 4 and len(r.outline.images) == 4
