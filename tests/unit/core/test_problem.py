"""Plane-problem files: clusters against brute force, round trip and every validation error."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from pa_cli.core.clusters import points_to_cluster
from pa_cli.core.problem import make_problem
from pa_cli.errors import FormatError, InputError, OutputError
from pa_cli.io.problem import load_problem, save_problem


def test_points_to_cluster_matches_brute_force():
    points = np.random.default_rng(0).normal(size=(37, 3))
    brute = np.zeros((4, 4))
    for p in points:
        ph = np.append(p, 1.0)
        brute += np.outer(ph, ph)
    np.testing.assert_allclose(points_to_cluster(points), brute, rtol=1e-13, atol=1e-12)


def _arrays(seed=0):
    """4 scans; plane 7 seen by scans 0,1,2; plane 3 by 1,3; plane 5 only by scan 2."""
    rng = np.random.default_rng(seed)
    plane_index = np.array([7, 3, 7, 5, 3, 7])
    scan_index = np.array([0, 1, 1, 2, 3, 2])
    clusters = np.stack([points_to_cluster(rng.normal(size=(10 + k, 3))) for k in range(6)])
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, :3, 3] = rng.normal(size=(4, 3))
    return plane_index, scan_index, clusters, poses


def test_round_trip_drops_single_scan_planes_and_renumbers(tmp_path, caplog):
    plane_index, scan_index, clusters, poses = _arrays()
    np.savez(tmp_path / "raw.npz", plane_index=plane_index, scan_index=scan_index, clusters=clusters,
             poses=poses)
    with caplog.at_level(logging.INFO, logger="pa_cli"):
        problem = load_problem(tmp_path / "raw.npz")
    assert "dropped 1 planes" in caplog.text
    assert problem.n_dropped_planes == 1 and problem.n_scans == 4 and problem.n_planes == 2
    # planes 3 -> 0, 7 -> 1; sorted by (plane, scan)
    np.testing.assert_array_equal(problem.plane_index, [0, 0, 1, 1, 1])
    np.testing.assert_array_equal(problem.scan_index, [1, 3, 0, 1, 2])
    np.testing.assert_array_equal(problem.clusters, clusters[[1, 4, 0, 2, 5]])
    np.testing.assert_array_equal(problem.T_world_scan, poses)
    assert problem.n_points == int(clusters[[1, 4, 0, 2, 5], 3, 3].sum())

    save_problem(tmp_path / "p.npz", problem)
    with pytest.raises(OutputError, match="--force"):
        save_problem(tmp_path / "p.npz", problem)
    again = load_problem(tmp_path / "p.npz")
    assert again.n_dropped_planes == 0
    for name in ("plane_index", "scan_index", "clusters", "T_world_scan"):
        np.testing.assert_array_equal(getattr(again, name), getattr(problem, name))
    with np.load(tmp_path / "p.npz") as data:
        assert data["plane_index"].dtype == np.int64 and data["clusters"].dtype == np.float64


def _expect(tmp_path, match, **overrides):
    plane_index, scan_index, clusters, poses = _arrays()
    arrays = {"plane_index": plane_index, "scan_index": scan_index, "clusters": clusters, "poses": poses}
    arrays.update(overrides)
    arrays = {k: v for k, v in arrays.items() if v is not None}
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(FormatError, match=match) as info:
        load_problem(tmp_path / "bad.npz")
    assert "bad.npz" in str(info.value)


def test_validation_errors(tmp_path):
    plane_index, scan_index, clusters, poses = _arrays()
    _expect(tmp_path, "'clusters' must have shape \\(6, 4, 4\\)", clusters=clusters[:, :3, :3])
    _expect(tmp_path, "'plane_index' has 6 entries but 'scan_index' has 5", scan_index=scan_index[:5])
    _expect(tmp_path, "'plane_index' must be a 1-D integer", plane_index=plane_index.astype(float))
    _expect(tmp_path, "'poses' must have shape", poses=poses[:, :3, :])
    asym = clusters.copy()
    asym[2, 0, 1] += 1.0
    _expect(tmp_path, "cluster 2 is not symmetric", clusters=asym)
    nan = clusters.copy()
    nan[4, 1, 1] = np.nan
    _expect(tmp_path, "NaN", clusters=nan)
    nan_poses = poses.copy()
    nan_poses[1, 0, 3] = np.inf
    _expect(tmp_path, "'poses' contains NaN", poses=nan_poses)
    _expect(tmp_path, "refers to scan 9 but there are only 4", scan_index=np.array([0, 1, 1, 2, 3, 9]))
    _expect(tmp_path, "non-negative", plane_index=np.array([7, 3, 7, -5, 3, 7]))
    _expect(tmp_path, "duplicate", scan_index=np.array([0, 1, 0, 2, 3, 2]))
    zero = clusters.copy()
    zero[0] = 0.0
    _expect(tmp_path, "point count", clusters=zero)
    _expect(tmp_path, "missing arrays \\['clusters'\\]", clusters=None)


def test_unreadable_and_missing_files(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_problem(tmp_path / "none.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip file")
    with pytest.raises(FormatError, match="junk.npz.*not a readable"):
        load_problem(tmp_path / "junk.npz")


def test_make_problem_without_poses_counts_scans():
    plane_index, scan_index, clusters, _ = _arrays()
    problem = make_problem(plane_index, scan_index, clusters)
    assert problem.n_scans == 4 and problem.T_world_scan is None
    assert make_problem(plane_index, scan_index, clusters, n_scans=6).n_scans == 6


def test_make_problem_orders_drops_and_renumbers_as_the_reference():
    """Observations in any order: kept ones sorted by (feature, scan), features seen by one scan
    dropped, the rest renumbered in order, clusters, range clusters and kinds following them; a
    duplicate (feature, scan) is refused. Reference: Python sorting of the observation tuples."""
    rng = np.random.default_rng(21)
    for trial in range(40):
        n_scans, n_features = int(rng.integers(2, 9)), int(rng.integers(1, 12))
        obs = sorted({(int(rng.integers(0, n_features)), int(rng.integers(0, n_scans))) for _ in range(30)})
        shuffled = [obs[i] for i in rng.permutation(len(obs))] if trial % 2 else obs
        plane_index, scan_index = np.array(shuffled).T
        clusters = np.array([points_to_cluster(rng.normal(size=(3, 3))) for _ in shuffled])
        kind = rng.integers(0, 2, n_features).astype(np.uint8)
        problem = make_problem(plane_index, scan_index, clusters, n_scans=n_scans, feature_kind=kind,
                               range_clusters=clusters / 2.0)
        seen = {p: sum(1 for q, _ in obs if q == p) for p, _ in obs}
        kept = sorted((p, s) for p, s in obs if seen[p] >= 2)
        renumber = {p: i for i, p in enumerate(sorted({p for p, _ in kept}))}
        assert problem.plane_index.tolist() == [renumber[p] for p, _ in kept]
        assert problem.scan_index.tolist() == [s for _, s in kept]
        where = [shuffled.index(o) for o in kept]
        assert np.array_equal(problem.clusters, clusters[where])
        assert np.array_equal(problem.range_clusters, clusters[where] / 2.0)
        assert problem.feature_kind.tolist() == [kind[p] for p in sorted(renumber)]
        assert problem.n_dropped_planes == len(seen) - len(renumber)
        if len(shuffled) > 1:
            with pytest.raises(FormatError, match="1 duplicate"):
                make_problem(np.append(plane_index, plane_index[0]), np.append(scan_index, scan_index[0]),
                             np.concatenate([clusters, clusters[:1]]), n_scans=n_scans)
