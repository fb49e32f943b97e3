"""The hierarchical backend: exact keyframe clusters, the flat optimum, the gauge, the memory
budget, and the same poses whether the windows run in this process or on a dask cluster."""

from __future__ import annotations

import numpy as np
import pytest

from pa_cli.adjust import plane_cost, solve
from pa_cli.adjust.hierarchical import (
    choose_backend,
    core_bounds,
    hierarchical_adjust,
    keyframe_problem,
    warm_config,
)
from pa_cli.adjust.odometry_factors import OdometryFactors, OdometryModel
from pa_cli.config import ExecutionConfig, SolverConfig
from pa_cli.core.geometry import rigid_inverse
from pa_cli.core.problem import FEATURE_EDGE, FEATURE_PLANE, make_problem
from pa_cli.errors import SolverError
from pa_cli.runtime.distributed import Execution, current_execution, execution
from pa_testing.synthetic_problems import make_scene, perturb, random_poses

TIGHT = {"cost_tolerance": 1e-14, "gradient_tolerance": 1e-12, "step_tolerance": 1e-14,
         "hierarchical_cost_tolerance": 1e-14}


def _scene(n_scans: int = 120, seed: int = 3):
    problem, T_gt = make_scene(n_scans, 3 * n_scans, 12, points_per_observation=15, noise_m=0.01, seed=seed)
    return problem, perturb(T_gt, np.deg2rad(1.0), 0.1, seed=seed + 1)


@pytest.mark.parametrize("n_scans, core, shift", [(10, 3, 0), (10, 4, 2), (7, 7, 0), (5, 8, 4), (9, 4, 3)])
def test_cores_cover_every_scan_once_in_order(n_scans, core, shift):
    bounds = core_bounds(n_scans, core, shift)
    assert bounds[0] == 0 and bounds[-1] == n_scans
    sizes = np.diff(bounds)
    assert np.all(sizes > 0) and np.all(sizes <= core)
    if shift and shift < n_scans:
        assert sizes[0] == shift


@pytest.mark.parametrize("core, with_edges", [(9, False), (30, False), (9, True)])
def test_keyframe_cost_equals_the_flat_cost_of_the_reanchored_scans(core, with_edges):
    problem, _ = _scene(60)
    if with_edges:  # every third feature an edge: its cost is lambda_min + lambda_mid of the same clusters
        kind = np.where(np.arange(problem.n_planes) % 3 == 0, FEATURE_EDGE, FEATURE_PLANE)
        problem = make_problem(problem.plane_index, problem.scan_index, problem.clusters, problem.n_scans,
                               feature_kind=kind)
    rng = np.random.default_rng(7)
    bounds = core_bounds(problem.n_scans, core, 0)
    core_of_scan = np.repeat(np.arange(len(bounds) - 1), np.diff(bounds))
    T_world_scan = random_poses(problem.n_scans, rng, 0.3, 3.0)
    T_world_kf = T_world_scan[bounds[:-1]]
    T_kf_scan = rigid_inverse(T_world_kf)[core_of_scan] @ T_world_scan
    kf = keyframe_problem(problem, core_of_scan, len(bounds) - 1, T_kf_scan)
    moved_kf = random_poses(len(T_world_kf), rng, 0.3, 3.0)
    T_moved = moved_kf[core_of_scan] @ T_kf_scan
    # planes seen within one core only drop out of the keyframe problem; rigid motions of the
    # core leave their cost unchanged, so the difference of the two costs is the same constant
    within_one_core = plane_cost(problem, T_world_scan) - plane_cost(kf, T_world_kf)
    scale = plane_cost(problem, T_moved)
    assert scale - plane_cost(kf, moved_kf) == pytest.approx(within_one_core, abs=1e-10 * scale)
    assert np.count_nonzero(kf.feature_kind == FEATURE_EDGE) == (problem.n_planes + 2) // 3 * with_edges
    if core == 9:  # every plane (seen by 12 consecutive scans) spans two cores
        assert kf.n_points == problem.n_points and within_one_core == pytest.approx(0.0, abs=1e-10 * scale)
    else:
        assert kf.n_points < problem.n_points and within_one_core > 1e-3 * scale


