"""An Ouster pcap recording with its metadata `.json`: the sensor's UDP lidar packets decoded here.

The metadata (`read_metadata`) gives the packet layout and the beam intrinsics; both its layouts
are read: the nested one of firmware 2.x and later / ouster-sdk (`beam_intrinsics`,
`lidar_intrinsics`, `lidar_data_format`, `sensor_info`, `config_params`) and the flat one of older
firmware (the same keys at the top, `data_format`, `lidar_mode`). The lidar packets are the UDP
datagrams of the metadata's packet size in the pcap (`pa_cli.io.pcap`); in a profile whose packet
header carries the serial number, those of another sensor are left out.

Packet layout (the sensor manual's "Lidar Data Format"), little-endian: LEGACY has no packet
header, columns of a 16-byte header (timestamp ns uint64, measurement id uint16, frame id uint16,
encoder count uint32), 12 bytes per pixel and a 4-byte status footer; the other profiles have a
32-byte packet header (packet type uint16, frame id uint16, init id 24 bits, serial number 40
bits), columns of a 12-byte header (timestamp ns uint64, measurement id uint16, status uint16)
and the pixels, and a 32-byte packet footer. A column whose status has bit 0 clear holds no data.
The range is the pixel's first uint32 masked (`PROFILES`), in mm, or in 8 mm steps for
RNG15_RFL8_NIR8; 0 means no return; for the dual-return profile the first (strongest) return.

Points (`xyz_lookup`): pixel (beam i, measurement id m) of a frame of w columns fires from the
encoder angle theta_e = 2 pi (1 - m / w) along theta = theta_e - beam_azimuth_angles[i] and
phi = beam_altitude_angles[i]; its beam origin sits at (bx cos theta_e, bx sin theta_e, bz) from
`beam_to_lidar_transform`'s translation (or `lidar_origin_to_beam_origin_mm` as bx, bz = 0), and
range r (mm) measured from the lidar origin puts it at (r - n) (cos theta cos phi, sin theta cos
phi, sin phi) + beam origin, n = |(bx, bz)|, in the lidar frame; `lidar_to_sensor_transform`
(translation in mm) takes it to the sensor frame, where pa reads it in metres - as ouster-sdk's
`XYZLut`.

Each frame (a run of packets of one frame id) is a scan: its returns column by column, as the
packets carry them (staggered), each at its column's timestamp. Per-point times are seconds from
the scan's earliest point, whose instant is the scan's timestamp (`DescribesTimeField`, as a ROS
bag's). A frame cut by the start or the end of the recording is a partial scan. Other profiles and
packet headers (`unsupported`), and per-pixel beam angles, are read with ouster-sdk when it is
installed (`OusterSdkSource`; not a dependency: `OUSTER_INSTALL`).
"""

from __future__ import annotations

import json
from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pa_cli.errors import FormatError, InputError
from pa_cli.io.pcap import GLOBAL_HEADER_BYTES, PcapFile
from pa_cli.sources.base import PointTimeField, ScanTimestamps

NS_PER_S = 1e9
M_PER_MM = 1e-3
# ouster-sdk 1.0 pins rosbags 0.9.23 and pa's bag reader needs rosbags >= 0.10, so pip will not install the two
# together: ouster-sdk without its pins and the modules its pcap reading imports (measured with ouster-sdk 1.0.1)
OUSTER_INSTALL = "pip install --no-deps 'ouster-sdk>=1.0' && pip install more-itertools prettytable threadpoolctl"
METADATA_FIX = ("use the .json saved with the recording (ouster-cli saves it beside the pcap; a sensor gives it at "
                "http://SENSOR/api/v1/sensor/metadata)")
COLUMNS_PER_PACKET = 16  # every Ouster lidar mode, for flat metadata without `data_format`
STANDARD_HEADER = "STANDARD"  # the packet header described above (`lidar_data_format.header_type`)
COLUMN_VALID = 0x1  # status bit 0: the column holds data


@dataclass(frozen=True)
class Profile:
    """A UDP lidar profile: bytes per pixel, the range's mask in the pixel's first uint32 and the
    left shift to mm, and the fields a pixel holds (for the report)."""

    pixel_bytes: int
    range_mask: int
    range_shift: int
    fields: tuple[str, ...]


