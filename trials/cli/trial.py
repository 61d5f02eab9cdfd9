"""``advobj trial``: plan real-robot trials, run them, export and report them (issue 8).

Heavy code is imported inside the command functions so ``advobj --help`` stays fast.
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from sim.runinfo import write_run_info
from trials.cli.options import key_values
from trials.real.store import DEFAULT_DB, StoreError, TrialStore

app = typer.Typer(no_args_is_help=True, help="Real-robot trials: plan, run, export, report.")


@app.command("plan")
def plan_command(
    out: Path = typer.Option(..., help="plan YAML to write"),
    scene: Optional[Path] = typer.Option(None, help="scene YAML (default: the built-in paper scene)"),
    seed: int = typer.Option(0, help="seed of the poses, layouts and the trial order"),
    env: List[str] = typer.Option(["A"], "--env", help="environment name (repeatable)"),
    shape: List[str] = typer.Option(
        ["cube", "cylinder"],
        "--shape",
        help="adversarial-object shape: an object's name in --scene (its mesh may be a file), or a built-in mesh "
        "(repeatable)",
    ),
    condition: List[str] = typer.Option(
        ["clean", "adv3d", "patch"], "--condition", help="clean, adv3d or patch (repeatable)"
    ),
    texture: List[str] = typer.Option(
        [],
        "--texture",
        help="SHAPE/adv3d=RUN_DIR or SHAPE/patch=RUN_DIR: attack run with the texture, optimised on that shape's "
        "mesh (repeatable)",
    ),
    tag: List[str] = typer.Option(
        [],
        "--tag",
        help="scenario tag, e.g. dim, bright, dynamic_lighting, occluded, moved_object; each adds a full "
        "block of trials",
    ),
    tcp_poses: int = typer.Option(5, "--tcp-poses", min=1, help="initial TCP poses"),
    object_poses: int = typer.Option(6, "--object-poses", min=1, help="object layouts"),
    pool: Optional[Path] = typer.Option(
        None, help="draw poses and layouts only from this (task-feasible) config pool JSON"
    ),
    sheet: Optional[Path] = typer.Option(None, help="also write the printable placement sheet PDF here"),
    force: bool = typer.Option(False, "--force", help="overwrite an existing plan at --out"),
    hardware: Optional[Path] = typer.Option(
        None, help="hardware YAML of the cell: start poses are drawn inside its safety workspace box"
    ),
    table_frame: Optional[Path] = typer.Option(
        None, "--table-frame", help="with --hardware: T_base_table YAML (default: base = table)"
    ),
) -> None:
    """Write the randomized real-trial plan (paper design: TCP poses x object layouts per env, shape, condition)."""
    import numpy as np  # lazy: CLI start-up (numpy)

    from trials.real.plan import PlanError  # lazy: CLI start-up (trimesh, PIL)

    # before any work: a session's trials are tied to its plan's sha256, a silent overwrite orphans them
    if out.is_dir():
        raise PlanError(f"--out: {out} is a directory; give the plan's file name (plan.yaml)")
    if out.exists() and not force:
        raise PlanError(
            f"--out: {out} exists; a plan is never overwritten (sessions are tied to its sha256): "
            "choose another file or pass --force"
        )
    if sheet is not None and sheet.is_dir():
        raise PlanError(f"--sheet: {sheet} is a directory; give the PDF's file name")
    from sim.configs import load_pool  # lazy: CLI start-up (trimesh, PIL)
    from sim.spec import load_spec  # lazy: CLI start-up (+22 ms)
    from trials.real.plan import (  # lazy: CLI start-up (trimesh, PIL)
        design_summary,
        make_plan,
        plan_sha256,
        save_plan,
        texture_ref,
    )

    spec = load_spec(scene)
    textures = {
        key: texture_ref(path, key, spec, None if scene is None else str(scene))
        for key, path in key_values(texture, "--texture").items()
    }
    workspace = None
    if table_frame is not None and hardware is None:
        raise PlanError("--table-frame: only with --hardware (it places the hardware's workspace box)")
    if hardware is not None:
        from robot_io.config import load_hardware_config  # lazy: CLI start-up (trimesh, PIL)
        from trials.real.session import load_T_base_table  # lazy: CLI start-up (torch, cv2)

        hw = load_hardware_config(hardware)
        workspace = (
            hw.safety.workspace_min_m,
            hw.safety.workspace_max_m,
            np.eye(4) if table_frame is None else load_T_base_table(table_frame),
        )
    plan = make_plan(
        spec,
        seed,
        env,
        shape,
        condition,
        textures,
        n_tcp_poses=tcp_poses,
        n_object_layouts=object_poses,
        tags=tag,
        pool=None if pool is None else load_pool(pool, spec),
        scene=None if scene is None else str(scene),
        workspace=workspace,
    )
    save_plan(plan, out)
    config = {
        "job": "trial-plan",
        "plan": str(out),
        "plan_sha256": plan_sha256(out),
        "pool": None if pool is None else str(pool),
        "sheet": None if sheet is None else str(sheet),
    }
    write_run_info(out.parent, config, seed, name=f"{out.stem}.run.json")
    typer.echo("\n".join(design_summary(plan)))
    typer.echo(f"wrote {out}")
    if sheet is not None:
        from trials.real.sheet import placement_sheet_pdf  # lazy: CLI start-up (matplotlib, trimesh)

        n_pages = placement_sheet_pdf(plan, sheet, spec)
        typer.echo(f"wrote {sheet} ({n_pages} pages; print at 100 %)")


@app.command("run")
def run_command(
    hardware: Path = typer.Option(..., help="hardware YAML (camera, arm, safety limits, calibration files)"),
    policy: Path = typer.Option(..., help="policy: .onnx file (onnxruntime) or checkpoint directory"),
    plan: Path = typer.Option(..., help="trial plan YAML from 'advobj trial plan'"),
    session: str = typer.Option(
        ...,
        help="session name (1-64 letters, digits, '.', '_' or '-', starting with a letter or digit; its frames "
        "go to frames/<session>/ beside the database); the same name resumes an interrupted session",
    ),
    db: Path = typer.Option(Path(DEFAULT_DB), help="trial database (frames go to frames/ beside it)"),
    auto_confirm: bool = typer.Option(
        False, "--auto-confirm", help="accept every automatic outcome (CI, scripted sessions)"
    ),
    answers: Optional[Path] = typer.Option(
        None, help="operator answers YAML: {trial_id: {outcome: ..., note: ...}} or a list in run order"
    ),
    registry: Optional[Path] = typer.Option(None, help="tag registry YAML (objects.yaml); needed with a real camera"),
    table_frame: Optional[Path] = typer.Option(
        None,
        help="YAML with T_base_table; default: estimated from the registry's table "
        "tags at the session's start, stored, reused on resume",
    ),
    max_trials: Optional[int] = typer.Option(None, min=0, help="run at most this many of the remaining trials"),
    rate_limit: Optional[bool] = typer.Option(
        None,
        "--rate-limit/--no-rate-limit",
        help="hold the plan's control rate (default: on, off for non-realtime sim arms)",
    ),
    threads: int = typer.Option(1, min=1, help="onnxruntime threads (1: leaves a core to the camera and renderer)"),
    take_over_stale_lock: bool = typer.Option(
        False,
        "--take-over-stale-lock",
        help="take the session over from a runner the database names but that holds no lock (one on another "
        "host, or a live process that is not that run); a dead runner on this host is taken over without it",
    ),
    view: bool = typer.Option(
        False,
        "--view",
        help="live view: serve the cameras' latest frames with the plan's placement overlay on a web page at "
        "127.0.0.1 while the session runs (the URL is printed)",
    ),
    view_port: Optional[int] = typer.Option(
        None, "--view-port", min=0, max=65535, help="the live view's port (default 8765; 0: any free port)"
    ),
) -> None:
    """Run (or resume) the plan's trials: placement check, policy loop, outcome, operator confirmation, commit."""
    import numpy as np  # lazy: CLI start-up (numpy)

    from trials.real.session import SessionOptions, run_session  # lazy: CLI start-up (torch, cv2)

    opts = SessionOptions(
        hardware=hardware,
        policy=policy,
        plan=plan,
        session=session,
        db=db,
        answers=answers,
        auto_confirm=auto_confirm,
        registry=registry,
        table_frame=table_frame,
        max_trials=max_trials,
        rate_limit=rate_limit,
        threads=threads,
        take_over_stale_lock=take_over_stale_lock,
        view=view,
        view_port=view_port,
    )
    summary = run_session(opts, log=typer.echo)
    t = summary.timings
    if t:
        typer.echo(
            f"{len(t)} trials committed; policy loop {np.median([x.loop_hz for x in t]):.1f} Hz median, "
            f"per-trial overhead {np.median([x.overhead_s for x in t]):.2f} s median (placement + move + "
            "outcome + commit)"
        )
    if summary.aborted:
        typer.secho(
            f"aborted ({summary.abort_reason}); {summary.remaining} trials left. "
            "Resume with the same command (committed trials are kept).",
            fg=typer.colors.YELLOW,
        )
        raise typer.Exit(3)
    typer.echo(
        f"session {summary.session}: {summary.planned - summary.remaining}/{summary.planned} trials done, data in {db}"
    )


