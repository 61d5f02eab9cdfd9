"""The printable placement sheet of a trial plan: where objects go, where the TCP starts, the run order.

Pages (A4 portrait, matplotlib ``PdfPages``):

1. one page per object layout: a top view of the table frame (origin = the table-frame tag,
   +x / +y arrows, a 5 cm grid) with each object's footprint outline, role, base-centre xy in cm,
   yaw in degrees and a heading arrow along the object's +x axis. The adversarial footprint is
   drawn for every shape of the plan (and the 2D patch when the plan has the patch condition),
   since one layout is used with each of them;
2. one page of TCP start poses: translation in cm, axis-angle in degrees, and the table point
   the TCP's +z (approach) axis meets. A start given as joint positions is drawn at their TCP,
   forward kinematics on the scene's arm (:func:`start_poses`), and marked ``J``;
3. the run order: order, trial id, env, shape, condition, TCP pose, layout, tags and a checkbox.

The layout pages are diagrams with a 5 cm grid, not true-scale templates: measure from the tag
with a ruler or tape.
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle
from scipy.spatial import ConvexHull

from sim.assets import build_mesh
from sim.geometry import so3_log
from sim.spec import load_spec

__all__ = [
    "placement_sheet_pdf",
    "placement_outlines",
    "footprint_xy_m",
    "ROWS_PER_PAGE",
    "sheet_page_count",
    "start_poses",
    "tcp_page_rows",
]

A4_IN = (210.0 / 25.4, 297.0 / 25.4)
ROWS_PER_PAGE = 50
GRID_M = 0.05


def footprint_xy_m(mesh: str, scale=1.0, **mesh_kwargs) -> np.ndarray:
    """Convex outline ``(M, 2)`` m of a mesh seen from above, in its own frame (counter-clockwise).

    ``mesh_kwargs``: a mesh file's ``units``, ``up_axis`` and ``placement`` (the scene object's
    :meth:`~sim.spec.ObjectSpec.mesh_kwargs`), so the outline is the one the sim places."""
    xy = np.asarray(build_mesh(mesh, scale, **mesh_kwargs).vertices, dtype=np.float64)[:, :2]
    return xy[ConvexHull(xy).vertices]


def placement_outlines(plan, spec) -> dict[str, dict[str, np.ndarray]]:
    """``{role: {label: outline (M, 2) m}}`` of every object ``plan`` places on ``spec``'s table, in
    its own frame (:func:`footprint_xy_m`): the goal's (labelled by its name) and, for the
    adversarial role, each mesh a trial of the plan uses (:meth:`~trials.real.plan.TrialPlan.mesh_for`,
    by mesh name) at the scene's adversarial scale."""
    adv_meshes = list(plan.shapes) + (["patch"] if "patch" in plan.conditions else [])
    return {
        "goal": {spec.goal.name: footprint_xy_m(spec.goal.mesh, spec.goal.scale, **spec.goal.mesh_kwargs())},
        "adversarial": {
            # a shape that is an object of the scene: its own mesh and size (TrialPlan.shape_object)
            m: footprint_xy_m(o.mesh, o.scale, **o.mesh_kwargs())
            if (o := getattr(plan.shape_object(m), "object", None)) is not None
            else footprint_xy_m(
                m, spec.adversarial.scale, **(spec.adversarial.mesh_kwargs() if m == spec.adversarial.mesh else {})
            )
            for m in adv_meshes
        },
    }


def sheet_page_count(plan) -> int:
    """Pages :func:`placement_sheet_pdf` writes for ``plan``."""
    return len(plan.object_layouts) + 1 + math.ceil(len(plan.trials) / ROWS_PER_PAGE)


