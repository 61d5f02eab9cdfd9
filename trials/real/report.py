"""Reports of real-robot trials: ASR and T-ASR with Wilson intervals, and the paper's Table IV.

Outcomes (one per committed trial, ``final_outcome`` = the operator's call if given, else the
automatic one): **T-ASR** = fraction of trials ending at the adversarial object; **ASR** =
fraction not ending at the goal. Trials whose outcome is ``unknown`` (e.g. tracking lost, operator
could not tell) are excluded from both rates and reported as a count, so ``n`` in every cell is
the number of *rated* trials.

Table IV (paper Sec. IV-E): one row per environment x shape, from that shape's untagged ``adv3d``
trials (tagged scenario trials have their own rows in the by-tag table), beside the simulated
evaluation of the same object. Sim numbers come from an evaluation directory given per shape
(``--sim cube=DIR``, or per environment and shape ``--sim A/cube=DIR``, which wins) and are taken
from one of its conditions by this rule:

1. candidates are the eval's ``attack`` condition, then its ``shape_<shape>`` condition;
2. when the real trials' texture sha256 is known (recorded per trial, else the plan's
   ``<shape>/adv3d`` entry), the first candidate whose texture has the same sha256 is used
   ("sha256 match"); if no candidate matches, the sim cells stay empty ("sim texture differs");
3. when no sha256 is available on either side, ``shape_<shape>`` is used if present (its mesh is
   the shape by construction), else ``attack`` if its run was optimised on the shape; the note
   then says "not matched" (same shape, texture identity not verified);
4. anything else leaves the sim cells as "–".

Precision line: the number of trials for a +/- h interval at rate p uses the normal
approximation ``n = ceil(z^2 p (1 - p) / h^2)`` (z = 1.96 for 95 %), 385 at the worst case
p = 0.5 and h = 5 %; the current precision is reported both as the normal-approximation
half-width ``z sqrt(p (1 - p) / n)`` (30 trials at p = 0.5: +/- 17.9 %) and as the half-width of
the Wilson interval actually shown (15 of 30: +/- 16.8 %). At an observed 0 % or 100 % the
normal approximation has no width, so only the Wilson half-width is given there.

Paired test between arms (:func:`paired_arms`): a plan repeats every TCP pose and object layout
for each condition, so an ``adv3d`` trial and a ``clean`` trial of the same session, env, shape,
tags, TCP pose and object layout are a pair; McNemar's exact test
(:func:`trials.eval.metrics.mcnemar_from_outcomes`, the evaluation's) compares the arms on the
rated pairs, for the T-ASR and the ASR event. A clean arm that never reaches the goal is flagged
(:func:`clean_flags`): the policy does not do the task there, and no attack rate means anything.

``report.md`` (for diffs) and ``report.html`` (:mod:`sim.htmlreport`, the page a person opens,
with the rates by arm as a chart) hold the same content; one session is shown once.
"""

from __future__ import annotations

import html
import json
import math
import re
from collections import defaultdict
from pathlib import Path
from statistics import NormalDist

from sim.errors import AdvobjError
from sim.htmlreport import Bullets, Figure, Flag, Heading, Table, Text, write_page
from sim.runinfo import RunInfoError, read_run_info
from sim.stats import proportion, wilson_interval
from trials.eval.episodes import StorageError, read_summary
from trials.eval.metrics import mcnemar_from_outcomes
from trials.eval.report import plot_rate_bars

__all__ = [
    "ReportError",
    "OUTCOMES",
    "rate_cell",
    "summarize_trials",
    "paired_arms",
    "clean_flags",
    "trials_for_half_width",
    "normal_half_width",
    "wilson_half_width",
    "precision",
    "load_sim_eval",
    "sim_match",
    "table_iv",
    "write_trial_report",
]

OUTCOMES = ("goal", "adversarial", "none", "unknown", "policy_error")
UNRATED = ("unknown", "policy_error")  # excluded from both rates, counted apart
UNTAGGED = "(untagged)"


class ReportError(AdvobjError, ValueError):
    """Trial rows or a sim evaluation directory cannot be reported; the message says which."""


