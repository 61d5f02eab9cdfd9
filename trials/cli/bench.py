"""``advobj bench``: measured trade-offs (parse -> :class:`trials.experiments.tradeoff.TradeoffJob` -> run,
as ``benchmarks/bench_tradeoff.py``)."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from trials.cli import grid as cli_grid
from trials.cli.options import int_list, key_values

app = typer.Typer(no_args_is_help=True, help="Benchmarks that answer 'what does this knob buy and what does it cost'.")


@app.command()
def tradeoff(
    policy: Path = typer.Option(
        ..., help="baseline policy checkpoint directory (its task-feasible pool is the evaluation set)"
    ),
    out: Path = typer.Option(Path("runs/tradeoff"), help="sweep directory; a re-run skips finished rows"),
    res_policy: List[str] = typer.Option(
        [], "--res-policy", help="SIZE=DIR: policy for a policy_resolution row (repeatable)"
    ),
    train_missing: bool = typer.Option(
        False,
        "--train-missing",
        help="train missing policy_resolution policies (quick preset) into OUT/policies, after the other rows",
    ),
    train_iterations: Optional[int] = typer.Option(
        None, min=1, help="DAgger iterations for --train-missing (default: the quick preset's)"
    ),
    rows: List[str] = typer.Option(
        [], "--rows", help="knob or row key to run, e.g. eot_envs or eot_envs=1 (repeatable; default: all)"
    ),
    episodes: Optional[int] = typer.Option(None, min=1, help="paired episodes per row (default 300)"),
    big_episodes: Optional[int] = typer.Option(
        None, min=1, help="episodes of the eval_episodes row (default: a third of --episodes)"
    ),
    attack_seeds: Optional[str] = typer.Option(
        None,
        "--attack-seeds",
        help="comma-separated attack seeds: the rows that change the attack run once per seed, each evaluated on "
        "the same configurations (default: 0)",
    ),
    pool: Optional[Path] = typer.Option(None, help="task-feasible pool of the baseline policy (default: its own)"),
    scene: Optional[Path] = typer.Option(None, help="scene YAML (default: the built-in paper scene)"),
    max_steps: Optional[int] = typer.Option(
        None, min=1, help="steps per episode (default 60; the pool must be made for it)"
    ),
    quick_check: bool = typer.Option(
        False, "--quick-check", help="tiny settings: checks the machinery, measures nothing"
    ),
    plot: Optional[Path] = typer.Option(None, help="Pareto plot PNG (default OUT/tradeoff_pareto.png)"),
    report_only: bool = typer.Option(
        False, "--report-only", help="only rebuild the report and plot from OUT/rows.jsonl"
    ),
    redo: bool = typer.Option(
        False, "--redo", help="measure the selected --rows again even if done (the newest record is reported)"
    ),
    workers: Optional[int] = cli_grid.WORKERS,
    address: Optional[str] = cli_grid.ADDRESS,
) -> None:
    """Sweep attack, evaluation and deployment knobs one at a time; table, Pareto plot and report in OUT."""
    from trials.experiments.tradeoff import TradeoffJob  # lazy: CLI start-up (torch, onnxruntime)

    job = TradeoffJob.build(
        policy,
        out,
        key_values(res_policy, "--res-policy", "SIZE", "DIR"),
        quick_check,
        episodes=episodes,
        big_episodes=big_episodes,
        attack_seeds=int_list(attack_seeds, "--attack-seeds"),
        pool=pool,
        scene=scene,
        max_steps=max_steps,
        rows=tuple(rows),
        train_missing=train_missing,
        train_iterations=train_iterations,
        plot=plot,
        report_only=report_only,
        redo=redo,
    )
    ex, _ = cli_grid.executor(workers, address, typer.echo)
    job.run(log=typer.echo, executor=None if workers is None and address is None else ex)
