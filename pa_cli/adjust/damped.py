"""The damped loop shared by the solver backends (Levenberg-Marquardt style damping).

`minimize_damped` minimises a cost over any state: it asks a model for a `Linearization` of the
cost at the current state, solves the damped system for increasing damping mu until a step
decreases the true cost, adapts mu with the Nielsen schedule (as Ceres does) and stops on the
relative cost decrease, gradient max-norm, step norm or the iteration budget (`SolverConfig`).
Every damped solve (accepted, rejected, or with a failed factorisation) counts as one iteration.

Damping scale: mu multiplies D = |diag H| (the Hessian's own diagonal, as in Ceres and BALM2), so
mu is dimensionless. The cost is a sum of squares (>= 0), so a step whose model predicts a decrease
larger than the cost itself is outside the model's trust region whatever its true cost: it is
rejected without evaluating the cost and mu is raised, so mu is set by the problem's own scale
within the first iterations (a moderate perturbation, whose Newton model can overshoot along a
weakly curved direction, does not spend evaluations on steps of absurd length).

Both backends run through this one loop on purpose: the Newton backend's state is the poses, the
LM baseline's state is poses and planes, and what differs between them (the linear model and the
retraction) is passed in; the stopping rules and the damping schedule are identical, so their
iteration counts and reports compare like with like. The loop knows nothing of planes or poses.
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


@dataclass
class IterationRecord:
    """One damped solve. `cost_m2` and `gradient_norm` are those of the state after the iteration
    (unchanged when the step was rejected); `time_s` is the wall time of this iteration (s)."""

    iteration: int
    cost_m2: float
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

    cost: float  # m^2
    gradient_norm: float

    def solve(self, mu: float) -> tuple[np.ndarray | None, float]: ...


def minimize_damped(
    state: State,
    linearize: Callable[[State], Linearization],
    cost: Callable[[State], float],
    retract: Callable[[State, np.ndarray], State],
    step_norm: Callable[[np.ndarray], float],
    config: SolverConfig,
    progress: Callable[[IterationRecord], None] | None = None,
) -> tuple[State, dict[str, Any]]:
    """Minimise a cost (m^2) by damped steps; never accepts a cost increase.

    Returns the final state and the report fields `iterations`, `cost_initial_m2`,
    `cost_final_m2`, `converged`, `stop_reason` and `history` (a list of `IterationRecord.as_dict()`).

    Damping (Nielsen 1999, as in Ceres): with gain ratio r = actual / predicted decrease, an
    accepted step (actual decrease > 0 and predicted decrease > 0) sets
    mu <- mu * max(1/3, 1 - (2r - 1)^3), nu <- 2; a rejected step (or a failed / indefinite
    factorisation, or a predicted decrease above the current cost) sets mu <- mu * nu, nu <- 2 nu.
    """
    lin = linearize(state)
    cost_initial = float(lin.cost)
    current_cost = cost_initial
    mu = float(config.initial_damping)
    nu = 2.0
    history: list[dict[str, Any]] = []
    converged = False
    stop_reason = "max_iterations"
    iteration = 0

    if lin.gradient_norm <= config.gradient_tolerance:
        converged, stop_reason = True, "gradient_tolerance"
    elif current_cost <= 0.0:
        converged, stop_reason = True, "zero_cost"
    while not converged and iteration < config.max_iterations:
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
            if norm <= config.step_tolerance:
                converged, stop_reason, stop_now = True, "step_tolerance", True
            elif 0.0 < predicted <= current_cost:
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
                    if lin.gradient_norm <= config.gradient_tolerance:
                        converged, stop_reason, stop_now = True, "gradient_tolerance", True
                    elif relative_decrease <= config.cost_tolerance:
                        converged, stop_reason, stop_now = True, "cost_tolerance", True
                    elif current_cost <= 0.0:
                        converged, stop_reason, stop_now = True, "zero_cost", True
        if not accepted and not stop_now:
            mu *= nu
            nu *= 2.0
        record = IterationRecord(
            iteration=iteration,
            cost_m2=current_cost,
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
        "cost_initial_m2": cost_initial,
        "cost_final_m2": current_cost,
        "converged": converged,
        "stop_reason": stop_reason,
        "history": history,
    }
