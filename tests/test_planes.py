"""Plane landmarks: detection, region growing, association (issue 6).

Synthetic scenes have exact per-point plane labels; every check is against those labels,
brute-force sums or the scene's true planes, never against numbers produced by the code.
"""

from __future__ import annotations

import numpy as np
import pytest

from pa_cli.config import PlanesConfig
from pa_cli.errors import InputError
from pa_cli.io.problem import points_to_cluster
from pa_cli.planes.associate import (
    associate_landmarks,
    build_plane_problem,
    world_plane_stats,
)
from pa_cli.planes.detect import decode_keys, detect_landmarks, encode_keys, merge_stats

INDOOR = PlanesConfig(voxel_size_m=0.5)


def _rot(axis: str, deg: float) -> np.ndarray:
    c, s = np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    R = np.eye(3)
    R[i, i] = R[j, j] = c
    R[i, j], R[j, i] = -s, s
    return R


def _rect(origin, u, v, a, b):
    return (np.array(origin, float), np.array(u, float), np.array(v, float), a, b)


def room_planes(with_pillar: bool = True) -> list[tuple]:
    """Rectangles (origin, u, v, extent_u, extent_v) of a 10 x 8 x 3 m room (+ a pillar)."""
    ex, ey, ez = np.eye(3)
    planes = [
        _rect([0, 0, 0], ex, ey, 10, 8),  # floor
        _rect([0, 0, 3], ex, ey, 10, 8),  # ceiling
        _rect([0, 0, 0], ey, ez, 8, 3),  # wall x = 0
        _rect([10, 0, 0], ey, ez, 8, 3),  # wall x = 10
        _rect([0, 0, 0], ex, ez, 10, 3),  # wall y = 0
        _rect([0, 8, 0], ex, ez, 10, 3),  # wall y = 8
    ]
    if with_pillar:
        planes += [
            _rect([4, 3.5, 0], ey, ez, 1, 3), _rect([5, 3.5, 0], ey, ez, 1, 3),
            _rect([4, 3.5, 0], ex, ez, 1, 3), _rect([4, 4.5, 0], ex, ez, 1, 3),
        ]
    return planes


def make_scene(planes, n_scans=6, density_per_m2=40.0, noise_m=0.01, seed=0, only_in_scan=None):
    """Scans (scan frame), poses T_world_scan, per-point labels, true planes (normals, points).

    The whole scene is rotated and shifted off the voxel grid. `only_in_scan` maps a plane
    index to the single scan that sees it.
    """
    rng = np.random.default_rng(seed)
    R0 = _rot("z", 20.0) @ _rot("x", 3.0)
    t0 = np.array([3.1, -2.3, 0.7])
    normals = np.array([R0 @ np.cross(u, v) for _, u, v, _, _ in planes])
    origins_world = np.array([R0 @ o + t0 for o, _, _, _, _ in planes])
    T = np.zeros((n_scans, 4, 4))
    scans, labels = [], []
    for j in range(n_scans):
        pos_room = np.array([rng.uniform(1.5, 3.5), rng.uniform(1.5, 6.5), 1.5])
        T[j] = np.eye(4)
        T[j, :3, :3] = R0 @ _rot("z", rng.uniform(-180, 180)) @ _rot("y", rng.uniform(-3, 3))
        T[j, :3, 3] = R0 @ pos_room + t0
        pts, lab = [], []
        for k, (o, u, v, a, b) in enumerate(planes):
            if only_in_scan is not None and k in only_in_scan and only_in_scan[k] != j:
                continue
            n = int(a * b * density_per_m2)
            st = rng.uniform(0, 1, (n, 2)) * [a, b]
            p_room = o + st[:, :1] * u + st[:, 1:] * v
            p_world = p_room @ R0.T + t0 + rng.normal(0, noise_m, (n, 1)) * normals[k]
            pts.append(p_world)
            lab.append(np.full(n, k))
        p_world = np.concatenate(pts)
        scans.append((p_world - T[j, :3, 3]) @ T[j, :3, :3])
        labels.append(np.concatenate(lab))
    return scans, T, labels, (normals, origins_world)


