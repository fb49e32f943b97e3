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


def _poses(values) -> np.ndarray:
    """The poses of `values` (GTSAM Values of Pose3 keyed 0..N-1) as (N, 4, 4) T_world_node."""
    import gtsam

    rows = gtsam.utilities.extractPose3(values)  # (N, 12): the rotation row by row, then the translation
    T = np.zeros((len(rows), 4, 4))
    T[:, :3, :3] = rows[:, :9].reshape(-1, 3, 3)
    T[:, :3, 3] = rows[:, 9:]
    T[:, 3, 3] = 1.0
    return T


class PoseGraph:
    """A pose graph kept between solves, for a graph that grows by edges and is re-solved as it grows.

    It holds two GTSAM factor graphs over the same edges, least squares and with the loop edges' Cauchy kernel
    (`kernel_sigmas`), each edge's factors built once, and the current estimate. `solve` runs the two passes of the
    module docstring from that estimate and keeps the result as the next start.
    """

    def __init__(self, T_world_node: np.ndarray, kernel_sigmas: float) -> None:
        import gtsam

        self.kernel = gtsam.noiseModel.mEstimator.Cauchy.Create(kernel_sigmas)
        self.least_squares = gtsam.NonlinearFactorGraph()
        self.robust = gtsam.NonlinearFactorGraph()
        gauge = gtsam.PriorFactorPose3(0, gtsam.Pose3(T_world_node[0]),
                                       gtsam.noiseModel.Isotropic.Sigma(6, GAUGE_SIGMA))
        self.least_squares.add(gauge)
        self.robust.add(gauge)
        self.has_robust = False
        self.values = gtsam.Values()
        for k, T in enumerate(T_world_node):
            self.values.insert(k, gtsam.Pose3(T))
        self.T_world_node = np.array(T_world_node, dtype=np.float64)

    def add(self, edges: list[Edge]) -> None:
        """Add edges to both factor graphs (the estimate is unchanged until `solve`)."""
        import gtsam

        for e in edges:
            measured = gtsam.Pose3(e.T_i_j)
            noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([e.sigma_rotation_rad] * 3 + [e.sigma_translation_m] * 3))
            factor = gtsam.BetweenFactorPose3(e.i, e.j, measured, noise)
            self.least_squares.add(factor)
            if e.robust:
                robust_noise = gtsam.noiseModel.Robust.Create(self.kernel, noise)
                factor = gtsam.BetweenFactorPose3(e.i, e.j, measured, robust_noise)
                self.has_robust = True
            self.robust.add(factor)

    def solve(self) -> dict:
        """Minimise the graph's cost from the current estimate, which becomes the result (`T_world_node`); a
        summary: the least-squares pass's error and, with robust edges, the robust pass's."""
        import gtsam

        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(MAX_ITERATIONS)
        values = gtsam.LevenbergMarquardtOptimizer(self.least_squares, self.values, params).optimize()
        summary = {"error_least_squares": float(self.least_squares.error(values))}
        if self.has_robust:
            values = gtsam.LevenbergMarquardtOptimizer(self.robust, values, params).optimize()
            summary["error_robust"] = float(self.robust.error(values))
        self.values = values
        self.T_world_node = _poses(values)
        return summary


def optimize_pose_graph(T_world_node: np.ndarray, edges: list[Edge], kernel_sigmas: float) -> tuple[np.ndarray, dict]:
    """The poses (N, 4, 4) minimising the graph's cost from `T_world_node`, and a summary."""
    graph = PoseGraph(T_world_node, kernel_sigmas)
    graph.add(edges)
    summary = graph.solve()
    return graph.T_world_node, summary


def edge_residuals(T_world_node: np.ndarray, edges: list[Edge]) -> np.ndarray:
    """Per edge: translation (m) and rotation (rad) of T_i_j^-1 (T_world_i^-1 T_world_j), (E, 2)."""
    out = np.empty((len(edges), 2))
    for n, e in enumerate(edges):
        D = np.linalg.inv(e.T_i_j) @ np.linalg.inv(T_world_node[e.i]) @ T_world_node[e.j]
        out[n] = np.linalg.norm(D[:3, 3]), np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1.0, 1.0))
    return out
