"""The loop stage: candidates, verification and the pose graph, from odometry to loop-closed poses.

1. Local maps (`local_maps`) of about `local_map_length_m` of path each, under the odometry.
2. Candidates: for each local map in turn, the earlier local maps at least
   `min_separation_m` (loops.min_separation_m) of path before it whose polar descriptors are nearest
   (`candidates_per_query`, distance below `max_descriptor_distance`).
3. Verification, per candidate: initial alignment from the descriptor's yaw and a bird's-eye
   correlation, GICP registration, then the gates in order:
   - registration: converged, `min_overlap`, `min_fitness`;
   - drift: the correction the closure makes to the current estimate of the two local maps'
     relative pose must be one the odometry can have drifted by along the shortest path between
     them (consecutive local maps plus the closures accepted so far, a closure counting as
     loop_translation_sigma_m / max_drift_fraction of path): `max_drift_fraction` x path +
     `drift_floor_m`, and likewise for the rotation. A look-alike place one block away needs a
     correction of a block, which a short path cannot explain;
   - ambiguity: when one local map verifies against two references whose registrations disagree
     about the references' relative pose (by more than the same drift bound between them), the
     place is ambiguous (repeated structure) and all its closures are rejected.
   The candidates do not depend on the closures accepted, so every local map's registrations run
   first, as one task per local map on the current execution (dask workers with --workers); the
   gates then examine the local maps in order. Accepted closures are added to a pose graph over
   the local maps, which is re-solved before the next local map is examined (unless the closures
   agree with it within the loop edges' kernel), so later gates measure against the loop-closed
   estimate.
4. The final pose graph over all scans: odometry edges between consecutive scans plus the loop
   edges between anchor scans (Cauchy kernel), initialised from the local-map solution.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from pa_cli.config import LoopClosureConfig
from pa_cli.loops.descriptors import (
    DescriptorSpectra,
    descriptor_spectra,
    initial_alignment,
    polar_descriptor,
    spectra_distances,
    yaw_of_shift,
)
from pa_cli.loops.local_maps import LocalMap, build_local_maps, path_lengths_m
from pa_cli.loops.pose_graph import Edge, odometry_edges, optimize_pose_graph
from pa_cli.loops.verification import Registration, prepare_local_map, register_local_maps
from pa_cli.runtime.distributed import current_execution

Progress = Callable[[int, int], None]
# Memory of one registration task per local-map point it holds (bytes): the points (24 B) sent to the worker, and
# there small_gicp's clouds at two voxel sizes (a 4-vector point and a 4 x 4 covariance each, 160 B) and trees.
REGISTRATION_BYTES_PER_POINT = 300


@dataclass
class Candidate:
    """One loop candidate (a query local map against an earlier reference) and its verdict."""

    query_map: int
    ref_map: int
    query_scan: int  # anchor scans: the loop edge joins these two scans
    ref_scan: int
    descriptor_distance: float
    yaw_deg: float  # the descriptor's yaw of the query relative to the reference
    fitness: float | None = None
    overlap: float | None = None
    rmse_m: float | None = None
    path_between_m: float | None = None  # shortest path between the two local maps when examined
    correction_m: float | None = None
    correction_deg: float | None = None
    drift_bound_m: float | None = None
    drift_bound_deg: float | None = None
    accepted: bool = False
    reason: str = ""


@dataclass
class LoopResult:
    """Loop-closed poses and the record of every candidate."""

    T_world_scan: np.ndarray  # (N, 4, 4)
    candidates: list[Candidate]
    local_maps: list[LocalMap]
    loop_edges: list[Edge]  # the accepted closures, between anchor scans
    graph: dict[str, Any]

    def report(self) -> dict[str, Any]:
        """The `loops` section of the refine report."""
        accepted = [c for c in self.candidates if c.accepted]
        return {"n_local_maps": len(self.local_maps), "n_candidates": len(self.candidates),
                "n_closures": len(accepted),
                "closures": [[c.ref_scan, c.query_scan] for c in accepted],
                "candidates": [asdict(c) for c in self.candidates], "pose_graph": self.graph}


def _angle_rad(R: np.ndarray) -> float:
    return float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))


class _MapGraph:
    """The pose graph over local-map anchors, re-solved as closures are accepted."""

    def __init__(self, maps: list[LocalMap], T_world_scan: np.ndarray, cfg: LoopClosureConfig) -> None:
        self.cfg = cfg
        self.path_m = np.array([m.path_m for m in maps])
        self.T_odometry = T_world_scan[[m.anchor for m in maps]]
        self.T_world_map = self.T_odometry.copy()
        self.odometry = odometry_edges(self.T_odometry, self.path_m, cfg.odometry_translation_sigma_m,
                                       np.deg2rad(cfg.odometry_rotation_sigma_deg), cfg.odometry_min_step_m)
        self.loops: list[Edge] = []
        self.closure_path_m = cfg.loop_translation_sigma_m / cfg.max_drift_fraction

    def path_from(self, source: int, q: int) -> np.ndarray:
        """Shortest path (m) from local map `source` to each local map up to q, along odometry and closures."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import dijkstra

        n = q + 1
        rows = list(range(q)) + [e.i for e in self.loops]
        cols = list(range(1, n)) + [e.j for e in self.loops]
        weights = list(np.maximum(np.diff(self.path_m[:n]), self.cfg.odometry_min_step_m))
        weights += [self.closure_path_m] * len(self.loops)
        graph = coo_matrix((weights, (rows, cols)), shape=(n, n)).tocsr()
        return dijkstra(graph, directed=False, indices=source)

    def drift_bounds(self, path_m: float) -> tuple[float, float]:
        cfg = self.cfg
        return (cfg.max_drift_fraction * path_m + cfg.drift_floor_m,
                cfg.max_drift_deg_per_m * path_m + cfg.drift_floor_deg)

    def add_loops(self, edges: list[Edge], correction_m: float, correction_deg: float) -> None:
        """Add verified loop edges, whose largest correction to the current estimate is `correction_m` /
        `correction_deg`; re-solve the graph unless that is within the loop edges' kernel (robust_kernel_sigmas loop
        sigmas): such closures agree with the estimate, a re-solve would move it by less, far below the drift bounds
        the gates compare with (metres)."""
        self.loops += edges
        cfg = self.cfg
        if (correction_m > cfg.robust_kernel_sigmas * cfg.loop_translation_sigma_m
                or correction_deg > cfg.robust_kernel_sigmas * cfg.loop_rotation_sigma_deg):
            self.T_world_map, _ = optimize_pose_graph(self.T_world_map, self.odometry + self.loops,
                                                      cfg.robust_kernel_sigmas)