def _label_table(scans, T, labels, landmarks, config, n_true):
    """(landmarks, true planes) point counts after association trimming."""
    table = np.zeros((landmarks.n_landmarks, n_true), dtype=np.int64)
    for pts, Tj, lab in zip(scans, T, labels, strict=True):
        lm, _ = landmarks.assign(pts @ Tj[:3, :3].T + Tj[:3, 3], config.outlier_sigma,
                                 config.outlier_sigma_floor_m)
        on = lm >= 0
        np.add.at(table, (lm[on], lab[on]), 1)
    return table


def _minority_distance(scans, T, labels, landmarks, config, majority, true_planes, kept,
                       clutter_label=None):
    """Largest distance (m) of a kept landmark's points of other labels to its majority plane.

    Landmarks made mostly of unlabelled points (clutter_label) have no true plane: skipped.
    """
    normals, origins = true_planes
    in_problem = np.zeros(landmarks.n_landmarks, dtype=bool)
    in_problem[kept] = True
    if clutter_label is not None:
        in_problem &= majority != clutter_label
    worst = 0.0
    for pts, Tj, lab in zip(scans, T, labels, strict=True):
        p_world = pts @ Tj[:3, :3].T + Tj[:3, 3]
        lm, _ = landmarks.assign(p_world, config.outlier_sigma, config.outlier_sigma_floor_m)
        on = np.flatnonzero(lm >= 0)
        on = on[in_problem[lm[on]]]
        k = majority[lm[on]]
        other = on[lab[on] != k]
        k = majority[lm[other]]
        d = np.abs(np.einsum("ij,ij->i", p_world[other] - origins[k], normals[k]))
        worst = max(worst, float(d.max(initial=0.0)))
    return worst


def _check_scene(scans, T, labels, true_planes, config, min_true_points=300, noise_m=0.01,
                 clutter_label=None):
    normals = true_planes[0]
    landmarks = detect_landmarks(scans, T, config)
    problem, counts, kept = associate_landmarks(scans, T, landmarks, config)
    full_table = _label_table(scans, T, labels, landmarks, config, len(normals))
    table = full_table[kept]
    majority = table.argmax(axis=1)
    # No landmark mixes two true planes: every point of a landmark that carries another label
    # (another plane, or clutter) lies on the landmark's majority true plane within 4 noise
    # sigmas, i.e. it is a point at the junction of the two planes, consistent with both (the
    # trimming gate is 3 sigma of the landmark's measured spread, slightly above the noise).
    # A share limit would be wrong here: at a shallow junction (20 degrees) many points of the
    # other plane lie within the noise of this one.
    assert _minority_distance(scans, T, labels, landmarks, config, full_table.argmax(axis=1),
                              true_planes, kept, clutter_label) <= 4 * noise_m
    # Every true plane with enough points is found; each landmark's normal within 1 degree.
    # "Enough points": min_true_points in all, and 5 x min_points_per_observation in each of
    # at least two scans (a far wall with ~20 sparse points per scan is not enough).
    true_points = np.bincount(np.concatenate(labels), minlength=len(normals))
    per_scan = np.array([np.bincount(lab, minlength=len(normals)) for lab in labels])
    dense_scans = (per_scan >= 5 * config.min_points_per_observation).sum(axis=0)
    found = np.zeros(len(normals), dtype=bool)
    found[majority] = True
    enough = (true_points >= min_true_points) & (dense_scans >= 2)
    if clutter_label is not None:
        # Unlabelled points: curved clutter and planar faces too small to get a label in the
        # simulator; a landmark made of the latter is legitimate but has no true plane to check.
        found[clutter_label] = enough[clutter_label] = False
        is_plane = majority != clutter_label
        table, majority, kept_checked = table[is_plane], majority[is_plane], kept[is_plane]
    else:
        kept_checked = kept
    assert np.all(found[enough]), f"missed true planes {np.flatnonzero(enough & ~found)}"
    # Normals within 1 degree, for landmarks with enough points (min_true_points) to define one.
    _, normal_world, thickness_m = world_plane_stats(problem, T, landmarks.centroid_world[kept])
    assert np.all(thickness_m <= config.max_thickness_m)
    normal_world = normal_world[np.isin(kept, kept_checked)]
    cos = np.abs(np.einsum("ij,ij->i", normal_world, normals[majority]))
    big = table.sum(axis=1) >= min_true_points
    assert np.degrees(np.arccos(np.minimum(cos[big], 1.0))).max() < 1.0
    n_true = int(np.sum(true_points[: len(normals) - (clutter_label is not None)] > 0))
    assert problem.n_planes <= 2 * n_true
    return landmarks, problem, counts, kept, table


