"""The calibration cost's exact derivatives (finite differences), the joint solver on synthetic
rigs, and the observability analysis on a degenerate rig and motion."""

from __future__ import annotations

import numpy as np
import pytest

from pa_cli.adjust.odometry_factors import OdometryFactors, OdometryModel
from pa_cli.calibration.composite import CalibrationCost, composite_second_order
from pa_cli.calibration.observability import analyse_extrinsics, describe_direction
from pa_cli.calibration.solver import solve_calibration
from pa_cli.config import PaConfig, SolverConfig
from pa_cli.core.geometry import exp_so3, rotation_angles
from pa_testing.calibration_problems import random_rig, rig_problem


def _scene(seed: int, n_base: int = 4, n_lidars: int = 3, noise_m: float = 0.02):
    rng = np.random.default_rng(seed)
    T_world_base, T_base_lidar = random_rig(n_base, n_lidars, rng)
    normals = rng.normal(size=(7, 3))
    centres = rng.normal(0, 4, (7, 3)) + [3, 0, 0]
    problem, layout = rig_problem(T_world_base, T_base_lidar, normals, centres, 3.0, 30, noise_m, seed + 1)
    return rng, problem, layout, layout.join(T_world_base, T_base_lidar)


def _fd_gradient_hessian(cost: CalibrationCost, state: np.ndarray, h: float, h2: float):
    n = 6 * len(state)

    def f(x: np.ndarray) -> float:
        return cost.cost(cost.layout.retract(state, x.reshape(-1, 6)))

    E = np.eye(n)
    g = np.array([(f(h * E[i]) - f(-h * E[i])) / (2 * h) for i in range(n)])
    H = np.zeros((n, n))
    for i in range(n):
        for j in range(i, n):
            a, b = h2 * E[i], h2 * E[j]
            H[i, j] = H[j, i] = (f(a + b) - f(a - b) - f(b - a) + f(-a - b)) / (4 * h2 * h2)
    return g, H


@pytest.mark.parametrize("seed", [3, 11])
def test_gradient_and_hessian_match_finite_differences(seed: int) -> None:
    rng, problem, layout, state = _scene(seed)
    cost = CalibrationCost(problem, layout)
    state = cost.layout.retract(state, rng.normal(0, 0.01, (layout.n_state, 6)))  # away from the optimum: g != 0
    _, g, H, _, _ = cost.derivatives(state)
    g_fd, H_fd = _fd_gradient_hessian(cost, state, 1e-6, 1e-4)
    assert np.abs(g - g_fd).max() < 1e-7 * np.abs(g).max()
    assert np.abs(H - H_fd).max() < 1e-6 * np.abs(H).max()
    # the second-order chain-rule term matters at this accuracy: without it the Hessian is off
    second = composite_second_order(state[layout.base_of_virtual], layout.composite(state),
                                    np.ones((len(layout.base_of_virtual), 6)), layout.lidar_of_virtual == 0)
    assert np.abs(second).max() > 0


def test_hessian_without_second_order_term_fails_finite_differences(monkeypatch: pytest.MonkeyPatch) -> None:
    rng, problem, layout, state = _scene(3)
    cost = CalibrationCost(problem, layout)
    state = cost.layout.retract(state, rng.normal(0, 0.01, (layout.n_state, 6)))
    _, H_fd = _fd_gradient_hessian(cost, state, 1e-6, 1e-4)
    import pa_cli.calibration.composite as composite

    monkeypatch.setattr(composite, "composite_second_order", lambda T, C, g, b: np.zeros((len(T), 12, 12)))
    _, _, H, _, _ = cost.derivatives(state)
    assert np.abs(H - H_fd).max() > 1e-4 * np.abs(H).max()


def test_pose_terms_enter_gradient_and_hessian() -> None:
    rng, problem, layout, truth = _scene(5, n_lidars=2)
    T_world_base, _ = layout.split(truth)
    odometry = OdometryFactors(T_world_base, OdometryModel.from_config(PaConfig()))
    cost = CalibrationCost(problem, layout, [odometry])
    moved = layout.retract(truth, rng.normal(0, 0.01, (layout.n_state, 6)))
    g = cost.derivatives(moved)[1]
    g_fd, _ = _fd_gradient_hessian(cost, moved, 1e-6, 1e-4)
    assert np.abs(g - g_fd).max() < 1e-6 * np.abs(g).max()
    # the odometry Hessian is Gauss-Newton, exact where its residuals vanish: base poses at the odometry
    step = np.zeros((layout.n_state, 6))
    step[layout.n_base:] = rng.normal(0, 0.01, (layout.n_lidars - 1, 6))
    at_odometry = layout.retract(truth, step)
    H = cost.derivatives(at_odometry)[2]
    _, H_fd = _fd_gradient_hessian(cost, at_odometry, 1e-6, 1e-4)
    assert np.abs(H - H_fd).max() < 1e-6 * np.abs(H).max()


def _perturb_extrinsics(state: np.ndarray, n_base: int, rng: np.random.Generator, angle_deg: float,
                        shift_m: float) -> np.ndarray:
    out = state.copy()
    for k in range(n_base, len(state)):
        axis = rng.normal(size=3)
        out[k, :3, :3] = exp_so3((np.deg2rad(angle_deg) * axis / np.linalg.norm(axis))[None])[0] @ out[k, :3, :3]
        shift = rng.normal(size=3)
        out[k, :3, 3] += shift_m * shift / np.linalg.norm(shift)
    return out


