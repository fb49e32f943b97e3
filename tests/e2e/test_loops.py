"""Loop closure (`pa_cli.loops`): descriptors, alignment, registration and the pose graph against
known transforms; the whole stage on simulated loops (genuine closures found, look-alike places
one block away rejected) with drifted ground truth as odometry."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pa_cli.config import LoopClosureConfig, LoopsConfig
from pa_cli.loops import close_loops, local_maps
from pa_cli.loops.descriptors import (
    descriptor_spectra,
    initial_alignment,
    polar_descriptor,
    spectra_distances,
    yaw_of_shift,
)
from pa_cli.loops.local_maps import build_local_maps, segment_scans, voxel_centroids
from pa_cli.loops.pose_graph import Edge, PoseGraph, odometry_edges, optimize_pose_graph
from pa_cli.loops.verification import COARSE_VOXEL_FACTOR, prepare_local_map, register_local_maps


def _pose(yaw_rad: float, xyz: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", yaw_rad).as_matrix()
    T[:3, 3] = xyz
    return T


def _transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


def _yard(rng: np.random.Generator, n: int = 20000) -> np.ndarray:
    """Points of a ground plane and a few walls and boxes of different heights (m), no symmetry."""
    ground = np.column_stack([rng.uniform(-40, 40, n // 2), rng.uniform(-40, 40, n // 2), np.zeros(n // 2)])
    parts = [ground]
    walls = [((-20, 15), (10, 15), 8.0), ((12, -30), (12, 5), 12.0), ((-25, -10), (-5, -25), 5.0),
             ((25, 20), (35, 28), 15.0), ((-8, 2), (-3, 2), 3.0)]
    for (x0, y0), (x1, y1), h in walls:
        m = n // 10
        t = rng.uniform(0, 1, m)
        parts.append(np.column_stack([x0 + t * (x1 - x0), y0 + t * (y1 - y0), rng.uniform(0, h, m)]))
    return np.vstack(parts)


def test_descriptor_shift_gives_the_yaw_between_frames():
    rng = np.random.default_rng(0)
    points_ref = _yard(rng)
    sectors = 60
    for k in (0, 7, 33):
        yaw = 2 * np.pi * k / sectors
        T_ref_query = _pose(yaw, (0.0, 0.0, 0.0))
        points_query = _transform(np.linalg.inv(T_ref_query), points_ref)
        ref = polar_descriptor(points_ref, 50.0, 20, sectors)
        query = polar_descriptor(points_query, 50.0, 20, sectors)
        distance, shift = spectra_distances(query, descriptor_spectra(ref[None]))
        assert distance[0] < 0.05
        assert np.isclose(np.angle(np.exp(1j * (yaw_of_shift(int(shift[0]), sectors) - yaw))), 0.0, atol=1e-9)
    other = polar_descriptor(_yard(np.random.default_rng(1))[:, [1, 0, 2]] * [1.3, 0.7, 1.0], 50.0, 20, sectors)
    assert spectra_distances(query, descriptor_spectra(other[None]))[0][0] > 0.1


def test_descriptor_distances_match_the_column_shifts_tried_one_by_one():
    rng = np.random.default_rng(4)
    rings, sectors = 6, 16
    refs = rng.uniform(0, 5, (7, rings, sectors)) * (rng.uniform(size=(7, 1, sectors)) > 0.3)  # empty columns too
    query = rng.uniform(0, 5, (rings, sectors)) * (rng.uniform(size=(1, sectors)) > 0.3)
    distance, shift = spectra_distances(query, descriptor_spectra(refs))

    def similarity(q: np.ndarray, r: np.ndarray) -> float:  # mean cosine of the columns occupied in both
        both = (np.linalg.norm(q, axis=0) > 0) & (np.linalg.norm(r, axis=0) > 0)
        cos = np.sum(q * r, axis=0)[both] / (np.linalg.norm(q, axis=0) * np.linalg.norm(r, axis=0))[both]
        return float(cos.mean()) if both.any() else 0.0

    for k, ref in enumerate(refs):
        brute = [similarity(query, np.roll(ref, -s, axis=1)) for s in range(sectors)]
        assert distance[k] == pytest.approx(1.0 - max(brute), abs=1e-9)
        assert brute[shift[k]] == pytest.approx(max(brute), abs=1e-9)


def test_a_path_shorter_than_the_separation_reads_no_scan():
    class Unreadable:
        def __len__(self) -> int:
            return 40

        def __getitem__(self, k: int) -> np.ndarray:
            raise AssertionError("a scan was read")

    T_world_scan = np.array([_pose(0.0, (1.2 * k, 0.0, 0.0)) for k in range(40)])  # 46.8 m of path
    result = close_loops(Unreadable(), T_world_scan, LoopClosureConfig(), min_separation_m=50.0)
    np.testing.assert_array_equal(result.T_world_scan, T_world_scan)
    assert result.candidates == [] and result.local_maps == [] and result.loop_edges == []


def test_initial_alignment_and_registration_recover_a_known_transform():
    rng = np.random.default_rng(2)
    points_ref = _yard(rng)
    T_ref_query = _pose(np.deg2rad(42.0), (3.2, -2.1, 0.05))
    points_query = _transform(np.linalg.inv(T_ref_query), points_ref) + rng.normal(0, 0.01, points_ref.shape)
    T_init = initial_alignment(points_ref, points_query, np.deg2rad(42.0), 50.0, 1.0)
    assert np.linalg.norm(T_init[:2, 3] - T_ref_query[:2, 3]) <= np.sqrt(2) * 1.0
    ref, query = (prepare_local_map(points, 0.5) for points in (points_ref, points_query))
    reg = register_local_maps(ref, query, T_init, 1.0, 0.2, 2.0)
    assert reg.converged and reg.fitness > 0.95 and reg.overlap > 0.9
    assert np.linalg.norm(reg.T_ref_query[:3, 3] - T_ref_query[:3, 3]) < 0.05
    D = np.linalg.inv(T_ref_query) @ reg.T_ref_query
    assert np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1))) < 0.2
    # A wrong start (a quarter turn off) ends misaligned: low fitness, the gate's first line.
    wrong = register_local_maps(ref, query, T_init @ _pose(np.pi / 2, (0, 0, 0)), 1.0, 0.2, 2.0)
    assert wrong.fitness < 0.8
    # The prepared maps give small_gicp's one-call result on the raw points up to its voxel sampling's rounding
    # (0.1 mm, far below the 0.2 m inlier distance): the preparation is the same downsampling (to twice the local
    # maps' voxel, COARSE_VOXEL_FACTOR) and covariances.
    import small_gicp

    T = T_init
    for distance_m in (4.0, 1.0):
        T = small_gicp.align(points_ref, points_query, T, registration_type="GICP",
                             downsampling_resolution=COARSE_VOXEL_FACTOR * 0.5,
                             max_correspondence_distance=distance_m, num_threads=1).T_target_source
    np.testing.assert_allclose(reg.T_ref_query, T, rtol=0, atol=1e-4)


def test_local_maps_hold_the_scans_in_the_anchor_frame(monkeypatch):
    rng = np.random.default_rng(3)
    n = 30
    T_world_scan = np.array([_pose(0.02 * k, (1.5 * k, 0.1 * k, 0.0)) for k in range(n)])
    points_world = rng.uniform(-20, 20, (n, 200, 3))
    scans = [_transform(np.linalg.inv(T_world_scan[k]), points_world[k]) for k in range(n)]
    path = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(T_world_scan[:, :3, 3], axis=0), axis=1))]
    runs = segment_scans(path, 10.0)
    assert runs[0][0] == 0 and runs[-1][1] == n - 1
    assert all(b[0] == a[1] + 1 for a, b in zip(runs[:-1], runs[1:], strict=True))
    assert all(path[last] - path[first] < 10.0 for first, last in runs)
    maps = build_local_maps(scans, T_world_scan, 10.0, 1e-3)  # a millimetre voxel: every point kept
    for m in maps:
        expected = _transform(np.linalg.inv(T_world_scan[m.anchor]), points_world[m.first:m.last + 1].reshape(-1, 3))
        got = m.points_anchor
        assert len(got) == len(expected)
        np.testing.assert_allclose(np.sort(got, axis=0), np.sort(expected, axis=0), atol=1e-6)
    # Scans thinned already (`thinned`) are merged as they are: only each local map is thinned, to the same points.
    thinned_sizes = []
    monkeypatch.setattr(local_maps, "voxel_centroids",
                        lambda points, voxel_m: thinned_sizes.append(len(points)) or voxel_centroids(points, voxel_m))
    merged = build_local_maps(scans, T_world_scan, 10.0, 1e-3, thinned=True)
    assert thinned_sizes == [200 * (m.last - m.first + 1) for m in maps]
    for a, b in zip(maps, merged, strict=True):
        np.testing.assert_allclose(np.sort(a.points_anchor, axis=0), np.sort(b.points_anchor, axis=0), atol=1e-9)


def _odometry_graph(T_odometry: np.ndarray) -> tuple[LoopClosureConfig, list[Edge], tuple[float, float]]:
    """The default loop config, the odometry edges of `T_odometry` and the loop edges' sigmas (rad, m)."""
    path = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(T_odometry[:, :3, 3], axis=0), axis=1))]
    cfg = LoopClosureConfig()
    edges = odometry_edges(T_odometry, path, cfg.odometry_translation_sigma_m,
                           np.deg2rad(cfg.odometry_rotation_sigma_deg), cfg.odometry_min_step_m)
    return cfg, edges, (np.deg2rad(cfg.loop_rotation_sigma_deg), cfg.loop_translation_sigma_m)