@app.command("export")
def export_command(
    db: Path = typer.Option(Path(DEFAULT_DB), help="trial database"),
    out: Path = typer.Option(..., help="output directory"),
    format: str = typer.Option("both", "--format", help="csv, parquet or both"),
) -> None:
    """Export sessions, trials, steps, object poses and events as CSV and/or Parquet tables."""
    if format not in ("csv", "parquet", "both"):
        raise StoreError(f"--format: {format!r} is not csv, parquet or both")
    with TrialStore(db, create=False) as store:
        paths = []
        if format in ("csv", "both"):
            paths += store.export_csv(out)
        if format in ("parquet", "both"):
            paths += store.export_parquet(out)
    for p in paths:
        typer.echo(f"wrote {p}")


@app.command("amend")
def amend_command(
    db: Path = typer.Option(Path(DEFAULT_DB), help="trial database"),
    session: str = typer.Option(..., help="session name"),
    trial: str = typer.Option(..., help="trial id, e.g. A-cube-adv3d-t0-o1"),
    outcome: Optional[str] = typer.Option(None, help="the corrected outcome: goal, adversarial, none or unknown"),
    note: Optional[str] = typer.Option(
        None, help="the trial's note (replaces the old one, which is kept in the audit)"
    ),
    reason: str = typer.Option("", help="why the trial is amended (kept in the audit)"),
) -> None:
    """Correct a committed trial's outcome or note; the old values stay in the 'amendments' table."""
    with TrialStore(db, create=False) as store:
        a = store.amend_trial(session, trial, outcome, note, reason)
    typer.echo(
        f"{session}/{trial}: outcome {a['old_final_outcome']} -> {a['new_final_outcome']}"
        + (f", note {a['old_note']!r} -> {a['new_note']!r}" if a["old_note"] != a["new_note"] else "")
        + f" (amended {a['amended_at']}; the old values are kept in 'amendments')"
    )


