"""Edge landmarks: detection of line-like voxels, growing, association, merging with planes."""

from __future__ import annotations

import numpy as np

from pa_cli.config import EdgesConfig
from pa_cli.core.clusters import points_to_cluster
from pa_cli.core.problem import FEATURE_EDGE, FEATURE_PLANE, make_problem
from pa_cli.planes.edges import build_edge_problem, merge_problems
from pa_testing.synthetic_problems import random_poses


def near_side(point_on_axis: np.ndarray, direction: np.ndarray, sensor: np.ndarray, radius_m: float,
              u: np.ndarray) -> np.ndarray:
    """Offsets from a cylinder's axis of the points a sensor sees on it: its near half, hit at lateral
    offsets u * radius (u in [-1, 1], rays spread evenly across it), in front of the axis."""
    toward = sensor - point_on_axis
    toward -= (toward @ direction) * direction
    toward /= np.linalg.norm(toward)
    lateral = np.cross(direction, toward)
    return radius_m * (u[:, None] * lateral + np.sqrt(1.0 - u**2)[:, None] * toward)


def pole_scans(seed: int, n_scans: int = 5, radius_m: float = 0.03):
    """Scans of three thin poles (two vertical, one tilted) above a noisy ground plane, each scan
    seeing the near side of each pole: (scans, T_gt, pole bases, pole directions)."""
    rng = np.random.default_rng(seed)
    T = random_poses(n_scans, rng, 0.2, 1.0)
    bases = np.array([[3.0, 1.0, 0.0], [-2.0, 4.0, 0.0], [0.5, -3.0, 0.0]])
    directions = np.array([[0, 0, 1.0], [0, 0, 1.0], [0.5, 0, 1.0]])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    scans = []
    for j in range(n_scans):
        parts = [np.column_stack([rng.uniform(-8, 8, (3000, 2)), rng.normal(0, 0.01, 3000)])]  # ground
        for base, d in zip(bases, directions, strict=True):
            t = rng.uniform(0.3, 4.0, 150)
            parts.append(base + t[:, None] * d + near_side(base, d, T[j, :3, 3], radius_m, rng.uniform(-1, 1, 150)))
        world = np.vstack(parts)
        scans.append((world - T[j, :3, 3]) @ T[j, :3, :3])
    return scans, T, bases, directions


def test_detects_each_pole_once_with_its_direction():
    scans, T, bases, directions = pole_scans(0)
    problem, diag = build_edge_problem(scans, T, EdgesConfig())
    assert problem.n_planes == 3
    assert np.all(problem.feature_kind == FEATURE_EDGE)
    assert diag["n_edges"] == 3
    # each scan's near half, moved onto the axis: spread r^2 / 3 across and r^2 (2/3 - pi^2/16) along the view
    assert abs(diag["edge_rms_point_to_line_m"] - 0.03 * np.sqrt(1 / 3 + 2 / 3 - np.pi**2 / 16)) < 0.002
    # every scan observes every pole, with only pole points (no ground point: z > 0.2 m)
    assert problem.n_observations == 3 * len(scans)
    for o in range(problem.n_observations):
        C = T[problem.scan_index[o]] @ problem.clusters[o] @ T[problem.scan_index[o]].T
        centroid = C[:3, 3] / C[3, 3]
        dist = [np.linalg.norm(np.cross(centroid - b, d)) for b, d in zip(bases, directions, strict=True)]
        assert min(dist) < 0.004  # on the axis (the near half's own centroid is (pi/4) 3 cm = 2.4 cm in front)


def test_voxel_moments_merged_as_they_come_are_those_merged_once(monkeypatch):
    """The per-scan voxel moments merged into the running sums every few scans (bounded memory) give the
    keys and clusters of one merge at the end, to the bit."""
    import pa_cli.planes.edges as edges_module

    scans, T, _, _ = pole_scans(3, n_scans=12)
    keys_once, clusters_once = edges_module.voxel_clusters(scans, T, 1.0)
    monkeypatch.setattr(edges_module, "MIN_PENDING_VOXELS", 10)
    keys, clusters = edges_module.voxel_clusters(scans, T, 1.0)
    assert len(keys) > 100 and np.array_equal(keys, keys_once) and np.array_equal(clusters, clusters_once)