@pytest.mark.parametrize("seed", [1, 2])
def test_joint_solver_recovers_extrinsics_from_5_deg_and_20_cm(seed: int) -> None:
    rng, problem, layout, truth = _scene(seed, n_base=5, noise_m=0.0)
    cost = CalibrationCost(problem, layout)
    start = _perturb_extrinsics(truth, layout.n_base, rng, 5.0, 0.2)
    final, report = solve_calibration(cost, start, SolverConfig(max_iterations=100))
    # gauge: base pose 0 fixed, so the noise-free optimum is the truth
    for k in range(layout.n_base, len(final)):
        turned = np.rad2deg(rotation_angles((final[k, :3, :3].T @ truth[k, :3, :3])[None])[0])
        assert turned < 1e-4 and np.linalg.norm(final[k, :3, 3] - truth[k, :3, 3]) < 1e-5
    assert report["cost_final_m2"] < 1e-10 * report["cost_initial_m2"]


def _corridor(turns: bool, seed: int = 0):
    """A rig driving straight down a corridor (floor, ceiling, two walls) without turning, or
    turning through a room with walls in three orientations."""
    rng = np.random.default_rng(seed)
    n_base = 6
    T_world_base = np.tile(np.eye(4), (n_base, 1, 1))
    T_world_base[:, 0, 3] = np.arange(n_base) * 1.0
    T_base_lidar = np.tile(np.eye(4), (2, 1, 1))
    T_base_lidar[1, :3, :3] = exp_so3(np.array([[0.1, 0.2, -0.5]]))[0]
    T_base_lidar[1, :3, 3] = [0.3, -0.4, 0.2]
    normals = np.array([[0, 0, 1.0], [0, 0, 1.0], [0, 1.0, 0], [0, 1.0, 0]])
    centres = np.array([[3, 0, -1.5], [3, 0, 2.0], [3, 2.0, 0], [3, -2.0, 0]])
    if turns:
        T_world_base[:, :3, :3] = exp_so3(np.column_stack([np.zeros(n_base), np.zeros(n_base),
                                                           np.linspace(-0.6, 0.6, n_base)]))
        normals = np.vstack([normals, [[1.0, 0, 0], [1.0, 0.3, 0]]])
        centres = np.vstack([centres, [[8.0, 0, 0], [-4.0, 0, 0]]])
    problem, layout = rig_problem(T_world_base, T_base_lidar, normals, centres, 6.0, 200, 0.01, seed)
    odometry = OdometryFactors(T_world_base, OdometryModel.from_config(PaConfig()))
    return rng, CalibrationCost(problem, layout, [odometry]), layout.join(T_world_base, T_base_lidar)


def test_straight_corridor_reports_translation_along_travel_unobservable() -> None:
    _, cost, truth = _corridor(turns=False)
    H_gn = cost.derivatives(truth)[3]
    (lidar1,) = analyse_extrinsics(H_gn, cost.layout.n_base, cost.layout.n_lidars, lever_arm_m=10.0,
                                   point_sigma_m=0.1, unobservable_sigma_m=0.05)
    assert lidar1.as_dict()["unobservable"] == ["lidar1: translation along base x"]
    assert lidar1.basis.shape == (6, 5)
    assert np.abs(lidar1.basis[3]).max() < 1e-3  # (nearly) no step along base x is allowed


def test_turning_through_a_room_observes_every_direction() -> None:
    _, cost, truth = _corridor(turns=True)
    (lidar1,) = analyse_extrinsics(cost.derivatives(truth)[3], cost.layout.n_base, cost.layout.n_lidars, 10.0,
                                   0.1, 0.05)
    assert lidar1.unobservable == [] and lidar1.basis.shape == (6, 6)


def test_held_direction_stays_at_its_initial_value() -> None:
    rng, cost, truth = _corridor(turns=False)
    lay = cost.layout
    (lidar1,) = analyse_extrinsics(cost.derivatives(truth)[3], lay.n_base, lay.n_lidars, 10.0, 0.1, 0.05)
    start = _perturb_extrinsics(truth, lay.n_base, rng, 2.0, 0.1)
    final, _ = solve_calibration(cost, start, SolverConfig(max_iterations=100), [lidar1.basis])
    X_start, X_final, X_true = start[-1], final[-1], truth[-1]
    # observable: rotation and the y, z translation reach the truth; x stays where --init put it
    assert np.rad2deg(rotation_angles((X_final[:3, :3].T @ X_true[:3, :3])[None])[0]) < 0.02
    assert np.abs(X_final[1:3, 3] - X_true[1:3, 3]).max() < 2e-3
    assert abs(X_final[0, 3] - X_start[0, 3]) < 1e-3
    assert abs(X_start[0, 3] - X_true[0, 3]) > 1e-2  # the held coordinate did start away from the truth


@pytest.mark.parametrize(("direction", "words"), [
    ([0, 0, 0, 0, 0, 1], "translation along base z"),
    ([1, 0, 0, 0, 0, 0], "rotation about base x"),
    ([0, 0.6, 0.8, 0, 0, 0], "rotation about base (0.00, 0.60, 0.80)"),
    ([0, 0, 0.7, 0, 0.7, 0], "rotation about base z with translation along base y"),
])
def test_directions_in_words(direction: list[float], words: str) -> None:
    assert describe_direction(np.array(direction, dtype=float)) == words
