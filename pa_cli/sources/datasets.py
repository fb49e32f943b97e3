"""Public dataset layouts as scan sources: KITTI odometry, MulRan, Newer College, NCLT, Ouster pcap.

`find_layout(path)` recognises a dataset's sequence folder (or its scan folder, or an Ouster
`.pcap`) by the names the dataset uses, and `open_dataset(layout)` opens it as a `ScanSource`:

- KITTI odometry: scans `SEQ/velodyne/*.bin`, timestamps `SEQ/times.txt`, no per-point times,
  ground truth `ROOT/poses/SEQ.txt` or `SEQ/poses.txt`;
- MulRan: scans `SEQ/Ouster/<ns>.bin` (or `SEQ/sensor_data/Ouster`), timestamps from the file
  names, per-point times from the point order, ground truth `SEQ/global_pose.csv`;
- Newer College: scans `SEQ/raw_format/ouster_scan/cloud_<s>_<ns>.pcd`, timestamps from the file
  names, per-point times from the PCD's `t` (ns), ground truth `SEQ/ground_truth/registered_poses.csv`;
- NCLT: scans `SEQ/velodyne_sync/<us>.bin`, timestamps from the file names, no per-point times,
  ground truth `groundtruth_SEQ.csv` in `SEQ/../ground_truth`, `SEQ/..` or `SEQ`;
- Ouster pcap: a `.pcap` and its metadata `.json`, timestamps and per-point times from the
  columns' timestamps, no ground truth.

KITTI and MulRan scans are KITTI `.bin` files and Newer College scans PCD files, read like a scan
folder (`FolderSource`); NCLT's `velodyne_sync` files (uint16 x y z scaled by 5 mm from -100 m,
uint8 intensity and laser, 8 bytes per point; `NCLT_*`) are read here, turned z-up as KISS-ICP's
`NCLTDataset` turns them (x, -y, -z), so that its ground-truth conversion applies. MulRan's Ouster
files keep all 64 x 1024 returns column by column: a scan of exactly that many points gets
per-point times from the point order (KISS-ICP's `MulranDataset.get_timestamps`, a fraction of
the sweep) times the sweep period (the median interval of the scans' timestamps); other scans
get none, as in KISS-ICP. Ouster pcap files are decoded by `pa_cli.sources.ouster` (the few packet
profiles it does not decode, with ouster-sdk when the user installed it). The ground truth of each
dataset is read by `pa_cli.io.dataset_gt` when given with `--gt`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pa_cli.errors import FormatError, InputError
from pa_cli.io.scans import KITTI_BIN_BYTES_PER_POINT, read_scan
from pa_cli.sources.base import ScanSource, ScanTimestamps
from pa_cli.sources.folder import TIMES_FILE, FolderSource
from pa_cli.sources.ouster import open_ouster_pcap

KITTI, MULRAN, NCD, NCLT, OUSTER = "KITTI odometry", "MulRan", "Newer College", "NCLT", "Ouster pcap"
MULRAN_COLUMNS, MULRAN_BEAMS = 1024, 64  # MulRan's OS1-64 in 1024x10 mode: every return kept, column by column
MULRAN_SWEEP_S = 0.1  # its sweep at 10 Hz, for a sequence of one scan (no interval to measure)
NCLT_SCALE_M, NCLT_OFFSET_M = 0.005, -100.0  # NCLT's velodyne_sync coordinates: raw * 5 mm - 100 m
NCLT_POINT = np.dtype([("x", "<u2"), ("y", "<u2"), ("z", "<u2"), ("intensity", "u1"), ("laser", "u1")])
NCD_NAME = re.compile(r"^cloud_(\d+)_(\d+)\.pcd$")
DIGITS = re.compile(r"^\d+$")


@dataclass(frozen=True)
class Layout:
    """A recognised dataset: its `kind` (one of the names above), the sequence folder `root`, where
    the scans are (`scans`: a folder, or the `.pcap` file), the ground truth found (or None) and,
    for an Ouster pcap, its metadata file."""

    kind: str
    root: Path
    scans: Path
    gt: Path | None = None
    metadata: Path | None = None


def find_layout(path: Path) -> Layout | None:
    """The dataset layout at `path` (a sequence folder, its scan folder or an Ouster `.pcap`), or None."""
    if path.is_file():
        return _ouster_layout(path) if path.suffix.lower() == ".pcap" else None
    if not path.is_dir():
        return None
    for root in (path, path.parent, path.parent.parent):
        layout = _layout_of_root(root, path)
        if layout is not None:
            return layout
    pcaps = sorted(path.glob("*.pcap"))
    return _ouster_layout(pcaps[0]) if len(pcaps) == 1 else None


def _layout_of_root(root: Path, given: Path) -> Layout | None:
    """The layout whose sequence folder is `root`, when `given` is that folder or its scan folder."""
    candidates = [
        (KITTI, root / "velodyne", "*.bin"),
        (MULRAN, root / "Ouster", "*.bin"),
        (MULRAN, root / "sensor_data" / "Ouster", "*.bin"),
        (NCD, root / "raw_format" / "ouster_scan", "cloud_*.pcd"),
        (NCLT, root / "velodyne_sync", "*.bin"),
    ]
    for kind, scans, pattern in candidates:
        if given not in (root, scans) or not scans.is_dir() or next(scans.glob(pattern), None) is None:
            continue
        if kind == KITTI and given == scans and not any((root / f).is_file() for f in ("calib.txt", TIMES_FILE)):
            continue  # a folder named velodyne/ without KITTI's files beside it is a plain scan folder
        return Layout(kind, root, scans, _ground_truth(kind, root))
    return None


def _ground_truth(kind: str, root: Path) -> Path | None:
    """The dataset's own ground-truth file for the sequence at `root`, where the dataset keeps it."""
    candidates = {
        KITTI: [root.parent.parent / "poses" / f"{root.name}.txt", root / "poses.txt"],
        MULRAN: [root / "global_pose.csv"],
        NCD: [root / "ground_truth" / "registered_poses.csv"],
        NCLT: [root.parent / "ground_truth" / f"groundtruth_{root.name}.csv",
               root.parent / f"groundtruth_{root.name}.csv", root / f"groundtruth_{root.name}.csv"],
    }[kind]
    return next((p for p in candidates if p.is_file()), None)