def test_edges_found_on_threads_are_those_of_one_thread_to_the_bit():
    """The passes over the scans on several threads (each scan's sums and labels on its own, gathered in scan
    order) give the keys, clusters, problem and labels of one thread."""
    from pa_cli.planes.edges import associate_edges, detect_edges, voxel_clusters

    scans, T, _, _ = pole_scans(5, n_scans=9)
    keys_1, clusters_1 = voxel_clusters(scans, T, 1.0)
    keys_3, clusters_3 = voxel_clusters(scans, T, 1.0, threads=3)
    assert len(keys_1) > 100 and np.array_equal(keys_3, keys_1) and np.array_equal(clusters_3, clusters_1)
    landmarks = detect_edges(scans, T, EdgesConfig(), threads=3)
    assert landmarks.n_landmarks == 3
    problem_1, labels_1 = associate_edges(scans, T, landmarks, EdgesConfig())
    problem_3, labels_3 = associate_edges(scans, T, landmarks, EdgesConfig(), threads=3)
    assert problem_1.n_observations == 3 * len(scans)
    for name in ("plane_index", "scan_index", "clusters", "range_clusters"):
        assert np.array_equal(getattr(problem_3, name), getattr(problem_1, name)), name
    assert np.array_equal(labels_3.shift_scan_m, labels_1.shift_scan_m)
    for a, b in zip(labels_3.point_index, labels_1.point_index, strict=True):
        assert np.array_equal(a, b)


def test_thick_cylinders_and_planes_are_not_edges():
    scans, T, _, _ = pole_scans(1, radius_m=0.3)
    problem, diag = build_edge_problem(scans, T, EdgesConfig())
    assert problem.n_planes == 0 and diag["n_edges"] == 0


def test_merged_problem_keeps_both_kinds():
    scans, T, _, _ = pole_scans(2)
    edges, _ = build_edge_problem(scans, T, EdgesConfig())
    planes = make_problem(np.array([0, 0]), np.array([0, 1]), edges.clusters[:2], n_scans=len(T))
    merged = merge_problems(planes, edges)
    assert merged.n_planes == 1 + edges.n_planes
    assert merged.feature_kind[0] == FEATURE_PLANE and np.all(merged.feature_kind[1:] == FEATURE_EDGE)
    assert merged.n_observations == 2 + edges.n_observations


def test_with_edges_follows_the_switch_and_counts_edges_in_the_constraint_report():
    from pa_cli.planes.edges import with_edges

    scans, T, _, _ = pole_scans(3)
    # one plane (the ground, normal z) seen by every scan: translations in x and y are free
    ground = [points_to_cluster(p[np.abs(p @ T[j, :3, :3].T[:, 2] + T[j, 2, 3]) < 0.05])
              for j, p in enumerate(scans)]
    planes = make_problem(np.zeros(len(T), np.int64), np.arange(len(T)), np.array(ground))
    diagnostics: dict = {"poorly_constrained_scans": list(range(len(T)))}
    unchanged, no_edges = with_edges(planes, diagnostics, scans, T, None, 0.1)
    assert unchanged is planes and no_edges is None
    assert set(diagnostics) == {"poorly_constrained_scans"}
    merged, _ = with_edges(planes, diagnostics, scans, T, EdgesConfig(), 0.1)
    assert merged.n_planes == 1 + diagnostics["edges"]["n_edges"] and diagnostics["edges"]["n_edges"] == 3
    # two vertical poles fix x and y, the ground z: every scan is constrained in all three directions
    assert diagnostics["poorly_constrained_scans"] == []
    assert diagnostics["edges"]["poorly_constrained_scans_planes_only"] == list(range(len(T)))
    assert min(diagnostics["constraint_eigenvalue_per_scan"]) > 0.9


