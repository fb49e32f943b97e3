"""Scan sources: a folder of scan files, a ROS bag or a public dataset's layout, behind one
`ScanSource` protocol.

`open_source(path, topic=..., glob=..., subset=...)` picks the source by path, here and nowhere
else: a ROS1 `.bag`, a ROS2 `.db3`/`.mcap` file or bag folder -> `BagSource`; a dataset's sequence
or scan folder, or an Ouster `.pcap` (KITTI odometry, MulRan, Newer College, NCLT, Ouster:
`pa_cli.sources.datasets`) -> its dataset source, unless `--glob` asks for the folder's files;
any other folder -> `FolderSource`. A folder that holds no scans itself but sits above them (a
dataset root with `scans/`, KITTI's `sequences/`, a folder of bags) is refused with the path to
give instead. `subset` (`--first/--last/--every`) keeps some of the scans (`SubsetSource`). A
new source is a class with the `ScanSource` methods plus a branch here.
"""

from __future__ import annotations

from pathlib import Path

from pa_cli.errors import InputError, UsageError
from pa_cli.io.scans import SCAN_EXTENSIONS, written_by_pa
from pa_cli.sources.bag import ROS1_SUFFIXES, ROS2_SUFFIXES, BagSource, is_bag_path
from pa_cli.sources.base import PointsView, ScanSource, ScanTimestamps
from pa_cli.sources.datasets import OUSTER, describe_source, find_layout, open_dataset
from pa_cli.sources.folder import FolderSource
from pa_cli.sources.subset import ScanSubset, SubsetSource

__all__ = ["PointsView", "ScanSource", "ScanSubset", "ScanTimestamps", "SubsetSource", "check_out_of_scans",
           "describe_source", "open_source", "reads_scans_apart"]

# How far below a dataset root the scans are looked for (KITTI: ROOT/sequences/00/velodyne) and
# how many folders are looked into at most, so that a huge tree costs little.
LAYOUT_MAX_DEPTH = 3
LAYOUT_MAX_FOLDERS = 200
LAYOUT_SHOWN = 3  # sources named in the message


def open_source(path: Path | str, *, topic: str | None = None, glob: str | None = None,
                subset: ScanSubset | None = None) -> ScanSource:
    """The scan source at `path` (a ROS bag, a dataset layout or a folder of scan files), keeping
    only the scans of `subset` when it is given."""
    source = _open_all(Path(path), topic, glob)
    return source if subset is None or subset.is_all else SubsetSource(source, subset)


def reads_scans_apart(path: Path | str, glob: str | None = None) -> bool:
    """A task that opens the source at `path` (`open_source`) reads a window of its scans at about the cost of those
    scans: true for a folder of scan files and a dataset's files; false for a ROS bag (opening it reads every message
    of the topic once, for the header stamps) and an Ouster pcap (indexed packet by packet on opening), which each
    task would read whole."""
    path = Path(path)
    if is_bag_path(path):
        return False
    layout = find_layout(path) if glob is None else None
    return layout is None or layout.kind != OUSTER


def _open_all(path: Path, topic: str | None, glob: str | None) -> ScanSource:
    if not path.exists():
        raise InputError(f"{path}: scans not found; expected a folder of PCD/PLY/BIN scans, a ROS bag "
                         f"({' '.join(ROS1_SUFFIXES + ROS2_SUFFIXES)} file or ROS2 bag folder) or a dataset's "
                         "sequence folder (KITTI, MulRan, Newer College, NCLT) or Ouster .pcap.")
    if is_bag_path(path):
        if glob is not None:
            raise UsageError(f"{path}: --glob selects files of a scan folder; a ROS bag takes --topic.")
        return BagSource(path, topic)
    if glob is None:
        layout = find_layout(path)
        if layout is not None:
            if topic is not None:
                raise UsageError(f"{path}: --topic selects a topic of a ROS bag; this is a {layout.kind} dataset.")
            return open_dataset(layout)
    if path.is_file():
        raise InputError(f"{path}: is a file; expected a folder of PCD/PLY/BIN scans or a ROS bag "
                         f"({' '.join(ROS1_SUFFIXES + ROS2_SUFFIXES)} file or ROS2 bag folder).")
    if topic is not None:
        raise UsageError(f"{path}: --topic selects a topic of a ROS bag; this is a folder of scan files.")
    if glob is None:
        _refuse_dataset_root(path)
    return FolderSource(path, glob)


def check_out_of_scans(scans: Path | str, out: Path | str, force: bool) -> None:
    """`UsageError` when the output `out` would land inside the scan folder `scans` (unless `force`):
    a later run on the folder would find it among the scans."""
    scans, out = Path(scans), Path(out)
    if force or not scans.is_dir() or is_bag_path(scans):
        return
    if out.resolve().parent.is_relative_to(scans.resolve()):
        raise UsageError(f"{out}: --out is inside the scan folder {scans}, where a later run would find the map "
                         f"next to the scans; write it to another folder (e.g. --out {scans.parent / out.name}) "
                         "or pass --force to write it there anyway.")


def _holds_scans(folder: Path) -> bool:
    return any(p.suffix.lower() in SCAN_EXTENSIONS and p.is_file() and not written_by_pa(p) for p in folder.iterdir())


def _sources_below(root: Path) -> list[Path]:
    """Bags and folders of scans below `root`, nearest first (breadth first, at most
    `LAYOUT_MAX_DEPTH` levels and `LAYOUT_MAX_FOLDERS` folders, hidden folders skipped)."""
    from natsort import natsorted, ns

    found: list[Path] = []
    level, visited = [root], 0
    for _ in range(LAYOUT_MAX_DEPTH):
        below: list[Path] = []
        for folder in level:
            entries = natsorted(folder.iterdir(), alg=ns.PATH)
            found += [p for p in entries if p.is_file() and is_bag_path(p)]
            for sub in (p for p in entries if p.is_dir() and not p.name.startswith(".")):
                visited += 1
                if visited > LAYOUT_MAX_FOLDERS:
                    return found
                if is_bag_path(sub) or _holds_scans(sub):
                    found.append(sub)
                else:
                    below.append(sub)
        level = below
    return found


def _refuse_dataset_root(folder: Path) -> None:
    """`InputError` naming the path to give when `folder` holds no scans but bags or scan folders
    sit below it (a dataset root given for its `scans/`)."""
    if _holds_scans(folder):
        return
    below = _sources_below(folder)
    if not below:
        return  # FolderSource says what the folder holds
    first = below[0]
    topic = " --topic TOPIC" if is_bag_path(first) else ""
    others = [str(p) for p in below[1:LAYOUT_SHOWN]] + (["..."] if len(below) > LAYOUT_SHOWN else [])
    also = f" (also below it: {', '.join(others)})" if others else ""
    raise InputError(f"{folder}: no scan files ({' '.join(SCAN_EXTENSIONS)}) in the folder itself, but scans sit "
                     f"below it; did you mean {first}{topic}?{also}")
