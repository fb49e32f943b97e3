"""`pa refine` on an Ouster pcap against the same scans read from a PCD folder.

Motion-distorted street sweeps from the simulator (16 beams, 512 columns, each column fired at its
own time and pose) are written twice: as a PCD folder with per-point times, and as an Ouster pcap
(`pa_testing.ouster_pcap`: RNG19_RFL8_SIG16_NIR16 packets, IP-fragmented, with IMU packets) whose
metadata describes the simulator's beams - an Ouster mounted upside down (lidar-to-sensor a half
turn about x), so that its clockwise columns sweep counter-clockwise in the sensor frame as the
simulator's do, beam i at the altitude of the simulator's beam i turned over, no beam-origin
offset. Each return's range is its distance in mm, each column's timestamp its firing time. The
pcap's points must be the simulator's to within half a millimetre, and its refined trajectory's
ATE within 2x of the folder's.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from pa_testing import ouster_pcap as op

N_SCANS, BEAMS, COLUMNS = 12, 16, 512
EPOCH_NS = 1_700_000_000_000_000_000
PRESET = "outdoor"
UPSIDE_DOWN = np.diag([1.0, -1.0, -1.0, 1.0])  # lidar-to-sensor: a half turn about x

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def street():
    from pa_cli.simulate import SimOptions, simulate_sequence

    return simulate_sequence(SimOptions(scene="street", scans=N_SCANS, beams=BEAMS, azimuth_steps=COLUMNS, seed=3,
                                        motion_distortion=True))


def _column_ns(column: np.ndarray) -> np.ndarray:
    from pa_cli.simulate import SCAN_PERIOD_S

    return np.rint(column / COLUMNS * SCAN_PERIOD_S * 1e9).astype(np.int64)


def _sweep_start_ns(k: int) -> int:
    from pa_cli.simulate import SCAN_PERIOD_S

    return EPOCH_NS + round(k * SCAN_PERIOD_S * 1e9)


def _write_pcap(path, street) -> None:
    """The sweeps as Ouster frames (module docstring); each point's beam from its elevation, its
    column from its time."""
    from pa_cli.simulate import SCAN_PERIOD_S

    elevation_deg = np.linspace(-street.options.vfov_deg / 2, street.options.vfov_deg / 2, BEAMS)
    meta = op.metadata(op.SINGLE, -elevation_deg, np.zeros(BEAMS), COLUMNS, (0.0, 0.0), UPSIDE_DOWN)
    datagrams = []
    for k, scan in enumerate(street.scans):
        p = scan.points_scan
        beam = np.rint((np.rad2deg(np.arcsin(p[:, 2] / np.linalg.norm(p, axis=1))) - elevation_deg[0])
                       / (elevation_deg[1] - elevation_deg[0])).astype(int)
        column = np.rint(scan.time / SCAN_PERIOD_S * COLUMNS).astype(int)
        ranges_mm = np.zeros((BEAMS, COLUMNS), dtype=np.int64)
        ranges_mm[beam, column] = np.rint(np.linalg.norm(p, axis=1) * 1000)
        stamps_ns = _sweep_start_ns(k) + _column_ns(np.arange(COLUMNS))
        for n, packet in enumerate(op.lidar_packets(op.SINGLE, k, ranges_mm, stamps_ns, np.ones(COLUMNS, bool))):
            datagrams.append((packet, op.LIDAR_PORT))
            if n % 8 == 0:
                datagrams.append((op.imu_packet(int(stamps_ns[0])), op.IMU_PORT))
    op.write_pcap(path / "drive.pcap", datagrams)
    (path / "drive.json").write_text(json.dumps(meta))


def _refine(scans, out_dir, gt) -> dict:
    from pa_cli.cli import run

    code = run([str(a) for a in ("refine", scans, "--out", out_dir / "map.ply", "--config", PRESET, "--gt", gt, "-q")])
    assert code == 0
    return json.loads((out_dir / "map_report.json").read_text())


def test_a_pcap_refines_as_the_same_scans_from_a_folder(tmp_path, street):
    from pa_cli.io.scans import write_pcd
    from pa_cli.io.trajectory import write_kitti
    from pa_cli.sources import open_source

    write_kitti(tmp_path / "gt.txt", street.T_world_scan)
    folder = tmp_path / "folder"
    (folder / "scans").mkdir(parents=True)
    for k, scan in enumerate(street.scans):
        write_pcd(folder / "scans" / f"{k:06d}.pcd", scan.points_scan, time=scan.time)
    (folder / "scans" / "times.txt").write_text("".join(f"{_sweep_start_ns(k) / 1e9:.9f}\n" for k in range(N_SCANS)))
    recording = tmp_path / "recording"
    recording.mkdir()
    _write_pcap(recording, street)

    source = open_source(recording / "drive.pcap")
    assert len(source) == N_SCANS
    for k in (0, N_SCANS - 1):  # column by column, beams in order: the simulator's order
        scan = street.scans[k]
        assert np.linalg.norm(source.points(k) - scan.points_scan, axis=1).max() <= 0.0005 + 1e-9
        np.testing.assert_allclose(source.point_times(k), scan.time - scan.time.min(), rtol=0, atol=1e-9)
    source.close()

    reference = _refine(folder / "scans", folder, tmp_path / "gt.txt")
    report = _refine(recording / "drive.pcap", recording, tmp_path / "gt.txt")
    assert report["input"]["n_scans"] == N_SCANS and report["gt"]["refined"]["n_poses"] == N_SCANS
    assert report["deskew"]["enabled"] and reference["deskew"]["enabled"]
    assert report["deskew"]["time_field"]["name"] == "timestamp"
    ate, ate_folder = report["gt"]["refined"]["ate_rmse_m"], reference["gt"]["refined"]["ate_rmse_m"]
    print(f"ATE RMSE: pcap {ate:.4f} m, PCD folder {ate_folder:.4f} m")
    assert ate <= 2 * ate_folder, (ate, ate_folder)
    for run in (report, reference):
        assert run["quality"]["verdict"] != "degraded", run["quality"]["reasons"]
