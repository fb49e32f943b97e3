"""Start-consistency: does the answer depend on the start's own relative motions?

The odometry factors take the initial trajectory's relative motions as measurements, so where the
features are weak the refined poses follow the start. The check draws a second start: every
consecutive relative motion of the initial trajectory perturbed within its odometry sigmas
(`OdometryModel.sigmas`, a fixed seed), integrated from the refined first pose (the gauge). The
final feature problem (the frozen association) is solved again from that start, with odometry
factors measured on it. The two results are compared scan by scan: a scan whose position moved by
more than the pose covariance's 3-sigma (Mahalanobis distance of the position difference beyond
the 99.73 % quantile of chi-square with 3 degrees of freedom) is one whose answer the start
decides beyond what the covariance admits; the verdict then cannot be `improved`, and the scans
and the direction of their move are named. Cost: one more solve of the last round's problem (two
when the horizontal was held: the comparison is then with the problem solved without the hold).

The association is kept: what a fresh association at another start would find is not checked.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pa_cli.adjust import solve
from pa_cli.adjust.odometry_factors import OdometryFactors, relative_motions
from pa_cli.config import SolverConfig
from pa_cli.core.geometry import exp_so3
from pa_cli.core.problem import FeatureProblem
from pa_cli.evaluation.degeneracy import describe, travel_frames

START_SEED = 20  # the second start's draw: fixed, so a run is repeatable
CHI2_3DOF_3SIGMA = 14.16  # 99.73 % quantile of chi-square with 3 degrees of freedom (3 sigma in 3-D)
LISTED_SCANS = 10  # scans named in the reason, largest first


@dataclass(frozen=True)
class StartConsistency:
    """The second start's result against the first: per-scan position difference (m) and its
    Mahalanobis distance under the pose covariance (None without a covariance), the scans beyond
    3 sigma with the direction of their move in words."""

    moved_m: np.ndarray  # (N,)
    mahalanobis: np.ndarray | None  # (N,)
    beyond: list[dict[str, Any]]
    iterations: int

    @property
    def consistent(self) -> bool:
        """No scan moved beyond the covariance's 3 sigma (True without a covariance to judge by)."""
        return not self.beyond

    def reason(self) -> str:
        """The doubt in words (for the verdict's reasons)."""
        listed = ", ".join(f"{b['scan']} ({b['moved_m']:.3f} m, {b['sigmas']:.1f} sigma, {b['direction']})"
                           for b in self.beyond[:LISTED_SCANS])
        more = " ..." if len(self.beyond) > LISTED_SCANS else ""
        return (f"refined again from a start whose relative motions were perturbed within the odometry's sigmas, "
                f"{len(self.beyond)} scan(s) end more than 3 sigma of the pose covariance away (scans {listed}{more}): "
                "there the answer follows the start's motions more than the covariance says")

    def report(self) -> dict[str, Any]:
        """The report's `start_consistency` section."""
        return {"max_moved_m": float(self.moved_m.max(initial=0.0)),
                "median_moved_m": float(np.median(self.moved_m)) if len(self.moved_m) else 0.0,
                "max_sigmas": None if self.mahalanobis is None else float(np.sqrt(self.mahalanobis.max(initial=0.0))),
                "scans_beyond_3_sigma": self.beyond, "iterations": self.iterations,
                "consistent": self.consistent}


def perturbed_start(T_initial: np.ndarray, factors: OdometryFactors, rng: np.random.Generator,
                    T_first: np.ndarray | None = None) -> np.ndarray:
    """T_initial's consecutive relative motions, each perturbed by N(0, sigma^2) per axis (the
    factors' rotation and translation sigmas of that pair), integrated from T_first (default
    T_initial[0])."""
    R_rel, t_rel = relative_motions(T_initial)
    n_pairs = len(t_rel)
    omega = rng.standard_normal((n_pairs, 3)) * factors.sigma_r_rad[:, None]
    rho = rng.standard_normal((n_pairs, 3)) * factors.sigma_t_m[:, None]
    R_rel = R_rel @ exp_so3(omega)
    t_rel = t_rel + rho
    T = np.empty_like(T_initial)
    T[0] = T_initial[0] if T_first is None else T_first
    for j in range(n_pairs):
        T[j + 1] = np.eye(4)
        T[j + 1, :3, :3] = T[j, :3, :3] @ R_rel[j]
        T[j + 1, :3, 3] = T[j, :3, :3] @ t_rel[j] + T[j, :3, 3]
    return T


def start_consistency(problem: FeatureProblem, T_initial: np.ndarray, T_refined: np.ndarray,
                      factors: OdometryFactors, solver_config: SolverConfig,
                      position_covariance_m2: np.ndarray | None, held: bool = False) -> StartConsistency:
    """Solve `problem` again from a start perturbed within the odometry factors' sigmas, with
    factors measured on that start, and compare with T_refined (see the module docstring).
    `position_covariance_m2` (N, 3, 3): the pose covariance's position blocks (m^2), or None.
    `held`: T_refined holds terms besides `factors` (the hold of the horizontal), so the comparison
    is with `problem` solved afresh with `factors` alone (one more solve)."""
    if held:
        T_refined = solve(problem, T_refined, solver_config, terms=[factors]).T_world_scan
    # from the refined first pose: the gauge the solver holds and the covariance is relative to
    # (the rounds may have moved it, relocalising a lost scan)
    T_start = perturbed_start(T_initial, factors, np.random.default_rng(START_SEED), T_refined[0])
    second = OdometryFactors(T_start, factors.model)
    result = solve(problem, T_start, solver_config, terms=[second])
    difference = result.T_world_scan[:, :3, 3] - T_refined[:, :3, 3]
    moved_m = np.linalg.norm(difference, axis=1)
    mahalanobis = None
    beyond: list[dict[str, Any]] = []
    if position_covariance_m2 is not None:
        inverse = np.linalg.pinv(position_covariance_m2, hermitian=True)
        mahalanobis = np.einsum("ni,nij,nj->n", difference, inverse, difference)
        frames = travel_frames(T_refined)
        for j in np.argsort(-mahalanobis, kind="stable"):
            if mahalanobis[j] <= CHI2_3DOF_3SIGMA:
                break
            direction = np.r_[np.zeros(3), difference[j] / max(moved_m[j], 1e-300)]
            beyond.append({"scan": int(j), "moved_m": float(moved_m[j]), "sigmas": float(np.sqrt(mahalanobis[j])),
                           "direction": describe(direction, frames[j])})
    return StartConsistency(moved_m, mahalanobis, beyond, int(result.report["iterations"]))