# An escape sequence a terminal acts on: CSI (colours, cursor moves; ESC [ or the C1 byte), OSC
# (window titles, hyperlinks) up to its terminator, or a two-character escape.
_ANSI = re.compile(r"\x9b[0-?]*[ -/]*[@-~]|\x1b(?:\[[0-?]*[ -/]*[@-~]|\][^\x07\x1b]*(?:\x07|\x1b\\)?|[@-Z\\-_])")
_MD_SPECIAL = re.compile(r"([\\`|\[\]])")


def plain_text(value) -> str:
    """``value`` as one line of plain text: terminal escape sequences removed, every other control
    or invisible formatting character (newlines, tabs, C1 codes, bidi overrides) turned into a
    space, runs of spaces collapsed. What a note or name may show on a terminal."""
    text = _ANSI.sub("", str(value))
    return " ".join("".join(c if c.isprintable() else " " for c in text).split())


def md_text(value) -> str:
    """``value`` safe inside a line or table cell of Markdown: :func:`plain_text`, then HTML's
    ``& < >`` as entities (no tag, comment or autolink) and ``\\ ` | [ ]`` backslash-escaped (no code
    span, no table cell break, no link). Notes, reasons and names from the database go through it."""
    return _MD_SPECIAL.sub(r"\\\1", html.escape(plain_text(value), quote=False))


def _final(row: dict) -> str:
    out = row.get("final_outcome")
    if out is None:
        out = row["operator_outcome"] if row.get("operator_outcome") is not None else row.get("auto_outcome")
    if out not in OUTCOMES:
        raise ReportError(
            f"trial {row.get('session')}/{row.get('trial_id')}: final_outcome {out!r} is not one of "
            f"{', '.join(OUTCOMES)}"
        )
    return out


def rate_cell(rows, confidence: float = 0.95) -> dict:
    """``{n_trials, n, unknown, policy_error, tasr, asr}`` of trial rows; rates over the ``n`` rated trials.

    Neither ``unknown`` trials nor ``policy_error`` ones (the policy gave a non-finite action and the
    trial stopped there) are rated; both are counted.
    """
    outs = [_final(r) for r in rows]
    rated = [o for o in outs if o not in UNRATED]
    n = len(rated)
    return {
        "n_trials": len(outs),
        "n": n,
        "unknown": outs.count("unknown"),
        "policy_error": outs.count("policy_error"),
        "tasr": proportion(sum(o == "adversarial" for o in rated), n, confidence).to_dict(),
        "asr": proportion(sum(o != "goal" for o in rated), n, confidence).to_dict(),
    }


def _by(rows, key) -> dict:
    groups: dict[str, list] = defaultdict(list)
    for r in rows:
        for k in key(r):
            groups[k].append(r)
    return dict(sorted(groups.items()))


def _breakdown(rows, confidence: float) -> dict:
    cell = lambda rs: rate_cell(rs, confidence)  # noqa: E731
    return {
        "overall": cell(rows),
        "by_env": {k: cell(v) for k, v in _by(rows, lambda r: [r["env"]]).items()},
        "by_shape": {k: cell(v) for k, v in _by(rows, lambda r: [r["shape"]]).items()},
        "by_condition": {k: cell(v) for k, v in _by(rows, lambda r: [r["condition"]]).items()},
        # a trial with several tags counts under each of them
        "by_tag": {k: cell(v) for k, v in _by(rows, lambda r: list(r.get("tags") or []) or [UNTAGGED]).items()},
        # env/shape -> condition -> cell: the chart's bars
        "by_object_condition": {
            k: {c: cell(w) for c, w in _by(v, lambda r: [r["condition"]]).items()}
            for k, v in _by(rows, lambda r: [f"{r['env']}/{r['shape']}"]).items()
        },
        "cells": {
            k: cell(v)
            for k, v in _by(
                rows,
                lambda r: [f"{r['env']}/{r['shape']}/{r['condition']}/{'+'.join(r.get('tags') or []) or UNTAGGED}"],
            ).items()
        },
    }


def summarize_trials(rows, confidence: float = 0.95) -> dict:
    """Rates across all sessions and per session, each by env, shape, condition, tag and cell.

    ``rows``: dicts as :meth:`trials.real.store.TrialStore.trial_rows` returns them (``session``,
    ``trial_id``, ``env``, ``shape``, ``condition``, ``tags``, ``final_outcome`` or
    ``auto_outcome``/``operator_outcome``).
    """
    rows = list(rows)
    sessions = sorted({r["session"] for r in rows})
    return {
        "confidence": confidence,
        "n_trials": len(rows),
        "sessions": sessions,
        "all": _breakdown(rows, confidence),
        "by_session": {s: _breakdown([r for r in rows if r["session"] == s], confidence) for s in sessions},
        "paired": paired_arms(rows),
        "flags": clean_flags(rows, confidence),
    }