@pytest.mark.parametrize("seed", [0, 4, 8])
def test_room_every_plane_found_pure_and_accurate(seed):
    planes = room_planes()
    scans, T, labels, true_planes = make_scene(planes, seed=seed)
    landmarks, problem, counts, kept, table = _check_scene(scans, T, labels, true_planes, INDOOR)
    # Region growing makes a whole floor / wall one landmark: the largest landmark of each big
    # plane holds at least 90 % of that plane's associated points.
    for k in range(6):
        assert table[:, k].max() >= 0.9 * table[:, k].sum()


@pytest.mark.parametrize("seed", [1, 3, 6])
@pytest.mark.parametrize("levels", [2, 3])
def test_room_one_meter_voxels_with_subdivision(seed, levels):
    # 1 m voxels around a 1 m pillar: only subdivided voxels hold its faces.
    scans, T, labels, true_planes = make_scene(room_planes(), seed=seed)
    _check_scene(scans, T, labels, true_planes,
                 PlanesConfig(voxel_size_m=1.0, max_subdivision_levels=levels))


def test_subdivision_recovers_points_near_corners():
    scans, T, labels, true_planes = make_scene(room_planes(), seed=2)
    covered = []
    for levels in (0, 2):
        cfg = PlanesConfig(voxel_size_m=1.0, max_subdivision_levels=levels)
        covered.append(build_plane_problem(scans, T, cfg)[1]["n_points_covered"])
    assert covered[1] > covered[0]


def test_clusters_equal_brute_force_sums_of_assigned_points():
    scans, T, labels, true_planes = make_scene(room_planes(), n_scans=4, seed=3)
    landmarks = detect_landmarks(scans, T, INDOOR)
    problem, counts, kept = associate_landmarks(scans, T, landmarks, INDOOR)
    n_covered = 0
    for o in range(problem.n_observations):
        j, lm_id = problem.scan_index[o], kept[problem.plane_index[o]]
        lm, _ = landmarks.assign(scans[j] @ T[j, :3, :3].T + T[j, :3, 3], INDOOR.outlier_sigma,
                                 INDOOR.outlier_sigma_floor_m)
        expected = points_to_cluster(scans[j][lm == lm_id])
        np.testing.assert_allclose(problem.clusters[o], expected, rtol=1e-10, atol=1e-8)
        n_covered += int((lm == lm_id).sum())
    assert counts["n_points_covered"] == n_covered
    assert counts["n_points_total"] == sum(len(s) for s in scans)


