"""Summaries and reports of an evaluation: rates with Wilson intervals, errors with bootstrap
intervals, the paper's bins, McNemar against the clean arm, plots, GIFs and texture thumbnails.

The headline compares ``attack`` with its control ``benign`` (the same mesh with the attack's
unoptimised start texture, :mod:`trials.eval.conditions`), paired by McNemar's exact test as every
comparison here (:func:`paired_tests`): the difference the optimisation made, which the comparison
with ``clean`` mixes with any change of the object's look or shape."""

from __future__ import annotations

import math
from pathlib import Path

import imageio.v3 as iio
import matplotlib
import matplotlib.pyplot as plt
import numpy as np
from PIL import Image

from sim.htmlreport import Bullets, Figure, Flag, Gallery, Heading, Table, Text, write_page
from sim.imaging import write_gif
from trials.eval.episodes import read_rows
from trials.eval.metrics import (
    DISTANCE_BINS_CM,
    PHI_BINS_DEG,
    attack_rates,
    bin_index,
    bin_labels,
    bootstrap_mean_ci,
    mcnemar_from_outcomes,
)

__all__ = [
    "summarize",
    "summarize_rows",
    "paired_tests",
    "HEADLINE",
    "write_report",
    "plot_rate_bars",
    "rate_bars_figure",
    "pick_rollout",
    "format_headline",
    "fmt_rate",
    "fmt_err",
    "METRIC_DEFINITIONS",
]

# The headline comparison: (the arm, its control).
HEADLINE = ("attack", "benign")

METRIC_DEFINITIONS = """\
- **ASR**: share of episodes that do not reach the goal object within the episode (95% Wilson interval).
- **T-ASR**: share of episodes that end by reaching the adversarial object (95% Wilson interval).
- **E_trans**: per step, L2 norm of the difference between the translation parts of the policy's
  actions on the attacked and on the clean observation of the same state, in normalised action
  units (1 = one full step of `max_step_m`; maximum 2*sqrt(3)); mean over the episode's steps,
  then over episodes (95% percentile-bootstrap interval over episodes). 0 for the clean arm.
- **E_rot**: per step, the angle (rad) between the rotations the two actions command
  (`exp(a[3:] * max_step_rad)`); aggregated like E_trans.
- **McNemar p**: exact two-sided McNemar test of the condition against the clean arm on the same
  configurations (b = episodes where only this condition has the event, c = only the clean arm).
- **benign**: the attacked mesh with the attack's unoptimised start texture (the control of the
  headline); **clean**: the scene's own object as it is.
- Bins: initial TCP distance r to the adversarial object (cm) and viewing angle phi (polar angle
  from its up axis, degrees), as in the paper's Tables I-II; bins are [lo, hi), the last [lo, hi].
"""


def summarize_rows(rows: list[dict], goal_index: int, adv_index: int, seed: int = 0) -> dict:
    """Rates and error means of a set of episode rows (any subset of one condition)."""
    reached = [r["reached"] for r in rows]
    rates = attack_rates(reached, goal_index, adv_index)
    return {
        "n": len(rows),
        "tasr": rates["tasr"].to_dict(),
        "asr": rates["asr"].to_dict(),
        "e_trans": bootstrap_mean_ci([r["e_trans"] for r in rows], seed=seed).to_dict(),
        "e_rot": bootstrap_mean_ci([r["e_rot"] for r in rows], seed=seed + 1).to_dict(),
        "mean_steps": float(np.mean([r["steps"] for r in rows])) if rows else math.nan,
    }


def _binned(rows, values, edges, goal, adv) -> dict:
    idx = bin_index(values, edges)
    out = {}
    for b, label in enumerate(bin_labels(edges)):
        out[label] = summarize_rows([r for r, i in zip(rows, idx) if i == b], goal, adv)
    out["outside"] = int((idx < 0).sum())
    return out


def paired_tests(rows_a: list[dict], rows_b: list[dict]) -> dict:
    """McNemar's exact test of arm A against arm B on the configurations (seeds) both ran, for the
    ASR event (goal not reached) and the T-ASR event (adversarial object reached).

    Returns ``{"asr": ..., "tasr": ...}`` (:class:`trials.eval.metrics.McNemar` dicts): ``b`` counts
    configurations where only A has the event, ``c`` only B, ``n_pairs`` the shared ones.
    """
    rb = {r["seed"]: r for r in rows_b}
    paired = [(x, rb[x["seed"]]) for x in rows_a if x["seed"] in rb]
    return {
        "asr": mcnemar_from_outcomes(
            [not x["success"] for x, _ in paired], [not y["success"] for _, y in paired]
        ).to_dict(),
        "tasr": mcnemar_from_outcomes([x["targeted"] for x, _ in paired], [y["targeted"] for _, y in paired]).to_dict(),
    }