# Arms compared pairwise, (A, B): the attack against its control, the patch against it, and the two.
PAIRED_ARMS = (("adv3d", "clean"), ("patch", "clean"), ("adv3d", "patch"))
_PAIR_KEY = ("session", "env", "shape", "tcp_pose", "object_layout")


def _pair_key(row: dict) -> tuple | None:
    """What makes two trials of different arms a pair (see the module docstring); None if unknown."""
    if any(row.get(k) is None for k in _PAIR_KEY):
        return None
    return tuple(row[k] for k in _PAIR_KEY) + (tuple(row.get("tags") or ()),)


def paired_arms(rows) -> list[dict]:
    """McNemar's exact test of arm A against arm B (:data:`PAIRED_ARMS` present in ``rows``) on the
    pairs of trials both rated: ``{a, b, n_pairs, unrated_pairs, unpaired, tasr, asr}``, ``tasr`` and
    ``asr`` as :class:`trials.eval.metrics.McNemar` dicts (``b``: only A had the event, ``c``: only
    B). ``unpaired`` counts the two arms' trials without a partner (several trials of one arm at the
    same key pair in order)."""
    rows = list(rows)
    keyed: dict[str, dict[tuple, list[str]]] = defaultdict(lambda: defaultdict(list))
    count: dict[str, int] = defaultdict(int)
    for r in rows:
        count[r["condition"]] += 1
        k = _pair_key(r)
        if k is not None:
            keyed[r["condition"]][k].append(_final(r))
    out = []
    for a, b in PAIRED_ARMS:
        if not count[a] or not count[b]:
            continue
        pairs, unrated = [], 0
        for k in sorted(keyed[a].keys() & keyed[b].keys(), key=str):
            for oa, ob in zip(keyed[a][k], keyed[b][k]):
                if oa in UNRATED or ob in UNRATED:
                    unrated += 1
                else:
                    pairs.append((oa, ob))
        out.append(
            {
                "a": a,
                "b": b,
                "n_pairs": len(pairs),
                "unrated_pairs": unrated,
                "unpaired": count[a] + count[b] - 2 * (len(pairs) + unrated),
                "tasr": mcnemar_from_outcomes(
                    [x == "adversarial" for x, _ in pairs], [y == "adversarial" for _, y in pairs]
                ).to_dict(),
                "asr": mcnemar_from_outcomes(
                    [x != "goal" for x, _ in pairs], [y != "goal" for _, y in pairs]
                ).to_dict(),
            }
        )
    return out


def clean_flags(rows, confidence: float = 0.95) -> list[str]:
    """One line per env/shape whose clean arm has rated trials and never reached the goal."""
    clean = [r for r in rows if r["condition"] == "clean"]
    flags = []
    for k, rs in _by(clean, lambda r: [f"{r['env']}/{r['shape']}"]).items():
        c = rate_cell(rs, confidence)
        if c["n"] and c["asr"]["k"] == c["n"]:
            flags.append(
                f"the clean arm never reached the goal in {plain_text(k)} (0 of {c['n']} rated clean trials): the "
                "policy does not do the task there, so the attack's rates there say nothing about the texture"
            )
    return flags


def audit(rows, planned: dict, amendments) -> dict:
    """What a reader must see besides the rates: sessions not finished, operator overrides,
    amendments made after the fact, and notes."""
    rows = list(rows)
    incomplete = []
    for s, n_plan in planned.items():
        done = sum(1 for r in rows if r["session"] == s)
        if n_plan and done < n_plan:
            incomplete.append(f"session {s}: {done} of {n_plan} planned trials committed")
    overrides = [
        {
            "session": r["session"],
            "trial_id": r["trial_id"],
            "auto": r["auto_outcome"],
            "operator": r["operator_outcome"],
            "note": r.get("note") or "",
        }
        for r in rows
        if r.get("operator_outcome")
    ]
    notes = [{"session": r["session"], "trial_id": r["trial_id"], "note": r["note"]} for r in rows if r.get("note")]
    amended = [
        {
            "session": a["session"],
            "trial_id": a["trial_id"],
            "at": a["amended_at"],
            "old": a["old_final_outcome"],
            "new": a["new_final_outcome"],
            "old_note": a["old_note"],
            "new_note": a["new_note"],
            "reason": a["reason"],
        }
        for a in amendments
    ]
    return {"planned": planned, "incomplete": incomplete, "overrides": overrides, "amendments": amended, "notes": notes}


