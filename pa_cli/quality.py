"""An honest verdict on a refinement: is the map really better than with the initial poses?

A refinement's own cost is measured on planes it found at its own poses, which favours them: a
broken trajectory can fit its own planes perfectly. The verdict therefore combines:

1. Cross-scored sharpness. Two plane associations are fixed per point: the one found at the
   INITIAL poses (round 1) and the one found at the REFINED poses (the last association). Both
   pose sets are scored on both (each with the points deskewed by its own trajectory): the RMS
   point-to-plane distance sqrt(sum of squared distances / points), planes at their best fit.
   The refined poses must be sharper on both.
2. Odometry consistency. Each consecutive pair's relative motion after refinement is compared
   with the initial one, in units of the odometry model's sigmas (rotation and translation
   separately); pairs changed by more than `quality_outlier_sigma` are listed: either the
   odometry broke there or the refinement did.
3. Ties. Two consecutive scans are tied by the map in the directions spanned by the normals of
   the landmarks they share: with M = sum of n n^T over those normals (unit, world frame), its
   middle eigenvalue below `quality_min_tie` means they share planes of one orientation only
   (e.g. the ground): rotation about that normal and sliding along the planes rest on the
   odometry alone, so a break of the initial trajectory there (a wrong turn) could be neither
   seen nor corrected.
4. Settling: whether the last round moved no pose more than the tolerance.
5. Mean map entropy (MME), a sharpness measure that needs no planes: for a query point of the
   map, the differential entropy of a Gaussian fit to the map points within `radius_m` of it,
   h = 1/2 ln det(2 pi e Sigma) (nats); MME is its mean over the query points. A sharper map has
   thinner neighbourhoods, hence a smaller det Sigma and a lower MME; a difference of
   3 ln(1 + x) nats is every neighbourhood's standard deviations growing by a fraction x.
   Both pose sets are scored on the same points (the same subsample of every scan, each deskewed
   by its own trajectory) and the same query points (those with enough neighbours under both).

Verdict: `degraded` when the refined RMS is worse than the initial by more than
`quality_rms_tolerance` (relative) on either association, or the refined MME is higher than the
initial by more than `quality_entropy_tolerance_nats`; `improved` when the RMS is better on both
associations, the MME is lower, and none of 2-4 raised a doubt; `uncertain` otherwise. `reasons`
says why, in words.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numba
import numpy as np

from pa_cli import _numba  # noqa: F401  (numba cache folder: see pa_cli/_numba.py)
from pa_cli.problem import FeatureProblem


def rms_point_to_plane(problem: FeatureProblem, T_world_scan: np.ndarray) -> float:
    """sqrt(plane cost / points) (m) of a problem at poses T_world_scan."""
    from pa_cli.adjust import plane_cost

    return float(np.sqrt(plane_cost(problem, T_world_scan) / max(problem.n_points, 1)))


def map_subsample(n_points_per_scan: Sequence[int], max_map_points: int) -> tuple[int, list[np.ndarray]]:
    """The map points of the map entropy: (stride s, per scan the sorted indices of its points kept).

    All points when they fit in `max_map_points`; else, with s the smallest integer that fits,
    ceil(N_k / s) points of scan k drawn without replacement by a generator seeded with k: the
    same points for any pose set, spread over every scan, and no aliasing with the scan pattern
    (a regular stride that divides the beam count would keep a few rings only, and a
    neighbourhood on a single ring is a line, far thinner than the map).
    """
    sizes = [int(n) for n in n_points_per_scan]
    stride = max(1, -(-sum(sizes) // max_map_points))
    if stride == 1:
        return 1, [np.arange(n) for n in sizes]
    return stride, [np.sort(np.random.default_rng(k).choice(n, -(-n // stride), replace=False))
                    for k, n in enumerate(sizes)]


@numba.njit(cache=True)
def _neighbourhood_moments(cell_keys, order_start, sorted_points, query_cells, queries, dims, radius_m):
    """Per query: count, sum of d and sum of d d^T (xx, xy, xz, yy, yz, zz) over the points within
    radius_m, d = point - query. Points are sorted by the key of their cell (edge radius_m), so a
    query's neighbours lie in the 27 cells around its own, each a run found by binary search."""
    n_queries = len(queries)
    moments = np.zeros((n_queries, 10))
    r2 = radius_m * radius_m
    for q in range(n_queries):
        qx, qy, qz = queries[q, 0], queries[q, 1], queries[q, 2]
        acc = moments[q]
        for cx in range(query_cells[q, 0] - 1, query_cells[q, 0] + 2):
            if cx < 0 or cx >= dims[0]:
                continue
            for cy in range(query_cells[q, 1] - 1, query_cells[q, 1] + 2):
                if cy < 0 or cy >= dims[1]:
                    continue
                for cz in range(query_cells[q, 2] - 1, query_cells[q, 2] + 2):
                    if cz < 0 or cz >= dims[2]:
                        continue
                    key = (cx * dims[1] + cy) * dims[2] + cz
                    lo = np.searchsorted(cell_keys, key)
                    if lo == len(cell_keys) or cell_keys[lo] != key:
                        continue
                    hi = order_start[lo + 1]
                    for i in range(order_start[lo], hi):
                        dx = sorted_points[i, 0] - qx
                        dy = sorted_points[i, 1] - qy
                        dz = sorted_points[i, 2] - qz
                        if dx * dx + dy * dy + dz * dz <= r2:
                            acc[0] += 1.0
                            acc[1] += dx
                            acc[2] += dy
                            acc[3] += dz
                            acc[4] += dx * dx
                            acc[5] += dx * dy
                            acc[6] += dx * dz
                            acc[7] += dy * dy
                            acc[8] += dy * dz
                            acc[9] += dz * dz
    return moments