def test_pose_graph_closes_a_drifted_loop_and_down_weights_a_wrong_closure():
    n = 80
    angle = 2 * np.pi * np.arange(n) / n
    T_true = np.array([_pose(a + np.pi / 2, (20 * np.cos(a), 20 * np.sin(a), 0.0)) for a in angle])
    step = np.linalg.inv(T_true[0]) @ T_true[1]
    drifted_step = step @ _pose(np.deg2rad(0.3), (0.02, 0.0, 0.0))  # a yaw and scale bias per step
    T_odometry = [T_true[0]]
    for _ in range(n - 1):
        T_odometry.append(T_odometry[-1] @ drifted_step)
    T_odometry = np.array(T_odometry)
    cfg, edges, sigmas = _odometry_graph(T_odometry)
    loop = Edge(0, n - 1, np.linalg.inv(T_true[0]) @ T_true[n - 1], *sigmas, robust=True)
    wrong = Edge(10, 50, _pose(0.0, (0.0, 0.0, 0.0)), *sigmas, robust=True)  # 40 m off

    def error_m(T: np.ndarray) -> float:
        return float(np.abs(T[:, :3, 3] - T_true[:, :3, 3]).max())

    closed, _ = optimize_pose_graph(T_odometry, edges + [loop], cfg.robust_kernel_sigmas)
    assert error_m(T_odometry) > 5.0  # the premise: the odometry has drifted by metres
    assert error_m(closed) < error_m(T_odometry) / 10
    with_wrong, _ = optimize_pose_graph(T_odometry, edges + [loop, wrong], cfg.robust_kernel_sigmas)
    plain = Edge(wrong.i, wrong.j, wrong.T_i_j, wrong.sigma_rotation_rad, wrong.sigma_translation_m, robust=False)
    without_kernel, _ = optimize_pose_graph(T_odometry, edges + [loop, plain], cfg.robust_kernel_sigmas)
    assert error_m(with_wrong) < error_m(without_kernel) / 3


