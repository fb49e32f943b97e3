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
from pathlib import Path
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


class SolverChoice(str, Enum):
    newton = "newton"
    lm = "lm"


@app.command("refine")
def refine_command(
    scans_dir: Annotated[Path | None, typer.Argument(
        help="Folder of scans (PCD/PLY/BIN, sensor frame, metres), sorted naturally.",
        show_default=False)] = None,
    out: Annotated[Path | None, typer.Option(
        "--out", "-o", help="Map to write (.ply); the other outputs are named after its stem.",
        show_default=False)] = None,
    poses: Annotated[Path | None, typer.Option(
        "--poses", help="Initial poses T_world_scan (KITTI or TUM, one per scan); skips KISS-ICP.")] = None,
    gt: Annotated[Path | None, typer.Option(
        "--gt", help="Ground-truth poses (KITTI or TUM): ATE of initial and refined poses in the report.")] = None,
    config_path: Annotated[Path | None, typer.Option(
        "--config", "-c", help="YAML config (see configs/default.yaml); missing keys keep defaults.")] = None,
    solver: Annotated[SolverChoice | None, typer.Option(
        "--solver", help="newton (planes eliminated) or lm (PA_LM baseline); overrides the config.")] = None,
    rounds: Annotated[int | None, typer.Option(
        "--rounds", min=1, help="Association + adjustment rounds at most; overrides refine.rounds.")] = None,
    save_problem: Annotated[Path | None, typer.Option(
        "--save-problem", help="Also write the last round's plane problem (.npz, for pa adjust).")] = None,
    glob: Annotated[str | None, typer.Option(
        "--glob", help="Only scans whose file name matches this pattern, e.g. '*.pcd'.")] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite existing outputs.")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bars, warnings only.")] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Debug messages.")] = False,
    print_config: Annotated[bool, typer.Option(
        "--print-config", help="Print the effective config (defaults < --config < flags) as YAML and exit.")] = False,
) -> None:
    """Refine LiDAR scan poses by plane adjustment and write a merged map.

    Stages (each with a progress bar on stderr): load the scans; initial poses by KISS-ICP
    (or --poses); rounds of plane association at the current poses and second-order plane
    adjustment, until no pose moves more than refine.pose_change_tolerance_m/_deg or
    --rounds is reached; write.

    Outputs next to MAP.ply: MAP.ply (map, float32 x y z + int32 scan_index, world frame),
    MAP_poses_kitti.txt, MAP_poses_tum.txt, MAP_initial_poses_kitti.txt, MAP_report.json,
    MAP_config.yaml. Existing outputs are refused without --force.

    Example:

        pa refine sample_data/office/scans --out office_map.ply --gt sample_data/office/gt_poses_tum.txt

        pa refine --print-config --config configs/indoor.yaml
    """
    from pa_cli.config import dump_config, load_config

    config = load_config(config_path)
    if solver is not None:
        config.solver.solver = solver.value
    if rounds is not None:
        config.refine.rounds = rounds
    if print_config:
        typer.echo(dump_config(config), nl=False)
        return
    if scans_dir is None:
        raise typer.BadParameter("SCANS_DIR is required (a folder of scans).", param_hint="SCANS_DIR")
    if out is None:
        raise typer.BadParameter("--out MAP.ply is required.", param_hint="--out")
    if out.suffix.lower() != ".ply":
        raise typer.BadParameter(f"expected a .ply path, got '{out}'.", param_hint="--out")
    if quiet:
        logging.getLogger("pa_cli").setLevel(logging.WARNING)
    elif verbose:
        logging.getLogger("pa_cli").setLevel(logging.DEBUG)

    from pa_cli.pipeline import RefinePipeline
    from pa_cli.report import print_refine_summary

    pipeline = RefinePipeline(scans_dir, out, config, poses=poses, gt=gt, save_problem=save_problem,
                              glob=glob, force=force, show_progress=not quiet,
                              config_source=str(config_path) if config_path else "defaults")
    report = pipeline.run()
    if not quiet:
        print_refine_summary(report, err_console)
    log.info("wrote %s and %s", out, ", ".join(
        str(p) for p in pipeline.outputs.all() if p != out))


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
