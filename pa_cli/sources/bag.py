"""A ROS bag of point clouds, read with the `rosbags` package (no ROS install).

Accepted: ROS1 `.bag` files, ROS2 bag folders (with `metadata.yaml`) and bare ROS2 storage
files (`.db3`, `.mcap`). One topic is read (`--topic`) of `sensor_msgs/PointCloud2` or Livox
`CustomMsg` (`pa_cli.sources.livox`); each message is one scan. The layouts of the common drivers
and how each is read are in docs/sensors.md.

- Points: the `x y z` fields (any numeric type, any offsets, padding, either endianness, organised
  or not), in the message's frame (the sensor frame), metres. Points with a NaN/inf coordinate
  and points at exactly (0, 0, 0) are dropped: organised clouds mark a missing return so.
- Per-point time: the first field named `time`, `t`, `timestamp` or `offset_time` (CustomMsg:
  `offset_time` from `timebase`). Its unit and kind come from the values over the whole topic
  (`pa_cli.sources.point_times`): the span of a message is one sweep, and absolute times (UNIX
  epoch) are far from 0. `point_times(k)` are seconds from scan k's earliest point; that point's
  instant (its absolute time, or the header stamp plus its relative time) is the scan's timestamp.
  So a driver that stamps a sweep at its end (Velodyne, Robosense) and one that stamps it at its
  start (Ouster, Hesai) give the same scans and the same timestamps: the sweep's start.
- Without a usable time field the timestamps are the header stamps and `time_field()` says why
  (which fields the messages have, which look like times, what pa reads).
- The scans are the messages in header-stamp order; of messages with the same stamp the first
  stored is read, the others are skipped (`read_issues()`, the report's `input.read_issues`). A bag
  that fails midway gives the messages before the failure; a ROS1 bag without index (a recording cut
  off) is read chunk by chunk (`pa_cli.sources.ros1_chunks`); other unreadable bags are a
  `FormatError` naming the repair.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pa_cli.errors import FormatError, InputError
from pa_cli.io.scans import TIME_FIELDS
from pa_cli.sources.base import PointTimeField, ReadIssues, ScanTimestamps, Skipped
from pa_cli.sources.livox import CUSTOM_MSGTYPES, check_definitions, decode_custom_msg, livox_types
from pa_cli.sources.point_times import TimeUnit, detect_time_unit, looks_like_time, sweep_times_s
from pa_cli.sources.ros1_chunks import open_unindexed

log = logging.getLogger(__name__)

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
SCAN_MSGTYPES = (POINTCLOUD2, *CUSTOM_MSGTYPES)
ROS1_SUFFIXES = (".bag",)
ROS2_SUFFIXES = (".db3", ".mcap")
NS_PER_S = 1e9
# The longest sweep a time field's unit is chosen for: refine.deskew_max_sweep_s's default (a bag
# is opened before the configuration is read; sweeps of 2 ms to 2 s are recognised).
MAX_SWEEP_S = 2.0
# Header stamps order the messages only when at least this fraction is distinct (a driver that
# leaves them at 0 gives no order).
MIN_DISTINCT_STAMPS = 0.5
NAMES_LOGGED = 5  # skipped scans named in a log record (the report names all)
# rosbags' errors for a ROS1 bag whose index is missing (a recording cut off) or damaged
_INDEX_MISSING = re.compile("Bag index looks damaged|Bag is not indexed")
# sensor_msgs/PointField datatype codes -> numpy type codes
_POINTFIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def is_bag_path(path: Path) -> bool:
    """True for a ROS1 `.bag`, a ROS2 `.db3`/`.mcap` file, or a folder holding a ROS2 bag."""
    if path.is_dir():
        return (path / "metadata.yaml").is_file() or any(
            p.suffix in ROS2_SUFFIXES for p in path.iterdir())
    return path.suffix.lower() in ROS1_SUFFIXES + ROS2_SUFFIXES


def bag_typestore() -> Any:
    """The types for bags without message definitions: ROS2 Humble's and Livox's CustomMsg."""
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS2_HUMBLE)
    typestore.register(livox_types())
    return typestore


@dataclass(frozen=True)
class Cloud:
    """One message decoded: points (N, 3) float64 (finite, not at the origin), their raw times (N,)
    as stored or None, the header stamp (s), the instant a relative time field counts from (s:
    the header stamp, a CustomMsg's timebase), the time field's name and numpy type, and the names
    of all the message's fields."""

    points: np.ndarray
    raw_time: np.ndarray | None
    stamp_s: float
    clock_s: float
    time_name: str | None
    time_dtype: str | None
    fields: tuple[str, ...]


@dataclass(frozen=True)
class _Entry:
    """Message `message` of the topic (its place in the bag): where it is (its bag time (ns), its
    rank among messages with that time), its header stamp and the instant its relative times count
    from (s), and the earliest and latest raw time of its points (None: no time field or no points)."""

    message: int
    bag_time_ns: int
    rank: int
    stamp_s: float
    clock_s: float
    raw_min: Any
    raw_max: Any


class BagSource:
    """The point cloud messages of one topic of a ROS bag, one scan per message."""

    def __init__(self, path: Path | str, topic: str | None) -> None:
        from rosbags.highlevel import AnyReader

        self.path = Path(path)
        if not self.path.exists():
            raise InputError(f"{self.path}: ROS bag not found.")
        self._cut_off: str | None = None  # where a ROS1 bag without index stops being readable
        try:
            self._reader = AnyReader([self.path], default_typestore=bag_typestore())
            self._reader.open()
        except Exception as exc:  # a library boundary: rosbags' reader errors become a FormatError
            self._reader = self._open_unindexed(exc)
        self._check_topic(topic)
        self.topic = topic
        self.name = f"{self.path} {topic}"
        self._connections = [c for c in self._reader.connections
                             if c.topic == topic and c.msgtype in SCAN_MSGTYPES]
        for msgtype in {c.msgtype for c in self._connections} & set(CUSTOM_MSGTYPES):
            check_definitions(self._reader.typestore.fielddefs, msgtype, self.name)
        self._index: list[_Entry] | None = None
        self._issues = ReadIssues()
        self._unit: TimeUnit | None = None
        self._time_field: PointTimeField | None = None
        self._last: tuple[int, Cloud] | None = None

    def _open_unindexed(self, exc: Exception) -> Any:
        """A reader over the complete chunks of a ROS1 bag without index (`pa_cli.sources.ros1_chunks`),
        logged; `FormatError` naming the repair for any other bag rosbags cannot open, or when no
        message can be read."""
        failed = f"{self.path}: cannot open the ROS bag ({type(exc).__name__}: {exc})."
        if not _INDEX_MISSING.search(str(exc)):
            raise FormatError(failed + _repair_hint(exc)) from None
        try:
            reader, scan = open_unindexed(self.path, bag_typestore())
        except Exception:  # a library boundary: not even the chunks can be read
            raise FormatError(failed + _repair_hint(exc)) from None
        n_messages = sum(c.msgcount for c in reader.connections)
        if n_messages == 0:
            reader.close()
            raise FormatError(f"{failed} Its chunks hold no complete message.{_repair_hint(exc)}")
        self._cut_off = f"{self.path}: no index; chunks read up to {scan.stopped or 'the end of the file'}"
        log.warning("%s: the bag has no index (a recording cut off?); read its %d complete messages chunk by "
                    "chunk, up to %s.", self.path, n_messages, scan.stopped or "the end of the file")
        return reader

    def _check_topic(self, topic: str | None) -> None:
        """`InputError` (the reader closed) unless `topic` is a point cloud topic of the bag; the
        message names the topic's type and lists the point cloud topics with their message counts."""
        by_topic: dict[str, tuple[str, int]] = {}
        for c in self._reader.connections:
            msgtype, count = by_topic.get(c.topic, (c.msgtype, 0))
            by_topic[c.topic] = (msgtype, count + c.msgcount)
        clouds = sorted(t for t, (msgtype, _) in by_topic.items() if msgtype in SCAN_MSGTYPES)
        if topic is not None and topic in clouds:
            return
        self._reader.close()
        listed = ", ".join(f"{t} ({by_topic[t][0]}, {by_topic[t][1]} messages)" for t in clouds)
        fits = f"the point cloud topics in the bag: {listed}" if clouds else \
            f"the bag has no point cloud topic (its topics: {', '.join(sorted(by_topic)) or 'none'})"
        if topic is None:
            found = "no --topic given (pa never guesses the topic)"
        elif topic in by_topic:
            found = (f"topic '{topic}' is of type {by_topic[topic][0]}; pa reads "
                     f"{', '.join(SCAN_MSGTYPES[:-1])} or {SCAN_MSGTYPES[-1]}")
        else:
            found = f"topic '{topic}' is not in the bag"
        raise InputError(f"{self.path}: {found}; {fits}. Choose one with --topic.")

    def __len__(self) -> int:
        """The number of scans: known once every message is read (`check()`, run here if not yet)."""
        if self._index is None:
            self.check()
        return len(self._index)

    def scan_name(self, k: int) -> str:
        """Scan k as its bag message: its place on the topic and its header stamp (after `check()`)."""
        if self._index is None:
            return f"{self.name} message {k}"
        entry = self._index[k]
        return f"{self.name} message {entry.message} (header stamp {entry.stamp_s:.6f} s)"

    def read_issues(self) -> ReadIssues:
        """Messages left out (duplicated header stamps), reordered, and where a damaged bag stopped."""
        return self._issues

    def check(self) -> None:
        """Read every message of the topic once (a bag's index holds no header stamps): layout,
        data size, header stamp and the span of the per-point times, from which the time field's
        unit is chosen. The scans are the messages in header-stamp order, a duplicated stamp's
        first message only (`_stamp_order`); a bag that stops being readable gives the messages
        before the damage (`ReadIssues.stopped`)."""
        entries: list[_Entry] = []
        previous_ns, rank = None, 0
        clouds_fields: set[tuple[str, ...]] = set()
        time_fields: set[tuple[str, str]] = set()
        messages = self._reader.messages(connections=self._connections)
        stopped = None
        for k, item in enumerate(_until_unreadable(messages)):
            if isinstance(item, Exception):
                stopped = self._stopped_at(k, entries, item)
                break
            connection, bag_time_ns, raw = item
            cloud = self._decode(raw, connection.msgtype, k)
            rank = rank + 1 if bag_time_ns == previous_ns else 0
            previous_ns = bag_time_ns
            timed = cloud.raw_time is not None and len(cloud.raw_time) > 0
            entries.append(_Entry(k, bag_time_ns, rank, cloud.stamp_s, cloud.clock_s,
                                  cloud.raw_time.min() if timed else None, cloud.raw_time.max() if timed else None))
            clouds_fields.add(cloud.fields)
            if cloud.time_name is not None:
                time_fields.add((cloud.time_name, cloud.time_dtype))
        kept, duplicates, n_reordered = _stamp_order(np.array([e.stamp_s for e in entries]), self.name)
        self._index = [entries[i] for i in kept]
        skipped = tuple(Skipped(f"{self.name} message {entries[i].message} (header stamp {entries[i].stamp_s:.6f} s)",
                                "duplicated header stamp") for i in duplicates)
        self._issues = ReadIssues(skipped, n_reordered, "; ".join(filter(None, (self._cut_off, stopped))) or None)
        if n_reordered:
            log.warning("%s: %d message(s) are stored out of the order of their header stamps; the scans are "
                        "read in header-stamp order.", self.name, n_reordered)
        if skipped:
            log.warning("%s: %d message(s) repeat the header stamp of an earlier message; the first is read, "
                        "the others skipped: %s", self.name, len(skipped), _first_names(skipped))
        clock = "timebase" if {c.msgtype for c in self._connections} <= set(CUSTOM_MSGTYPES) else "header stamp"
        self._unit, self._time_field = _interpret_times(self._index, clouds_fields, time_fields, clock, self.name)

    def _stopped_at(self, k: int, entries: list[_Entry], exc: Exception) -> str:
        """Where the messages stopped being readable, logged; `FormatError` when none could be read."""
        expected = sum(c.msgcount for c in self._connections)
        reason = f"{type(exc).__name__}: {exc}"
        if not entries:
            raise FormatError(f"{self.name}: no message of the topic can be read ({reason}); the bag is damaged "
                              f"or truncated.{_repair_hint(exc)}")
        where = (f"after message {k - 1} (bag time {entries[-1].bag_time_ns / NS_PER_S:.6f} s): {k} of "
                 f"{expected} messages read ({reason})")
        log.warning("%s: the bag cannot be read %s; the run uses the messages read.", self.name, where)
        return f"{self.name}: unreadable {where}"

    def time_field(self) -> PointTimeField | None:
        """How the per-point times are read (field, unit, reference instant), or why there are none."""
        if self._index is None:
            self.check()
        return self._time_field

    def _decode(self, raw: Any, msgtype: str, k: int) -> Cloud:
        where = f"{self.name} message {k}"
        if msgtype in CUSTOM_MSGTYPES:
            scan = decode_custom_msg(raw, self._reader.is2, where)
            return _cloud(scan.xyz, scan.offset_time_ns, scan.stamp_s, scan.timebase_s, "offset_time",
                          ("x", "y", "z", "offset_time", "reflectivity", "tag", "line"))
        try:
            message = self._reader.deserialize(raw, msgtype)
        except Exception as exc:  # a library boundary: a corrupt message becomes a FormatError
            raise FormatError(f"{where}: cannot decode the {msgtype} message "
                              f"({type(exc).__name__}: {exc}).") from None
        return decode_pointcloud2(message, where)

    def _cloud(self, k: int) -> Cloud:
        if self._last is None or self._last[0] != k:
            if self._index is None:
                self.check()
            entry = self._index[k]
            messages = self._reader.messages(connections=self._connections, start=entry.bag_time_ns,
                                             stop=entry.bag_time_ns + 1)
            for rank, (connection, _, raw) in enumerate(messages):
                if rank == entry.rank:
                    self._last = (k, self._decode(raw, connection.msgtype, entry.message))
                    break
            else:
                raise InputError(f"{self.name}: message {k} is no longer in the bag; was it modified while reading?")
        return self._last[1]

    def points(self, k: int) -> np.ndarray:
        return self._cloud(k).points

    def point_times(self, k: int) -> np.ndarray | None:
        """Seconds from scan k's earliest point (its timestamp), or None without a usable time field."""
        cloud = self._cloud(k)
        if self._unit is None or cloud.raw_time is None:
            return None
        if len(cloud.raw_time) == 0:
            return np.empty(0)
        return sweep_times_s(cloud.raw_time, self._unit, cloud.clock_s)[0]

    def timestamps(self) -> ScanTimestamps:
        """The instant of each scan's earliest point with a usable time field, else the header stamps."""
        if self._index is None:
            self.check()
        header_s = np.array([e.stamp_s for e in self._index])
        if self._unit is None:
            return ScanTimestamps(header_s, f"{self.name} header stamps")
        reference_s = _reference_s(self._index, self._unit)
        missing = ~np.isfinite(reference_s)
        if missing.any():  # messages without points or times: their stamp, shifted as the others' are
            reference_s[missing] = header_s[missing] - self._time_field.stamp_minus_reference_s
        return ScanTimestamps(reference_s, f"{self.name} earliest point of each message "
                                           f"({self._time_field.reference})")

    def close(self) -> None:
        self._reader.close()


def _until_unreadable(messages: Iterator[Any]) -> Iterator[Any]:
    """The items of `messages`, then, when the reader fails (a damaged or truncated bag), its
    exception as the last item."""
    while True:
        try:
            item = next(messages)
        except StopIteration:
            return
        except Exception as exc:  # a library boundary: rosbags' errors on a damaged bag
            yield exc
            return
        yield item


def _stamp_order(stamps_s: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray, int]:
    """(the messages kept, in header-stamp order; the duplicates left out; how many messages are
    stored after a later-stamped one), message indices in bag order.

    Equal stamps keep the message stored first. Stamps of which fewer than `MIN_DISTINCT_STAMPS`
    are distinct (a driver that leaves them at 0) order nothing: the bag's order is kept, all read.
    """
    n = len(stamps_s)
    if n == 0 or len(np.unique(stamps_s)) < MIN_DISTINCT_STAMPS * n:
        if n > 1:
            log.warning("%s: %d distinct header stamps for %d messages; the messages are read in the bag's "
                        "order.", where, len(np.unique(stamps_s)), n)
        return np.arange(n), np.empty(0, dtype=int), 0
    order = np.argsort(stamps_s, kind="stable")
    n_reordered = int((stamps_s[1:] < np.maximum.accumulate(stamps_s)[:-1]).sum())
    stamps_sorted = stamps_s[order]
    duplicate = np.r_[False, stamps_sorted[1:] == stamps_sorted[:-1]]
    return order[~duplicate], np.sort(order[duplicate]), n_reordered


def _first_names(skipped: tuple[Skipped, ...]) -> str:
    """The first `NAMES_LOGGED` skipped scans' names, for a log record."""
    names = ", ".join(s.scan for s in skipped[:NAMES_LOGGED])
    return names + (f", ... ({len(skipped)} in all, each in the report)" if len(skipped) > NAMES_LOGGED else "")


def _repair_hint(exc: Exception) -> str:
    """How to repair a bag rosbags cannot read, from its error (empty when the error names no repair)."""
    text = str(exc)
    if _INDEX_MISSING.search(text):
        return (" A ROS1 bag whose recording was cut off has no index; `rosbag reindex` rebuilds it "
                "from what can be read.")
    if "File end magic is invalid" in text:
        return (" An MCAP file whose recording was cut off has no footer: `mcap recover IN.mcap -o OUT.mcap` "
                "(the mcap CLI) writes what can be read.")
    if "malformed" in text:
        return (" A damaged SQLite3 bag: `sqlite3 IN.db3 .recover | sqlite3 OUT.db3` copies what can be "
                "read (keep metadata.yaml beside it).")
    return ""


def _reference_s(entries: list[_Entry], unit: TimeUnit) -> np.ndarray:
    """Each message's earliest point's instant (s; NaN without times), as `sweep_times_s` gives it."""
    origin = [0.0 if unit.absolute else e.clock_s for e in entries]
    return np.array([np.nan if e.raw_min is None else o + float(e.raw_min) * unit.seconds_per_unit
                     for e, o in zip(entries, origin, strict=True)])


def _interpret_times(entries: list[_Entry], clouds_fields: set[tuple[str, ...]], time_fields: set[tuple[str, str]],
                     clock: str, where: str) -> tuple[TimeUnit | None, PointTimeField]:
    """The unit of the topic's time field and its description, or the reason it has none. `clock`
    names what a relative field counts from; `where` names the topic in errors."""
    fields = tuple(dict.fromkeys(name for names in sorted(clouds_fields) for name in names))
    unknown = tuple(name for name in fields if looks_like_time(name) and name not in TIME_FIELDS)
    read_by = "pa reads per-point times from a field named " + ", ".join(TIME_FIELDS) + " (docs/sensors.md)"
    if not time_fields:
        if unknown:
            problem = (f"the field(s) {', '.join(unknown)} look like per-point times but {read_by}; the messages "
                       f"have the fields {' '.join(fields)}")
        else:
            problem = f"no per-point time field: the messages have the fields {' '.join(fields)}; {read_by}"
        return None, PointTimeField(None, None, None, None, None, None, fields, problem, unknown)
    if len(time_fields) > 1:
        used = ", ".join(f"{n} ({d})" for n, d in sorted(time_fields))
        raise FormatError(f"{where}: the messages have different time fields ({used}); pa reads one layout "
                          "per topic. Write each layout to its own topic.")
    ((name, dtype),) = time_fields
    timed = [e for e in entries if e.raw_min is not None]
    unit = detect_time_unit([e.raw_min for e in timed], [e.raw_max for e in timed], MAX_SWEEP_S) if timed else None
    if unit is None:
        spans = [float(e.raw_max) - float(e.raw_min) for e in timed]
        found = (f"its values span {np.median(spans):.6g} (median over the messages)" if timed and max(spans) > 0
                 else "its values are the same for every point of a message")
        problem = (f"the time field '{name}' ({dtype}) does not span a sweep: {found}, and no unit of s, ms, us or "
                   f"ns puts that between {MAX_SWEEP_S / 1000:g} and {MAX_SWEEP_S:g} s")
        return None, PointTimeField(name, dtype, None, None, None, None, fields, problem, (name, *unknown))
    reference_s = _reference_s(entries, unit)
    offset_s = np.array([e.stamp_s for e in entries]) - reference_s
    reference = (f"the earliest point of each message (absolute '{name}')" if unit.absolute
                 else f"the earliest point of each message ({clock} + relative '{name}')")
    return unit, PointTimeField(name, dtype, unit.name, unit.absolute, reference,
                                float(np.nanmedian(offset_s)) if np.isfinite(offset_s).any() else None, fields,
                                suspects=unknown)


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


def decode_pointcloud2(message: Any, where: str) -> Cloud:
    """A PointCloud2 message's valid points and raw per-point times (see `Cloud`)."""
    dtype = _cloud_dtype(message, where)
    height, width, row_step = int(message.height), int(message.width), int(message.row_step)
    data = np.frombuffer(np.asarray(message.data, dtype=np.uint8).tobytes(), dtype=np.uint8)
    rows = data[:height * row_step].reshape(height, row_step)[:, :width * dtype.itemsize]
    cloud = np.ascontiguousarray(rows).view(dtype).reshape(-1)
    time_name = dtype.names[3] if len(dtype.names) == 4 else None
    stamp_s = _stamp_s(message)
    return _cloud(np.column_stack([cloud[a] for a in "xyz"]), None if time_name is None else cloud[time_name],
                  stamp_s, stamp_s, time_name, tuple(f.name for f in message.fields))


def _cloud(xyz: np.ndarray, raw_time: np.ndarray | None, stamp_s: float, clock_s: float, time_name: str | None,
           fields: tuple[str, ...]) -> Cloud:
    """A `Cloud` of the points with finite coordinates (and a finite time) that are not at the origin."""
    points = xyz.astype(np.float64)
    valid = np.isfinite(points).all(axis=1) & points.any(axis=1)
    if raw_time is None:
        return Cloud(points[valid], None, stamp_s, clock_s, None, None, fields)
    valid &= np.isfinite(raw_time)
    return Cloud(points[valid], raw_time[valid], stamp_s, clock_s, time_name, raw_time.dtype.name, fields)