def summarize(rows: list[dict], spec, condition_names, meta: dict | None = None) -> dict:
    """The evaluation summary: per condition overall, by phi, by distance, and vs clean; the
    headline (``attack`` vs ``benign``) when both ran."""
    goal, adv = spec.object_index("goal"), spec.object_index("adversarial")
    by_cond = {c: sorted((r for r in rows if r["condition"] == c), key=lambda r: r["seed"]) for c in condition_names}
    out = {"meta": meta or {}, "goal": spec.objects[goal].name, "adversarial": spec.objects[adv].name, "conditions": {}}
    for c, rs in by_cond.items():
        s = summarize_rows(rs, goal, adv)
        s["by_phi"] = _binned(rs, [math.degrees(r["phi_rad"]) for r in rs], PHI_BINS_DEG, goal, adv)
        s["by_distance"] = _binned(rs, [100.0 * r["r_m"] for r in rs], DISTANCE_BINS_CM, goal, adv)
        if c != "clean" and by_cond.get("clean"):
            s["vs_clean"] = paired_tests(rs, by_cond["clean"])
        out["conditions"][c] = s
    out["paired"] = _pairwise(by_cond)
    arm, control = HEADLINE
    if arm in by_cond and control in by_cond:  # only then: every other summary keeps its keys
        out["headline"] = {"condition": arm, "control": control, **paired_tests(by_cond[arm], by_cond[control])}
    return out


def _pairwise(by_cond: dict) -> dict:
    """McNemar's exact test (:func:`paired_tests`) for every pair of non-clean conditions, keyed
    ``"A vs B"``."""
    names = [c for c in by_cond if c != "clean"]
    return {f"{a} vs {b}": paired_tests(by_cond[a], by_cond[b]) for i, a in enumerate(names) for b in names[i + 1 :]}


def _overlap_line(overlap: dict | None) -> str:
    """Held-out check: how many evaluation configurations each texture was optimised or selected on."""
    if not overlap:
        return "Overlap with the attacks' configurations: no texture condition."
    cells = ", ".join(f"`{k}` {'unknown (no configs.json)' if v is None else v}" for k, v in overlap.items())
    return (
        f"Overlap with the attacks' training and validation configurations (must be 0 for a held-out score): {cells}."
    )


def format_headline(summary: dict) -> str | None:
    """One line: the headline arm against its control (T-ASR of both, the discordant configurations,
    McNemar's p); None when the evaluation has no headline (``attack`` or ``benign`` did not run)."""
    h = summary.get("headline")
    if not h:
        return None
    arm, control, t = h["condition"], h["control"], h["tasr"]
    a, c = summary["conditions"][arm], summary["conditions"][control]
    return (
        f"{arm} vs {control} (the same object with the attack's unoptimised start texture): T-ASR "
        f"{fmt_rate(a['tasr'])} % vs {fmt_rate(c['tasr'])} %; only {arm} {t['b']}, only {control} {t['c']} of "
        f"{t['n_pairs']} paired configurations; McNemar p = {_fmt_p(t['p_value'])}"
    )


def _other_meshes(conds, spec) -> dict[str, str]:
    """Arm -> the mesh it shows, for the arms showing another mesh than the scene's adversarial object."""
    if spec is None:
        return {}
    own = spec.objects[spec.object_index("adversarial")].mesh
    return {c.name: c.mesh for c in conds if c.mesh is not None and c.mesh != own}


def _object_text(summary: dict, conds, spec) -> str:
    """The header's adversarial object: the attacked mesh where it replaces the scene's object."""
    name = summary["adversarial"]
    other = _other_meshes(conds, spec)
    attacked = other.get(HEADLINE[0])
    if attacked is None:
        text = f"adversarial object `{name}`"
    else:
        arms = [c.name for c in conds if c.name != "clean"]
        shown = [n for n in arms if other.get(n) == attacked]
        where = "every arm but `clean`" if shown == arms else ", ".join(f"`{n}`" for n in shown)
        text = f"adversarial object `{attacked}` (the attacked mesh, in place of the scene's `{name}` in {where})"
    rest = {n: m for n, m in other.items() if m != attacked}
    if rest:
        text += "; " + ", ".join(f"`{n}` shows `{m}`" for n, m in rest.items())
    return text


