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
   The candidates do not depend on the closures accepted, so the registrations of each local map's
   FIRST_REGISTERED nearest candidates run first, on the current execution, and the gates then
   examine the local maps in order; a local map's further candidates are registered when the gates
   examine it, and only when its nearest ones do not all pass. Each local map is
   prepared for registration (`verification.PreparedMap`) about once (`_schedule`,
   `_PreparedMaps`): the registrations are ordered so that those sharing a local map come close
   together, and this process holds each prepared map until its last registration, within
   PREPARED_CACHE_BYTES. With dask workers (--workers) a prepared map cannot travel (small_gicp's
   clouds do not pickle, and their covariances cannot be set from Python), so a task carries the
   points of up to TASK_MAPS local maps and prepares each once for all its registrations.
   Accepted closures are added to a pose graph over the local maps, which is re-solved before the
   next local map is examined (unless the closures agree with it within the loop edges' kernel),
   so later gates measure against the loop-closed estimate.
4. The final pose graph over all scans: odometry edges between consecutive scans plus the loop
   edges between anchor scans (Cauchy kernel), initialised from the local-map solution.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
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
from pa_cli.loops.pose_graph import Edge, PoseGraph, odometry_edges, optimize_pose_graph
from pa_cli.loops.verification import (
    PREPARED_BYTES_PER_POINT,
    PreparedMap,
    Registration,
    prepare_local_map,
    register_local_maps,
)
from pa_cli.runtime.distributed import current_execution

Progress = Callable[[int, int], None]
# Prepared local maps this process holds for registrations to come (bytes): 16 local maps of 17,000 points (6 MB
# each), enough in `_schedule`'s order to prepare each local map of a circuit driven ten times 1.2 times on average
# (twice the budget: 1.05 times), while the stage's peak memory grows by little (docs/throughput.md, "The loop stage").
PREPARED_CACHE_BYTES = 100e6
# Candidates of a local map registered before the gates examine it: two, the fewest the ambiguity test compares. Its
# further candidates (up to candidates_per_query) are registered only when these two do not both pass: a place
# driven for the tenth time has more earlier visits than it needs closures, and two that agree anchor it.
FIRST_REGISTERED = 2
# Local maps one task on dask workers (or on processes of this machine) prepares and shares among its registrations: a
# few places' visits, about 95 MB at 16,000 points a map, and still tens of tasks to spread over the workers.
TASK_MAPS = 16
# Without a cluster the registrations go to processes of this machine only where each gets at least this many: a
# process's start (spawn, imports: about 0.7 s) against about 25 ms per registration, so two processes gain from
# about 60 registrations on.
MIN_PAIRS_PER_PROCESS = 40


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
        T_odometry = T_world_scan[[m.anchor for m in maps]]
        self.pose_graph = PoseGraph(T_odometry, cfg.robust_kernel_sigmas)
        self.pose_graph.add(odometry_edges(T_odometry, self.path_m, cfg.odometry_translation_sigma_m,
                                           np.deg2rad(cfg.odometry_rotation_sigma_deg), cfg.odometry_min_step_m))
        self.loops: list[Edge] = []
        self.closure_path_m = cfg.loop_translation_sigma_m / cfg.max_drift_fraction

    @property
    def T_world_map(self) -> np.ndarray:
        """The current estimate of the local maps' anchor poses (M, 4, 4)."""
        return self.pose_graph.T_world_node

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
        self.pose_graph.add(edges)
        cfg = self.cfg
        if (correction_m > cfg.robust_kernel_sigmas * cfg.loop_translation_sigma_m
                or correction_deg > cfg.robust_kernel_sigmas * cfg.loop_rotation_sigma_deg):
            self.pose_graph.solve()


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
class _Pair:
    """One candidate's registration: the query and reference local maps, the reference viewpoint the descriptor
    matched (T_anchor_view, reference anchor frame) and the descriptor's yaw (rad)."""

    query: int
    ref: int
    T_anchor_view: np.ndarray
    yaw_rad: float


@dataclass
class _PairsTask:
    """Registrations and the local maps they need: each prepared already, or its points (anchor frame, m) to be
    prepared once in the task; the threads of its agreement's neighbour searches."""

    maps: dict[int, PreparedMap | np.ndarray]
    pairs: list[_Pair]
    cfg: LoopClosureConfig
    threads: int = 1


def _register_pairs(task: _PairsTask) -> list[Registration]:
    """The registration of each pair's query onto its reference (a task for `current_execution`)."""
    cfg = task.cfg
    prepared = {i: m if isinstance(m, PreparedMap) else prepare_local_map(m, cfg.local_map_voxel_m)
                for i, m in task.maps.items()}
    out = []
    for pair in task.pairs:
        ref, query = prepared[pair.ref], prepared[pair.query]
        T = pair.T_anchor_view
        T_init = T @ initial_alignment((ref.points - T[:3, 3]) @ T[:3, :3], query.points, pair.yaw_rad,
                                       cfg.descriptor_range_m, cfg.bev_cell_m)
        out.append(register_local_maps(ref, query, T_init, cfg.max_correspondence_m, cfg.inlier_distance_m,
                                       cfg.overlap_distance_m, task.threads))
    return out


def _schedule(pairs: list[_Pair], n_maps: int) -> list[_Pair]:
    """The pairs in an order where those sharing a local map come close together: the local maps ranked in reverse
    Cuthill-McKee order of the graph the pairs make (the visits of one place, which register with each other, rank
    close together), the pairs by the rank of their first-ranked local map, then of the other. A local map's pairs
    with the maps ranked after it come in one run, those with the maps ranked before it within the ranking's
    bandwidth (of the order of a place's visits and their neighbours')."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    if not pairs:
        return []
    ends = np.array([(p.query, p.ref) for p in pairs])
    graph = coo_matrix((np.ones(len(pairs)), (ends[:, 0], ends[:, 1])), shape=(n_maps, n_maps)).tocsr()
    rank = np.empty(n_maps, dtype=np.int64)
    rank[reverse_cuthill_mckee((graph + graph.T).tocsr(), symmetric_mode=True)] = np.arange(n_maps)
    ranks = np.sort(rank[ends], axis=1)
    return [pairs[k] for k in np.lexsort((ranks[:, 1], ranks[:, 0]))]


def _group(pairs: list[_Pair], max_maps: int) -> list[list[_Pair]]:
    """Consecutive runs of `pairs` that need at most `max_maps` (>= 2) local maps each."""
    groups: list[list[_Pair]] = []
    held: set[int] = set()
    for pair in pairs:
        if not groups or len(held | {pair.query, pair.ref}) > max_maps:
            groups.append([])
            held = set()
        groups[-1].append(pair)
        held |= {pair.query, pair.ref}
    return groups


def _maps_of(group: list[_Pair]) -> list[int]:
    """The local maps a group of pairs needs, in the order they first appear."""
    return list(dict.fromkeys(i for pair in group for i in (pair.query, pair.ref)))


class _PreparedMaps:
    """Prepared local maps, asked for in a known order (`order`, local-map indices): each is prepared when asked for
    and not held, and held while a use of it is to come, within `budget_bytes`; over the budget, the held maps whose
    next use is furthest are dropped first (Belady's rule, optimal for a known order)."""

    def __init__(self, maps: list[LocalMap], order: list[int], voxel_m: float, budget_bytes: float,
                 threads: int = 1) -> None:
        self.maps, self.order, self.voxel_m, self.budget_bytes = maps, order, voxel_m, budget_bytes
        self.threads = threads
        self.next_use = np.full(len(order), np.inf)  # of the local map asked for at each position: its next position
        last: dict[int, int] = {}
        for position in range(len(order) - 1, -1, -1):
            self.next_use[position] = last.get(order[position], np.inf)
            last[order[position]] = position
        self.held: dict[int, tuple[PreparedMap, float]] = {}  # local map: its prepared map and next use

    def in_order(self) -> Iterator[PreparedMap]:
        """The prepared map of each entry of `order`, in turn."""
        for position, i in enumerate(self.order):
            prepared = (self.held[i][0] if i in self.held
                        else prepare_local_map(self.maps[i].points_anchor, self.voxel_m, self.threads))
            self.held[i] = (prepared, self.next_use[position])
            held_bytes = sum(m.n_bytes for m, _ in self.held.values())
            for j in sorted(self.held, key=lambda j: -self.held[j][1]):
                if held_bytes <= self.budget_bytes and self.held[j][1] < np.inf:
                    break
                held_bytes -= self.held.pop(j)[0].n_bytes
            yield prepared


def _register(pairs: list[_Pair], maps: list[LocalMap], cfg: LoopClosureConfig,
              cache_bytes: float = PREPARED_CACHE_BYTES, threads: int = 1) -> dict[tuple[int, int], Registration]:
    """The registration of every pair, by (query, reference), on the current execution. In this process each task
    is one pair whose local maps come prepared from a `_PreparedMaps` within `cache_bytes`, and the preparations and
    the agreement's neighbour searches run on `threads` threads; on dask workers, or without a cluster on the
    execution's processes of this machine (small_gicp holds the GIL; when at least two get `MIN_PAIRS_PER_PROCESS`
    pairs each), a task is a run of pairs needing up to TASK_MAPS local maps, which it prepares itself (one thread:
    the processes are the parallelism)."""
    execution = current_execution()
    on_processes = execution.spreads(len(pairs), MIN_PAIRS_PER_PROCESS)
    apart = execution.client is not None or on_processes  # the tasks prepare their own local maps
    task_threads = 1 if apart else threads
    ordered = _schedule(pairs, len(maps))
    groups = _group(ordered, TASK_MAPS if apart else 2)
    cache = None
    if not apart:
        cache = _PreparedMaps(maps, [i for group in groups for i in _maps_of(group)], cfg.local_map_voxel_m,
                              cache_bytes, threads)

    def tasks() -> Iterator[_PairsTask]:
        prepared = None if cache is None else cache.in_order()
        for group in groups:
            needed = _maps_of(group)
            held = {i: maps[i].points_anchor if prepared is None else next(prepared) for i in needed}
            yield _PairsTask(held, group, cfg, task_threads)

    task_bytes = max((PREPARED_BYTES_PER_POINT * sum(len(maps[i].points_anchor) for i in _maps_of(group))
                      for group in groups), default=0)
    registered = execution.imap(_register_pairs, tasks(), item_bytes=task_bytes, holds_gil=on_processes)
    out = {}
    for group, registrations in zip(groups, registered, strict=True):
        out.update({(pair.query, pair.ref): reg for pair, reg in zip(group, registrations, strict=True)})
    return out


def _propose(q: int, maps: list[LocalMap], places: _Places, path_m: np.ndarray, cfg: LoopClosureConfig,
             min_separation_m: float) -> tuple[list[Candidate], list[_Pair]]:
    """The candidates of local map q (the earlier local maps at least `min_separation_m` of path before it, nearest
    descriptors first) and their registrations to run."""
    n_eligible = int(np.count_nonzero(path_m[q] - path_m[:q] >= min_separation_m))  # a prefix: the path only grows
    records, pairs = [], []
    for r, view, distance, shift in places.nearest(q, n_eligible, cfg.candidates_per_query):
        if distance > cfg.max_descriptor_distance:
            continue
        yaw = yaw_of_shift(shift, cfg.descriptor_sectors)
        records.append(Candidate(query_map=q, ref_map=r, query_scan=maps[q].anchor, ref_scan=maps[r].anchor,
                                 descriptor_distance=distance, yaw_deg=float(np.degrees(yaw))))
        pairs.append(_Pair(q, r, places.T_anchor_view[view], yaw))
    return records, pairs


def _judge_query(q: int, records: list[Candidate], registrations: list[Registration], graph: _MapGraph,
                 cfg: LoopClosureConfig) -> list[Edge]:
    """Apply the gates to the registered candidates of local map q (filling in their records) against the current
    loop-closed estimate; return the accepted loop edges."""
    if not records:
        return []
    graph_path_m = graph.path_from(q, q)
    passed = []
    for c, reg in zip(records, registrations, strict=True):
        c.accepted = False
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
                min_separation_m: float, progress: Progress | None = None, threads: int = 1,
                thinned: bool = False) -> LoopResult:
    """Loop-closed T_world_scan (N, 4, 4) from odometry poses and the scans (sensor frame, m); places
    at least `min_separation_m` of path apart are loop candidates (loops.min_separation_m). `thinned`: the
    scans hold one point per voxel of at most `local_map_voxel_m` already (`build_local_maps`). In this
    process the local maps are prepared for registration on `threads` threads (execution.threads).

    `progress(done, total)` counts scans while the local maps are built, then local maps examined.
    Without an accepted closure the odometry poses are returned unchanged; a path shorter than
    `min_separation_m` holds no two places far enough apart, and its scans are not read.
    """
    T_world_scan = np.asarray(T_world_scan, dtype=np.float64)
    if path_lengths_m(T_world_scan)[-1] < min_separation_m:
        return LoopResult(T_world_scan.copy(), [], [], [], {"n_loop_edges": 0})
    maps = build_local_maps(points, T_world_scan, cfg.local_map_length_m, cfg.local_map_voxel_m, progress,
                            thinned)
    places = _Places.build(maps, cfg)
    graph = _MapGraph(maps, T_world_scan, cfg)
    proposals = [_propose(q, maps, places, graph.path_m, cfg, min_separation_m) for q in range(len(maps))]
    registered = _register([pair for _, pairs in proposals for pair in pairs[:FIRST_REGISTERED]], maps, cfg,
                           threads=threads)
    candidates: list[Candidate] = []
    for q, (records, pairs) in enumerate(proposals):
        first = records[:FIRST_REGISTERED]
        registrations = [registered[q, c.ref_map] for c in first]
        edges = _judge_query(q, first, registrations, graph, cfg)
        if len(records) > FIRST_REGISTERED and len(edges) < FIRST_REGISTERED:
            later = _register(pairs[FIRST_REGISTERED:], maps, cfg, threads=threads)
            registrations += [later[q, c.ref_map] for c in records[FIRST_REGISTERED:]]
            edges = _judge_query(q, records, registrations, graph, cfg)
        else:
            for c in records[FIRST_REGISTERED:]:
                c.reason = f"not registered: its {FIRST_REGISTERED} nearer candidates were verified"
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
