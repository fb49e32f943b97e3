"""Pieces shared by the plane-adjustment solvers: options, the pose retraction and the damped loop.

Retraction (used by every solver in `pa_cli.adjust`): a step delta_j = (omega_j, rho_j) of pose j,
omega in radians (rotation vector), rho in metres, both expressed in the WORLD frame, acts on the
left:

    T_world_scan_j  <-  [[Exp(omega_j), rho_j], [0, 1]] @ T_world_scan_j
    i.e.  R_j <- Exp(omega_j) R_j,   t_j <- Exp(omega_j) t_j + rho_j,

so a world point q of scan j moves to Exp(omega_j) q + rho_j. `retract_poses` implements exactly
this; the Newton derivatives in `newton.py` are derivatives with respect to it at delta = 0.

`damped_newton` is the generic damped (Levenberg-Marquardt style) loop: it asks a model for a
`Linearization` of the cost at the current state, solves the damped system for increasing damping
mu until a step decreases the true cost, adapts mu with the Nielsen schedule (as Ceres does) and
stops on the relative cost decrease, gradient max-norm, step norm or the iteration budget. Every
damped solve (accepted, rejected, or with a failed factorisation) counts as one iteration.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any, Protocol, TypeVar

import numpy as np

from pa_cli.config import SolverConfig

State = TypeVar("State")

MAX_DAMPING = 1e32  # mu above this: no descent step can be found; stop (not converged)
MIN_DAMPING = 1e-32  # mu never falls below this (keeps the damped system well defined)


@dataclass(frozen=True)
class SolverOptions:
    """Stopping rules and damping of the damped loop.

    - max_iterations: damped solves (accepted or rejected) at most.
    - cost_tolerance: stop (converged) when an accepted step decreases the cost by less than
      this fraction of the cost.
    - gradient_tolerance: stop (converged) when the max-norm of the gradient (m^2 per rad or per
      m) is at most this.
    - step_tolerance: stop (converged) when the step norm (2-norm of all (omega rad, rho m)) is at
      most this.
    - initial_damping: first mu; the damped system is (H + mu * D) step = -g with D the clamped
      diagonal of H, so mu is relative to the Hessian diagonal.
    - fixed_pose: index of the pose held fixed (gauge).
    - eigen_gap_tolerance: Newton only; when lambda_k - lambda_min < this * lambda_max for a plane,
      1/(lambda_min - lambda_k) is clamped to -1/(this * lambda_max) (reported as a warning).
    """

    max_iterations: int = 100
    cost_tolerance: float = 1e-10
    gradient_tolerance: float = 1e-10
    step_tolerance: float = 1e-10
    initial_damping: float = 1e-4
    fixed_pose: int = 0
    eigen_gap_tolerance: float = 1e-6

    @classmethod
    def from_config(cls, config: SolverConfig) -> SolverOptions:
        return cls(
            max_iterations=config.max_iterations,
            cost_tolerance=config.cost_tolerance,
            gradient_tolerance=config.gradient_tolerance,
            step_tolerance=config.step_tolerance,
            initial_damping=config.initial_damping,
            fixed_pose=config.fixed_pose,
            eigen_gap_tolerance=config.eigen_gap_tolerance,
        )


@dataclass
class IterationRecord:
    """One damped solve. `cost` and `gradient_norm` are those of the state after the iteration
    (unchanged when the step was rejected); `time_s` is the wall time of this iteration (s)."""

    iteration: int
    cost: float
    gradient_norm: float
    mu: float
    step_norm: float | None
    accepted: bool
    time_s: float

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class Linearization(Protocol):
    """A local model of the cost at one state.

    `solve(mu)` returns (step, predicted_decrease): the damped step and the model's predicted
    cost decrease for it (cost - model(step)). `step` is None when the damped system could not
    be factorised or is not positive definite (raising numpy.linalg.LinAlgError means the same);
    the loop then rejects and raises mu.
    """

    cost: float
    gradient_norm: float

    def solve(self, mu: float) -> tuple[np.ndarray | None, float]: ...


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices: skew(a) @ b = a x b."""
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -v[..., 2], v[..., 1]
    K[..., 1, 0], K[..., 1, 2] = v[..., 2], -v[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -v[..., 1], v[..., 0]
    return K


def exp_so3(omega: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) of rotation vectors omega (N, 3) in radians (Rodrigues)."""
    omega = np.asarray(omega, dtype=np.float64)
    theta2 = np.einsum("ni,ni->n", omega, omega)
    theta = np.sqrt(theta2)
    small = theta2 < 1e-12
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    K = skew(omega)
    return np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)


def retract_poses(T_world_scan: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Apply steps delta (N, 6) = (omega rad, rho m), world frame, on the left of poses (N, 4, 4).

    Returns new T_world_scan with R <- Exp(omega) R and t <- Exp(omega) t + rho.
    """
    delta = np.asarray(delta, dtype=np.float64)
    R_delta = exp_so3(delta[:, :3])
    T_new = np.array(T_world_scan, dtype=np.float64, copy=True)
    T_new[:, :3, :3] = R_delta @ T_world_scan[:, :3, :3]
    T_new[:, :3, 3] = np.einsum("nij,nj->ni", R_delta, T_world_scan[:, :3, 3]) + delta[:, 3:]
    return T_new


def damped_newton(
    state: State,
    linearize: Callable[[State], Linearization],
    cost: Callable[[State], float],
    retract: Callable[[State, np.ndarray], State],
    step_norm: Callable[[np.ndarray], float],
    options: SolverOptions,
    progress: Callable[[IterationRecord], None] | None = None,
) -> tuple[State, dict[str, Any]]:
    """Minimise a cost by damped Newton steps; never accepts a cost increase.

    Returns the final state and the report fields `iterations`, `cost_initial`, `cost_final`,
    `converged`, `stop_reason` and `history` (a list of `IterationRecord.as_dict()`).

    Damping (Nielsen 1999, as in Ceres): with gain ratio r = actual / predicted decrease, an
    accepted step (actual decrease > 0 and predicted decrease > 0) sets
    mu <- mu * max(1/3, 1 - (2r - 1)^3), nu <- 2; a rejected step (or a failed / indefinite
    factorisation) sets mu <- mu * nu, nu <- 2 nu.
    """
    lin = linearize(state)
    cost_initial = float(lin.cost)
    current_cost = cost_initial
    mu = float(options.initial_damping)
    nu = 2.0
    history: list[dict[str, Any]] = []
    converged = False
    stop_reason = "max_iterations"
    iteration = 0

    if lin.gradient_norm <= options.gradient_tolerance:
        converged, stop_reason = True, "gradient_tolerance"
    elif current_cost <= 0.0:
        converged, stop_reason = True, "zero_cost"
    while not converged and iteration < options.max_iterations:
        iteration += 1
        t0 = time.perf_counter()
        mu_used = mu
        try:
            step, predicted = lin.solve(mu)
        except np.linalg.LinAlgError:
            step, predicted = None, 0.0
        accepted = False
        norm: float | None = None  # None: no step (failed factorisation)
        stop_now = False
        if step is not None and np.all(np.isfinite(step)):
            norm = float(step_norm(step))
            if norm <= options.step_tolerance:
                converged, stop_reason, stop_now = True, "step_tolerance", True
            elif predicted > 0.0:
                new_state = retract(state, step)
                new_cost = float(cost(new_state))
                actual = current_cost - new_cost
                if np.isfinite(new_cost) and actual > 0.0:
                    accepted = True
                    ratio = actual / predicted
                    mu = max(mu * max(1.0 / 3.0, 1.0 - (2.0 * ratio - 1.0) ** 3), MIN_DAMPING)
                    nu = 2.0
                    relative_decrease = actual / current_cost
                    state, current_cost = new_state, new_cost
                    lin = linearize(state)
                    current_cost = float(lin.cost)
                    if lin.gradient_norm <= options.gradient_tolerance:
                        converged, stop_reason, stop_now = True, "gradient_tolerance", True
                    elif relative_decrease <= options.cost_tolerance:
                        converged, stop_reason, stop_now = True, "cost_tolerance", True
                    elif current_cost <= 0.0:
                        converged, stop_reason, stop_now = True, "zero_cost", True
        if not accepted and not stop_now:
            mu *= nu
            nu *= 2.0
        record = IterationRecord(
            iteration=iteration,
            cost=current_cost,
            gradient_norm=float(lin.gradient_norm),
            mu=mu_used,
            step_norm=norm,
            accepted=accepted,
            time_s=time.perf_counter() - t0,
        )
        history.append(record.as_dict())
        if progress is not None:
            progress(record)
        if stop_now:
            break
        if mu > MAX_DAMPING:
            stop_reason = "damping_too_large"
            break

    return state, {
        "iterations": iteration,
        "cost_initial": cost_initial,
        "cost_final": current_cost,
        "converged": converged,
        "stop_reason": stop_reason,
        "history": history,
    }
