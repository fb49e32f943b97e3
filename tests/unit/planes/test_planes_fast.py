"""The numba fast paths of plane detection/association against the straightforward numpy
formulation they replaced (reference implementations below: sort + bincount per scan and
level, searchsorted leaf lookup, vectorised trimming). Same keys, same labels, sums equal up
to summation order."""

from __future__ import annotations

import numpy as np
import pytest

from pa_cli.config import PlanesConfig
from pa_cli.core.clusters import RANGE_WEIGHT_FLOOR_M, range_weights
from pa_cli.core.geometry import transform_points
from pa_cli.core.voxels import decode_keys, encode_keys
from pa_cli.errors import InputError
from pa_cli.planes import detect, kernels
from pa_cli.planes.associate import build_plane_problem
from pa_cli.planes.detect import detect_landmarks
from tests.unit.planes.test_planes import make_scene, room_planes

CONFIG = PlanesConfig(voxel_size_m=0.5)


# ---- reference implementations (numpy, one sort per scan and level) ----

def _ref_moments(keys: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    uniq, inverse = np.unique(keys, return_inverse=True)
    cols = [np.ones(len(q)), q[:, 0], q[:, 1], q[:, 2], q[:, 0] * q[:, 0], q[:, 0] * q[:, 1],
            q[:, 0] * q[:, 2], q[:, 1] * q[:, 1], q[:, 1] * q[:, 2], q[:, 2] * q[:, 2]]
    return uniq, np.stack([np.bincount(inverse, c, minlength=len(uniq)) for c in cols])


def ref_accumulate(scans, T, config: PlanesConfig) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per level: sorted voxel keys and sums (10, K) of [1, q, q q^T] over all scans."""
    out = []
    for level in range(config.max_subdivision_levels + 1):
        size_m = config.voxel_size_m / 2**level
        keys, sums = [], []
        for j, pts in enumerate(scans):
            p = transform_points(T[j], pts)
            coords = np.floor(p / size_m)
            k, s = _ref_moments(encode_keys(coords, size_m), p - (coords + 0.5) * size_m)
            keys.append(k)
            sums.append(s)
        uniq, inverse = np.unique(np.concatenate(keys), return_inverse=True)
        s = np.concatenate(sums, axis=1)
        out.append((uniq, np.stack([np.bincount(inverse, s[c], minlength=len(uniq)) for c in range(10)])))
    return out


def lookup(lms: detect.Landmarks, points_world: np.ndarray) -> np.ndarray:
    """Landmark id (M,) of the leaf holding each world point, -1 when none: the kernel without trimming."""
    return lms._run_kernel(points_world, False, np.zeros(lms.n_landmarks))[0]


def ref_lookup(lms: detect.Landmarks, points_world: np.ndarray) -> np.ndarray:
    labels = np.full(len(points_world), -1, dtype=np.int64)
    todo = np.arange(len(points_world))
    for level, (keys, landmark) in enumerate(zip(lms.leaf_keys, lms.leaf_landmark, strict=True)):
        if len(keys) == 0 or len(todo) == 0:
            continue
        size_m = lms.voxel_size_m / 2**level
        k = encode_keys(np.floor(points_world[todo] / size_m), size_m)
        pos = np.minimum(np.searchsorted(keys, k), len(keys) - 1)
        hit = keys[pos] == k
        labels[todo[hit]] = landmark[pos[hit]]
        todo = todo[~hit]
    return labels


def ref_assign(lms: detect.Landmarks, points_world: np.ndarray, outlier_sigma: float,
               sigma_floor_m: float) -> tuple[np.ndarray, int]:
    labels = ref_lookup(lms, points_world)
    on = np.flatnonzero(labels >= 0)
    lm = labels[on]
    p = points_world[on]
    dist_m = np.abs(np.einsum("ij,ij->i", p - lms.centroid_world[lm], lms.normal_world[lm]))
    gate_m = outlier_sigma * np.maximum(lms.sigma_m, sigma_floor_m)
    out = dist_m > gate_m[lm]
    if len(lms.near_keys) and len(on):
        k0 = encode_keys(np.floor(p / lms.voxel_size_m), lms.voxel_size_m)
        lo = np.searchsorted(lms.near_keys, k0, side="left")
        n_cand = np.searchsorted(lms.near_keys, k0, side="right") - lo
        pt = np.repeat(np.arange(len(on)), n_cand)
        first = np.repeat(lo - (np.cumsum(n_cand) - n_cand), n_cand)
        other = lms.near_landmark[first + np.arange(len(pt))]
        mine = lm[pt]
        keep = other != mine
        pt, other, mine = pt[keep], other[keep], mine[keep]
        d_other = np.abs(np.einsum("ij,ij->i", p[pt] - lms.centroid_world[other], lms.normal_world[other]))
        cos_min = np.cos(np.deg2rad(lms.max_normal_angle_deg))
        parallel = np.abs(np.einsum("ij,ij->i", lms.normal_world[mine], lms.normal_world[other])) >= cos_min
        same_plane = parallel & (d_other <= gate_m[other])
        inside_other = d_other <= np.where(parallel, np.maximum(gate_m[other], gate_m[mine]), gate_m[other])
        out[pt[~same_plane & (inside_other | (d_other < dist_m[pt]))]] = True
    labels[on[out]] = -1
    return labels, int(out.sum())


def ref_observe(lms: detect.Landmarks, points_scan: np.ndarray, T_world_scan: np.ndarray, outlier_sigma: float,
                sigma_floor_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int]:
    """`Landmarks.observe` in numpy: finite rows, transform_points, ref_assign, bincount sums of the
    scan-frame moments [1, x, y, z, xx, xy, xz, yy, yz, zz], plain and weighted by `range_weights`."""
    rows = np.asarray(points_scan, dtype=np.float64)
    finite = np.isfinite(rows).all(axis=1)
    p = rows[finite]
    labels, n_trimmed = ref_assign(lms, transform_points(T_world_scan, p), outlier_sigma, sigma_floor_m)
    on = labels >= 0
    x, y, z = p[on].T
    moments = [np.ones(len(x)), x, y, z, x * x, x * y, x * z, y * y, y * z, z * z]
    w = range_weights(p)[on]
    sums = np.column_stack([np.bincount(labels[on], m, minlength=lms.n_landmarks) for m in moments])
    range_sums = np.column_stack([np.bincount(labels[on], w * m, minlength=lms.n_landmarks) for m in moments])
    out = np.full(len(rows), -1, dtype=np.int32)
    out[finite] = labels
    return out, sums, range_sums, len(p), n_trimmed


# ---- tests ----

@pytest.fixture(scope="module")
def scene():
    scans, T, _, _ = make_scene(room_planes(), n_scans=6, seed=3)
    # clutter (non-planar voxels, subdivision) and one scan far from the others
    rng = np.random.default_rng(1)
    scans = [np.vstack([s, rng.uniform(-4, 4, (400, 3))]) for s in scans]
    return scans, T


@pytest.mark.parametrize("levels", [0, 2])
def test_accumulate_matches_reference(scene, levels):
    scans, T = scene
    config = CONFIG.model_copy(update={"max_subdivision_levels": levels})
    fast = detect.accumulate_voxels(scans, T, config)
    ref = ref_accumulate(scans, T, config)
    assert len(fast) == levels + 1
    for level, (st, (keys, sums)) in enumerate(zip(fast, ref, strict=True)):
        np.testing.assert_array_equal(st.keys, keys)
        np.testing.assert_array_equal(st.count, sums[0])
        size_m = config.voxel_size_m / 2**level
        mean_local = sums[1:4].T / sums[0][:, None]
        np.testing.assert_allclose(st.mean_world, (decode_keys(keys) + 0.5) * size_m + mean_local,
                                   rtol=0, atol=1e-12)
        xx, xy, xz, yy, yz, zz = sums[4:]
        second = np.stack([xx, xy, xz, xy, yy, yz, xz, yz, zz], -1).reshape(-1, 3, 3)
        scatter = second - sums[0][:, None, None] * mean_local[:, :, None] * mean_local[:, None, :]
        np.testing.assert_allclose(st.scatter, scatter, rtol=1e-9, atol=1e-12)


def test_accumulate_drops_non_finite_points(scene):
    """A scan with NaN / inf rows gives the voxel statistics of its finite points."""
    scans, T = scene
    dirty = [s.copy() for s in scans]
    dirty[2][[5, 40, 41], 1] = np.nan
    dirty[4][7, 0] = np.inf
    clean = [s[np.isfinite(s).all(axis=1)] for s in dirty]
    assert sum(map(len, clean)) == sum(map(len, scans)) - 4
    for st_dirty, st_clean in zip(detect.accumulate_voxels(dirty, T, CONFIG),
                                  detect.accumulate_voxels(clean, T, CONFIG), strict=True):
        np.testing.assert_array_equal(st_dirty.keys, st_clean.keys)
        np.testing.assert_array_equal(st_dirty.count, st_clean.count)
        np.testing.assert_array_equal(st_dirty.scatter, st_clean.scatter)


def test_accumulate_does_not_depend_on_the_threads(scene):
    scans, T = scene
    one, three = (detect.accumulate_voxels(scans, T, CONFIG.model_copy(update={"association_threads": n}))
                  for n in (1, 3))
    for a, b in zip(one, three, strict=True):
        np.testing.assert_array_equal(a.keys, b.keys)
        np.testing.assert_array_equal(a.scatter, b.scatter)  # sums added in scan order either way


def _adaptive_cells(rng: np.random.Generator) -> detect.VoxelStats:
    """Non-overlapping cells of a 3-level adaptive grid: random level-0 voxels, some split into
    their 8 children, some of those split again; a random part of the leaves kept."""
    coords = {0: np.unique(rng.integers(-3, 3, (60, 3)), axis=0)}
    cells = []
    for level in range(3):
        split = rng.random(len(coords[level])) < (0.4 if level < 2 else 0.0)
        keep = ~split & (rng.random(len(coords[level])) < 0.8)
        cells += [(level, c) for c in coords[level][keep]]
        children = (2 * coords[level][split])[:, None, :] + _CHILD[None]
        coords[level + 1] = children.reshape(-1, 3)
    level = np.array([lv for lv, _ in cells])
    keys = encode_keys(np.array([c for _, c in cells]))
    n = len(cells)
    return detect.VoxelStats(level=level, keys=keys, count=np.ones(n), mean_world=np.zeros((n, 3)),
                             scatter=np.zeros((n, 3, 3)))


_CHILD = np.array(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij")).reshape(3, -1).T


@pytest.mark.parametrize("neighbourhood", [6, 26])
def test_adjacency_matches_brute_force(neighbourhood):
    """Cell pairs (a, b), b at a's level or coarser, with b holding a's voxel moved by one
    neighbour offset, by brute force over all pairs and offsets."""
    cells = _adaptive_cells(np.random.default_rng(4))
    coords, level = decode_keys(cells.keys), cells.level
    expected = set()
    for a in range(len(level)):
        for b in range(len(level)):
            if level[b] > level[a] or a == b:
                continue
            moved = np.floor_divide(coords[a] + detect.NEIGHBOUR_OFFSETS[neighbourhood], 2 ** (level[a] - level[b]))
            if (moved == coords[b]).all(axis=1).any():
                expected.add((a, b))
    assert len(expected) > 100 and len({lv for a, b in expected for lv in (level[a] - level[b],)}) == 3
    adjacency = detect._Adjacency(cells, neighbourhood, 3)
    everything = np.arange(len(level))
    assert set(map(tuple, adjacency.pairs(everything, finer=False).tolist())) == expected
    both = expected | {(b, a) for a, b in expected}
    assert set(map(tuple, adjacency.pairs(everything).tolist())) == both
    first = len(level) // 2  # targets from an index on, from some sources only
    sources = everything[::3]
    assert set(map(tuple, adjacency.pairs(sources, first).tolist())) == \
        {(a, b) for a, b in both if a in set(sources.tolist()) and b >= first}


@pytest.mark.parametrize("threads", [2, 3])
def test_adjacency_split_over_threads_gives_the_same_pairs(monkeypatch, threads):
    """Sources split into row blocks (one per thread): the same pairs in the same order."""
    cells = _adaptive_cells(np.random.default_rng(5))
    everything = np.arange(len(cells.keys))
    one = detect._Adjacency(cells, 26, 3).pairs(everything)
    monkeypatch.setattr(detect, "MIN_ROWS_PER_THREAD", 7)
    split = detect._Adjacency(cells, 26, 3, threads).pairs(everything)
    assert len(one) > 1000
    np.testing.assert_array_equal(split, one)


def test_in_parts_covers_the_rows_in_order(monkeypatch):
    monkeypatch.setattr(detect, "MIN_ROWS_PER_THREAD", 10)
    x, y = np.arange(95), np.arange(95) * 10
    parts = detect.in_parts(lambda a, b: a + b, len(x), 3, x, y)
    assert len(parts) == 3 and min(map(len, parts)) >= 10
    np.testing.assert_array_equal(np.concatenate(parts), x + y)
    assert len(detect.in_parts(lambda a: a, 25, 3, x[:25])) == 2  # blocks of at least 10 rows
    assert len(detect.in_parts(lambda a: a, 95, 1, x)) == 1


def test_accumulate_of_float32_scans_equals_their_float64_values(scene):
    """Scans as float32 (the scan cache) are moved in float64 like their float64 copies."""
    scans, T = scene
    single = [s.astype(np.float32) for s in scans]
    for a, b in zip(detect.accumulate_voxels(single, T, CONFIG),
                    detect.accumulate_voxels([s.astype(np.float64) for s in single], T, CONFIG), strict=True):
        np.testing.assert_array_equal(a.keys, b.keys)
        np.testing.assert_array_equal(a.scatter, b.scatter)


def test_detection_does_not_depend_on_the_threads(scene, monkeypatch):
    """Landmarks with every threaded step split into blocks (small MIN_ROWS_PER_THREAD) equal
    those of one thread: leaves, landmark ids, planes and junction keys."""
    scans, T = scene
    one = detect_landmarks(scans, T, CONFIG.model_copy(update={"association_threads": 1}))
    monkeypatch.setattr(detect, "MIN_ROWS_PER_THREAD", 3)
    many = detect_landmarks(scans, T, CONFIG.model_copy(update={"association_threads": 3}))
    assert one.n_landmarks > 5
    for a, b in zip(one.leaf_keys + one.leaf_landmark, many.leaf_keys + many.leaf_landmark, strict=True):
        np.testing.assert_array_equal(a, b)
    for name in ("normal_world", "centroid_world", "sigma_m", "count", "near_keys", "near_landmark"):
        np.testing.assert_array_equal(getattr(one, name), getattr(many, name))


def test_finite_points_drops_exactly_the_non_finite_rows():
    rng = np.random.default_rng(5)
    points = rng.normal(size=(50, 3))
    assert detect.finite_points(points) is points  # all finite: no copy
    huge = np.array([[1e308, 1e308, 1e308], [1e308, 0.0, 1.0]])  # finite, but their sum overflows
    np.testing.assert_array_equal(detect.finite_points(huge), huge)
    dirty = points.copy()
    dirty[[3, 9], 2] = np.nan
    dirty[20, 0] = -np.inf
    dirty[[30, 31], :] = [np.inf, -np.inf, 0.0]  # inf - inf would cancel to NaN in a sum, still dropped
    kept = detect.finite_points(dirty)
    np.testing.assert_array_equal(kept, np.delete(points, [3, 9, 20, 30, 31], axis=0))


def test_assign_and_lookup_match_reference(scene):
    scans, T = scene
    lms = detect_landmarks(scans, T, CONFIG)
    assert lms.n_landmarks > 5 and len(lms.near_keys) > 0
    rng = np.random.default_rng(2)
    n_trimmed_total = 0
    for j, pts in enumerate(scans):
        T_moved = T[j].copy()
        T_moved[:3, 3] += rng.normal(0, 0.02, 3)  # off the detection poses: points get trimmed
        p = transform_points(T_moved, pts)
        np.testing.assert_array_equal(lookup(lms, p), ref_lookup(lms, p))
        labels, n_trimmed = lms.assign(p, CONFIG.outlier_sigma, CONFIG.outlier_sigma_floor_m)
        ref_labels, ref_trimmed = ref_assign(lms, p, CONFIG.outlier_sigma, CONFIG.outlier_sigma_floor_m)
        np.testing.assert_array_equal(labels, ref_labels)
        assert n_trimmed == ref_trimmed
        n_trimmed_total += n_trimmed
    assert n_trimmed_total > 0


def test_build_plane_problem_matches_reference_path(scene, monkeypatch):
    scans, T = scene
    fast, fast_diag = build_plane_problem(scans, T, CONFIG)

    def ref_accumulate_stats(scans, T, config, *args, **kwargs):
        return [detect._stats_from_sums(level, keys, sums, config.voxel_size_m)
                for level, (keys, sums) in enumerate(ref_accumulate(scans, T, config))]

    def ref_landmarks_observe(lms, points_scan, T_world_scan, gate_m):
        np.testing.assert_array_equal(gate_m, lms.gates_m(CONFIG.outlier_sigma, CONFIG.outlier_sigma_floor_m))
        return ref_observe(lms, points_scan, T_world_scan, CONFIG.outlier_sigma, CONFIG.outlier_sigma_floor_m)

    monkeypatch.setattr(detect, "accumulate_voxels", ref_accumulate_stats)
    monkeypatch.setattr(detect.Landmarks, "observe", ref_landmarks_observe)
    ref, ref_diag = build_plane_problem(scans, T, CONFIG)
    assert fast.n_planes == ref.n_planes > 5
    np.testing.assert_array_equal(fast.plane_index, ref.plane_index)
    np.testing.assert_array_equal(fast.scan_index, ref.scan_index)
    np.testing.assert_allclose(fast.clusters, ref.clusters, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(fast.range_clusters, ref.range_clusters, rtol=1e-12, atol=1e-12)
    for key in ("n_landmarks_detected", "n_points_covered", "n_points_trimmed", "n_leaves"):
        assert fast_diag[key] == ref_diag[key]


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_observe_matches_the_numpy_form(scene, dtype):
    """One pass per scan (transform, finiteness, assignment, both sums) against the numpy steps,
    off the detection poses (points get trimmed), with non-finite rows and float32 input."""
    scans, T = scene
    lms = detect_landmarks(scans, T, CONFIG)
    gate_m = lms.gates_m(CONFIG.outlier_sigma, CONFIG.outlier_sigma_floor_m)
    rng = np.random.default_rng(4)
    n_trimmed_total = 0
    for j, pts in enumerate(scans):
        T_moved = T[j].copy()
        T_moved[:3, 3] += rng.normal(0, 0.02, 3)
        rows = pts.astype(dtype)
        rows[rng.choice(len(rows), 5, replace=False), rng.integers(0, 3, 5)] = [np.nan, np.inf, -np.inf, np.nan, np.nan]
        labels, sums, range_sums, n_finite, n_trimmed = lms.observe(rows, T_moved, gate_m)
        ref_labels, ref_sums, ref_range_sums, ref_finite, ref_trimmed = ref_observe(
            lms, rows, T_moved, CONFIG.outlier_sigma, CONFIG.outlier_sigma_floor_m)
        assert labels.dtype == np.int32 and len(labels) == len(rows)
        np.testing.assert_array_equal(labels, ref_labels)
        assert (n_finite, n_trimmed) == (ref_finite, ref_trimmed) and n_finite == len(rows) - 5
        np.testing.assert_allclose(sums, ref_sums, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(range_sums, ref_range_sums, rtol=1e-12, atol=1e-12)
        assert (sums[:, 0] > 0).sum() > 3
        n_trimmed_total += n_trimmed
    assert n_trimmed_total > 0


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_observation_moments_match_bincount(dtype):
    """Sums of points added to given rows (negative rows skipped), plain and range-weighted,
    against bincount of the moments and `range_weights` (points near the origin: the floor)."""
    rng = np.random.default_rng(5)
    points = rng.normal(0.0, 10.0, (3000, 3)).astype(dtype)
    points[:20] = rng.normal(0.0, 0.03, (20, 3))  # within RANGE_WEIGHT_FLOOR_M of the sensor
    observation = rng.integers(-1, 7, len(points)).astype(np.int32)
    sums, range_sums = np.ones((7, 10)), np.ones((7, 10))  # the scan's sums are added to these
    scratch = (np.zeros((7, 10)), np.zeros((7, 10)), np.zeros(7, dtype=np.bool_), np.empty(7, dtype=np.int64))
    kernels.observation_moments(observation, points, sums, range_sums, True, RANGE_WEIGHT_FLOOR_M**2, *scratch)
    assert not scratch[0].any() and not scratch[1].any() and not scratch[2].any()  # left clean
    p = points.astype(np.float64)
    on = observation >= 0
    x, y, z = p[on].T
    moments = [np.ones(len(x)), x, y, z, x * x, x * y, x * z, y * y, y * z, z * z]
    w = range_weights(p)[on]
    assert w.max() == 1.0 / RANGE_WEIGHT_FLOOR_M**2
    for c, m in enumerate(moments):
        np.testing.assert_allclose(sums[:, c], 1 + np.bincount(observation[on], m, minlength=7), rtol=1e-12)
        np.testing.assert_allclose(range_sums[:, c], 1 + np.bincount(observation[on], w * m, minlength=7),
                                   rtol=1e-12)
    plain_only = np.ones((7, 10))
    kernels.observation_moments(observation, points, plain_only, np.zeros((0, 10)), False, RANGE_WEIGHT_FLOOR_M**2,
                                 *scratch)
    np.testing.assert_array_equal(plain_only, sums)


def test_points_outside_the_grid_raise(scene):
    scans, T = scene
    far = T.copy()
    far[1, 0, 3] = 1e6  # 1000 km: beyond the 0.5 m grid (+-262 km)
    with pytest.raises(InputError, match="from the world origin"):
        detect.accumulate_voxels(scans, far, CONFIG)
    lms = detect_landmarks(scans, T, CONFIG)
    with pytest.raises(InputError, match="from the world origin"):
        lms.assign(transform_points(far[1], scans[1]), 3.0, 0.002)
    with pytest.raises(InputError, match="from the world origin"):
        lms.observe(scans[1], far[1], lms.gates_m(3.0, 0.002))