def test_a_kept_pose_graph_grown_and_re_solved_equals_a_graph_built_afresh():
    """PoseGraph keeps its factors and estimate between solves: after edges are added in two batches and solved after
    each, its poses are those of a graph built afresh from the first solve's poses with all the edges (the same
    optimum, so no edge was lost or counted twice), and its pose extraction matches GTSAM's own matrices."""
    n = 60
    angle = 2 * np.pi * np.arange(n) / n
    T_true = np.array([_pose(a + np.pi / 2, (15 * np.cos(a), 15 * np.sin(a), 0.0)) for a in angle])
    rng = np.random.default_rng(5)
    T_odometry = [T_true[0]]
    for k in range(1, n):
        step = np.linalg.inv(T_true[k - 1]) @ T_true[k] @ _pose(rng.normal(0, 0.005), (0.02, rng.normal(0, 0.01), 0))
        T_odometry.append(T_odometry[-1] @ step)
    T_odometry = np.array(T_odometry)
    cfg, edges, sigmas = _odometry_graph(T_odometry)
    loops = [Edge(i, j, np.linalg.inv(T_true[i]) @ T_true[j], *sigmas, robust=True) for i, j in ((0, 59), (5, 50))]

    graph = PoseGraph(T_odometry, cfg.robust_kernel_sigmas)
    graph.add(edges + loops[:1])
    graph.solve()
    T_first = graph.T_world_node.copy()
    graph.add(loops[1:])
    summary = graph.solve()
    afresh, afresh_summary = optimize_pose_graph(T_first, edges + loops, cfg.robust_kernel_sigmas)
    assert np.abs(graph.T_world_node - afresh).max() < 1e-9
    assert summary == pytest.approx(afresh_summary, rel=1e-9)
    assert np.abs(T_first - graph.T_world_node).max() > 1e-3  # the premise: the second batch moved the poses
    matrices = np.array([graph.values.atPose3(k).matrix() for k in range(n)])
    assert np.array_equal(graph.T_world_node, matrices)


