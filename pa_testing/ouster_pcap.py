"""Ouster recordings written for the tests from the sensor manual: metadata `.json`, lidar packets
and the pcap carrying them, independent of pa's reader (`pa_cli.sources.ouster`).

- `metadata`: the nested metadata of firmware 2.x and later, or the flat one of older firmware.
- `beams`: each pixel's beam origin and direction in the sensor frame (metres), built by rotating
  the beam origin (bx, 0, bz) about z by the encoder angle and the direction (cos phi, 0, sin phi)
  by the encoder angle minus the beam's azimuth offset, then the lidar-to-sensor transform.
- `lidar_packets`: one frame's packets field by field with `struct` (LEGACY, the single- and
  dual-return 19-bit profiles, the 15-bit low-bandwidth one), flag bits set at random above the
  range and garbage in the pixels of invalid columns, so that a reader must mask and check status.
- `write_pcap`: UDP datagrams in IPv4 over Ethernet (optionally 802.1Q-tagged) or Linux cooked
  capture, fragmented at the MTU as a capture of a real sensor is, in a classic pcap file
  (microsecond or nanosecond, either byte order).
- `ray_cast_room`: ranges per (beam, column) of the beams against the planes of a room.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

ENCODER_TICKS = 90112  # encoder counts per turn (LEGACY column header)
SINGLE, DUAL, LOW_BANDWIDTH = "RNG19_RFL8_SIG16_NIR16", "RNG19_RFL8_SIG16_NIR16_DUAL", "RNG15_RFL8_NIR8"
RANGE_STEP_MM = {"LEGACY": 1, SINGLE: 1, DUAL: 1, LOW_BANDWIDTH: 8}
LIDAR_PORT, IMU_PORT = 7502, 7503
MTU_BYTES = 1500


def metadata(profile: str, altitude_deg, azimuth_deg, columns_per_frame: int, beam_origin_mm=(15.806, 0.0),
             lidar_to_sensor=None, serial: int = 992109000123, columns_per_packet: int = 16,
             flat: bool = False) -> dict:
    """A sensor's metadata; `flat`: the pre-2.0 layout (no beam_to_lidar_transform, no profile)."""
    bx, bz = beam_origin_mm
    lidar_to_sensor = np.diag([-1.0, -1.0, 1.0, 1.0]) if lidar_to_sensor is None else np.asarray(lidar_to_sensor)
    beam_to_lidar = np.eye(4)
    beam_to_lidar[0, 3], beam_to_lidar[2, 3] = bx, bz
    altitude, azimuth = [float(a) for a in altitude_deg], [float(a) for a in azimuth_deg]
    data_format = {"pixels_per_column": len(altitude), "columns_per_packet": columns_per_packet,
                   "columns_per_frame": columns_per_frame, "column_window": [0, columns_per_frame - 1],
                   "pixel_shift_by_row": [0] * len(altitude)}
    if flat:
        return {"beam_altitude_angles": altitude, "beam_azimuth_angles": azimuth,
                "lidar_origin_to_beam_origin_mm": bx, "lidar_to_sensor_transform": lidar_to_sensor.ravel().tolist(),
                "lidar_mode": f"{columns_per_frame}x10", "prod_sn": str(serial), "data_format": data_format}
    return {"sensor_info": {"prod_sn": str(serial), "initialization_id": 7, "prod_line": "OS-1-64"},
            "beam_intrinsics": {"beam_altitude_angles": altitude, "beam_azimuth_angles": azimuth,
                                "beam_to_lidar_transform": beam_to_lidar.ravel().tolist(),
                                "lidar_origin_to_beam_origin_mm": float(np.hypot(bx, bz))},
            "lidar_intrinsics": {"lidar_to_sensor_transform": lidar_to_sensor.ravel().tolist()},
            "imu_intrinsics": {"imu_to_sensor_transform": np.eye(4).ravel().tolist()},
            "calibration_status": {},
            "lidar_data_format": {**data_format, "udp_profile_lidar": profile, "udp_profile_imu": "LEGACY",
                                  "header_type": "STANDARD"},
            "config_params": {"lidar_mode": f"{columns_per_frame}x10", "udp_port_lidar": LIDAR_PORT,
                              "udp_port_imu": IMU_PORT}}


