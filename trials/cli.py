"""The ``advobj`` command line: parse -> build -> run. Sub-commands live in ``trials/cli_*.py``."""

from __future__ import annotations

from pathlib import Path

import typer

app = typer.Typer(no_args_is_help=True, add_completion=False, help="Red-team wrist-camera visuomotor policies with 3D adversarial objects.")


from trials import cli_scene  # noqa: E402

app.add_typer(cli_scene.app, name="scene")
from trials import cli_attack  # noqa: E402

app.add_typer(cli_attack.app, name="attack")
from trials import cli_eval  # noqa: E402

app.command("eval")(cli_eval.eval_command)
from trials import cli_fabricate  # noqa: E402

app.command("fabricate")(cli_fabricate.fabricate_command)
from trials import cli_experiment  # noqa: E402

app.add_typer(cli_experiment.app, name="experiment")


@app.command()
def demo(out: Path = typer.Option(Path("runs/demo"), help="output directory"), seed: int = typer.Option(0)) -> None:
    """The main job on the built-in scene, with quick settings."""
    from trials.demo import run_demo

    from trials.cli_eval import format_summary

    result = run_demo(out, seed, log=typer.echo)
    typer.echo(format_summary(result["summary"]))
    typer.echo(f"demo: report in {result['report']}")


from trials import cli_hw  # noqa: E402

app.add_typer(cli_hw.app, name="hw")


from trials import cli_calibrate  # noqa: E402

app.add_typer(cli_calibrate.app, name="calibrate")
from trials import cli_policy  # noqa: E402

app.add_typer(cli_policy.app, name="policy")
from trials import cli_bench  # noqa: E402

app.add_typer(cli_bench.app, name="bench")
from trials import cli_trial  # noqa: E402

app.add_typer(cli_trial.app, name="trial")


def main() -> None:
    import sys

    from sim.errors import AdvobjError

    try:
        app()
    except AdvobjError as err:
        typer.secho(f"error: {err}", err=True, fg=typer.colors.RED)
        sys.exit(2)


if __name__ == "__main__":
    main()