PROFILES = {
    "LEGACY": Profile(12, 0x000FFFFF, 0, ("range", "reflectivity", "signal", "near_ir")),
    "RNG19_RFL8_SIG16_NIR16": Profile(12, 0x0007FFFF, 0, ("range", "reflectivity", "signal", "near_ir")),
    "RNG19_RFL8_SIG16_NIR16_DUAL": Profile(16, 0x0007FFFF, 0, ("range", "reflectivity", "range2", "reflectivity2",
                                                                "signal", "signal2", "near_ir")),
    "RNG15_RFL8_NIR8": Profile(4, 0x7FFF, 3, ("range", "reflectivity", "near_ir")),
}


@dataclass(frozen=True)
class OusterMetadata:
    """What pa needs of a sensor's metadata: the packet layout and the beam intrinsics
    (angles in degrees, transforms 4x4 with translations in mm)."""

    path: Path
    profile: str
    header_type: str
    pixels_per_column: int
    columns_per_frame: int
    columns_per_packet: int
    beam_altitude_deg: np.ndarray
    beam_azimuth_deg: np.ndarray
    beam_to_lidar: np.ndarray
    lidar_to_sensor: np.ndarray
    serial: int

    def unsupported(self) -> str | None:
        """Why pa's decoder does not read this sensor's packets, or None when it does."""
        if self.profile not in PROFILES:
            return f"UDP lidar profile {self.profile}"
        if self.header_type != STANDARD_HEADER:
            return f"packet header type {self.header_type}"
        if len(self.beam_altitude_deg) != self.pixels_per_column:
            return "an angle per pixel"
        return None

    @property
    def legacy(self) -> bool:
        return self.profile == "LEGACY"

    @property
    def packet_header_bytes(self) -> int:
        return 0 if self.legacy else 32

    @property
    def column_header_bytes(self) -> int:
        return 16 if self.legacy else 12

    @property
    def column_bytes(self) -> int:
        footer = 4 if self.legacy else 0
        return self.column_header_bytes + self.pixels_per_column * PROFILES[self.profile].pixel_bytes + footer

    @property
    def packet_bytes(self) -> int:
        footer = 0 if self.legacy else 32
        return self.packet_header_bytes + self.columns_per_packet * self.column_bytes + footer


def read_metadata(path: Path) -> OusterMetadata:
    """The metadata `.json` of an Ouster recording; `FormatError` naming the file, the key and the fix."""
    try:
        meta = json.loads(path.read_text())
    except OSError as exc:
        raise InputError(f"{path}: the Ouster metadata cannot be read ({exc.strerror}).") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise FormatError(f"{path}: the Ouster metadata is not JSON ({exc}); {METADATA_FIX}.") from None
    if not isinstance(meta, dict):
        raise FormatError(f"{path}: the Ouster metadata is a JSON {type(meta).__name__}, not an object; "
                          f"{METADATA_FIX}.")

    def value(group: str, key: str, default: Any = None) -> Any:
        """`meta[group][key]` (nested metadata), else `meta[key]` (flat), else `default`."""
        nested = meta.get(group)
        if isinstance(nested, dict) and key in nested:
            return nested[key]
        if key in meta:
            return meta[key]
        if default is None:
            raise FormatError(f"{path}: the Ouster metadata has no `{key}` (nor `{group}.{key}`); {METADATA_FIX}.")
        return default

    try:
        altitude = np.asarray(value("beam_intrinsics", "beam_altitude_angles"), dtype=np.float64)
        azimuth = np.asarray(value("beam_intrinsics", "beam_azimuth_angles"), dtype=np.float64)
        lidar_to_sensor = np.asarray(value("lidar_intrinsics", "lidar_to_sensor_transform"), dtype=np.float64)
        beam_to_lidar = value("beam_intrinsics", "beam_to_lidar_transform", [])
        if len(beam_to_lidar):
            beam_to_lidar = np.asarray(beam_to_lidar, dtype=np.float64)
        else:  # older metadata: the beam origin offset along x only
            beam_to_lidar = np.eye(4).ravel()
            beam_to_lidar[3] = float(value("beam_intrinsics", "lidar_origin_to_beam_origin_mm"))
        data_format = meta.get("lidar_data_format", meta.get("data_format", {}))
        mode = str(value("config_params", "lidar_mode", "x"))
        columns = data_format.get("columns_per_frame") or (int(mode.split("x")[0]) if mode.split("x")[0].isdigit()
                                                           else None)
        serial = value("sensor_info", "prod_sn", 0)
        result = OusterMetadata(
            path=path, profile=str(data_format.get("udp_profile_lidar", "LEGACY")),
            header_type=str(data_format.get("header_type", STANDARD_HEADER)),
            pixels_per_column=int(data_format.get("pixels_per_column", len(altitude))),
            columns_per_frame=int(columns) if columns else 0,
            columns_per_packet=int(data_format.get("columns_per_packet", COLUMNS_PER_PACKET)),
            beam_altitude_deg=altitude, beam_azimuth_deg=azimuth, beam_to_lidar=beam_to_lidar.reshape(4, 4),
            lidar_to_sensor=lidar_to_sensor.reshape(4, 4), serial=int(serial) if str(serial).isdigit() else 0)
    except (TypeError, ValueError, AttributeError) as exc:
        raise FormatError(f"{path}: a value of the Ouster metadata has the wrong type or shape ({exc}); "
                          f"{METADATA_FIX}.") from None
    pixels = result.pixels_per_column
    if (result.columns_per_frame <= 0 or altitude.ndim != 1 or len(azimuth) != len(altitude)
            or len(altitude) not in (pixels, pixels * result.columns_per_frame)):
        raise FormatError(f"{path}: the Ouster metadata gives {result.columns_per_frame} columns per frame of "
                          f"{pixels} pixels, {len(altitude)} beam altitude and {len(azimuth)} azimuth angles; "
                          f"{METADATA_FIX}.")
    return result


