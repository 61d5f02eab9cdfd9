"""The ``advobj`` command line: parse -> build -> run. Sub-commands live beside this file in ``trials/cli/``."""

from __future__ import annotations

import importlib.metadata
import os
import stat
import sys
from pathlib import Path
from typing import Optional

import typer
from pydantic import ValidationError
from typer._click.exceptions import ClickException, NoArgsIsHelpError, UsageError

from sim.errors import AdvobjError, format_validation_error
from trials.cli import attack as cli_attack
from trials.cli import bench as cli_bench
from trials.cli import calibrate as cli_calibrate
from trials.cli import eval as cli_eval
from trials.cli import experiment as cli_experiment
from trials.cli import fabricate as cli_fabricate
from trials.cli import grid as cli_grid
from trials.cli import hw as cli_hw
from trials.cli import policy as cli_policy
from trials.cli import record as cli_record
from trials.cli import scene as cli_scene
from trials.cli import trial as cli_trial
from trials.cli.eval import format_summary

app = typer.Typer(
    no_args_is_help=True,
    add_completion=False,
    help="Red-team wrist-camera visuomotor policies with 3D adversarial objects.",
    context_settings={"help_option_names": ["-h", "--help"]},
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"advobj {importlib.metadata.version('advobj')}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="print the version and exit"
    ),
) -> None:
    """Red-team wrist-camera visuomotor policies with 3D adversarial objects."""


app.add_typer(cli_scene.app, name="scene")

app.add_typer(cli_attack.app, name="attack")

app.command("eval")(cli_eval.eval_command)

app.command("fabricate")(cli_fabricate.fabricate_command)

app.add_typer(cli_experiment.app, name="experiment")


@app.command()
def demo(
    out: Path = typer.Option(Path("runs/demo"), help="output directory"),
    seed: int = typer.Option(0, min=0),
    workers: Optional[int] = cli_grid.WORKERS,
    address: Optional[str] = cli_grid.ADDRESS,
) -> None:
    """The main job on the built-in scene, with quick settings."""
    from trials.experiments.demo import run_demo  # lazy: CLI start-up (trimesh, PIL)

    ex, _ = cli_grid.executor(workers, address, typer.echo)
    result = run_demo(out, seed, log=typer.echo, executor=ex)
    typer.echo(format_summary(result["summary"]))
    typer.echo(f"demo: report in {result['report']}")


app.add_typer(cli_hw.app, name="hw")


app.add_typer(cli_calibrate.app, name="calibrate")

app.add_typer(cli_policy.app, name="policy")

app.add_typer(cli_bench.app, name="bench")

app.add_typer(cli_trial.app, name="trial")

app.add_typer(cli_record.app, name="record")


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def special_file_argument(argv: list[str]) -> str | None:
    """The first command-line value naming a FIFO, a device or a socket, as an error line, or None.

    advobj reads files, never a stream: opening a FIFO with no writer, ``/dev/zero`` or
    ``/dev/stdin`` would block or never end. ``os.stat`` answers without opening, so this costs
    nothing and runs before any command. (A camera device is named in a hardware YAML, never as
    a command-line value.)
    """
    flag = None
    for tok in argv:
        if tok.startswith("--") and "=" in tok:
            flag, value = tok.split("=", 1)
        elif tok.startswith("-") and len(tok) > 1:
            flag = tok
            continue
        else:
            value = tok
        try:
            mode = os.stat(value).st_mode
        except (OSError, ValueError):
            mode = None
        if mode is not None and not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
            kind = "a FIFO" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode) else "a device"
            where = f"{flag}: " if flag else ""
            return f"{where}{value} is {kind}, not a file; give a regular file"
        flag = None
    return None


def main() -> None:
    """Run the CLI; every input error ends as one line on stderr (``error: ...``) and exit code 2.

    Errors of the project (:class:`~sim.errors.AdvobjError`), the command line's own usage errors
    (a bad flag value, a missing option: typer would draw a multi-line box), a pydantic validation
    of options that reached a model, and an OS error naming a file (``--out`` naming a directory,
    a read-only folder) all print one line naming the flag, field or file.
    """

    def fail(message: str, code: int = 2):
        typer.secho(f"error: {_one_line(message)}", err=True, fg=typer.colors.RED)
        sys.exit(code)

    special = special_file_argument(sys.argv[1:])
    if special is not None:
        fail(special)
    try:
        rc = app(standalone_mode=False)
    except AdvobjError as err:
        fail(str(err), getattr(err, "exit_code", None) or 2)
    except NoArgsIsHelpError as err:  # 'advobj' or 'advobj trial' alone: the help, as before
        err.show()
        sys.exit(2)
    except UsageError as err:
        where = err.ctx.command_path if err.ctx is not None else "advobj"
        fail(f"{where}: {err.format_message()}", err.exit_code if err.exit_code else 2)
    except ClickException as err:
        fail(err.format_message(), err.exit_code or 1)
    except typer.Abort:
        typer.echo("Aborted!", err=True)
        sys.exit(1)
    except ValidationError as err:
        fail(format_validation_error(err, "options"))
    except OSError as err:
        if err.filename is None:
            raise
        fail(f"{err.filename}: {err.strerror or err}")
    sys.exit(rc if isinstance(rc, int) else 0)


if __name__ == "__main__":
    main()
