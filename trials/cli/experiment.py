"""``advobj experiment``: the paper's tables as recipes (quick and paper presets)."""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import List, Optional

import typer

from sim.runtime import set_torch_threads
from trials.cli.grid import ADDRESS, SHARDS, WORKERS, executor
from trials.cli.options import MIN_CLEAN_SUCCESS, int_list, key_values, name_list
from trials.experiments.recipes import RECIPES, ExperimentConfig, resolve_experiment, run_experiment

__all__ = ["app", "CONFIG_OPTIONS", "experiment_config", "experiment_targets", "parse_experiment"]

app = typer.Typer(no_args_is_help=True, help="Reproduce the paper's experiments (Tables I, II, III and V).")


def experiment_config(
    preset: str,
    episodes: Optional[int] = None,
    pool: Optional[Path] = None,
    device: str = "cpu",
    archs: Optional[str] = None,
    iterations: Optional[int] = None,
    attack_seeds: Optional[str] = None,
    rows: Optional[str] = None,
    min_clean_success: Optional[float] = None,
) -> ExperimentConfig:
    """The config ``advobj experiment`` runs a recipe with, from the values of its options as the
    command takes them: ``--pool`` a path, ``--archs`` and ``--rows`` comma-separated names,
    ``--attack-seeds`` comma-separated integers, ``--iterations`` every attack's; None keeps the
    preset's. A malformed value is one :class:`~trials.cli.options.OptionError` line naming
    ``--attack-seeds`` or one :class:`~trials.experiments.recipes.ExperimentError` line naming the
    field. The command's checks of which recipe takes which option are not made here."""
    return resolve_experiment(
        preset,
        episodes=episodes,
        pool=None if pool is None else str(pool),
        device=device,
        attack_overrides=None if iterations is None else {"iterations": iterations},
        transfer_targets=name_list(archs),
        attack_seeds=int_list(attack_seeds, "--attack-seeds"),
        rows=name_list(rows),
        min_clean_success=min_clean_success,
    )


def experiment_targets(target: List[str]) -> dict[str, Path]:
    """The ``--target ARCH=PATH`` items as ``{arch: path}``; a malformed or repeated one is one
    :class:`~trials.cli.options.OptionError` line naming ``--target``."""
    return {arch: Path(d) for arch, d in key_values(target, "--target", "ARCH", "PATH").items()}


#: The options :func:`experiment_config` reads, by parameter name.
CONFIG_OPTIONS = tuple(inspect.signature(experiment_config).parameters)


def parse_experiment(recipe: str, args: List[str]) -> tuple[ExperimentConfig, dict]:
    """What ``advobj experiment RECIPE ARGS...`` runs with, without running it: its config
    (:func:`experiment_config`) and the values of all its options by parameter name, parsed by the
    command's own options with their defaults (for a record of a command that ran: its ``run.json``).
    A ``click`` exception when ``args`` do not parse; :func:`experiment_config`'s errors otherwise."""
    params = typer.main.get_command(app).commands[recipe].make_context(recipe, list(args)).params
    return experiment_config(**{k: params[k] for k in CONFIG_OPTIONS}), params


def _run(
    name: str,
    preset: str,
    out: Optional[Path],
    policy: Optional[Path],
    target: List[str],
    episodes: Optional[int],
    scene: Optional[Path],
    pool: Optional[Path],
    archs: Optional[str] = None,
    iterations: Optional[int] = None,
    grid: tuple = (None, None, None, "cpu"),
    attack_seeds: Optional[str] = None,
    rows: Optional[str] = None,
    min_clean_success: Optional[float] = None,
) -> None:
    set_torch_threads()
    targets = experiment_targets(target)
    workers, address, shards, device = grid
    ex, default_shards = executor(workers, address, typer.echo)
    cfg = experiment_config(
        preset,
        episodes=episodes,
        pool=pool,
        device=device,
        archs=archs,
        iterations=iterations,
        attack_seeds=attack_seeds,
        rows=rows,
        min_clean_success=min_clean_success,
    )
    path = run_experiment(
        name,
        cfg,
        out or Path("runs") / f"{name}-{preset}",
        policy,
        targets,
        scene,
        log=typer.echo,
        executor=ex,
        shards=shards or default_shards,
    )
    typer.echo(path.read_text())
    typer.echo(f"table: {path}")


_PRESET = typer.Option("quick", help="quick (2 CPU cores) or paper (the paper's budget)")
_OUT = typer.Option(None, help="output directory (default: runs/<experiment>-<preset>); re-running it resumes")
_POLICY = typer.Option(
    None, help="reference (source) policy checkpoint; default: train one with the preset's policy preset"
)
_EPISODES = typer.Option(None, min=1, help="override the preset's episodes per condition")
_SCENE = typer.Option(None, help="scene YAML (default: the built-in paper scene)")
_POOL = typer.Option(None, help="task-feasible pool JSON for every evaluation (default: each policy's own)")
_ITERATIONS = typer.Option(None, min=1, help="attack iterations of every attack (default: the attack preset's)")
_ATTACK_SEEDS = typer.Option(
    None,
    "--attack-seeds",
    help="comma-separated attack seeds: independent attack runs per arm, each evaluated on the same configurations "
    "(default: 0)",
)
_ROWS = typer.Option(None, "--rows", help="comma-separated Table II rows to run (default: all; table2 only)")
_DEVICE = typer.Option("cpu", help="torch device of every job; 'cuda' jobs ask Ray for a GPU each")


_TARGET = typer.Option(
    [],
    help="ARCH=PATH target policy (resnet34, vgg16, inception_v3; checkpoint or .onnx); missing targets are "
    "trained (transfer only)",
)
_ARCHS = typer.Option(
    None,
    "--archs",
    help="comma-separated target architectures to run (default: resnet34,vgg16,inception_v3; transfer only)",
)


def _command(name: str, recipe):
    """The ``advobj experiment NAME`` command of one registry entry (the options every recipe shares)."""

    def command(
        preset: str = _PRESET,
        out: Optional[Path] = _OUT,
        policy: Optional[Path] = _POLICY,
        target: List[str] = _TARGET,
        episodes: Optional[int] = _EPISODES,
        scene: Optional[Path] = _SCENE,
        pool: Optional[Path] = _POOL,
        archs: Optional[str] = _ARCHS,
        iterations: Optional[int] = _ITERATIONS,
        workers: Optional[int] = WORKERS,
        address: Optional[str] = ADDRESS,
        shards: Optional[int] = SHARDS,
        device: str = _DEVICE,
        attack_seeds: Optional[str] = _ATTACK_SEEDS,
        rows: Optional[str] = _ROWS,
        min_clean_success: float = MIN_CLEAN_SUCCESS,
    ) -> None:
        if rows is not None and name != "table2":
            raise typer.BadParameter("only the table2 recipe has rows", param_hint="--rows")
        if not recipe.transfer:
            for flag, given in (("--target", target), ("--archs", archs)):
                if given:
                    raise typer.BadParameter("only the transfer recipe attacks other policies", param_hint=flag)
        elif pool is not None:
            raise typer.BadParameter("the transfer recipe evaluates each target on its own pool", param_hint="--pool")
        _run(
            name,
            preset,
            out,
            policy,
            target,
            episodes,
            scene,
            pool,
            archs,
            iterations=iterations,
            grid=(workers, address, shards, device),
            attack_seeds=attack_seeds,
            rows=rows,
            min_clean_success=min_clean_success,
        )

    command.__doc__ = recipe.help
    command.__name__ = name
    return command


for _name, _recipe in RECIPES.items():
    app.command(_name)(_command(_name, _recipe))
