"""The Ouster pcap reader (`pa_cli.sources.ouster`, `pa_cli.io.pcap`) against recordings written from
the sensor manual (`pa_testing.ouster_pcap`): a room ray-cast with each pixel's beam, its ranges
in each profile's packets, fragmented in a pcap with IMU packets, another sensor's packets and
other traffic; the points must be the ray-cast hits to within half a range step, at their
columns' times. With ouster-sdk installed, pa's points are also checked against its `XYZLut`, on
pcaps written by ouster-sdk and on those written here."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pa_cli.errors import FormatError, InputError
from pa_cli.sources import describe_source, open_source
from pa_cli.sources.ouster import OUSTER_INSTALL, OusterPcapSource, OusterSdkSource
from pa_testing import ouster_pcap as op

BEAMS, COLUMNS, N_FRAMES = 32, 512, 3  # 512: the narrowest lidar mode
EPOCH_NS, PERIOD_NS = 1_700_000_000_000_000_000, 100_000_000
MAX_RANGE_M = 7.5  # the room's far corners give no return
# the room, sensor frame (n . x + d = 0): floor, ceiling, four walls and a slanted panel
ROOM = np.array([[0, 0, 1, 1.2], [0, 0, -1, 2.5], [1, 0, 0, -6], [-1, 0, 0, -7], [0, 1, 0, -4], [0, -1, 0, -5]],
                dtype=np.float64)
PANEL_NORMAL = np.array([-1.0, -1.0, 0.5]) / np.linalg.norm([-1.0, -1.0, 0.5])
ROOM = np.vstack([ROOM, np.r_[PANEL_NORMAL, -PANEL_NORMAL @ np.array([3.0, 2.0, 0.0])]])
OS1_LIDAR_TO_SENSOR = np.array([[-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 1, 36.18], [0, 0, 0, 1]], dtype=np.float64)


def _sensor_metadata(profile: str, beam_origin_mm=(15.806, 0.0), tilt_deg: float = 0.0, flat: bool = False,
                     serial: int = 992109000123) -> dict:
    """An OS1-like sensor: uneven beam altitudes, staggered azimuth offsets, optionally tilted in its mount."""
    altitude = np.linspace(21.2, -21.5, BEAMS) + 0.05 * np.sin(np.arange(BEAMS))
    azimuth = np.tile([4.23, 1.41, -1.41, -4.23], BEAMS // 4)
    lidar_to_sensor = OS1_LIDAR_TO_SENSOR.copy()
    lidar_to_sensor[:3, :3] = Rotation.from_euler("xy", [tilt_deg, -tilt_deg / 2], degrees=True).as_matrix() \
        @ lidar_to_sensor[:3, :3]
    return op.metadata(profile, altitude, azimuth, COLUMNS, beam_origin_mm, lidar_to_sensor, serial=serial, flat=flat)


def _frames(meta: dict, profile: str):
    """Per frame: ranges (H, W) mm as the sensor quantises them, column timestamps, valid columns, and
    the hit points (H, W, 3) the ranges stand for."""
    origins, directions = op.beams(meta)
    distance_m, hits = op.ray_cast_room(origins, directions, ROOM, MAX_RANGE_M)
    step = op.RANGE_STEP_MM[profile]
    ranges_mm = np.where(np.isnan(distance_m), 0,
                         np.rint((np.nan_to_num(distance_m) * 1000 + op.beam_origin_offset_mm(meta)) / step) * step)
    frames = []
    for k in range(N_FRAMES):
        stamps_ns = EPOCH_NS + k * PERIOD_NS + np.arange(COLUMNS) * (PERIOD_NS // COLUMNS) + 37 * k
        valid = np.ones(COLUMNS, dtype=bool)
        valid[40 + 8 * k:70] = False  # columns outside the window, differing per frame
        frames.append((ranges_mm.astype(np.int64), stamps_ns, valid, hits))
    return frames


def _datagrams(meta: dict, profile: str, frames, other_serial: int | None = None) -> list[tuple[bytes, int]]:
    """The frames' packets with IMU packets, another sensor's packets and unrelated traffic between them."""
    datagrams = [(b"\x00" * 100, 5353)]
    serial = int(meta.get("sensor_info", meta)["prod_sn"])
    for k, (ranges_mm, stamps_ns, valid, _) in enumerate(frames):
        packets = op.lidar_packets(profile, 1000 + k, ranges_mm, stamps_ns, valid, serial=serial, seed=k)
        for n, packet in enumerate(packets):
            datagrams.append((packet, op.LIDAR_PORT))
            if n % 4 == 0:
                datagrams.append((op.imu_packet(int(stamps_ns[0])), op.IMU_PORT))
            if other_serial is not None and n == 5:
                datagrams.append((op.lidar_packets(profile, 7, ranges_mm + 500, stamps_ns, valid,
                                                   serial=other_serial)[2], op.LIDAR_PORT))
    return datagrams


def _write(tmp_path, meta: dict, datagrams, **pcap_options):
    op.write_pcap(tmp_path / "drive.pcap", datagrams, **pcap_options)
    (tmp_path / "drive.json").write_text(json.dumps(meta))
    return tmp_path / "drive.pcap"


def _expected(frame):
    """The hit points and column timestamps of a frame's returns, column by column, beams in order."""
    ranges_mm, stamps_ns, valid, hits = frame
    returns = (ranges_mm != 0) & valid[None, :]
    column, beam = np.nonzero(returns.T)
    return hits[beam, column], stamps_ns[column]