def neighbourhood_entropy(points_world: np.ndarray, queries: np.ndarray, radius_m: float, min_neighbours: int,
                          min_sigma_m: float) -> np.ndarray:
    """(Q,) entropy (nats) of a Gaussian fit to the points within radius_m of each query point, NaN
    for a query with fewer than min_neighbours neighbours (itself included when it is a map point).

    The covariance is the maximum-likelihood one (divided by the count); its eigenvalues are
    floored at min_sigma_m^2, so a noise-free planar neighbourhood gets a finite entropy. One pass
    over a grid of cells of edge radius_m: every query sums the moments of its neighbours centred
    on itself (no cancellation far from the origin), in memory linear in the points and queries
    however dense the map (single-threaded).
    """
    points_world = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    queries = np.asarray(queries, dtype=np.float64).reshape(-1, 3)
    out = np.full(len(queries), np.nan)
    if len(points_world) == 0 or len(queries) == 0:
        return out
    origin = points_world.min(axis=0)
    cells = np.floor((points_world - origin) / radius_m).astype(np.int64)
    dims = cells.max(axis=0) + 1
    keys = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    order = np.argsort(keys, kind="stable")
    cell_keys, starts = np.unique(keys[order], return_index=True)
    order_start = np.append(starts, len(keys)).astype(np.int64)
    # queries far outside the map: clipped one cell beyond it, where they find no neighbour
    query_cells = np.clip(np.floor((queries - origin) / radius_m), -2, dims + 1).astype(np.int64)
    moments = _neighbourhood_moments(cell_keys, order_start, points_world[order], query_cells, queries, dims,
                                     float(radius_m))
    n = moments[:, 0]
    ok = n >= max(min_neighbours, 1)
    n, mean = n[ok, None], moments[ok, 1:4] / n[ok, None]
    second = moments[ok, 4:] / n
    cov = np.empty((int(ok.sum()), 3, 3))
    for slot, (a, b) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))):
        cov[:, a, b] = cov[:, b, a] = second[:, slot] - mean[:, a] * mean[:, b]
    eig = np.maximum(np.linalg.eigvalsh(cov), min_sigma_m**2)
    out[ok] = 0.5 * (3.0 * np.log(2.0 * np.pi * np.e) + np.log(eig).sum(axis=1))
    return out


