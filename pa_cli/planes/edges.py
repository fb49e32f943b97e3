"""Edge (line) landmarks: line-like voxels grown along their direction, associated by point-to-line distance.

1. **Voxels.** The scans are moved to the world frame at the given poses and hashed into voxels
   of `voxel_size_m`; each voxel keeps its point cluster (all scans together). A voxel is
   line-like with at least `min_points` points, lambda_mid / lambda_max <= `max_mid_ratio` (one
   long axis), lambda_min / lambda_mid >= `min_round_ratio` (a round cross-section, not a plane
   strip) and RMS distance to its line sqrt((lambda_min + lambda_mid) / N) <= `max_thickness_m`.
2. **Growing.** Touching line voxels (26-neighbourhood) are joined when their directions differ
   by at most `max_direction_angle_deg` and each centroid lies within `max_line_distance_m` of the
   other's line; a component is one landmark, refit on its summed cluster, kept when it is still
   line-like and at least `min_length_m` long.
3. **Association.** A second pass gives one cluster (scan frame) per (landmark, scan): the points
   in the landmark's voxels and their neighbours that lie within `max_point_distance_m` of its line
   and within its extent, spanning at least `min_elevation_spread_deg` of elevation seen from the
   sensor (more than one beam's scan line), with at least `min_points_per_observation` points.
   Landmarks that do not stand free (more than `max_clearance_fraction` of their points again
   between `max_point_distance_m` and `clearance_m` from the line: surfaces running away from it)
   and landmarks seen by fewer than two scans are dropped (`make_problem`). Each observation is
   moved away from its sensor by the offset of a pole's near half (`view_shifts`).

The result is a feature problem of edges (`feature_kind` = `FEATURE_EDGE`); `merge_problems`
joins it to the plane problem. `EdgeLabels` keeps the association per point, so the rounds freeze
the edges with the planes: a frozen round re-sums the same points (re-deskewed) on the same lines.
Diagnostics: number of edges, observations, points and the RMS point-to-line distance (thickness)
of the landmarks.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pa_cli.config import EdgesConfig
from pa_cli.core.clusters import clusters_from_moments, scatter, sum_by_feature, transform_clusters
from pa_cli.core.geometry import transform_points
from pa_cli.core.point_moments import clusters_by_label, moments_by_label
from pa_cli.core.problem import FEATURE_EDGE, FeatureProblem, make_problem
from pa_cli.core.voxels import decode_keys, encode_keys, voxel_keys
from pa_cli.planes.labels import PointLabels
from pa_cli.runtime.distributed import in_order

CONFIG_KEY = "advanced.edges.voxel_size_m"
# per-scan voxel moments held before they are merged into the running sums, at least (`voxel_clusters`)
MIN_PENDING_VOXELS = 1 << 20
NEIGHBOUR_OFFSETS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)])


@dataclass
class EdgeLandmarks:
    """Detected lines (world frame): centroid (L, 3) m, unit direction (L, 3), extent along the
    direction from the centroid (L, 2) m, and the voxel keys (V,) with their landmark (V,)."""

    centroid_world: np.ndarray
    direction_world: np.ndarray
    extent_m: np.ndarray
    voxel_key: np.ndarray
    voxel_landmark: np.ndarray

    @property
    def n_landmarks(self) -> int:
        return len(self.centroid_world)


@dataclass(frozen=True)
class EdgeLabels:
    """An edge association kept fixed while the points or poses change (as `PointLabels` keeps the
    planes'): the points of each scan on an edge (`point_index`, per scan an int32 array of point indices,
    ascending: few, so only they are held) and the edge observation of each (`labels`, over those points,
    observations in the edge problem's order), each observation's view correction (`shift_scan_m` (O, 3), m,
    scan frame: `view_shifts`) and the number of lines detected."""

    labels: PointLabels
    point_index: list[np.ndarray]
    shift_scan_m: np.ndarray
    n_detected: int

    def problem(self, scans: Sequence[np.ndarray]) -> FeatureProblem:
        """The edge problem of this association on `scans` (the points it was made on, or others of the
        same scans, e.g. re-deskewed), each observation shifted by its view correction, with range clusters
        (the covariance's range model: the shifted points weighted by 1/|p|^2 of the points as measured)."""
        on_edges = [np.asarray(points)[index] for points, index in zip(scans, self.point_index, strict=True)]
        points = self.labels.problem(on_edges, with_range=True)
        shift = np.repeat(np.eye(4)[None], len(self.shift_scan_m), axis=0)
        shift[:, :3, 3] = self.shift_scan_m
        n_edges = int(self.labels.plane_index.max()) + 1 if len(self.labels.plane_index) else 0
        return make_problem(self.labels.plane_index, self.labels.scan_index, transform_clusters(points.clusters, shift),
                            n_scans=self.labels.n_scans, source="edge association",
                            feature_kind=np.full(n_edges, FEATURE_EDGE, np.uint8),
                            range_clusters=transform_clusters(points.range_clusters, shift))


def voxel_clusters(scans: Sequence[np.ndarray], T_world_scan: np.ndarray, voxel_size_m: float, threads: int = 1
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Voxel keys (V,) ascending and their world point clusters (V, 4, 4), all scans together. Each scan's
    per-voxel moments are summed on one of `threads` threads; they are merged into the running sums in scan
    order whenever they outnumber them (`_merged`), so memory follows the voxels of the map, not those of
    every scan; every voxel's moments are summed in scan order either way, to the same bits."""
    def scan_sums(j: int) -> tuple[np.ndarray, np.ndarray]:
        points_world = transform_points(T_world_scan[j], scans[j])
        keys, inverse = np.unique(voxel_keys(points_world, voxel_size_m, CONFIG_KEY), return_inverse=True)
        return keys, moments_by_label(inverse.ravel(), points_world, len(keys))

    keys_total, sums_total = np.empty(0, np.int64), np.empty((0, 10))
    keys_pending, sums_pending, n_pending = [], [], 0
    for keys, sums in in_order(scan_sums, len(scans), threads):
        keys_pending.append(keys)
        sums_pending.append(sums)
        n_pending += len(keys)
        if n_pending > max(len(keys_total), MIN_PENDING_VOXELS):
            keys_total, sums_total = _merged([keys_total, *keys_pending], [sums_total, *sums_pending])
            keys_pending, sums_pending, n_pending = [], [], 0
    keys, total = _merged([keys_total, *keys_pending], [sums_total, *sums_pending])
    return keys, clusters_from_moments(total)


def _merged(keys: list[np.ndarray], sums: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The distinct keys (ascending) of the key arrays and their summed moments (10 per key), each key's
    in the order of the arrays (bincount adds in index order)."""
    distinct, inverse = np.unique(np.concatenate(keys), return_inverse=True)
    stacked = np.concatenate(sums)
    return distinct, np.stack([np.bincount(inverse.ravel(), stacked[:, c], minlength=len(distinct))
                               for c in range(10)], axis=1)


def line_fit(clusters: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Scatter eigenvalues (K, 3) ascending (m^2, clamped at 0), directions (K, 3), centroids
    (K, 3) m and counts (K,) of clusters (K, 4, 4)."""
    S, centroid, count = scatter(clusters)
    lam, vec = np.linalg.eigh(S)
    return np.maximum(lam, 0.0), vec[:, :, 2], centroid, count


def is_line(lam: np.ndarray, count: np.ndarray, config: EdgesConfig) -> np.ndarray:
    """Line-like clusters (see the module docstring) from eigenvalues (K, 3) and counts (K,)."""
    big = np.maximum(lam[:, 2], 1e-300)
    mid = np.maximum(lam[:, 1], 1e-300)
    thickness = np.sqrt((lam[:, 0] + lam[:, 1]) / np.maximum(count, 1))
    return ((count >= config.min_points) & (lam[:, 1] / big <= config.max_mid_ratio)
            & (lam[:, 0] / mid >= config.min_round_ratio) & (thickness <= config.max_thickness_m))


def _distance_to_line(points: np.ndarray, centroid: np.ndarray, direction: np.ndarray) -> np.ndarray:
    d = points - centroid
    return np.linalg.norm(d - np.einsum("ki,ki->k", d, direction)[:, None] * direction, axis=1)


def _components(n: int, pairs: np.ndarray) -> np.ndarray:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def detect_edges(scans: Sequence[np.ndarray], T_world_scan: np.ndarray, config: EdgesConfig,
                 threads: int = 1) -> EdgeLandmarks:
    """Edge landmarks from scans ((M, 3) scan-frame points, m) at T_world_scan (N, 4, 4): one pass (the scans on
    `threads` threads)."""
    keys, clusters = voxel_clusters(scans, T_world_scan, config.voxel_size_m, threads)
    lam, direction, centroid, count = line_fit(clusters)
    line = np.flatnonzero(is_line(lam, count, config))
    keys, clusters, direction, centroid = keys[line], clusters[line], direction[line], centroid[line]
    if not len(keys):
        return EdgeLandmarks(np.empty((0, 3)), np.empty((0, 3)), np.empty((0, 2)), keys, np.empty(0, np.int64))
    coords = decode_keys(keys)
    pairs = []
    for offset in NEIGHBOUR_OFFSETS[14:]:  # 13 of the 26 neighbours (13 is the voxel itself): each pair once
        target = encode_keys(coords + offset, config.voxel_size_m, CONFIG_KEY)
        other = np.minimum(np.searchsorted(keys, target), len(keys) - 1)
        hit = np.flatnonzero(keys[other] == target)
        pairs.append(np.column_stack([hit, other[hit]]))
    pairs = np.concatenate(pairs)
    a, b = pairs[:, 0], pairs[:, 1]
    cos_angle = np.abs(np.einsum("ki,ki->k", direction[a], direction[b]))
    agree = ((cos_angle >= np.cos(np.deg2rad(config.max_direction_angle_deg)))
             & (_distance_to_line(centroid[b], centroid[a], direction[a]) <= config.max_line_distance_m)
             & (_distance_to_line(centroid[a], centroid[b], direction[b]) <= config.max_line_distance_m))
    component = _components(len(keys), pairs[agree])
    n_comp = int(component.max()) + 1
    merged = sum_by_feature(clusters, component, n_comp)
    lam_c, dir_c, cen_c, count_c = line_fit(merged)
    along = np.einsum("ki,ki->k", centroid - cen_c[component], dir_c[component])
    lo = np.full(n_comp, np.inf)
    hi = np.full(n_comp, -np.inf)
    np.minimum.at(lo, component, along - 0.5 * config.voxel_size_m)
    np.maximum.at(hi, component, along + 0.5 * config.voxel_size_m)
    keep = is_line(lam_c, count_c, config) & (hi - lo >= config.min_length_m)
    new_id = np.full(n_comp, -1)
    new_id[keep] = np.arange(int(keep.sum()))
    voxel_landmark = new_id[component]
    in_landmark = voxel_landmark >= 0
    return EdgeLandmarks(cen_c[keep], dir_c[keep], np.column_stack([lo, hi])[keep], keys[in_landmark],
                         voxel_landmark[in_landmark])


def _dilated(landmarks: EdgeLandmarks, voxel_size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Voxel keys (ascending, unique) of the landmarks' voxels and their neighbours, and the landmark
    of each (a voxel next to two landmarks goes to the lower landmark index)."""
    coords = decode_keys(landmarks.voxel_key)
    keys = np.concatenate([encode_keys(coords + off, voxel_size_m, CONFIG_KEY) for off in NEIGHBOUR_OFFSETS])
    owner = np.tile(landmarks.voxel_landmark, len(NEIGHBOUR_OFFSETS))
    order = np.lexsort((owner, keys))
    keys, owner = keys[order], owner[order]
    first = np.r_[True, keys[1:] != keys[:-1]] if len(keys) else np.empty(0, bool)
    return keys[first], owner[first]


def _free_standing(core: np.ndarray, surround: np.ndarray, config: EdgesConfig) -> np.ndarray:
    """(L,) landmarks whose surroundings are clear (see `associate_edges`), from the point counts of
    all scans within `max_point_distance_m` (core) and in the clearance annulus (surround)."""
    return surround <= config.max_clearance_fraction * core


def _single_beam(points_scan: np.ndarray, label: np.ndarray, n_landmarks: int, min_spread_rad: float) -> np.ndarray:
    """(M,) points whose landmark this scan sees within less than `min_spread_rad` of elevation
    (as seen from the sensor, the scan-frame origin): one beam's scan line across a surface, which
    looks like a line in one scan wherever the surface is, not a line in the world."""
    on = np.flatnonzero(label >= 0)
    elevation = np.arctan2(points_scan[on, 2], np.hypot(points_scan[on, 0], points_scan[on, 1]))
    lo = np.full(n_landmarks, np.inf)
    hi = np.full(n_landmarks, -np.inf)
    np.minimum.at(lo, label[on], elevation)
    np.maximum.at(hi, label[on], elevation)
    out = np.zeros(len(label), bool)
    out[on] = (hi - lo)[label[on]] < min_spread_rad
    return out


def associate_edges(scans: Sequence[np.ndarray], T_world_scan: np.ndarray, landmarks: EdgeLandmarks,
                    config: EdgesConfig, threads: int = 1) -> tuple[FeatureProblem, EdgeLabels]:
    """The edge problem: one scan-frame cluster per (landmark, scan) (see the module docstring), and the
    association that made it (`EdgeLabels`).

    Only free-standing lines are kept: over the middle of a landmark's extent (`clearance_m` in
    from each end, at most a quarter of its length, so the ground at a pole's foot is not counted),
    the points of all scans between `max_point_distance_m` and `clearance_m` (at most one voxel)
    from its line may number at most `max_clearance_fraction` of those within
    `max_point_distance_m`. A line with surfaces running away from it (the corner of two walls, a
    kerb, the rim of a slab or a car body, one side of a thick trunk) is seen differently from
    every viewpoint: the centroid of its visible points moves with the sensor and would pull the
    poses; those surfaces belong to the planes. The scans are read and labelled on `threads` threads, their counts and
    clusters gathered in scan order.
    """
    keys, owner = _dilated(landmarks, config.voxel_size_m)
    clearance_m = min(config.clearance_m, config.voxel_size_m)
    length_m = landmarks.extent_m[:, 1] - landmarks.extent_m[:, 0]
    margin_m = np.minimum(clearance_m, 0.25 * length_m)

    def observe(j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Scan j's points near each landmark's line (core) and in its clearance (surround), its observations'
        landmarks and clusters, and its points on an edge with their landmarks."""
        points = scans[j]
        world = transform_points(T_world_scan[j], points)
        k = voxel_keys(world, config.voxel_size_m, CONFIG_KEY)
        slot = np.minimum(np.searchsorted(keys, k), len(keys) - 1)
        label = np.where(keys[slot] == k, owner[slot], -1)
        cand = np.flatnonzero(label >= 0)
        lm = label[cand]
        d = world[cand] - landmarks.centroid_world[lm]
        along = np.einsum("ki,ki->k", d, landmarks.direction_world[lm])
        dist = np.linalg.norm(d - along[:, None] * landmarks.direction_world[lm], axis=1)
        inside = (along >= landmarks.extent_m[lm, 0]) & (along <= landmarks.extent_m[lm, 1])
        ok = inside & (dist <= config.max_point_distance_m)
        middle = ((along >= landmarks.extent_m[lm, 0] + margin_m[lm])
                  & (along <= landmarks.extent_m[lm, 1] - margin_m[lm]))
        core_j = np.bincount(lm[middle & ok], minlength=landmarks.n_landmarks)
        surround_j = np.bincount(lm[middle & ~ok & (dist <= clearance_m)], minlength=landmarks.n_landmarks)
        label[cand[~ok]] = -1
        label[_single_beam(points, label, landmarks.n_landmarks, np.deg2rad(config.min_elevation_spread_deg))] = -1
        ids, c = clusters_by_label(points, label, config.min_points_per_observation)
        on_edge = np.flatnonzero(label >= 0)
        return core_j, surround_j, ids, c, on_edge.astype(np.int32), label[on_edge]

    core = np.zeros(landmarks.n_landmarks)
    surround = np.zeros(landmarks.n_landmarks)
    feature, scan, clusters, point_index, landmark_of_point = [], [], [], [], []
    if not len(keys):  # no landmark: no scan is read
        point_index = [np.empty(0, np.int32) for _ in range(len(scans))]
        landmark_of_point = [np.empty(0, np.int64) for _ in range(len(scans))]
    observed = in_order(observe, len(scans) if len(keys) else 0, threads)
    for j, (core_j, surround_j, ids, c, on_edge, on_edge_landmark) in enumerate(observed):
        core += core_j
        surround += surround_j
        feature.append(ids)
        scan.append(np.full(len(ids), j))
        clusters.append(c)
        point_index.append(on_edge)
        landmark_of_point.append(on_edge_landmark)
    feature_index = np.concatenate(feature) if feature else np.empty(0, np.int64)
    scan_index = np.concatenate(scan) if scan else np.empty(0, np.int64)
    all_clusters = np.concatenate(clusters) if clusters else np.empty((0, 4, 4))
    # the free-standing observations of landmarks seen by two scans or more, by (landmark, scan): the
    # order and numbering `make_problem` keeps, so the shifts and labels follow the problem's observations
    kept = _free_standing(core, surround, config)[feature_index]
    kept &= (np.bincount(feature_index[kept], minlength=landmarks.n_landmarks) >= 2)[feature_index]
    order = np.flatnonzero(kept)[np.lexsort((scan_index[kept], feature_index[kept]))]
    feature_index, scan_index = feature_index[order], scan_index[order]
    direction_scan = np.einsum("oji,oj->oi", T_world_scan[scan_index, :3, :3],
                               landmarks.direction_world[feature_index])
    shift_scan_m = view_shifts(all_clusters[order], direction_scan, feature_index, landmarks.n_landmarks)
    found = make_problem(feature_index, scan_index, all_clusters[order], n_scans=len(T_world_scan),
                         source="edge problem", feature_kind=np.full(landmarks.n_landmarks, FEATURE_EDGE, np.uint8))
    labels = PointLabels.from_association(landmark_of_point, landmarks.n_landmarks, np.unique(feature_index), found)
    kept = [obs >= 0 for obs in labels.observation_of_point]  # the points of the observations kept
    labels = PointLabels(labels.plane_index, labels.scan_index, labels.n_scans,
                         [obs[k] for obs, k in zip(labels.observation_of_point, kept, strict=True)])
    edges = EdgeLabels(labels, [index[k] for index, k in zip(point_index, kept, strict=True)], shift_scan_m,
                       landmarks.n_landmarks)
    return edges.problem(scans), edges


def view_shifts(clusters_scan: np.ndarray, direction_scan: np.ndarray, feature_index: np.ndarray,
                n_features: int) -> np.ndarray:
    """(O, 3) scan-frame shifts (m) that move the observation clusters (O, 4, 4, scan frame) away from
    the sensor by the offset of a round line seen from one side.

    A scan sees the near half of a pole of radius r: rays evenly spread across it hit at lateral
    offsets u uniform in [-r, r] and depth sqrt(r^2 - u^2) in front of the axis, so the centroid of
    its points lies (pi/4) r in front of the axis, towards the sensor, and moves round the pole with
    the viewpoint; fitted as they are, the points of all scans pull the poses towards each other by
    up to twice that. The lateral spread of the points is r^2 / 3, so r = sqrt(3 s), s = the variance
    of all observations of the line across the line and the viewing ray (the scan frame's origin to
    the observation's centroid). Each observation is shifted by (pi/4) r along that ray, across the
    line (`direction_scan` (O, 3), the line's unit direction in the scan frame). A thin line has
    r ~ 0 and is not moved.
    """
    S, centroid, count = scatter(clusters_scan)
    toward_line = centroid - np.einsum("oi,oi->o", centroid, direction_scan)[:, None] * direction_scan
    toward_line /= np.maximum(np.linalg.norm(toward_line, axis=1, keepdims=True), 1e-12)
    lateral = np.cross(direction_scan, toward_line)
    spread = np.einsum("oi,oij,oj->o", lateral, S, lateral)  # m^2, summed over the observation's points
    radius_m = np.sqrt(3.0 * np.bincount(feature_index, spread, n_features)
                       / np.maximum(np.bincount(feature_index, count, n_features), 1.0))
    return (0.25 * np.pi * radius_m[feature_index])[:, None] * toward_line


def edge_diagnostics(problem: FeatureProblem, T_world_scan: np.ndarray, n_detected: int) -> dict:
    """Number of edges (detected, kept), observations, points and the RMS point-to-line distance (m)."""
    world = transform_clusters(problem.clusters, T_world_scan[problem.scan_index])
    lam, _, _, count = line_fit(sum_by_feature(world, problem.plane_index, problem.n_planes))
    cost = lam[:, 0] + lam[:, 1]
    thickness = np.sqrt(cost / np.maximum(count, 1))
    return {"n_edges_detected": int(n_detected), "n_edges": int(problem.n_planes),
            "n_edge_observations": int(problem.n_observations), "n_edge_points": int(problem.n_points),
            "edge_rms_point_to_line_m": float(np.sqrt(cost.sum() / max(count.sum(), 1))),
            "edge_thickness_rms_m": {"median": float(np.median(thickness)) if len(thickness) else None,
                                     "max": float(thickness.max()) if len(thickness) else None}}


def build_edge_problem(scans: Sequence[np.ndarray], T_world_scan: np.ndarray, config: EdgesConfig
                       ) -> tuple[FeatureProblem, dict]:
    """Edge problem and diagnostics from scans at T_world_scan; each scan is read twice."""
    landmarks = detect_edges(scans, T_world_scan, config)
    problem, _ = associate_edges(scans, T_world_scan, landmarks, config)
    return problem, edge_diagnostics(problem, T_world_scan, landmarks.n_landmarks)


def merge_problems(planes: FeatureProblem, edges: FeatureProblem) -> FeatureProblem:
    """One problem with the features of both (edges numbered after the planes), with range clusters when
    both have them."""
    kinds = np.concatenate([planes.feature_kind, edges.feature_kind])
    with_range = planes.range_clusters is not None and edges.range_clusters is not None
    return make_problem(np.concatenate([planes.plane_index, edges.plane_index + planes.n_planes]),
                        np.concatenate([planes.scan_index, edges.scan_index]),
                        np.concatenate([planes.clusters, edges.clusters]), n_scans=planes.n_scans,
                        T_world_scan=planes.T_world_scan, source="plane and edge problem", feature_kind=kinds,
                        range_clusters=np.concatenate([planes.range_clusters, edges.range_clusters]) if with_range
                        else None)


def translation_constraints(problem: FeatureProblem, T_world_scan: np.ndarray) -> np.ndarray:
    """(N, 3, 3) per scan: the sum over the features it observes of the translation directions
    each one fixes, n n^T for a plane (its normal) and I - d d^T for an edge (across its direction
    d), world frame. Its smallest eigenvalue is the weakest direction's count of features."""
    M = np.asarray(T_world_scan, dtype=np.float64)[problem.scan_index]
    first = np.searchsorted(problem.plane_index, np.arange(problem.n_planes))
    M[:, :3, 3] -= T_world_scan[problem.scan_index[first], :3, 3][problem.plane_index]  # near each feature
    S = scatter(sum_by_feature(transform_clusters(problem.clusters, M), problem.plane_index, problem.n_planes))[0]
    vec = np.linalg.eigh(S)[1]
    normal, direction = vec[:, :, 0], vec[:, :, 2]
    fixed = np.where((problem.feature_kind == FEATURE_EDGE)[:, None, None],
                     np.eye(3) - direction[:, :, None] * direction[:, None, :], normal[:, :, None] * normal[:, None, :])
    out = np.zeros((problem.n_scans, 3, 3))
    np.add.at(out, problem.scan_index, fixed[problem.plane_index])
    return out


def with_edges(planes: FeatureProblem, diagnostics: dict, scans: Sequence[np.ndarray], T_world_scan: np.ndarray,
               config: EdgesConfig | None, min_constraint_eigenvalue: float, frozen: EdgeLabels | None = None,
               threads: int = 1) -> tuple[FeatureProblem, EdgeLabels | None]:
    """The plane problem joined by the edges found at T_world_scan with `config` (`PaConfig.edges_config()`),
    or with `frozen` those of that association on `scans`, and the edge association used; the plane problem
    unchanged and None when `config` is None (scene.edges off). With edges, their diagnostics go
    to `diagnostics["edges"]` and the per-scan constraint report counts them too:
    `constraint_eigenvalue_per_scan` (smallest eigenvalue of `translation_constraints`) and
    `poorly_constrained_scans` (below `min_constraint_eigenvalue`); the planes-only list moves to
    `diagnostics["edges"]["poorly_constrained_scans_planes_only"]`. The passes over the scans run on `threads`
    threads."""
    if config is None:
        return planes, None
    if frozen is None:
        landmarks = detect_edges(scans, T_world_scan, config, threads)
        edges, frozen = associate_edges(scans, T_world_scan, landmarks, config, threads)
    else:
        edges = frozen.problem(scans)
    diagnostics["edges"] = edge_diagnostics(edges, T_world_scan, frozen.n_detected)
    if not edges.n_observations:
        return planes, frozen
    merged = merge_problems(planes, edges)
    lam = np.linalg.eigvalsh(translation_constraints(merged, T_world_scan))[:, 0]
    diagnostics["edges"]["poorly_constrained_scans_planes_only"] = diagnostics.get("poorly_constrained_scans", [])
    diagnostics["constraint_eigenvalue_per_scan"] = [round(float(x), 4) for x in lam]
    diagnostics["poorly_constrained_scans"] = [int(j) for j in np.flatnonzero(lam < min_constraint_eigenvalue)]
    return merged, frozen


def edges_hold_weak_scans(diagnostics: dict) -> bool:
    """Whether the edges leave fewer scans poorly constrained than the planes alone (the diagnostics of a
    `with_edges` call with edges on; no edge observation leaves the planes' count)."""
    with_lines = diagnostics.get("poorly_constrained_scans", [])
    return len(with_lines) < len(diagnostics["edges"].get("poorly_constrained_scans_planes_only", with_lines))
