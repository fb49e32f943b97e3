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


class SceneName(str, Enum):
    office = "office"
    street = "street"


@app.command()
def simulate(
    scene: Annotated[SceneName, typer.Argument(help="Built-in scene: office (indoor floor, 30 x 20 m) "
                                               "or street (outdoor, ~150 m).")],
    out_dir: Annotated[str, typer.Argument(help="Output folder (must not exist or be empty, "
                                           "unless --force).")],
    scans: Annotated[int, typer.Option(help="Number of scans (one per 0.1 s).")] = 50,
    step_m: Annotated[float | None, typer.Option(
        help="Path length per scan (m); default 0.1 (office, walking) or 1.0 (street, driving).")] = None,
    beams: Annotated[int, typer.Option(help="Number of laser beams: 16, 32 or 64.")] = 16,
    vfov_deg: Annotated[float | None, typer.Option(
        help="Vertical field of view (deg), symmetric about the horizon; default 30 / 40 / 45 "
             "for 16 / 32 / 64 beams.")] = None,
    azimuth_steps: Annotated[int, typer.Option(help="Columns per 360 deg sweep.")] = 1024,
    range_noise_m: Annotated[float, typer.Option(help="Gaussian range noise along the ray, sigma (m).")] = 0.01,
    max_range_m: Annotated[float | None, typer.Option(
        help="Drop returns farther than this (m); default 30 (office) or 100 (street).")] = None,
    min_range_m: Annotated[float, typer.Option(help="Drop returns closer than this (m).")] = 0.5,
    seed: Annotated[int, typer.Option(help="Random seed of the range noise (same seed: identical files).")] = 0,
    motion_distortion: Annotated[bool, typer.Option(
        "--motion-distortion/--no-motion-distortion",
        help="Cast each azimuth column from the pose at its firing time and store per-point time.")] = False,
    force: Annotated[bool, typer.Option("--force", help="Replace the contents of a non-empty OUT_DIR.")] = False,
) -> None:
    r"""Ray-cast a LiDAR sequence with exact ground truth (poses, plane labels, plane equations).

    Outputs in OUT_DIR (built beside it, then renamed into place):
    - scans/000000.pcd ...: binary PCD, float32 x y z intensity \[time], points in the sensor frame
    - labels/000000.npy ...: int32 true plane label per point (same order), -1 = no plane
    - planes.npy: (P, 4) rows n_x n_y n_z d with n.x + d = 0 (world frame, m), row = label
    - gt_poses_kitti.txt, gt_poses_tum.txt: T_world_scan at each scan's start, timestamps k * 0.1 s
    - meta.json: scene, options, seed, version

    Example:

        pa simulate office out/office --scans 60 --beams 16 --seed 1
    """
    from rich.progress import Progress

    from pa_cli.simulate import SimOptions
    from pa_cli.simulate import simulate as run_simulation

    options = SimOptions(scene=scene.value, scans=scans, step_m=step_m, beams=beams, vfov_deg=vfov_deg,
                         azimuth_steps=azimuth_steps, range_noise_m=range_noise_m,
                         max_range_m=max_range_m, min_range_m=min_range_m, seed=seed,
                         motion_distortion=motion_distortion)
    with Progress(console=err_console, transient=True) as bar:
        task = bar.add_task(f"simulate {scene.value}", total=scans)
        meta = run_simulation(options, out_dir, force=force,
                              progress=lambda done, total: bar.update(task, completed=done))
    log.info("wrote %d scans, %d points, %d true planes to %s", meta["n_scans"], meta["n_points"],
             meta["n_planes"], out_dir)


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
