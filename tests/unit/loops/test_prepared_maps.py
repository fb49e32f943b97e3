"""Local maps prepared once for all their registrations (`pa_cli.loops.closure._register`,
`_PreparedMaps`, `_schedule`): the same registrations as with maps prepared afresh for each, each
local map prepared once when the cache allows, the cache's bound and its eviction rule."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pa_cli.config import ExecutionConfig, LoopClosureConfig
from pa_cli.loops import closure
from pa_cli.loops.closure import _group, _Pair, _PreparedMaps, _register, _register_pairs, _schedule
from pa_cli.loops.descriptors import initial_alignment
from pa_cli.loops.local_maps import LocalMap, voxel_centroids
from pa_cli.loops.verification import prepare_local_map, register_local_maps
from pa_cli.runtime.distributed import execution

VOXEL_M = 0.5


def _pose(yaw_rad: float, xyz: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", yaw_rad).as_matrix()
    T[:3, 3] = xyz
    return T


def _yard(rng: np.random.Generator, n: int = 12000) -> np.ndarray:
    """A ground plane and walls of different heights and directions (m), no symmetry."""
    parts = [np.column_stack([rng.uniform(-30, 30, n // 2), rng.uniform(-30, 30, n // 2), np.zeros(n // 2)])]
    for (x0, y0), (x1, y1), h in [((-20, 15), (10, 15), 8.0), ((12, -25), (12, 5), 12.0),
                                  ((-25, -10), (-5, -25), 5.0), ((20, 18), (28, 26), 15.0)]:
        t = rng.uniform(0, 1, n // 8)
        parts.append(np.column_stack([x0 + t * (x1 - x0), y0 + t * (y1 - y0), rng.uniform(0, h, n // 8)]))
    return np.vstack(parts)


def _local_maps(n_maps: int, seed: int = 0) -> tuple[list[LocalMap], np.ndarray]:
    """Local maps of one yard seen from `n_maps` anchors, and the true T_yard_anchor of each."""
    rng = np.random.default_rng(seed)
    yard = _yard(rng)
    maps, T_yard_anchor = [], []
    for k in range(n_maps):
        T = _pose(rng.uniform(-0.3, 0.3), (rng.uniform(-2, 2), rng.uniform(-2, 2), 0.0))
        points = (yard - T[:3, 3]) @ T[:3, :3] + rng.normal(0, 0.01, yard.shape)
        maps.append(LocalMap(first=k, last=k, anchor=k, path_m=10.0 * k, points_anchor=voxel_centroids(points, VOXEL_M),
                             T_anchor_scan=np.eye(4)[None]))
        T_yard_anchor.append(T)
    return maps, np.array(T_yard_anchor)


def _pairs(T_yard_anchor: np.ndarray, ends: list[tuple[int, int]]) -> list[_Pair]:
    """Pairs (query, reference) with the true relative yaw as the descriptor's and the anchor as the viewpoint."""
    out = []
    for q, r in ends:
        T_ref_query = np.linalg.inv(T_yard_anchor[r]) @ T_yard_anchor[q]
        out.append(_Pair(q, r, np.eye(4), float(np.arctan2(T_ref_query[1, 0], T_ref_query[0, 0]))))
    return out


def _fresh(pair: _Pair, maps: list[LocalMap], cfg: LoopClosureConfig):
    """The registration of a pair with both local maps prepared for it alone."""
    ref, query = maps[pair.ref].points_anchor, maps[pair.query].points_anchor
    T_init = initial_alignment(ref, query, pair.yaw_rad, cfg.descriptor_range_m, cfg.bev_cell_m)
    return register_local_maps(prepare_local_map(ref, VOXEL_M), prepare_local_map(query, VOXEL_M), T_init,
                               cfg.max_correspondence_m, cfg.inlier_distance_m, cfg.overlap_distance_m)


ENDS = [(2, 0), (2, 1), (3, 0), (3, 2), (4, 1), (4, 3), (3, 1)]  # map 1: reference 3 times; 2 and 3: query and ref


