"""Damped Newton on base poses and extrinsics together (the loop of `pa_cli.adjust.damped`).

The unknowns are the free base poses (the first base pose is the gauge and stays fixed) and the
extrinsics of lidar1..; an extrinsic may be restricted to a subspace of its 6 directions (a basis
B_k, 6 x m_k, in (omega rad, rho m) of the base frame): the directions the data leave free are
then held at their starting value (`pa_cli.calibration.observability`). The system is solved dense
(`composite` explains why); when H + mu D is not positive definite the same iteration uses the
Gauss-Newton Hessian, as the pose solver does (`pa_cli.adjust.newton.NewtonLinearization`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from pa_cli.adjust.damped import IterationRecord, minimize_damped
from pa_cli.calibration.composite import BLOCK, DIAG_FLOOR, CalibrationCost
from pa_cli.config import SolverConfig


def free_basis(n_base: int, extrinsic_bases: Sequence[np.ndarray]) -> np.ndarray:
    """(6 (N + K - 1), m) map from the free unknowns to the full step vector: base poses 1..N-1
    (pose 0 is the gauge) and each extrinsic k through its basis B_k (6, m_k)."""
    m = BLOCK * (n_base - 1) + sum(B.shape[1] for B in extrinsic_bases)
    P = np.zeros((BLOCK * (n_base + len(extrinsic_bases)), m))
    P[BLOCK:BLOCK * n_base, :BLOCK * (n_base - 1)] = np.eye(BLOCK * (n_base - 1))
    col = BLOCK * (n_base - 1)
    for k, B in enumerate(extrinsic_bases):
        row = BLOCK * (n_base + k)
        P[row:row + BLOCK, col:col + B.shape[1]] = B
        col += B.shape[1]
    return P


class CalibrationLinearization:
    """The damped model at one state, in the free unknowns (see `free_basis`)."""

    def __init__(self, cost: CalibrationCost, basis: np.ndarray, state: np.ndarray) -> None:
        self.cost, g, H, H_gn, self.n_guarded = cost.derivatives(state)
        self.basis = basis
        self.n_state = len(state)
        self.g = basis.T @ g
        self.H = basis.T @ H @ basis
        self.H_gn = basis.T @ H_gn @ basis
        self.gradient_norm = float(np.abs(self.g).max(initial=0.0))

    def solve(self, mu: float) -> tuple[np.ndarray | None, float]:
        """(step (N + K - 1, 6), predicted decrease), exact Hessian first, Gauss-Newton if not PD."""
        for H in (self.H, self.H_gn):
            d = np.abs(np.diag(H))
            D = np.maximum(d, DIAG_FLOOR * max(float(d.max(initial=0.0)), 1e-300))
            try:
                L = np.linalg.cholesky(H + mu * np.diag(D))
            except np.linalg.LinAlgError:
                continue
            x = -np.linalg.solve(L.T, np.linalg.solve(L, self.g))
            predicted = 0.5 * (-(self.g @ x) + mu * (x @ (D * x)))
            return (self.basis @ x).reshape(self.n_state, BLOCK), float(predicted)
        return None, 0.0


def solve_calibration(cost: CalibrationCost, state: np.ndarray, config: SolverConfig,
                      extrinsic_bases: Sequence[np.ndarray] | None = None,
                      progress: Callable[[IterationRecord], None] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
    """Minimise the calibration cost from `state` (N + K - 1, 4, 4); returns the final state and the
    damped loop's report fields (`pa_cli.adjust.damped.minimize_damped`). `extrinsic_bases`: per
    extrinsic the directions it may move in (None: all six)."""
    layout = cost.layout
    bases = list(extrinsic_bases) if extrinsic_bases is not None else [np.eye(BLOCK)] * (layout.n_lidars - 1)
    basis = free_basis(layout.n_base, bases)
    final, report = minimize_damped(np.asarray(state, dtype=np.float64),
                                    lambda s: CalibrationLinearization(cost, basis, s), cost.cost,
                                    layout.retract, lambda step: float(np.linalg.norm(step)), config, progress)
    return final, report
