"""`pa refine` on each public dataset's layout against the same scans read from a plain folder.

Motion-distorted street sweeps from the simulator (ground truth at each sweep's start) are written
in KITTI odometry, MulRan, Newer College and NCLT layouts (`pa_testing.dataset_layouts`), each with
its ground truth in the dataset's own file and convention, given to `--gt`. Each run must find
its layout, convert its ground truth, and reach an ATE within 2x of `pa refine` on the same scans
from a folder (with per-point times for Newer College, whose PCDs carry `t`; without for the
others, whose files carry none). `--first/--last/--every` on a dataset gives the run of a folder
holding only the kept scans, with the ground truth following. The Ouster pcap layout is checked
in tests/e2e/test_ouster_pcap.py.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from pa_testing import dataset_layouts as layouts

N_SCANS = 10
AZIMUTH_STEPS = 512
PRESET = "outdoor"

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def street():
    from pa_cli.simulate import SimOptions, simulate_sequence

    return simulate_sequence(SimOptions(scene="street", scans=N_SCANS, beams=16, azimuth_steps=AZIMUTH_STEPS,
                                        seed=3, motion_distortion=True))


def _refine(scans, out_dir, *extra) -> dict:
    from pa_cli.cli import run

    code = run([str(a) for a in ("refine", scans, "--out", out_dir / "map.ply", "--config", PRESET, *extra)])
    assert code == 0
    return json.loads((out_dir / "map_report.json").read_text())


@pytest.fixture(scope="module")
def folder_runs(tmp_path_factory, street):
    """The reference runs: the sweeps as a PCD folder with per-point times and as a BIN folder without."""
    from pa_cli.io.scans import write_pcd
    from pa_cli.io.trajectory import write_kitti

    root = tmp_path_factory.mktemp("folders")
    write_kitti(root / "gt.txt", street.T_world_scan)
    stamps = "".join(f"{t:.9f}\n" for t in layouts.stamps_s(N_SCANS))
    runs = {}
    for name in ("times", "plain"):
        (root / name / "scans").mkdir(parents=True)
        for k, scan in enumerate(street.scans):
            if name == "times":
                write_pcd(root / name / "scans" / f"{k:06d}.pcd", scan.points_scan, time=scan.time)
            else:
                layouts.write_bin(root / name / "scans" / f"{k:06d}.bin", scan.points_scan)
        (root / name / "scans" / "times.txt").write_text(stamps)
        runs[name] = _refine(root / name / "scans", root / name, "--gt", root / "gt.txt", "-q")
    return runs


def _write(kind: str, tmp_path, street):
    """The sweeps in `kind`'s layout with its ground truth: (path to give pa refine, --gt file)."""
    points = [scan.points_scan for scan in street.scans]
    stamps = layouts.stamps_s(N_SCANS)
    T = street.T_world_scan
    if kind == "kitti":
        seq = tmp_path / "sequences" / "07"
        layouts.write_kitti_scans(seq, points, stamps)
        return seq, layouts.write_kitti_gt(tmp_path, T, "07")
    if kind == "mulran":
        seq = tmp_path / "Sejong01"
        layouts.write_mulran_scans(seq, points, stamps)
        return seq, layouts.write_mulran_gt(seq, T, stamps)
    if kind == "ncd":
        seq = tmp_path / "01_short_experiment"
        layouts.write_ncd_scans(seq, points, [scan.time for scan in street.scans], stamps)
        return seq, layouts.write_ncd_gt(seq, T, stamps)
    seq = tmp_path / "2012-01-08"
    layouts.write_nclt_scans(seq, points, stamps)
    return seq, layouts.write_nclt_gt(seq, T, stamps)


@pytest.mark.parametrize(("kind", "name", "reference"), [
    ("kitti", "KITTI odometry", "plain"), ("mulran", "MulRan", "plain"), ("ncd", "Newer College", "times"),
    ("nclt", "NCLT", "plain")])
def test_each_layout_refines_as_the_same_scans_from_a_folder(tmp_path, street, folder_runs, capsys, kind, name,
                                                             reference):
    seq, gt = _write(kind, tmp_path, street)
    report = _refine(seq, tmp_path, "--gt", gt)
    err = "".join(capsys.readouterr().err.split())
    assert "".join(f"{seq}: {name} layout, {N_SCANS} scans".split()) in err
    assert "".join(f"ground truth {gt} (pass it with --gt)".split()) in err
    folder = folder_runs[reference]
    assert report["deskew"]["enabled"] == folder["deskew"]["enabled"] == (reference == "times")
    assert report["input"]["n_scans"] == N_SCANS and report["gt"]["refined"]["n_poses"] == N_SCANS
    ate, ate_folder = report["gt"]["refined"]["ate_rmse_m"], folder["gt"]["refined"]["ate_rmse_m"]
    assert ate <= 2 * ate_folder, (ate, ate_folder)
    assert report["quality"]["verdict"] != "degraded", report["quality"]["reasons"]


def test_a_subset_of_a_dataset_is_the_folder_of_its_scans(tmp_path, street):
    """--first 1 --last 8 --every 2 of a KITTI sequence (scans 1 3 5 7) with its camera-frame ground
    truth: the same poses as a folder holding those four scans, with the truth of those four."""
    from pa_cli.io.trajectory import read_trajectory, write_kitti

    seq, gt = _write("kitti", tmp_path / "kitti", street)
    report = _refine(seq, tmp_path, "--gt", gt, "--first", "1", "--last", "8", "--every", "2", "-q")
    kept = [1, 3, 5, 7]
    folder = tmp_path / "kept"
    (folder / "scans").mkdir(parents=True)
    for i, k in enumerate(kept):
        shutil.copy(seq / "velodyne" / f"{k:06d}.bin", folder / "scans" / f"{i:06d}.bin")
    times = (seq / "times.txt").read_text().splitlines()
    (folder / "scans" / "times.txt").write_text("".join(times[k] + "\n" for k in kept))
    write_kitti(folder / "gt.txt", street.T_world_scan[kept])
    reference = _refine(folder / "scans", folder, "--gt", folder / "gt.txt", "-q")
    assert report["input"]["n_scans"] == 4 and report["input"]["subset"].startswith("scans 1 to scan 8")
    assert report["gt"]["refined"]["n_poses"] == 4
    np.testing.assert_allclose(read_trajectory(tmp_path / "map_poses_kitti.txt").T_world_scan,
                               read_trajectory(folder / "map_poses_kitti.txt").T_world_scan, rtol=0, atol=1e-6)
    np.testing.assert_allclose(report["gt"]["refined"]["ate_rmse_m"], reference["gt"]["refined"]["ate_rmse_m"],
                               rtol=0, atol=1e-6)
