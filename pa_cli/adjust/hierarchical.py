"""The `hierarchical` backend: feature adjustment of long sequences, window by window.

Layers (the structure of HBA, hierarchical bundle adjustment):

1. **Windows.** The scans are cut into consecutive cores of `hierarchical_window_scans`; each
   window refines its core plus `hierarchical_overlap_scans` scans on either side (its context)
   by the flat `newton` backend, on the observations of those scans alone (features seen by fewer
   than two of them carry no constraint there and drop out), its poses expressed relative to its
   held scan (`solve_from_held_pose`), with the left retraction's steps (a window lies within
   tens of metres of its held scan; there they take fewer iterations than steps centred on each
   scan, which the layers spanning the whole sequence need). Windows are independent tasks
   (`pa_cli.runtime.distributed`): each
   holds only its own clusters.
2. **Keyframes.** Each core becomes one keyframe whose pose is its anchor scan's refined pose and
   whose clusters are the sums of its scans' clusters moved into the keyframe frame,
   T_kf_scan C T_kf_scan^T (clusters add exactly, `pa_cli.core.clusters`; planes and edges alike).
   Every observation belongs to exactly one core, so the keyframe problem's cost at keyframe
   poses T_world_kf equals the flat cost at the scan poses T_world_kf T_kf_scan: the global layer
   minimises the flat cost over rigid motions of whole cores.
3. **Global.** Flat `newton` over the keyframes, relative to the gauge keyframe; every scan is re-anchored,
   T_world_scan = T_world_kf T_kf_scan.
4. **Seams.** What stays is the flexibility across core boundaries. Cycles 1-3 repeat
   (`hierarchical_cycles`), every second one with the cores shifted by half a core so the previous
   seams fall inside windows; then `hierarchical_final_iterations` flat newton iterations over all
   scans, with the pose terms, finish at the flat optimum. The flat pass is skipped, with a
   warning, when its estimated memory exceeds the memory budget of the current execution
   (`execution.memory_budget_gb`, `pa_cli.runtime.distributed.current_execution`).

A solve that starts at the optimum of a nearby problem (a later round of `pa refine`, its start
check) or of its pose terms (the first round, at the chain of their measured motions) runs the
final flat pass alone when it fits the budget (`warm_config`).

Pose terms (`pa_cli.adjust.terms`) enter the final flat pass only; the layers before it minimise
the feature cost. When the layers raise the whole objective (features and terms), for example
where the features leave a scan free in some direction and only the terms hold it, their result
is discarded with a warning and the final pass starts from the initial poses: it is then the whole
flat solve, not a polish of the layers' result, and runs up to the flat solver's `max_iterations`
(a pass cut short leaves the poses where the next association would be made unconverged). The gauge pose
`fixed_pose` is held fixed in every layer: its window holds it fixed, it anchors its core's
keyframe, and that keyframe is the global layer's gauge.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from pa_cli.adjust.backend import BackendResult
from pa_cli.adjust.damped import IterationRecord
from pa_cli.adjust.newton import FeatureCost, solve_newton
from pa_cli.adjust.terms import PoseTerm
from pa_cli.config import SolverConfig
from pa_cli.core.clusters import sum_by_feature, transform_clusters
from pa_cli.core.geometry import rigid_inverse
from pa_cli.core.problem import FeatureProblem, make_problem
from pa_cli.errors import SolverError
from pa_cli.runtime.distributed import GB, current_execution

# Peak bytes of a flat newton solve per observation, above what bench/scale.py measures (clusters,
# scan-frame and world moments, the exact and Gauss-Newton Hessian pieces A, A_gn (6x6) and Bt,
# Bt_gn (3x6) and their temporaries); the Hessian itself is per pose pair and much smaller.
FLAT_BYTES_PER_OBSERVATION = 4096
# Bytes a window task holds per observation: its clusters, the result and one flat iteration.
WINDOW_BYTES_PER_OBSERVATION = FLAT_BYTES_PER_OBSERVATION + 2 * 128


def flat_pass_gb(problem: FeatureProblem) -> float:
    """The estimated peak memory (GB) of a flat newton pass over every observation of `problem`."""
    return problem.n_observations * FLAT_BYTES_PER_OBSERVATION / GB


@dataclass
class WindowTask:
    """One window: its observations (scans numbered 0..n_scans-1 within the window; features by
    their problem-wide index, `feature_kind` of every feature), the poses of its scans and the scan
    held fixed (local index, or -1: the first scan)."""

    plane_index: np.ndarray
    scan_index: np.ndarray
    clusters: np.ndarray
    feature_kind: np.ndarray
    T_world_scan: np.ndarray  # (W, 4, 4)
    fixed_scan: int
    config: SolverConfig


def refine_window(task: WindowTask) -> np.ndarray:
    """The window's poses T_world_scan (W, 4, 4) refined by flat newton on its own observations,
    down to `hierarchical_cost_tolerance`, with the left retraction's steps about its held scan.

    A window without a plane seen by two of its scans keeps its poses.
    """
    n_scans = len(task.T_world_scan)
    problem = make_problem(task.plane_index, task.scan_index, task.clusters, n_scans=n_scans,
                           source="hierarchical window", feature_kind=task.feature_kind)
    if problem.n_planes == 0 or n_scans < 2:
        return task.T_world_scan
    config = task.config.model_copy(update={"solver": "newton", "fixed_pose": max(task.fixed_scan, 0),
                                            "cost_tolerance": task.config.hierarchical_cost_tolerance})
    return solve_from_held_pose(problem, task.T_world_scan, config, centred=False)


def solve_from_held_pose(problem: FeatureProblem, T_world_scan: np.ndarray, config: SolverConfig,
                         centred: bool = True) -> np.ndarray:
    """Flat newton (no pose terms) with the poses expressed relative to the held pose
    `config.fixed_pose`, T_held_scan = T_world_held^-1 T_world_scan; returns poses (N, 4, 4) in
    the world frame, the held one exactly as given.

    The feature cost is invariant to one rigid motion of all poses (clusters are in scan frames),
    so the optimum is the same in either frame. Relative to the held pose the system's axes are
    those of the held scan, so every window (and the keyframe layer) is the same system wherever,
    and however turned, it lies along the sequence. `centred`: the solver's steps turn each scan
    about its own position (`retract_centred`), else about the held scan (`retract_left` in the
    held frame).
    """
    held = config.fixed_pose
    T_world_held = T_world_scan[held]
    T_held_scan = rigid_inverse(T_world_held[None])[0] @ T_world_scan
    T_held_scan[held] = np.eye(4)
    refined = T_world_held @ solve_newton(problem, T_held_scan, config, centred=centred).T_world_scan
    refined[held] = T_world_held
    return refined


def core_bounds(n_scans: int, core_scans: int, shift: int) -> np.ndarray:
    """Boundaries (K + 1,) of consecutive cores of `core_scans` scans; with 0 < shift < core_scans the
    first core has `shift` scans (the cores move by core_scans - shift)."""
    inner = np.arange(shift if shift > 0 else core_scans, n_scans, core_scans)
    return np.unique(np.concatenate([[0], inner, [n_scans]])).astype(np.int64)


@dataclass
class HierarchicalResult:
    """Poses, the final flat pass's report fields and the cost (m^2) and time (s) after every layer."""

    T_world_scan: np.ndarray
    fields: dict
    warnings: list[str] = field(default_factory=list)
    stages: list[dict] = field(default_factory=list)  # {"stage", "cost_m2", "time_s", "cpu_s"}


