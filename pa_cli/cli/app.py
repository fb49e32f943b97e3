"""The typer app of `pa`, its global options and the choices shared by several commands.

Only cheap imports here (typer, rich): the commands import what they need inside their
functions, so that `pa --help` stays fast.
"""

from __future__ import annotations

import logging
from enum import Enum
from typing import Annotated

import typer
from rich.console import Console
from rich.logging import RichHandler

from pa_cli import __version__

err_console = Console(stderr=True)
log = logging.getLogger("pa_cli")

app = typer.Typer(
    name="pa",
    help="LiDAR map refinement by second-order plane adjustment.\n\n"
    "Poses are T_world_scan (maps scan-frame points to the world), metres and seconds.",
    rich_markup_mode="rich",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

state = {"debug": False}


def setup_logging(level: int) -> None:
    """Log records of `pa_cli` to stderr, as plain text (no rich markup in messages)."""
    root = logging.getLogger("pa_cli")
    root.handlers.clear()
    handler = RichHandler(console=err_console, show_time=False, show_path=False, markup=False)
    handler.setFormatter(logging.Formatter("%(message)s"))
    root.addHandler(handler)
    root.setLevel(level)
    root.propagate = False


def _version_callback(value: bool) -> None:
    if value:
        typer.echo(f"pa {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[
        bool, typer.Option("--version", callback=_version_callback, is_eager=True,
                           help="Print the version and exit.")
    ] = False,
    debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks of errors.")] = False,
) -> None:
    state["debug"] = debug
    setup_logging(logging.DEBUG if debug else logging.INFO)


class TrajFormat(str, Enum):
    kitti = "kitti"
    tum = "tum"


def fmt_value(value: TrajFormat | None) -> str | None:
    """The format name of a `--format` option, or None (detect from the file)."""
    return None if value is None else value.value


class SolverChoice(str, Enum):
    newton = "newton"
    lm = "lm"
