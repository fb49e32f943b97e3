"""`pa adjust --backend`, `--workers` / `--scheduler` on the command line, and the bounded point cache."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pa_cli.io.problem import save_problem
from pa_cli.io.trajectory import read_trajectory
from pa_cli.sources.cache import CachedSource
from pa_cli.sources.memory import ArraySource
from pa_testing.synthetic_problems import make_scene, perturb


@pytest.fixture
def scene(tmp_path):
    problem, T_gt = make_scene(40, 120, 8, points_per_observation=12, noise_m=0.005, seed=9)
    problem.T_world_scan = perturb(T_gt, np.deg2rad(1.0), 0.1, seed=10)
    path = tmp_path / "problem.npz"
    save_problem(path, problem)
    return path


def _adjust(run_pa, path, tmp_path, name, *args):
    out, report = tmp_path / f"{name}.txt", tmp_path / f"{name}.json"
    code, _, err = run_pa("adjust", path, "--out", out, "--report", report, *args)
    assert code == 0, err
    return read_trajectory(out).T_world_scan, json.loads(report.read_text()), " ".join(err.split())


def test_hierarchical_backend_reaches_the_flat_poses(run_pa, scene, tmp_path):
    T_flat, flat, err_flat = _adjust(run_pa, scene, tmp_path, "flat", "--backend", "flat")
    T_hier, hier, err_hier = _adjust(run_pa, scene, tmp_path, "hier", "--backend", "hierarchical")
    assert flat["solver"] == "newton" and hier["solver"] == "hierarchical"
    assert "hierarchical_min_scans" not in err_flat + err_hier  # an explicit backend is not announced
    assert hier["cost_final_m2"] == pytest.approx(flat["cost_final_m2"], rel=1e-6)
    np.testing.assert_allclose(T_hier[:, :3, 3], T_flat[:, :3, 3], atol=1e-5)


def test_default_backend_is_picked_by_size_and_said_with_verbose(run_pa, scene, tmp_path):
    _, small, err = _adjust(run_pa, scene, tmp_path, "default")
    assert small["solver"] == "newton" and "hierarchical_min_scans" not in err  # not asked for
    _, small, err = _adjust(run_pa, scene, tmp_path, "verbose", "-v")
    assert small["solver"] == "newton" and "40 scans < advanced.solver.hierarchical_min_scans (3000)" in err
    config = tmp_path / "few.yaml"
    config.write_text("advanced:\n  solver:\n    hierarchical_min_scans: 30\n")
    _, large, err = _adjust(run_pa, scene, tmp_path, "by_size", "--config", config, "--verbose")
    assert large["solver"] == "hierarchical" and "using the hierarchical backend" in err


@pytest.mark.parametrize("args, message", [
    (["--workers", "2", "--scheduler", "tcp://127.0.0.1:8786"], "not both"),
    (["--scheduler", "127.0.0.1:8786"], "tcp://HOST:PORT"),
    (["--backend", "tree"], "tree"),
    (["--workers", "-1"], "--workers")])
def test_bad_execution_options_are_usage_errors(run_pa, scene, tmp_path, args, message):
    code, _, err = run_pa("adjust", scene, "--out", tmp_path / "x.txt", *args)
    assert code == 2 and message in " ".join(err.split())


def test_hierarchical_with_lm_is_a_known_error(run_pa, scene, tmp_path):
    code, _, err = run_pa("adjust", scene, "--out", tmp_path / "x.txt", "--backend", "hierarchical", "--solver", "lm")
    assert code == 1 and "--backend flat" in " ".join(err.split())


def test_point_cache_stops_growing_at_its_budget():
    rng = np.random.default_rng(0)
    scans = [rng.normal(size=(100, 3)) for _ in range(5)]  # 1200 bytes each as float32
    reads = []

    class Counting(ArraySource):
        def points(self, k):
            reads.append(k)
            return super().points(k)

    cached = CachedSource(Counting(scans), max_bytes=2500)
    for _ in range(3):
        for k in range(5):
            assert np.array_equal(cached.points(k), scans[k].astype(np.float32))
    assert cached.n_bytes == 2400
    assert reads == [0, 1, 2, 3, 4, 2, 3, 4, 2, 3, 4]  # the first two stay cached, the rest are re-read


def test_refine_with_the_hierarchical_backend_matches_flat(run_pa, tmp_path):
    """With the registered motions as pose terms, every round of the hierarchical backend runs its final flat pass
    alone (`warm_config`): the first from the chain of the motions, the second from the first's optimum; the poses
    are the flat backend's. (Its layers are tested in tests/unit/adjust/test_hierarchical.py.)"""
    from pa_cli.io.trajectory import write_kitti
    from pa_testing.room_scene import ground_truth_poses, write_room_folder

    room = write_room_folder(tmp_path)
    init = tmp_path / "init.txt"
    write_kitti(init, perturb(ground_truth_poses(), np.deg2rad(0.5), 0.05, seed=3))
    common = "sensor: {max_range_m: 30.0}\nscene: {plane_voxel_m: 1.0}\nrefine: {max_rounds: 2}\nmap: {voxel_m: 0.2}\n"
    flat_cfg, hier_cfg = tmp_path / "flat.yaml", tmp_path / "hier.yaml"
    flat_cfg.write_text(common)
    hier_cfg.write_text(common + "advanced: {solver: {solver: hierarchical, hierarchical_window_scans: 4, "
                        "hierarchical_overlap_scans: 1, hierarchical_final_iterations: 50}}\n")
    poses = {}
    for name, cfg in (("flat", flat_cfg), ("hier", hier_cfg)):
        out = tmp_path / f"{name}.ply"
        code, _, err = run_pa("refine", room / "scans", "--out", out, "--config", cfg, "--poses", init, "-q",
                              "--workers", "0")
        assert code == 0, err
        report = json.loads(out.with_name(f"{name}_report.json").read_text())
        assert [r["solver"]["solver"] for r in report["rounds"]] == ["newton", "newton"]
        poses[name] = read_trajectory(out.with_name(f"{name}_poses_kitti.txt")).T_world_scan
    np.testing.assert_allclose(poses["hier"][:, :3, 3], poses["flat"][:, :3, 3], atol=1e-5)
    np.testing.assert_allclose(poses["hier"][:, :3, :3], poses["flat"][:, :3, :3], atol=1e-6)


