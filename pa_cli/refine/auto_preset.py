"""The preset for scans given without `--config`: chosen from what the scans show, said in words.

A few scans spread over the sequence are read. Their ranges (distance of each point from the
sensor) tell the scene's scale: where all but a few stray returns come from within the indoor
preset's range (`sensor.max_range_m`, 30 m), the scene is a room, hall or corridor (`indoor`:
0.5 m plane voxels, fine map); else a street or campus (`outdoor`). The points per scan, the rings
(beams) and the per-point times are reported with the choice; motion compensation follows the times
by itself (`sensor.deskew: auto`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pa_cli.config import load_config

SAMPLED_SCANS = 5  # scans read to decide, spread evenly over the sequence (first and last included)
# the scene's scale: the range all returns but the farthest 0.1 % lie within (a few stray far returns
# through a door or window do not make a room a street; the far end of a street or campus does)
RANGE_PERCENTILE = 99.9
RING_BIN_DEG = 0.1  # elevation histogram bin for counting rings; below any spinning LiDAR's ring spacing
MIN_RING_SHARE = 0.002  # an elevation bin holding at least this share of the points (and a local peak) is a ring
MIN_RINGED_SHARE = 0.5  # rings are reported when their bins (and their neighbours) hold this share of the points


@dataclass(frozen=True)
class PresetChoice:
    """The preset chosen (`name`) and the measurements behind it."""

    name: str
    range_m: float  # RANGE_PERCENTILE percentile of the sampled points' ranges
    points_per_scan: int  # median over the sampled scans
    rings: int  # elevation rings counted in the sampled scans (0: not a spinning sensor's pattern)
    with_times: bool  # some sampled scan carries per-point times

    def reason(self) -> str:
        """The choice in one sentence, for the log."""
        scale = "within" if self.name == "indoor" else "beyond"
        indoor_m = load_config("indoor").sensor.max_range_m
        rings = f", about {self.rings} rings" if self.rings else ""
        times = "per-point times (motion compensation on)" if self.with_times else "no per-point times"
        return (f"no --config: using the {self.name} preset: {RANGE_PERCENTILE:g} % of the returns lie within "
                f"{self.range_m:.1f} m ({scale} the indoor preset's range, {indoor_m:g} m); "
                f"{self.points_per_scan:,} points per scan{rings}; {times}. Give --config indoor|outdoor|PATH "
                "to choose yourself (pa config show PRESET prints one).")


def count_rings(points_scan: np.ndarray) -> int:
    """Local peaks of the points' elevation histogram (RING_BIN_DEG bins) holding at least
    MIN_RING_SHARE of the points: the rings (beams) of a spinning LiDAR; 0 when the peaks and their
    neighbouring bins hold less than MIN_RINGED_SHARE of the points (no ring pattern: a thinned or
    merged cloud, a solid-state sensor)."""
    if len(points_scan) == 0:
        return 0
    horizontal = np.hypot(points_scan[:, 0], points_scan[:, 1])
    elevation_deg = np.degrees(np.arctan2(points_scan[:, 2], horizontal))
    edges = np.arange(elevation_deg.min(), elevation_deg.max() + 2 * RING_BIN_DEG, RING_BIN_DEG)
    counts, _ = np.histogram(elevation_deg, edges)
    padded = np.r_[0, counts, 0]
    rings = (padded[1:-1] >= padded[:-2]) & (padded[1:-1] > padded[2:]) & (counts >= MIN_RING_SHARE * len(points_scan))
    near_rings = np.convolve(rings, np.ones(3))[1:-1] > 0  # a peak's bin and its neighbours, as many as bins
    return int(rings.sum()) if counts[near_rings].sum() >= MIN_RINGED_SHARE * len(points_scan) else 0


def choose_preset(source: Any) -> PresetChoice:
    """The preset for `source` (a `pa_cli.sources.ScanSource`, at least one scan) from SAMPLED_SCANS of its scans."""
    n = len(source)
    picked = np.unique(np.linspace(0, n - 1, min(n, SAMPLED_SCANS)).round().astype(int))
    ranges, sizes, rings, with_times = [], [], [], False
    for k in picked:
        points = np.asarray(source.points(int(k)), dtype=np.float64)
        points = points[np.isfinite(points).all(axis=1) & points.any(axis=1)]  # (0, 0, 0): no return
        r = np.linalg.norm(points, axis=1)
        ranges.append(r[r > 0])
        sizes.append(len(points))
        rings.append(count_rings(points))
        with_times = with_times or source.point_times(int(k)) is not None
    all_ranges = np.concatenate(ranges)
    range_m = float(np.percentile(all_ranges, RANGE_PERCENTILE)) if len(all_ranges) else 0.0
    name = "indoor" if range_m <= load_config("indoor").sensor.max_range_m else "outdoor"
    return PresetChoice(name, range_m, int(np.median(sizes)), int(np.median(rings)), with_times)
