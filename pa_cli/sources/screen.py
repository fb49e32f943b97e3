"""Leave out the scans that hold too few valid points, named and counted.

A scan whose points are all at the origin (a driver's mark for no return), all NaN, or fewer
than `MIN_VALID_POINTS` cannot be registered and adds nothing to the map. `ScreenedSource.check()`
reads every scan once (through the point cache when the source is wrapped in one, so the
odometry then reads from memory), keeps the others in their order and names each scan left out
in the log and in `read_issues()` (the report's `input.read_issues`). A run in which no scan is
left is an `InputError`.

The kept scans' indices (`indices`) refer to the wrapped source; whoever opens the source again
(a dask worker) reads scan k as the wrapped source's scan `indices[k]`.
"""

from __future__ import annotations

import logging

import numpy as np

from pa_cli.errors import InputError
from pa_cli.sources.base import IndexedSource, ReadIssues, ScanSource, Skipped, read_issues, scan_name

log = logging.getLogger(__name__)

# Fewer valid points than this cannot be registered: KISS-ICP's adaptive threshold and the plane
# observations (10 points each, several surfaces) need hundreds; a LiDAR sweep holds thousands.
MIN_VALID_POINTS = 100
NAMES_LOGGED = 5  # scans named in the log record (the report names all)


def n_valid_points(points: np.ndarray) -> int:
    """Points with finite coordinates that are not at exactly (0, 0, 0)."""
    points = np.asarray(points)
    return int((np.isfinite(points).all(axis=1) & points.any(axis=1)).sum())


class ScreenedSource(IndexedSource):
    """The scans of `source` with at least `min_points` valid points (decided by `check()`; every scan
    before it)."""

    def __init__(self, source: ScanSource, min_points: int = MIN_VALID_POINTS) -> None:
        super().__init__(source, None)
        self.min_points = min_points
        self._skipped: tuple[Skipped, ...] = ()

    def check(self) -> None:
        """Check the wrapped source, then read every scan once and leave out those with too few valid points."""
        self.source.check()
        n_valid = np.array([n_valid_points(self.source.points(k)) for k in range(len(self.source))], dtype=int)
        few = n_valid < self.min_points
        self._skipped = tuple(Skipped(scan_name(self.source, int(k)), _reason(int(n_valid[k]), self.min_points))
                              for k in np.flatnonzero(few))
        if few.all():
            raise InputError(f"{self.name}: none of the {len(n_valid)} scans holds {self.min_points} or more valid "
                             "points (finite, not at the origin); the most in one scan is "
                             f"{n_valid.max(initial=0)}. Check that the scans hold x y z in metres (a driver "
                             "that marks no return with 0 0 0 or NaN, a wrong --topic or --glob).")
        if few.any():
            names = ", ".join(f"{s.scan} ({s.reason})" for s in self._skipped[:NAMES_LOGGED])
            more = f", ... ({len(self._skipped)} in all, each in the report)" if len(self._skipped) > NAMES_LOGGED \
                else ""
            log.warning("%s: %d of %d scans hold fewer than %d valid points (finite, not at the origin) and are "
                        "skipped: %s%s", self.name, len(self._skipped), len(n_valid), self.min_points, names, more)
        self.indices = np.flatnonzero(~few)

    @property
    def kept(self) -> np.ndarray | None:
        """The wrapped source's indices of the scans kept (None before `check()`)."""
        return self.indices

    def skipped_indices(self) -> tuple[int, ...]:
        """The wrapped source's indices of the scans left out (after `check()`), for `kept_indices`."""
        if self.indices is None:
            return ()
        return tuple(int(k) for k in np.setdiff1d(np.arange(len(self.source)), self.indices))

    def read_issues(self) -> ReadIssues:
        """The wrapped source's issues, then the scans left out here."""
        return read_issues(self.source) + ReadIssues(self._skipped)


def kept_indices(skipped: tuple[int, ...], first: int, stop: int) -> np.ndarray:
    """The source's indices of scans first..stop-1 of the sequence that leaves out `skipped`
    (`ScreenedSource.skipped_indices`)."""
    return np.setdiff1d(np.arange(stop + len(skipped)), np.asarray(skipped, dtype=int))[first:stop]


def _reason(n_valid: int, min_points: int) -> str:
    return "no valid point" if n_valid == 0 else f"fewer than {min_points} valid points"
