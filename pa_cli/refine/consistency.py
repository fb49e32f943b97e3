"""Start-consistency: does the answer depend on the start's own relative motions?

Where the features are weak, the odometry factors' measurements (each consecutive pair's relative
motion: registered, or the initial trajectory's) decide the refined poses. The check draws the
measurements again: each relative motion perturbed within its sigmas (`OdometryFactors.sigmas`:
measured for registered motions, the odometry model's otherwise; a fixed seed). The final feature
problem (the frozen association) is solved again with odometry factors on the perturbed
measurements, warm-started from the refined poses (the first pose, the gauge, stays). The two
results are compared scan by scan: a scan whose position moved by more than the pose covariance's
3-sigma (Mahalanobis distance of the position difference beyond the 99.73 % quantile of chi-square
with 3 degrees of freedom) is one whose answer the motions decide beyond what the covariance admits;
the verdict then cannot be `improved`, and the scans and the direction of their move are named.
Cost: one more solve of the last round's problem, a few iterations from the warm start.

The warm start keeps the check cheap on long sequences: the chain of the perturbed motions wanders
by metres over a thousand scans, and a solve from there takes 20-40 iterations to reach the same
answer. Whether the rounds reach the same answer from another start is what the rounds' own
start (the registration chain) and `bench/robust.py starts` measure, not this check.

The association is kept: what a fresh association at another start would find is not checked.
What a fresh association changes is measured by `association_within`: when the association was
frozen by its cap while its last fresh round still moved scans beyond
`advanced.association.settle_m` (the rounds then did not settle), those moves are compared with the
same 3-sigma of the pose covariance. A move within it is below what the data resolve; a move beyond
it is the association deciding the answer.

The covariance of the adjustment takes the association as given. It is not: two fresh
associations at poses that differ by less than the noise group the points into planes differently
(region growing is discrete), and the answer moves with them, most along the directions the planes
decide least (along a road). `association_spread` adds that spread, measured: the last fresh
association's change of the answer (`RoundsResult.association_change`, against the fresh round
before) is one draw of the difference of two answers, so each pose's covariance gains half its
outer product. It is added after both checks above, which judge moves against the adjustment's own
covariance.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pa_cli.adjust import solve
from pa_cli.adjust.covariance import PoseCovariance
from pa_cli.adjust.odometry_factors import OdometryFactors
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
        return (f"refined again with the relative motions perturbed within the odometry's sigmas, "
                f"{len(self.beyond)} scan(s) end more than 3 sigma of the pose covariance away (scans {listed}{more}): "
                "there the answer follows the start's motions more than the covariance says")

    def report(self) -> dict[str, Any]:
        """The report's `start_consistency` section."""
        return {"max_moved_m": float(self.moved_m.max(initial=0.0)),
                "median_moved_m": float(np.median(self.moved_m)) if len(self.moved_m) else 0.0,
                "max_sigmas": None if self.mahalanobis is None else float(np.sqrt(self.mahalanobis.max(initial=0.0))),
                "scans_beyond_3_sigma": self.beyond, "iterations": self.iterations,
                "consistent": self.consistent}


