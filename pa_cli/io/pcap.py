"""UDP datagrams from a packet capture in the classic libpcap format, IPv4 fragments reassembled.

A capture is a 24-byte global header (magic 0xa1b2c3d4 for microsecond or 0xa1b23c4d for
nanosecond timestamps, written in either byte order, which the magic tells; the link type at byte
20), then records: a 16-byte header (seconds, fraction, captured length, original length) and the
captured bytes. Link types read: Ethernet (with 802.1Q / 802.1ad tags), Linux cooked capture v1
and v2, and raw IP. Only IPv4 UDP datagrams are given; other packets (IPv6, TCP, ARP) are skipped.
A datagram larger than the link's MTU arrives in IPv4 fragments, joined here by (source,
destination, identification); a fragment never completed (lost in the capture) is dropped. A
record captured shorter than it was sent (a snap length) is skipped and counted, and so is a
record cut off by the end of the file. pcapng files (Wireshark's default) are refused with the
command that converts them.

`PcapFile.datagrams(start, end)` reads the records from byte `start` (a record's start, as given
by an earlier pass) to byte `end`, each datagram with the byte span of the records that carried
it, so that a reader can come back to a stretch of the capture without reading it all again.
"""

from __future__ import annotations

import mmap
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from pa_cli.errors import FormatError, InputError

GLOBAL_HEADER_BYTES, RECORD_HEADER_BYTES = 24, 16
MAGIC_US, MAGIC_NS = 0xA1B2C3D4, 0xA1B23C4D
PCAPNG_MAGIC = 0x0A0D0D0A  # a pcapng Section Header Block
LINKTYPE_ETHERNET, LINKTYPE_RAW, LINKTYPE_LINUX_SLL, LINKTYPE_LINUX_SLL2 = 1, 101, 113, 276
ETHERTYPE_IPV4, ETHERTYPE_VLAN, ETHERTYPE_QINQ = 0x0800, 0x8100, 0x88A8
IP_PROTOCOL_UDP = 17
UDP_HEADER_BYTES = 8
IP_MORE_FRAGMENTS, IP_FRAGMENT_OFFSET = 0x2000, 0x1FFF  # in the IPv4 flags/fragment-offset word; offset in 8 bytes
PENDING_DATAGRAMS = 256  # fragmented datagrams waiting for their other fragments; a sender sends them back to back


@dataclass(frozen=True)
class Datagram:
    """A UDP payload, its destination port and the byte span [start, end) of the records carrying it."""

    payload: bytes
    dst_port: int
    start: int
    end: int


@dataclass
class _Fragments:
    """The fragments of one IPv4 datagram seen so far: bytes by offset, its length once the last came."""

    start: int
    pieces: dict[int, bytes]
    length: int | None = None


