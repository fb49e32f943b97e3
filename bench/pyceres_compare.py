"""PA_LM on Ceres (pyceres, analytic Jacobians) vs our numpy/scipy `solve_lm`. Prints tables.

Issue 5 asks for PA_LM in "numpy/scipy, or pyceres with analytic Jacobians, whichever is faster
by measurement"; issue 4 asks for the sparse factorisation "chosen by measurement", naming the
SuiteSparse inside pyceres as an option. This script measures both questions.

(a) The same PA_LM problem on Ceres: one residual block per observation (4 residuals
    r_o = L_o^T T_j^T pi_i, L_o the cluster square root of `joint_lm.cluster_sqrt`), Ceres' LM
    (trust region radius = 1/mu, the same Nielsen schedule and diagonal clamp [1e-6, 1e32] as
    ours) with SPARSE_SCHUR on SuiteSparse (CHOLMOD). pyceres 2.6 cannot run Python manifolds
    (its trampoline raises "<PlusJacobian> not implemented"), so the parameter blocks use Ceres'
    own manifolds and the Jacobians are handed over in ambient coordinates:
    - pose j: a quaternion block (QuaternionManifold, left update q <- [cos|d|, sin|d| d/|d|] q,
      i.e. R <- Exp(2 d) R) and a translation block (Euclidean, t <- t + rho). The ambient
      Jacobian reuses joint_lm's left-perturbation Jacobian J = (J_omega, J_rho)
      (`JointModel.jacobians`): with our retraction t <- Exp(omega) t + rho the Ceres
      coordinates are rho_ours = rho + skew(t) omega, so J_omega_ceres = J_omega + J_rho skew(t);
      then d r/d q = 2 J_omega_ceres P(q)^T with P(q) the (4, 3) PlusJacobian (orthonormal
      columns, so Ceres' product J_q P = 2 J_omega_ceres exactly).
    - plane i: one homogeneous unit 4-vector pi_loc = [n; e] on SphereManifold(4), expressed about
      the plane's anchor a_i (its centroid at the initial poses, as joint_lm does): the world
      plane is [n; e - n . a] / |n|, so r_o = L_o^T T_j^T A_i^T pi_loc / |n| with A_i = [[I, -a],
      [0, 1]]. Same 3 dof, same anchoring as joint_lm; the tangent basis differs (Ceres').
    The cost functions are Python (pyceres' only way besides its two built-in factors), so every
    evaluation makes one Python call per observation; Ceres' summary splits the time into
    evaluation (Python) and linear solver (C++), so the table also shows what Ceres alone costs.
(b) pyceres exposes no linear solver for a user matrix (its API: Problem, CostFunction,
    manifolds, losses, SolverOptions/solve, Covariance, CRSMatrix for Jacobian output only), so
    the factorisation is compared inside (a): Ceres' SPARSE_SCHUR linear-solver time per solve
    (Schur complement + CHOLMOD) against our `JointLinearization.solve` (Schur complement +
    SuperLU) on the same problems, and on the 1000 x 5000 x 40 problem of bench/solver.py also
    against the newton engine's solve (QDLDL on its augmented pose-plane system, whose Schur
    complement is the pose Hessian, the reduced camera system's sparsity).

    PYTHONPATH=. python bench/pyceres_compare.py            # ~5 min on 2 cores
    PYTHONPATH=. python bench/pyceres_compare.py --quick    # synthetic 100 scans only
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import pyceres
from scipy.spatial.transform import Rotation

from pa_cli.adjust.joint_lm import JointModel, solve_lm
from pa_cli.adjust.newton import plane_cost
from pa_cli.config import SolverConfig
from pa_cli.core.geometry import skew
from pa_cli.core.problem import FeatureProblem
from pa_cli.evaluation import PERTURBATION_LEVELS, perturb_poses

REL_OPT = 1e-6


# ------------------------------------------------------------------------------------------
# Ceres model
# ------------------------------------------------------------------------------------------


def quat_plus_jacobian(q: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions (w, x, y, z) -> (..., 4, 3) Ceres QuaternionManifold PlusJacobian."""
    w, v = q[..., 0], q[..., 1:]
    P = np.empty((*q.shape[:-1], 4, 3))
    P[..., 0, :] = -v
    P[..., 1:, :] = w[..., None, None] * np.eye(3) - skew(v)
    return P