def _correction(T_expected: np.ndarray, T_measured: np.ndarray) -> tuple[float, float]:
    D = np.linalg.inv(T_expected) @ T_measured
    return float(np.linalg.norm(D[:3, 3])), float(np.degrees(_angle_rad(D[:3, :3])))


@dataclass
class _Places:
    """The descriptor database: the query descriptor of each local map (at its anchor) and the
    reference descriptors at viewpoints every `descriptor_spacing_m` along each local map."""

    query: np.ndarray  # (M, R, S)
    view: DescriptorSpectra  # of V descriptors, in local-map order
    view_map: np.ndarray  # (V,) local map of each viewpoint, non-decreasing
    T_anchor_view: np.ndarray  # (V, 4, 4)

    @classmethod
    def build(cls, maps: list[LocalMap], cfg: LoopClosureConfig) -> _Places:
        def describe(points: np.ndarray) -> np.ndarray:
            return polar_descriptor(points, cfg.descriptor_range_m, cfg.descriptor_rings, cfg.descriptor_sectors)

        query, view, view_map, T_views = [], [], [], []
        for i, m in enumerate(maps):
            query.append(describe(m.points_anchor))
            position = m.T_anchor_scan[:, :3, 3]
            along_m = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(position, axis=0), axis=1))]
            ticks = np.arange(along_m[0], along_m[-1] + cfg.descriptor_spacing_m / 2, cfg.descriptor_spacing_m)
            for k in np.unique(np.searchsorted(along_m, ticks).clip(0, len(along_m) - 1)):
                T = m.T_anchor_scan[k]
                view.append(describe((m.points_anchor - T[:3, 3]) @ T[:3, :3]))
                view_map.append(i)
                T_views.append(T)
        return cls(np.array(query), descriptor_spectra(np.array(view)), np.array(view_map), np.array(T_views))

    def nearest(self, q: int, n_eligible_maps: int, k: int) -> list[tuple[int, int, float, int]]:
        """Up to k (map, viewpoint, distance, shift) of distinct maps among the first `n_eligible_maps`, nearest
        first."""
        n_views = int(np.searchsorted(self.view_map, n_eligible_maps))
        if n_views == 0:
            return []
        view = self.view
        distance, shift = spectra_distances(self.query[q], DescriptorSpectra(view.unit[:n_views],
                                                                             view.occupied[:n_views], view.sectors))
        best: dict[int, tuple[int, float, int]] = {}
        for n in np.argsort(distance, kind="stable"):
            m = int(self.view_map[n])
            if m not in best:
                best[m] = (int(n), float(distance[n]), int(shift[n]))
            if len(best) == k:
                break
        return [(m, *value) for m, value in best.items()]