class PcapFile:
    """An open classic pcap file (module docstring); `skipped` counts the records not read whole."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            self._file = open(path, "rb")  # noqa: SIM115 - kept open for the mmap, closed by close()
        except OSError as exc:
            raise InputError(f"{path}: cannot be opened ({exc.strerror}).") from None
        size = path.stat().st_size
        if size < GLOBAL_HEADER_BYTES:
            self._file.close()
            raise FormatError(f"{path}: {size} bytes, shorter than a pcap file's {GLOBAL_HEADER_BYTES}-byte "
                              "header; the recording is empty or was cut off.")
        self._data = mmap.mmap(self._file.fileno(), 0, access=mmap.ACCESS_READ)
        self._endian, self.linktype = self._global_header()
        self._record = struct.Struct(self._endian + "IIII")
        self.size = size
        self.skipped = 0

    def _global_header(self) -> tuple[str, int]:
        for endian in "<>":
            magic, linktype = struct.unpack_from(endian + "I", self._data, 0)[0], None
            if magic in (MAGIC_US, MAGIC_NS):
                linktype = struct.unpack_from(endian + "I", self._data, 20)[0] & 0xFFFF
                if linktype not in (LINKTYPE_ETHERNET, LINKTYPE_RAW, LINKTYPE_LINUX_SLL, LINKTYPE_LINUX_SLL2):
                    self.close()
                    raise FormatError(f"{self.path}: pcap link type {linktype}; pa reads Ethernet (1), raw IP "
                                      "(101) and Linux cooked captures (113, 276).")
                return endian, linktype
        first = struct.unpack_from("<I", self._data, 0)[0]
        self.close()
        if first == PCAPNG_MAGIC:
            raise FormatError(f"{self.path}: a pcapng file; pa reads the classic pcap format. Convert it with "
                              f"Wireshark's editcap: `editcap -F pcap {self.path.name} out.pcap`.")
        raise FormatError(f"{self.path}: not a pcap file (its first 4 bytes are 0x{first:08x}, not the pcap "
                          "magic 0xa1b2c3d4 or 0xa1b23c4d).")

    def datagrams(self, start: int = GLOBAL_HEADER_BYTES, end: int | None = None) -> Iterator[Datagram]:
        """The UDP datagrams of the records from byte `start` to `end` (default: the end of the file)."""
        data, record, linktype = self._data, self._record, self.linktype
        end = self.size if end is None else end
        pending: dict[tuple[bytes, bytes, int], _Fragments] = {}
        at = start
        while at + RECORD_HEADER_BYTES <= end:
            _, _, captured, original = record.unpack_from(data, at)
            body = at + RECORD_HEADER_BYTES
            if body + captured > self.size:
                self.skipped += 1  # cut off by the end of the file
                return
            record_start, at = at, body + captured
            if captured < original:
                self.skipped += 1
                continue
            ip = _ip_start(data, body, captured, linktype)
            if ip is None:
                continue
            datagram = _udp(data, ip, body + captured, record_start, at, pending)
            if datagram is not None:
                yield datagram

    def close(self) -> None:
        self._data.close()
        self._file.close()


def _ip_start(data: mmap.mmap, body: int, captured: int, linktype: int) -> int | None:
    """Where the IPv4 header of a record starts, or None for a record that holds none."""
    if linktype == LINKTYPE_RAW:
        return body if captured > 0 and data[body] >> 4 == 4 else None
    if linktype == LINKTYPE_LINUX_SLL:
        type_at, ip = body + 14, body + 16
    elif linktype == LINKTYPE_LINUX_SLL2:
        type_at, ip = body, body + 20
    else:
        type_at, ip = body + 12, body + 14
        while ip <= body + captured and struct.unpack_from(">H", data, type_at)[0] in (ETHERTYPE_VLAN, ETHERTYPE_QINQ):
            type_at, ip = type_at + 4, ip + 4
    if ip > body + captured or struct.unpack_from(">H", data, type_at)[0] != ETHERTYPE_IPV4:
        return None
    return ip


def _udp(data: mmap.mmap, ip: int, record_end: int, record_start: int, after: int,
         pending: dict[tuple[bytes, bytes, int], _Fragments]) -> Datagram | None:
    """The UDP datagram an IPv4 packet completes (itself, or the last missing fragment), or None."""
    if ip + 20 > record_end or data[ip + 9] != IP_PROTOCOL_UDP:
        return None
    header_bytes = (data[ip] & 0x0F) * 4
    total, ident, flags = struct.unpack_from(">HHH", data, ip + 2)
    body = data[ip + header_bytes:min(ip + total, record_end)]
    offset, more = (flags & IP_FRAGMENT_OFFSET) * 8, bool(flags & IP_MORE_FRAGMENTS)
    start = record_start
    if offset or more:
        key = (data[ip + 12:ip + 16], data[ip + 16:ip + 20], ident)
        fragments = pending.pop(key, None) or _Fragments(record_start, {})
        fragments.pieces[offset] = body
        if not more:
            fragments.length = offset + len(body)
        if fragments.length is None or sum(len(p) for p in fragments.pieces.values()) < fragments.length:
            pending[key] = fragments
            if len(pending) > PENDING_DATAGRAMS:
                del pending[next(iter(pending))]  # the oldest: a fragment of it was lost
            return None
        body = b"".join(fragments.pieces[o] for o in sorted(fragments.pieces))
        start = fragments.start
    if len(body) < UDP_HEADER_BYTES:
        return None
    dst_port, length = struct.unpack_from(">HH", body, 2)
    return Datagram(body[UDP_HEADER_BYTES:length], dst_port, start, after)