# ---------------------------------------------------------------------------- the stage on simulated loops


def _drifted(T_true: np.ndarray, yaw_deg_per_step: float, scale: float) -> np.ndarray:
    """Odometry from ground truth with a constant heading bias and scale error per step."""
    T = [T_true[0]]
    for k in range(1, len(T_true)):
        step = np.linalg.inv(T_true[k - 1]) @ T_true[k]
        step[:3, 3] *= scale
        T.append(T[-1] @ step @ _pose(np.deg2rad(yaw_deg_per_step), (0.0, 0.0, 0.0)))
    return np.array(T)


def _simulated_loops(scene: str, scans: int, step_m: float, path: str | None = None, seed: int = 11):
    from pa_cli.simulate import SimOptions, simulate_sequence

    seq = simulate_sequence(SimOptions(scene=scene, path=path, scans=scans, step_m=step_m, beams=16,
                                       azimuth_steps=512, seed=seed))
    return [s.points_scan for s in seq.scans], seq.T_world_scan


def _closure_errors(result, T_true: np.ndarray) -> list[float]:
    errors = []
    for c in result.candidates:
        if c.accepted:
            T_true_rel = np.linalg.inv(T_true[c.ref_scan]) @ T_true[c.query_scan]
            edge = next(e for e in result.loop_edges if (e.i, e.j) == (c.ref_scan, c.query_scan))
            errors.append(float(np.linalg.norm((np.linalg.inv(T_true_rel) @ edge.T_i_j)[:3, 3])))
    return errors


@pytest.mark.slow
@pytest.mark.parametrize(("path", "scans", "seed", "yaw_deg_per_step", "scale"),
                         [("circuit", 220, 11, 0.01, 1.01),  # 1.2 laps of identical blocks
                          ("figure8", 300, 4, 0.02, 0.99)])  # 1.6 figure eights, through the centre crossing
