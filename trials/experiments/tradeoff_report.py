"""Tables, Pareto plot and machine block of a speed-vs-accuracy sweep (:mod:`trials.experiments.tradeoff`).

Everything is computed from ``<out>/rows.jsonl``, ``<out>/sweep.json`` and ``<out>/machine.json``,
so the report can be rebuilt at any time, also from a partial sweep.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt

__all__ = [
    "pareto_front",
    "attack_table",
    "deployment_table",
    "episodes_table",
    "machine_markdown",
    "plot_pareto",
    "write_report",
]


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats: cost (first) no higher and value (second) no
    lower, one of them strictly. Sorted by cost."""
    front = []
    for i, (c, v) in enumerate(points):
        dominated = any((c2 <= c and v2 >= v) and (c2 < c or v2 > v) for j, (c2, v2) in enumerate(points) if j != i)
        if not dominated:
            front.append(i)
    return sorted(front, key=lambda i: (points[i][0], -points[i][1]))


def _ok(rows, kinds) -> list[dict]:
    return [r for r in rows if r.get("status") == "ok" and r["kind"] in kinds]


def _order(rows: list[dict], knobs: tuple[str, ...]) -> list[dict]:
    """Rows by knob (in ``knobs`` order, unknown knobs last), then by value."""

    def key(r):
        try:
            v = (0, float(r["value"]), "")
        except ValueError:
            v = (1, 0.0, r["value"])
        return knobs.index(r["knob"]) if r["knob"] in knobs else len(knobs), v

    return sorted(rows, key=key)


def _rate(p: dict | None) -> str:
    if not p or not p.get("n"):
        return "n/a"
    return f"{100 * p['rate']:.0f} [{100 * p['lo']:.0f}, {100 * p['hi']:.0f}]"


def _mean(m: dict | None, d: int = 3) -> str:
    if not m or not m.get("n") or m["mean"] is None or m["mean"] != m["mean"]:
        return "n/a"
    return f"{m['mean']:.{d}f}"


def _num(x, d: int = 0) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{d}f}"


def _load(r: dict) -> str:
    a, b = r.get("load_start"), r.get("load_end")
    return "n/a" if not a or not b else f"{a[0]:.1f}->{b[0]:.1f}"