class _ObservationsByScan:
    """Observations of a problem grouped by scan, to cut out windows of consecutive scans fast."""

    def __init__(self, problem: FeatureProblem):
        self.problem = problem
        self.order = np.argsort(problem.scan_index, kind="stable")
        self.ptr = np.searchsorted(problem.scan_index[self.order], np.arange(problem.n_scans + 1))

    def between(self, first: int, stop: int) -> np.ndarray:
        """Indices of the observations by scans first..stop-1."""
        return self.order[self.ptr[first]:self.ptr[stop]]


def _window_tasks(by_scan: _ObservationsByScan, T_world_scan: np.ndarray, bounds: np.ndarray, overlap: int,
                  fixed_pose: int, config: SolverConfig) -> Iterator[WindowTask]:
    problem = by_scan.problem
    for first_core, stop_core in zip(bounds[:-1], bounds[1:], strict=True):
        first, stop = max(first_core - overlap, 0), min(stop_core + overlap, problem.n_scans)
        obs = by_scan.between(first, stop)
        fixed = fixed_pose - first if first <= fixed_pose < stop else -1
        yield WindowTask(problem.plane_index[obs], problem.scan_index[obs] - first, problem.clusters[obs],
                         problem.feature_kind, T_world_scan[first:stop], fixed, config)


