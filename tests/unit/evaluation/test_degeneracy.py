"""Degeneracy from the plane information: a corridor leaves translation along it free."""

import numpy as np
import pytest

from pa_cli.adjust.odometry_factors import OdometryFactors, OdometryModel
from pa_cli.core.clusters import points_to_cluster
from pa_cli.core.geometry import exp_so3
from pa_cli.core.problem import make_problem
from pa_cli.evaluation.degeneracy import describe, plane_information, scan_degeneracy, travel_frames

MODEL = OdometryModel(point_sigma_m=0.01, translation_sigma_m=0.02, translation_sigma_per_m=0.01,
                      rotation_sigma_rad=np.deg2rad(0.1), rotation_sigma_per_rad=0.02,
                      rotation_sigma_rad_per_m=np.deg2rad(0.01))


def _corridor(heading_rad: float, with_end_wall: bool, n_scans: int = 6, seed: int = 0):
    """Floor, ceiling and two walls along the heading; scans 0.5 m apart along it; exact points.
    With an end wall, scans also see a plane square to the corridor."""
    rng = np.random.default_rng(seed)
    along = np.array([np.cos(heading_rad), np.sin(heading_rad), 0.0])
    across = np.array([-along[1], along[0], 0.0])
    T = np.tile(np.eye(4), (n_scans, 1, 1))
    T[:, :3, :3] = exp_so3(np.column_stack([rng.normal(0, 0.02, n_scans), rng.normal(0, 0.02, n_scans),
                                            heading_rad + rng.normal(0, 0.05, n_scans)]))
    T[:, :3, 3] = 0.5 * np.arange(n_scans)[:, None] * along + np.array([0.0, 0.0, 1.2])
    faces = [(np.array([0, 0, 1.0]), 0.0), (np.array([0, 0, 1.0]), 2.5), (across, -1.5), (across, 1.5)]
    if with_end_wall:
        faces.append((along, 12.0))
    plane_index, scan_index, clusters = [], [], []
    for j in range(n_scans):
        for i, (n, d) in enumerate(faces):
            u = np.cross(n, [0.3, 0.5, 0.8])
            u /= np.linalg.norm(u)
            v = np.cross(n, u)
            a, b = rng.uniform(-4, 4, (2, 300))
            q = n * d + np.outer(a, u) + np.outer(b, v) + np.array([0, 0, 1.25]) * (n[2] == 0)
            R, t = T[j, :3, :3], T[j, :3, 3]
            plane_index.append(i)
            scan_index.append(j)
            clusters.append(points_to_cluster((q - t) @ R))
    return make_problem(np.array(plane_index), np.array(scan_index), np.array(clusters), n_scans=n_scans), T


@pytest.mark.parametrize("heading_deg", [0.0, 37.0])
def test_corridor_is_free_along_the_direction_of_travel(heading_deg):
    problem, T = _corridor(np.deg2rad(heading_deg), with_end_wall=False)
    odometry_information = OdometryFactors(T, MODEL).linearize(T).pose_blocks
    report = scan_degeneracy(problem, T, 10.0, odometry_information)
    for scan in report.per_scan:
        assert scan["smallest_eigenvalue"] < 1e-6 * np.abs(plane_information(problem, T)).max()
        assert scan["direction"] == "translation along the direction of travel"
    assert report.held_by_odometry_scans == list(range(problem.n_scans))
    assert all("translation along the direction of travel" in h["directions"] for h in report.held_by_odometry)


def test_end_wall_constrains_the_corridor():
    problem, T = _corridor(0.3, with_end_wall=True)
    odometry_information = OdometryFactors(T, MODEL).linearize(T).pose_blocks
    report = scan_degeneracy(problem, T, 10.0, odometry_information)
    assert report.held_by_odometry_scans == []
    assert min(s["points_equivalent"] for s in report.per_scan) > 10.0


def test_plane_information_matches_the_cost_curvature_along_a_direction():
    """v^T H_j v equals the second derivative of the plane cost when scan j alone moves along v
    (at the optimum, where Gauss-Newton is exact)."""
    from pa_cli.adjust import plane_cost
    from pa_cli.core.geometry import retract_left as retract_poses

    problem, T = _corridor(0.2, with_end_wall=True)
    H = plane_information(problem, T)
    v = np.array([0.01, -0.02, 0.03, 0.5, -0.3, 0.2])
    h = 1e-4
    d = np.zeros((problem.n_scans, 6))
    d[2] = h * v
    second = (plane_cost(problem, retract_poses(T, d)) - 2 * plane_cost(problem, T)
              + plane_cost(problem, retract_poses(T, -d))) / h**2
    assert v @ H[2] @ v == pytest.approx(second, rel=1e-3)


def test_words_for_directions():
    T = np.tile(np.eye(4), (3, 1, 1))
    T[:, 1, 3] = [0.0, 1.0, 2.0]  # travelling along world y
    frame = travel_frames(T)[1]
    assert describe(np.array([0, 0, 0, 0, 1.0, 0]), frame) == "translation along the direction of travel"
    assert describe(np.array([0, 0, 0, 1.0, 0, 0]), frame) == "sideways translation (across the direction of travel)"
    assert describe(np.array([0, 0, 1.0, 0, 0, 0]), frame) == "rotation about the vertical (yaw)"
    assert describe(np.array([0, 1.0, 0, 0, 0, 0]), frame) == "rotation about the direction of travel (roll)"
    assert describe(np.array([0, 0, 0, 0, 0, 1.0]), frame) == "vertical translation"
