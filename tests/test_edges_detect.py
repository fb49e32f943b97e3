"""Edge landmarks: detection of line-like voxels, growing, association, merging with planes."""

from __future__ import annotations

import numpy as np

from pa_cli.clusters import points_to_cluster
from pa_cli.config import EdgesConfig
from pa_cli.geometry import exp_so3
from pa_cli.planes.edges import build_edge_problem, merge_problems
from pa_cli.problem import FEATURE_EDGE, FEATURE_PLANE, make_problem
from tests.synthetic_problems import random_poses


def pole_scans(seed: int, n_scans: int = 5, radius_m: float = 0.03):
    """Scans of three thin poles (two vertical, one tilted) above a noisy ground plane: (scans, T_gt,
    pole bases, pole directions)."""
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
            angle = rng.uniform(0, 2 * np.pi, 150)
            across = exp_so3(np.cross([0, 0, 1.0], d)[None] * 1.0)[0]  # any frame across d
            ring = np.column_stack([np.cos(angle), np.sin(angle), np.zeros(150)]) * radius_m
            parts.append(base + t[:, None] * d + ring @ across.T)
        world = np.vstack(parts)
        scans.append((world - T[j, :3, 3]) @ T[j, :3, :3])
    return scans, T, bases, directions


def test_detects_each_pole_once_with_its_direction():
    scans, T, bases, directions = pole_scans(0)
    problem, diag = build_edge_problem(scans, T, EdgesConfig())
    assert problem.n_planes == 3
    assert np.all(problem.feature_kind == FEATURE_EDGE)
    assert diag["n_edges"] == 3
    assert diag["edge_rms_point_to_line_m"] < 0.03  # points lie 3 cm from the axis
    assert diag["edge_rms_point_to_line_m"] > 0.02
    # every scan observes every pole, with only pole points (no ground point: z > 0.2 m)
    assert problem.n_observations == 3 * len(scans)
    for o in range(problem.n_observations):
        C = T[problem.scan_index[o]] @ problem.clusters[o] @ T[problem.scan_index[o]].T
        centroid = C[:3, 3] / C[3, 3]
        dist = [np.linalg.norm(np.cross(centroid - b, d)) for b, d in zip(bases, directions, strict=True)]
        assert min(dist) < 0.05


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
    assert with_edges(planes, diagnostics, scans, T, EdgesConfig(enabled=False), 0.1) is planes
    assert set(diagnostics) == {"poorly_constrained_scans"}
    merged = with_edges(planes, diagnostics, scans, T, EdgesConfig(enabled=True), 0.1)
    assert merged.n_planes == 1 + diagnostics["edges"]["n_edges"] and diagnostics["edges"]["n_edges"] == 3
    # two vertical poles fix x and y, the ground z: every scan is constrained in all three directions
    assert diagnostics["poorly_constrained_scans"] == []
    assert diagnostics["edges"]["poorly_constrained_scans_planes_only"] == list(range(len(T)))
    assert min(diagnostics["constraint_eigenvalue_per_scan"]) > 0.9


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
    (tmp_path / "cfg.yaml").write_text("edges: {enabled: true}\nrefine: {max_rounds: 2}\n")
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