def keyframe_problem(problem: FeatureProblem, core_of_scan: np.ndarray, n_cores: int,
                     T_kf_scan: np.ndarray) -> FeatureProblem:
    """The problem over keyframes: per (plane, core) the sum of the core's clusters in the keyframe
    frame, T_kf_scan C T_kf_scan^T (`T_kf_scan` (N, 4, 4): each scan relative to its keyframe)."""
    moved = transform_clusters(problem.clusters, T_kf_scan[problem.scan_index])
    core = core_of_scan[problem.scan_index]
    keys, group = np.unique(problem.plane_index * n_cores + core, return_inverse=True)
    summed = sum_by_feature(moved, group, len(keys))
    summed = 0.5 * (summed + summed.transpose(0, 2, 1))
    return make_problem(keys // n_cores, keys % n_cores, summed, n_scans=n_cores, source="keyframe problem",
                        feature_kind=problem.feature_kind)


def _windows(by_scan: _ObservationsByScan, T_world_scan: np.ndarray, bounds: np.ndarray,
             config: SolverConfig) -> np.ndarray:
    """The window layer: every core's poses (N, 4, 4) as its window refined them."""
    problem = by_scan.problem
    tasks = _window_tasks(by_scan, T_world_scan, bounds, config.hierarchical_overlap_scans, config.fixed_pose, config)
    item_bytes = problem.n_observations / max(len(bounds) - 1, 1) * WINDOW_BYTES_PER_OBSERVATION
    refined = current_execution().map(refine_window, tasks, item_bytes)
    overlap = config.hierarchical_overlap_scans
    T_windows = np.empty_like(T_world_scan)
    for T_context, first_core, stop_core in zip(refined, bounds[:-1], bounds[1:], strict=True):
        first = max(first_core - overlap, 0)
        T_windows[first_core:stop_core] = T_context[first_core - first:stop_core - first]
    return T_windows


def _global_layer(problem: FeatureProblem, T_windows: np.ndarray, bounds: np.ndarray,
                  config: SolverConfig) -> np.ndarray:
    """Keyframes from the window poses, the global adjustment over them, every scan re-anchored."""
    fixed = config.fixed_pose
    n_cores = len(bounds) - 1
    anchor = np.where((bounds[:-1] <= fixed) & (fixed < bounds[1:]), fixed, bounds[:-1])
    core_of_scan = np.repeat(np.arange(n_cores), np.diff(bounds))
    T_world_kf = T_windows[anchor]
    T_kf_scan = rigid_inverse(T_world_kf)[core_of_scan] @ T_windows
    T_kf_scan[anchor] = np.eye(4)  # exactly: the gauge pose anchors its keyframe and must not move
    kf_problem = keyframe_problem(problem, core_of_scan, n_cores, T_kf_scan)
    if n_cores < 2 or kf_problem.n_planes == 0:
        return T_windows
    kf_config = config.model_copy(update={"solver": "newton", "fixed_pose": int(core_of_scan[fixed])})
    T_world_kf = solve_from_held_pose(kf_problem, T_world_kf, kf_config)
    return T_world_kf[core_of_scan] @ T_kf_scan