def perturbed_measurements(factors: OdometryFactors, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The factors' relative motions (R_z, t_z), each perturbed by N(0, sigma^2) per axis (its
    pair's sigmas): one draw of the measurement noise the factors model."""
    omega = rng.standard_normal((len(factors.t_z), 3)) * factors.sigmas[:, :3]
    rho = rng.standard_normal((len(factors.t_z), 3)) * factors.sigmas[:, 3:]
    return factors.R_z @ exp_so3(omega), factors.t_z + rho


def start_consistency(problem: FeatureProblem, T_refined: np.ndarray,
                      factors: OdometryFactors, solver_config: SolverConfig,
                      position_covariance_m2: np.ndarray | None) -> StartConsistency:
    """Solve `problem` again with the odometry factors' measurements perturbed within their sigmas,
    from T_refined, and compare with T_refined (see the module docstring).
    `position_covariance_m2` (N, 3, 3): the pose covariance's position blocks (m^2), or None."""
    R_z, t_z = perturbed_measurements(factors, np.random.default_rng(START_SEED))
    second = OdometryFactors.from_motions(R_z, t_z, factors.model, factors.sigmas)
    result = solve(problem, T_refined, solver_config, terms=[second])
    difference = result.T_world_scan[:, :3, 3] - T_refined[:, :3, 3]
    moved_m = np.linalg.norm(difference, axis=1)
    mahalanobis = None
    beyond: list[dict[str, Any]] = []
    if position_covariance_m2 is not None:
        mahalanobis = _mahalanobis_sq(difference, position_covariance_m2)
        frames = travel_frames(T_refined)
        for j in np.argsort(-mahalanobis, kind="stable"):
            if mahalanobis[j] <= CHI2_3DOF_3SIGMA:
                break
            direction = np.r_[np.zeros(3), difference[j] / max(moved_m[j], 1e-300)]
            beyond.append({"scan": int(j), "moved_m": float(moved_m[j]), "sigmas": float(np.sqrt(mahalanobis[j])),
                           "direction": describe(direction, frames[j])})
    return StartConsistency(moved_m, mahalanobis, beyond, int(result.report["iterations"]))


def association_within(unsettled: dict[str, Any], position_covariance_m2: np.ndarray | None) -> dict[str, Any]:
    """The moves of the last fresh association (`unsettled`: `pa_cli.refine.rounds`'
    `unsettled_association`, its scans with their position change `change_m`, m) against the pose
    covariance's position blocks (N, 3, 3; m^2): each scan's distance in sigmas (the square root of
    the Mahalanobis distance), the scans beyond 3 sigma (chi-square, 3 degrees of freedom, 99.73 %)
    and `within_3_sigma`, whether none is (False without a covariance to judge by)."""
    if position_covariance_m2 is None:
        return {"max_sigmas": None, "scans_beyond_3_sigma": [s["scan"] for s in unsettled["scans"]],
                "within_3_sigma": False}
    scans = np.array([s["scan"] for s in unsettled["scans"]], dtype=np.int64)
    change = np.array([s["change_m"] for s in unsettled["scans"]], dtype=np.float64).reshape(-1, 3)
    sigmas = np.sqrt(np.maximum(_mahalanobis_sq(change, position_covariance_m2[scans]), 0.0))
    beyond = [int(j) for j in scans[sigmas**2 > CHI2_3DOF_3SIGMA]]
    return {"max_sigmas": float(sigmas.max(initial=0.0)), "scans_beyond_3_sigma": beyond,
            "within_3_sigma": not beyond}


def association_spread(covariance: PoseCovariance, change: np.ndarray, round_number: int
                       ) -> tuple[PoseCovariance, dict[str, Any]]:
    """`covariance` plus the spread of the answer over the association (see the module docstring):
    `change` (N, 6; omega rad, rho m, `tangent_error`, the covariance's frame) is what the fresh
    association of round `round_number` changed. Returns the covariance and the report's record:
    per scan the position 1-sigma the spread adds, |d p| / sqrt(2) (m), its median and largest, and
    the scans it adds most to."""
    spread = covariance.with_spread(change)
    added_m = np.sqrt(np.maximum(
        np.linalg.eigvalsh(spread.position_covariance_m2() - covariance.position_covariance_m2())[:, -1], 0.0))
    largest = np.argsort(-added_m, kind="stable")[:LISTED_SCANS]
    record = {"round": round_number, "median_added_position_sigma_m": float(np.median(added_m)),
              "max_added_position_sigma_m": float(added_m.max(initial=0.0)),
              "largest": [{"scan": int(j), "added_position_sigma_m": float(added_m[j])} for j in largest]}
    return spread, record


def _mahalanobis_sq(difference_m: np.ndarray, position_covariance_m2: np.ndarray) -> np.ndarray:
    """Per scan, d^T C^+ d of position differences (N, 3; m) under position covariances (N, 3, 3; m^2),
    the pseudo-inverse leaving out directions the covariance does not span (the gauge scan's zero)."""
    inverse = np.linalg.pinv(position_covariance_m2, hermitian=True)
    return np.einsum("ni,nij,nj->n", difference_m, inverse, difference_m)