def _ouster_layout(pcap: Path) -> Layout:
    """An Ouster pcap and its metadata: `NAME.json` beside it, else the `.json` sharing the longest
    name prefix with the pcap (as ouster-sdk and KISS-ICP match them)."""
    same = pcap.with_suffix(".json")
    if same.is_file():
        return Layout(OUSTER, pcap.parent, pcap, metadata=same)
    jsons = sorted(pcap.parent.glob("*.json"))
    if not jsons:
        raise InputError(f"{pcap}: an Ouster pcap needs the sensor's metadata .json recorded with it; none in "
                         f"{pcap.parent}. Put it beside the pcap as {same.name}.")
    best = max(jsons, key=lambda j: len(_common_prefix(j.stem, pcap.stem)))
    return Layout(OUSTER, pcap.parent, pcap, metadata=best)


def _common_prefix(a: str, b: str) -> str:
    n = 0
    while n < min(len(a), len(b)) and a[n] == b[n]:
        n += 1
    return a[:n]


def open_dataset(layout: Layout) -> ScanSource:
    """The scan source of a recognised dataset layout."""
    if layout.kind == OUSTER:
        return open_ouster_pcap(layout.scans, layout.metadata)
    if layout.kind == NCLT:
        return DatasetSource(layout, NcltFiles(layout.scans))
    return DatasetSource(layout, FolderSource(layout.scans, "cloud_*.pcd" if layout.kind == NCD else "*.bin"))


def describe_source(source: object) -> str | None:
    """One line on what a dataset source found (layout, scans, per-point times, ground truth), or
    None for a source that is not a dataset's; a wrapping source (subset, cache) is looked through."""
    while source is not None:
        describe = getattr(source, "describe", None)
        if callable(describe):
            return describe()
        source = getattr(source, "source", None)
    return None


def stamps_from_names(files: list[Path], kind: str) -> np.ndarray:
    """Per-scan timestamps (s) from the dataset's file names: MulRan `<ns>.bin`, NCLT `<us>.bin`,
    Newer College `cloud_<s>_<ns>.pcd`; `FormatError` naming the first file not so named."""
    stamps = np.empty(len(files))
    for k, path in enumerate(files):
        if kind == NCD:
            match = NCD_NAME.match(path.name)
            if match is None:
                raise FormatError(f"{path}: Newer College scans are named cloud_<seconds>_<nanoseconds>.pcd; "
                                  "rename it, or read the folder as plain scan files with --glob '*.pcd'.")
            stamps[k] = int(match.group(1)) + int(match.group(2)) * 1e-9
        else:
            if not DIGITS.match(path.stem):
                unit = "nanoseconds" if kind == MULRAN else "microseconds"
                raise FormatError(f"{path}: {kind} scans are named by their time in {unit} (e.g. "
                                  f"{'1566535665113759000' if kind == MULRAN else '1326030975726043'}.bin); "
                                  "rename it, or read the folder as plain scan files with --glob '*.bin'.")
            stamps[k] = int(path.stem) / (1e9 if kind == MULRAN else 1e6)
    return stamps


