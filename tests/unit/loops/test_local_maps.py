"""Local maps' thinning (`pa_cli.loops.local_maps.voxel_centroids`) against a brute-force mean per voxel."""

from __future__ import annotations

import numpy as np

from pa_cli.loops.local_maps import voxel_centroids


def test_voxel_centroids_are_the_mean_of_each_occupied_voxel():
    rng = np.random.default_rng(11)
    voxel_m = 0.5
    # clustered points (many per voxel) and scattered ones (one per voxel), off the origin and negative
    points = np.vstack([rng.normal((3.2, -7.9, 1.1), 0.6, (4000, 3)), rng.uniform(-40.0, 40.0, (300, 3))])
    keys = np.floor(points / voxel_m).astype(np.int64)
    expected = {}
    for key in {tuple(k) for k in keys}:
        expected[key] = points[(keys == key).all(axis=1)].mean(axis=0)
    got = voxel_centroids(points, voxel_m)
    assert len(got) == len(expected)
    for centroid in got:
        key = tuple(np.floor(centroid / voxel_m).astype(np.int64))  # a mean of points in a voxel lies in it
        np.testing.assert_allclose(centroid, expected[key], atol=1e-9)
    np.testing.assert_array_equal(voxel_centroids(points, voxel_m), got)  # the same order every call
    assert voxel_centroids(np.empty((0, 3)), voxel_m).shape == (0, 3)