def test_a_frozen_edge_association_is_the_fresh_one_on_the_same_points_and_follows_moved_points():
    """The edges found at poses T, re-summed from their per-point labels on the same points, give the same
    problem; on the points moved within each scan they follow the points (every point keeps its edge), while
    a fresh association at the same poses changes."""
    from pa_cli.planes.edges import with_edges

    scans, T, _, _ = pole_scans(8, n_scans=6)
    ground = [points_to_cluster(p[np.abs(p @ T[j, :3, :3].T[:, 2] + T[j, 2, 3]) < 0.05]) for j, p in enumerate(scans)]
    planes = make_problem(np.zeros(len(T), np.int64), np.arange(len(T)), np.array(ground))
    fresh_diagnostics: dict = {}
    fresh, edges = with_edges(planes, fresh_diagnostics, scans, T, EdgesConfig(), 0.1)
    assert edges.n_detected == 3 and len(edges.shift_scan_m) == fresh.n_observations - len(T)
    assert np.linalg.norm(edges.shift_scan_m, axis=1).min() > 0.01  # (pi/4) 3 cm: the near halves moved
    frozen_diagnostics: dict = {}
    again, kept = with_edges(planes, frozen_diagnostics, scans, T, EdgesConfig(), 0.1, frozen=edges)
    assert kept is edges
    np.testing.assert_array_equal(again.plane_index, fresh.plane_index)
    np.testing.assert_array_equal(again.scan_index, fresh.scan_index)
    np.testing.assert_allclose(again.clusters, fresh.clusters, rtol=1e-12, atol=1e-9)
    assert frozen_diagnostics["edges"] == fresh_diagnostics["edges"]
    # every point 12 cm further out along its ray: beyond max_point_distance_m of the lines for a fresh
    # association, but each frozen observation keeps its points, now summed where they lie
    moved = [p * (1.0 + 0.12 / np.linalg.norm(p, axis=1, keepdims=True)) for p in scans]
    follows, _ = with_edges(planes, {}, moved, T, EdgesConfig(), 0.1, frozen=edges)
    np.testing.assert_array_equal(follows.plane_index, fresh.plane_index)
    is_edge = follows.plane_index > 0
    counts = follows.clusters[is_edge, 3, 3]
    np.testing.assert_array_equal(counts, fresh.clusters[is_edge, 3, 3])
    expected = edges.labels.clusters([p[index] for p, index in zip(moved, edges.point_index, strict=True)])
    # only the points on edges are held: the same points as the association's in the full scans
    assert sum(len(index) for index in edges.point_index) == sum(
        int(fresh.clusters[o, 3, 3]) for o in np.flatnonzero(fresh.plane_index > 0))
    shift = np.repeat(np.eye(4)[None], len(expected), axis=0)
    shift[:, :3, 3] = edges.shift_scan_m
    np.testing.assert_allclose(follows.clusters[is_edge], shift @ expected @ shift.transpose(0, 2, 1), rtol=1e-12,
                               atol=1e-9)
    # the merged problem keeps both kinds' range clusters (planes: none given here, so none)
    assert follows.range_clusters is None and edges.problem(moved).range_clusters is not None
    refound, _ = with_edges(planes, {}, moved, T, EdgesConfig(), 0.1)
    assert refound.n_observations != follows.n_observations or not np.allclose(refound.clusters, follows.clusters)


def test_refine_with_edges_end_to_end(run_pa, tmp_path):
    """`pa refine` with edges on: a ground plane and three poles hold every pose; the saved problem
    holds the edges and the refined poses are closer to the truth than the perturbed ones."""
    import json

    from pa_cli.evaluation.perturbation import perturb_poses
    from pa_cli.io.problem import load_problem
    from pa_cli.io.scans import write_pcd
    from pa_cli.io.trajectory import read_trajectory, write_kitti

    scans, T_gt, _, _ = pole_scans(4, n_scans=6)
    (tmp_path / "scans").mkdir()
    for j, points in enumerate(scans):
        write_pcd(tmp_path / "scans" / f"{j:06d}.pcd", points)
    T0 = perturb_poses(T_gt, np.deg2rad(0.2), 0.01, np.random.default_rng(5))
    write_kitti(tmp_path / "init.txt", T0)
    write_kitti(tmp_path / "gt.txt", T_gt)
    (tmp_path / "cfg.yaml").write_text("scene: {edges: true}\nrefine: {max_rounds: 2}\n")
    code, _, err = run_pa("refine", tmp_path / "scans", "--out", tmp_path / "map.ply", "--poses", tmp_path / "init.txt",
                          "--gt", tmp_path / "gt.txt", "--config", tmp_path / "cfg.yaml",
                          "--save-problem", tmp_path / "problem.npz", "-q")
    assert code == 0, err
    report = json.loads((tmp_path / "map_report.json").read_text())
    assert report["rounds"][0]["planes"]["edges"]["n_edges"] == 3
    problem = load_problem(tmp_path / "problem.npz")
    assert np.count_nonzero(problem.feature_kind == FEATURE_EDGE) == 3
    assert report["gt"]["refined"]["ate_rmse_m"] < 0.5 * report["gt"]["initial"]["ate_rmse_m"]
    assert len(read_trajectory(tmp_path / "map_poses_kitti.txt")) == len(T_gt)