class NcltFiles:
    """NCLT's `velodyne_sync/*.bin` scans (see the module docstring), one file per scan, sorted by name."""

    def __init__(self, folder: Path) -> None:
        from natsort import natsorted

        self.folder = folder
        self.files = natsorted(folder.glob("*.bin"), key=lambda p: p.name)
        self.name = str(folder)

    def __len__(self) -> int:
        return len(self.files)

    def check(self) -> None:
        for path in self.files:
            size = path.stat().st_size
            if size % NCLT_POINT.itemsize:
                raise FormatError(f"{path}: {size} bytes is not a multiple of {NCLT_POINT.itemsize}; an NCLT "
                                  "velodyne_sync scan holds uint16 x y z, uint8 intensity and laser per point.")

    def points(self, k: int) -> np.ndarray:
        raw = np.fromfile(self.files[k], dtype=NCLT_POINT)
        xyz = np.column_stack([raw["x"], raw["y"], raw["z"]]).astype(np.float64) * NCLT_SCALE_M + NCLT_OFFSET_M
        return xyz * np.array([1.0, -1.0, -1.0])

    def point_times(self, k: int) -> np.ndarray | None:
        return None

    def point_intensity(self, k: int) -> np.ndarray | None:
        return np.fromfile(self.files[k], dtype=NCLT_POINT)["intensity"].astype(np.float64)

    def timestamps(self) -> ScanTimestamps:
        return ScanTimestamps(stamps_from_names(self.files, NCLT), f"{self.folder} (file names, us)")

    def close(self) -> None:
        """Nothing kept open."""


class DatasetSource:
    """The scans of a KITTI, MulRan, Newer College or NCLT sequence (`files`: the source of its scan
    files), with the dataset's timestamps and per-point times (module docstring)."""

    def __init__(self, layout: Layout, files: FolderSource | NcltFiles) -> None:
        self.layout = layout
        self.files = files
        self.name = str(layout.root)
        self._sweep_s: float | None = None

    def __len__(self) -> int:
        return len(self.files)

    def check(self) -> None:
        self.files.check()

    def points(self, k: int) -> np.ndarray:
        return self.files.points(k)

    def point_times(self, k: int) -> np.ndarray | None:
        if self.layout.kind != MULRAN:
            return self.files.point_times(k)
        n_points = len(self.files.points(k))
        if n_points != MULRAN_BEAMS * MULRAN_COLUMNS:
            return None  # a scan missing returns: its points' columns are unknown
        from kiss_icp.datasets.mulran import MulranDataset

        return MulranDataset.get_timestamps() * self._sweep_period_s()

    def point_intensity(self, k: int) -> np.ndarray | None:
        return self.files.point_intensity(k)

    def timestamps(self) -> ScanTimestamps:
        if self.layout.kind in (MULRAN, NCD):
            unit = "ns" if self.layout.kind == MULRAN else "s, ns"
            return ScanTimestamps(stamps_from_names(self.files.files, self.layout.kind),
                                  f"{self.layout.scans} (file names, {unit})")
        return self.files.timestamps()

    def close(self) -> None:
        self.files.close()

    def _sweep_period_s(self) -> float:
        """The median interval of the scans' timestamps (s): one sweep of the spinning sensor. The
        intervals are taken between the integer nanoseconds of the names (float seconds since 1970
        keep only 0.2 us)."""
        if self._sweep_s is None:
            self.timestamps()  # the names are checked there
            stamps_ns = np.array([int(p.stem) for p in self.files.files], dtype=np.int64)
            self._sweep_s = float(np.median(np.diff(stamps_ns))) / 1e9 if len(stamps_ns) > 1 else MULRAN_SWEEP_S
        return self._sweep_s

    def describe(self) -> str:
        """What was found: layout, scans, per-point times, ground truth (`describe_source`)."""
        stamps = self.timestamps()
        times = self._times_found()
        gt = f"ground truth {self.layout.gt} (pass it with --gt)" if self.layout.gt else "no ground truth found"
        stamped = f"timestamps from {stamps.origin}" if stamps.stamps_s is not None else "no timestamps"
        return (f"{self.name}: {self.layout.kind} layout, {len(self)} scans in {self.layout.scans}, {stamped}, "
                f"{times}, {gt}")

    def _times_found(self) -> str:
        if self.layout.kind in (KITTI, NCLT) or len(self) == 0:
            return "no per-point times"
        if self.layout.kind == NCD:
            has = read_scan(self.files.files[0]).time is not None
            return "per-point times from the PCD's t field" if has else "no per-point times (no t field)"
        size = self.files.files[0].stat().st_size // KITTI_BIN_BYTES_PER_POINT
        if size == MULRAN_BEAMS * MULRAN_COLUMNS:
            return "per-point times from the point order (64 x 1024, column by column)"
        return f"no per-point times (scan 0 holds {size} points, not 64 x 1024)"