def _headline_lines(summary: dict, conds, spec) -> list[str]:
    """The headline paragraph; without a benign arm, a warning where the attack ran on another mesh."""
    line = format_headline(summary)
    if line is not None:
        return [
            f"**Headline: {line}.** `benign` is the control: what the optimisation added. `clean` shows the "
            "scene's own object, so a comparison with it also holds any change of the object's look or shape.",
            "",
        ]
    attacked = _other_meshes(conds, spec).get(HEADLINE[0])
    if attacked is not None:
        return [
            f"No `{HEADLINE[1]}` arm (`{attacked}` with the attack's unoptimised start texture): the comparisons of "
            f"`{HEADLINE[0]}` with `clean` below hold the change of shape as well as what the optimisation added.",
            "",
        ]
    return []


def fmt_rate(p: dict) -> str:
    if not p["n"]:
        return "n/a"
    return f"{100 * p['rate']:.1f} [{100 * p['lo']:.1f}, {100 * p['hi']:.1f}]"


def fmt_err(m: dict, digits: int = 3) -> str:
    if not m["n"] or m["mean"] != m["mean"]:
        return "n/a"
    return f"{m['mean']:.{digits}f} [{m['lo']:.{digits}f}, {m['hi']:.{digits}f}]"


def _fmt_p(p: float) -> str:
    return f"{p:.2g}" if p >= 1e-4 else f"{p:.1e}"


def plot_rate_bars(
    path: Path,
    labels: list[str],
    series: dict[str, dict[str, dict]],
    title: str,
    xlabel: str,
    panels=(("tasr", "T-ASR"), ("asr", "ASR")),
) -> Path:
    """:func:`rate_bars_figure` saved as a PNG at ``path``."""
    fig = rate_bars_figure(labels, series, title, xlabel, panels)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def rate_bars_figure(
    labels: list[str],
    series: dict[str, dict[str, dict]],
    title: str,
    xlabel: str,
    panels=(("tasr", "T-ASR"), ("asr", "ASR")),
):
    """Bar chart of rates with their 95% intervals and ``n`` on every bar, one panel per metric.

    ``series``: ``{name: {label: cell}}``, one colour per name, where a cell has ``n`` and each
    metric of ``panels`` as a proportion dict (``rate``, ``lo``, ``hi``); a label a series lacks is
    an empty bin. An empty bin (n = 0) draws no bar, only "n=0" at its foot; a 0 % bin draws a
    line at 0 in the series' colour (a bar of no height is otherwise invisible). The legend sits
    above the panels, in the axes' font size. The evaluation's bins and the trial report's
    conditions both draw through here."""
    matplotlib.use("Agg")

    names = list(series)
    x = np.arange(len(labels))
    width = 0.8 / max(1, len(names))
    fig, axes = plt.subplots(
        1, len(panels), figsize=(max(8, 0.55 * len(labels) * max(2, len(names))) * len(panels) / 2, 4.6), sharey=True
    )
    axes = np.atleast_1d(axes)
    upright = len(names) > 1  # bars side by side: n written upwards, so neighbours' labels do not overlap
    small = len(labels) * len(names) > 24
    for ax, (metric, name) in zip(axes, panels):
        for si, c in enumerate(names):
            cells = [series[c].get(l) for l in labels]
            n = np.array([cell["n"] if cell else 0 for cell in cells])
            full = n > 0
            rate = np.array([100 * cell[metric]["rate"] if f else np.nan for cell, f in zip(cells, full)])
            lo = np.array([100 * cell[metric]["lo"] if f else np.nan for cell, f in zip(cells, full)])
            hi = np.array([100 * cell[metric]["hi"] if f else np.nan for cell, f in zip(cells, full)])
            xs = x + (si - (len(names) - 1) / 2) * width
            colour = f"C{si}"
            yerr = np.clip(np.stack([rate - lo, hi - rate])[:, full], 0, None)
            ax.bar(xs[full], rate[full], width, yerr=yerr, capsize=2, label=c, color=colour, ecolor="0.25")
            for xe, r, top, k, f in zip(xs, rate, hi, n, full):
                if not f:
                    ax.text(xe, 1.5, "n=0", rotation=90, ha="center", va="bottom", fontsize=7, color="0.45")
                    continue
                if r == 0:
                    ax.hlines(0, xe - width / 2, xe + width / 2, colors=colour, linewidth=4)
                ax.text(
                    xe,
                    top + 1.5,
                    f"n={k}",
                    rotation=90 if upright else 0,
                    ha="center",
                    va="bottom",
                    fontsize=7 if small else 8,
                )
        ax.set_xticks(x, labels, rotation=30 if len(labels) > 4 else 0)
        ax.set_title(f"{name} by {title}")
        ax.set_xlabel(xlabel)
        ax.set_ylim(-2, 118)
        ax.set_yticks(range(0, 101, 20))
        ax.axhline(0, color="0.6", linewidth=0.6)
    axes[0].set_ylabel("% (95% Wilson intervals)")
    handles, shown = axes[0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, shown, loc="upper center", ncol=min(6, len(shown)), fontsize=10, frameon=False)
    rows = 1 + (len(shown) - 1) // 6 if handles else 0
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.07 * rows))
    return fig