def test_refine_freezes_the_edges_with_the_planes(run_pa, tmp_path, monkeypatch):
    """Once the rounds freeze the association, the edges are not detected again: the frozen round adjusts
    the edges of the last fresh association, each point on its line."""
    import json

    import pa_cli.planes.edges as edges_module
    from pa_cli.evaluation.perturbation import perturb_poses
    from pa_cli.io.scans import write_pcd
    from pa_cli.io.trajectory import write_kitti

    detected = []
    detect = edges_module.detect_edges
    monkeypatch.setattr(edges_module, "detect_edges", lambda *a, **k: detected.append(1) or detect(*a, **k))
    scans, T_gt, _, _ = pole_scans(9, n_scans=6)
    (tmp_path / "scans").mkdir()
    for j, points in enumerate(scans):
        write_pcd(tmp_path / "scans" / f"{j:06d}.pcd", points)
    write_kitti(tmp_path / "init.txt", perturb_poses(T_gt, np.deg2rad(0.2), 0.01, np.random.default_rng(6)))
    (tmp_path / "cfg.yaml").write_text("scene: {edges: true}\nrefine: {max_rounds: 3}\n"
                                       "advanced: {association: {rounds: 1, settle_m: 1.0}}\n")
    code, _, err = run_pa("refine", tmp_path / "scans", "--out", tmp_path / "map.ply", "--poses", tmp_path / "init.txt",
                          "--config", tmp_path / "cfg.yaml", "-q")
    assert code == 0, err
    rounds = json.loads((tmp_path / "map_report.json").read_text())["rounds"]
    assert [r["association"] for r in rounds[:2]] == ["new", "frozen"]
    assert len(detected) == 1
    fresh, frozen = rounds[0]["planes"]["edges"], rounds[1]["planes"]["edges"]
    assert frozen["n_edges"] == fresh["n_edges"] >= 2
    assert frozen["n_edge_observations"] == fresh["n_edge_observations"]
    assert frozen["n_edge_points"] == fresh["n_edge_points"]
    # the same points on lines the adjustment pulled together
    assert frozen["edge_rms_point_to_line_m"] < 0.5 * fresh["edge_rms_point_to_line_m"]


def _refine_report(run_pa, tmp_path, scans, T_gt, config: str) -> dict:
    """`pa refine` of scans (sensor frames) from the truth perturbed by 0.2 deg / 1 cm with `config`: its report."""
    import json

    from pa_cli.evaluation.perturbation import perturb_poses
    from pa_cli.io.scans import write_pcd
    from pa_cli.io.trajectory import write_kitti

    (tmp_path / "scans").mkdir()
    for j, points in enumerate(scans):
        write_pcd(tmp_path / "scans" / f"{j:06d}.pcd", points)
    write_kitti(tmp_path / "init.txt", perturb_poses(T_gt, np.deg2rad(0.2), 0.01, np.random.default_rng(6)))
    (tmp_path / "cfg.yaml").write_text(config)
    code, _, err = run_pa("refine", tmp_path / "scans", "--out", tmp_path / "map.ply", "--poses", tmp_path / "init.txt",
                          "--config", tmp_path / "cfg.yaml", "-q")
    assert code == 0, err
    return json.loads((tmp_path / "map_report.json").read_text())


def _counting_detections(monkeypatch) -> list:
    import pa_cli.planes.edges as edges_module

    detected: list = []
    detect = edges_module.detect_edges
    monkeypatch.setattr(edges_module, "detect_edges", lambda *a, **k: detected.append(1) or detect(*a, **k))
    return detected


