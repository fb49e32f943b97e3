"""Livox's own point message, `livox_ros_driver/CustomMsg` (and `livox_ros_driver2/CustomMsg`).

The message (the same in both packages)::

    std_msgs/Header header
    uint64 timebase              # ns, the instant offset_time counts from
    uint32 point_num
    uint8 lidar_id
    uint8[3] rsvd
    CustomPoint[] points         # uint32 offset_time (ns), float32 x y z, uint8 reflectivity tag line

`livox_types` gives these definitions for rosbags' type store, so a bag that carries no message
definitions (ROS2 sqlite3 bags before Iron) opens. A scan of 20 000 points is decoded with numpy
straight from the serialized bytes (`decode_custom_msg`): rosbags would build one Python object per
point, 0.1 s per message. The byte layout follows from the definition, so a bag whose definition
of these types differs is refused (`check_definitions`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pa_cli.errors import FormatError

PACKAGES = ("livox_ros_driver", "livox_ros_driver2")
CUSTOM_MSGTYPES = tuple(f"{package}/msg/CustomMsg" for package in PACKAGES)
CUSTOM_POINT_DEFINITION = """uint32 offset_time
float32 x
float32 y
float32 z
uint8 reflectivity
uint8 tag
uint8 line
"""
CUSTOM_MSG_DEFINITION = """std_msgs/Header header
uint64 timebase
uint32 point_num
uint8 lidar_id
uint8[3] rsvd
CustomPoint[] points
"""
NS_PER_S = 1e9
_CDR_HEADER_BYTES = 4  # encapsulation: 2 bytes kind (byte 1: 0 big-endian, 1 little-endian), 2 options
_POINT_FIELDS = ["offset_time", "x", "y", "z", "reflectivity", "tag", "line"]
_POINT_OFFSETS = [0, 4, 8, 12, 16, 17, 18]
_POINT_BYTES = 19  # one CustomPoint, packed (ROS1); CDR aligns each to 4 bytes (stride 20)


def livox_types() -> dict[str, Any]:
    """rosbags type definitions of CustomMsg and CustomPoint of both Livox packages."""
    from rosbags.typesys import get_types_from_msg

    types: dict[str, Any] = {}
    for package in PACKAGES:
        types.update(get_types_from_msg(CUSTOM_POINT_DEFINITION, f"{package}/msg/CustomPoint"))
        types.update(get_types_from_msg(CUSTOM_MSG_DEFINITION, f"{package}/msg/CustomMsg"))
    return types


def check_definitions(fielddefs: dict[str, Any], msgtype: str, where: str) -> None:
    """Refuse a bag whose definition of `msgtype` (or its point) is not Livox's: the bytes would not
    be where `decode_custom_msg` reads them."""
    ours = livox_types()
    point_type = msgtype.replace("CustomMsg", "CustomPoint")
    for name in (msgtype, point_type):
        if name in fielddefs and fielddefs[name] != ours[name]:
            found = " ".join(field for field, _ in fielddefs[name][1])
            expected = " ".join(field for field, _ in ours[name][1])
            raise FormatError(f"{where}: the bag defines {name} with the fields {found}; pa reads the Livox "
                              f"driver's definition ({expected}). Convert the topic to PointCloud2 first.")


@dataclass(frozen=True)
class CustomScan:
    """One decoded CustomMsg: header stamp and timebase (s), x y z (N, 3) float32, offset_time (N,) uint32 ns."""

    stamp_s: float
    timebase_s: float
    xyz: np.ndarray
    offset_time_ns: np.ndarray


def decode_custom_msg(raw: bytes | memoryview, ros2: bool, where: str) -> CustomScan:
    """A serialized CustomMsg (ROS1, or ROS2 CDR when `ros2`) decoded with numpy; `FormatError`
    naming `where` when the bytes are too few for the point count they declare."""
    data = bytes(raw)
    try:
        if ros2:
            endian = "<" if data[1] == 1 else ">"
            base = _CDR_HEADER_BYTES
            sec, nanosec, name_bytes = np.frombuffer(data, endian + "u4", 3, base)
            position = _align(12 + int(name_bytes), 8)  # offsets count from the end of the encapsulation
            stride = _align(_POINT_BYTES, 4)
        else:
            endian, base = "<", 0
            _, sec, nanosec, name_bytes = np.frombuffer(data, "<u4", 4, 0)
            position = 16 + int(name_bytes)
            stride = _POINT_BYTES
        timebase_ns = int(np.frombuffer(data, endian + "u8", 1, base + position)[0])
        position += 8 + 4 + 1 + 3  # timebase, point_num, lidar_id, rsvd
        if ros2:
            position = _align(position, 4)
        n_points = int(np.frombuffer(data, endian + "u4", 1, base + position)[0])
        start = base + position + 4
    except (IndexError, ValueError):
        raise FormatError(f"{where}: {len(data)} bytes are too few for a Livox CustomMsg header.") from None
    needed = start + max(n_points - 1, 0) * stride + (_POINT_BYTES if n_points else 0)
    if len(data) < needed:
        raise FormatError(f"{where}: a Livox CustomMsg with {n_points} points needs {needed} bytes, the message "
                          f"holds {len(data)}; it is truncated.")
    point = np.dtype({"names": _POINT_FIELDS,
                      "formats": [endian + "u4", endian + "f4", endian + "f4", endian + "f4", "u1", "u1", "u1"],
                      "offsets": _POINT_OFFSETS, "itemsize": stride})
    body = data[start:start + n_points * stride].ljust(n_points * stride, b"\0")  # CDR's last point: no padding
    points = np.frombuffer(body, dtype=point, count=n_points)
    xyz = np.column_stack([points[a] for a in "xyz"]) if n_points else np.empty((0, 3), np.float32)
    return CustomScan(float(sec) + float(nanosec) / NS_PER_S, timebase_ns / NS_PER_S, xyz,
                      points["offset_time"].copy())


def _align(position: int, size: int) -> int:
    return -(-position // size) * size