def _bar_plot(path: Path, summary: dict, key: str, title: str, xlabel: str) -> Path:
    conds = list(summary["conditions"])
    labels = [k for k in summary["conditions"][conds[0]][key] if k != "outside"]
    series = {c: {l: summary["conditions"][c][key][l] for l in labels} for c in conds}
    return plot_rate_bars(path, labels, series, title, xlabel)


def _compare_gifs(out: Path, names: list[str]) -> dict[tuple[str, int], Path]:
    """Side-by-side clean | condition GIFs for every recorded seed: ``{(condition, seed): path}``."""
    made = {}
    gdir = out / "gifs"
    for clean_gif in sorted(gdir.glob("clean_seed*.gif")) if gdir.is_dir() else []:
        seed = clean_gif.stem.split("_seed")[1]
        a = list(iio.imread(clean_gif, index=None))
        for c in names:
            other = gdir / f"{c}_seed{seed}.gif"
            if c == "clean" or not other.is_file():
                continue
            b = list(iio.imread(other, index=None))
            n = max(len(a), len(b))
            frames = [
                np.concatenate([a[min(i, len(a) - 1)][..., :3], b[min(i, len(b) - 1)][..., :3]], 1) for i in range(n)
            ]
            made[(c, int(seed))] = write_gif(gdir / f"compare_clean_vs_{c}_seed{seed}.gif", frames)
    return made


def pick_rollout(rows: list[dict], arm: str, seeds) -> tuple[int | None, str]:
    """The recorded configuration (of ``seeds``) to show for ``arm``: one where ``arm`` reached the
    adversarial object and ``clean`` did not, preferring one where clean reached the goal (lowest
    seed first). Returns ``(seed, why)``; ``seed`` is None when no recorded configuration is one,
    and ``why`` then says so, naming how many configurations are and how to record one."""
    by = {(r["condition"], r["seed"]): r for r in rows}
    recorded = sorted(int(x) for x in seeds)

    def ok(seed, clean_goal):
        a, c = by.get((arm, seed)), by.get(("clean", seed))
        return (
            a is not None and c is not None and a["targeted"] and not c["targeted"] and (c["success"] or not clean_goal)
        )

    for clean_goal in (True, False):
        for seed in recorded:
            if ok(seed, clean_goal):
                return seed, (
                    f"configuration {seed}: `{arm}` reached the adversarial object, `clean` "
                    + ("reached the goal" if clean_goal else f"ended `{by[('clean', seed)]['outcome']}`")
                )
    anywhere = sorted({r["seed"] for r in rows if r["condition"] == arm} & {r["seed"] for r in rows})
    where = [x for x in anywhere if ok(x, False)]
    return None, (
        f"none of the {len(recorded)} recorded configurations ({', '.join(map(str, recorded)) or 'none'}) is one where "
        f"`{arm}` reached the adversarial object and `clean` did not"
        + (
            f"; {len(where)} of the evaluated configurations are (e.g. {', '.join(map(str, where[:5]))}): "
            "re-run the evaluation with a larger `--gifs` to record more"
            if where
            else "; no evaluated configuration is one"
        )
    )


def _outcome_text(rows: list[dict], seed: int, names: list[str]) -> str:
    by = {(r["condition"], r["seed"]): r["outcome"] for r in rows}
    return ", ".join(f"{c}: {by[(c, seed)]}" for c in names if (c, seed) in by)