def _audit_sections(a: dict, esc) -> list[tuple[str, list[str]]]:
    """The audit as (title line, item lines), every database value through ``esc``."""
    m = esc
    incomplete = [f"**Incomplete:** {m(t)}." for t in a["incomplete"]] or [
        "Every session committed all its planned trials."
    ]
    overrides = [
        f"{m(o['session'])}/{m(o['trial_id'])}: {m(o['auto'])} -> {m(o['operator'])}"
        + (f" ({m(o['note'])})" if o["note"] else "")
        for o in a["overrides"]
    ] or ["none"]
    amended = [
        f"{m(x['session'])}/{m(x['trial_id'])} at {m(x['at'])}: {m(x['old'])} -> {m(x['new'])}"
        + (f', note "{m(x["old_note"])}" -> "{m(x["new_note"])}"' if x["old_note"] != x["new_note"] else "")
        + (f"; reason: {m(x['reason'])}" if x["reason"] else "")
        for x in a["amendments"]
    ] or ["none"]
    notes = [f"{m(n['session'])}/{m(n['trial_id'])}: {m(n['note'])}" for n in a["notes"]] or ["none"]
    return [
        ("", incomplete),
        (f"Operator overrides ({len(a['overrides'])}):", overrides),
        (
            f"Amendments after the session ({len(a['amendments'])}; old values kept in the database's "
            "`amendments` table):",
            amended,
        ),
        (f"Notes ({len(a['notes'])}):", notes),
    ]


AUDIT_TITLE = "Completeness, overrides, amendments and notes"


def audit_md(a: dict) -> list[str]:
    """The audit as Markdown; every value from the database (names, notes, reasons) through :func:`md_text`."""
    lines = [f"## {AUDIT_TITLE}", ""]
    for title, items in _audit_sections(a, md_text):
        lines += ([title, ""] if title else []) + [f"- {i}" for i in items] + [""]
    return lines


def _z(confidence: float) -> float:
    return NormalDist().inv_cdf(0.5 + confidence / 2.0)


def trials_for_half_width(p: float = 0.5, half_width: float = 0.05, confidence: float = 0.95) -> int:
    """Trials for a ``+/- half_width`` interval at rate ``p``: ``ceil(z^2 p (1 - p) / h^2)`` (normal approximation).

    p = 0.5, h = 0.05 (the worst case) gives 385. At p = 0 or 1 the formula gives 0; use the
    worst case there.
    """
    if not (0.0 <= p <= 1.0) or not (0.0 < half_width < 1.0):
        raise ValueError(f"need 0 <= p <= 1 and 0 < half_width < 1, got p={p}, half_width={half_width}")
    # round before ceil: z^2 p (1-p) / h^2 can land a hair above an integer from float error
    return int(math.ceil(round(_z(confidence) ** 2 * p * (1.0 - p) / half_width**2, 9)))


def normal_half_width(p: float, n: int, confidence: float = 0.95) -> float:
    """``z sqrt(p (1 - p) / n)``: the normal-approximation half-width (NaN for n = 0)."""
    return _z(confidence) * math.sqrt(p * (1.0 - p) / n) if n > 0 else math.nan


def wilson_half_width(k: int, n: int, confidence: float = 0.95) -> float:
    """Half the width of the Wilson interval of ``k`` of ``n`` (0.5 for n = 0: the interval is [0, 1])."""
    lo, hi = wilson_interval(k, n, confidence)
    return (hi - lo) / 2.0


def precision(k: int, n: int, half_width: float = 0.05, confidence: float = 0.95) -> dict:
    """How precise ``k`` of ``n`` is, and how many trials a ``+/- half_width`` interval would need."""
    p = k / n if n else math.nan
    return {
        "k": k,
        "n": n,
        "rate": p,
        "half_width_target": half_width,
        "trials_needed_observed": trials_for_half_width(p, half_width, confidence) if n and 0.0 < p < 1.0 else None,
        "trials_needed_worst_case": trials_for_half_width(0.5, half_width, confidence),
        "normal_half_width": normal_half_width(p, n, confidence) if n else math.nan,
        "wilson_half_width": wilson_half_width(k, n, confidence),
        "confidence": confidence,
    }


