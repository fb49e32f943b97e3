"""The typer app of `pa`, its global options and the choices shared by several commands.

Only cheap imports here (typer, rich): the commands import what they need inside their
functions, so that `pa --help` stays fast.
"""

from __future__ import annotations

import contextlib
import logging
import re
from collections.abc import Iterator
from enum import Enum
from pathlib import PurePath
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.console import Console
from rich.logging import RichHandler
from typer.core import TyperCommand, TyperGroup

from pa_cli import __version__

if TYPE_CHECKING:
    from pa_cli.config import ExecutionConfig

err_console = Console(stderr=True)
log = logging.getLogger("pa_cli")


class _FlagsTakeNoValue:
    """typer's help shows a flag's type (`--force <bool>`) as if the flag took a value: flags get an
    empty metavar, so that the help shows their names only."""

    def get_params(self, ctx: typer.Context) -> list[Any]:
        params = super().get_params(ctx)  # type: ignore[misc]
        for param in params:
            if getattr(param, "is_flag", False) and param.metavar is None:
                param.metavar = ""
        return params


class _Command(_FlagsTakeNoValue, TyperCommand):
    pass


class Group(_FlagsTakeNoValue, TyperGroup):
    pass


class Typer(typer.Typer):
    """`typer.Typer` whose commands are `_Command`s."""

    def command(self, *args: Any, cls: type[TyperCommand] | None = None, **kwargs: Any) -> Any:
        return super().command(*args, cls=cls or _Command, **kwargs)


app = Typer(
    cls=Group,
    name="pa",
    help="LiDAR map refinement by second-order plane adjustment.\n\n"
    "Poses are T_world_scan (maps scan-frame points to the world), metres and seconds.",
    rich_markup_mode="rich",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

state = {"debug": False}


_PLACEHOLDER = re.compile(r"%(?:\(\w+\))?[-#0 +]*\d*(?:\.\d+)?[diouxXeEfFgGcrsa%]")


class _Fold:
    """The warnings of one kind: the first (shown when it came), how many came and, for warnings
    about files, which files."""

    def __init__(self, record: logging.LogRecord, file: str | None) -> None:
        self.first, self.first_file = record, file
        self.count = 1
        self.files = {file} if file is not None else set()

    def add(self, file: str | None) -> None:
        self.count += 1
        if file is not None:
            self.files.add(file)

    def line(self) -> str | None:
        """The folded line, or None when nothing was held back but exact repeats of the first."""
        if self.first_file is None:
            return f"{self.first.getMessage()} ({self.count} times)" if self.count > 1 else None
        if len(self.files) < 2:
            return None
        text = _PLACEHOLDER.sub(lambda m: "%" if m.group() == "%%" else "...", str(self.first.msg))
        return f"{text.removeprefix('...: ')} ({len(self.files)} files; first: {self.first_file})"


class WarningFolder(logging.Filter):
    """A handler filter that folds repeated warnings: the first warning of each kind passes, the
    others are held, and `flush` logs one line per kind that repeated, with a count.

    A warning about a file (its first argument a path, as in `log.warning("%s: PCD header says POINTS
    %d ...", path, ...)`) is of the kind of its message template, whatever the file and the numbers;
    any other warning is of the kind of its text."""

    def __init__(self) -> None:
        super().__init__()
        self._folds: dict[str, _Fold] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno != logging.WARNING or getattr(record, "folded", False):
            return True
        args = record.args if isinstance(record.args, tuple) else ()
        file = str(args[0]) if args and isinstance(args[0], PurePath) else None
        key = str(record.msg) if file is not None else record.getMessage()
        if key not in self._folds:
            self._folds[key] = _Fold(record, file)
            return True
        self._folds[key].add(file)
        return False

    def flush(self) -> None:
        """Log the folded line of every kind that repeated, and forget them all."""
        folds, self._folds = self._folds, {}
        for fold in folds.values():
            line = fold.line()
            if line is not None:
                log.warning("%s", line, extra={"folded": True})


warning_folder = WarningFolder()


@contextlib.contextmanager
def folded_warnings() -> Iterator[None]:
    """Repeated warnings logged in the block are folded (`WarningFolder`) and shown at its end."""
    try:
        yield
    finally:
        warning_folder.flush()


def setup_logging(level: int) -> None:
    """Log records of `pa_cli` to stderr, as plain text (no rich markup in messages), repeated
    warnings folded (`warning_folder`)."""
    root = logging.getLogger("pa_cli")
    root.handlers.clear()
    handler = RichHandler(console=err_console, show_time=False, show_path=False, markup=False)
    handler.setFormatter(logging.Formatter("%(message)s"))
    handler.addFilter(warning_folder)
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


class NoiseModelChoice(str, Enum):
    """The point noise models of the pose covariance (`pa_cli.adjust.covariance.NOISE_MODELS`)."""

    auto = "auto"
    range = "range"
    observation = "observation"
    plane = "plane"


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