def _place(outline: np.ndarray, xy, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return outline @ np.array([[c, s], [-s, c]]) + np.asarray(xy)


def _layout_page(pdf, plan, layout, outlines: dict) -> None:
    fig = Figure(figsize=A4_IN)
    fig.suptitle(f"Object layout o{layout.index}  (plan seed {plan.seed})", fontsize=13, y=0.97)
    ax = fig.add_axes((0.1, 0.36, 0.82, 0.56))
    ax.set_aspect("equal")
    pts = [np.asarray(p.xy_m) for p in layout.objects.values()] + [np.zeros(2)]
    lo = np.min(pts, axis=0) - 0.15
    hi = np.max(pts, axis=0) + 0.15
    lo, hi = np.floor(lo / GRID_M) * GRID_M, np.ceil(hi / GRID_M) * GRID_M
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ticks_x = np.arange(lo[0], hi[0] + 1e-9, GRID_M)
    ticks_y = np.arange(lo[1], hi[1] + 1e-9, GRID_M)
    ax.set_xticks(ticks_x, [f"{100 * v:.0f}" for v in ticks_x], fontsize=7)
    ax.set_yticks(ticks_y, [f"{100 * v:.0f}" for v in ticks_y], fontsize=7)
    ax.grid(True, color="0.85", linewidth=0.6)
    ax.set_xlabel("table x (cm)")
    ax.set_ylabel("table y (cm)")
    # the table frame: origin tag and axes
    ax.add_patch(_square((0.0, 0.0), 0.03, facecolor="black", alpha=0.8))
    ax.annotate("", xy=(0.1, 0.0), xytext=(0.0, 0.0), arrowprops=dict(arrowstyle="-|>", color="red", lw=2))
    ax.annotate("", xy=(0.0, 0.1), xytext=(0.0, 0.0), arrowprops=dict(arrowstyle="-|>", color="green", lw=2))
    ax.text(0.105, 0.0, "+x", color="red", va="center", fontsize=9)
    ax.text(0.0, 0.105, "+y", color="green", ha="center", fontsize=9)
    ax.text(0.012, -0.03, "origin tag", fontsize=8, va="top")
    styles = {"goal": dict(color="tab:blue", lw=2.0)}
    dashes = ["-", "--", ":", "-."]
    lines = []
    for role in ("goal", "adversarial"):
        p = layout.objects[role]
        for i, (label, outline) in enumerate(outlines[role].items()):
            poly = _place(outline, p.xy_m, p.yaw_rad)
            style = styles.get(role, dict(color="tab:red", lw=1.6))
            ax.fill(poly[:, 0], poly[:, 1], facecolor=style["color"], alpha=0.08 if i else 0.15, edgecolor="none")
            ax.plot(
                *np.vstack([poly, poly[:1]]).T, linestyle=dashes[i % len(dashes)], label=f"{role}: {label}", **style
            )
        head = np.asarray(p.xy_m) + 0.06 * np.array([math.cos(p.yaw_rad), math.sin(p.yaw_rad)])
        ax.annotate("", xy=head, xytext=p.xy_m, arrowprops=dict(arrowstyle="-|>", color="black", lw=1.2))
        ax.plot(*p.xy_m, marker="+", color="black", markersize=10)
        text = f"{role}\nx {100 * p.xy_m[0]:.1f} cm\ny {100 * p.xy_m[1]:.1f} cm\nyaw {math.degrees(p.yaw_rad):.0f}°"
        ax.text(
            p.xy_m[0] + 0.045,
            p.xy_m[1] + 0.045,
            text,
            fontsize=8,
            va="bottom",
            bbox=dict(facecolor="white", alpha=0.8, edgecolor="0.6"),
        )
        lines.append(
            f"{role:<12} x = {100 * p.xy_m[0]:7.1f} cm   y = {100 * p.xy_m[1]:7.1f} cm   yaw = "
            f"{math.degrees(p.yaw_rad):7.1f}°"
        )
    ax.legend(loc="lower left", fontsize=7, framealpha=0.9)
    notes = [
        "Table frame: origin at the table-frame tag, z up.",
        "Positions are base centres; yaw is about +z from the table +x axis;",
        "the arrow shows the object's +x axis (heading).",
        f"Placement tolerance: {100 * plan.placement_tolerance_m:.1f} cm, "
        f"{math.degrees(plan.placement_tolerance_rad):.1f}°.",
        "",
        *lines,
        "",
        "Trials using this layout: " + str(sum(t.object_layout == layout.index for t in plan.trials)),
    ]
    fig.text(0.08, 0.29, "\n".join(notes), fontsize=9, family="monospace", va="top")
    pdf.savefig(fig)


def _square(center, side, **kw):
    return Rectangle((center[0] - side / 2, center[1] - side / 2), side, side, **kw)


def start_poses(plan, spec) -> dict[int, np.ndarray | None]:
    """``{tcp_poses index: T_table_tcp (4, 4)}``: where each start of ``plan`` puts the TCP, in the
    table frame, as the session takes it.

    A start given as a TCP pose only is that pose. A start given as ``joint_positions`` is their
    forward kinematics on ``spec``'s arm, its base where the scene places it
    (:func:`trials.real.runner.resolve_starts`, which also checks their number, their limits and,
    with a TCP pose given too, that the two agree). A joints-only start needs that arm: on a scene
    without one it raises :class:`trials.real.runner.StartError` in one line naming the start and a
    trial using it; one no trial uses is ``None`` (the sheet lists its joints). With no arm, a start
    given both ways is drawn at its TCP pose (the session's arm checks the joints).
    """
    given = {tp.index: None if tp.T_table_tcp is None else tp.T_table_tcp.T() for tp in plan.tcp_poses}
    if all(tp.joint_positions is None for tp in plan.tcp_poses):
        return given
    from trials.real.runner import StartError, resolve_starts  # lazy: optional dependency (torch, for joint starts)

    if spec.arm is None:
        for tp in plan.tcp_poses:
            users = [t.trial_id for t in plan.trials if t.tcp_pose == tp.index]
            if given[tp.index] is None and users:
                more = f" and {len(users) - 1} more" if len(users) > 1 else ""
                raise StartError(
                    f"trial plan: tcp_poses.{tp.index} (trial {users[0]}{more}): a start given as joint_positions "
                    f"only, and scene {spec.name!r} has no arm (arm: urdf, base_link, tool_link) whose forward "
                    "kinematics would place its TCP; give its T_table_tcp too, or plan on the scene of the arm"
                )
        return given
    starts = resolve_starts(plan, plan.trials, np.eye(4), spec.arm.scene_arm(), joint_space=False)
    return {k: starts[k].T_base_tcp if k in starts else T for k, T in given.items()}


def tcp_page_rows(plan, poses: dict) -> list[str]:
    """The text of the TCP start page: one row per start of ``plan`` at its pose ``poses[index]``
    (:func:`start_poses`; cm and degrees), the point the approach axis meets the table, a ``J`` for
    a start given as joints; then the notes and the trials per start."""
    rows = ["pose   x (cm)   y (cm)   z (cm)    rotvec (deg)                 approach axis meets table at (cm)", ""]
    for tcp in plan.tcp_poses:
        mark = "J" if tcp.joint_positions is not None else " "
        T = poses[tcp.index]
        if T is None:
            q = ", ".join(f"{v:.3f}" for v in tcp.joint_positions)
            rows.append(f"t{tcp.index:<4}{mark} joints [{q}] (no trial starts here)")
            continue
        p, z = T[:3, 3], T[:3, 2]
        hit = "(points upward)"
        if z[2] < -1e-9:
            s = -p[2] / z[2]
            hit = f"({100 * (p[0] + s * z[0]):6.1f}, {100 * (p[1] + s * z[1]):6.1f})"
        given = tcp.T_table_tcp is not None and tcp.joint_positions is None
        rv = np.degrees(tcp.T_table_tcp.rotvec_rad if given else so3_log(T[:3, :3]))
        rows.append(
            f"t{tcp.index:<4}{mark} {100 * p[0]:7.1f}  {100 * p[1]:7.1f}  {100 * p[2]:7.1f}    "
            f"({rv[0]:7.1f}, {rv[1]:7.1f}, {rv[2]:7.1f})    {hit}"
        )
    rows += [
        "",
        "T_table_tcp: TCP pose in the table frame (translation + axis-angle); the runner drives the arm there",
        "through the hand-eye and table calibration. Trials per pose: "
        + ", ".join(f"t{tcp.index}: {sum(t.tcp_pose == tcp.index for t in plan.trials)}" for tcp in plan.tcp_poses),
    ]
    if any(tcp.joint_positions is not None for tcp in plan.tcp_poses):
        rows.append(
            "J: a start given as joint positions; the arm moves in joint space to them, and the TCP shown is "
            "their forward kinematics on the scene's arm."
        )
    return rows


def _tcp_page(pdf, plan, poses: dict) -> None:
    fig = Figure(figsize=A4_IN)
    fig.suptitle(f"Initial TCP poses  (plan seed {plan.seed})", fontsize=13, y=0.97)
    fig.text(0.06, 0.92, "\n".join(tcp_page_rows(plan, poses)), fontsize=8, family="monospace", va="top")
    pdf.savefig(fig)


def _order_pages(pdf, plan) -> None:
    n_pages = math.ceil(len(plan.trials) / ROWS_PER_PAGE)
    head = (
        f"{'order':>5}  {'trial id':<34} {'env':<5} {'shape':<10} {'cond':<6} {'tcp':<4} {'layout':<6} "
        f"{'tags':<16} done"
    )
    for page in range(n_pages):
        fig = Figure(figsize=A4_IN)
        fig.suptitle(f"Run order  (page {page + 1}/{n_pages}, {len(plan.trials)} trials)", fontsize=13, y=0.97)
        rows = [head, "-" * len(head)]
        for t in plan.trials[page * ROWS_PER_PAGE : (page + 1) * ROWS_PER_PAGE]:
            rows.append(
                f"{t.order:>5}  {t.trial_id:<34} {t.env:<5} {t.shape:<10} {t.condition:<6} t{t.tcp_pose:<3} "
                f"o{t.object_layout:<5} {','.join(t.tags) or '-':<16} [  ]"
            )
        fig.text(0.04, 0.93, "\n".join(rows), fontsize=8, family="monospace", va="top", linespacing=1.5)
        pdf.savefig(fig)


def placement_sheet_pdf(plan, path, spec=None) -> int:
    """Write the placement sheet of ``plan`` to ``path``; returns the number of pages.

    ``spec``: the scene the plan was made for (default: ``plan.scene`` or the built-in scene); it
    gives the goal mesh and the adversarial object's scale for the footprints, and the arm that
    places a start given as joints (:func:`start_poses`).
    """
    matplotlib.use("Agg", force=False)

    spec = load_spec(plan.scene) if spec is None else spec
    poses = start_poses(plan, spec)  # a start it cannot place: refused before anything is written
    outlines = placement_outlines(plan, spec)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with PdfPages(path) as pdf:
        for layout in plan.object_layouts:
            _layout_page(pdf, plan, layout, outlines)
        _tcp_page(pdf, plan, poses)
        _order_pages(pdf, plan)
        n = pdf.get_pagecount()
    return n