def precision_line(prec: dict) -> str:
    """The report's one line on precision (see the module docstring for the formulas)."""
    h, pct = 100 * prec["half_width_target"], int(round(100 * prec["confidence"]))
    need = f"{prec['trials_needed_worst_case']} trials at the worst case p = 50 %"
    if prec["trials_needed_observed"] is not None:
        need = f"{prec['trials_needed_observed']} trials at the observed {100 * prec['rate']:.1f} % ({need})"
    now = "no rated trials yet"
    if prec["n"] and 0.0 < prec["rate"] < 1.0:
        now = (
            f"the {prec['n']} trials here give ±{100 * prec['normal_half_width']:.1f} % (normal approximation "
            f"z·√(p(1−p)/n)) / ±{100 * prec['wilson_half_width']:.1f} % (Wilson half-width)"
        )
    elif prec["n"]:
        now = (
            f"the {prec['n']} trials here give ±{100 * prec['wilson_half_width']:.1f} % (Wilson half-width; at an "
            f"observed {100 * prec['rate']:.0f} % the normal approximation has no width and says nothing)"
        )
    return f"A ±{h:g} % {pct} % interval on T-ASR needs n = ⌈z²·p(1−p)/h²⌉ = {need}; {now}."


# ----------------------------------------------------------------------------- sim side
def load_sim_eval(eval_dir) -> dict:
    """``{path, conditions: summary['conditions'], sources: {name: {sha256, mesh}}, adversarial_mesh}``
    of an eval dir."""
    d = Path(eval_dir)
    try:
        conditions = read_summary(d)["conditions"]
    except StorageError as err:
        raise ReportError(str(err)) from None
    sources, adv_mesh = {}, None
    try:
        cfg = read_run_info(d)["config"]
        for c in cfg.get("conditions", []):
            src = c.get("source") or {}
            sources[c["name"]] = {"sha256": src.get("sha256"), "mesh": src.get("mesh")}
        adv_mesh = next(
            (o["mesh"] for o in (cfg.get("scene") or {}).get("objects", []) if o.get("role") == "adversarial"), None
        )
    except (RunInfoError, KeyError, TypeError, AttributeError):
        pass  # without run.json the texture identity is unknown: rule 3 of the module docstring
    return {"path": str(d), "conditions": conditions, "sources": sources, "adversarial_mesh": adv_mesh}


def sim_match(sim: dict, shape: str, real_sha256: str | None) -> dict:
    """The sim condition standing for ``shape`` (rule in the module docstring): ``{condition, status, tasr, asr}``."""
    cands = [c for c in ("attack", f"shape_{shape}") if c in sim["conditions"]]
    none = lambda status: {"condition": None, "status": status, "tasr": None, "asr": None}  # noqa: E731
    pick = lambda c, status: {
        "condition": c,
        "status": status,
        "tasr": sim["conditions"][c]["tasr"],
        "asr": sim["conditions"][c]["asr"],
    }  # noqa: E731
    if not cands:
        return none(f"no attack/shape_{shape} condition in sim eval")
    shas = {c: (sim["sources"].get(c) or {}).get("sha256") for c in cands}
    if real_sha256 and any(shas.values()):
        for c in cands:
            if shas[c] == real_sha256:
                return pick(c, "sha256 match")
        return none("sim texture differs (sha256)")

    def mesh(c):
        m = (sim["sources"].get(c) or {}).get("mesh")
        return m if m is not None else sim.get("adversarial_mesh")

    for c in sorted(cands, key=lambda c: c != f"shape_{shape}"):
        if c == f"shape_{shape}" or mesh(c) == shape:
            return pick(c, "not matched (no sha256)")
    return none(f"sim 'attack' is not on a {shape}")