CASES = {  # name: profile, metadata options, pcap options
    "legacy": ("LEGACY", {}, {}),
    "legacy-flat-metadata": ("LEGACY", {"flat": True}, {"link": "vlan", "big_endian": True}),
    "single-return": (op.SINGLE, {"beam_origin_mm": (27.67, 4.5), "tilt_deg": 3.0},
                      {"link": "sll", "nanoseconds": True}),
    "dual-return": (op.DUAL, {}, {"big_endian": True, "nanoseconds": True}),
    "low-bandwidth": (op.LOW_BANDWIDTH, {"tilt_deg": -2.0}, {"mtu": 576}),
}


@pytest.mark.parametrize("name", list(CASES))
def test_each_profile_reads_the_ray_cast_room(tmp_path, name):
    profile, meta_options, pcap_options = CASES[name]
    meta = _sensor_metadata(profile, **meta_options)
    frames = _frames(meta, profile)
    other = None if profile == "LEGACY" else 992109000999  # a second sensor on the network
    pcap = _write(tmp_path, meta, _datagrams(meta, profile, frames, other), **pcap_options)
    source = open_source(tmp_path)  # the folder holding one pcap and its .json
    assert isinstance(source, OusterPcapSource) and len(source) == N_FRAMES
    assert f"{pcap}: Ouster pcap layout (metadata {tmp_path / 'drive.json'}, {profile} profile), 3 scans" \
        in describe_source(source)
    source.check()
    half_step_m = op.RANGE_STEP_MM[profile] / 2 / 1000
    stamps_s = source.timestamps().stamps_s
    for k in (1, 0, 2):
        hits, stamps_ns = _expected(frames[k])
        points = source.points(k)
        assert points.shape == hits.shape and len(points) > 0.5 * BEAMS * COLUMNS
        assert np.linalg.norm(points - hits, axis=1).max() <= half_step_m + 1e-9
        np.testing.assert_array_equal(source.point_times(k), (stamps_ns - stamps_ns.min()) / 1e9)
        assert stamps_s[k] == stamps_ns.min() / 1e9
    field = source.time_field()
    assert (field.name, field.dtype, field.unit, field.absolute) == ("timestamp", "uint64", "ns", True)
    source.close()


def test_a_frame_cut_by_the_recording_is_a_partial_scan(tmp_path):
    meta = _sensor_metadata(op.SINGLE)
    frames = _frames(meta, op.SINGLE)
    datagrams = _datagrams(meta, op.SINGLE, frames)
    _write(tmp_path, meta, datagrams[:-9])  # the last frame's last packets were not recorded
    source = open_source(tmp_path / "drive.pcap")
    hits, _ = _expected(frames[2])
    points = source.points(2)
    assert len(source) == N_FRAMES and 0 < len(points) < len(hits)
    assert np.linalg.norm(points - hits[:len(points)], axis=1).max() <= 0.0005 + 1e-9
    source.close()


# ---------------------------------------------------------------------------- errors


def _written(tmp_path, profile: str = op.SINGLE, **pcap_options):
    meta = _sensor_metadata(profile)
    return _write(tmp_path, meta, _datagrams(meta, profile, _frames(meta, profile)[:1]), **pcap_options), meta