@dataclass
class _QueryTask:
    """What registering one local map's candidates needs: its points and, per candidate, the reference's points
    (both anchor frames, m), the reference viewpoint the descriptor matched (T_anchor_view) and the yaw (rad)."""

    query_points: np.ndarray
    refs: list[tuple[np.ndarray, np.ndarray, float]]
    cfg: LoopClosureConfig


def _register_query(task: _QueryTask) -> list[Registration]:
    """The registration of the query onto each of its candidate references (a task for `current_execution`)."""
    cfg = task.cfg
    query = prepare_local_map(task.query_points, cfg.local_map_voxel_m)
    out = []
    for ref_points, T_anchor_view, yaw in task.refs:
        ref_in_view = (ref_points - T_anchor_view[:3, 3]) @ T_anchor_view[:3, :3]
        T_init = T_anchor_view @ initial_alignment(ref_in_view, task.query_points, yaw, cfg.descriptor_range_m,
                                                   cfg.bev_cell_m)
        out.append(register_local_maps(prepare_local_map(ref_points, cfg.local_map_voxel_m), query, T_init,
                                       cfg.max_correspondence_m, cfg.inlier_distance_m, cfg.overlap_distance_m))
    return out


def _propose(q: int, maps: list[LocalMap], places: _Places, path_m: np.ndarray, cfg: LoopClosureConfig,
             min_separation_m: float) -> tuple[list[Candidate], _QueryTask]:
    """The candidates of local map q (the earlier local maps at least `min_separation_m` of path before it, nearest
    descriptors first) and the task registering them."""
    n_eligible = int(np.count_nonzero(path_m[q] - path_m[:q] >= min_separation_m))  # a prefix: the path only grows
    records, refs = [], []
    for r, view, distance, shift in places.nearest(q, n_eligible, cfg.candidates_per_query):
        if distance > cfg.max_descriptor_distance:
            continue
        yaw = yaw_of_shift(shift, cfg.descriptor_sectors)
        records.append(Candidate(query_map=q, ref_map=r, query_scan=maps[q].anchor, ref_scan=maps[r].anchor,
                                 descriptor_distance=distance, yaw_deg=float(np.degrees(yaw))))
        refs.append((maps[r].points_anchor, places.T_anchor_view[view], yaw))
    return records, _QueryTask(maps[q].points_anchor, refs, cfg)


def _judge_query(q: int, records: list[Candidate], registrations: list[Registration], graph: _MapGraph,
                 cfg: LoopClosureConfig) -> list[Edge]:
    """Apply the gates to the registered candidates of local map q (filling in their records) against the current
    loop-closed estimate; return the accepted loop edges."""
    if not records:
        return []
    graph_path_m = graph.path_from(q, q)
    passed = []
    for c, reg in zip(records, registrations, strict=True):
        r = c.ref_map
        c.fitness, c.overlap, c.rmse_m = reg.fitness, reg.overlap, reg.rmse_m
        c.path_between_m = float(graph_path_m[r])
        T_expected = np.linalg.inv(graph.T_world_map[r]) @ graph.T_world_map[q]
        c.correction_m, c.correction_deg = _correction(T_expected, reg.T_ref_query)
        c.drift_bound_m, c.drift_bound_deg = graph.drift_bounds(c.path_between_m)
        if not reg.converged:
            c.reason = "registration did not converge"
        elif reg.overlap < cfg.min_overlap:
            c.reason = f"overlap {reg.overlap:.2f} < min_overlap {cfg.min_overlap}"
        elif reg.fitness < cfg.min_fitness:
            c.reason = f"fitness {reg.fitness:.2f} < min_fitness {cfg.min_fitness}"
        elif c.correction_m > c.drift_bound_m or c.correction_deg > c.drift_bound_deg:
            c.reason = (f"correction {c.correction_m:.2f} m / {c.correction_deg:.2f} deg exceeds the drift bound "
                        f"{c.drift_bound_m:.2f} m / {c.drift_bound_deg:.2f} deg over {c.path_between_m:.0f} m of path")
        else:
            passed.append((c, reg.T_ref_query))
    for a in range(len(passed)):
        for b in range(a + 1, len(passed)):
            (ca, Ta), (cb, Tb) = passed[a], passed[b]
            T_expected = np.linalg.inv(graph.T_world_map[ca.ref_map]) @ graph.T_world_map[cb.ref_map]
            moved_m, turned_deg = _correction(T_expected, Ta @ np.linalg.inv(Tb))
            bound_m, bound_deg = graph.drift_bounds(float(graph.path_from(ca.ref_map, q)[cb.ref_map]))
            if moved_m > bound_m or turned_deg > bound_deg:
                for c, _ in passed:
                    c.reason = (f"ambiguous: local maps {ca.ref_map} and {cb.ref_map} both match but disagree by "
                                f"{moved_m:.2f} m / {turned_deg:.2f} deg (bound {bound_m:.2f} m / {bound_deg:.2f} deg)")
                return []
    edges = []
    for c, T in passed:
        c.accepted, c.reason = True, "verified"
        edges.append(Edge(c.ref_map, c.query_map, T, np.deg2rad(cfg.loop_rotation_sigma_deg),
                          cfg.loop_translation_sigma_m, robust=True))
    return edges


