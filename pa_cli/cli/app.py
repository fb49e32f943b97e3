"""The typer app of `pa`, its global options and the choices shared by several commands.

Only cheap imports here (typer, rich): the commands import what they need inside their
functions, so that `pa --help` stays fast.
"""

from __future__ import annotations

import logging
from enum import Enum
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.console import Console
from rich.logging import RichHandler

from pa_cli import __version__

if TYPE_CHECKING:
    from pa_cli.config import ExecutionConfig

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


def set_verbosity(quiet: bool, verbose: bool) -> None:
    """`--quiet` shows warnings and errors only, `--verbose` adds debug messages."""
    if quiet:
        log.setLevel(logging.WARNING)
    elif verbose:
        log.setLevel(logging.DEBUG)


def require(value: Any, message: str, param_hint: str) -> None:
    """A usage error (exit 2) naming the parameter when a required value is missing."""
    if value is None:
        raise typer.BadParameter(message, param_hint=param_hint)


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


class BackendChoice(str, Enum):
    flat = "flat"
    hierarchical = "hierarchical"


def execution_config(base: ExecutionConfig, workers: int | None, scheduler: str | None) -> ExecutionConfig:
    """The `execution` config section with --workers / --scheduler applied (they exclude each other)."""
    if workers is not None and scheduler is not None:
        raise typer.BadParameter("give --workers (a local cluster) or --scheduler (a running one), not both",
                                 param_hint="--scheduler")
    if scheduler is not None and not scheduler.startswith(("tcp://", "tls://", "inproc://", "ucx://")):
        raise typer.BadParameter(f"expected an address like tcp://HOST:PORT, got '{scheduler}'",
                                 param_hint="--scheduler")
    updates: dict[str, Any] = {}
    if workers is not None:
        updates["workers"] = workers
    if scheduler is not None:
        updates["scheduler_address"] = scheduler
    return base.model_copy(update=updates)


CONFIG_METAVAR = "indoor|outdoor|PATH"
CONFIG_HELP = ("A preset shipped with pa (indoor, outdoor) or a YAML config file; keys left out keep their defaults. "
               "`pa config show [indoor|outdoor|PATH]` prints the effective config with every key described.")

WORKERS_HELP = ("Run the hierarchical backend's windows on a local dask cluster of this many worker processes "
                "(0: in this process); overrides execution.workers.")
SCHEDULER_HELP = "Run the windows on the running dask cluster at this address (tcp://HOST:PORT)."