@pytest.mark.parametrize(("change", "message"), [
    (lambda meta: "{not json", r"the Ouster metadata is not JSON \(Expecting property name"),
    (lambda meta: "[1, 2]", "the Ouster metadata is a JSON list, not an object"),
    (lambda meta: {**meta, "beam_intrinsics": {}}, r"has no `beam_altitude_angles` \(nor `beam_intrinsics.beam_"),
    (lambda meta: {**meta, "lidar_intrinsics": {"lidar_to_sensor_transform": [1, 0, 0]}},
     "a value of the Ouster metadata has the wrong type or shape"),
    (lambda meta: {**meta, "beam_intrinsics": {**meta["beam_intrinsics"], "beam_azimuth_angles": [0.0] * 3}},
     "gives 512 columns per frame of 32 pixels, 32 beam altitude and 3 azimuth angles"),
    (lambda meta: {**meta, "lidar_data_format": {**meta["lidar_data_format"], "pixels_per_column": 64}},
     "gives 512 columns per frame of 64 pixels, 32 beam altitude and 32 azimuth angles"),
    (lambda meta: {**meta, "lidar_data_format": {}, "config_params": {"lidar_mode": ""}},
     "gives 0 columns per frame"),
])
def test_bad_metadata_names_the_file_and_the_fix(tmp_path, change, message):
    pcap, meta = _written(tmp_path)
    changed = change(meta)
    (tmp_path / "drive.json").write_text(changed if isinstance(changed, str) else json.dumps(changed))
    with pytest.raises(FormatError, match=message) as error:
        open_source(pcap)
    assert str(tmp_path / "drive.json") in str(error.value) and "use the .json saved with the recording" in \
        str(error.value)


def test_bad_metadata_exits_1_without_a_traceback(tmp_path, run_pa):
    pcap, _ = _written(tmp_path)
    (tmp_path / "drive.json").write_text("{}")
    code, _, err = run_pa("refine", pcap, "--out", tmp_path / "map.ply")
    assert code == 1 and "Traceback" not in err and "has no `beam_altitude_angles`" in err
    assert not (tmp_path / "map.ply").exists()


def test_metadata_of_another_mode_or_sensor_finds_no_packets(tmp_path):
    pcap, meta = _written(tmp_path)
    other_mode = {**meta, "lidar_data_format": {**meta["lidar_data_format"], "udp_profile_lidar": "LEGACY"}}
    (tmp_path / "drive.json").write_text(json.dumps(other_mode))
    with pytest.raises(FormatError, match=r"no Ouster lidar packets of 6464 bytes \(the LEGACY profile, 32 pixels "
                                          r"x 16 columns per packet, as .*drive.json gives\) among the UDP datagrams "
                                          r"\(found: 32 of 6400 bytes, 8 of 48 bytes, 1 of 100 bytes\)"):
        open_source(pcap)
    other_sensor = {**meta, "sensor_info": {**meta["sensor_info"], "prod_sn": "992109000999"}}
    (tmp_path / "drive.json").write_text(json.dumps(other_sensor))
    with pytest.raises(FormatError, match="of 6400 bytes from serial number 992109000999 .* The metadata must be "
                                          "the one recorded with this pcap"):
        open_source(pcap)


def test_a_capture_cut_to_a_snap_length_is_reported(tmp_path):
    pcap, _ = _written(tmp_path, snap_bytes=1000)
    with pytest.raises(FormatError, match="records were captured cut short"):
        open_source(pcap)


@pytest.mark.parametrize(("content", "message"), [
    (bytes.fromhex("0a0d0d0a") + bytes(40), "a pcapng file; pa reads the classic pcap format. Convert it with "
                                            "Wireshark's editcap: `editcap -F pcap drive.pcap out.pcap`"),
    (b"GIF89a" + bytes(40), "not a pcap file"),
    (bytes(10), "shorter than a pcap file's 24-byte header"),
])
def test_a_file_that_is_no_classic_pcap_is_refused(tmp_path, content, message):
    _, meta = _written(tmp_path)
    (tmp_path / "drive.pcap").write_bytes(content)
    with pytest.raises(FormatError, match=message):
        open_source(tmp_path / "drive.pcap")


def test_another_profile_without_ouster_sdk_names_it_and_the_install(tmp_path, monkeypatch):
    pcap, meta = _written(tmp_path)
    five_word = {**meta, "lidar_data_format": {**meta["lidar_data_format"], "udp_profile_lidar": "FIVE_WORD_PIXEL"}}
    (tmp_path / "drive.json").write_text(json.dumps(five_word))
    monkeypatch.setitem(sys.modules, "ouster", None)  # as if ouster-sdk were not installed
    monkeypatch.setitem(sys.modules, "ouster.sdk", None)
    with pytest.raises(InputError, match="the sensor sends its lidar data with UDP lidar profile FIVE_WORD_PIXEL; pa "
                                         "decodes the LEGACY, RNG19_RFL8_SIG16_NIR16, .* not installed") as error:
        open_source(pcap)
    assert OUSTER_INSTALL in str(error.value)


