"""A rig folder: one scan folder per LiDAR (`lidar0/`, `lidar1/`, ...), scans matched to the base's.

`lidar0` is the base LiDAR: its scans define the base poses. Every other LiDAR's scan k is paired
with a base scan: by `times.txt` (one timestamp per scan, in the LiDAR's folder or the rig
folder, as `pa simulate` writes it) when every LiDAR has one, the nearest base scan within
`advanced.calibrate.time_match_tolerance_s`; otherwise by index (scan k with base scan k).
A `ScanSubset` (`--first/--last/--every`) keeps some of the base's scans; the other LiDARs' scans
are then matched to the kept ones (by time, or by their index in the whole base folder).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pa_cli.errors import InputError
from pa_cli.io.extrinsics import lidar_name
from pa_cli.sources import ScanSubset, SubsetSource, open_source
from pa_cli.sources.base import ScanSource

log = logging.getLogger(__name__)


@dataclass
class RigScans:
    """The scan sources of a rig and, per LiDAR k, its matched pairs (base scan t, scan of LiDAR k)."""

    rig_dir: Path
    sources: list[ScanSource]
    matches: list[np.ndarray]  # per LiDAR (M_k, 2) int64: base scan index, own scan index
    base_timestamps: np.ndarray | None  # (N,) s, from lidar0's times.txt
    matched_by: str  # "times.txt" or "index"

    @property
    def n_lidars(self) -> int:
        return len(self.sources)

    @property
    def n_base(self) -> int:
        return len(self.sources[0])

    def close(self) -> None:
        for source in self.sources:
            source.close()


def lidar_folders(rig_dir: Path) -> list[Path]:
    """lidar0/, lidar1/, ... of a rig folder, in order; errors name what is missing."""
    if not rig_dir.is_dir():
        raise InputError(f"{rig_dir}: rig folder not found; expected a folder holding lidar0/, lidar1/, ... "
                         "(one scan folder per LiDAR, lidar0 the base; `pa simulate --rig` writes one).")
    folders = []
    while (rig_dir / lidar_name(len(folders))).is_dir():
        folders.append(rig_dir / lidar_name(len(folders)))
    others = sorted(p.name for p in rig_dir.glob("lidar*") if p.is_dir() and p not in folders)
    if len(folders) < 2:
        raise InputError(f"{rig_dir}: found {len(folders)} of the scan folders lidar0/, lidar1/ a rig needs "
                         f"(other lidar folders: {', '.join(others) or 'none'}); put the base LiDAR's scans in "
                         "lidar0/ and each other LiDAR's in lidar1/, lidar2/, ...")
    if others:
        raise InputError(f"{rig_dir}: {', '.join(others)} do not continue lidar0..lidar{len(folders) - 1}; "
                         "number the LiDAR folders without gaps.")
    return folders


def match_by_time(base_s: np.ndarray, own_s: np.ndarray, tolerance_s: float) -> np.ndarray:
    """(M, 2) pairs (base index, own index): each own scan with the base scan nearest in time, kept
    within `tolerance_s`; a base scan keeps only its nearest own scan."""
    order = np.argsort(base_s)
    pos = np.clip(np.searchsorted(base_s[order], own_s), 1, len(base_s) - 1) if len(base_s) > 1 \
        else np.zeros(len(own_s), dtype=np.int64)
    left, right = order[np.maximum(pos - 1, 0)], order[pos]
    nearest = np.where(np.abs(base_s[left] - own_s) <= np.abs(base_s[right] - own_s), left, right)
    gap = np.abs(base_s[nearest] - own_s)
    own = np.flatnonzero(gap <= tolerance_s)
    best: dict[int, int] = {}
    for j in own[np.argsort(gap[own], kind="stable")]:
        best.setdefault(int(nearest[j]), int(j))
    pairs = np.array(sorted(best.items()), dtype=np.int64).reshape(-1, 2)
    return pairs


def open_rig(rig_dir: Path | str, time_match_tolerance_s: float, subset: ScanSubset | None = None) -> RigScans:
    """Open the scan folders of a rig, keep the base scans of `subset`, and match every LiDAR's scans
    to the base's."""
    rig_dir = Path(rig_dir)
    sources = [open_source(folder) for folder in lidar_folders(rig_dir)]
    for folder, source in zip(lidar_folders(rig_dir), sources, strict=True):
        if len(source) == 0:
            raise InputError(f"{folder}: no scans (PCD/PLY/BIN files) found; every LiDAR folder needs its scans.")
        source.check()
    counts = [len(source) for source in sources]  # whole folders, before the subset
    base_index = np.arange(counts[0])  # each kept base scan's index in the base folder
    if subset is not None and not subset.is_all:
        sources[0] = SubsetSource(sources[0], subset)
        base_index = sources[0].indices
    stamps = [source.timestamps().stamps_s for source in sources]
    if all(s is not None for s in stamps):
        matches = [np.column_stack([np.arange(len(sources[0]))] * 2)]
        for k in range(1, len(sources)):
            pairs = match_by_time(stamps[0], stamps[k], time_match_tolerance_s)
            if len(pairs) == 0:
                raise InputError(f"{rig_dir / lidar_name(k)}: no scan is within {time_match_tolerance_s} s of a "
                                 f"{lidar_name(0)} scan (times.txt); check the timestamps or raise "
                                 "advanced.calibrate.time_match_tolerance_s in the config.")
            matches.append(pairs)
        return RigScans(rig_dir, sources, matches, stamps[0], "times.txt")
    if len(set(counts)) > 1:
        log.warning("%s: the LiDAR folders hold %s scans and not every one has times.txt; matching scan k with "
                    "base scan k for the first %d.", rig_dir, "/".join(map(str, counts)), min(counts))
    kept = np.flatnonzero(base_index < min(counts))
    matches = [np.column_stack([kept, base_index[kept]]) for _ in sources]
    matches[0] = np.column_stack([np.arange(len(base_index))] * 2)
    return RigScans(rig_dir, sources, matches, stamps[0], "index")