def quat_to_R(q: np.ndarray) -> np.ndarray:
    """(4,) quaternion (w, x, y, z), normalised first -> (3, 3) rotation."""
    return Rotation.from_quat(q[[1, 2, 3, 0]]).as_matrix()


class ObservationCost(pyceres.CostFunction):
    """4 residuals of one observation; blocks [q (4), t (3), pi_loc (4)]; ambient Jacobians."""

    def __init__(self, L_T: np.ndarray, anchor: np.ndarray) -> None:
        super().__init__()
        self.set_num_residuals(4)
        self.set_parameter_block_sizes([4, 3, 4])
        self.L_T = L_T
        self.A_T = np.eye(4)
        self.A_T[3, :3] = -anchor  # A^T: pi_world = A^T pi_loc

    def Evaluate(self, params, residuals, jacobians) -> bool:  # noqa: N802 (pyceres API)
        q, t, pl = params
        s = np.sqrt(pl[0] ** 2 + pl[1] ** 2 + pl[2] ** 2)
        pw = self.A_T @ pl  # unnormalised world plane
        n = pw[:3] / s
        d = pw[3] / s
        R = quat_to_R(q)
        y = np.empty(4)
        y[:3] = R.T @ n
        y[3] = t @ n + d
        r = self.L_T @ y
        residuals[:] = r
        if jacobians is None:
            return True
        LR = self.L_T[:, :3] @ R.T  # (4, 3)
        J_rho = np.outer(self.L_T[:, 3], n)  # (4, 3) = L^T [0; n^T]
        if jacobians[0] is not None or jacobians[1] is not None:
            # joint_lm's J_omega at rho = 0 for the Ceres translation coordinates: L^T [R^T skew(n); 0]
            J_om = LR @ skew(n)
            if jacobians[0] is not None:
                qn = q / np.linalg.norm(q)
                jacobians[0][:] = (2.0 * J_om @ quat_plus_jacobian(qn).T).ravel()
            if jacobians[1] is not None:
                jacobians[1][:] = J_rho.ravel()
        if jacobians[2] is not None:
            # d r / d pi_world = L^T T^T, pi_world = A^T pl / |n|
            M = np.empty((4, 4))
            M[:, :3] = LR + np.outer(self.L_T[:, 3], t)
            M[:, 3] = self.L_T[:, 3]
            dn = np.zeros((4, 4))
            dn[:, :3] = np.outer(pw, pl[:3]) / s**3
            jacobians[2][:] = (M @ (self.A_T / s - dn)).ravel()
        return True


class Recorder(pyceres.IterationCallback):
    """Cost (our scale: sum r^2, m^2) and cumulative time (s) after every Ceres iteration."""

    def __init__(self) -> None:
        super().__init__()
        self.costs: list[float] = []
        self.times: list[float] = []

    def __call__(self, summary):
        self.costs.append(2.0 * summary.cost)
        self.times.append(summary.cumulative_time_in_seconds)
        return pyceres.CallbackReturnType.SOLVER_CONTINUE


