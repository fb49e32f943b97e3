"""A subset of a source's scans: `--first N --last M --every K`.

Indices are 0-based positions in the source's scan order (the sorted files, the bag's messages);
`first` and `last` are both kept (inclusive), `every` keeps every K-th scan from `first`. A
`last` beyond the source's last scan means its last scan. Scan k of the subset is scan
`indices[k]` of the source; a trajectory with one pose per source scan (`--poses`, a KITTI
`--gt`) follows with `follow`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pa_cli.errors import UsageError
from pa_cli.io.trajectory import Trajectory
from pa_cli.sources.base import IndexedSource, ScanSource


@dataclass(frozen=True)
class ScanSubset:
    """Scans first..last (0-based, both inclusive; None: to the end), every `every`-th."""

    first: int = 0
    last: int | None = None
    every: int = 1

    def __post_init__(self) -> None:
        if self.first < 0 or (self.last is not None and self.last < 0) or self.every < 1:
            raise UsageError(f"--first {self.first} --last {self.last} --every {self.every}: --first and --last "
                             "are 0-based scan indices (at least 0) and --every is at least 1.")
        if self.last is not None and self.last < self.first:
            raise UsageError(f"--last {self.last} is before --first {self.first}; both are 0-based scan indices "
                             "and both are kept.")

    @property
    def is_all(self) -> bool:
        """Whether the subset keeps every scan."""
        return self.first == 0 and self.last is None and self.every == 1

    def indices(self, n_scans: int, name: str) -> np.ndarray:
        """The kept indices of a source of `n_scans` scans; `UsageError` naming `name` when none is kept."""
        if self.first >= n_scans:
            raise UsageError(f"{name}: --first {self.first} but the source holds {n_scans} scans (indices 0.."
                             f"{n_scans - 1}); give a smaller --first.")
        stop = n_scans if self.last is None else min(self.last + 1, n_scans)
        return np.arange(self.first, stop, self.every)

    def describe(self) -> str:
        """The subset in words, for the log and the report."""
        last = "the last scan" if self.last is None else f"scan {self.last}"
        every = "" if self.every == 1 else f", one scan in {self.every}"
        return f"scans {self.first} to {last}{every} (0-based, inclusive)"


class SubsetSource(IndexedSource):
    """The scans of `source` at `indices` (a `ScanSubset`'s), scan k being the source's `indices[k]`."""

    def __init__(self, source: ScanSource, subset: ScanSubset) -> None:
        super().__init__(source, subset.indices(len(source), source.name))
        self.subset = subset
        self.n_source = len(source)

    def timestamps_origin(self, origin: str) -> str:
        return f"{origin}, {self.subset.describe()}"

    def select_poses(self, T: np.ndarray) -> np.ndarray | None:
        """The rows of `T` (poses or timestamps, one per source scan) of the kept scans, or None when
        `T` does not have one row per source scan."""
        return np.asarray(T)[self.indices] if len(T) == self.n_source else None

    def follow(self, trajectory: Trajectory, by_time: bool) -> Trajectory:
        """`trajectory` for the kept scans: its kept poses (and timestamps) when it has one pose per
        source scan, unless `by_time` and it has timestamps (then it pairs with the kept scans by time
        and stays whole); else as it is (the count check of its user names the mismatch)."""
        kept = self.select_poses(trajectory.T_world_scan)
        if kept is None or (by_time and trajectory.timestamps is not None):
            return trajectory
        stamps = None if trajectory.timestamps is None else trajectory.timestamps[self.indices]
        return Trajectory(kept, stamps, trajectory.source)
