"""The ``advobj`` command line: parse -> build -> run. Sub-commands live in ``trials/cli_*.py``."""

from __future__ import annotations

import typer

app = typer.Typer(no_args_is_help=True, add_completion=False, help="Red-team wrist-camera visuomotor policies with 3D adversarial objects.")


def main() -> None:
    app()