def test_look_alike_blocks_are_not_closed_and_true_revisits_are(path: str, scans: int, seed: int,
                                                               yaw_deg_per_step: float, scale: float):
    points, T_true = _simulated_loops("blocks", scans=scans, step_m=2.5, path=path, seed=seed)
    T_odometry = _drifted(T_true, yaw_deg_per_step, scale)
    result = close_loops(points, T_odometry, LoopClosureConfig(), LoopsConfig().min_separation_m)
    position = T_true[:, :3, 3]
    look_alikes = [c for c in result.candidates if np.linalg.norm(position[c.ref_scan] - position[c.query_scan]) > 30.0]
    assert look_alikes, "the descriptor proposed no look-alike place: the test would not exercise the gate"
    assert any(c.fitness >= 0.8 and c.overlap >= 0.3 for c in look_alikes)  # registration alone would accept
    assert not any(c.accepted for c in look_alikes)
    errors = _closure_errors(result, T_true)
    assert errors and max(errors) < 0.5


@pytest.mark.slow
@pytest.mark.parametrize(("path", "thinned"), [("circuit", False), ("figure8", False), ("circuit", True)])
def test_revisits_of_a_loop_are_closed_and_the_drift_removed(path: str, thinned: bool):
    """Also with the local maps merged from scans thinned as KISS-ICP thins its frames (one point per voxel of the
    local maps' voxel, `thinned`), as `pa refine` hands them on from the odometry."""
    from kiss_icp.voxelization import voxel_down_sample

    points, T_true = _simulated_loops("town", scans=230, step_m=2.5, path=path)
    cfg = LoopClosureConfig()
    if thinned:
        points = [voxel_down_sample(p, cfg.local_map_voxel_m) for p in points]
    T_odometry = _drifted(T_true, 0.02, 1.01)
    result = close_loops(points, T_odometry, cfg, LoopsConfig().min_separation_m, thinned=thinned)
    errors = _closure_errors(result, T_true)
    assert len(errors) >= 3 and max(errors) < 0.5

    def revisit_errors_m(T: np.ndarray) -> np.ndarray:
        """Error (m) of the relative pose of each closed scan pair: the gap a wall seen twice shows."""
        pairs = [(e.i, e.j) for e in result.loop_edges]
        return np.array([np.linalg.norm((np.linalg.inv(np.linalg.inv(T_true[i]) @ T_true[j])
                                         @ np.linalg.inv(T[i]) @ T[j])[:3, 3]) for i, j in pairs])

    # The premise: the odometry's revisits are metres apart (a figure eight's crossings also come after a short
    # path, where they are not).
    assert revisit_errors_m(T_odometry).max() > 2.0
    assert revisit_errors_m(result.T_world_scan).max() < 0.5
    # A systematic drift is not removed mid-loop (the plane rounds do that), but it shrinks everywhere.
    worst_m = [np.linalg.norm(T[:, :3, 3] - T_true[:, :3, 3], axis=1).max() for T in (T_odometry, result.T_world_scan)]
    assert worst_m[1] < worst_m[0] / 2


@pytest.mark.slow
def test_a_third_candidate_is_registered_only_when_the_two_nearest_do_not_both_pass(monkeypatch):
    """3.8 laps of the town circuit: later local maps have three earlier visits. Each local map's two nearest
    candidates are registered first; the third only where those two do not both pass, here forced by failing the
    nearest candidate's registration of every even local map."""
    from pa_cli.loops import closure
    from pa_cli.loops.verification import Registration

    points, T_true = _simulated_loops("town", scans=720, step_m=2.5, path="circuit")
    T_odometry = _drifted(T_true, 0.005, 1.002)
    registered: list[tuple[int, int]] = []
    original = closure._register

    def register(pairs, maps, cfg, **kwargs):
        out = original(pairs, maps, cfg, **kwargs)
        if not registered:  # the first batch: fail the nearest candidate of every even local map
            for q in {p.query for p in pairs if p.query % 2 == 0}:
                nearest = next(p for p in pairs if p.query == q)
                out[q, nearest.ref] = Registration(np.eye(4), 0.0, 0.0, float("inf"), converged=False)
        registered.extend((p.query, p.ref) for p in pairs)
        return out

    monkeypatch.setattr(closure, "_register", register)
    result = close_loops(points, T_odometry, LoopClosureConfig(), LoopsConfig().min_separation_m)
    by_query: dict[int, list] = {}
    for c in result.candidates:
        by_query.setdefault(c.query_map, []).append(c)
    triples = [records for records in by_query.values() if len(records) == 3]
    both_passed = [r for r in triples if r[0].accepted and r[1].accepted]
    forced = [r for r in triples if r[0].query_map % 2 == 0]
    assert both_passed and forced  # the premise: both branches are taken
    for first, second, third in triples:
        assert registered.count((first.query_map, first.ref_map)) == 1
        assert registered.count((second.query_map, second.ref_map)) == 1
        if first.accepted and second.accepted:
            assert (third.query_map, third.ref_map) not in registered
            assert third.fitness is None and not third.accepted and third.reason.startswith("not registered")
        else:
            assert registered.count((third.query_map, third.ref_map)) == 1 and third.fitness is not None
    assert all(not r[0].accepted and r[0].reason == "registration did not converge" for r in forced)
    assert any(r[2].accepted for r in forced)  # the third candidate closes a place whose nearest one failed
    errors = _closure_errors(result, T_true)
    assert errors and max(errors) < 0.5