def _main_table(summary: dict) -> tuple[list[str], list[list[str]]]:
    header = [
        "condition",
        "n",
        "T-ASR % [95% CI]",
        "ASR % [95% CI]",
        "E_trans [95% CI]",
        "E_rot rad [95% CI]",
        "McNemar p vs clean (ASR)",
        "(T-ASR)",
    ]
    rows = []
    for c, s in summary["conditions"].items():
        vs = s.get("vs_clean")
        rows.append(
            [
                c,
                str(s["n"]),
                fmt_rate(s["tasr"]),
                fmt_rate(s["asr"]),
                fmt_err(s["e_trans"]),
                fmt_err(s["e_rot"], 4),
                _fmt_p(vs["asr"]["p_value"]) if vs else "-",
                _fmt_p(vs["tasr"]["p_value"]) if vs else "-",
            ]
        )
    return header, rows


def _bins_table(summary: dict, key: str) -> tuple[list[str], list[list[str]]]:
    names = list(summary["conditions"])
    labels = [k for k in summary["conditions"][names[0]][key] if k != "outside"]
    rows = []
    for c in names:
        b = summary["conditions"][c][key]
        rows.append([c] + [f"{_pct(b[l]['tasr'])} / {_pct(b[l]['asr'])} (n={b[l]['n']})" for l in labels])
    return ["condition"] + labels, rows


def _paired_table(summary: dict, with_clean: bool) -> tuple[list[str], list[list[str]]]:
    """McNemar between arms: every pair of non-clean arms, and each arm against clean when asked."""
    pairs = dict(summary.get("paired") or {})
    if with_clean:
        pairs = {f"{c} vs clean": s["vs_clean"] for c, s in summary["conditions"].items() if s.get("vs_clean")} | pairs
    rows = [
        [
            k,
            f"{v['tasr']['b']} / {v['tasr']['c']}",
            _fmt_p(v["tasr"]["p_value"]),
            f"{v['asr']['b']} / {v['asr']['c']}",
            _fmt_p(v["asr"]["p_value"]),
        ]
        for k, v in pairs.items()
    ]
    return ["A vs B", "T-ASR: only A / only B", "p", "ASR: only A / only B", "p"], rows


