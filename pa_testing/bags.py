"""Bag writers for the tests: ROS1 `.bag` and ROS2 (sqlite3 or mcap) with rosbags' type stores."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def bag_writer(path: Path, ros: int, storage: str = "sqlite3") -> tuple[Any, Any, Any]:
    """(writer, serialize, typestore) for a ROS1 bag (`ros` 1: Noetic types) or a ROS2 bag folder
    (Humble types, `storage` sqlite3 or mcap); `serialize(message, msgtype)` gives the bytes to write."""
    from rosbags.typesys import Stores, get_typestore

    if ros == 1:
        from rosbags.rosbag1 import Writer

        typestore = get_typestore(Stores.ROS1_NOETIC)
        return Writer(path), typestore.serialize_ros1, typestore
    from rosbags.rosbag2 import StoragePlugin, Writer

    typestore = get_typestore(Stores.ROS2_HUMBLE)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    return Writer(path, version=9, storage_plugin=plugin), typestore.serialize_cdr, typestore
