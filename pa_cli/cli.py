"""The `pa` command line. The only place where errors become messages and exit codes.

Exit codes: 0 ok, 1 a known error (`PaError`: message on stderr, no traceback unless
`--debug`), 2 a usage error. Heavy imports (open3d, kiss-icp, the solver) happen inside the
commands so that `pa --help` stays fast.
"""

from __future__ import annotations

import logging
import sys
import traceback
from enum import Enum
from typing import Annotated

import typer
from rich.console import Console
from rich.logging import RichHandler
from typer.exceptions import TyperException

from pa_cli import __version__
from pa_cli.errors import PaError

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

_state = {"debug": False}


def _setup_logging(level: int) -> None:
    root = logging.getLogger("pa_cli")
    root.handlers.clear()
    handler = RichHandler(console=err_console, show_time=False, show_path=False)
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
    _state["debug"] = debug
    _setup_logging(logging.DEBUG if debug else logging.INFO)


class TrajFormat(str, Enum):
    kitti = "kitti"
    tum = "tum"


def _fmt(value: TrajFormat | None) -> str | None:
    return None if value is None else value.value


# --------------------------------------------------------------------------------------------
# pa perturb
# --------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------
# pa eval
# --------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------
# pa simulate
# --------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------
# pa adjust
# --------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------
# pa refine
# --------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------
# entry point: the one place that maps errors to exit codes
# --------------------------------------------------------------------------------------------


def run(argv: list[str] | None = None) -> int:
    """Run the CLI on `argv` and return the exit code (never raises for known errors)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    _state["debug"] = "--debug" in argv
    try:
        app(args=argv, prog_name="pa", standalone_mode=False)
    except typer.Exit as exc:
        return exc.exit_code
    except typer.Abort:
        err_console.print("Aborted.")
        return 130
    except TyperException as exc:  # click's usage errors (typer vendors click): exit 2
        exc.show(file=sys.stderr)
        return exc.exit_code
    except PaError as exc:
        if _state["debug"]:
            traceback.print_exc(file=sys.stderr)
        err_console.print(f"[bold red]error:[/] {exc}", highlight=False, markup=True,
                          soft_wrap=True)
        return exc.exit_code
    except KeyboardInterrupt:
        err_console.print("Interrupted.")
        return 130
    return 0


def main() -> None:
    sys.exit(run())


if __name__ == "__main__":
    main()
