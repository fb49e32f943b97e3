"""The cost-term protocol: one class per cost on the poses, each giving cost, gradient and Hessian.

The objective the backends minimise is the plane cost (`newton.PlaneCost`, planes eliminated, or the
LM baseline's planes-as-unknowns form of it) plus any number of pose terms. A pose term is a class
with

- `name`: a short identifier; the solver report holds its costs as `{name}_cost_initial_m2` and
  `{name}_cost_final_m2`;
- `cost(T_world_scan) -> float`: its cost in m^2 at poses (N, 4, 4);
- `linearize(T_world_scan) -> TermLinearization`: cost, gradient (N, 6) and Hessian blocks with
  respect to the left retraction of `pa_cli.core.geometry.retract_left` (steps (omega rad, rho m));
- `pose_pairs() -> (K, 2) int array`: the pose pairs (j, k), j != k, whose off-diagonal Hessian
  block the term fills, fixed for the problem (the sparsity pattern is built from it once).

`TermLinearization.pose_blocks` (N, 6, 6) are added to the diagonal blocks H_jj, and
`pair_blocks[i]` (6, 6) to H_jk for (j, k) = pose_pairs()[i] (its transpose to H_kj). The Hessian
must be positive semi-definite (Gauss-Newton) or exact; the damped loop tolerates either.
`odometry_factors.OdometryFactors` is one: a factor between each pair of consecutive scans
(pose_pairs() = [(j, j + 1)]).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np


@dataclass
class TermLinearization:
    """Cost (m^2), gradient (N, 6) and Hessian blocks of one pose term at one state."""

    cost: float
    gradient: np.ndarray  # (N, 6): d cost / d (omega, rho)
    pose_blocks: np.ndarray  # (N, 6, 6): added to H_jj
    pair_blocks: np.ndarray  # (K, 6, 6): added to H_jk for (j, k) in pose_pairs()


class PoseTerm(Protocol):
    """A cost on the poses alone, added to the plane cost (see the module docstring)."""

    name: str

    def cost(self, T_world_scan: np.ndarray) -> float: ...

    def linearize(self, T_world_scan: np.ndarray) -> TermLinearization: ...

    def pose_pairs(self) -> np.ndarray: ...


def no_pairs() -> np.ndarray:
    """The (0, 2) pose-pair list of a term with diagonal blocks only."""
    return np.empty((0, 2), dtype=np.int64)