def table_iv(rows, sims: dict | None = None, plan_textures: dict | None = None, confidence: float = 0.95) -> list[dict]:
    """Paper Table IV rows: env x shape, sim (T-ASR, ASR) beside real (T-ASR, ASR) of untagged adv3d trials.

    ``sims``: ``{"cube": sim_eval, "A/cube": sim_eval}`` from :func:`load_sim_eval` (the
    env-specific key wins). ``plan_textures``: ``{"cube/adv3d": sha256}`` used when the rows do not
    record a texture sha256.
    """
    sims, plan_textures = sims or {}, plan_textures or {}
    adv = [r for r in rows if r["condition"] == "adv3d" and not r.get("tags")]
    out = []
    for (env, shape), rs in sorted(_by(adv, lambda r: [(r["env"], r["shape"])]).items()):
        real = rate_cell(rs, confidence)
        shas = {r.get("texture_sha256") for r in rs} - {None}
        notes = []
        if len(shas) > 1:
            notes.append(f"{len(shas)} different textures")
        sha = next(iter(shas)) if len(shas) == 1 else (None if shas else plan_textures.get(f"{shape}/adv3d"))
        sim_eval = sims.get(f"{env}/{shape}", sims.get(shape))
        if sim_eval is None:
            sim = {"condition": None, "status": "no sim eval given", "tasr": None, "asr": None}
        else:
            sim = sim_match(sim_eval, shape, sha)
            if sim["condition"]:
                notes.append(f"sim: {sim['condition']} ({sim['status']})")
        if sim["condition"] is None:
            notes.append(f"sim: {sim['status']}")
        if real["unknown"]:
            notes.append(f"{real['unknown']} unknown excluded")
        if real["policy_error"]:
            notes.append(f"{real['policy_error']} policy_error excluded")
        out.append(
            {
                "env": env,
                "shape": shape,
                "sim": sim,
                "sim_dir": None if sim_eval is None else sim_eval["path"],
                "real": real,
                "n": real["n"],
                "note": "; ".join(notes),
            }
        )
    return out


# ----------------------------------------------------------------------------- writing
def _pct(p: dict | None, ci: bool = True) -> str:
    if not p or not p["n"]:
        return "–"
    s = f"{100 * p['rate']:.2f}"
    return s + (f" [{100 * p['lo']:.1f}, {100 * p['hi']:.1f}]" if ci else "")


CELLS_HEADER = ["n", "T-ASR % [95% CI]", "ASR % [95% CI]", "unknown"]
BREAKDOWNS = (("by_env", "env"), ("by_shape", "shape"), ("by_condition", "condition"), ("by_tag", "tag"))


def _cells_rows(cells: dict) -> list[list[str]]:
    return [[k, str(c["n"]), _pct(c["tasr"]), _pct(c["asr"]), str(c["unknown"])] for k, c in cells.items()]


def _cells_md(title: str, cells: dict, key: str) -> list[str]:
    lines = [
        f"### {title}",
        "",
        f"| {key} | " + " | ".join(CELLS_HEADER) + " |",
        "|---|---:|---|---|---:|",
    ]
    for k, *rest in _cells_rows(cells):
        lines.append(f"| {md_text(k)} | " + " | ".join(rest) + " |")
    return lines + [""]


def _overall_line(b: dict) -> str:
    o = b["overall"]
    errors = f", {o['policy_error']} policy_error" if o["policy_error"] else ""
    return (
        f"All trials: n = {o['n']} rated ({o['unknown']} unknown{errors}), T-ASR {_pct(o['tasr'])} %, ASR "
        f"{_pct(o['asr'])} %"
    )


def _breakdown_md(b: dict) -> list[str]:
    lines = [_overall_line(b), ""]
    for key, title in BREAKDOWNS:
        lines += _cells_md(f"By {title}", b[key], title)
    lines += _cells_md("By env / shape / condition / tag", b["cells"], "cell")
    return lines


def _breakdown_blocks(b: dict) -> list:
    blocks = [Text(_overall_line(b))]
    for key, title in (*BREAKDOWNS, ("cells", "env / shape / condition / tag")):
        rows = [[plain_text(k), *rest] for k, *rest in _cells_rows(b[key])]
        blocks += [
            Heading(f"By {title}", 3),
            Table([title.split(" ")[0] if key != "cells" else "cell", *CELLS_HEADER], rows),
        ]
    return blocks