def beams(meta: dict) -> tuple[np.ndarray, np.ndarray]:
    """(origins, directions), each (H, W, 3), sensor frame, metres and unit vectors."""
    intrinsics = meta.get("beam_intrinsics", meta)
    altitude = np.deg2rad(intrinsics["beam_altitude_angles"])
    azimuth = np.deg2rad(intrinsics["beam_azimuth_angles"])
    transform = np.reshape(meta.get("lidar_intrinsics", meta)["lidar_to_sensor_transform"], (4, 4))
    if "beam_to_lidar_transform" in intrinsics:
        origin_mm = np.reshape(intrinsics["beam_to_lidar_transform"], (4, 4))[[0, 2], 3]
    else:
        origin_mm = np.array([intrinsics["lidar_origin_to_beam_origin_mm"], 0.0])
    w = meta.get("lidar_data_format", meta.get("data_format"))["columns_per_frame"]
    encoder = 2 * np.pi * (w - np.arange(w)) / w
    origin_lidar = Rotation.from_rotvec(np.outer(encoder, [0, 0, 1])).apply([origin_mm[0], 0.0, origin_mm[1]])
    origins = np.broadcast_to((origin_lidar @ transform[:3, :3].T + transform[:3, 3]) / 1000.0,
                              (len(altitude), w, 3))
    beam = np.column_stack([np.cos(altitude), np.zeros_like(altitude), np.sin(altitude)])  # (H, 3)
    angle = encoder[None, :] - azimuth[:, None]  # (H, W)
    directions = Rotation.from_rotvec(angle.reshape(-1, 1) * [0, 0, 1]).apply(np.repeat(beam, w, axis=0))
    directions = directions.reshape(len(altitude), w, 3) @ transform[:3, :3].T
    return origins, directions


def beam_origin_offset_mm(meta: dict) -> float:
    """n: the range the sensor adds from the lidar origin to the beam origin (mm)."""
    intrinsics = meta.get("beam_intrinsics", meta)
    if "beam_to_lidar_transform" in intrinsics:
        t = np.reshape(intrinsics["beam_to_lidar_transform"], (4, 4))
        return float(np.hypot(t[0, 3], t[2, 3]))
    return float(intrinsics["lidar_origin_to_beam_origin_mm"])