def ceres_solve(problem: FeatureProblem, T_init: np.ndarray, options: SolverConfig, threads: int = 1) -> dict:
    """Run PA_LM on Ceres from T_init (planes by PCA, as joint_lm); returns timings and costs."""
    t0 = time.perf_counter()
    model = JointModel(problem, options.fixed_pose)
    state = model.initial_state(T_init)
    anchors = state.anchors_world
    quats = Rotation.from_matrix(T_init[:, :3, :3]).as_quat()[:, [3, 0, 1, 2]].copy()
    trans = T_init[:, :3, 3].copy()
    planes = np.concatenate([state.normals_world, (np.einsum("pa,pa->p", state.normals_world, anchors)
                                                   + state.offsets_m)[:, None]], axis=1)
    q_blocks = [np.ascontiguousarray(quats[j]) for j in range(problem.n_scans)]
    t_blocks = [np.ascontiguousarray(trans[j]) for j in range(problem.n_scans)]
    p_blocks = [np.ascontiguousarray(planes[i]) for i in range(problem.n_planes)]
    prob = pyceres.Problem()
    costs = []  # keep the Python cost functions alive
    for o in range(problem.n_observations):
        i, j = int(problem.plane_index[o]), int(problem.scan_index[o])
        c = ObservationCost(np.ascontiguousarray(model.L_T[o]), anchors[i])
        costs.append(c)
        prob.add_residual_block(c, None, [q_blocks[j], t_blocks[j], p_blocks[i]])
    for j in range(problem.n_scans):
        prob.set_manifold(q_blocks[j], pyceres.QuaternionManifold())
    for i in range(problem.n_planes):
        prob.set_manifold(p_blocks[i], pyceres.SphereManifold(4))
    prob.set_parameter_block_constant(q_blocks[options.fixed_pose])
    prob.set_parameter_block_constant(t_blocks[options.fixed_pose])
    t_setup = time.perf_counter() - t0

    opts = pyceres.SolverOptions()
    opts.linear_solver_type = pyceres.LinearSolverType.SPARSE_SCHUR
    opts.sparse_linear_algebra_library_type = pyceres.SparseLinearAlgebraLibraryType.SUITE_SPARSE
    opts.trust_region_strategy_type = pyceres.TrustRegionStrategyType.LEVENBERG_MARQUARDT
    opts.initial_trust_region_radius = 1.0 / options.initial_damping
    opts.min_lm_diagonal, opts.max_lm_diagonal = 1e-6, 1e32
    opts.max_num_iterations = options.max_iterations
    opts.function_tolerance = options.cost_tolerance
    opts.gradient_tolerance = options.gradient_tolerance
    opts.parameter_tolerance = options.step_tolerance
    opts.num_threads = threads
    opts.logging_type = pyceres.LoggingType.SILENT
    rec = Recorder()
    opts.callbacks = [rec]
    opts.update_state_every_iteration = False
    summary = pyceres.SolverSummary()
    t1 = time.perf_counter()
    pyceres.solve(opts, prob, summary)
    wall = time.perf_counter() - t1
    T = np.tile(np.eye(4), (problem.n_scans, 1, 1))
    T[:, :3, :3] = Rotation.from_quat(np.array(q_blocks)[:, [1, 2, 3, 0]]).as_matrix()
    T[:, :3, 3] = np.array(t_blocks)
    iters = len(rec.costs) - 1  # the callback also reports Ceres' iteration 0 (the initial state)
    return {"T": T, "iterations": iters, "wall_s": wall, "setup_s": t_setup,
            "eval_s": summary.residual_evaluation_time_in_seconds + summary.jacobian_evaluation_time_in_seconds,
            "linsolve_s": summary.linear_solver_time_in_seconds, "n_linsolves": summary.num_linear_solves,
            "costs": np.array(rec.costs), "times": np.array(rec.times),
            "termination": str(summary.termination_type).split(".")[-1], "message": summary.message,
            "summary": summary}


def check_jacobians(problem: FeatureProblem) -> None:
    """The Ceres cost's ambient Jacobians against central differences, and its pose Jacobian
    (in Ceres' tangent coordinates) against joint_lm's `JointModel.jacobians` after the change of
    coordinates rho_ours = rho + skew(t) omega, on every observation of a small problem."""
    T = perturb_poses(problem.T_world_scan, 0.05, 0.1, np.random.default_rng(0), keep_first=True)
    model = JointModel(problem)
    state = model.initial_state(T)
    state = model.retract(state, np.random.default_rng(1).normal(0, 0.01, 6 * problem.n_scans
                                                                   + 3 * problem.n_planes))
    _, J_pose, _ = model.jacobians(state)
    quats = Rotation.from_matrix(state.T_world_scan[:, :3, :3]).as_quat()[:, [3, 0, 1, 2]]
    pl = np.concatenate([state.normals_world, (np.einsum("pa,pa->p", state.normals_world, state.anchors_world)
                                               + state.offsets_m)[:, None]], axis=1)
    worst_fd = worst_lm = 0.0
    h = 1e-6
    for o in range(problem.n_observations):
        i, j = problem.plane_index[o], problem.scan_index[o]
        cost = ObservationCost(model.L_T[o], state.anchors_world[i])
        blocks = [quats[j].copy(), state.T_world_scan[j, :3, 3].copy(), pl[i].copy()]
        r = np.zeros(4)
        J = [np.zeros(16), np.zeros(12), np.zeros(16)]
        cost.Evaluate(blocks, r, J)
        for b, size in enumerate((4, 3, 4)):
            Jb = J[b].reshape(4, size)
            for k in range(size):
                plus = [x.copy() for x in blocks]
                minus = [x.copy() for x in blocks]
                plus[b][k] += h
                minus[b][k] -= h
                rp, rm = np.zeros(4), np.zeros(4)
                cost.Evaluate(plus, rp, None)
                cost.Evaluate(minus, rm, None)
                fd = (rp - rm) / (2 * h)
                worst_fd = max(worst_fd, float(np.abs(fd - Jb[:, k]).max() / max(np.abs(Jb).max(), 1e-12)))
        J_om_ceres = J[0].reshape(4, 4) @ quat_plus_jacobian(quats[j]) / 2.0
        J_om_ours = J_pose[o, :, :3] + J_pose[o, :, 3:] @ skew(state.T_world_scan[j, :3, 3])
        scale = max(np.abs(J_pose[o]).max(), 1e-12)
        worst_lm = max(worst_lm, float(np.abs(J_om_ceres - J_om_ours).max() / scale),
                       float(np.abs(J[1].reshape(4, 3) - J_pose[o, :, 3:]).max() / scale))
    print(f"Jacobian checks on {problem.n_observations} observations: ambient vs central differences "
          f"{worst_fd:.1e}, pose Jacobian vs joint_lm {worst_lm:.1e} (max relative error)")