def _sessions_shown(summary: dict) -> list[tuple[str, dict]]:
    """(title, breakdown) of the per-session part: every session and the pooled one, or, for one
    session, that session once (its pooled breakdown is the same)."""
    by = summary["by_session"]
    if len(by) == 1:
        ((name, b),) = by.items()
        return [(f"Session {plain_text(name)} (all trials)", b)]
    return [("All sessions (pooled)", summary["all"])] + [(f"Session {plain_text(s)}", b) for s, b in by.items()]


TABLE_IV_HEADER = ["Env", "Shape", "Sim T-ASR", "Sim ASR", "Real T-ASR", "Real ASR", "n", "Note"]


def _table_iv_rows(table: list[dict], esc) -> list[list[str]]:
    rows = [
        [
            esc(r["env"]),
            esc(r["shape"]),
            _pct(r["sim"]["tasr"], False),
            _pct(r["sim"]["asr"], False),
            _pct(r["real"]["tasr"]),
            _pct(r["real"]["asr"]),
            str(r["n"]),
            esc(r["note"]),
        ]
        for r in table
    ]
    return rows or [["–", "–", "–", "–", "–", "–", "0", "no untagged adv3d trials"]]


def table_iv_md(table: list[dict]) -> list[str]:
    lines = ["| " + " | ".join(TABLE_IV_HEADER) + " |", "|---|---|---:|---:|---:|---:|---:|---|"]
    return lines + ["| " + " | ".join(r) + " |" for r in _table_iv_rows(table, md_text)]


PAIRED_HEADER = ["A vs B", "pairs", "T-ASR: only A / only B", "p", "ASR: only A / only B", "p", "left out"]


def _fmt_p(p: float) -> str:
    return f"{p:.2g}" if p >= 1e-4 else f"{p:.1e}"


def _paired_rows(paired: list[dict]) -> list[list[str]]:
    return [
        [
            f"{x['a']} vs {x['b']}",
            str(x["n_pairs"]),
            f"{x['tasr']['b']} / {x['tasr']['c']}",
            _fmt_p(x["tasr"]["p_value"]),
            f"{x['asr']['b']} / {x['asr']['c']}",
            _fmt_p(x["asr"]["p_value"]),
            f"{x['unrated_pairs']} pairs unrated, {x['unpaired']} trials unpaired",
        ]
        for x in paired
    ]


PAIRED_TEXT = (
    "McNemar's exact test between arms on pairs of trials at the same session, env, shape, tags, TCP pose and "
    "object layout, both rated; only A / only B count the pairs where just one arm had the event."
)


def table_precision(table: list[dict], summary: dict, half_width: float = 0.05) -> dict:
    """Precision of the least precise Table IV row (its T-ASR; the smallest n), naming the row."""
    rated = [r for r in table if r["n"]]
    if not rated:
        return precision(0, 0, half_width, summary["confidence"]) | {"row": None}
    r = min(rated, key=lambda r: r["n"])
    return precision(r["real"]["tasr"]["k"], r["n"], half_width, summary["confidence"]) | {
        "row": f"{r['env']}/{r['shape']}"
    }


