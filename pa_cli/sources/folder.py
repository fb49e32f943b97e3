"""A folder of PCD / PLY / KITTI BIN scans (read by `pa_cli.io.scans`), sorted naturally.

One format per folder (`--glob` picks one where there are several); the maps pa writes are
skipped (`pa_cli.io.scans.list_scan_files`).

Per-scan timestamps come from `times.txt` (one line per scan, seconds) in the folder or its
parent, the layout of KITTI odometry sequences and of `pa simulate` output.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pa_cli.io.scans import Scan, check_scan_header, list_scan_files, read_scan
from pa_cli.io.trajectory import read_timestamps
from pa_cli.sources.base import ScanTimestamps

TIMES_FILE = "times.txt"


class FolderSource:
    """The scans of a folder, one file per scan, each read on access (`pa refine SCANS` with a folder)."""

    def __init__(self, folder: Path | str, glob: str | None = None) -> None:
        self.folder = Path(folder)
        self.files = list_scan_files(self.folder, glob)
        self.name = str(self.folder)
        self._last: tuple[int, Scan] | None = None

    def __len__(self) -> int:
        return len(self.files)

    def scan_name(self, k: int) -> str:
        """Scan k's file."""
        return str(self.files[k])

    def check(self) -> None:
        for path in self.files:
            check_scan_header(path)

    def scan(self, k: int) -> Scan:
        """Scan k as read from its file (the last one read is kept, so points and times share a read)."""
        if self._last is None or self._last[0] != k:
            self._last = (k, read_scan(self.files[k]))
        return self._last[1]

    def points(self, k: int) -> np.ndarray:
        return self.scan(k).points_scan

    def point_times(self, k: int) -> np.ndarray | None:
        return self.scan(k).time

    def point_intensity(self, k: int) -> np.ndarray | None:
        return self.scan(k).intensity

    def timestamps(self) -> ScanTimestamps:
        candidates = (self.folder / TIMES_FILE, self.folder.parent / TIMES_FILE)
        ignored = []
        for candidate in candidates:
            if candidate.is_file():
                stamps = read_timestamps(candidate)
                if len(stamps) == len(self):
                    return ScanTimestamps(stamps, str(candidate))
                ignored.append(f"{candidate} has {len(stamps)} timestamps for {len(self)} scans (ignored)")
        if not ignored:
            return ScanTimestamps(None, f"no {TIMES_FILE} in {self.folder} or its parent")
        return ScanTimestamps(None, "; ".join(ignored))

    def close(self) -> None:
        self._last = None