@app.command("report")
def report_command(
    db: Path = typer.Option(Path(DEFAULT_DB), help="trial database"),
    session: List[str] = typer.Option([], "--session", help="session name (repeatable; default: all sessions)"),
    sim: List[str] = typer.Option(
        [],
        "--sim",
        help="SHAPE=EVAL_DIR or ENV/SHAPE=EVAL_DIR: 'advobj eval' directory of the same object (repeatable)",
    ),
    plan: Optional[Path] = typer.Option(
        None, help="plan YAML: its texture sha256s match sim conditions when trials did not record one"
    ),
    out: Path = typer.Option(Path("trial_report"), help="report directory (report.html, report.md, report.json)"),
) -> None:
    """ASR and T-ASR with Wilson intervals per session and pooled, and Table IV beside the sim evaluation."""
    from trials.real.report import (  # lazy: CLI start-up (+12 ms)
        ReportError,
        audit,
        load_sim_eval,
        summarize_trials,
        table_iv,
        write_trial_report,
    )

    sims = {key: load_sim_eval(d) for key, d in key_values(sim, "--sim").items()}
    plan_textures = {}
    if plan is not None:
        from trials.real.plan import load_plan  # lazy: CLI start-up (trimesh, PIL)

        plan_textures = {k: t.sha256 for k, t in load_plan(plan).textures.items()}
    with TrialStore(db, create=False) as store:
        missing = sorted(set(session) - set(store.session_names()))
        if missing:
            raise ReportError(
                f"--session: no session {', '.join(missing)} in {db} (have: "
                f"{', '.join(store.session_names()) or 'none'})"
            )
        rows = store.trial_rows(list(session) or None)
        names = list(session) or store.session_names()
        planned = {s: store.planned_trials(s) for s in names}
        amendments = store.amendments(names)
    summary = summarize_trials(rows)
    summary["audit"] = audit(rows, planned, amendments)
    table = table_iv(rows, sims, plan_textures, summary["confidence"])
    sources = {
        "db": str(db),
        "sessions": summary["sessions"],
        "sim": {k: v["path"] for k, v in sims.items()},
        "plan": None if plan is None else str(plan),
    }
    md, js = write_trial_report(out, summary, table, sources=sources)
    write_run_info(out, {"job": "trial-report", **sources}, None)
    from trials.real.report import plain_text, table_iv_md  # lazy: CLI start-up (+12 ms)

    typer.echo("\n".join(table_iv_md(table)))  # names and notes escaped: no terminal escape reaches the screen
    for line in summary["audit"]["incomplete"]:
        typer.echo(f"INCOMPLETE: {plain_text(line)}")
    from sim.htmlreport import REPORT_HTML  # lazy: CLI start-up (numpy)

    typer.echo(f"{summary['n_trials']} trials; report in {out / REPORT_HTML} (open it in a browser), {md} and {js}")