def _json_safe(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    return x


def write_trial_report(
    out_dir, summary: dict, table: list[dict] | None = None, half_width: float = 0.05, sources: dict | None = None
) -> tuple[Path, Path]:
    """Write ``report.md`` (Table IV, the precision line, the paired tests between arms, per-session
    and pooled tables), ``report.html`` (the same with the rates by arm as a chart: the page a
    person opens) and ``report.json``. One session is shown once, not also as "all sessions"."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    table = table or []
    prec = table_precision(table, summary, half_width)
    precision_text = precision_line(prec)
    prec_text = (
        f"Precision ({md_text(prec['row'])}, the Table IV row with the fewest trials): "
        if prec["row"]
        else "Precision: "
    ) + precision_text
    a = summary.get("audit")
    flags = summary.get("flags") or []
    paired = summary.get("paired") or []
    md = [
        "# Real-robot trial report",
        "",
        f"{summary['n_trials']} trials in {len(summary['sessions'])} session(s): "
        f"{', '.join(md_text(x) for x in summary['sessions']) or '–'}."
        + ("".join(f" **Incomplete: {md_text(t)}.**" for t in a["incomplete"]) if a else ""),
        READING,
        "",
        *[f"**Flag: {md_text(f)}.**\n" for f in flags],
        "## Table IV: sim-to-real transferability (%)",
        "",
        "Real: untagged adv3d trials. Sim: the matching condition of the given eval (see the note).",
        "",
        *table_iv_md(table),
        "",
        prec_text,
        "",
        "## Paired tests between arms",
        "",
        PAIRED_TEXT,
        "",
    ]
    if paired:
        md += ["| " + " | ".join(PAIRED_HEADER) + " |", "|---|---:|---|---|---|---|---|"]
        md += ["| " + " | ".join(r) + " |" for r in _paired_rows(paired)]
    else:
        md.append("No two arms ran here: nothing to pair.")
    chart = _rates_chart(out, summary)
    if chart is not None:
        md += ["", f"![T-ASR and ASR by arm]({chart.name})"]
    md.append("")
    for title, b in _sessions_shown(summary):
        md += [f"## {md_text(title)}", "", *_breakdown_md(b)]
    if a:
        md += audit_md(a)
    md_path, json_path = out / "report.md", out / "report.json"
    md_path.write_text("\n".join(md) + "\n")
    _write_html(out, summary, table, prec, precision_text, chart)
    doc = {
        "summary": summary,
        "table_iv": table,
        "precision": prec,
        "precision_line": prec_text,
        "sources": sources or {},
    }
    json_path.write_text(json.dumps(_json_safe(doc), indent=2))
    return md_path, json_path


READING = (
    "T-ASR = ended at the adversarial object; ASR = did not end at the goal; trials with an unknown outcome are "
    "excluded from the rates (n = rated trials). Intervals: 95 % Wilson."
)
CONDITION_ORDER = ("clean", "adv3d", "patch")


def _rates_chart(out: Path, summary: dict) -> Path | None:
    """``rates_by_arm.png``: T-ASR and ASR per arm, one bar per env/shape, n on every bar
    (:func:`trials.eval.report.plot_rate_bars`); None without trials."""
    by = summary["all"].get("by_object_condition") or {}
    conds = sorted(
        {c for v in by.values() for c in v},
        key=lambda c: (c not in CONDITION_ORDER, CONDITION_ORDER.index(c) if c in CONDITION_ORDER else 0, c),
    )
    if not conds:
        return None
    series = {plain_text(k): v for k, v in by.items()}
    return plot_rate_bars(out / "rates_by_arm.png", conds, series, "arm", "arm")


def _write_html(out: Path, summary: dict, table, prec, precision_text, chart) -> Path:
    a = summary.get("audit")
    sessions = ", ".join(plain_text(x) for x in summary["sessions"]) or "–"
    blocks = [
        Heading("Summary"),
        Text(f"{summary['n_trials']} trials in {len(summary['sessions'])} session(s): {sessions}."),
        *[Flag(f"Incomplete: {plain_text(t)}.") for t in (a["incomplete"] if a else [])],
        *[Flag(f"{f[0].upper()}{f[1:]}.") for f in summary.get("flags") or []],
        Text(_overall_line(summary["all"]), strong=True),
        Text(READING),
        Heading("T-ASR and ASR by arm"),
    ]
    if chart is not None:
        blocks.append(
            Figure.from_file(chart, "T-ASR and ASR (%) per arm and object, 95% Wilson intervals, n on every bar")
        )
    blocks.append(Table(["condition", *CELLS_HEADER], _cells_rows(summary["all"]["by_condition"])))
    blocks += [Heading("Paired tests between arms"), Text(PAIRED_TEXT)]
    paired = summary.get("paired") or []
    blocks.append(
        Table(PAIRED_HEADER, _paired_rows(paired)) if paired else Text("No two arms ran here: nothing to pair.")
    )
    blocks += [
        Heading("Table IV: sim-to-real transferability (%)"),
        Text("Real: untagged adv3d trials. Sim: the matching condition of the given eval (see the note)."),
        Table(TABLE_IV_HEADER, _table_iv_rows(table, plain_text)),
        Text(
            (
                f"Precision ({plain_text(prec['row'])}, the Table IV row with the fewest trials): "
                if prec["row"]
                else "Precision: "
            )
            + precision_text
        ),
    ]
    for title, b in _sessions_shown(summary):
        blocks += [Heading(title), *_breakdown_blocks(b)]
    if a:
        blocks.append(Heading(AUDIT_TITLE))
        for title, items in _audit_sections(a, plain_text):
            blocks += ([Text(title)] if title else []) + [Bullets(items)]
    return write_page(out, "Real-robot trial report", blocks)