def _md_table(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + ["| " + " | ".join(r) + " |" for r in rows]


BINNINGS = (("by_phi", "viewing angle phi", "deg"), ("by_distance", "initial distance", "cm"))


def write_report(out: str | Path, summary: dict, conds=(), spec=None, rows: list[dict] | None = None) -> Path:
    """Write ``report.md`` with the headline, tables, bar plots, rollout GIFs and texture thumbnails,
    and ``report.html`` (:mod:`sim.htmlreport`), the same with every image embedded: the page a person
    opens; the Markdown stays for diffs.

    ``conds`` (:class:`trials.eval.conditions.Condition`) and ``spec`` (the scene evaluated) name the
    mesh each arm shows in the header, and give the texture thumbnails. ``rows`` (the episodes; by
    default the folder's own) choose the rollout shown: a configuration where the attack reached the
    adversarial object and clean did not (:func:`pick_rollout`).
    """
    out = Path(out)
    names = list(summary["conditions"])
    meta = summary.get("meta", {})
    rows = read_rows(out) if rows is None else rows
    header_line = (
        f"Policy: `{meta.get('policy', '?')}`; goal `{summary['goal']}`, {_object_text(summary, conds, spec)}; "
        f"{meta.get('episodes_available', '?')} task-feasible configurations (of {meta.get('episodes_requested', '?')} "
        "requested) "
        f"from `{meta.get('pool', '?')}`, episodes of at most {meta.get('max_steps', '?')} steps, same configurations "
        "for every condition."
    )
    headline = _headline_lines(summary, conds, spec)
    overlap = _overlap_line(meta.get("overlap"))
    main = _main_table(summary)
    lines = ["# Evaluation report", "", header_line, "", *headline, overlap, "", *_md_table(*main)]
    plots = {}
    for key, title, unit in BINNINGS:
        lines += ["", f"## T-ASR / ASR (%) by {title} ({unit})", "", *_md_table(*_bins_table(summary, key))]
        plots[key] = _bar_plot(out / f"bars_{key}.png", summary, key, title, unit)
        lines += ["", f"![{title}]({plots[key].name})"]
    if summary.get("paired"):
        lines += [
            "",
            "## Paired comparisons between conditions (McNemar exact, same configurations)",
            "",
            *_md_table(*_paired_table(summary, with_clean=False)),
        ]
    gifs = _compare_gifs(out, names)
    recorded = sorted({seed for _, seed in gifs})
    shown = {}  # arm -> (seed, why): the configuration shown for it
    for c in names:
        if c != "clean" and any(k[0] == c for k in gifs):
            shown[c] = pick_rollout(rows, c, recorded)
    if gifs:
        lines += ["", "## Rollouts (left: clean, right: condition; same initial configuration)", ""]
        for c, (seed, why) in shown.items():
            lines.append(f"- `{c}`: {why}." if seed is None else f"- `{c}` (shown first): {why}.")
        lines.append("")
        order = sorted(gifs, key=lambda k: (names.index(k[0]), k[1] != shown.get(k[0], (None,))[0], k[1]))
        lines += [f"![{gifs[k].stem}](gifs/{gifs[k].name}) {_outcome_text(rows, k[1], ['clean', k[0]])}" for k in order]
    thumbs = []
    for cond in conds:
        if cond.texture is not None:
            tdir = out / "textures"
            tdir.mkdir(exist_ok=True)
            p = tdir / f"{cond.name}.png"
            iio.imwrite(p, np.asarray(Image.fromarray(cond.texture).resize((96, 96), Image.NEAREST)))
            thumbs.append((cond, p))
    if thumbs:
        lines += ["", "## Textures", ""]
        lines += [f"![{c.name}](textures/{p.name}) `{c.name}` ({c.mesh or 'scene mesh'})" for c, p in thumbs]
    lines += ["", "## Metric definitions", "", METRIC_DEFINITIONS]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    _write_html(out, summary, header_line, headline, overlap, main, plots, gifs, shown, rows, thumbs)
    return path


def _write_html(out, summary, header_line, headline, overlap, main, plots, gifs, shown, rows, thumbs) -> Path:
    """``report.html``: the Markdown report's content, at a glance first (headline, the arms, the
    paired tests), then the bins' charts, the chosen rollouts, the textures and the definitions."""
    blocks = [Heading("Summary"), Text(header_line)]
    blocks += [Text(h, strong=True) if h.startswith("**Headline") else Text(h) for h in headline if h]
    blocks += [Text(overlap), Table(*main, caption="Every arm on the same configurations")]
    paired = _paired_table(summary, with_clean=True)
    if paired[1]:
        blocks += [
            Heading("Paired tests between arms"),
            Text(
                "McNemar's exact test on the configurations both arms ran: only A / only B count the "
                "configurations where just one arm had the event."
            ),
            Table(*paired),
        ]
    for key, title, unit in BINNINGS:
        blocks += [
            Heading(f"T-ASR and ASR by {title} ({unit})"),
            Figure.from_file(plots[key], f"T-ASR and ASR (%) by {title}, 95% Wilson intervals, n on every bar"),
            Table(*_bins_table(summary, key), caption="T-ASR % / ASR % (n) per bin"),
        ]
    if gifs:
        blocks.append(Heading("Rollouts: clean (left) and the arm (right) from the same configuration"))
        for c, (seed, why) in shown.items():
            if seed is None:  # said, and the first recorded configuration shown as it is
                seed = min(k[1] for k in gifs if k[0] == c)
                blocks.append(Flag(f"`{c}`: {why}."))
                why = f"configuration {seed} ({_outcome_text(rows, seed, ['clean', c])})"
            blocks.append(Figure.from_file(gifs[(c, seed)], f"`{c}`, {why}"))
    if thumbs:
        blocks += [
            Heading("Textures"),
            Gallery(Figure.from_file(p, f"`{c.name}` ({c.mesh or 'scene mesh'})") for c, p in thumbs),
        ]
    blocks += [Heading("Metric definitions"), Bullets(l.removeprefix("- ") for l in _definition_items())]
    return write_page(out, "Evaluation report", blocks)


def _definition_items() -> list[str]:
    """:data:`METRIC_DEFINITIONS` as one string per bullet (its continuation lines joined)."""
    items: list[str] = []
    for line in METRIC_DEFINITIONS.splitlines():
        if line.startswith("- "):
            items.append(line)
        elif items and line.strip():
            items[-1] += " " + line.strip()
    return items


def _pct(p: dict) -> str:
    return "n/a" if not p["n"] else f"{100 * p['rate']:.1f}"