def close_loops(points: Sequence[np.ndarray], T_world_scan: np.ndarray, cfg: LoopClosureConfig,
                min_separation_m: float, progress: Progress | None = None) -> LoopResult:
    """Loop-closed T_world_scan (N, 4, 4) from odometry poses and the scans (sensor frame, m); places
    at least `min_separation_m` of path apart are loop candidates (loops.min_separation_m).

    `progress(done, total)` counts scans while the local maps are built, then local maps examined.
    Without an accepted closure the odometry poses are returned unchanged; a path shorter than
    `min_separation_m` holds no two places far enough apart, and its scans are not read.
    """
    T_world_scan = np.asarray(T_world_scan, dtype=np.float64)
    if path_lengths_m(T_world_scan)[-1] < min_separation_m:
        return LoopResult(T_world_scan.copy(), [], [], [], {"n_loop_edges": 0})
    maps = build_local_maps(points, T_world_scan, cfg.local_map_length_m, cfg.local_map_voxel_m, progress)
    places = _Places.build(maps, cfg)
    graph = _MapGraph(maps, T_world_scan, cfg)
    proposals = [_propose(q, maps, places, graph.path_m, cfg, min_separation_m) for q in range(len(maps))]
    tasks = [task for _, task in proposals if task.refs]
    task_bytes = max((REGISTRATION_BYTES_PER_POINT * (len(t.query_points) + sum(len(ref) for ref, _, _ in t.refs))
                      for t in tasks), default=0)
    registered = current_execution().imap(_register_query, tasks, item_bytes=task_bytes)
    candidates: list[Candidate] = []
    for q, (records, task) in enumerate(proposals):
        edges = _judge_query(q, records, next(registered) if task.refs else [], graph, cfg)
        candidates += records
        if edges:
            accepted = [c for c in records if c.accepted]
            graph.add_loops(edges, max(c.correction_m for c in accepted), max(c.correction_deg for c in accepted))
        if progress is not None:
            progress(q + 1, len(maps))
    if not graph.loops:
        return LoopResult(T_world_scan.copy(), candidates, maps, [], {"n_loop_edges": 0})
    # Scans follow their local map's anchor, then the full graph settles the steps between local maps.
    T_init = np.empty_like(T_world_scan)
    for m, T_map in zip(maps, graph.T_world_map, strict=True):
        correction = T_map @ np.linalg.inv(T_world_scan[m.anchor])
        T_init[m.first:m.last + 1] = correction @ T_world_scan[m.first:m.last + 1]
    edges = odometry_edges(T_world_scan, path_lengths_m(T_world_scan), cfg.odometry_translation_sigma_m,
                           np.deg2rad(cfg.odometry_rotation_sigma_deg), cfg.odometry_min_step_m)
    loop_edges = [Edge(maps[e.i].anchor, maps[e.j].anchor, e.T_i_j, e.sigma_rotation_rad, e.sigma_translation_m,
                       robust=True) for e in graph.loops]
    T_closed, summary = optimize_pose_graph(T_init, edges + loop_edges, cfg.robust_kernel_sigmas)
    summary["n_loop_edges"] = len(loop_edges)
    return LoopResult(T_closed, candidates, maps, loop_edges, summary)