def ray_cast_room(origins: np.ndarray, directions: np.ndarray, planes: np.ndarray,
                  max_range_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Each beam's first hit on the planes (n . x + d = 0, sensor frame) within `max_range_m`:
    the distance from its origin (H, W), NaN for none, and the hit points (H, W, 3)."""
    best = np.full(origins.shape[:2], np.inf)
    for plane in planes:
        along = directions @ plane[:3]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -(origins @ plane[:3] + plane[3]) / along
        best = np.where((t > 0) & (t < best), t, best)
    best[best > max_range_m] = np.nan
    return best, origins + best[..., None] * directions


def _pixel(profile: str, range_mm: int, rng: np.random.Generator) -> bytes:
    """One pixel with random flag bits above the range and random other fields."""
    refl, signal, nir = (int(v) for v in rng.integers(0, 256, 3))
    flags = int(rng.integers(0, 32))
    if profile == "LEGACY":  # 20-bit range, then reflectivity, signal, near-IR, unused (uint16 each)
        return struct.pack("<IHHHH", range_mm | (flags << 27), refl, signal, nir, 0)
    if profile == SINGLE:  # 19-bit range, 5 flag bits; reflectivity, reserved (uint8); signal, near-IR, reserved
        return struct.pack("<IBBHHH", range_mm | (flags << 19), refl, 0, signal, nir, 0)
    if profile == DUAL:  # two returns: 19-bit range, 5 flag bits, reflectivity (8 bits) each; signals, near-IR
        second = int(rng.integers(0, 1 << 19))
        return struct.pack("<IIHHHH", range_mm | (flags << 19) | (refl << 24), second | (refl << 24), signal,
                           signal, nir, 0)
    # low bandwidth: 15-bit range in 8 mm steps, a flag bit; reflectivity, near-IR (uint8)
    return struct.pack("<HBB", (range_mm >> 3) | ((flags & 1) << 15), refl, nir)


def lidar_packets(profile: str, frame_id: int, ranges_mm: np.ndarray, stamps_ns: np.ndarray, valid: np.ndarray,
                  serial: int = 992109000123, init_id: int = 7, columns_per_packet: int = 16,
                  seed: int = 0) -> list[bytes]:
    """One frame's lidar packets: `ranges_mm` (H, W), column timestamps (W,), `valid` columns (W,)."""
    rng = np.random.default_rng(seed)
    h, w = ranges_mm.shape
    packets = []
    for first in range(0, w, columns_per_packet):
        columns = []
        for m in range(first, first + columns_per_packet):
            ok = bool(valid[m])
            values = ranges_mm[:, m] if ok else rng.integers(1, 1 << 15, h)  # an invalid column holds garbage
            pixels = b"".join(_pixel(profile, int(r), rng) for r in values)
            if profile == "LEGACY":
                header = struct.pack("<QHHI", int(stamps_ns[m]), m, frame_id, m * ENCODER_TICKS // w)
                columns.append(header + pixels + struct.pack("<I", 0xFFFFFFFF if ok else 0))
            else:
                columns.append(struct.pack("<QHH", int(stamps_ns[m]), m, 1 if ok else 0) + pixels)
        if profile == "LEGACY":
            packets.append(b"".join(columns))
        else:
            header = struct.pack("<HH", 1, frame_id) + init_id.to_bytes(3, "little") + serial.to_bytes(5, "little")
            packets.append(header + bytes(20) + b"".join(columns) + bytes(32))
    return packets


def imu_packet(stamp_ns: int) -> bytes:
    """A 48-byte IMU packet (three timestamps, six float32 readings)."""
    return struct.pack("<QQQ6f", stamp_ns, stamp_ns, stamp_ns, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)


def _ipv4_packets(payload: bytes, port: int, ident: int, mtu: int) -> list[bytes]:
    """The IPv4 packets of one UDP datagram (fragments of at most `mtu` bytes)."""
    udp = struct.pack(">HHHH", 50000, port, 8 + len(payload), 0) + payload
    step = (mtu - 20) // 8 * 8
    packets = []
    for at in range(0, len(udp), step):
        piece = udp[at:at + step]
        more = at + step < len(udp)
        header = struct.pack(">BBHHHBBH4s4s", 0x45, 0, 20 + len(piece), ident, (0x2000 if more else 0) | at // 8,
                             64, 17, 0, bytes([10, 0, 0, 2]), bytes([10, 0, 0, 1]))
        packets.append(header + piece)
    return packets


def write_pcap(path: Path, datagrams: list[tuple[bytes, int]], link: str = "ethernet", nanoseconds: bool = False,
               big_endian: bool = False, mtu: int = MTU_BYTES, snap_bytes: int | None = None) -> None:
    """A classic pcap of UDP datagrams `(payload, destination port)`; `link` is "ethernet", "vlan" or
    "sll"; `snap_bytes` cuts every record to that many bytes, as `tcpdump -s` does."""
    e = ">" if big_endian else "<"
    linktype = 113 if link == "sll" else 1
    out = [struct.pack(e + "IHHiIII", 0xA1B23C4D if nanoseconds else 0xA1B2C3D4, 2, 4, 0, 0, 262144, linktype)]
    for n, (payload, port) in enumerate(datagrams):
        for packet in _ipv4_packets(payload, port, n & 0xFFFF, mtu):
            if link == "sll":
                frame = struct.pack(">HHH8sH", 0, 1, 6, bytes(8), 0x0800) + packet
            elif link == "vlan":
                frame = bytes(12) + struct.pack(">HHH", 0x8100, 5, 0x0800) + packet
            else:
                frame = bytes(12) + struct.pack(">H", 0x0800) + packet
            kept = frame if snap_bytes is None else frame[:snap_bytes]
            out.append(struct.pack(e + "IIII", 1_700_000_000, n, len(kept), len(frame)) + kept)
    path.write_bytes(b"".join(out))