def mean_map_entropy(scans_by_pose_set: dict[str, Sequence[np.ndarray]], T_by_pose_set: dict[str, np.ndarray],
                     n_points_per_scan: Sequence[int], radius_m: float, min_neighbours: int, max_map_points: int,
                     n_queries: int, min_sigma_m: float) -> dict[str, Any]:
    """The MME (nats) of each pose set on the same points (`map_subsample`) and query points (at
    most `n_queries` map points drawn without replacement by a generator seeded with 0).

    `scans_by_pose_set[name][k]`: scan k's (N_k, 3) points in its frame as that pose set sees
    them (deskewed by its trajectory; the same N_k = `n_points_per_scan[k]` points in the same
    order for every pose set; read one scan at a time, so only the subsampled map is held);
    `T_by_pose_set[name]`: (N, 4, 4) T_world_scan. A query point counts when it has at least
    `min_neighbours` neighbours under every pose set, so all are averaged over the same points.
    """
    names = list(T_by_pose_set)
    stride, kept = map_subsample(n_points_per_scan, max_map_points)
    n_map = sum(len(k) for k in kept)
    queries = np.sort(np.random.default_rng(0).choice(n_map, min(n_queries, n_map), replace=False))
    entropies = {}
    for name in names:
        scans, T = scans_by_pose_set[name], T_by_pose_set[name]
        world = np.concatenate([np.asarray(scans[k], dtype=np.float64)[index] @ T[k, :3, :3].T + T[k, :3, 3]
                                for k, index in enumerate(kept)])
        entropies[name] = neighbourhood_entropy(world, world[queries], radius_m, min_neighbours, min_sigma_m)
    valid = np.all([np.isfinite(h) for h in entropies.values()], axis=0)
    return {"radius_m": radius_m, "min_neighbours": min_neighbours, "n_map_points": int(n_map),
            "map_stride": stride, "n_query_points": int(valid.sum()),
            "mme_nats": {name: float(h[valid].mean()) if np.any(valid) else None for name, h in entropies.items()}}