def test_auto_edges_are_used_where_they_hold_the_scans_the_planes_leave_free(run_pa, tmp_path, monkeypatch):
    """A ground plane leaves every scan free across it; the poles hold them: scene.edges auto keeps the edges,
    in every round."""
    detected = _counting_detections(monkeypatch)
    scans, T_gt, _, _ = pole_scans(12, n_scans=6)
    report = _refine_report(run_pa, tmp_path, scans, T_gt, "refine: {max_rounds: 3}\n")
    first = report["rounds"][0]["planes"]
    assert first["edges"]["poorly_constrained_scans_planes_only"] == list(range(len(T_gt)))
    assert first["poorly_constrained_scans"] == [] and first["edges"]["n_edges"] >= 2
    assert all(r["planes"]["edges"]["n_edges"] == first["edges"]["n_edges"] for r in report["rounds"])
    assert "used" not in first["edges"] and len(detected) >= 1


def test_auto_edges_that_hold_no_weak_scan_are_dropped(run_pa, tmp_path, monkeypatch):
    """Ground and walls facing x leave every scan free along y; horizontal rails along y hold x and z only: scene.edges
    auto finds them once and adjusts the planes alone."""
    detected = _counting_detections(monkeypatch)
    rng = np.random.default_rng(13)
    n_scans = 6
    T = random_poses(n_scans, rng, 0.05, 0.5)
    T[:, :3, :3] = np.eye(3)
    rails = [(np.array([3.0, 0.0, 1.5]), np.array([0.0, 1.0, 0.0])), (np.array([-3.0, 0.0, 2.0]),
                                                                         np.array([0.0, 1.0, 0.0]))]
    scans = []
    for j in range(n_scans):
        parts = [np.column_stack([rng.uniform(-8, 8, (3000, 2)), rng.normal(0, 0.01, 3000)])]  # ground
        for x in (-7.0, 7.0):  # walls facing x
            parts.append(np.column_stack([x + rng.normal(0, 0.01, 2000), rng.uniform(-8, 8, 2000),
                                          rng.uniform(0, 4, 2000)]))
        for base, d in rails:
            t = rng.uniform(-4.0, 4.0, 300)
            parts.append(base + t[:, None] * d + near_side(base, d, T[j, :3, 3], 0.03, rng.uniform(-1, 1, 300)))
        world = np.vstack(parts)
        scans.append((world - T[j, :3, 3]) @ T[j, :3, :3])
    report = _refine_report(run_pa, tmp_path, scans, T, "refine: {max_rounds: 3}\n")
    first = report["rounds"][0]["planes"]
    assert first["edges"]["used"] is False and first["edges"]["n_edges"] >= 1
    assert first["edges"]["reason"] == "the edges hold no scan the planes leave poorly constrained"
    assert first["poorly_constrained_scans"] == list(range(n_scans))  # the planes' own list, restored
    assert len(detected) == 1 and all("edges" not in r["planes"] for r in report["rounds"][1:])


def test_auto_edges_are_not_looked_for_where_the_planes_hold_every_scan(run_pa, tmp_path, monkeypatch):
    from pa_testing.room_scene import ground_truth_poses, write_room_folder

    detected = _counting_detections(monkeypatch)
    (tmp_path / "room").mkdir()
    folder = write_room_folder(tmp_path / "room")
    from pa_cli.sources import open_source

    source = open_source(folder / "scans")
    scans = [np.asarray(source.points(k), dtype=np.float64) for k in range(len(source))]
    report = _refine_report(run_pa, tmp_path, scans, ground_truth_poses(),
                            "sensor: {max_range_m: 30.0, min_range_m: 0.2}\nrefine: {max_rounds: 2}\n")
    assert report["rounds"][0]["planes"]["edges"] == {"used": False, "reason": "the planes hold every scan"}
    assert detected == [] and all("edges" not in r["planes"] for r in report["rounds"][1:])


def _landmarks(lines: list[tuple[np.ndarray, np.ndarray, float]], voxel_size_m: float):
    """EdgeLandmarks for lines given as (centroid, unit direction, half length), with the voxels they cross."""
    from pa_cli.core.voxels import voxel_keys
    from pa_cli.planes.edges import CONFIG_KEY, EdgeLandmarks

    keys, owner = [], []
    for i, (centroid, direction, half) in enumerate(lines):
        along = np.linspace(-half, half, 200)[:, None]
        k = np.unique(voxel_keys(centroid + along * direction, voxel_size_m, CONFIG_KEY))
        keys.append(k)
        owner.append(np.full(len(k), i))
    return EdgeLandmarks(np.array([c for c, _, _ in lines]), np.array([d for _, d, _ in lines]),
                         np.array([[-h, h] for _, _, h in lines]), np.concatenate(keys), np.concatenate(owner))


