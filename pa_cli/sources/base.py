"""The `ScanSource` protocol: where `pa refine` gets its scans from.

A source is a sequence of LiDAR scans in their sensor frame (metres). It knows how many scans
it holds, gives the points of scan k as an (N, 3) float64 array, their per-point times when the
data has them and the per-scan timestamps (seconds). A source whose files may hold intensities
also has `point_intensity(k)` (`IntensitySource`); read them through `point_intensity(source, k)`,
which gives None for the other sources. Sources read lazily (one scan per access) and check every
scan's header up front with `check()`, so a corrupt scan is reported before any work.

Per-point times are either as stored (a scan folder: raw values whose unit
`pa_cli.refine.deskew` detects) or, from a source that interprets its time field itself (a ROS
bag, `DescribesTimeField`), seconds from the scan's earliest point, whose instant is then the
scan's timestamp.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class ScanTimestamps:
    """Per-scan timestamps (s) or None, and where they came from (or why there are none)."""

    stamps_s: np.ndarray | None
    origin: str


@runtime_checkable
class ScanSource(Protocol):
    """A sequence of scans in their sensor frame; `name` names the source in messages."""

    name: str

    def __len__(self) -> int:
        """Number of scans."""

    def check(self) -> None:
        """Read every scan's header (cheaply) and raise a `PaError` naming the first bad one."""

    def points(self, k: int) -> np.ndarray:
        """Points of scan k, (N, 3) float64, sensor frame, metres."""

    def point_times(self, k: int) -> np.ndarray | None:
        """Per-point times of scan k, (N,) float64, or None (see the module docstring for the unit)."""

    def timestamps(self) -> ScanTimestamps:
        """Per-scan timestamps (s), or None with the reason."""

    def close(self) -> None:
        """Release open files."""


@runtime_checkable
class IntensitySource(Protocol):
    """A source that can give its scans' per-point intensities (besides the `ScanSource` methods)."""

    def point_intensity(self, k: int) -> np.ndarray | None:
        """Per-point intensities of scan k, (N,) float64 as stored in the data, or None."""


def point_intensity(source: ScanSource, k: int) -> np.ndarray | None:
    """Scan k's per-point intensities, (N,) as stored, or None (none in the data, or a source without them)."""
    return source.point_intensity(k) if isinstance(source, IntensitySource) else None


@dataclass(frozen=True)
class PointTimeField:
    """How a source reads its per-point times, for the report, or why it gives none.

    `name`, `dtype`: the field read (None: none is read); `unit` (s, ms, us, ns) and `absolute`: as
    detected from the values; `reference`: the instant `point_times` count from, in words;
    `stamp_minus_reference_s`: median over the scans of (header stamp - that instant), e.g. about
    +0.1 s for a driver that stamps a sweep at its end; `fields`: every field of the messages;
    `problem`: why no times are given (None when they are); `suspects`: fields that look like
    times but are not read (an unreadable time field, or one of an unknown name).
    """

    name: str | None
    dtype: str | None
    unit: str | None
    absolute: bool | None
    reference: str | None
    stamp_minus_reference_s: float | None
    fields: tuple[str, ...]
    problem: str | None = None
    suspects: tuple[str, ...] = ()

    def report(self) -> dict:
        """The report's `deskew.time_field` entry."""
        return {"name": self.name, "dtype": self.dtype, "unit": self.unit, "absolute": self.absolute,
                "reference_instant": self.reference, "stamp_minus_reference_s": self.stamp_minus_reference_s,
                "fields": list(self.fields)}


@runtime_checkable
class DescribesTimeField(Protocol):
    """A source that interprets its per-point time field itself (a ROS bag)."""

    def time_field(self) -> PointTimeField | None:
        """How the per-point times were read (None: not known, e.g. a wrapped folder source)."""


@dataclass(frozen=True)
class Skipped:
    """One scan (a file, a bag message) left out of the sequence: its name and why."""

    scan: str
    reason: str


