"""`pa perturb`: Gaussian noise on every pose of a trajectory."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pa_cli.cli.app import TrajFormat, app, fmt_value, log


@app.command("perturb")
def perturb_command(
    poses: Annotated[Path, typer.Argument(help="Input trajectory (KITTI or TUM), T_world_scan.")],
    out: Annotated[Path, typer.Option("--out", help="Output trajectory file.")],
    rot_deg: Annotated[float | None, typer.Option(
        "--rot-deg", min=0.0, help="Rotation noise sigma per axis, degrees (w ~ N(0, sigma^2 I)).")] = None,
    trans_m: Annotated[float | None, typer.Option(
        "--trans-m", min=0.0, help="Translation noise sigma per axis, metres.")] = None,
    level: Annotated[int | None, typer.Option(
        "--level", min=1, max=4, help="Paper preset: 1=(0.1 deg, 0.01 m) 2=(1 deg, 0.1 m) "
        "3=(2 deg, 0.2 m) 4=(3 deg, 0.3 m). Replaces --rot-deg/--trans-m.")] = None,
    seed: Annotated[int, typer.Option("--seed", help="Random seed; the same seed gives the same file.")] = 0,
    keep_first: Annotated[bool, typer.Option("--keep-first", help="Leave pose 0 unperturbed.")] = False,
    fmt: Annotated[TrajFormat | None, typer.Option(
        "--format", help="Format of the input and output (default: detected from the input).")] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite OUT if it exists.")] = False,
) -> None:
    """Perturb every pose with Gaussian noise (Zhou, seed 000, section 5.2).

    t <- t + N(0, SIGMA_T^2 I) and R <- Exp(w) R with w ~ N(0, SIGMA_R^2 I), unless --keep-first.

    Give either --level or both sigmas. The output keeps the input format and TUM timestamps.

    Example:

        pa perturb poses_kitti.txt --rot-deg 1 --trans-m 0.1 --seed 7 --out noisy.txt

        pa perturb poses_tum.txt --level 3 --keep-first --out noisy_tum.txt
    """
    import numpy as np

    from pa_cli.evaluation import PERTURBATION_LEVELS, perturb_poses
    from pa_cli.io.atomic import check_writable
    from pa_cli.io.trajectory import Trajectory, read_trajectory, write_trajectory

    if level is not None:
        if rot_deg is not None or trans_m is not None:
            raise typer.BadParameter("give either --level or --rot-deg/--trans-m, not both.",
                                     param_hint="--level")
        rot_deg, trans_m = PERTURBATION_LEVELS[level]
    elif rot_deg is None or trans_m is None:
        raise typer.BadParameter("give both --rot-deg and --trans-m (or a preset --level 1..4).",
                                 param_hint="--rot-deg/--trans-m")
    check_writable([out], force, inputs=[poses])
    trajectory = read_trajectory(poses, fmt_value(fmt))
    out_fmt = fmt_value(fmt) or ("tum" if trajectory.timestamps is not None else "kitti")
    rng = np.random.default_rng(seed)
    T_noisy = perturb_poses(trajectory.T_world_scan, np.deg2rad(rot_deg), trans_m, rng,
                            keep_first=keep_first)
    write_trajectory(out, Trajectory(T_noisy, trajectory.timestamps), out_fmt, force)
    log.info("Wrote %d perturbed poses to %s (sigma %.4g deg, %.4g m, seed %d%s).", len(T_noisy),
             out, rot_deg, trans_m, seed, ", first pose kept" if keep_first else "")
