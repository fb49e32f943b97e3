"""Scans already in memory (from Python code) as a `ScanSource`."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pa_cli.sources.base import ScanTimestamps


class ArraySource:
    """A `ScanSource` over (N, 3) scan-frame point arrays, with optional per-point times and timestamps (s)."""

    def __init__(self, points_scan: Sequence[np.ndarray], point_times_s: Sequence[np.ndarray] | None = None,
                 timestamps_s: np.ndarray | None = None, name: str = "arrays") -> None:
        self._points = points_scan
        self._times = point_times_s
        self._stamps = None if timestamps_s is None else np.asarray(timestamps_s, dtype=np.float64)
        self.name = name

    def __len__(self) -> int:
        return len(self._points)

    def check(self) -> None:
        """Nothing to read: arrays are checked by whoever made them."""

    def points(self, k: int) -> np.ndarray:
        return np.asarray(self._points[k], dtype=np.float64)

    def point_times(self, k: int) -> np.ndarray | None:
        return None if self._times is None else np.asarray(self._times[k], dtype=np.float64)

    def timestamps(self) -> ScanTimestamps:
        return ScanTimestamps(self._stamps, self.name if self._stamps is not None else f"{self.name}: none given")

    def close(self) -> None:
        """Nothing to release."""