def test_outliers_are_trimmed():
    planes = room_planes(with_pillar=False)
    scans, T, labels, true_planes = make_scene(planes, n_scans=3, seed=4)
    # 30 points per scan 0.15 m above the floor (3 sigma = 0.03 m < 0.15 m): clutter, not floor.
    rng = np.random.default_rng(5)
    o, u, v, _, _ = planes[0]
    R0, t0 = _rot("z", 20.0) @ _rot("x", 3.0), np.array([3.1, -2.3, 0.7])
    n_extra = 30
    for j in range(3):
        st = rng.uniform(2, 8, (n_extra, 2))
        p_world = (o + st[:, :1] * u + st[:, 1:] * v + [0, 0, 0.15]) @ R0.T + t0
        scans[j] = np.vstack([scans[j], (p_world - T[j, :3, 3]) @ T[j, :3, :3]])
    landmarks = detect_landmarks(scans, T, INDOOR)
    for j in range(3):
        lm, n_trimmed = landmarks.assign(scans[j] @ T[j, :3, :3].T + T[j, :3, 3],
                                         INDOOR.outlier_sigma, INDOOR.outlier_sigma_floor_m)
        assert np.all(lm[-n_extra:] == -1)
        assert n_trimmed >= 1


def test_curved_surface_is_split_into_planar_landmarks():
    # A quarter cylinder of radius 4 m: adjacent voxels differ by a few degrees only, so
    # growing chains them; the merged region is not planar and must be split.
    rng = np.random.default_rng(6)
    n = 40000
    phi, z = rng.uniform(0, np.pi / 2, n), rng.uniform(0, 3, n)
    pts = np.column_stack([4 * np.cos(phi), 4 * np.sin(phi), z]) + rng.normal(0, 0.005, (n, 3))
    T = np.repeat(np.eye(4)[None], 2, axis=0)
    T[1, :3, 3] = [0.2, 0.1, 0.0]
    scans = [pts[: n // 2], pts[n // 2:] - T[1, :3, 3]]
    config = PlanesConfig(voxel_size_m=0.5, max_thickness_m=0.02)
    problem, diag = build_plane_problem(scans, T, config)
    assert problem.n_planes >= 3
    assert diag["thickness_rms_m"]["max"] <= config.max_thickness_m
    assert diag["n_regions_split"] >= 1


def test_single_scan_landmarks_dropped_and_counted():
    planes = room_planes(with_pillar=False) + [_rect([2, 2, 1], [1, 0, 0], [0, 0.6, 0.8], 2, 1)]
    scans, T, labels, true_planes = make_scene(planes, n_scans=3, seed=7, only_in_scan={6: 1})
    landmarks = detect_landmarks(scans, T, INDOOR)
    problem, counts, kept = associate_landmarks(scans, T, landmarks, INDOOR)
    table = _label_table(scans, T, labels, landmarks, INDOOR, len(planes))
    slanted = np.flatnonzero(table[:, 6] > 0.5 * table.sum(axis=1))
    assert len(slanted) >= 1  # detected ...
    assert not np.isin(slanted, kept).any()  # ... but not in the problem
    assert counts["n_landmarks_single_scan"] >= len(slanted)


def test_diagnostics_flag_scans_without_three_normal_directions():
    ex, ey, ez = np.eye(3)
    corridor = [_rect([0, 0, 0], ex, ey, 10, 8), _rect([0, 0, 0], ex, ez, 10, 3),
                _rect([0, 8, 0], ex, ez, 10, 3)]  # floor + two parallel walls: x unconstrained
    scans, T, _, _ = make_scene(corridor, n_scans=3, seed=8)
    _, diag = build_plane_problem(scans, T, INDOOR)
    assert diag["poorly_constrained_scans"] == [0, 1, 2]
    assert diag["warnings"]
    scans, T, _, _ = make_scene(room_planes(), n_scans=3, seed=8)
    _, diag = build_plane_problem(scans, T, INDOOR)
    assert diag["poorly_constrained_scans"] == []
    assert sum(diag["landmarks_per_scan"]) == diag["n_observations"]
    assert diag["observations_per_landmark"]["min"] >= 2
    assert 0.5 < diag["covered_fraction"] <= 1.0
    import json
    json.dumps(diag)  # JSON-serialisable


def test_progress_and_input_errors():
    scans, T, _, _ = make_scene(room_planes(with_pillar=False), n_scans=2, seed=9)
    calls = []
    build_plane_problem(scans, T, INDOOR, progress=lambda d, t: calls.append((d, t)))
    assert calls == [(k, 4) for k in range(1, 5)]
    with pytest.raises(InputError, match="3 scans but 2 poses"):
        build_plane_problem(scans + [scans[0]], T, INDOOR)


def test_keys_round_trip_and_merge_matches_brute_force():
    rng = np.random.default_rng(10)
    coords = rng.integers(-5000, 5000, (1000, 3))
    np.testing.assert_array_equal(decode_keys(encode_keys(coords)), coords)
    with pytest.raises(InputError, match="voxel_size_m"):
        encode_keys(np.array([[1 << 20, 0, 0]]))
    groups = [rng.normal(size=(n, 3)) * [3, 1, 0.1] + rng.normal(size=3) * 50 for n in (5, 9, 20)]
    count = np.array([len(g) for g in groups], float)
    mean = np.array([g.mean(0) for g in groups])
    scatter = np.array([(g - g.mean(0)).T @ (g - g.mean(0)) for g in groups])
    n, m, s = merge_stats(np.array([0, 1, 0]), 2, count, mean, scatter)
    both = np.vstack([groups[0], groups[2]])
    np.testing.assert_allclose(n, [len(both), len(groups[1])])
    np.testing.assert_allclose(m[0], both.mean(0), rtol=1e-12)
    np.testing.assert_allclose(s[0], (both - both.mean(0)).T @ (both - both.mean(0)), rtol=1e-10)


def test_pa_simulate_office_planes_found_pure_and_accurate(tmp_path, run_pa):
    from pa_cli.io.scans import ScanFolder
    from pa_cli.io.trajectory import read_trajectory

    out = tmp_path / "office"
    code, _, err = run_pa("simulate", "office", out, "--scans", "20", "--step-m", "0.3",
                          "--azimuth-steps", "512")
    assert code == 0, err
    scans = list(ScanFolder(out / "scans").points)
    T = read_trajectory(out / "gt_poses_kitti.txt").T_world_scan
    planes = np.load(out / "planes.npy")  # (P, 4): n . x + d = 0, world frame, row = label
    n_planes = len(planes)
    # label -1 (clutter, small faces) becomes an extra label
    labels = [np.where(lab < 0, n_planes, lab).astype(np.int64)
              for lab in (np.load(f) for f in sorted((out / "labels").glob("*.npy")))]
    normals = np.vstack([planes[:, :3], [[0.0, 0.0, 1.0]]])
    origins = np.vstack([-planes[:, 3:] * planes[:, :3], [[0.0, 0.0, 1e6]]])
    # The indoor voxel size (configs/indoor.yaml); 1 m voxels in this cluttered office merge
    # desk clutter into thin landmarks (see the README's tuning notes).
    _check_scene(scans, T, labels, (normals, origins), PlanesConfig(voxel_size_m=0.5),
                 min_true_points=300, noise_m=0.01, clutter_label=n_planes)


def test_balm_campus_median_thickness_below_5cm(shared_data):
    from pa_cli.io.scans import ScanFolder
    from pa_cli.io.trajectory import read_trajectory

    folder = shared_data / "balm-campus-30"
    if not folder.is_dir():
        pytest.skip(f"{folder} not present")
    scans = ScanFolder(folder / "scans").points  # lazy: each file read once per pass
    T = read_trajectory(folder / "poses_kitti.txt").T_world_scan
    problem, diag = build_plane_problem(scans, T, PlanesConfig())
    assert diag["thickness_rms_m"]["median"] < 0.05
    assert diag["n_landmarks"] >= 30
    assert diag["poorly_constrained_scans"] == []
