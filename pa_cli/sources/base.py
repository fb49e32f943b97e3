"""The `ScanSource` protocol: where `pa refine` gets its scans from.

A source is a sequence of LiDAR scans in their sensor frame (metres). It knows how many scans
it holds, gives the points of scan k as an (N, 3) float64 array, their per-point times when the
data has them (seconds relative to the scan's timestamp) and the per-scan timestamps (seconds).
A source whose files may hold intensities also has `point_intensity(k)` (`IntensitySource`); read
them through `point_intensity(source, k)`, which gives None for the other sources.
Sources read lazily (one scan per access) and check every scan's header up front with
`check()`, so a corrupt scan is reported before any work.
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
        """Per-point times of scan k, (N,) float64 s relative to its timestamp, or None."""

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