def test_lines_with_surfaces_running_away_from_them_are_not_edges():
    """A wall corner (two faces meeting at a vertical line) is left out; a free pole next to it is kept.
    Seen from each viewpoint the corner's visible points centre elsewhere: it belongs to its planes."""
    from pa_cli.planes.edges import associate_edges

    rng = np.random.default_rng(7)
    T = np.repeat(np.eye(4)[None], 4, axis=0)
    T[:, 0, 3] = np.arange(4) * 0.5
    pole_axis, corner = np.array([3.0, 1.0]), np.array([5.0, 5.0])
    scans = []
    for j in range(len(T)):
        z = rng.uniform(0.3, 4.0, (3, 300))
        pole = np.r_[pole_axis, 0.0] + near_side(np.r_[pole_axis, 0.0], np.array([0.0, 0.0, 1.0]), T[j, :3, 3], 0.03,
                                                 rng.uniform(-1, 1, 300))
        pole[:, 2] = z[0]
        face_a = np.column_stack([corner[0] - rng.uniform(0, 1.0, 300), np.full(300, corner[1]), z[1]])
        face_b = np.column_stack([np.full(300, corner[0]), corner[1] - rng.uniform(0, 1.0, 300), z[2]])
        world = np.vstack([pole, face_a, face_b]) + rng.normal(0, 0.005, (900, 3))
        scans.append(world - T[j, :3, 3])
    up = np.array([0.0, 0.0, 1.0])
    config = EdgesConfig()
    landmarks = _landmarks([(np.r_[pole_axis, 2.15], up, 1.85), (np.r_[corner, 2.15], up, 1.85)], config.voxel_size_m)
    problem, _ = associate_edges(scans, T, landmarks, config)
    assert problem.n_planes == 1 and problem.n_observations == len(T)
    centroids = problem.clusters[:, :3, 3] / problem.clusters[:, 3:, 3] + T[problem.scan_index, :3, 3]
    assert np.all(np.linalg.norm(centroids[:, :2] - pole_axis, axis=1) < 0.01)
    # without the clearance test the corner would be an edge too
    unchecked, _ = associate_edges(scans, T, landmarks, config.model_copy(update={"max_clearance_fraction": np.inf}))
    assert unchecked.n_planes == 2


def test_one_beams_scan_line_on_the_ground_is_not_an_edge():
    """Each beam traces a ring on the ground: a piece of it is a line in every scan from that spot,
    but all its points have one elevation angle. A pole hit by several beams is kept."""
    from pa_cli.planes.edges import associate_edges

    rng = np.random.default_rng(8)
    height_m, beams = 1.8, np.deg2rad(np.arange(-15.0, 15.1, 2.0))
    azimuth = np.deg2rad(np.arange(0.0, 360.0, 0.35))
    pole_axis, radius_m = np.array([6.0, 1.0]), 0.05
    scans = []
    for _ in range(3):
        ground = [np.column_stack([rho * np.cos(azimuth), rho * np.sin(azimuth), np.full(len(azimuth), -height_m)])
                  for rho in height_m / np.tan(-beams[beams < 0])]
        distance = np.linalg.norm(pole_axis)
        z = distance * np.tan(beams)
        z = z[(z > -height_m) & (z < 3.0)]
        across = np.linspace(-radius_m, radius_m, 3)
        toward = -pole_axis / distance
        side = np.array([-toward[1], toward[0]])
        arc = pole_axis + across[:, None] * side + np.sqrt(radius_m**2 - across**2)[:, None] * toward
        pole = np.column_stack([np.repeat(arc, len(z), axis=0), np.tile(z, len(arc))])
        points = np.vstack([*ground, pole])
        scans.append(points + rng.normal(0, 0.005, points.shape) * (points / np.linalg.norm(points, axis=1)[:, None]))
    T = np.repeat(np.eye(4)[None], 3, axis=0)
    ring_rho = height_m / np.tan(np.deg2rad(9.0))
    config = EdgesConfig()
    landmarks = _landmarks([(np.r_[pole_axis, 0.5], np.array([0.0, 0.0, 1.0]), 2.0),
                            (np.array([0.0, ring_rho, -height_m]), np.array([1.0, 0.0, 0.0]), 0.75)],
                           config.voxel_size_m)
    problem, _ = associate_edges(scans, T, landmarks, config)
    assert problem.n_planes == 1 and problem.n_observations == 3
    centroids = problem.clusters[:, :3, 3] / problem.clusters[:, 3:, 3]
    assert np.all(np.linalg.norm(centroids[:, :2] - pole_axis, axis=1) < 0.06)
    # without the elevation test the ring would be an edge too
    unchecked, _ = associate_edges(scans, T, landmarks, config.model_copy(update={"min_elevation_spread_deg": 0.0}))
    assert unchecked.n_planes == 2