def pair_ties(problem: FeatureProblem, T_world_scan: np.ndarray) -> np.ndarray:
    """(N-1,) middle eigenvalue of sum n n^T over the landmarks scans j and j+1 both observe.

    Works on the observation list (memory linear in observations, not scans x landmarks)."""
    from pa_cli.planes.associate import world_plane_stats

    normals = world_plane_stats(problem, T_world_scan)[1]
    n_scans = problem.n_scans
    keys = np.unique(problem.plane_index.astype(np.int64) * n_scans + problem.scan_index)
    scan = keys % n_scans
    shared = keys[np.isin(keys + 1, keys) & (scan < n_scans - 1)]  # (landmark, j) also seen by j + 1
    M = np.zeros((max(n_scans - 1, 0), 3, 3))
    n = normals[shared // n_scans]
    np.add.at(M, shared % n_scans, n[:, :, None] * n[:, None, :])
    return np.linalg.eigvalsh(M)[:, 1]


def _pairs(indices: np.ndarray) -> list[list[int]]:
    return [[int(j), int(j) + 1] for j in indices]


def _list(pairs: list[list[int]], limit: int = 8) -> str:
    text = ", ".join(f"{a}-{b}" for a, b in pairs[:limit])
    return text + (" ..." if len(pairs) > limit else "")


def assess(rms: dict[str, dict[str, float]], odometry_sigmas: np.ndarray | None, ties: np.ndarray,
           settled: bool, outlier_sigma: float, min_tie: float, rms_tolerance: float,
           entropy: dict[str, Any] | None = None, entropy_tolerance_nats: float = 0.0) -> dict[str, Any]:
    """The `quality` report section.

    `rms[association][pose_set]` (m) for associations `planes_at_initial_poses`,
    `planes_at_refined_poses` and pose sets `initial`, `refined`; `odometry_sigmas` (N-1, 2):
    the change of each pair's relative rotation and translation in odometry sigmas (None: no
    factors); `ties` (N-1,): `pair_ties` of consecutive scans; `entropy`: `mean_map_entropy` of
    the pose sets `initial` and `refined` (None: not measured).
    """
    reasons: list[str] = []
    worse = [a for a, r in rms.items() if r["refined"] > r["initial"] * (1.0 + rms_tolerance)]
    not_better = [a for a, r in rms.items() if not r["refined"] < r["initial"]]
    for a in not_better:
        r = rms[a]
        reasons.append(f"RMS point-to-plane on the {a.replace('_', ' ')} is {r['refined']:.4f} m refined "
                       f"against {r['initial']:.4f} m initial: the refined map is not sharper there")
    mme = None if entropy is None else entropy["mme_nats"]
    if mme is not None and (mme["initial"] is None or mme["refined"] is None):
        mme = None  # no query point had enough neighbours: not measured
    if mme is not None:
        if mme["refined"] > mme["initial"] + entropy_tolerance_nats:
            worse.append("mean map entropy")
        if not mme["refined"] < mme["initial"]:
            reasons.append(f"mean map entropy ({entropy['radius_m']:g} m radius) is {mme['refined']:.4f} nats refined "
                           f"against {mme['initial']:.4f} initial: the refined map is not sharper by this measure")
    disagree: list[list[int]] = []
    worst = None
    if odometry_sigmas is not None and len(odometry_sigmas):
        beyond = np.flatnonzero(odometry_sigmas.max(axis=1) > outlier_sigma)
        disagree = _pairs(beyond)
        worst = float(odometry_sigmas.max())
        if len(beyond):
            reasons.append(f"{len(beyond)} consecutive pair(s) changed their relative motion by more than "
                           f"{outlier_sigma:g} odometry sigmas (up to {worst:.1f}; pairs {_list(disagree)}): "
                           "the odometry or the refinement is wrong there")
    weak = np.flatnonzero(ties < min_tie)
    untied = _pairs(weak)
    if len(weak):
        reasons.append(f"{len(weak)} consecutive pair(s) share planes of one orientation only (pairs "
                       f"{_list(untied)}): the map does not tie them, their relative heading and sliding along "
                       "those planes rest on the odometry alone (a break there would go unseen)")
    if not settled:
        reasons.append("the rounds did not settle: the last round still moved a pose more than the tolerance")
    if worse:
        verdict = "degraded"
    elif reasons:
        verdict = "uncertain"
    else:
        verdict = "improved"
        reasons.append("the refined poses give a sharper map on planes found at the initial and at the refined "
                       "poses" + (" and by mean map entropy" if mme is not None else "") +
                       ", agree with the odometry within its model, and the rounds settled")
    return {
        "verdict": verdict,
        "reasons": reasons,
        "rms_point_to_plane_m": rms,
        "map_entropy": entropy,
        "odometry_outlier_sigma": outlier_sigma,
        "pairs_beyond_odometry_sigma": disagree,
        "n_scans_beyond_odometry_sigma": len({j for pair in disagree for j in pair}),
        "max_odometry_change_sigma": worst,
        "min_pair_tie": float(ties.min()) if len(ties) else None,
        "pairs_not_tied_by_planes": untied,
        "settled": bool(settled),
    }


def verdict_warning(quality: dict[str, Any] | None) -> str | None:
    """The end-of-run warning for a verdict other than `improved` (None when improved or absent)."""
    if not quality or quality["verdict"] == "improved":
        return None
    lines = [f"WARNING: quality verdict '{quality['verdict'].upper()}' - do not trust the refined poses blindly:"]
    lines += [f"  - {reason}" for reason in quality["reasons"]]
    lines.append("  (see 'quality' in the report; --strict turns this into exit code 1)")
    return "\n".join(lines)
