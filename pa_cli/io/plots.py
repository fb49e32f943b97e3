"""Plots written as PNG files (matplotlib's Agg backend: no display needed)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pa_cli.io.atomic import atomic_path


def plot_trajectories_top_view(path: Path | str, trajectories: Sequence[tuple[str, np.ndarray]],
                               title: str = "", force: bool = False) -> None:
    """Write a top view (world x-y, metres) of trajectories to a PNG, atomically.

    `trajectories`: (label, T_world_scan (N, 4, 4)) pairs, drawn in order; the start of each is
    marked. Uses matplotlib's Agg backend, so it works without a display.
    """
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 6), dpi=120)
    ax = fig.add_subplot(1, 1, 1)
    for label, T_world_scan in trajectories:
        xy = np.asarray(T_world_scan)[:, :2, 3]
        line = ax.plot(xy[:, 0], xy[:, 1], label=label, linewidth=1.2)[0]
        ax.plot(xy[:1, 0], xy[:1, 1], marker="o", color=line.get_color())
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, linewidth=0.3)
    ax.legend()
    if title:
        ax.set_title(title)
    fig.tight_layout()
    with atomic_path(path, force) as tmp:
        fig.savefig(tmp, format="png")