def xyz_lookup(meta: OusterMetadata) -> tuple[np.ndarray, np.ndarray]:
    """(direction, offset), each (H, W, 3) in the sensor frame: pixel (i, m) with range r mm is at
    r * direction[i, m] + offset[i, m] metres (module docstring)."""
    w = meta.columns_per_frame
    theta_e = 2 * np.pi * (1 - np.arange(w) / w)[None, :]
    theta = theta_e - np.deg2rad(meta.beam_azimuth_deg)[:, None]
    phi = np.deg2rad(meta.beam_altitude_deg)[:, None]
    direction = np.stack(np.broadcast_arrays(np.cos(theta) * np.cos(phi), np.sin(theta) * np.cos(phi), np.sin(phi)),
                         axis=-1)
    bx, bz = meta.beam_to_lidar[0, 3], meta.beam_to_lidar[2, 3]
    origin = np.stack(np.broadcast_arrays(bx * np.cos(theta_e), bx * np.sin(theta_e), np.full_like(theta_e, bz)),
                      axis=-1)
    offset_lidar_mm = origin - np.hypot(bx, bz) * direction
    rotation, translation_mm = meta.lidar_to_sensor[:3, :3], meta.lidar_to_sensor[:3, 3]
    return direction @ rotation.T * M_PER_MM, (offset_lidar_mm @ rotation.T + translation_mm) * M_PER_MM


@dataclass(frozen=True)
class _Frame:
    """Where a frame's packets are in the pcap (bytes [start, end)), its frame id and timestamp (ns)."""

    frame_id: int
    start: int
    end: int
    stamp_ns: int


