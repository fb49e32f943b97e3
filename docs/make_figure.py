"""Make docs/map_before_after.png: a horizontal slice of the sample-data map under the KISS-ICP
poses and under the refined poses.

    pa refine sample_data/office/scans --out /tmp/office.ply --config indoor --force
    python docs/make_figure.py /tmp/office.ply
"""

from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from pa_cli.io.scans import ScanFolder  # noqa: E402
from pa_cli.io.trajectory import read_trajectory  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SLICE_Z_M = (0.9, 1.5)  # world heights kept in the top view (m)
ZOOM = ((-3.5, 11.0), (3.5, 9.7))  # x and y limits of the zoomed panels (m)


def slice_world(scans: ScanFolder, T_world_scan: np.ndarray) -> np.ndarray:
    parts = []
    for k in range(len(scans)):
        p = scans.points[k] @ T_world_scan[k, :3, :3].T + T_world_scan[k, :3, 3]
        parts.append(p[(p[:, 2] > SLICE_Z_M[0]) & (p[:, 2] < SLICE_Z_M[1])])
    return np.concatenate(parts)


def main() -> None:
    map_ply = Path(sys.argv[1])
    stem = map_ply.with_suffix("")
    scans = ScanFolder(REPO / "sample_data" / "office" / "scans")
    T_initial = read_trajectory(f"{stem}_initial_poses_kitti.txt").T_world_scan
    T_refined = read_trajectory(f"{stem}_poses_kitti.txt").T_world_scan
    fig, axes = plt.subplots(2, 2, figsize=(11, 9), gridspec_kw={"height_ratios": [1, 1.1]})
    for col, (T, title) in enumerate(((T_initial, "KISS-ICP poses"), (T_refined, "after pa refine"))):
        q = slice_world(scans, T)
        for row, (s, zoom) in enumerate(((0.05, None), (0.4, ZOOM))):
            ax = axes[row, col]
            ax.scatter(q[:, 0], q[:, 1], s=s, c="k", alpha=0.4, linewidths=0)
            ax.plot(T[:, 0, 3], T[:, 1, 3], "r-", lw=1.5, label="trajectory")
            if zoom is not None:
                ax.set_xlim(*zoom[0])
                ax.set_ylim(*zoom[1])
                ax.set_title(f"{title}: zoom on the room at the top left")
            else:
                ax.set_title(f"{title}: slice z in [{SLICE_Z_M[0]}, {SLICE_Z_M[1]}] m")
            ax.set_aspect("equal")
            ax.set_xlabel("x (m)")
            ax.set_ylabel("y (m)")
    axes[0, 0].legend(loc="lower right")
    fig.suptitle("sample_data/office: all 40 scans merged (world frame = scan 0)")
    fig.tight_layout()
    fig.savefig(REPO / "docs" / "map_before_after.png", dpi=110)


if __name__ == "__main__":
    main()
