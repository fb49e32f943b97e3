"""`pa simulate`: ground-truth consistency, determinism, bad arguments, motion distortion."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pa_cli.io.trajectory import read_trajectory
from pa_cli.simulate import (
    SCAN_PERIOD_S,
    SimOptions,
    Simulator,
    build_problem_from_labels,
    make_scene,
    simulate_sequence,
)

SIGMA_M = 0.01
SMALL = ["--scans", "4", "--azimuth-steps", "128"]


def _read_pcd(path: Path) -> tuple[np.ndarray, list[str]]:
    from pypcd4 import PointCloud

    cloud = PointCloud.from_path(path)
    return cloud.numpy().astype(np.float64), list(cloud.fields)


def _world(points_scan: np.ndarray, T_world_scan: np.ndarray) -> np.ndarray:
    """Points (M, 3) to the world with one pose (4, 4) or one pose per point (M, 4, 4)."""
    if T_world_scan.ndim == 2:
        return points_scan @ T_world_scan[:3, :3].T + T_world_scan[:3, 3]
    return np.einsum("nij,nj->ni", T_world_scan[:, :3, :3], points_scan) + T_world_scan[:, :3, 3]


def _signed_dist(points_world: np.ndarray, labels: np.ndarray, planes: np.ndarray) -> np.ndarray:
    pl = planes[labels]
    return np.einsum("ij,ij->i", pl[:, :3], points_world) + pl[:, 3]


# ---------------------------------------------------------------------------- scene geometry


@pytest.mark.parametrize("name", ["office", "street", "town", "blocks"])
def test_every_labelled_triangle_lies_on_its_plane(name):
    mesh = make_scene(name).mesh
    planes = mesh.planes_world
    assert len(planes) > 20
    np.testing.assert_allclose(np.linalg.norm(planes[:, :3], axis=1), 1.0, atol=1e-12)
    lab = mesh.triangle_label >= 0
    tri_vertices = mesh.vertices[mesh.triangles[lab]]  # (T, 3, 3)
    pl = planes[mesh.triangle_label[lab]]
    dist = np.einsum("tk,tvk->tv", pl[:, :3], tri_vertices) + pl[:, 3:4]
    assert np.abs(dist).max() < 1e-9
    # Distinct labels are distinct infinite planes (no duplicates up to sign).
    canon = planes * np.where(planes[:, :3] @ [1.0, np.pi, np.e] >= 0, 1.0, -1.0)[:, None]
    gaps = np.linalg.norm(canon[:, None, :] - canon[None, :, :], axis=2)
    np.fill_diagonal(gaps, np.inf)
    assert gaps.min() > 1e-4
    assert np.any(mesh.triangle_label < 0)  # clutter exists


@pytest.mark.parametrize(("name", "path"), [("office", None), ("street", None), ("town", "circuit"),
                                            ("town", "figure8"), ("blocks", "circuit")])
def test_sensor_path_stays_clear_of_the_geometry(name, path):
    from pa_cli.runtime.open3d_preload import open3d

    o3d = open3d()
    sim = Simulator(SimOptions(scene=name, path=path, azimuth_steps=64))
    s = np.linspace(0.0, sim.path.length_m, 4000)
    T = sim.path.poses(s)
    clearance = sim._raycaster.compute_distance(o3d.core.Tensor(T[:, :3, 3].astype(np.float32))).numpy()
    assert clearance.min() > 0.25
    # Poses are rotations, yaw follows the path, roll/pitch stay small.
    R = T[:, :3, :3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    forward = np.diff(T[:, :2, 3], axis=0)
    forward /= np.linalg.norm(forward, axis=1, keepdims=True)
    assert np.min(np.einsum("ij,ij->i", forward, R[:-1, :2, 0]) / np.linalg.norm(R[:-1, :2, 0], axis=1)) > 0.99
    assert np.degrees(np.arcsin(np.abs(R[:, 2, 0]).max())) < 3.0


@pytest.mark.slow
def test_loop_paths_revisit_places():
    """The circuit repeats itself lap after lap; the figure eight crosses itself at right angles."""
    for path in ("circuit", "figure8"):
        sim = Simulator(SimOptions(scene="town", path=path, scans=3000, azimuth_steps=64))
        T = sim.gt_poses()
        lap_scans = sim.path.length_m / sim.options.step_m
        assert len(T) > 6 * lap_scans  # thousands of scans drive the path again and again
        s = np.linspace(0.0, sim.path.length_m, 2000, endpoint=False)
        np.testing.assert_allclose(sim.path.poses(s + sim.path.length_m), sim.path.poses(s), atol=1e-9)
    sim = Simulator(SimOptions(scene="town", path="figure8", azimuth_steps=64))
    s = np.linspace(0.0, sim.path.length_m, 4000, endpoint=False)
    T = sim.path.poses(s)
    gap = np.linalg.norm(T[:, None, :2, 3] - T[None, :, :2, 3], axis=2)
    apart = np.abs(s[:, None] - s[None, :]) > 50.0  # far apart along the path
    i, j = np.unravel_index(np.argmin(np.where(apart, gap, np.inf)), gap.shape)
    assert gap[i, j] < 0.2
    assert abs(T[i, :2, 0] @ T[j, :2, 0]) < 0.05  # the headings are perpendicular at the crossing


# ---------------------------------------------------------------------------- GT consistency


@pytest.mark.parametrize("name", ["office", "street"])
def test_noise_free_points_are_the_first_hit_on_their_true_plane(name):
    seq = simulate_sequence(SimOptions(scene=name, scans=3, beams=32, azimuth_steps=256, range_noise_m=0.0))
    sim = Simulator(SimOptions(scene=name, azimuth_steps=64))  # independent raycaster
    o3d_tensor = __import__("pa_cli.runtime.open3d_preload", fromlist=["open3d"]).open3d().core.Tensor
    for scan, T in zip(seq.scans, seq.T_world_scan, strict=True):
        lab = scan.labels >= 0
        assert lab.mean() > 0.8
        pw = _world(scan.points_scan[lab], T)
        assert np.abs(_signed_dist(pw, scan.labels[lab], seq.planes_world)).max() < 1e-9
        # Re-cast the rays through the stored points: the first hit is at the stored range.
        r = np.linalg.norm(scan.points_scan, axis=1)
        dirs_world = (scan.points_scan / r[:, None]) @ T[:3, :3].T
        rays = np.hstack([np.broadcast_to(T[:3, 3], dirs_world.shape), dirs_world]).astype(np.float32)
        t_hit = sim._raycaster.cast_rays(o3d_tensor(rays))["t_hit"].numpy()
        assert np.abs(t_hit - r).max() < 2e-3 * max(1.0, r.max() / 10)
        assert r.min() >= 0.5 and r.max() <= seq.options.max_range_m


def test_range_noise_is_gaussian_along_the_ray():
    seq = simulate_sequence(SimOptions(scene="office", scans=4, beams=32, azimuth_steps=512,
                                       range_noise_m=SIGMA_M, seed=3))
    along_ray = []
    for scan, T in zip(seq.scans, seq.T_world_scan, strict=True):
        lab = scan.labels >= 0
        pts = scan.points_scan[lab]
        pw = _world(pts, T)
        normals_scan = seq.planes_world[scan.labels[lab], :3] @ T[:3, :3]
        cos_incidence = np.einsum("ij,ij->i", normals_scan, pts / np.linalg.norm(pts, axis=1, keepdims=True))
        along_ray.append(_signed_dist(pw, scan.labels[lab], seq.planes_world) / cos_incidence)
    e = np.concatenate(along_ray)
    assert len(e) > 50_000
    assert abs(e.mean()) < 5 * SIGMA_M / np.sqrt(len(e))
    assert abs(e.std() / SIGMA_M - 1.0) < 0.02
    assert np.abs(e).max() < 6.5 * SIGMA_M


def test_files_hold_the_ground_truth(tmp_path, run_pa):
    out = tmp_path / "seq"
    code, _, err = run_pa("simulate", "street", out, "--scans", "5", "--beams", "32", "--azimuth-steps", "256",
                          "--seed", "7")
    assert code == 0, err
    T = read_trajectory(out / "gt_poses_kitti.txt").T_world_scan
    tum = read_trajectory(out / "gt_poses_tum.txt")
    np.testing.assert_allclose(tum.T_world_scan, T, atol=1e-8)
    np.testing.assert_allclose(tum.timestamps, np.arange(5) * SCAN_PERIOD_S, atol=1e-9)
    # Driving speed: 1 m per scan by default on the street.
    np.testing.assert_allclose(np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1), 1.0, atol=0.02)
    planes = np.load(out / "planes.npy")
    meta = json.loads((out / "meta.json").read_text())
    assert meta["n_planes"] == len(planes) and meta["options"]["seed"] == 7
    for k in range(5):
        data, fields = _read_pcd(out / "scans" / f"{k:06d}.pcd")
        assert fields == ["x", "y", "z", "intensity"]
        labels = np.load(out / "labels" / f"{k:06d}.npy")
        assert labels.dtype == np.int32 and labels.shape == (len(data),)
        lab = labels >= 0
        pw = _world(data[lab, :3], T[k])
        dist = _signed_dist(pw, labels[lab], planes)
        # |dist| = |noise| * |cos incidence| <= |noise|; plus float32 rounding of the coordinates.
        assert np.abs(dist).max() < 6.5 * SIGMA_M + 1e-4
        assert 0.5 * SIGMA_M < dist.std() < SIGMA_M
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp folders left


# ---------------------------------------------------------------------------- determinism


def _tree_bytes(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_same_seed_gives_byte_identical_files(tmp_path, run_pa):
    """Within one installation the simulator is byte-deterministic (README, sample-data contract)."""
    for name in ("a", "b"):
        code, _, err = run_pa("simulate", "office", tmp_path / name, *SMALL, "--seed", "5",
                              "--motion-distortion")
        assert code == 0, err
    a, b = _tree_bytes(tmp_path / "a"), _tree_bytes(tmp_path / "b")
    assert len(a) == 4 + 4 + 5 and a == b  # scans, labels; 2 poses files, planes, meta, times
    code, _, err = run_pa("simulate", "office", tmp_path / "c", *SMALL, "--seed", "6", "--motion-distortion")
    assert code == 0, err
    c = _tree_bytes(tmp_path / "c")
    assert c["scans/000000.pcd"] != a["scans/000000.pcd"]
    assert c["gt_poses_kitti.txt"] == a["gt_poses_kitti.txt"]  # the seed drives the noise only


# ---------------------------------------------------------------------------- bad arguments


@pytest.mark.parametrize("args, needle", [
    (["park"], "park"),
    (["office", "--beams", "12"], "--beams"),
    (["office", "--scans", "0"], "--scans"),
    (["office", "--scans", "-3"], "--scans"),
    (["office", "--step-m", "-0.1"], "--step-m"),
    (["office", "--azimuth-steps", "0"], "--azimuth-steps"),
    (["office", "--range-noise-m", "-0.01"], "--range-noise-m"),
    (["office", "--max-range-m", "0"], "--max-range-m"),
    (["office", "--vfov-deg", "-5"], "--vfov-deg"),
    (["office", "--seed", "-1"], "--seed"),
    (["office", "--scans", "many"], "--scans"),
    (["office", "--path", "figure8"], "--path"),
])
def test_bad_arguments_are_usage_errors(tmp_path, run_pa, args, needle):
    scene, *rest = args
    code, _, err = run_pa("simulate", scene, tmp_path / "out", *rest)
    assert code == 2
    assert needle in err
    assert "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_non_empty_out_dir_needs_force(tmp_path, run_pa):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    code, _, err = run_pa("simulate", "office", out, *SMALL)
    assert code == 1
    assert "--force" in err and "not empty" in err
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    code, _, err = run_pa("simulate", "office", out, *SMALL, "--force")
    assert code == 0, err
    assert not (out / "keep.txt").exists() and (out / "scans" / "000003.pcd").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_empty_out_dir_is_used_and_missing_parent_is_refused(tmp_path, run_pa):
    out = tmp_path / "empty"
    out.mkdir()
    assert run_pa("simulate", "office", out, *SMALL)[0] == 0
    code, _, err = run_pa("simulate", "office", tmp_path / "no" / "such" / "dir", *SMALL)
    assert code == 1 and "does not exist" in err
    file_out = tmp_path / "file"
    file_out.write_text("x")
    code, _, err = run_pa("simulate", "office", file_out, *SMALL)
    assert code == 1 and "not a folder" in err


@pytest.mark.parametrize("case", ["file", "no_parent", "not_empty", "bad_option"])
def test_refusals_are_one_clean_line_naming_the_folder(tmp_path, run_pa, case):
    """Like every command: `error: PATH: problem; fix` as the first line, nothing written."""
    out = {"file": tmp_path / "taken", "no_parent": tmp_path / "no" / "out",
           "not_empty": tmp_path / "full", "bad_option": tmp_path / "out"}[case]
    if case == "file":
        out.write_text("x")
    if case == "not_empty":
        out.mkdir()
        (out / "keep.txt").write_text("mine")
    before = sorted(tmp_path.rglob("*"))
    extra = ["--min-range-m", "5", "--max-range-m", "2"] if case == "bad_option" else []
    code, out_text, err = run_pa("simulate", "office", out, *SMALL, *extra)
    assert code == (2 if case == "bad_option" else 1)
    assert out_text == "" and "Traceback" not in err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ")
    problem = {"file": "not a folder", "no_parent": "does not exist", "not_empty": "not empty",
               "bad_option": "--max-range-m"}[case]
    assert problem in err
    if case != "bad_option":
        assert lines[0].startswith(f"error: {out}: ")
    assert sorted(tmp_path.rglob("*")) == before


# ---------------------------------------------------------------------------- motion distortion


def test_motion_distortion_time_field_and_per_column_poses(tmp_path, run_pa):
    out = tmp_path / "md"
    code, _, err = run_pa("simulate", "street", out, "--scans", "3", "--azimuth-steps", "256",
                          "--motion-distortion", "--range-noise-m", "0")
    assert code == 0, err
    T = read_trajectory(out / "gt_poses_kitti.txt").T_world_scan
    planes = np.load(out / "planes.npy")
    sim = Simulator(SimOptions(scene="street"))
    for k in range(3):
        data, fields = _read_pcd(out / "scans" / f"{k:06d}.pcd")
        assert fields == ["x", "y", "z", "intensity", "time"]
        time = data[:, 4]
        assert np.all(np.diff(time) >= 0)  # stored column by column, counter-clockwise
        assert time.min() >= 0 and time.max() < SCAN_PERIOD_S and time.max() > 0.9 * SCAN_PERIOD_S
        # The azimuth of the points grows with their time (one sweep per period).
        azimuth = np.mod(np.arctan2(data[:, 1], data[:, 0]), 2 * np.pi)
        np.testing.assert_allclose(azimuth, 2 * np.pi * time / SCAN_PERIOD_S, atol=1e-3)
        labels = np.load(out / "labels" / f"{k:06d}.npy")
        lab = labels >= 0
        # Deskewed with the true pose at each point's time: on the plane (float32 rounding only).
        T_points = sim.poses_at_times(k * SCAN_PERIOD_S + time[lab])
        np.testing.assert_allclose(sim.poses_at_times(np.array([k * SCAN_PERIOD_S]))[0], T[k], atol=1e-8)
        d_true = _signed_dist(_world(data[lab, :3], T_points), labels[lab], planes)
        assert np.abs(d_true).max() < 1e-4
        # With the scan-start pose only (no deskew) late points are far off: the sensor moved 1 m.
        d_start = _signed_dist(_world(data[lab, :3], T[k]), labels[lab], planes)
        # (Noise is off, so any offset is distortion; planes facing the motion see most of it.)
        assert np.abs(d_start).max() > 0.5
        assert np.mean(np.abs(d_start) > 0.01) > 0.1


# ---------------------------------------------------------------------------- plane problems


def _cost_brute_force(problem, T_world_scan) -> float:
    """Sum over planes of lambda_min of the world-frame scatter, by plain loops (m^2)."""
    total = 0.0
    for i in range(problem.n_planes):
        C = np.zeros((4, 4))
        for o in np.flatnonzero(problem.plane_index == i):
            Tj = T_world_scan[problem.scan_index[o]]
            C += Tj @ problem.clusters[o] @ Tj.T
        P, v, n = C[:3, :3], C[:3, 3], C[3, 3]
        total += np.linalg.eigvalsh(P - np.outer(v, v) / n)[0]
    return total


def test_build_problem_from_labels_at_gt_has_noise_level_cost(tmp_path, run_pa):
    out = tmp_path / "seq"
    code, _, err = run_pa("simulate", "office", out, "--scans", "6", "--azimuth-steps", "256", "--seed", "2")
    assert code == 0, err
    problem = build_problem_from_labels(out, min_points=10)
    T = read_trajectory(out / "gt_poses_kitti.txt").T_world_scan
    np.testing.assert_allclose(problem.T_world_scan, T)
    assert problem.n_scans == 6 and problem.n_planes > 10
    # Clusters equal the brute-force sum over the labelled points of one (plane, scan).
    data, _ = _read_pcd(out / "scans" / "000002.pcd")
    labels = np.load(out / "labels" / "000002.npy")
    planes_true = np.load(out / "planes.npy")
    counts = np.bincount(labels[labels >= 0])
    biggest = int(np.argmax(counts))
    pts = data[labels == biggest, :3]
    brute = sum(np.outer(np.r_[p, 1.0], np.r_[p, 1.0]) for p in pts)
    matches = [o for o in range(problem.n_observations)
               if problem.scan_index[o] == 2 and problem.clusters[o, 3, 3] == len(pts)
               and np.allclose(problem.clusters[o], brute, rtol=1e-10)]
    assert len(matches) == 1
    # Cost at the GT poses: at most the squared distances to the TRUE planes (the optimal
    # planes fit at least as well), and close to it (each plane fit absorbs only 3 dof).
    cost = _cost_brute_force(problem, T)
    # Which (label, scan) pairs the problem must hold: >= 10 points, label seen by >= 2 scans.
    all_labels = [np.load(out / "labels" / f"{k:06d}.npy") for k in range(6)]
    kept_per_scan = []
    for labels in all_labels:
        uniq, counts = np.unique(labels[labels >= 0], return_counts=True)
        kept_per_scan.append(uniq[counts >= 10])
    seen, n_seen = np.unique(np.concatenate(kept_per_scan), return_counts=True)
    multi = seen[n_seen >= 2]
    assert problem.n_planes == len(multi)
    sse_true = 0.0
    n_points = 0
    for k in range(6):
        data, _ = _read_pcd(out / "scans" / f"{k:06d}.pcd")
        labels = all_labels[k]
        keep = np.isin(labels, np.intersect1d(kept_per_scan[k], multi))
        pw = _world(data[keep, :3], T[k])
        sse_true += np.sum(_signed_dist(pw, labels[keep], planes_true) ** 2)
        n_points += int(keep.sum())
    assert n_points == problem.n_points
    assert cost <= sse_true * (1 + 1e-9)
    assert cost >= 0.9 * sse_true
    assert cost / n_points < SIGMA_M ** 2  # each squared distance is noise^2 * cos^2 <= noise^2


def test_noise_free_problem_has_zero_cost():
    seq = simulate_sequence(SimOptions(scene="street", scans=4, azimuth_steps=256, range_noise_m=0.0))
    problem = build_problem_from_labels(seq, min_points=5)
    assert problem.n_planes > 10
    cost = _cost_brute_force(problem, seq.T_world_scan)
    assert abs(cost) < 1e-8 * problem.n_points
    # A perturbed pose raises the cost well above zero.
    T = seq.T_world_scan.copy()
    T[2, :3, 3] += [0.05, 0.0, 0.02]
    # (Scan 2 alone is off by 2 cm vertically, so its ground points alone add ~N_ground * 4e-4 m^2.)
    assert _cost_brute_force(problem, T) > 0.1


# ---------------------------------------------------------------------------- committed sample data

SAMPLE = Path(__file__).resolve().parents[3] / "sample_data" / "office"
SAMPLE_COMMAND = ["simulate", "office", "--scans", "40", "--beams", "16", "--azimuth-steps", "352", "--step-m", "0.2",
                  "--seed", "0"]


# The contract of the committed sample data across numpy / scipy / Open3D versions (README,
# "Sample data"): byte-identical files are promised only within one installation (see
# test_same_seed_gives_byte_identical_files); across versions the arithmetic may round the
# last bit differently, so the regenerated folder matches within these tolerances.
SAMPLE_COORD_TOL_M = 1e-5  # a few float32 steps at 30 m range (one step is 1.9e-6 m)
SAMPLE_INTENSITY_TOL = 1e-3  # intensity 0..255 is float32; one step at 255 is 1.5e-5
SAMPLE_PLANE_TOL = 1e-12  # planes.npy is float64: n unit, |d| <= 30 m (one step of 30 is 3.6e-15)
SAMPLE_TEXT_TOL = 2e-9  # poses and times are written with 9 decimals: one rounding flip of the last
SAMPLE_MAX_RELABELLED = 1e-4  # fraction of points whose ray may hit another triangle (grazing an edge)


def _pcd_header_and_data(path: Path) -> tuple[list[bytes], np.ndarray]:
    from pypcd4 import PointCloud

    header = path.read_bytes().split(b"DATA binary\n", 1)[0].splitlines()
    return header, PointCloud.from_path(path).numpy().astype(np.float64)


def assert_same_sequence_within_contract(committed: Path, fresh: Path) -> None:
    """The regeneration contract: same files, headers, point counts and labels; values within tolerance."""
    names = sorted(str(p.relative_to(committed)) for p in committed.rglob("*") if p.is_file())
    assert names == sorted(str(p.relative_to(fresh)) for p in fresh.rglob("*") if p.is_file())
    meta_committed = json.loads((committed / "meta.json").read_text())
    meta_fresh = json.loads((fresh / "meta.json").read_text())
    for key in ("options", "n_scans", "n_points", "n_planes", "scene"):
        assert meta_committed[key] == meta_fresh[key], key
    np.testing.assert_allclose(np.load(fresh / "planes.npy"), np.load(committed / "planes.npy"),
                               rtol=0, atol=SAMPLE_PLANE_TOL)
    for name in ("gt_poses_kitti.txt", "gt_poses_tum.txt", "times.txt"):
        np.testing.assert_allclose(np.loadtxt(fresh / name), np.loadtxt(committed / name), rtol=0,
                                   atol=SAMPLE_TEXT_TOL, err_msg=name)
    n_points = n_relabelled = 0
    for pcd in sorted((committed / "scans").glob("*.pcd")):
        header_c, data_c = _pcd_header_and_data(pcd)
        header_f, data_f = _pcd_header_and_data(fresh / "scans" / pcd.name)
        assert header_f == header_c, pcd.name  # fields, types, WIDTH and POINTS
        labels_c = np.load(committed / "labels" / f"{pcd.stem}.npy")
        labels_f = np.load(fresh / "labels" / f"{pcd.stem}.npy")
        assert labels_f.dtype == labels_c.dtype == np.int32 and labels_f.shape == labels_c.shape
        same = labels_f == labels_c
        n_points += len(same)
        n_relabelled += int((~same).sum())
        np.testing.assert_allclose(data_f[same, :3], data_c[same, :3], rtol=0, atol=SAMPLE_COORD_TOL_M,
                                   err_msg=pcd.name)
        np.testing.assert_allclose(data_f[same, 3], data_c[same, 3], rtol=0, atol=SAMPLE_INTENSITY_TOL,
                                   err_msg=pcd.name)
    assert n_points == meta_committed["n_points"]
    assert n_relabelled <= SAMPLE_MAX_RELABELLED * n_points


def test_sample_data_is_regenerated_by_the_documented_command(tmp_path, run_pa):
    if not SAMPLE.is_dir():
        pytest.skip("sample_data/office not present")
    out = tmp_path / "office"
    code, _, err = run_pa(SAMPLE_COMMAND[0], SAMPLE_COMMAND[1], out, *SAMPLE_COMMAND[2:])
    assert code == 0, err
    assert_same_sequence_within_contract(SAMPLE, out)
    assert sum(p.stat().st_size for p in SAMPLE.rglob("*") if p.is_file()) < 5_000_000


def test_regeneration_contract_detects_changes(tmp_path, run_pa):
    """The contract check fails on a moved point, a changed label, a changed header or a lost file."""
    import shutil

    from pa_cli.io.scans import read_scan, write_pcd

    base = tmp_path / "base"
    assert run_pa("simulate", "office", base, *SMALL, "--seed", "4")[0] == 0
    assert_same_sequence_within_contract(base, base)

    def mutated(name: str, change) -> Path:
        copy = tmp_path / name
        shutil.copytree(base, copy)
        change(copy)
        return copy

    def move_point(folder: Path) -> None:
        scan = read_scan(folder / "scans" / "000001.pcd")
        points = scan.points_scan.copy()
        points[7, 2] += 3 * SAMPLE_COORD_TOL_M
        (folder / "scans" / "000001.pcd").unlink()
        write_pcd(folder / "scans" / "000001.pcd", points, intensity=scan.intensity)

    def relabel(folder: Path) -> None:
        labels = np.load(folder / "labels" / "000002.npy")
        labels[:5] += 1
        np.save(folder / "labels" / "000002.npy", labels)

    def drop_point(folder: Path) -> None:
        scan = read_scan(folder / "scans" / "000003.pcd")
        (folder / "scans" / "000003.pcd").unlink()
        write_pcd(folder / "scans" / "000003.pcd", scan.points_scan[:-1], intensity=scan.intensity[:-1])

    for name, change in (("moved", move_point), ("relabelled", relabel), ("dropped", drop_point),
                         ("lost", lambda f: (f / "times.txt").unlink())):
        with pytest.raises(AssertionError):
            assert_same_sequence_within_contract(base, mutated(name, change))