def test_hierarchical_reaches_the_flat_optimum_and_keeps_the_gauge_pose():
    problem, T0 = _scene()
    config = SolverConfig(fixed_pose=37, hierarchical_window_scans=25, hierarchical_overlap_scans=5, **TIGHT)
    flat = solve(problem, T0, config)
    hier = solve(problem, T0, config.model_copy(update={"solver": "hierarchical"}))
    assert hier.report["solver"] == "hierarchical"
    assert hier.report["cost_final_m2"] == pytest.approx(flat.report["cost_final_m2"], rel=1e-6)
    assert hier.report["cost_final_m2"] < 0.01 * hier.report["cost_initial_m2"]
    np.testing.assert_array_equal(hier.T_world_scan[37], T0[37])
    np.testing.assert_allclose(hier.T_world_scan[:, :3, 3], flat.T_world_scan[:, :3, 3], atol=1e-6)


def test_layers_alone_come_close_and_every_layer_lowers_the_cost():
    problem, T0 = _scene()
    config = SolverConfig(hierarchical_window_scans=25, hierarchical_cycles=2, hierarchical_final_iterations=0)
    result = hierarchical_adjust(problem, T0, config)
    optimum = solve(problem, T0, SolverConfig(**TIGHT)).report["cost_final_m2"]
    globals_ = [s["cost_m2"] for s in result.stages if s["stage"].endswith("global")]
    assert [s["stage"] for s in result.stages] == ["cycle 1 windows", "cycle 1 global", "cycle 2 windows",
                                                   "cycle 2 global"]
    assert globals_[0] < result.stages[0]["cost_m2"] < plane_cost(problem, T0)
    assert globals_[-1] <= optimum * (1 + 1e-3)
    assert result.fields["iterations"] == 0 and result.fields["stop_reason"] == "hierarchical_cycles"


def test_pose_terms_enter_the_final_pass():
    problem, T0 = _scene(80)
    model = OdometryModel(point_sigma_m=0.01, translation_sigma_m=0.05, translation_sigma_per_m=0.01,
                          rotation_sigma_rad=np.deg2rad(0.5), rotation_sigma_per_rad=0.02,
                          rotation_sigma_rad_per_m=np.deg2rad(0.01))
    factors = OdometryFactors(T0, model)  # strong enough to move the optimum
    config = SolverConfig(hierarchical_window_scans=20, **TIGHT)
    flat = solve(problem, T0, config, terms=[factors])
    hier = solve(problem, T0, config.model_copy(update={"solver": "hierarchical"}), terms=[factors])
    total = {name: r.report["cost_final_m2"] + r.report["odometry_cost_final_m2"] for name, r in
             (("flat", flat), ("hier", hier))}
    assert flat.report["odometry_cost_final_m2"] > 1e-3 * flat.report["cost_final_m2"]
    assert total["hier"] == pytest.approx(total["flat"], rel=1e-6)
    assert hier.report["odometry_cost_final_m2"] == pytest.approx(flat.report["odometry_cost_final_m2"], rel=1e-4)


def test_layers_that_raise_the_whole_objective_are_discarded():
    problem, T0 = _scene(60)
    tight = OdometryModel(point_sigma_m=0.01, translation_sigma_m=1e-5, translation_sigma_per_m=0.0,
                          rotation_sigma_rad=1e-6, rotation_sigma_per_rad=0.0, rotation_sigma_rad_per_m=0.0)
    factors = OdometryFactors(T0, tight)  # holds the relative motions of T0: the features' optimum costs more
    config = SolverConfig(hierarchical_window_scans=20, hierarchical_final_iterations=1)
    result = hierarchical_adjust(problem, T0, config, terms=[factors])
    assert any("raised the whole objective" in w for w in result.warnings)
    total = plane_cost(problem, result.T_world_scan) + factors.cost(result.T_world_scan)
    assert total <= plane_cost(problem, T0) + factors.cost(T0)
    kept = hierarchical_adjust(problem, T0, config)  # without terms the layers' result is kept
    assert not any("raised the whole objective" in w for w in kept.warnings)