def attack_table(rows: list[dict], knobs: tuple[str, ...] = ()) -> str:
    """The main table: one line per attack/snapshot/episodes row (errors listed too)."""
    lines = [
        "| knob | value | policy px | attack wall s | attack CPU s | eval wall s | eval CPU s | peak MB | episodes | "
        "T-ASR % [95% CI] | ASR % [95% CI] | E_trans | E_rot | load 1-min | notes |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in _order([r for r in rows if r["kind"] != "deployment"], knobs):
        if r.get("status") != "ok":
            lines.append(f"| {r['knob']} | {r['value']} | | | | | | | | | | | | | failed: {r.get('error', '')} |")
            continue
        lines.append(
            f"| {r['knob']} | {r['value']} | {r.get('image_size', '')} | {_num(r.get('attack_wall_s'))} | "
            f"{_num(r.get('attack_cpu_s'))} | "
            f"{_num(r.get('eval_wall_s'))} | {_num(r.get('eval_cpu_s'))} | {_num(r.get('peak_rss_mb'))} | "
            f"{r.get('episodes', '')} | "
            f"{_rate(r.get('tasr'))} | {_rate(r.get('asr'))} | {_mean(r.get('e_trans'))} | {_mean(r.get('e_rot'), 4)} "
            f"| {_load(r)} | "
            f"{r.get('note', '')} |"
        )
    return "\n".join(lines) + "\n"


def episodes_table(rows: list[dict]) -> str:
    """Interval widths: the baseline texture on N episodes (and on the first ``episodes`` of that set)."""
    lines = [
        "| evaluation | episodes | T-ASR % [95% CI] | T-ASR CI width (pp) | ASR % [95% CI] | ASR CI width (pp) | "
        "E_trans [95% CI] | eval wall s | eval CPU s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]

    def width(p):
        return "n/a" if not p or not p.get("n") else f"{100 * (p['hi'] - p['lo']):.1f}"

    def ci(m):
        return "n/a" if not m or not m.get("n") else f"{m['mean']:.3f} [{m['lo']:.3f}, {m['hi']:.3f}]"

    base = [r for r in _ok(rows, ("attack",)) if r["knob"] == "baseline"]
    for r in base:
        lines.append(
            f"| baseline row (fixed set) | {r['episodes']} | {_rate(r['tasr'])} | {width(r['tasr'])} | "
            f"{_rate(r['asr'])} | "
            f"{width(r['asr'])} | {ci(r['e_trans'])} | {_num(r['eval_wall_s'])} | {_num(r['eval_cpu_s'])} |"
        )
    for r in _ok(rows, ("episodes",)):
        s = r.get("subset")
        if s:
            lines.append(
                f"| eval_episodes={r['value']}, first {s['episodes']} configs | {s['episodes']} | {_rate(s['tasr'])} "
                f"| {width(s['tasr'])} | "
                f"{_rate(s['asr'])} | {width(s['asr'])} | {ci(s['e_trans'])} | (inside the row below) | |"
            )
        lines.append(
            f"| eval_episodes={r['value']} | {r['episodes']} | {_rate(r['tasr'])} | {width(r['tasr'])} | "
            f"{_rate(r['asr'])} | "
            f"{width(r['asr'])} | {ci(r['e_trans'])} | {_num(r['eval_wall_s'])} | {_num(r['eval_cpu_s'])} |"
        )
    return "\n".join(lines) + "\n"


def deployment_table(rows: list[dict], knobs: tuple[str, ...] = ()) -> str:
    lines = [
        "| variant | wall ms/image, batch 1 (median, p90) | CPU ms/image, batch 1 (mean) | wall ms/image, batch 8 "
        "(median) | "
        "CPU ms/image, batch 8 (mean) | max abs action error vs torch fp32 | "
        "mean abs action error | clean success on the eval set [95% CI] | model KB | peak MB | load 1-min |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in _order([r for r in rows if r["kind"] == "deployment"], knobs):
        if r.get("status") != "ok":
            lines.append(f"| {r['value']} | failed: {r.get('error', '')} | | | | | | | | | |")
            continue
        lat = r["latency_ms"]
        cs = r.get("clean_success")
        succ = "n/a" if not cs else f"{cs['k']}/{cs['n']} = {_rate(cs)}"
        kb = "n/a" if r.get("model_bytes") is None else f"{r['model_bytes'] / 1024:.0f}"
        lines.append(
            f"| {r['value']} | {lat['b1']['median']:.2f} ({lat['b1']['p90']:.2f}) | "
            f"{_num(lat['b1'].get('cpu_mean'), 2)} | "
            f"{lat['b8']['median']:.2f} | {_num(lat['b8'].get('cpu_mean'), 2)} | "
            f"{r['action_err_max']:.2e} | {r['action_err_mean']:.2e} | {succ} | {kb} | {_num(r.get('peak_rss_mb'))} "
            f"| {_load(r)} |"
        )
    n = next((r["frames"] for r in rows if r["kind"] == "deployment" and r.get("status") == "ok"), None)
    if n:
        lines.append(
            f"\nAction errors over {n} frames the torch fp32 policy saw on clean rollouts of the evaluation set."
        )
    return "\n".join(lines) + "\n"


def machine_markdown(machine: dict) -> str:
    runs = machine.get("runs", [])
    if not runs:
        return "(no machine record)\n"
    s = runs[0]["start"]
    loads = [(r["start"]["loadavg"], r.get("end", {}).get("loadavg")) for r in runs]
    lines = [
        f"- CPU: {s['cpu_model']}; {s['cpu_count']} logical cores ({s['cpus_usable']} usable), "
        f"{s.get('mem_total_gb')} GB RAM",
        f"- torch {s['torch']} with {s['torch_threads']} intra-op thread(s) per row process; onnxruntime "
        f"{s['onnxruntime']} "
        f"(intra-op threads = the same); numpy {s['numpy']}; Python {s['python']}; {s['platform']}",
        "- load average (1, 5, 15 min) at start -> end of each sweep invocation: "
        + "; ".join(f"{_fmt_load(a)} -> {_fmt_load(b)}" for a, b in loads),
    ]
    return "\n".join(lines) + "\n"


def _fmt_load(x) -> str:
    return "n/a" if not x else "(" + ", ".join(f"{v:.2f}" for v in x) + ")"


_COST_LABEL = {
    "attack_wall_s": "attack wall time, s (log; shared 2-core CPU, see load in the table)",
    "attack_cpu_s": "attack process CPU time, s (log; all threads of the row's process)",
}


def plot_pareto(rows: list[dict], path: str | Path, cost: str = "attack_wall_s") -> Path:
    """T-ASR (Wilson error bars) against attack cost (``attack_wall_s`` or ``attack_cpu_s``); the
    Pareto front of the baseline policy's rows."""
    if cost not in _COST_LABEL:
        raise ValueError(f"cost: one of {sorted(_COST_LABEL)}, got {cost!r}")

    matplotlib.use("Agg")

    pts = [r for r in _ok(rows, ("attack", "snapshot")) if r.get(cost) is not None and r["tasr"].get("n")]
    same = [r for r in pts if r["policy"] == "ref"]
    other = [r for r in pts if r["policy"] != "ref"]
    front = [same[i] for i in pareto_front([(r[cost], r["tasr"]["rate"]) for r in same])]
    fig, ax = plt.subplots(figsize=(8, 5.5))

    def draw(rs, **kw):
        if not rs:
            return
        x = [r[cost] for r in rs]
        y = [100 * r["tasr"]["rate"] for r in rs]
        lo = [100 * (r["tasr"]["rate"] - r["tasr"]["lo"]) for r in rs]
        hi = [100 * (r["tasr"]["hi"] - r["tasr"]["rate"]) for r in rs]
        ax.errorbar(x, y, yerr=[lo, hi], fmt="none", ecolor=kw.pop("ecolor", "0.6"), elinewidth=1, capsize=2, zorder=1)
        ax.scatter(x, y, zorder=2, **kw)
        for r, xi, yi in zip(rs, x, y):
            ax.annotate(r["key"], (xi, yi), textcoords="offset points", xytext=(4, 3), fontsize=7)

    draw([r for r in same if r not in front], c="tab:blue", label="one knob changed (baseline policy)")
    draw(front, c="tab:red", ecolor="tab:red", marker="D", label="Pareto front (baseline policy)")
    if len(front) > 1:
        ax.step(
            [r[cost] for r in front],
            [100 * r["tasr"]["rate"] for r in front],
            where="post",
            c="tab:red",
            lw=1,
            alpha=0.6,
        )
    draw(other, c="tab:green", marker="s", label="policy resolution (other policy, own eval set)")
    ax.set_xscale("log")
    ax.set_xlabel(_COST_LABEL[cost])
    ax.set_ylabel("T-ASR, % (95% Wilson interval)")
    ax.set_title("Speed vs accuracy of the attack knobs")
    ax.grid(alpha=0.3, which="both")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8, loc="best")
    else:
        ax.text(0.5, 0.5, "no finished attack rows yet", transform=ax.transAxes, ha="center")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def write_report(
    out: str | Path, rows: list[dict], expected: list[str], knobs: tuple[str, ...], plot: str | Path | None = None
) -> Path:
    """``<out>/report.md`` (machine block, tables, rows not run) and the Pareto plots.

    ``rows``: the measured records (``rows.jsonl``); ``expected``: every row key the sweep's
    settings define, so the ones not measured are listed; ``knobs``: the table order. The sweep
    (:func:`trials.experiments.tradeoff.write_tradeoff_report`) gathers them: this module only renders.
    """
    out = Path(out)
    machine = json.loads((out / "machine.json").read_text()) if (out / "machine.json").is_file() else {}
    plot_path = plot_pareto(rows, plot or out / "tradeoff_pareto.png")
    # On a shared machine wall time mostly measures the neighbours; CPU time is the steadier cost.
    cpu_path = plot_pareto(rows, plot_path.with_name(plot_path.stem + "_cpu" + plot_path.suffix), cost="attack_cpu_s")
    have = {r["key"] for r in rows if r.get("status") == "ok"}
    missing = [k for k in expected if k not in have]
    text = [
        "## Machine",
        "",
        machine_markdown(machine),
        "## Attack knobs",
        "",
        attack_table(rows, knobs),
        "## Evaluation episodes",
        "",
        episodes_table(rows),
        "## Deployment",
        "",
        deployment_table(rows, knobs),
        f"Pareto plots: `{plot_path.name}` (attack wall time), `{cpu_path.name}` (attack CPU time).",
        "",
    ]
    if missing:
        text += [f"Rows not run (or failed): {', '.join(missing)}.", ""]
    path = out / "report.md"
    path.write_text("\n".join(text))
    return path
