"""A ROS1 bag without its index (a recording cut off): the messages of its complete chunks.

`rosbag record` writes the index at the end of the file when it closes the bag; a recording that
was killed, or a file cut off in a copy, has none, and rosbags refuses to open it.
`ChunkScanReader` is rosbags' ROS1 `Reader` whose `open()` walks the records from the start instead
of reading the index: each complete chunk's connections and messages are indexed, and the walk
stops at the first record that is cut off or damaged (`stopped` says where). Everything else
(reading messages, deserialising) is rosbags' own: `open_unindexed` gives an `AnyReader` over it.
"""

from __future__ import annotations

import os
from collections import defaultdict
from io import BytesIO
from typing import Any, BinaryIO

from rosbags.rosbag1.reader import (
    Chunk,
    Header,
    IndexData,
    Reader,
    ReaderError,
    RecordType,
    decompressors,
    read_bytes,
    read_uint32,
)

ROS1_MAGIC = b"#ROSBAG V2.0\n"


class ChunkScanReader(Reader):
    """rosbags' ROS1 reader, opened by a walk over the records instead of the index."""

    stopped: str | None = None

    def open(self) -> None:
        """Index the messages of every complete chunk, from the start of the file."""
        self.bio = self.path.open("rb")
        size = self.path.stat().st_size
        if self.bio.readline() != ROS1_MAGIC:
            raise ReaderError("File magic is invalid; not a ROS1 bag (version 2.0).")
        Header.read(self.bio, RecordType.BAGHEADER)
        self.bio.seek(read_uint32(self.bio), os.SEEK_CUR)  # the bag header's padding
        connections: dict[int, Any] = {}
        indexes: dict[int, list[IndexData]] = defaultdict(list)
        while self.bio.tell() < size:
            pos = self.bio.tell()
            try:
                self._read_record(pos, connections, indexes)
            except Exception as exc:  # a library boundary: a record cut off or damaged ends the walk
                self.stopped = f"byte {pos} of {size} ({type(exc).__name__}: {exc})"
                break
        self.indexes = {cid: sorted(indexes[cid]) for cid in connections}
        self.connections = [c._replace(msgcount=len(self.indexes[c.id])) for c in connections.values()]

    def _read_record(self, pos: int, connections: dict[int, Any], indexes: dict[int, list[IndexData]]) -> None:
        """Read the record at `pos` (the file's position): a connection is kept, a chunk indexed, others skipped."""
        header = Header.read(self.bio)
        op = header.get_uint8("op")
        datasize = read_uint32(self.bio)
        if op == RecordType.CONNECTION:
            self.bio.seek(pos)
            connection = self._connection(self.bio)
            connections.setdefault(connection.id, connection)
        elif op == RecordType.CHUNK:
            decompressor = decompressors[header.get_string("compression")]
            datapos = self.bio.tell()
            found = self._chunk_records(BytesIO(decompressor(read_bytes(self.bio, datasize))), pos, connections)
            self.chunks[pos] = Chunk(datasize, datapos, decompressor)
            for cid, entry in found:
                indexes[cid].append(entry)
        else:
            self.bio.seek(datasize, os.SEEK_CUR)

    def _chunk_records(self, chunk: BinaryIO, chunk_pos: int, connections: dict[int, Any]
                       ) -> list[tuple[int, IndexData]]:
        """(connection id, index entry) of each message of a decompressed chunk; its connections kept."""
        found = []
        size = len(chunk.getbuffer())
        while chunk.tell() < size:
            offset = chunk.tell()
            header = Header.read(chunk)
            op = header.get_uint8("op")
            if op == RecordType.CONNECTION:
                chunk.seek(offset)
                connection = self._connection(chunk)
                connections.setdefault(connection.id, connection)
                continue
            if op == RecordType.MSGDATA:
                found.append((header.get_uint32("conn"), IndexData(header.get_time("time"), chunk_pos, offset)))
            chunk.seek(read_uint32(chunk), os.SEEK_CUR)
        return found

    def _connection(self, src: BinaryIO) -> Any:
        """The connection record at `src`'s position, read by rosbags' `read_connection`."""
        bio, self.bio = self.bio, src
        try:
            return self.read_connection()
        finally:
            self.bio = bio


def open_unindexed(path: Any, default_typestore: Any) -> tuple[Any, ChunkScanReader]:
    """An open `AnyReader` over the ROS1 bag `path` read by `ChunkScanReader`, and that reader."""
    from rosbags.highlevel import AnyReader

    reader = AnyReader([path], default_typestore=default_typestore)
    scan = ChunkScanReader(path)
    reader.readers = [scan]
    reader.open()
    return reader, scan
