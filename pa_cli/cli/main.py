"""The entry point of `pa`: the one place where errors become messages and exit codes.

Exit codes: 0 ok, 1 a known error (`PaError`: message on stderr, no traceback unless
`--debug`), 2 a usage error, 130 interrupted (Ctrl-C). Messages are printed as plain text:
paths and formulas in them (`[p;1]`, `[/x]`) are never read as rich markup.
"""

from __future__ import annotations

import contextlib
import sys
import traceback
import warnings
from collections.abc import Iterator
from pathlib import Path

import typer
from rich.text import Text
from typer.exceptions import TyperException

from pa_cli.cli import adjust, calibrate, config, evaluate, perturb, refine, simulate, view  # noqa: F401  (registers the commands)
from pa_cli.cli.app import app, err_console, folded_warnings, log, state
from pa_cli.errors import PaError

INTERRUPTED = 130


def _print_error(message: str) -> None:
    err_console.print(Text.assemble(("error:", "bold red"), " ", message), highlight=False, soft_wrap=True)


def _interrupted() -> int:
    err_console.print(Text("interrupted"), highlight=False)
    return INTERRUPTED


def _log_warning(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                 file: object = None, line: str | None = None) -> None:
    """Show a Python warning (numpy's RuntimeWarning, ...) as one log record instead of raw lines."""
    log.warning("%s: %s (%s:%d)", category.__name__, message, Path(filename).name, lineno)


@contextlib.contextmanager
def _only_the_command(argv: list[str]) -> Iterator[None]:
    """typer builds the click command of every registered command on each run (signatures and
    annotations read again): when `argv` names a command (its first word: the global options are
    flags), only that one is built; `pa --help`, a mistyped name and no command see them all."""
    name = next((arg for arg in argv if not arg.startswith("-")), None)
    commands = [c for c in app.registered_commands
                if (c.name or (c.callback.__name__ if c.callback else "")).replace("_", "-") == name]
    groups = [g for g in app.registered_groups if g.name == name or g.typer_instance.info.name == name]
    if not commands and not groups:
        yield
        return
    every = app.registered_commands, app.registered_groups
    app.registered_commands, app.registered_groups = commands, groups
    try:
        yield
    finally:
        app.registered_commands, app.registered_groups = every


def run(argv: list[str] | None = None) -> int:
    """Run the CLI on `argv` and return the exit code (never raises for known errors)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    state["debug"] = "--debug" in argv
    try:
        with warnings.catch_warnings(), folded_warnings(), _only_the_command(argv):  # repeats shown before an error
            warnings.showwarning = _log_warning
            code = app(args=argv, prog_name="pa", standalone_mode=False)
    except typer.Exit as exc:
        return exc.exit_code
    except typer.Abort:
        return _interrupted()
    except TyperException as exc:  # click's usage errors (typer vendors click): exit 2
        exc.show(file=sys.stderr)
        return exc.exit_code
    except PaError as exc:
        if state["debug"]:
            traceback.print_exc(file=sys.stderr)
        _print_error(str(exc))
        return exc.exit_code
    except KeyboardInterrupt:
        return _interrupted()
    # typer returns the code of an Exit raised inside a command; it turns Ctrl-C into Exit(130)
    if code == INTERRUPTED:
        return _interrupted()
    return code if isinstance(code, int) else 0


def main() -> None:
    sys.exit(run())
