"""The state the stages of `pa refine` pass on: trajectories by role, the association, the records.

Poses are T_world_scan (N, 4, 4), metres, in the local frame of `pa_cli.core.local_frame` (the
world frame moved by `origin_world_m`, whole kilometres; zero near the world origin); the
outputs turn them back into the world frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pa_cli.adjust.odometry_factors import OdometryFactors
from pa_cli.core.problem import FeatureProblem
from pa_cli.evaluation.degeneracy import Degeneracy
from pa_cli.evaluation.quality import Quality
from pa_cli.planes.edges import EdgeLabels
from pa_cli.planes.labels import PointLabels
from pa_cli.refine.deskew import DeskewedPoints


@dataclass
class Assessment:
    """The evidence on the current poses: the plane cost summary, the degeneracy, the verdict."""

    summary: dict[str, Any]
    degeneracy: Degeneracy
    quality: Quality


@dataclass
class RoundsResult:
    """What the rounds made (`pa_cli.refine.rounds`): the poses, the last round's feature problem
    (`problem`, planes and edges) and its planes alone (`plane_problem`), the association of the
    last round (`PointLabels`; the first round's serves the assessment inside the rounds and is
    not kept: an int32 per point), a record per round, whether
    the rounds settled (the last round moved no pose more than the tolerances, and once
    `pa_cli.refine.stages.association_check` judged it, the association stopped changing the
    answer before it was frozen; `unsettled_association`: the scans the last fresh association
    still moved when the cap froze it, with that judgement), the pose terms of the adjustment and
    the solver's state of the last solve (reused by the covariance; None when it does not hold the
    final terms)."""

    T_world_scan: np.ndarray
    problem: FeatureProblem
    plane_problem: FeatureProblem
    labels_final: PointLabels
    rounds: list[dict[str, Any]]
    settled: bool
    terms: list[Any]
    odometry_factors: OdometryFactors | None
    solver_model: Any
    assessment: Assessment
    unsettled_association: dict[str, Any] | None = None
    start_consistency: dict[str, Any] | None = None  # `pa_cli.refine.consistency`'s record, once checked
    # (N, 6) (omega rad, rho m; `tangent_error`): how the last fresh association changed the answer of the
    # fresh round before it (None: one fresh association)
    association_change: np.ndarray | None = None
    edge_labels: EdgeLabels | None = None  # the edges of the last fresh association (None: the run uses none)
    # the registrations' noise the odometry factors take (`MotionNoise.report`; None: not measured)
    motion_noise: dict[str, Any] | None = None


@dataclass
class RoundsCarry:
    """What one round of `pa_cli.refine.rounds` hands the next, all the next needs to continue
    exactly: the index of the next round (0 for the first), the poses it starts from, the rounds'
    records so far, the association of the first and of the latest fresh round, whether that
    association is frozen, the association the cap froze while it still moved (None: none) and the
    deskew fixed point's memory (`DeskewFixedPoint.memory`), how the latest fresh association
    changed the answer (`RoundsResult.association_change`) and its edges (None: the run uses none)."""

    next_round: int
    T_world_scan: np.ndarray
    records: list[dict[str, Any]]
    labels_initial: PointLabels | None = None
    labels_final: PointLabels | None = None
    frozen: bool = False
    unsettled_association: dict[str, Any] | None = None
    fixed_point: dict[str, np.ndarray] = field(default_factory=dict)
    association_change: np.ndarray | None = None
    edge_labels: EdgeLabels | None = None


@dataclass
class RefineState:
    """Trajectories by role and what the stages made, in stage order.

    `T_odometry`: KISS-ICP's poses or those of --poses; `T_initial`: the rounds' start (loop-closed
    when loops ran, moved to the scans' reference instants when deskewing after KISS-ICP);
    `T_current`: the latest estimate. `timestamps` (N,) s or None; `odometry_frames`: the scans as
    KISS-ICP thinned them (`pa_cli.refine.odometry.run_kiss_icp`'s frames, float32, sensor frame, m), kept
    for the loop stage's local maps when they are fine enough for them and dropped after it (None
    otherwise); `deskewed`: the scans' motion-compensated points (None without motion compensation).
    The dicts are the stages' records for the report.
    """

    origin_world_m: np.ndarray
    T_odometry: np.ndarray
    T_initial: np.ndarray
    T_current: np.ndarray
    initial_poses_source: str
    timestamps: np.ndarray | None = None
    timestamps_source: str = "scan index"
    odometry_frames: list[np.ndarray] | None = None
    loops: dict[str, Any] = field(default_factory=lambda: {"enabled": False})
    deskew: dict[str, Any] = field(default_factory=dict)
    deskewed: DeskewedPoints | None = None
    rounds: RoundsResult | None = None
    covariance: Any = None
    covariance_report: dict[str, Any] | None = None
    gt: dict[str, Any] | None = None
