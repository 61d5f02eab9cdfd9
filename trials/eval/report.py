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

from sim.imaging import write_gif
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


def _bar_plot(path: Path, summary: dict, key: str, title: str, xlabel: str) -> Path:
    matplotlib.use("Agg")

    conds = list(summary["conditions"])
    labels = [k for k in summary["conditions"][conds[0]][key] if k != "outside"]
    x = np.arange(len(labels))
    width = 0.8 / max(1, len(conds))
    fig, axes = plt.subplots(1, 2, figsize=(max(8, 1.2 * len(labels) * 2), 4.0), sharey=True)
    for ax, metric, name in zip(axes, ("tasr", "asr"), ("T-ASR", "ASR")):
        for ci, c in enumerate(conds):
            bins = summary["conditions"][c][key]
            rate = np.array([bins[l][metric]["rate"] if bins[l]["n"] else np.nan for l in labels]) * 100
            lo = np.array([bins[l][metric]["lo"] for l in labels]) * 100
            hi = np.array([bins[l][metric]["hi"] for l in labels]) * 100
            yerr = np.stack([np.nan_to_num(rate - lo), np.nan_to_num(hi - rate)])
            xs = x + (ci - (len(conds) - 1) / 2) * width
            full = ~np.isnan(rate)
            ax.bar(xs[full], rate[full], width, yerr=yerr[:, full], capsize=2, label=c, color=f"C{ci}")
            # An empty bin is not a 0% bin: no bar, a hatched outline and "n=0".
            for xe in xs[~full]:
                ax.bar(xe, 100, width, fill=False, hatch="//", edgecolor="0.7", linewidth=0.5)
                ax.text(xe, 50, "n=0", rotation=90, ha="center", va="center", fontsize=6, color="0.4")
        ax.set_xticks(x, labels, rotation=30)
        ax.set_title(f"{name} by {title}")
        ax.set_xlabel(xlabel)
        ax.set_ylim(0, 105)
    axes[0].set_ylabel("% (95% Wilson intervals)")
    # The legend goes below the axes: inside, it covers bars once a table has many conditions.
    handles, names = axes[0].get_legend_handles_labels()
    fig.legend(handles, names, loc="lower center", ncol=min(6, len(names)), fontsize=7, frameon=False)
    fig.tight_layout(rect=(0, 0.06 + 0.05 * ((len(names) - 1) // 6), 1, 1))
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _compare_gifs(out: Path, names: list[str]) -> list[Path]:
    """Side-by-side clean | condition GIFs for every recorded seed."""
    made = []
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
            made.append(write_gif(gdir / f"compare_clean_vs_{c}_seed{seed}.gif", frames))
    return made


def write_report(out: str | Path, summary: dict, conds=(), spec=None) -> Path:
    """Write ``report.md`` with the headline, tables, bar plots, rollout GIFs and texture thumbnails.

    ``conds`` (:class:`trials.eval.conditions.Condition`) and ``spec`` (the scene evaluated) name the
    mesh each arm shows in the header, and give the texture thumbnails.
    """
    out = Path(out)
    names = list(summary["conditions"])
    meta = summary.get("meta", {})
    lines = [
        "# Evaluation report",
        "",
        f"Policy: `{meta.get('policy', '?')}`; goal `{summary['goal']}`, {_object_text(summary, conds, spec)}; "
        f"{meta.get('episodes_available', '?')} task-feasible configurations (of {meta.get('episodes_requested', '?')} "
        "requested) "
        f"from `{meta.get('pool', '?')}`, episodes of at most {meta.get('max_steps', '?')} steps, same configurations "
        "for every condition.",
        "",
        *_headline_lines(summary, conds, spec),
        _overlap_line(meta.get("overlap")),
        "",
        "| condition | n | T-ASR % [95% CI] | ASR % [95% CI] | E_trans [95% CI] | E_rot rad [95% CI] | McNemar p "
        "vs clean (ASR) | (T-ASR) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for c in names:
        s = summary["conditions"][c]
        vs = s.get("vs_clean")
        pa = _fmt_p(vs["asr"]["p_value"]) if vs else "-"
        pt = _fmt_p(vs["tasr"]["p_value"]) if vs else "-"
        lines.append(
            f"| {c} | {s['n']} | {fmt_rate(s['tasr'])} | {fmt_rate(s['asr'])} | {fmt_err(s['e_trans'])} | "
            f"{fmt_err(s['e_rot'], 4)} | {pa} | {pt} |"
        )
    for key, title, unit in (("by_phi", "viewing angle phi", "deg"), ("by_distance", "initial distance", "cm")):
        labels = [k for k in summary["conditions"][names[0]][key] if k != "outside"]
        lines += [
            "",
            f"## T-ASR / ASR (%) by {title} ({unit})",
            "",
            "| condition | " + " | ".join(labels) + " |",
            "|---|" + "---|" * len(labels),
        ]
        for c in names:
            b = summary["conditions"][c][key]
            cells = [f"{_pct(b[l]['tasr'])} / {_pct(b[l]['asr'])} (n={b[l]['n']})" for l in labels]
            lines.append(f"| {c} | " + " | ".join(cells) + " |")
        png = _bar_plot(out / f"bars_{key}.png", summary, key, title, unit)
        lines += ["", f"![{title}]({png.name})"]
    if summary.get("paired"):
        lines += [
            "",
            "## Paired comparisons between conditions (McNemar exact, same configurations)",
            "",
            "| A vs B | T-ASR: only A / only B | p | ASR: only A / only B | p |",
            "|---|---|---|---|---|",
        ]
        for k, v in summary["paired"].items():
            lines.append(
                f"| {k} | {v['tasr']['b']} / {v['tasr']['c']} | {_fmt_p(v['tasr']['p_value'])} | "
                f"{v['asr']['b']} / {v['asr']['c']} | {_fmt_p(v['asr']['p_value'])} |"
            )
    gifs = _compare_gifs(out, names)
    if gifs:
        lines += ["", "## Rollouts (left: clean, right: condition; same initial configuration)", ""]
        lines += [f"![{g.stem}](gifs/{g.name})" for g in gifs]
    thumbs = []
    for cond in conds:
        if cond.texture is not None:
            tdir = out / "textures"
            tdir.mkdir(exist_ok=True)
            p = tdir / f"{cond.name}.png"
            iio.imwrite(p, np.asarray(Image.fromarray(cond.texture).resize((96, 96), Image.NEAREST)))
            thumbs.append(f"![{cond.name}](textures/{p.name}) `{cond.name}` ({cond.mesh or 'scene mesh'})")
    if thumbs:
        lines += ["", "## Textures", ""] + thumbs
    lines += ["", "## Metric definitions", "", METRIC_DEFINITIONS]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def _pct(p: dict) -> str:
    return "n/a" if not p["n"] else f"{100 * p['rate']:.1f}"