class _Frames(ABC):
    """A pcap's frames as scans: points and per-point times from `_frame(k)`."""

    @abstractmethod
    def _frame(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Scan k's points (N, 3) (m, sensor frame) and their column timestamps (N,) uint64 ns."""

    def points(self, k: int) -> np.ndarray:
        return self._frame(k)[0]

    def point_times(self, k: int) -> np.ndarray | None:
        stamps_ns = self._frame(k)[1]
        if not len(stamps_ns):
            return None
        return (stamps_ns - stamps_ns.min()).astype(np.float64) / NS_PER_S


class OusterPcapSource(_Frames):
    """The frames of an Ouster pcap as scans, decoded by pa (module docstring)."""

    def __init__(self, pcap: Path, meta: OusterMetadata) -> None:
        self.metadata = meta.path
        self.name = str(pcap)
        self._meta = meta
        self._direction, self._offset = xyz_lookup(meta)
        self._pcap = PcapFile(pcap)
        self._last: tuple[int, np.ndarray, np.ndarray] | None = None
        self._frames = self._index()

    def _frame_id_and_serial(self, payload: bytes) -> tuple[int, int]:
        if self._meta.legacy:
            return int.from_bytes(payload[10:12], "little"), 0
        return int.from_bytes(payload[2:4], "little"), int.from_bytes(payload[7:12], "little")

    def _lidar_packets(self, start: int, end: int | None = None) -> Iterator[tuple[int, int, int, bytes]]:
        """(frame id, start byte, end byte, payload) of the metadata's sensor's lidar packets."""
        size, serial = self._meta.packet_bytes, self._meta.serial
        for datagram in self._pcap.datagrams(start, end):
            if len(datagram.payload) != size:
                continue
            frame_id, packet_serial = self._frame_id_and_serial(datagram.payload)
            if serial and packet_serial and packet_serial != serial:
                continue
            yield frame_id, datagram.start, datagram.end, datagram.payload

    def _index(self) -> list[_Frame]:
        """One pass over the pcap: each frame's packets' byte span and its timestamp."""
        frames: list[_Frame] = []
        packets: list[bytes] = []
        current: tuple[int, int, int] | None = None  # frame id, start, end

        def close_frame() -> None:
            if current is not None:
                frames.append(_Frame(*current, self._stamp_ns(packets)))

        for frame_id, start, end, payload in self._lidar_packets(GLOBAL_HEADER_BYTES):
            if current is None or frame_id != current[0]:
                close_frame()
                current, packets = (frame_id, start, end), []
            current = (frame_id, current[1], end)
            packets.append(payload)
        close_frame()
        if not frames:
            raise FormatError(self._no_packets())
        return frames

    def _no_packets(self) -> str:
        sizes: dict[int, int] = {}
        for datagram in self._pcap.datagrams():
            sizes[len(datagram.payload)] = sizes.get(len(datagram.payload), 0) + 1
        found = ", ".join(f"{n} of {s} bytes" for s, n in sorted(sizes.items(), key=lambda kv: -kv[1])[:5]) or "none"
        meta = self._meta
        serial = f" from serial number {meta.serial}" if meta.serial and not meta.legacy else ""
        cut = f"; {self._pcap.skipped} records were captured cut short" if self._pcap.skipped else ""
        return (f"{self.name}: no Ouster lidar packets of {meta.packet_bytes} bytes{serial} (the {meta.profile} "
                f"profile, {meta.pixels_per_column} pixels x {meta.columns_per_packet} columns per packet, as "
                f"{meta.path} gives) among the UDP datagrams (found: {found}){cut}. The metadata must be the one "
                "recorded with this pcap.")

    def _columns(self, packets: list[bytes]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The valid columns of lidar packets: measurement ids (C,), timestamps (C,) uint64 ns, ranges (C, H) mm."""
        meta = self._meta
        profile = PROFILES[meta.profile]
        raw = np.frombuffer(b"".join(packets), dtype=np.uint8).reshape(len(packets), meta.packet_bytes)
        body = meta.packet_header_bytes + meta.columns_per_packet * meta.column_bytes
        columns = raw[:, meta.packet_header_bytes:body].reshape(-1, meta.column_bytes)
        stamps_ns = columns[:, 0:8].copy().view("<u8")[:, 0]
        measurement = columns[:, 8:10].copy().view("<u2")[:, 0]
        status = (columns[:, -4:].copy().view("<u4") if meta.legacy else columns[:, 10:12].copy().view("<u2"))[:, 0]
        pixels_end = meta.column_header_bytes + meta.pixels_per_column * profile.pixel_bytes
        pixels = columns[:, meta.column_header_bytes:pixels_end].reshape(len(columns), meta.pixels_per_column, -1)
        first_word = pixels[:, :, 0:4].copy().view("<u4")[:, :, 0]
        ranges_mm = (first_word & profile.range_mask) << profile.range_shift
        valid = ((status & COLUMN_VALID) != 0) & (measurement < meta.columns_per_frame)
        return measurement[valid].astype(np.intp), stamps_ns[valid], ranges_mm[valid]

    def _stamp_ns(self, packets: list[bytes]) -> int:
        """A frame's timestamp: its earliest return's column time (its earliest column's without returns)."""
        _, stamps_ns, ranges_mm = self._columns(packets)
        with_return = (ranges_mm != 0).any(axis=1)
        if with_return.any():
            return int(stamps_ns[with_return].min())
        if len(stamps_ns):
            return int(stamps_ns.min())
        first = packets[0]
        header = self._meta.packet_header_bytes
        return int.from_bytes(first[header:header + 8], "little")  # no valid column: the first column's time

    def __len__(self) -> int:
        return len(self._frames)

    def check(self) -> None:
        """Every frame was found and its packets' sizes checked when the pcap was indexed on opening."""

    def _frame(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Scan k's points (N, 3) and their column timestamps (N,) uint64 ns (the last one read is kept)."""
        if self._last is None or self._last[0] != k:
            frame = self._frames[k]
            packets = [payload for frame_id, _, _, payload in self._lidar_packets(frame.start, frame.end)
                       if frame_id == frame.frame_id]
            measurement, stamps_ns, ranges_mm = self._columns(packets)
            column, beam = np.nonzero(ranges_mm)
            m = measurement[column]
            points = ranges_mm[column, beam][:, None] * self._direction[beam, m] + self._offset[beam, m]
            self._last = (k, points, stamps_ns[column])
        return self._last[1], self._last[2]

    def timestamps(self) -> ScanTimestamps:
        return ScanTimestamps(np.array([f.stamp_ns for f in self._frames], dtype=np.float64) / NS_PER_S,
                              f"{self.name} (each frame's earliest return's column timestamp)")

    def time_field(self) -> PointTimeField:
        """The columns' timestamps, read as ns from the scan's earliest point (`DescribesTimeField`)."""
        return PointTimeField("timestamp", "uint64", "ns", True, "the scan's earliest point", 0.0,
                              ("timestamp", *PROFILES[self._meta.profile].fields))

    def close(self) -> None:
        self._last = None
        self._pcap.close()

    def describe(self) -> str:
        """What was found (`pa_cli.sources.datasets.describe_source`)."""
        return (f"{self.name}: Ouster pcap layout (metadata {self.metadata}, {self._meta.profile} profile), "
                f"{len(self)} scans, per-point times from the columns' timestamps, no ground truth in the layout")


def open_ouster_pcap(pcap: Path, metadata: Path) -> OusterPcapSource | OusterSdkSource:
    """The scans of an Ouster pcap: decoded by pa, or by ouster-sdk for what pa's decoder does not read."""
    meta = read_metadata(metadata)
    reason = meta.unsupported()
    if reason is None:
        return OusterPcapSource(pcap, meta)
    return OusterSdkSource(pcap, metadata, reason)


def import_ouster(reason: str, metadata: Path) -> tuple[Any, Any]:
    """ouster-sdk's `core` module and `open_source`; `InputError` naming how to install it when it is missing."""
    try:
        import ouster.sdk.core as core
        from ouster.sdk import open_source
    except ImportError:
        raise InputError(f"{metadata}: the sensor sends its lidar data with {reason}; pa decodes the LEGACY, "
                         f"{', '.join(p for p in PROFILES if p != 'LEGACY')} profiles with the standard header and "
                         "reads the others with ouster-sdk (1.0 or later), which is not installed. It pins rosbags "
                         f"0.9.23, older than pa's bag reader needs, so install it without its pins: "
                         f"`{OUSTER_INSTALL}`.") from None
    return core, open_source


class OusterSdkSource(_Frames):
    """The frames of an Ouster pcap as scans, read with ouster-sdk's `XYZLut` (the same scans, points
    and times as `OusterPcapSource`), for the packets pa's decoder does not read."""

    def __init__(self, pcap: Path, metadata: Path, reason: str) -> None:
        self.metadata = metadata
        self.name = str(pcap)
        self._reason = reason
        self._core, open_source = import_ouster(reason, metadata)
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
            returns = (frame.field(self._core.ChanField.RANGE) != 0).T  # column by column, as pa's decoder
            xyz = np.asarray(self._lut(frame)).transpose(1, 0, 2)[returns]
            stamps_ns = np.broadcast_to(np.asarray(frame.timestamp, dtype=np.uint64)[:, None], returns.shape)[returns]
            self._starts_ns[k] = int(stamps_ns.min()) if len(stamps_ns) else int(np.min(frame.timestamp))
            self._last = (k, np.asarray(xyz, dtype=np.float64), stamps_ns)
        return self._last[1], self._last[2]

    def timestamps(self) -> ScanTimestamps:
        for k in range(self._n):
            if k not in self._starts_ns:
                self._frame(k)
        return ScanTimestamps(np.array([self._starts_ns[k] / NS_PER_S for k in range(self._n)]),
                              f"{self.name} (each frame's earliest return's column timestamp)")

    def time_field(self) -> PointTimeField:
        """The columns' timestamps, read as ns from the scan's earliest point (`DescribesTimeField`)."""
        return PointTimeField("timestamp", "uint64", "ns", True, "the scan's earliest point", 0.0,
                              ("timestamp", *(str(f).lower() for f in self._source[0][0].fields)) if self._n else ())

    def close(self) -> None:
        self._last = None
        self._source.close()

    def describe(self) -> str:
        """What was found (`pa_cli.sources.datasets.describe_source`)."""
        return (f"{self.name}: Ouster pcap layout (metadata {self.metadata}, {self._reason}, read with ouster-sdk), "
                f"{self._n} scans, per-point times from the columns' timestamps, no ground truth in the layout")