def test_covariance_lower_bound_counts_the_blocks_of_the_smallest_pattern():
    """Brute-force block counts of the pair form (every pair of scans sharing a feature) and of the
    node forms (a block per node and per observation of a node, pairs for the other features)."""
    from pa_cli.adjust.covariance import LARGE_FEATURE_FACTOR
    from pa_cli.adjust.linalg import PAIR_MAX_SCANS
    from pa_cli.core.problem import make_problem
    from pa_cli.refine.stages import COVARIANCE_BYTES_PER_BLOCK, covariance_lower_bound_gb

    rng = np.random.default_rng(4)
    seen_by = {0: range(0, 30), 1: range(10, 15), 2: range(28, 40)}  # feature -> the scans seeing it
    plane = np.concatenate([[f] * len(s) for f, s in seen_by.items()])
    scan = np.concatenate([list(s) for s in seen_by.values()])
    points = rng.normal(size=(len(plane), 20, 3))
    clusters = np.einsum("nki,nkj->nij", np.pad(points, ((0, 0), (0, 0), (0, 1)), constant_values=1.0),
                         np.pad(points, ((0, 0), (0, 0), (0, 1)), constant_values=1.0))
    problem = make_problem(plane, scan, clusters, n_scans=40)
    median = np.median([len(s) for s in seen_by.values()])
    counts = []
    for node in (lambda s: False, lambda s: len(s) > PAIR_MAX_SCANS, lambda s: len(s) > LARGE_FEATURE_FACTOR * median):
        pairs = {(a, b) for s in seen_by.values() if not node(s) for a in s for b in s if a < b}  # once each
        nodes = [s for s in seen_by.values() if node(s)]
        counts.append(40 + len(nodes) + sum(len(s) for s in nodes) + len(pairs))
    assert counts[1] < counts[0]  # here the node form is the smaller
    assert covariance_lower_bound_gb(problem) * 1e9 == pytest.approx(min(counts) * COVARIANCE_BYTES_PER_BLOCK)


@pytest.mark.parametrize("limit, message", [("execution: {memory_budget_gb: 1.0e-7}", "needs at least")])
def test_refine_skips_a_covariance_above_the_memory_budget(run_pa, tmp_path, limit, message):
    from pa_cli.io.trajectory import write_kitti
    from pa_testing.room_scene import ground_truth_poses, write_room_folder

    room = write_room_folder(tmp_path)
    init = tmp_path / "init.txt"
    write_kitti(init, perturb(ground_truth_poses(), np.deg2rad(0.5), 0.05, seed=3))
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(f"sensor: {{max_range_m: 30.0}}\nscene: {{plane_voxel_m: 1.0}}\nrefine: {{max_rounds: 1}}\n"
                   f"{limit}\n")
    out = tmp_path / "m.ply"
    code, _, err = run_pa("refine", room / "scans", "--out", out, "--config", cfg, "--poses", init, "-q")
    assert code == 0, err
    report = json.loads(out.with_name("m_report.json").read_text())
    assert message in report["covariance"]["error"] and "execution.memory_budget_gb" in " ".join(err.split())
    assert not out.with_name("m_covariance.npz").exists() and out.exists()


def test_refine_on_workers_associates_in_windows_and_matches_the_process(run_pa, tmp_path):
    """`pa refine --workers 2`: the workers read their windows' scans for both association passes;
    the planes found and the refined poses are those of the run in this process (the merged
    window voxels equal one pass's voxels to rounding)."""
    from pa_cli.io.trajectory import write_kitti
    from pa_testing.room_scene import ground_truth_poses, write_room_folder

    room = write_room_folder(tmp_path)
    init = tmp_path / "init.txt"
    write_kitti(init, perturb(ground_truth_poses(), np.deg2rad(0.5), 0.05, seed=3))
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("sensor: {max_range_m: 30.0}\nscene: {plane_voxel_m: 1.0}\nrefine: {max_rounds: 2}\n"
                   "map: {voxel_m: 0.2}\nadvanced: {execution: {window_scans: 3}}\n")
    poses, rounds = {}, {}
    for name, extra in (("process", []), ("workers", ["--workers", "2"])):
        out = tmp_path / f"{name}.ply"
        code, _, err = run_pa("refine", room / "scans", "--out", out, "--config", cfg, "--poses", init, "-q", *extra)
        assert code == 0, err
        rounds[name] = json.loads(out.with_name(f"{name}_report.json").read_text())["rounds"]
        poses[name] = read_trajectory(out.with_name(f"{name}_poses_kitti.txt")).T_world_scan
    counts = ("n_planes", "n_observations", "n_points")
    for a, b in zip(rounds["workers"], rounds["process"], strict=True):
        assert [a[key] for key in counts] == [b[key] for key in counts]
    np.testing.assert_allclose(poses["workers"], poses["process"], rtol=0, atol=1e-7)
    assert np.abs(poses["process"] - read_trajectory(init).T_world_scan).max() > 1e-3  # the poses did move