def test_wall_thickness_of_two_passes_matches_brute_force():
    """The bench's wall thickness: a wall tile seen on two passes, the second offset along its normal."""
    from bench.loops import REVISIT_GAP_M, wall_thickness

    rng = np.random.default_rng(5)
    planes = np.array([[1.0, 0.0, 0.0, -10.0], [0.0, 0.0, 1.0, 0.0]])  # the wall x = 10 and the ground
    y_m = np.r_[0.0, 1.0, 2.0, 3.0, 10.0 * REVISIT_GAP_M, 20.0 * REVISIT_GAP_M, 0.5, 1.5, 2.5]
    T_true = np.array([_pose(0.1 * k, (0.0, y, 0.0)) for k, y in enumerate(y_m)])
    offset_m, noise_m = 0.05, 0.01
    T_estimate = T_true.copy()
    T_estimate[6:, 0, 3] += offset_m  # the second pass lands offset_m off the first along the normal
    frames, world = [], {"truth": [], "estimate": []}
    for k, T in enumerate(T_true):
        if 4 <= k <= 5:  # away from the wall: ground only
            points_world = np.column_stack([rng.uniform(-5, 5, (300, 2)) + T[:2, 3], np.zeros(300)])
            labels = np.ones(300, dtype=np.int32)
        else:
            n = 400
            points_world = np.column_stack([10.0 + rng.normal(0, noise_m, n), rng.uniform(2, 18, n),
                                            rng.uniform(0, 5, n)])
            labels = np.zeros(n, dtype=np.int32)
            world["truth"].append(points_world)
            world["estimate"].append(points_world + (offset_m if k >= 6 else 0.0) * np.r_[1.0, 0.0, 0.0])
        frames.append((_transform(np.linalg.inv(T), points_world), labels))
    result = wall_thickness(frames, planes, T_true, {"truth": T_true, "estimate": T_estimate})

    def thickness(points: np.ndarray) -> float:
        centred = points - points.mean(axis=0)
        return float(np.sqrt(np.linalg.eigvalsh(centred.T @ centred / len(points))[0]))

    for name, parts in world.items():
        passes = [np.vstack(parts[:4]), np.vstack(parts[4:])]
        once_m = np.mean([thickness(p) for p in passes])
        assert result[name]["n_tiles"] == 1
        assert result[name]["once_m"] == pytest.approx(once_m, rel=1e-6)
        assert result[name]["revisited_m"] == pytest.approx(thickness(np.vstack(passes)), rel=1e-6)
    assert result["truth"]["ratio_median"] == pytest.approx(1.0, abs=0.1)
    # Two halves offset_m apart: sqrt(noise^2 + offset^2 / 4) against the noise alone.
    expected = np.hypot(noise_m, offset_m / 2) / noise_m
    assert result["estimate"]["ratio_median"] == pytest.approx(expected, rel=0.1)