# ------------------------------------------------------------------------------------------
# numpy solve_lm, with its solve time split out
# ------------------------------------------------------------------------------------------


def numpy_solve(problem: FeatureProblem, T_init: np.ndarray, options: SolverConfig) -> dict:
    from pa_cli.adjust import joint_lm

    solve_times: list[float] = []
    original = joint_lm.JointLinearization.solve

    def timed(self, mu):
        t = time.perf_counter()
        out = original(self, mu)
        solve_times.append(time.perf_counter() - t)
        return out

    stamps: list[tuple[float, float]] = []
    t0 = time.perf_counter()
    joint_lm.JointLinearization.solve = timed
    try:
        result = solve_lm(problem, T_init, options,
                          progress=lambda rec: stamps.append((rec.cost_m2, time.perf_counter() - t0)))
        T, fields = result.T_world_scan, result.fields
    finally:
        joint_lm.JointLinearization.solve = original
    wall = time.perf_counter() - t0
    return {"T": T, "iterations": fields["iterations"], "wall_s": wall, "linsolve_s": float(np.sum(solve_times)),
            "n_linsolves": len(solve_times), "costs": np.array([c for c, _ in stamps]),
            "times": np.array([t for _, t in stamps]), "termination": fields["stop_reason"]}


def time_to_opt(run: dict, cost_opt: float) -> tuple[float | None, int | None]:
    """(time s, iteration) of the first iterate within REL_OPT of the optimum. Ceres' record starts
    at its iteration 0 (the initial state), ours at iteration 1."""
    hit = np.flatnonzero(run["costs"] <= cost_opt * (1.0 + REL_OPT))
    if not len(hit):
        return None, None
    return float(run["times"][hit[0]]), int(hit[0]) + (0 if "setup_s" in run else 1)


# ------------------------------------------------------------------------------------------
# problems
# ------------------------------------------------------------------------------------------


def synthetic(n_scans: int) -> FeatureProblem:
    from pa_testing.synthetic_problems import make_scene

    return make_scene(n_scans=n_scans, n_planes=4 * n_scans, window=8 if n_scans <= 100 else 20,
                      points_per_observation=30, noise_m=0.01, seed=0)[0]


def kaist() -> FeatureProblem | None:
    sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
    from convergence import Skip, _real

    try:
        return _real("kaist03-21")
    except Skip as exc:
        print(f"kaist03-21 skipped: {exc}")
        return None


def fmt(v, spec=".3f") -> str:
    return "-" if v is None else format(v, spec)


