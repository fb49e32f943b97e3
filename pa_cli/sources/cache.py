"""A `ScanSource` that keeps each scan's points (and per-point times) in memory after their first read."""

from __future__ import annotations

import numpy as np

from pa_cli.sources.base import (
    DescribesTimeField,
    PointTimeField,
    ReadIssues,
    ScanSource,
    ScanTimestamps,
    point_intensity,
    read_issues,
    scan_name,
)


class CachedSource:
    """Wrap a source: each scan is read once and kept as float32 (12 bytes per point, 4 more with times).

    Plane association reads every scan two or three times per round and the map write once
    more; scan files hold float32, so keeping float32 loses nothing. Per-point times are kept as
    their earliest value (float64) and float32 offsets from it: a sweep's offsets (under a
    second, or 1e8 ns) keep well below a microsecond, even when the times are absolute (UNIX
    time in s or ns, which float32 alone would round by minutes).

    The cache stops growing at `max_bytes`: scans first read after that are read from the source
    every time (the passes read scans in order, so keeping the first ones is as good as any).
    """

    def __init__(self, source: ScanSource, max_bytes: float = float("inf")) -> None:
        self.source = source
        self.name = source.name
        self.max_bytes = max_bytes
        self.n_bytes = 0
        self._scans: list[tuple[np.ndarray, tuple[float, np.ndarray] | None] | None] | None = None

    def __len__(self) -> int:
        return len(self.source)

    def check(self) -> None:
        """Check the source; its scan count may change (a bag's duplicated messages), so the cache starts empty."""
        self.source.check()
        self._scans = [None] * len(self.source)
        self.n_bytes = 0

    def _scan(self, k: int) -> tuple[np.ndarray, tuple[float, np.ndarray] | None]:
        if self._scans is None:
            self._scans = [None] * len(self.source)
        cached = self._scans[k]
        if cached is None:
            times = self.source.point_times(k)
            kept_times = None
            if times is not None:
                times = np.asarray(times)
                finite = times[np.isfinite(times)]
                first = finite.min() if len(finite) else times.dtype.type(0)
                kept_times = (float(first), (times - first).astype(np.float32))
            cached = (np.asarray(self.source.points(k), dtype=np.float32), kept_times)
            size = cached[0].nbytes + (0 if kept_times is None else kept_times[1].nbytes)
            if self.n_bytes + size <= self.max_bytes:
                self._scans[k] = cached
                self.n_bytes += size
        return cached

    def points(self, k: int) -> np.ndarray:
        return self._scan(k)[0].astype(np.float64)

    def point_times(self, k: int) -> np.ndarray | None:
        times = self._scan(k)[1]
        return None if times is None else times[0] + times[1].astype(np.float64)

    def point_intensity(self, k: int) -> np.ndarray | None:
        """Read from the source, not cached: only the map write reads them."""
        return point_intensity(self.source, k)

    def timestamps(self) -> ScanTimestamps:
        return self.source.timestamps()

    def time_field(self) -> PointTimeField | None:
        """The wrapped source's time field description (`DescribesTimeField`), else None."""
        return self.source.time_field() if isinstance(self.source, DescribesTimeField) else None

    def scan_name(self, k: int) -> str:
        return scan_name(self.source, k)

    def read_issues(self) -> ReadIssues:
        return read_issues(self.source)

    def close(self) -> None:
        self.source.close()
