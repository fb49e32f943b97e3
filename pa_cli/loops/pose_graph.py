"""The pose graph: odometry edges between consecutive nodes plus verified loop edges (GTSAM).

Nodes are poses T_world_node. An edge (i, j) measures T_i_j with independent Gaussian noise on
the rotation (rad) and the translation (m) of the tangent-space error (GTSAM's Pose3 between
factor). Odometry edges have sigmas growing with the square root of the path they span, so
drift spreads along the path like a random walk; loop edges have fixed sigmas and a Cauchy
kernel. Node 0 is held by a tight prior (gauge).

Solved by Levenberg-Marquardt twice: first without the kernel (a closure that ends a long
drift starts hundreds of sigmas off, where a robust kernel would ignore it), then with the
kernel from that solution, so a closure that disagrees with the rest is down-weighted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

GAUGE_SIGMA = 1e-6  # prior on node 0: rad and m, far below any edge's sigma
MAX_ITERATIONS = 100  # Levenberg-Marquardt iterations per pass; a chain with loops converges in tens


@dataclass
class Edge:
    """A relative-pose measurement T_i_j between nodes i and j."""

    i: int
    j: int
    T_i_j: np.ndarray  # (4, 4)
    sigma_rotation_rad: float
    sigma_translation_m: float
    robust: bool = False


def odometry_edges(T_world_node: np.ndarray, path_m: np.ndarray, sigma_translation_m: float,
                   sigma_rotation_rad: float, min_step_m: float) -> list[Edge]:
    """Edges between consecutive nodes measuring the odometry's relative poses.

    Sigmas are per sqrt(m) of path between the nodes (at least `min_step_m`).
    """
    edges = []
    for i in range(len(T_world_node) - 1):
        root_m = np.sqrt(max(path_m[i + 1] - path_m[i], min_step_m))
        edges.append(Edge(i, i + 1, np.linalg.inv(T_world_node[i]) @ T_world_node[i + 1],
                          sigma_rotation_rad * root_m, sigma_translation_m * root_m))
    return edges


def _solve(T_world_node: np.ndarray, edges: list[Edge], kernel_sigmas: float | None) -> tuple[np.ndarray, float]:
    import gtsam

    graph = gtsam.NonlinearFactorGraph()
    gauge = gtsam.noiseModel.Isotropic.Sigma(6, GAUGE_SIGMA)
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(T_world_node[0]), gauge))
    for e in edges:
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, e.sigma_rotation_rad),
                                                       np.full(3, e.sigma_translation_m)])
        if e.robust and kernel_sigmas is not None:
            noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(kernel_sigmas), noise)
        graph.add(gtsam.BetweenFactorPose3(e.i, e.j, gtsam.Pose3(e.T_i_j), noise))
    values = gtsam.Values()
    for k, T in enumerate(T_world_node):
        values.insert(k, gtsam.Pose3(T))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(MAX_ITERATIONS)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    out = np.array([result.atPose3(k).matrix() for k in range(len(T_world_node))])
    return out, float(graph.error(result))


def optimize_pose_graph(T_world_node: np.ndarray, edges: list[Edge], kernel_sigmas: float) -> tuple[np.ndarray, dict]:
    """The poses (N, 4, 4) minimising the graph's cost from `T_world_node`, and a summary."""
    least_squares, error_l2 = _solve(T_world_node, edges, None)
    if not any(e.robust for e in edges):
        return least_squares, {"error_least_squares": error_l2}
    robust, error_robust = _solve(least_squares, edges, kernel_sigmas)
    return robust, {"error_least_squares": error_l2, "error_robust": error_robust}


def edge_residuals(T_world_node: np.ndarray, edges: list[Edge]) -> np.ndarray:
    """Per edge: translation (m) and rotation (rad) of T_i_j^-1 (T_world_i^-1 T_world_j), (E, 2)."""
    out = np.empty((len(edges), 2))
    for n, e in enumerate(edges):
        D = np.linalg.inv(e.T_i_j) @ np.linalg.inv(T_world_node[e.i]) @ T_world_node[e.j]
        out[n] = np.linalg.norm(D[:3, 3]), np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1.0, 1.0))
    return out
