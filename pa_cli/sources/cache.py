"""A `ScanSource` that keeps each scan's points in memory after their first read."""

from __future__ import annotations

import numpy as np

from pa_cli.sources.base import ScanSource, ScanTimestamps


class CachedSource:
    """Wrap a source: points are read once and kept as float32 (12 bytes per point).

    Plane association reads every scan two or three times per round and the map write once
    more; scan files hold float32, so keeping float32 loses nothing. Times and timestamps are
    passed through.
    """

    def __init__(self, source: ScanSource) -> None:
        self.source = source
        self.name = source.name
        self._points: list[np.ndarray | None] = [None] * len(source)

    def __len__(self) -> int:
        return len(self._points)

    def check(self) -> None:
        self.source.check()

    def points(self, k: int) -> np.ndarray:
        cached = self._points[k]
        if cached is None:
            cached = np.asarray(self.source.points(k), dtype=np.float32)
            self._points[k] = cached
        return cached.astype(np.float64)

    def point_times(self, k: int) -> np.ndarray | None:
        return self.source.point_times(k)

    def timestamps(self) -> ScanTimestamps:
        return self.source.timestamps()

    def close(self) -> None:
        self.source.close()