def test_discarded_layers_leave_the_final_pass_the_whole_flat_solve():
    """With the layers' result discarded the final pass starts from the initial poses; it then runs
    to the flat optimum of features and terms, not only hierarchical_final_iterations iterations."""
    problem, T0 = _scene(60)
    tight = OdometryModel(point_sigma_m=0.01, translation_sigma_m=1e-3, translation_sigma_per_m=0.0,
                          rotation_sigma_rad=1e-4, rotation_sigma_per_rad=0.0, rotation_sigma_rad_per_m=0.0)
    factors = OdometryFactors(T0, tight)
    config = SolverConfig(hierarchical_window_scans=20, hierarchical_final_iterations=1, **TIGHT)
    result = hierarchical_adjust(problem, T0, config, terms=[factors])
    assert any("raised the whole objective" in w for w in result.warnings)
    flat = solve(problem, T0, config, terms=[factors])
    assert flat.report["iterations"] > 1
    total = plane_cost(problem, result.T_world_scan) + factors.cost(result.T_world_scan)
    assert total == pytest.approx(flat.report["cost_final_m2"] + flat.report["odometry_cost_final_m2"], rel=1e-6)


def test_final_pass_above_the_memory_budget_is_skipped_with_a_warning():
    problem, T0 = _scene(60)
    config = SolverConfig(solver="hierarchical", hierarchical_window_scans=20)
    with execution(ExecutionConfig(memory_budget_gb=1e-6)):
        result = solve(problem, T0, config)
    assert result.report["iterations"] == 0
    assert any("memory_budget_gb" in w for w in result.report["warnings"])
    assert result.report["cost_final_m2"] < 0.01 * result.report["cost_initial_m2"]


def test_a_warm_start_runs_the_final_flat_pass_alone_within_the_budget():
    """From the optimum of a nearby problem (here: the same problem's hierarchical optimum, its
    clusters perturbed) the flat pass alone reaches the hierarchical run's optimum; above the memory
    budget, or for a flat config, the config is kept."""
    problem, T0 = _scene(60)
    config = SolverConfig(solver="hierarchical", hierarchical_window_scans=20, **TIGHT)
    T_near = solve(problem, T0, config).T_world_scan
    rng = np.random.default_rng(11)
    nearby = make_problem(problem.plane_index, problem.scan_index,
                          problem.clusters * (1.0 + 1e-3 * rng.standard_normal((problem.n_observations, 1, 1))),
                          problem.n_scans)
    warm = warm_config(config, nearby)
    assert warm.solver == "newton" and warm.cost_tolerance == config.hierarchical_cost_tolerance
    assert warm.max_iterations == config.max_iterations
    from_warm = solve(nearby, T_near, warm)
    from_layers = solve(nearby, T_near, config)
    assert from_warm.report["solver"] == "newton"
    assert from_warm.report["cost_final_m2"] == pytest.approx(from_layers.report["cost_final_m2"], rel=1e-9)
    np.testing.assert_allclose(from_warm.T_world_scan[:, :3, 3], from_layers.T_world_scan[:, :3, 3], atol=1e-6)
    with execution(ExecutionConfig(memory_budget_gb=1e-6)):
        assert warm_config(config, nearby) is config
    flat = config.model_copy(update={"solver": "newton"})
    assert warm_config(flat, nearby) is flat


def test_in_process_map_keeps_order_and_bounds_tasks_in_flight():
    assert current_execution().client is None
    assert Execution(memory_budget_gb=1.0).map(abs, (x for x in [-3, 2, -1])) == [3, 2, 1]
    assert Execution(memory_budget_gb=1.0).max_in_flight(item_bytes=0.4e9) == 2
    assert Execution(memory_budget_gb=1.0).max_in_flight(item_bytes=5e9) == 1