def hierarchical_adjust(problem: FeatureProblem, T_world_scan_init: np.ndarray, config: SolverConfig,
                        terms: Sequence[PoseTerm] = (),
                        progress: Callable[[IterationRecord], None] | None = None) -> HierarchicalResult:
    """Refine poses (N, 4, 4) by the layers of the module docstring; `progress` sees the final pass.

    `stages` records, per layer of every cycle and for the final pass, the feature cost after it
    (m^2) and the wall and this process's CPU time it took (s).
    """
    clock = [time.perf_counter(), time.process_time()]
    by_scan = _ObservationsByScan(problem)
    T0 = np.asarray(T_world_scan_init, dtype=np.float64)
    T = T0
    feature_cost = FeatureCost(problem, config.eigen_gap_tolerance)
    stages: list[dict] = []

    def record(stage: str, T_stage: np.ndarray) -> None:
        now = [time.perf_counter(), time.process_time()]
        stages.append({"stage": stage, "cost_m2": feature_cost.cost(T_stage), "time_s": now[0] - clock[0],
                       "cpu_s": now[1] - clock[1]})
        clock[:] = time.perf_counter(), time.process_time()  # the cost evaluation is no layer's time

    def objective(T_state: np.ndarray) -> float:
        return feature_cost.cost(T_state) + sum(term.cost(T_state) for term in terms)

    core = config.hierarchical_window_scans
    for cycle in range(config.hierarchical_cycles):
        bounds = core_bounds(problem.n_scans, core, core // 2 if cycle % 2 else 0)
        T = _windows(by_scan, T, bounds, config)
        record(f"cycle {cycle + 1} windows", T)
        T = _global_layer(problem, T, bounds, config)
        record(f"cycle {cycle + 1} global", T)

    warnings: list[str] = []
    iterations = config.hierarchical_final_iterations
    if terms:
        start_m2, layered_m2 = objective(T0), objective(T)
        if not layered_m2 < start_m2:
            warnings.append(f"hierarchical: the window and keyframe layers, which minimise the features alone, raised "
                            f"the whole objective (features and pose terms) from {start_m2:.6g} to {layered_m2:.6g} "
                            "m^2; the final flat pass starts from the initial poses instead, with up to "
                            f"max_iterations ({config.max_iterations}) iterations.")
            T = T0
            if iterations:
                iterations = max(iterations, config.max_iterations)
    flat_gb = flat_pass_gb(problem)
    budget_gb = current_execution().memory_budget_gb
    if iterations and flat_gb > budget_gb:
        warnings.append(f"hierarchical: the final flat pass over {problem.n_scans} scans would need about "
                        f"{flat_gb:.1f} GB, above execution.memory_budget_gb = {budget_gb:g}; skipped, "
                        "the seams between windows are not polished (raise the budget or "
                        "advanced.solver.hierarchical_cycles).")
        iterations = 0
    final_config = config.model_copy(update={"solver": "newton", "max_iterations": max(iterations, 1),
                                             "cost_tolerance": config.hierarchical_cost_tolerance})
    if iterations:
        result = solve_newton(problem, T, final_config, terms, progress)
        T, fields = result.T_world_scan, result.fields
        warnings += result.warnings
        fields["cost_initial_m2"] = objective(T0)
        record("final flat pass", T)
    else:
        fields = {"iterations": 0, "cost_initial_m2": objective(T0), "cost_final_m2": objective(T),
                  "converged": False, "stop_reason": "hierarchical_cycles", "history": []}
    return HierarchicalResult(T, fields, warnings, stages)


def solve_hierarchical(problem: FeatureProblem, T_world_scan_init: np.ndarray, config: SolverConfig,
                       terms: Sequence[PoseTerm] = (),
                       progress: Callable[[IterationRecord], None] | None = None) -> BackendResult:
    """The `hierarchical` backend (see the module docstring); the report's iterations and history
    are those of the final flat pass."""
    result = hierarchical_adjust(problem, T_world_scan_init, config, terms, progress)
    return BackendResult(result.T_world_scan, result.fields, result.warnings)


BACKENDS = ("flat", "hierarchical")


def warm_config(config: SolverConfig, problem: FeatureProblem) -> SolverConfig:
    """The solver config of a solve that starts at the optimum of a nearby problem (a round after the
    round before, a perturbed second solve) or of its pose terms (the chain of their measured motions):
    for the hierarchical backend its final flat pass alone, run to convergence, when that pass fits
    `execution.memory_budget_gb` (the layers bring a far start near the optimum of the features, and
    minimise the features alone; from such a start the flat pass is all that remains to do); else
    `config`."""
    if config.solver != "hierarchical" or flat_pass_gb(problem) > current_execution().memory_budget_gb:
        return config
    return config.model_copy(update={"solver": "newton", "cost_tolerance": config.hierarchical_cost_tolerance})


def choose_backend(config: SolverConfig, n_scans: int, backend: str | None = None) -> tuple[SolverConfig, str | None]:
    """The solver config for `backend` ("flat": `config.solver` as given; "hierarchical"), or, when
    `backend` is None, for the size of the problem: hierarchical from `hierarchical_min_scans` scans
    on when the config asks for `newton`. Returns the config and, for a choice made by size, a
    message saying which backend was picked and why (None otherwise)."""
    if backend is not None and backend not in BACKENDS:
        raise SolverError(f"unknown backend '{backend}'; expected one of {list(BACKENDS)} (--backend).")
    if backend == "hierarchical" and config.solver == "lm":
        raise SolverError("the hierarchical backend runs newton in its windows; it cannot run the lm baseline "
                          "(drop --solver lm or use --backend flat).")
    if backend == "hierarchical":
        return config.model_copy(update={"solver": "hierarchical"}), None
    if backend == "flat" or config.solver != "newton":
        return config, None
    if n_scans >= config.hierarchical_min_scans:
        return (config.model_copy(update={"solver": "hierarchical"}),
                f"{n_scans} scans >= advanced.solver.hierarchical_min_scans ({config.hierarchical_min_scans}): "
                "using the hierarchical backend (--backend flat forces the flat one).")
    return config, (f"{n_scans} scans < advanced.solver.hierarchical_min_scans ({config.hierarchical_min_scans}): "
                    "using the flat newton backend (--backend hierarchical forces the hierarchical one).")