def _counting(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    count = [0]

    def counted(points: np.ndarray, voxel_m: float, threads: int = 1):
        count[0] += 1
        return prepare_local_map(points, voxel_m, threads)

    monkeypatch.setattr(closure, "prepare_local_map", counted)
    return count


def test_a_prepared_map_reused_registers_as_a_fresh_one_and_the_true_transform_is_found():
    maps, T_yard_anchor = _local_maps(3)
    cfg = LoopClosureConfig()
    pairs = _pairs(T_yard_anchor, [(1, 0), (2, 0), (0, 2)])  # map 0: reference twice, then query; map 2 both roles
    # prepared and their agreement searched on two threads, fresh (`_fresh`) on one: the same registrations bit for bit
    prepared = {i: prepare_local_map(maps[i].points_anchor, VOXEL_M, threads=2) for i in range(3)}
    from_prepared = _register_pairs(closure._PairsTask(prepared, pairs, cfg, threads=2))
    from_points = _register_pairs(closure._PairsTask({i: m.points_anchor for i, m in enumerate(maps)}, pairs, cfg))
    for pair, a, b in zip(pairs, from_prepared, from_points, strict=True):
        fresh = _fresh(pair, maps, cfg)
        for reg in (a, b):
            np.testing.assert_array_equal(reg.T_ref_query, fresh.T_ref_query)
            assert (reg.fitness, reg.overlap, reg.rmse_m, reg.converged) == (
                fresh.fitness, fresh.overlap, fresh.rmse_m, fresh.converged)
        T_true = np.linalg.inv(T_yard_anchor[pair.ref]) @ T_yard_anchor[pair.query]
        assert fresh.converged and fresh.fitness > 0.9
        assert np.linalg.norm(fresh.T_ref_query[:3, 3] - T_true[:3, 3]) < 0.05


def test_each_local_map_used_is_prepared_once_and_every_pair_registers_as_afresh(monkeypatch):
    maps, T_yard_anchor = _local_maps(6)  # map 5 takes part in no pair
    cfg = LoopClosureConfig()
    pairs = _pairs(T_yard_anchor, ENDS)
    count = _counting(monkeypatch)
    registered = _register(pairs, maps, cfg, threads=2)  # prepared and searched on two threads, fresh on one
    assert count[0] == len({i for end in ENDS for i in end}) == 5
    assert sorted(registered) == sorted(ENDS)
    for pair in pairs:
        fresh = _fresh(pair, maps, cfg)
        np.testing.assert_array_equal(registered[pair.query, pair.ref].T_ref_query, fresh.T_ref_query)
        assert registered[pair.query, pair.ref].fitness == fresh.fitness


def test_a_cache_of_one_map_prepares_more_often_and_registers_the_same(monkeypatch):
    maps, T_yard_anchor = _local_maps(5)
    cfg = LoopClosureConfig()
    pairs = _pairs(T_yard_anchor, ENDS)
    roomy = _register(pairs, maps, cfg)
    count = _counting(monkeypatch)
    one_map_bytes = max(prepare_local_map(m.points_anchor, VOXEL_M).n_bytes for m in maps)
    tight = _register(pairs, maps, cfg, cache_bytes=one_map_bytes)
    assert count[0] > 5
    for key, reg in roomy.items():
        np.testing.assert_array_equal(tight[key].T_ref_query, reg.T_ref_query)


class _Sized:
    """A stand-in prepared map of a given size."""

    def __init__(self, n_bytes: int) -> None:
        self.n_bytes = n_bytes


def _stand_in_preparations(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    prepared: list[int] = []

    def prepare(points: np.ndarray, voxel_m: float, threads: int = 1) -> _Sized:
        prepared.append(int(points[0, 0]))
        return _Sized(100)

    monkeypatch.setattr(closure, "prepare_local_map", prepare)
    return prepared


def _index_maps(n: int) -> list[LocalMap]:
    """Local maps whose single point holds their index (what the stand-in preparation records)."""
    return [LocalMap(k, k, k, float(k), np.full((1, 3), float(k)), np.eye(4)[None]) for k in range(n)]


def test_the_cache_keeps_its_bound_and_drops_the_map_needed_furthest_ahead(monkeypatch):
    prepared = _stand_in_preparations(monkeypatch)
    order = [0, 1, 2, 0, 1, 2, 0]
    cache = _PreparedMaps(_index_maps(3), order, VOXEL_M, budget_bytes=200)  # room for two
    for _ in cache.in_order():
        assert sum(m.n_bytes for m, _ in cache.held.values()) <= 200
    # By hand: 0, 1 prepared; 2 prepared and dropped at once (its next use is the furthest); 0, 1 held; 1 dropped
    # after its last use; 2 prepared again; 0 held. An LRU cache of two would prepare all seven.
    assert prepared == [0, 1, 2, 2]
    assert cache.held == {}


def test_the_schedule_orders_every_pair_once_and_needs_fewer_preparations_than_the_query_order(monkeypatch):
    # A circuit of 12 places driven 5 times: the local map of lap L at place p is 12 L + p; each registers with the
    # visits of its place on the three laps before.
    places, laps = 12, 5
    ends = [(lap * places + p, earlier * places + p) for lap in range(1, laps) for p in range(places)
            for earlier in range(max(lap - 3, 0), lap)]
    pairs = [_Pair(q, r, np.eye(4), 0.0) for q, r in ends]
    scheduled = _schedule(pairs, places * laps)
    assert sorted((p.query, p.ref) for p in scheduled) == sorted(ends)

    def preparations(ordered: list[_Pair]) -> int:
        prepared = _stand_in_preparations(monkeypatch)
        order = [i for group in _group(ordered, 2) for i in closure._maps_of(group)]
        for _ in _PreparedMaps(_index_maps(places * laps), order, VOXEL_M, budget_bytes=600).in_order():
            pass
        return len(prepared)

    assert preparations(scheduled) == places * laps  # once each: a place's five visits fit the cache of six
    assert preparations(pairs) > 2 * places * laps


def test_groups_are_consecutive_runs_within_their_map_bound():
    pairs = [_Pair(q, r, np.eye(4), 0.0) for q, r in [(2, 0), (2, 1), (3, 0), (3, 2), (4, 1), (4, 3), (5, 4)]]
    for max_maps in (2, 3, 4, 16):
        groups = _group(pairs, max_maps)
        assert [p for g in groups for p in g] == pairs
        assert all(len(closure._maps_of(g)) <= max_maps for g in groups)
        # A group ends only where the next pair would exceed the bound.
        for a, b in zip(groups, groups[1:], strict=False):
            assert len(closure._maps_of(a + b[:1])) > max_maps


@pytest.mark.slow
def test_dask_workers_register_as_this_process(monkeypatch):
    pytest.importorskip("distributed")
    maps, T_yard_anchor = _local_maps(5)
    cfg = LoopClosureConfig()
    pairs = _pairs(T_yard_anchor, ENDS)
    local = _register(pairs, maps, cfg)
    monkeypatch.setattr(closure, "TASK_MAPS", 3)  # several tasks, some maps in two of them
    with execution(ExecutionConfig(workers=2, memory_budget_gb=1.0)):
        remote = _register(pairs, maps, cfg)
    assert sorted(remote) == sorted(local)
    for key, reg in local.items():
        np.testing.assert_array_equal(remote[key].T_ref_query, reg.T_ref_query)
        assert remote[key].fitness == reg.fitness


def test_processes_of_this_machine_register_as_this_process(monkeypatch):
    """Without a cluster, with 2 processes and enough pairs for both (the least share lowered), the registrations
    run as tasks that prepare their own local maps on the processes (no prepared-map cache here), and equal this
    process's bit for bit; with fewer pairs than the share they stay in this process, with its cache."""
    maps, T_yard_anchor = _local_maps(5)
    cfg = LoopClosureConfig()
    pairs = _pairs(T_yard_anchor, ENDS)
    local = _register(pairs, maps, cfg)
    caches = []

    class Counted(_PreparedMaps):
        def __init__(self, *args, **kwargs):
            caches.append(1)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(closure, "_PreparedMaps", Counted)
    monkeypatch.setattr(closure, "TASK_MAPS", 3)
    for least_share, cached in ((1, False), (len(pairs), True)):
        monkeypatch.setattr(closure, "MIN_PAIRS_PER_PROCESS", least_share)
        caches.clear()
        with execution(ExecutionConfig(threads=2)):
            registered = _register(pairs, maps, cfg)
        assert bool(caches) == cached
        assert sorted(registered) == sorted(local)
        for key, reg in local.items():
            np.testing.assert_array_equal(registered[key].T_ref_query, reg.T_ref_query)
            assert registered[key].fitness == reg.fitness
