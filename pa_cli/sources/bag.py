"""A ROS bag of `sensor_msgs/PointCloud2` messages, read with the `rosbags` package (no ROS install).

Accepted: ROS1 `.bag` files, ROS2 bag folders (with `metadata.yaml`) and bare ROS2 storage
files (`.db3`, `.mcap`). One topic is read (`--topic`); each message is one scan.

- Points: the `x y z` fields (any numeric type), in the message's frame (the sensor frame),
  metres; points with a NaN/inf coordinate (organised clouds) are dropped.
- Per-scan timestamp: the message's `header.stamp` (s).
- Per-point time: the first field named `time`, `t` or `timestamp`. Integer fields are
  nanoseconds (Ouster `t`); float fields are seconds, and values at or above
  `ABSOLUTE_TIME_MIN_S` are absolute (Hesai, Livox) and made relative to the header stamp.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pa_cli.errors import FormatError, InputError
from pa_cli.io.scans import TIME_FIELDS
from pa_cli.sources.base import ScanTimestamps

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
ROS1_SUFFIXES = (".bag",)
ROS2_SUFFIXES = (".db3", ".mcap")
NS_PER_S = 1e9
# A per-point time this large (s) is an absolute epoch time, not an offset within a scan:
# a scan lasts well under a second, 1e6 s is 11.6 days after 1970.
ABSOLUTE_TIME_MIN_S = 1e6
# sensor_msgs/PointField datatype codes -> numpy type codes
_POINTFIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def is_bag_path(path: Path) -> bool:
    """True for a ROS1 `.bag`, a ROS2 `.db3`/`.mcap` file, or a folder holding a ROS2 bag."""
    if path.is_dir():
        return (path / "metadata.yaml").is_file() or any(
            p.suffix in ROS2_SUFFIXES for p in path.iterdir())
    return path.suffix.lower() in ROS1_SUFFIXES + ROS2_SUFFIXES


@dataclass(frozen=True)
class _Entry:
    """Where message k is: its bag time (ns), its rank among messages with that time, its stamp (s)."""

    bag_time_ns: int
    rank: int
    stamp_s: float


class BagSource:
    """The PointCloud2 messages of one topic of a ROS bag, one scan per message."""

    def __init__(self, path: Path | str, topic: str | None) -> None:
        from rosbags.highlevel import AnyReader

        self.path = Path(path)
        if not self.path.exists():
            raise InputError(f"{self.path}: ROS bag not found.")
        try:
            self._reader = AnyReader([self.path])
            self._reader.open()
        except Exception as exc:  # a library boundary: rosbags' reader errors become a FormatError
            raise FormatError(f"{self.path}: cannot open the ROS bag ({type(exc).__name__}: {exc}).") from None
        clouds = sorted({c.topic for c in self._reader.connections if c.msgtype == POINTCLOUD2})
        available = ", ".join(clouds) if clouds else "none"
        if topic is None or topic not in clouds:
            self._reader.close()
            found = "no --topic given" if topic is None else f"topic '{topic}' is not one of them"
            raise InputError(f"{self.path}: {found}; PointCloud2 topics in the bag: {available}. "
                             "Choose one with --topic.")
        self.topic = topic
        self.name = f"{self.path} {topic}"
        self._connections = [c for c in self._reader.connections
                             if c.topic == topic and c.msgtype == POINTCLOUD2]
        self._n = sum(c.msgcount for c in self._connections)
        self._index: list[_Entry] | None = None
        self._last: tuple[int, np.ndarray, np.ndarray | None] | None = None

    def __len__(self) -> int:
        return self._n

    def check(self) -> None:
        """Read every message of the topic once (a bag's index holds no header stamps): layout,
        data size and header stamp; the points are not decoded."""
        entries = []
        previous_ns, rank = None, 0
        for k, (connection, bag_time_ns, raw) in enumerate(self._reader.messages(connections=self._connections)):
            message = self._deserialize(raw, connection.msgtype, k)
            _cloud_dtype(message, f"{self.name} message {k}")
            rank = rank + 1 if bag_time_ns == previous_ns else 0
            previous_ns = bag_time_ns
            entries.append(_Entry(bag_time_ns, rank, _stamp_s(message)))
        self._index = entries
        self._n = len(entries)

    def _deserialize(self, raw: bytes, msgtype: str, k: int) -> Any:
        try:
            return self._reader.deserialize(raw, msgtype)
        except Exception as exc:  # a library boundary: a corrupt message becomes a FormatError
            raise FormatError(f"{self.name} message {k}: cannot decode the {msgtype} message "
                              f"({type(exc).__name__}: {exc}).") from None

    def _message(self, k: int) -> Any:
        if self._index is None:
            self.check()
        entry = self._index[k]
        messages = self._reader.messages(connections=self._connections, start=entry.bag_time_ns,
                                         stop=entry.bag_time_ns + 1)
        for rank, (connection, _, raw) in enumerate(messages):
            if rank == entry.rank:
                return self._deserialize(raw, connection.msgtype, k)
        raise InputError(f"{self.name}: message {k} is no longer in the bag; was it modified while reading?")

    def _read(self, k: int) -> tuple[np.ndarray, np.ndarray | None]:
        if self._last is None or self._last[0] != k:
            message = self._message(k)
            points, time_s = decode_pointcloud2(message, f"{self.name} message {k}")
            self._last = (k, points, time_s)
        return self._last[1], self._last[2]

    def points(self, k: int) -> np.ndarray:
        return self._read(k)[0]

    def point_times(self, k: int) -> np.ndarray | None:
        return self._read(k)[1]

    def timestamps(self) -> ScanTimestamps:
        if self._index is None:
            self.check()
        return ScanTimestamps(np.array([e.stamp_s for e in self._index]), f"{self.name} header stamps")

    def close(self) -> None:
        self._reader.close()


def _stamp_s(message: Any) -> float:
    stamp = message.header.stamp
    return float(stamp.sec) + float(stamp.nanosec) / NS_PER_S


def _cloud_dtype(message: Any, where: str) -> np.dtype:
    """The numpy dtype of one point (x y z and a time field), checked against the message layout."""
    fields = {f.name: f for f in message.fields}
    missing = [a for a in "xyz" if a not in fields]
    if missing:
        raise FormatError(f"{where}: no {'/'.join(missing)} field; expected PointCloud2 fields x y z, "
                          f"found {' '.join(fields) or 'none'}.")
    endian = ">" if message.is_bigendian else "<"
    names = [*"xyz", *[n for n in TIME_FIELDS if n in fields][:1]]
    formats = []
    for name in names:
        code = _POINTFIELD_TYPES.get(int(fields[name].datatype))
        if code is None:
            raise FormatError(f"{where}: field '{name}' has PointField datatype {fields[name].datatype}; "
                              "expected 1..8 (INT8 .. FLOAT64).")
        formats.append(endian + code)
    offsets = [int(fields[n].offset) for n in names]
    point_step = int(message.point_step)
    if any(o + np.dtype(f).itemsize > point_step for o, f in zip(offsets, formats, strict=True)):
        raise FormatError(f"{where}: a field lies beyond point_step {point_step} bytes.")
    needed = int(message.height) * int(message.row_step)
    if int(message.row_step) < int(message.width) * point_step or len(message.data) < needed:
        raise FormatError(f"{where}: {len(message.data)} data bytes for {message.height} x {message.width} "
                          f"points (row_step {message.row_step}, point_step {point_step}); the message is "
                          "truncated or its layout is inconsistent.")
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})


def decode_pointcloud2(message: Any, where: str) -> tuple[np.ndarray, np.ndarray | None]:
    """(N, 3) float64 points and (N,) per-point times (s, relative to the header stamp) or None."""
    dtype = _cloud_dtype(message, where)
    height, width, row_step = int(message.height), int(message.width), int(message.row_step)
    data = np.frombuffer(np.asarray(message.data, dtype=np.uint8).tobytes(), dtype=np.uint8)
    rows = data[:height * row_step].reshape(height, row_step)[:, :width * dtype.itemsize]
    cloud = np.ascontiguousarray(rows).view(dtype).reshape(-1)
    points = np.column_stack([cloud[a].astype(np.float64) for a in "xyz"])
    time_s = None
    if len(dtype.names) == 4:
        name = dtype.names[3]
        raw_time = cloud[name]
        time_s = raw_time.astype(np.float64)
        if np.issubdtype(raw_time.dtype, np.integer):
            time_s /= NS_PER_S
        else:
            finite_time_s = np.abs(time_s[np.isfinite(time_s)])
            if finite_time_s.size and finite_time_s.min() >= ABSOLUTE_TIME_MIN_S:
                time_s -= _stamp_s(message)
    finite = np.isfinite(points).all(axis=1)
    if not finite.all():
        points = points[finite]
        time_s = None if time_s is None else time_s[finite]
    return points, time_s