@pytest.mark.slow
def test_dask_local_cluster_gives_the_in_process_poses():
    pytest.importorskip("distributed")
    problem, T0 = _scene(60, seed=11)
    config = SolverConfig(solver="hierarchical", hierarchical_window_scans=20, hierarchical_final_iterations=2)
    local = solve(problem, T0, config)
    with execution(ExecutionConfig(workers=2, memory_budget_gb=2.0)) as ex:
        assert ex.n_workers == 2
        assert ex.map(abs, iter(range(-7, 0)), item_bytes=1.0) == list(range(7, 0, -1))
        remote = solve(problem, T0, config)
    assert current_execution().client is None
    np.testing.assert_allclose(remote.T_world_scan, local.T_world_scan, rtol=0, atol=1e-9)
    assert remote.report["cost_final_m2"] == pytest.approx(local.report["cost_final_m2"], rel=1e-12)


def test_default_settings_land_within_1e_4_of_the_flat_optimum():
    problem, T0 = _scene(150, seed=5)
    flat = solve(problem, T0, SolverConfig(**TIGHT)).report["cost_final_m2"]
    hier = solve(problem, T0, SolverConfig(solver="hierarchical", hierarchical_window_scans=40)).report
    assert hier["cost_final_m2"] == pytest.approx(flat, rel=1e-4)
    assert hier["converged"]


@pytest.mark.parametrize("backend, solver, n_scans, expected, says", [
    (None, "newton", 2999, "newton", True), (None, "newton", 3000, "hierarchical", True),
    (None, "lm", 5000, "lm", False), ("flat", "newton", 5000, "newton", False),
    ("hierarchical", "newton", 10, "hierarchical", False)])
def test_backend_by_size_says_what_it_picked(backend, solver, n_scans, expected, says):
    config, message = choose_backend(SolverConfig(solver=solver, hierarchical_min_scans=3000), n_scans, backend)
    assert config.solver == expected
    assert (message is not None) == says
    if says:
        assert expected.replace("newton", "flat") in message and str(n_scans) in message


def test_hierarchical_lm_and_unknown_backends_are_refused():
    with pytest.raises(SolverError, match="--backend flat"):
        choose_backend(SolverConfig(solver="lm"), 10, "hierarchical")
    with pytest.raises(SolverError, match="unknown backend 'tree'"):
        choose_backend(SolverConfig(), 10, "tree")


def test_windows_solve_alike_wherever_they_lie_along_the_sequence(monkeypatch):
    """A window's refined poses and its iterations do not depend on where the world origin is: the
    same window moved kilometres away (one rigid motion of all its poses) takes the same steps to
    the same poses, moved alike, and the held pose comes back exactly as given."""
    from pa_cli.adjust import hierarchical
    from pa_cli.adjust.newton import solve_newton

    iterations = []

    def counting(*args, **kwargs):
        result = solve_newton(*args, **kwargs)
        iterations.append(result.fields["iterations"])
        return result

    monkeypatch.setattr(hierarchical, "solve_newton", counting)
    problem, T0 = _scene(40, seed=11)
    config = SolverConfig(fixed_pose=5, cost_tolerance=1e-8)  # the windows' tolerance
    far = random_poses(1, np.random.default_rng(12), 0.5, 1.0)[0]
    far[:3, 3] += [8000.0, -3000.0, 50.0]  # a window 8.5 km from the origin
    at_origin = hierarchical.solve_from_held_pose(problem, T0, config)
    moved = hierarchical.solve_from_held_pose(problem, far @ T0, config)
    assert iterations[0] == iterations[1]
    np.testing.assert_array_equal(moved[5], (far @ T0)[5])
    np.testing.assert_allclose(moved[:, :3, :3], (far @ at_origin)[:, :3, :3], atol=1e-9)
    np.testing.assert_allclose(moved[:, :3, 3], (far @ at_origin)[:, :3, 3], atol=1e-7)
    flat = solve_newton(problem, T0, config.model_copy(update=TIGHT)).T_world_scan
    assert plane_cost(problem, at_origin) == pytest.approx(plane_cost(problem, flat), rel=1e-7)