@dataclass(frozen=True)
class ReadIssues:
    """What reading a source left out or changed, for the log and the report's `input.read_issues`.

    `skipped`: scans left out, each named with its reason; `n_reordered`: messages a bag stored out
    of the order of their header stamps (the scans are in stamp order); `stopped`: where a damaged
    input stopped being readable (None: read to its end).
    """

    skipped: tuple[Skipped, ...] = ()
    n_reordered: int = 0
    stopped: str | None = None

    def __add__(self, other: ReadIssues) -> ReadIssues:
        return ReadIssues(self.skipped + other.skipped, self.n_reordered + other.n_reordered,
                          "; ".join(s for s in (self.stopped, other.stopped) if s) or None)

    def report(self) -> dict:
        """The report's `input.read_issues` entry: counts by reason and every skipped scan named."""
        by_reason: dict[str, int] = {}
        for skip in self.skipped:
            by_reason[skip.reason] = by_reason.get(skip.reason, 0) + 1
        return {"n_skipped": len(self.skipped), "skipped_by_reason": by_reason,
                "skipped": [{"scan": s.scan, "reason": s.reason} for s in self.skipped],
                "n_reordered": self.n_reordered, "stopped": self.stopped}


@runtime_checkable
class ReportsReadIssues(Protocol):
    """A source that can leave scans out (a bag's duplicated stamps, scans without valid points)."""

    def read_issues(self) -> ReadIssues:
        """What reading left out or changed so far (complete after `check()`)."""


def read_issues(source: ScanSource) -> ReadIssues:
    """The source's `ReadIssues`, or none for a source that never leaves scans out."""
    return source.read_issues() if isinstance(source, ReportsReadIssues) else ReadIssues()


@runtime_checkable
class NamesScans(Protocol):
    """A source that can name one scan in a message (its file, its bag message and stamp)."""

    def scan_name(self, k: int) -> str:
        """Scan k as a person finds it: a file path, a bag message with its stamp."""


def scan_name(source: ScanSource, k: int) -> str:
    """Scan k of `source` named for a message (`NamesScans`), else `"<source> scan k"`."""
    return source.scan_name(k) if isinstance(source, NamesScans) else f"{source.name} scan {k}"


class IndexedSource:
    """The scans of `source` at `indices` (scan k is the source's scan `indices[k]`; None: every scan),
    every reading method passing through with the index mapped: the base of a subset
    (`pa_cli.sources.subset`) and of the screen of scans without valid points (`pa_cli.sources.screen`)."""

    def __init__(self, source: ScanSource, indices: np.ndarray | None) -> None:
        self.source = source
        self.name = source.name
        self.indices = indices

    def __len__(self) -> int:
        return len(self.source) if self.indices is None else len(self.indices)

    def _k(self, k: int) -> int:
        return k if self.indices is None else int(self.indices[k])

    def check(self) -> None:
        self.source.check()

    def points(self, k: int) -> np.ndarray:
        return self.source.points(self._k(k))

    def point_times(self, k: int) -> np.ndarray | None:
        return self.source.point_times(self._k(k))

    def point_intensity(self, k: int) -> np.ndarray | None:
        return point_intensity(self.source, self._k(k))

    def scan_name(self, k: int) -> str:
        return scan_name(self.source, self._k(k))

    def read_issues(self) -> ReadIssues:
        return read_issues(self.source)

    def timestamps(self) -> ScanTimestamps:
        found = self.source.timestamps()
        if found.stamps_s is None or self.indices is None:
            return found
        return ScanTimestamps(found.stamps_s[self.indices], self.timestamps_origin(found.origin))

    def timestamps_origin(self, origin: str) -> str:
        """Where the kept scans' timestamps come from, in words (the source's by default)."""
        return origin

    def time_field(self) -> PointTimeField | None:
        """The wrapped source's time field description (`DescribesTimeField`), else None."""
        return self.source.time_field() if isinstance(self.source, DescribesTimeField) else None

    def close(self) -> None:
        self.source.close()


class PointsView:
    """`Sequence[np.ndarray]` of a source's scan points (what plane association consumes)."""

    def __init__(self, source: ScanSource) -> None:
        self._source = source

    def __len__(self) -> int:
        return len(self._source)

    def __getitem__(self, k: int) -> np.ndarray:
        if not -len(self) <= k < len(self):
            raise IndexError(k)
        return self._source.points(k % len(self))
