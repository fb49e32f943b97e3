"""A `ScanSource` that keeps each scan's points (and per-point times) in memory after their first read."""

from __future__ import annotations

import numpy as np

from pa_cli.sources.base import ScanSource, ScanTimestamps, point_intensity


class CachedSource:
    """Wrap a source: each scan is read once and kept as float32 (12 bytes per point, 4 more with times).

    Plane association reads every scan two or three times per round and the map write once
    more; scan files hold float32, so keeping float32 loses nothing. Per-point times are
    relative to the scan's timestamp (under a second), so float32 keeps them to well below
    a microsecond.

    The cache stops growing at `max_bytes`: scans first read after that are read from the source
    every time (the passes read scans in order, so keeping the first ones is as good as any).
    """

    def __init__(self, source: ScanSource, max_bytes: float = float("inf")) -> None:
        self.source = source
        self.name = source.name
        self.max_bytes = max_bytes
        self.n_bytes = 0
        self._scans: list[tuple[np.ndarray, np.ndarray | None] | None] = [None] * len(source)

    def __len__(self) -> int:
        return len(self._scans)

    def check(self) -> None:
        self.source.check()

    def _scan(self, k: int) -> tuple[np.ndarray, np.ndarray | None]:
        cached = self._scans[k]
        if cached is None:
            times = self.source.point_times(k)
            cached = (np.asarray(self.source.points(k), dtype=np.float32),
                      None if times is None else np.asarray(times, dtype=np.float32))
            size = cached[0].nbytes + (0 if cached[1] is None else cached[1].nbytes)
            if self.n_bytes + size <= self.max_bytes:
                self._scans[k] = cached
                self.n_bytes += size
        return cached

    def points(self, k: int) -> np.ndarray:
        return self._scan(k)[0].astype(np.float64)

    def point_times(self, k: int) -> np.ndarray | None:
        times = self._scan(k)[1]
        return None if times is None else times.astype(np.float64)

    def point_intensity(self, k: int) -> np.ndarray | None:
        """Read from the source, not cached: only the map write reads them."""
        return point_intensity(self.source, k)

    def timestamps(self) -> ScanTimestamps:
        return self.source.timestamps()

    def close(self) -> None:
        self.source.close()
