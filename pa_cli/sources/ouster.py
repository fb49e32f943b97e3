"""An Ouster pcap recording with its metadata `.json`, read with ouster-sdk (installed by the user:
`OUSTER_INSTALL`).

Each frame of the pcap (one sweep) is a scan: the points of the returns with a range (the
sensor's `XYZLut`, metres, sensor frame), staggered as the packets carry them, each at the
timestamp of its column. Per-point times are seconds from the scan's earliest point, whose
instant is the scan's timestamp (`DescribesTimeField`, as a ROS bag's). KISS-ICP's
`OusterDataloader` is not used: it imports `ouster.sdk.client`, which ouster-sdk 1.0 no longer has.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pa_cli.errors import FormatError, InputError
from pa_cli.sources.base import PointTimeField, ScanTimestamps

NS_PER_S = 1e9
# ouster-sdk 1.0 pins rosbags 0.9.23 and pa's bag reader needs rosbags >= 0.10, so pip will not install the two
# together: ouster-sdk without its pins and the modules its pcap reading imports (measured with ouster-sdk 1.0.1)
OUSTER_INSTALL = "pip install --no-deps 'ouster-sdk>=1.0' && pip install more-itertools prettytable threadpoolctl"


def import_ouster() -> tuple[Any, Any]:
    """ouster-sdk's `core` module and `open_source`; `InputError` naming how to install it when it is missing."""
    try:
        import ouster.sdk.core as core
        from ouster.sdk import open_source
    except ImportError:
        raise InputError(f"reading an Ouster pcap needs ouster-sdk (1.0 or later), which is not installed. It pins "
                         f"rosbags 0.9.23, older than pa's bag reader needs, so install it without its pins: "
                         f"`{OUSTER_INSTALL}`.") from None
    return core, open_source


class OusterPcapSource:
    """The frames of an Ouster pcap as scans (module docstring)."""

    def __init__(self, pcap: Path, metadata: Path) -> None:
        self.metadata = metadata
        self.name = str(pcap)
        self._core, open_source = import_ouster()
        try:
            self._source = open_source(str(pcap), meta=[str(metadata)], index=True, sensor_idx=0)
            self._info = self._source.sensor_info[0]
            self._lut = self._core.XYZLut(self._info)
        except Exception as exc:  # a library boundary: whatever ouster-sdk raises becomes a FormatError
            raise FormatError(f"{pcap}: ouster-sdk cannot read the pcap with the metadata "
                              f"{metadata} ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
                              "; the metadata must be the one recorded with the pcap.") from None
        self._n = len(self._source)
        self._starts_ns: dict[int, int] = {}
        self._last: tuple[int, np.ndarray, np.ndarray] | None = None

    def __len__(self) -> int:
        return self._n

    def check(self) -> None:
        """The pcap's index was read on opening; there is no per-scan header to check."""

    def _frame(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Scan k's points (N, 3) and their column timestamps (N,) uint64 ns (the last one read is kept)."""
        if self._last is None or self._last[0] != k:
            frame = self._source[k][0]
            valid = frame.field(self._core.ChanField.RANGE) != 0
            xyz = self._lut(frame)[valid]
            stamps_ns = np.broadcast_to(np.asarray(frame.timestamp, dtype=np.uint64)[None, :], valid.shape)[valid]
            if len(stamps_ns):
                self._starts_ns[k] = int(stamps_ns.min())
            self._last = (k, np.asarray(xyz, dtype=np.float64), stamps_ns)
        return self._last[1], self._last[2]

    def points(self, k: int) -> np.ndarray:
        return self._frame(k)[0]

    def point_times(self, k: int) -> np.ndarray | None:
        stamps_ns = self._frame(k)[1]
        if not len(stamps_ns):
            return None
        return (stamps_ns - stamps_ns.min()).astype(np.float64) / NS_PER_S

    def timestamps(self) -> ScanTimestamps:
        for k in range(self._n):
            if k not in self._starts_ns:
                self._frame(k)
        if len(self._starts_ns) < self._n:
            return ScanTimestamps(None, f"{self.name}: a frame without returns has no timestamp")
        return ScanTimestamps(np.array([self._starts_ns[k] / NS_PER_S for k in range(self._n)]),
                              f"{self.name} (each frame's earliest column timestamp)")

    def time_field(self) -> PointTimeField:
        """The columns' timestamps, read as ns from the scan's earliest point (`DescribesTimeField`)."""
        return PointTimeField("timestamp", "uint64", "ns", True, "the scan's earliest point", 0.0,
                              ("timestamp", *(str(f) for f in self._source[0][0].fields)) if self._n else ())

    def close(self) -> None:
        self._last = None
        self._source.close()

    def describe(self) -> str:
        """What was found (`pa_cli.sources.datasets.describe_source`)."""
        return (f"{self.name}: Ouster pcap layout (metadata {self.metadata}), {self._n} scans, per-point "
                "times from the columns' timestamps, no ground truth in the layout")
