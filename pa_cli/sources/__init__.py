"""Scan sources: a folder of scan files or a ROS bag, behind one `ScanSource` protocol.

`open_source(path, topic=..., glob=...)` picks the source by path: a ROS1 `.bag`, a ROS2
`.db3`/`.mcap` file or bag folder -> `BagSource`; any other folder -> `FolderSource`.
A new source is a class with the `ScanSource` methods plus a branch here.
"""

from __future__ import annotations

from pathlib import Path

from pa_cli.errors import InputError, UsageError
from pa_cli.sources.bag import ROS1_SUFFIXES, ROS2_SUFFIXES, BagSource, is_bag_path
from pa_cli.sources.base import PointsView, ScanSource, ScanTimestamps
from pa_cli.sources.folder import FolderSource

__all__ = ["PointsView", "ScanSource", "ScanTimestamps", "open_source"]


def open_source(path: Path | str, *, topic: str | None = None, glob: str | None = None) -> ScanSource:
    """The scan source at `path`: a ROS bag (file or ROS2 folder) or a folder of scan files."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: scans not found; expected a folder of PCD/PLY/BIN scans or a ROS bag "
                         f"({' '.join(ROS1_SUFFIXES + ROS2_SUFFIXES)} file or ROS2 bag folder).")
    if is_bag_path(path):
        if glob is not None:
            raise UsageError(f"{path}: --glob selects files of a scan folder; a ROS bag takes --topic.")
        return BagSource(path, topic)
    if path.is_file():
        raise InputError(f"{path}: is a file; expected a folder of PCD/PLY/BIN scans or a ROS bag "
                         f"({' '.join(ROS1_SUFFIXES + ROS2_SUFFIXES)} file or ROS2 bag folder).")
    if topic is not None:
        raise UsageError(f"{path}: --topic selects a topic of a ROS bag; this is a folder of scan files.")

    return FolderSource(path, glob)
