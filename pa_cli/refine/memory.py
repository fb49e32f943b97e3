"""Memory estimates of the stages of `pa refine` that grow with the sequence, checked before each.

Each estimate counts what the stage holds at once from the sizes known before it starts (the
scans, their points, the feature observations) and is compared with `execution.memory_budget_gb`;
above it a warning names the stage, the estimate and the key that changes it. The run goes on
(the estimates are estimates, and a stopped run continues with `--resume`). The number of points
is estimated from the scan files' bytes before any point is read. The pose covariance checks its
own bound (`pa_cli.refine.stages.pose_covariance`) and skips itself above the budget.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from pa_cli.config import PaConfig, SolverConfig
from pa_cli.core.problem import FeatureProblem
from pa_cli.refine.stages import covariance_lower_bound_gb
from pa_cli.runtime.distributed import GB

log = logging.getLogger(__name__)

FILE_BYTES_PER_POINT = 16  # float32 x y z and one more field (intensity or time): the usual PCD, BIN, PointCloud2
CACHED_POINT_BYTES = 16  # the point cache: float32 x y z and a float32 time offset (`CachedSource`)
POINT_BYTES = 24  # a point placed by a pose or held by a local map: float64 x y z
FRAME_BYTES = 12  # a point of the odometry's thinned frames kept for the loop stage: float32 x y z
LABEL_BYTES = 2 * 4  # the association of the first and of the last round: an int32 observation per point each
DESKEW_BYTES = 24 + 8  # a deskewed point: float64 x y z and its float64 time
# a map point until written: float64 x y z and time, int32 scan, float32 intensity, and its voxel's key in the
# writer's hash set (at most 32 bytes, `pa_cli.io.voxel_key_set`)
MAP_POINT_BYTES = 72
POSE_BYTES = 16 * 8  # a 4x4 float64 pose
CLUSTER_BYTES = 2 * 16 * 8  # an observation's 4x4 float64 cluster and its range cluster
SYSTEM_MATRICES = 2  # the flat solve's reduced matrix and its factor (the covariance's bound counts three)


# per stage over the sequence: bytes held per point besides the cache, what is held, the key that lowers it
SEQUENCE_STAGES = {
    "odometry": (0, "the point cache", "lower execution.cache_budget_gb"),
    "loops": (POINT_BYTES, "the point cache and the local maps",
              "raise advanced.loops.local_map_voxel_m or lower execution.cache_budget_gb"),
    "planes": (POINT_BYTES + LABEL_BYTES + DESKEW_BYTES,
               "the point cache, the points at the poses, their association and deskewed copies",
               "lower execution.cache_budget_gb or use fewer scans (--glob)"),
    "map": (MAP_POINT_BYTES, "the point cache and the map's points", "raise map.voxel_m (--map-voxel-m)"),
}


@dataclass(frozen=True)
class SequenceSize:
    """The sequence's scan count and its number of points, estimated from the scan files' bytes."""

    n_scans: int
    n_points: int

    @classmethod
    def from_files(cls, n_scans: int, n_bytes: int) -> SequenceSize:
        return cls(int(n_scans), int(n_bytes) // FILE_BYTES_PER_POINT)


def check_memory(stage: str, needed_gb: float, holds: str, fix: str, config: PaConfig) -> bool:
    """Warn when `stage` is expected to hold `needed_gb` (GB; `holds` says of what) above
    execution.memory_budget_gb; `fix` names the key that lowers the estimate. True when within."""
    budget_gb = config.execution.memory_budget_gb
    if needed_gb <= budget_gb:
        return True
    log.warning("%s: expected to hold about %.2f GB (%s), above execution.memory_budget_gb = %g; %s, or raise "
                "execution.memory_budget_gb if the machine has the memory (a run stopped by lack of memory "
                "continues with --resume).", stage, needed_gb, holds, budget_gb, fix)
    return False


def _cache_gb(size: SequenceSize, config: PaConfig) -> float:
    """The point cache when every point is read: at most execution.cache_budget_gb."""
    if not config.advanced.execution.cache_points:
        return 0.0
    return min(size.n_points * CACHED_POINT_BYTES / GB, config.execution.cache_budget_gb)


def check_sequence_memory(stage: str, size: SequenceSize, config: PaConfig) -> bool:
    """The check before a stage over the whole sequence's points: "odometry" (the point cache and
    the poses; with loops, the thinned frames it keeps for them), "loops" (and the local maps, at
    most every point), "planes" (and the points placed by the poses, the per-point association and,
    with motion compensation, the deskewed points) or "map" (and the map's points until written)."""
    cache_gb = _cache_gb(size, config)
    poses_gb = size.n_scans * POSE_BYTES / GB
    per_point, held, fix = SEQUENCE_STAGES[stage.split()[0]]
    if stage in ("odometry", "loops") and config.loops.enabled:
        per_point += FRAME_BYTES  # at most every point, until the loop stage is done with them
        held += " (and the odometry's thinned frames)"
    needed_gb = cache_gb + poses_gb + size.n_points * per_point / GB
    return check_memory(stage, needed_gb, f"{held} of {size.n_scans} scans, about {size.n_points:,} points",
                        fix, config)


def check_adjust_memory(stage: str, problem: FeatureProblem, solver: SolverConfig, config: PaConfig) -> bool:
    """The check before an adjustment: the observations' clusters and, for a flat backend, its
    reduced matrix and factor (at least `covariance_lower_bound_gb`'s blocks; the hierarchical
    backend bounds its own windows by the budget)."""
    needed_gb = problem.n_observations * CLUSTER_BYTES / GB
    holds = f"the clusters of {problem.n_observations:,} observations"
    if solver.solver != "hierarchical":
        needed_gb += covariance_lower_bound_gb(problem) * SYSTEM_MATRICES / 3
        holds += f" and the reduced system of {problem.n_scans} scans"
    return check_memory(stage, needed_gb, holds, "set advanced.solver.solver to hierarchical", config)

