"""Solver backends: what a backend is, and the registry `solve` picks one from by name.

A backend is a function

    backend(problem, T_world_scan_init, config, terms, progress) -> BackendResult

that refines poses T_world_scan (N, 4, 4) against a `FeatureProblem` of planes plus the pose
terms (`pa_cli.adjust.terms`), holds pose `config.fixed_pose` fixed and calls `progress(record)`
after every iteration. `pa_cli.adjust` registers `newton` (planes eliminated) and `lm` (the PA_LM
baseline, planes as unknowns); `register_backend` adds another (its name must also be added to
`SolverConfig.solver` so configs and the CLI accept it).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from pa_cli.adjust.damped import IterationRecord
from pa_cli.adjust.terms import PoseTerm
from pa_cli.config import SolverConfig
from pa_cli.core.problem import FeatureProblem
from pa_cli.errors import SolverError


@dataclass
class BackendResult:
    """Refined poses (N, 4, 4), the damped loop's report fields (`minimize_damped`; costs of the
    whole objective, m^2) and warnings."""

    T_world_scan: np.ndarray
    fields: dict[str, Any]
    warnings: list[str] = field(default_factory=list)
    model: Any = None  # the `newton` backend's NewtonModel (for the pose covariance), else None


class Backend(Protocol):
    def __call__(self, problem: FeatureProblem, T_world_scan_init: np.ndarray, config: SolverConfig,
                 terms: Sequence[PoseTerm] = (),
                 progress: Callable[[IterationRecord], None] | None = None) -> BackendResult: ...


_BACKENDS: dict[str, Backend] = {}


def register_backend(name: str, backend: Backend) -> None:
    """Make `backend` available to `solve` as `name` (replaces a backend of that name)."""
    _BACKENDS[name] = backend


def get_backend(name: str) -> Backend:
    """The backend registered as `name`."""
    if name not in _BACKENDS:
        raise SolverError(f"unknown solver '{name}'; expected one of {sorted(_BACKENDS)} (--solver).")
    return _BACKENDS[name]