def test_degeneracy_report_counts_edge_information():
    """Ground plane alone: every scan free in x, y and yaw; with the poles no scan is held by nothing."""
    from pa_cli.evaluation.degeneracy import plane_information, scan_degeneracy
    from pa_cli.planes.edges import with_edges

    scans, T, _, _ = pole_scans(9)
    ground = [points_to_cluster(p[np.abs(p @ T[j, :3, :3].T[:, 2] + T[j, 2, 3]) < 0.05]) for j, p in enumerate(scans)]
    planes = make_problem(np.zeros(len(T), np.int64), np.arange(len(T)), np.array(ground))
    merged, _ = with_edges(planes, {}, scans, T, EdgesConfig(), 0.1)
    assert merged.n_planes == 4
    odometry = np.repeat(1e-3 * np.eye(6)[None], len(T), axis=0)  # a weak odometry prior on every scan
    planes_only = scan_degeneracy(planes, T, 10.0, odometry)
    with_lines = scan_degeneracy(merged, T, 10.0, odometry)
    assert planes_only.held_by_odometry_scans == list(range(len(T)))
    assert with_lines.held_by_odometry_scans == []
    # the information of the merged problem is that of the planes plus that of the edges alone, and an
    # edge (a vertical pole) fixes both horizontal translations of every scan that sees it, not one
    is_edge = merged.plane_index > 0
    edges_only = make_problem(merged.plane_index[is_edge] - 1, merged.scan_index[is_edge], merged.clusters[is_edge],
                              n_scans=len(T), feature_kind=merged.feature_kind[1:])
    np.testing.assert_allclose(plane_information(merged, T),
                               plane_information(planes, T) + plane_information(edges_only, T), atol=1e-9)
    first_pole = edges_only.plane_index == 0
    one_pole = make_problem(np.zeros(int(first_pole.sum()), np.int64), edges_only.scan_index[first_pole],
                            edges_only.clusters[first_pole], n_scans=len(T), feature_kind=edges_only.feature_kind[:1])
    horizontal = np.linalg.eigvalsh(plane_information(one_pole, T)[:, 3:5, 3:5])
    assert np.all(horizontal[:, 0] > 0.5 * horizontal[:, 1])


def test_poles_seen_from_one_side_do_not_pull_the_poses(monkeypatch):
    """Poles of 8 cm radius, each scan seeing their near half: from the true poses the adjustment of
    ground plus edges stays put; without the view correction the near halves pull the scans apart."""
    import pa_cli.planes.edges as edges_module
    from pa_cli.adjust import solve
    from pa_cli.config import SolverConfig

    scans, T, _, _ = pole_scans(10, n_scans=6, radius_m=0.08)
    ground = [points_to_cluster(p[np.abs(p @ T[j, :3, :3].T[:, 2] + T[j, 2, 3]) < 0.05]) for j, p in enumerate(scans)]
    planes = make_problem(np.zeros(len(T), np.int64), np.arange(len(T)), np.array(ground))

    def moved_m() -> float:
        edges, _ = build_edge_problem(scans, T, EdgesConfig(max_thickness_m=0.1))
        assert edges.n_planes == 3
        result = solve(merge_problems(planes, edges), T, SolverConfig())
        return float(np.linalg.norm(result.T_world_scan[:, :3, 3] - T[:, :3, 3], axis=1).max())

    # what is left is the sampling noise of 150 points per near half: r / sqrt(3 * 150) = 4 mm per scan
    assert moved_m() < 0.01
    monkeypatch.setattr(edges_module, "view_shifts", lambda clusters, *_: np.zeros((len(clusters), 3)))
    assert moved_m() > 0.02  # near halves (pi/4) 8 cm = 6 cm in front of the axis, from different sides