def compare(name: str, problem: FeatureProblem, levels: list[int], seeds: int, max_iterations: int) -> None:
    from pa_cli.adjust import solve

    tight = SolverConfig(max_iterations=200, cost_tolerance=1e-15, gradient_tolerance=1e-12, step_tolerance=1e-14)
    ref = solve(problem, problem.T_world_scan, tight)
    T_opt, cost_opt = ref.T_world_scan, ref.report["cost_final_m2"]
    print(f"\n### {name}: {problem.n_scans} scans, {problem.n_planes} planes, {problem.n_observations} "
          f"observations; optimum {cost_opt:.9g} m^2 (newton)\n")
    print("| level | seed | solver | iterations | to opt: iter / s | total s | s/iter | linear solve s/solve "
          "| Python eval s | final plane cost/opt - 1 | stop |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    options = SolverConfig(max_iterations=max_iterations)
    for level in levels:
        sr, st = PERTURBATION_LEVELS[level]
        for seed in range(seeds):
            T_init = perturb_poses(T_opt, np.deg2rad(sr), st, np.random.default_rng(1000 * level + seed),
                                   keep_first=True)
            for label, fn in (("numpy lm", numpy_solve), ("ceres lm", ceres_solve)):
                run = fn(problem, T_init, options)
                t_opt, it_opt = time_to_opt(run, cost_opt)
                gap = plane_cost(problem, run["T"]) / cost_opt - 1.0
                extra = f" (+{run['setup_s']:.2f} setup)" if "setup_s" in run else ""
                print(f"| {level} | {seed} | {label} | {run['iterations']} | {fmt(it_opt, 'd')} / {fmt(t_opt)} | "
                      f"{run['wall_s']:.3f}{extra} | {run['wall_s'] / max(run['iterations'], 1):.4f} | "
                      f"{run['linsolve_s'] / max(run['n_linsolves'], 1):.4f} | {fmt(run.get('eval_s'))} | "
                      f"{gap:.1e} | {run['termination']} |")
                sys.stdout.flush()


def big_solve(iterations: int) -> None:
    """1000 scans x 5000 planes x 40 observations/plane (bench/solver.py's target case)."""
    from pa_cli.adjust import linalg, solve
    from pa_testing.synthetic_problems import make_scene, perturb

    problem, T_gt = make_scene(1000, 5000, 40, points_per_observation=10, noise_m=0.01, seed=0)
    T0 = perturb(T_gt, np.deg2rad(1.0), 0.1, seed=2)
    print(f"\n### 1000 x 5000 x 40: {problem.n_observations} observations, {iterations} iterations each\n")
    options = SolverConfig(max_iterations=iterations)
    newton_solves: list[float] = []
    original = linalg.damped_solve

    def timed(*a, **k):
        t = time.perf_counter()
        out = original(*a, **k)
        newton_solves.append(time.perf_counter() - t)
        return out

    import pa_cli.adjust.newton as newton_mod

    newton_mod.damped_solve = timed
    try:
        t = time.perf_counter()
        res = solve(problem, T0, options)
        t_newton = time.perf_counter() - t
    finally:
        newton_mod.damped_solve = original
    rows = [("newton (QDLDL on the augmented pose-plane system)", res.report["iterations"], t_newton,
             float(np.mean(newton_solves)) if newton_solves else None, None)]
    run = numpy_solve(problem, T0, options)
    rows.append(("numpy lm (Schur + SuperLU)", run["iterations"], run["wall_s"],
                 run["linsolve_s"] / max(run["n_linsolves"], 1), None))
    run = ceres_solve(problem, T0, options)
    rows.append((f"ceres lm (SPARSE_SCHUR + CHOLMOD), setup {run['setup_s']:.1f} s", run["iterations"],
                 run["wall_s"], run["linsolve_s"] / max(run["n_linsolves"], 1), run["eval_s"]))
    print("| solver | iterations | total s | linear solve s/solve | Python eval s |\n|---|---|---|---|---|")
    for label, it, tot, per, ev in rows:
        print(f"| {label} | {it} | {tot:.2f} | {fmt(per)} | {fmt(ev, '.2f')} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--max-iterations", type=int, default=100)
    ap.add_argument("--no-big", action="store_true", help="skip the 1000 x 5000 x 40 solve comparison")
    args = ap.parse_args()

    check_jacobians(synthetic(12))
    compare("synthetic 100", synthetic(100), [1, 2, 3, 4], args.seeds, args.max_iterations)
    if args.quick:
        return
    compare("synthetic 300", synthetic(300), [2, 4], 1, args.max_iterations)
    problem = kaist()
    if problem is not None:
        compare("kaist03-21", problem, [3], 1, args.max_iterations)
    if not args.no_big:
        big_solve(3)


if __name__ == "__main__":
    main()