# ---------------------------------------------------------------------------- ouster-sdk


def _sdk_frames(core, info, n: int = 3):
    """Frames with random ranges (multiples of 8 mm, every profile holds them), no return in a band
    and an invalid stretch of columns."""
    rng = np.random.default_rng(1)
    frames = []
    for k in range(n):
        frame = core.LidarFrame(info)
        ranges = frame.field(core.ChanField.RANGE)
        ranges[:] = rng.integers(60, 10_000, ranges.shape) * 8
        ranges[:, 100 + k:140] = 0
        frame.timestamp[:] = EPOCH_NS + k * PERIOD_NS + np.arange(info.w) * (PERIOD_NS // info.w)
        frame.status[:] = 1
        frame.status[200:216] = 0
        frame.frame_id = k
        frame.measurement_id[:] = np.arange(info.w)
        frames.append(frame)
    return frames


@pytest.mark.parametrize("profile", ["LEGACY", op.SINGLE, op.DUAL, op.LOW_BANDWIDTH, "RNG15_RFL8_NIR8_DUAL"])
def test_ouster_sdk_packets_read_as_its_xyz_lut_gives_them(tmp_path, profile):
    """Packets written by ouster-sdk; a profile pa does not decode is read through ouster-sdk."""
    core = pytest.importorskip("ouster.sdk.core", reason="ouster-sdk is not installed (see OUSTER_INSTALL)")
    from ouster.sdk import pcap

    info = core.SensorInfo.from_default(core.LidarMode._512x10)
    info.format.udp_profile_lidar = getattr(core.UDPProfileLidar, profile)
    info.config.udp_port_lidar, info.config.udp_port_imu = 7502, 7503
    frames = _sdk_frames(core, info)
    packets = [p for frame in frames for p in core.frame_to_packets(frame, core.PacketFormat(info), info.init_id,
                                                                     info.sn)]
    pcap.record(packets, str(tmp_path / "drive.pcap"))
    (tmp_path / "drive.json").write_text(info.to_json_string())
    source = open_source(tmp_path / "drive.pcap")
    assert isinstance(source, OusterSdkSource if profile == "RNG15_RFL8_NIR8_DUAL" else OusterPcapSource)
    lut = core.XYZLut(info)
    for k, frame in enumerate(frames):
        returns = ((frame.field(core.ChanField.RANGE) != 0) & (frame.status != 0)[None, :]).T  # column by column
        np.testing.assert_allclose(source.points(k), lut(frame).transpose(1, 0, 2)[returns], rtol=0, atol=1e-9)
        columns = np.broadcast_to(np.arange(info.w)[:, None], returns.shape)[returns]
        np.testing.assert_allclose(source.point_times(k), (columns - columns.min()) * (PERIOD_NS // info.w) / 1e9,
                                   rtol=0, atol=1e-9)
    source.close()


@pytest.mark.parametrize("name", list(CASES))
def test_ouster_sdk_reads_the_pcaps_written_here_as_pa_does(tmp_path, name):
    """The writer of these tests against ouster-sdk's reading: the same frames, points and times.
    Unfragmented (jumbo) packets: ouster-sdk 1.0.1's indexed pcap reading loses the first packet of
    the third frame of a fragmented capture (its unindexed reading does not)."""
    pytest.importorskip("ouster.sdk.core", reason="ouster-sdk is not installed (see OUSTER_INSTALL)")
    profile, meta_options, pcap_options = CASES[name]
    meta = _sensor_metadata(profile, **meta_options)
    frames = _frames(meta, profile)
    pcap = _write(tmp_path, meta, _datagrams(meta, profile, frames), **{**pcap_options, "mtu": 9000})
    ours = open_source(pcap)
    sdk = OusterSdkSource(pcap, tmp_path / "drive.json", "a cross-check")
    assert len(sdk) == len(ours) == N_FRAMES
    for k in range(N_FRAMES):
        by_position = np.lexsort(np.round(ours.points(k), 6).T)
        by_position_sdk = np.lexsort(np.round(sdk.points(k), 6).T)
        np.testing.assert_allclose(ours.points(k)[by_position], sdk.points(k)[by_position_sdk], rtol=0, atol=1e-9)
        np.testing.assert_allclose(ours.point_times(k)[by_position], sdk.point_times(k)[by_position_sdk], rtol=0,
                                   atol=1e-9)
    np.testing.assert_allclose(ours.timestamps().stamps_s, sdk.timestamps().stamps_s, rtol=0, atol=1e-9)
    ours.close()
    sdk.close()
