"""Benchmark of the second-order plane adjustment (`pa adjust --solver newton`). Prints tables.

Every case runs in its own subprocess so that its peak memory (ru_maxrss, includes building the
synthetic problem) is its own. Scenes come from `pa_testing.synthetic_problems.make_scene`: planes seen
by a window of consecutive scans, 1 cm point noise (so the optimum has a non-zero cost).

    PYTHONPATH=. python bench/solver.py            # all tables (~5 min on 2 cores)
    PYTHONPATH=. python bench/solver.py --quick    # smaller cases only
    PYTHONPATH=. python bench/solver.py --problems office.npz street.npz [--seeds 3]

`--problems`: saved plane problems (`pa refine --save-problem` at the true poses), perturbed at
levels 1-4 (fix pose 0); per problem and level, pa's `newton` backend against a dense reference
in the same process: the same damped loop, the dense Hessian H = blockdiag(A) - U U^T (BLAS) and
a dense Cholesky (LAPACK, one BLAS thread) of H + mu D, with the same Gauss-Newton fallback (a
stand-in for BALM2's dense 6N x 6N LDL^T). Medians over seeds.
    PYTHONPATH=. python bench/solver.py --cold-start office.npz   # `pa adjust` process wall vs solver time
    PYTHONPATH=. python bench/solver.py --factorisations office.npz street.npz   # pair vs augmented systems
    PYTHONPATH=. python bench/solver.py --compare BEFORE_CHECKOUT . --cold-start office100.npz \
        --per-iteration office100.npz street200.npz --profile street600.npz   # checkouts side by side

`--compare CHECKOUT ...`: the same measurements for each checkout (its folder put first on
PYTHONPATH), interleaved run by run so that the machine's load falls on all of them alike: the
`pa adjust` process wall (medians of 5) and what `python -X importtime` says it imported; the
solver's time per iteration (medians over the iterations of `--seeds` perturbations at level 2)
and the largest difference of the results from the first checkout's; and with `--profile` a
cProfile of one solve, its functions grouped by what they do.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np

from bench.common import markdown_table

LEVELS = {1: (0.1, 0.01), 2: (1.0, 0.1), 3: (2.0, 0.2), 4: (3.0, 0.3)}


def run_case(kind: str, n_scans: int, n_planes: int, window: int, points: int, level: int, iters: int) -> dict:
    from pa_cli.adjust import solve
    from pa_cli.adjust.newton import NewtonModel
    from pa_cli.config import SolverConfig
    from pa_testing.synthetic_problems import make_scene, perturb

    t0 = time.perf_counter()
    problem, T_gt = make_scene(n_scans, n_planes, window, points_per_observation=points, noise_m=0.01, seed=0)
    t_build = time.perf_counter() - t0
    r_rot, r_trans = LEVELS[level]
    T0 = perturb(T_gt, np.deg2rad(r_rot), r_trans, seed=level)
    out = {"n_scans": n_scans, "n_planes": problem.n_planes, "n_obs": problem.n_observations,
           "points": points, "level": level, "build_s": t_build}
    if kind == "levels":
        tight = SolverConfig(cost_tolerance=0.0, gradient_tolerance=0.0, step_tolerance=1e-12, max_iterations=50)
        cost_opt = solve(problem, T_gt, tight).report["cost_final_m2"]
        res = solve(problem, T0, SolverConfig())
        hist = res.report["history"]
        reached = [h["iteration"] for h in hist if h["cost_m2"] <= cost_opt * (1 + 1e-6)]
        out.update(iterations=res.report["iterations"], reached=reached[0] if reached else None,
                   rejected=sum(not h["accepted"] for h in hist), cost_opt=cost_opt,
                   rel_gap=(res.report["cost_final_m2"] - cost_opt) / cost_opt, time_s=res.report["time_s"],
                   s_per_iter=float(np.mean([h["time_s"] for h in hist])), stop=res.report["stop_reason"])
    else:
        t0 = time.perf_counter()
        model = NewtonModel(problem)
        t_setup = time.perf_counter() - t0
        res = solve(problem, T0, SolverConfig(max_iterations=iters))
        hist = res.report["history"]
        # an accepted iteration = solve + cost + new linearisation; the first linearisation is in time_s only
        out.update(setup_s=t_setup, iterations=res.report["iterations"], time_s=res.report["time_s"],
                   s_per_iter=float(np.mean([h["time_s"] for h in hist])),
                   s_per_accepted=float(np.mean([h["time_s"] for h in hist if h["accepted"]] or [np.nan])),
                   n_blocks=model.pattern.n_blocks)
    out["peak_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    return out


class DenseLinearization:
    """The Newton model of `pa_cli.adjust.newton` solved densely: H formed as a dense matrix and
    factorised by dense Cholesky (LAPACK potrf); the reference for the sparse augmented solve."""

    def __init__(self, model, T):
        from pa_cli.adjust.newton import NewtonLinearization

        self.lin = NewtonLinearization(model, T)
        self.cost, self.gradient_norm, self.g = self.lin.cost, self.lin.gradient_norm, self.lin.g
        self.H = self.lin.H.hessian()
        self.H_gn = None

    def _solve(self, H, D, mu):
        import scipy.linalg as sla

        try:
            factor = sla.cho_factor(H + mu * np.diag(D), check_finite=False)
        except np.linalg.LinAlgError:
            return None
        return sla.cho_solve(factor, -self.g, check_finite=False)

    def solve(self, mu):
        system = self.lin.H
        x = self._solve(self.H, system.damping(), mu)
        if x is None:
            lin = self.lin
            if self.H_gn is None:
                lin._H_gn = lin._pattern.assemble(lin._der.A_gn, lin._der.Bt_gn, lin._pose_blocks,
                                                  lin._pair_blocks)
                self.H_gn = lin._H_gn.hessian()
            system = self.lin._H_gn
            x = self._solve(self.H_gn, system.damping(), mu)
            if x is None:
                return None, 0.0
        predicted = 0.5 * (-(self.g @ x) + mu * (x @ (system.damping() * x)))
        return self.lin._pattern.expand_vector(x), float(predicted)


def run_problem(path: str, level: int, seed: int) -> dict:
    """pa `newton` and the dense reference on one saved problem at one perturbation level."""
    from pa_cli.adjust import solve
    from pa_cli.adjust.damped import minimize_damped
    from pa_cli.adjust.linalg import HessianPattern
    from pa_cli.adjust.newton import NewtonModel
    from pa_cli.config import SolverConfig
    from pa_cli.core.geometry import retract_left
    from pa_cli.evaluation import PERTURBATION_LEVELS, perturb_poses
    from pa_cli.io.problem import load_problem

    problem = load_problem(path)
    rot_deg, trans_m = PERTURBATION_LEVELS[level]
    T0 = perturb_poses(problem.T_world_scan, np.deg2rad(rot_deg), trans_m, np.random.default_rng(seed),
                       keep_first=True)
    config = SolverConfig()
    factorise, factorisations = HessianPattern.factorise, []

    def counted(pattern, upper):  # every damped system factorised: exact ones and Gauss-Newton fallbacks
        factorisations.append(1)
        return factorise(pattern, upper)

    HessianPattern.factorise = counted
    cpu_start = time.process_time()
    report = solve(problem, T0, config).report
    cpu_s = time.process_time() - cpu_start
    HessianPattern.factorise = factorise
    t0 = time.perf_counter()
    model = NewtonModel(problem, config.fixed_pose, config.eigen_gap_tolerance)
    _, fields = minimize_damped(T0, lambda T: DenseLinearization(model, T), model.cost, retract_left,
                                lambda step: float(np.linalg.norm(step)), config)
    t_dense = time.perf_counter() - t0
    k = np.bincount(problem.plane_index)
    return {"n_scans": problem.n_scans, "n_planes": problem.n_planes, "n_obs": problem.n_observations,
            "sum_k2": int(np.sum(k * k)), "iterations": report["iterations"], "rejected": report["rejected_steps"],
            "factorisations": len(factorisations),
            "time_s": report["time_s"], "s_per_iter": report["time_s"] / report["iterations"],
            "cpu_s_per_iter": cpu_s / report["iterations"],
            "cost_m2": report["cost_final_m2"], "dense_iterations": fields["iterations"], "dense_time_s": t_dense,
            "dense_cost_m2": fields["cost_final_m2"]}


def bench_problems(paths: list[str], seeds: int) -> None:
    # one BLAS thread: the dense reference's LAPACK Cholesky is fastest so on a shared 2-core machine
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    rows = []
    for path in paths:
        for level in LEVELS:
            runs = [spawn_json([sys.executable, __file__, "--problem-case", path, str(level), str(seed)], env)
                    for seed in range(seeds)]
            med = {key: float(np.median([r[key] for r in runs])) for key in
                   ("iterations", "rejected", "factorisations", "time_s", "s_per_iter", "cpu_s_per_iter",
                    "dense_iterations", "dense_time_s")}
            gap = max(abs(r["cost_m2"] - r["dense_cost_m2"]) / r["dense_cost_m2"] for r in runs)
            r = runs[0]
            rows.append([path.rsplit("/", 1)[-1], f"{r['n_scans']} / {r['n_planes']} / {r['n_obs']} / {r['sum_k2']}",
                         level, med["iterations"], med["rejected"], med["factorisations"], med["time_s"],
                         med["s_per_iter"], med["cpu_s_per_iter"],
                         med["dense_iterations"], med["dense_time_s"], med["time_s"] / med["dense_time_s"], gap])
    markdown_table(f"Saved problems, levels 1-4 (medians of {seeds} seeds; pa newton vs dense Cholesky reference, "
                   f"same process; load average {os.getloadavg()[0]:.1f} at the end)",
                   ["problem", "scans / planes / obs / sum K^2", "level", "pa iterations", "pa rejected",
                    "pa factorisations (exact + Gauss-Newton fallbacks)", "pa solver s",
                    "pa s/iter", "pa CPU s/iter", "dense iterations", "dense s", "pa / dense time",
                    "max rel. cost difference"], rows)


def bench_factorisations(paths: list[str], repeats: int) -> None:
    """Assembly and factorisation of one damped system per saved problem (at its saved poses, mu = 1):
    pose-pair blocks for every plane + SuperLU (the previous solver), the augmented system + SuperLU,
    + QDLDL (fresh: ordering and symbolic analysis included) and + QDLDL refactorisation (the
    solver's steady state), and + PARDISO when `pypardiso` is installed. Medians of `repeats`."""
    import importlib.util

    import qdldl
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    from pa_cli.adjust.linalg import HessianPattern
    from pa_cli.adjust.newton import PlaneCost
    from pa_cli.io.problem import load_problem

    def median_s(f, *args) -> float:
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            f(*args)
            times.append(time.perf_counter() - t0)
        return float(np.median(times))

    def superlu(upper):
        full = (upper + sp.triu(upper, 1).T).tocsc()
        return splu(full, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})

    have_pardiso = importlib.util.find_spec("pypardiso") is not None
    rows = []
    for path in paths:
        problem = load_problem(path)
        cost = PlaneCost(problem)
        der = cost.linearize(problem.T_world_scan)
        row = [path.rsplit("/", 1)[-1]]
        for pair_max_scans in (problem.n_scans, 3):
            pattern = HessianPattern(problem.plane_index, problem.scan_index, problem.n_scans, 0, cost.starts,
                                     pair_max_scans=pair_max_scans)
            system = pattern.assemble(der.A, der.Bt)
            data = system.data.copy()
            data[pattern.csc_diag_pos] += system.damping()
            upper = system.upper(data)
            row += [pattern.dim, upper.nnz, median_s(pattern.assemble, der.A, der.Bt), median_s(superlu, upper)]
        solver = qdldl.Solver(upper, upper=True)
        row += [median_s(qdldl.Solver, upper, True), median_s(solver.update, upper, True), solver.factors()[0].nnz]
        block_args = (problem.plane_index, problem.scan_index, problem.n_scans, 0, cost.starts)

        def analysed_and_factorised(args: tuple, upper: sp.csc_matrix) -> None:
            HessianPattern(*args, pair_max_scans=3, blocks=True).factorise(upper)

        blocks = HessianPattern(*block_args, pair_max_scans=3, blocks=True)
        blocks.factorise(upper)
        row += [median_s(analysed_and_factorised, block_args, upper), median_s(blocks.factorise, upper)]
        if have_pardiso:
            import pypardiso

            full = (upper + sp.triu(upper, 1).T).tocsr()
            rhs = np.ones(upper.shape[0])
            row.append(median_s(pypardiso.spsolve, full, rhs))
        rows.append(row)
    markdown_table(f"One damped system: assembly and factorisation (s, medians of {repeats})",
                   ["problem", "pairs: dim", "pairs: nnz (upper)", "pairs: assemble", "pairs: SuperLU",
                    "augmented: dim", "augmented: nnz (upper)", "augmented: assemble", "augmented: SuperLU",
                    "augmented: QDLDL", "augmented: QDLDL refactor", "QDLDL nnz(L)",
                    "augmented: block LDL^T (with the pattern)", "augmented: block LDL^T refactor"]
                   + (["augmented: PARDISO solve"] if have_pardiso else []), rows)


# Run in a child `python -c`: the phases of one `pa adjust` process, each import timed where the
# CLI would first need it, the solver timed by wrapping `pa_cli.adjust.solve` (wall and CPU, s).
_PHASES = """
import json, sys, time
marks = [("start", time.perf_counter(), time.process_time())]
def mark(name):
    marks.append((name, time.perf_counter(), time.process_time()))
import numpy
mark("numpy")
import scipy.sparse, qdldl
mark("scipy.sparse + qdldl (the factorisation)")
import pydantic, pa_cli.config
mark("pydantic + pa_cli.config (models)")
import typer, rich.console
from pa_cli.cli.main import run
mark("typer, rich, pa_cli.cli (commands registered)")
import pa_cli.adjust
mark("pa_cli.adjust and the rest of pa_cli it imports")
solver = []
solve = pa_cli.adjust.solve
def timed(*args, **kwargs):
    t0, c0 = time.perf_counter(), time.process_time()
    result = solve(*args, **kwargs)
    solver.append((time.perf_counter() - t0, time.process_time() - c0))
    return result
pa_cli.adjust.solve = timed
run(sys.argv[1:])
mark("run")
phases = [(name, t - t_prev, c - c_prev) for (_, t_prev, c_prev), (name, t, c) in zip(marks, marks[1:])]
wall, cpu = phases.pop()[1:]
phases += [("typer parsing, config, problem load, outputs", wall - solver[0][0], cpu - solver[0][1]),
           ("solver", *solver[0])]
print(json.dumps(phases))
"""


def _process_times(cmd: list[str]) -> tuple[float, float, str]:
    """Wall and CPU (user + sys of the child) seconds of one process, and its stdout."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, check=True, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), proc.stdout


def bench_cold_start(path: str, repeats: int) -> None:
    """Wall and CPU time of whole `pa adjust` processes against the solver time in their reports, the
    phases of such a process (imports, parsing, solver), and the floor: the interpreter alone and with
    the imports no `pa adjust` can avoid (numpy; scipy.sparse, which the QDLDL binding imports; typer,
    which imports pydantic). Medians of `repeats`."""
    import tempfile
    from pathlib import Path

    from pa_cli.evaluation import PERTURBATION_LEVELS, perturb_poses
    from pa_cli.io.problem import load_problem
    from pa_cli.io.trajectory import write_kitti

    problem = load_problem(path)
    rot_deg, trans_m = PERTURBATION_LEVELS[2]
    T0 = perturb_poses(problem.T_world_scan, np.deg2rad(rot_deg), trans_m, np.random.default_rng(0),
                       keep_first=True)
    rows, phases = [], []
    floors = {"python -c pass": "pass", "python -c 'import numpy'": "import numpy",
              "python -c 'import numpy, scipy.sparse, qdldl, typer, pydantic'":
              "import numpy, scipy.sparse, qdldl, typer, pydantic"}
    floor_times: dict[str, list] = {name: [] for name in floors}
    with tempfile.TemporaryDirectory() as tmp:
        poses, out, report = Path(tmp) / "init_kitti.txt", Path(tmp) / "out.txt", Path(tmp) / "report.json"
        write_kitti(poses, T0)
        args = ["adjust", path, "--poses", str(poses), "--out", str(out), "--report", str(report), "--force"]
        for _ in range(repeats):
            wall, cpu, _ = _process_times([sys.executable, "-m", "pa_cli", *args])
            solver_s = json.loads(report.read_text())["time_s"]
            rows.append([wall, cpu, solver_s, wall - solver_s, wall / solver_s])
            phases.append(json.loads(_process_times([sys.executable, "-c", _PHASES, *args])[2].splitlines()[-1]))
            for name, code in floors.items():
                floor_times[name].append(_process_times([sys.executable, "-c", code])[:2])
    load = os.getloadavg()[0]
    med = np.median(np.array(rows), axis=0)
    markdown_table(f"`pa adjust` process wall vs solver time ({path}, level 2, medians of {repeats} runs, "
                   f"load average {load:.1f})",
                   ["process wall s", "process CPU s", "solver s", "outside the solver s", "wall / solver"],
                   [list(map(float, med))])
    markdown_table("Phases of one `pa adjust` process (in-process timers, medians)", ["phase", "wall s", "CPU s"],
                   [[p[0], *map(float, np.median([run[i][1:] for run in phases], axis=0))]
                    for i, p in enumerate(phases[0])])
    markdown_table("Floor: bare interpreter processes (medians)", ["process", "wall s", "CPU s"],
                   [[name, *map(float, np.median(np.array(v), axis=0))] for name, v in floor_times.items()])


# Run in a child `python -c` with a checkout first on PYTHONPATH: one solve from a level-2 perturbation
# (seed argv[2]), its per-iteration times and the result, as JSON; with a third argument, under
# cProfile, with the cumulative seconds of the functions named in `PROFILED` (those a checkout lacks: None).
_SOLVE = """
import json, sys, time
import numpy as np
from pa_cli.adjust import solve
from pa_cli.config import SolverConfig
from pa_cli.evaluation import PERTURBATION_LEVELS, perturb_poses
from pa_cli.io.problem import load_problem
t0 = time.perf_counter()
problem = load_problem(sys.argv[1])
t_load = time.perf_counter() - t0
rot_deg, trans_m = PERTURBATION_LEVELS[2]
T0 = perturb_poses(problem.T_world_scan, np.deg2rad(rot_deg), trans_m, np.random.default_rng(int(sys.argv[2])),
                   keep_first=True)
profile = len(sys.argv) > 3
if profile:
    import cProfile, importlib, pstats
    profiler = cProfile.Profile()
    profiler.enable()
result = solve(problem, T0, SolverConfig())
report = result.report
out = {"load_s": t_load, "iterations": report["iterations"], "time_s": report["time_s"],
       "per_iteration_s": [h["time_s"] for h in report["history"]], "cost_m2": report["cost_final_m2"],
       "T": result.T_world_scan.tolist()}
if profile:
    profiler.disable()
    stats = pstats.Stats(profiler).stats
    def key(name):
        if name.startswith("<"):
            return ("~", 0, name)
        module, _, attr = name.rpartition(":")
        obj = importlib.import_module(module)
        for part in attr.split("."):
            obj = getattr(obj, part, None)
        code = getattr(obj, "__code__", None)
        return None if code is None else (code.co_filename, code.co_firstlineno, code.co_name)
    out["profile"] = [stats[k][3] if (k := key(name)) in stats else None for name in sys.argv[3].split(",")]
print(json.dumps(out))
"""

# cProfile rows: (label, function as module:qualified name or a builtin's cProfile name); cumulative s
PROFILED = [
    ("feature linearisation (FeatureCost.linearize)", "pa_cli.adjust.newton:FeatureCost.linearize"),
    ("  of which plane_eigen", "pa_cli.adjust.newton:plane_eigen"),
    ("centring pass over the observations (_centre)", "pa_cli.adjust.newton:NewtonLinearization._centre"),
    ("trial costs (FeatureCost.cost)", "pa_cli.adjust.newton:FeatureCost.cost"),
    ("assembly (HessianPattern.assemble)", "pa_cli.adjust.linalg:HessianPattern.assemble"),
    ("damped solves (damped_solve)", "pa_cli.adjust.linalg:damped_solve"),
    ("  factorisations (the first with ordering)", "pa_cli.adjust.linalg:HessianPattern.factorise"),
    ("  of which QDLDL numeric refactorisations", "<built-in method qdldl.update>"),
    ("  of which block LDL^T numeric factorisations", "pa_cli.adjust.selected_inverse:BlockLDL.factorise"),
    ("  pivot signs: solver.factors() (copies L)", "<built-in method qdldl.factors>"),
    ("  QDLDL solves", "<built-in method qdldl.solve>"),
    ("  block LDL^T solves", "pa_cli.adjust.selected_inverse:BlockLDL.solve"),
    ("Hessian pattern (once per problem)", "pa_cli.adjust.linalg:HessianPattern.__init__"),
    ("  of which pair_form_is_smaller", "pa_cli.adjust.linalg:pair_form_is_smaller"),
    ("whole solve", "pa_cli.adjust:solve"),
]


_HEAVY_MODULES = ["numba", "matplotlib", "open3d", "pa_cli.adjust.covariance", "pa_cli.adjust.selected_inverse",
                  "scipy.sparse.linalg", "scipy.sparse.csgraph", "scipy.sparse", "pydantic", "typer",
                  "pa_cli.config.model", "pa_cli.adjust", "pa_cli.cli"]


def _import_times(stderr: str) -> dict[str, float]:
    """Cumulative import seconds by module from `python -X importtime` output (the first import only)."""
    times: dict[str, float] = {}
    for line in stderr.splitlines():
        _, cumulative, name = (line.split("|") + ["", ""])[:3]
        if line.startswith("import time:") and cumulative.strip().isdigit():
            times.setdefault(name.strip(), int(cumulative) / 1e6)
    return times


def bench_compare(checkouts: list[str], cold_start: str | None, per_iteration: list[str], profile: str | None,
                  repeats: int, seeds: int) -> None:
    """The measurements of the module docstring's `--compare`, each checkout's runs interleaved."""
    import tempfile
    from pathlib import Path

    # each child runs in its checkout: `python -c` and `-m` put the working folder first on sys.path
    dirs = [str(Path(c).resolve()) for c in checkouts]
    envs = [dict(os.environ, PYTHONPATH=d) for d in dirs]
    names = [Path(d).name for d in dirs]
    cold_start = cold_start and str(Path(cold_start).resolve())
    per_iteration = [str(Path(p).resolve()) for p in per_iteration]
    profile = profile and str(Path(profile).resolve())
    load = [os.getloadavg()[0]]
    if cold_start:
        from pa_cli.evaluation import PERTURBATION_LEVELS, perturb_poses
        from pa_cli.io.problem import load_problem
        from pa_cli.io.trajectory import write_kitti

        problem = load_problem(cold_start)
        rot_deg, trans_m = PERTURBATION_LEVELS[2]
        T0 = perturb_poses(problem.T_world_scan, np.deg2rad(rot_deg), trans_m, np.random.default_rng(0),
                           keep_first=True)
        walls: list[list] = [[] for _ in checkouts]
        cpus: list[list] = [[] for _ in checkouts]
        solver_s: list[list] = [[] for _ in checkouts]
        imports: list[dict] = [{} for _ in checkouts]
        with tempfile.TemporaryDirectory() as tmp:
            poses = Path(tmp) / "init_kitti.txt"
            write_kitti(poses, T0)
            for run in range(repeats + 1):  # the first round warms the file cache and numba's
                for i, env in enumerate(envs):
                    out, report = Path(tmp) / f"out{i}.txt", Path(tmp) / f"report{i}.json"
                    cmd = [sys.executable, "-m", "pa_cli", "adjust", cold_start, "--poses", str(poses), "--out",
                           str(out), "--report", str(report), "--force"]
                    before = resource.getrusage(resource.RUSAGE_CHILDREN)
                    t0 = time.perf_counter()
                    subprocess.run(cmd, check=True, capture_output=True, env=env, cwd=dirs[i])
                    wall = time.perf_counter() - t0
                    after = resource.getrusage(resource.RUSAGE_CHILDREN)
                    if run:
                        walls[i].append(wall)
                        cpus[i].append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
                        solver_s[i].append(json.loads(report.read_text())["time_s"])
                    if run == repeats:
                        proc = subprocess.run([sys.executable, "-X", "importtime", *cmd[1:]], check=True,
                                              capture_output=True, text=True, env=env, cwd=dirs[i])
                        imports[i] = _import_times(proc.stderr)
        load.append(os.getloadavg()[0])
        markdown_table(f"`pa adjust` process on {Path(cold_start).name} (level 2; medians of {repeats}, "
                       f"checkouts interleaved; load average {load[0]:.1f} -> {load[-1]:.1f})",
                       ["checkout", "process wall s", "process CPU s", "solver s", "wall / first"],
                       [[name, float(np.median(w)), float(np.median(c)), float(np.median(s)),
                         float(np.median(w) / np.median(walls[0]))]
                        for name, w, c, s in zip(names, walls, cpus, solver_s, strict=True)])
        markdown_table("Imported by `pa adjust` (python -X importtime, cumulative s of the first import; "
                       "- : not imported)", ["module", *names],
                       [[module, *[imp.get(module, "-") for imp in imports]] for module in _HEAVY_MODULES])
    for path in per_iteration:
        runs: list[list[dict]] = [[] for _ in checkouts]
        for seed in range(seeds):
            for i, env in enumerate(envs):
                runs[i].append(spawn_json([sys.executable, "-c", _SOLVE, path, str(seed)], env, dirs[i]))
        load.append(os.getloadavg()[0])
        first = [np.array(r["T"]) for r in runs[0]]
        rows = []
        for name, rs in zip(names, runs, strict=True):
            per_iter = float(np.median([t for r in rs for t in r["per_iteration_s"]]))
            rows.append([name, float(np.median([r["load_s"] for r in rs])), "/".join(str(r["iterations"]) for r in rs),
                         float(np.median([r["time_s"] for r in rs])), per_iter,
                         per_iter / float(np.median([t for r in runs[0] for t in r["per_iteration_s"]])),
                         max(abs(r["cost_m2"] - r0["cost_m2"]) / r0["cost_m2"]
                             for r, r0 in zip(rs, runs[0], strict=True)),
                         max(float(np.abs(np.array(r["T"]) - T).max()) for r, T in zip(rs, first, strict=True))])
        markdown_table(f"Solver on {Path(path).name} (level 2, seeds 0-{seeds - 1}, checkouts interleaved; "
                       f"load average {load[-1]:.1f})",
                       ["checkout", "load_problem s", "iterations", "solver s", "s per iteration (median)",
                        "per iteration / first", "max rel. cost difference", "max pose difference"], rows)
    if profile:
        names_arg = ",".join(name for _, name in PROFILED)
        groups = [spawn_json([sys.executable, "-c", _SOLVE, profile, "0", names_arg], env, d)["profile"]
                  for env, d in zip(envs, dirs, strict=True)]
        markdown_table(f"cProfile of one solve, {Path(profile).name} (level 2, seed 0; cumulative s; load average "
                       f"{os.getloadavg()[0]:.1f})", ["part", *names],
                       [[label, *["-" if g[k] is None else g[k] for g in groups]]
                        for k, (label, _) in enumerate(PROFILED)])


def spawn_json(cmd: list[str], env: dict | None = None, cwd: str | None = None) -> dict:
    text = subprocess.run(cmd, check=True, capture_output=True, text=True, env=env, cwd=cwd).stdout
    return json.loads(text.strip().splitlines()[-1])


def spawn(*args) -> dict:
    return spawn_json([sys.executable, __file__, "--case", *[str(a) for a in args]])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--case", nargs=7)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--problem-case", nargs=3)
    ap.add_argument("--problems", nargs="+")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--cold-start", metavar="PROBLEM.npz")
    ap.add_argument("--factorisations", nargs="+", metavar="PROBLEM.npz")
    ap.add_argument("--compare", nargs="+", metavar="CHECKOUT")
    ap.add_argument("--per-iteration", nargs="*", default=[], metavar="PROBLEM.npz")
    ap.add_argument("--profile", metavar="PROBLEM.npz")
    args = ap.parse_args()
    if args.compare:
        bench_compare(args.compare, args.cold_start, args.per_iteration, args.profile, 5, args.seeds)
        return
    if args.factorisations:
        bench_factorisations(args.factorisations, 3)
        return
    if args.cold_start:
        bench_cold_start(args.cold_start, 5)
        return
    if args.problem_case:
        path, level, seed = args.problem_case
        print(json.dumps(run_problem(path, int(level), int(seed))))
        return
    if args.problems:
        bench_problems(args.problems, args.seeds)
        return
    if args.case:
        kind, *nums = args.case
        print(json.dumps(run_case(kind, *[int(x) for x in nums])))
        return

    rows = []
    for n in ([100] if args.quick else [100, 200, 300]):
        for level in LEVELS:
            r = spawn("levels", n, 4 * n, 20, 20, level, 0)
            rows.append([n, r["n_planes"], r["n_obs"], level, r["iterations"], r["rejected"], r["reached"],
                         r["stop"], r["rel_gap"], r["s_per_iter"]])
    markdown_table("Levels 1-4: iterations to the optimum (noise 1 cm, window 20, 20 points/observation)",
                   ["scans", "planes", "obs", "level", "iterations", "rejected", "first iter within 1e-6 of optimum",
                    "stop", "final rel. gap", "s/iter"], rows)

    rows = []
    scans = [100, 500, 1000] if args.quick else [100, 500, 1000, 2000]
    for n in scans:
        r = spawn("time", n, 5 * n, 40, 10, 2, 5)
        rows.append([n, r["n_planes"], r["n_obs"], r["n_blocks"], r["setup_s"], r["s_per_iter"],
                     r["s_per_accepted"], r["peak_gb"]])
    markdown_table("Time per iteration vs scans (planes = 5 x scans, window 40, level 2, 5 iterations)",
                   ["scans", "planes", "obs", "pose-pair blocks", "setup s", "s/iter", "s/accepted iter", "peak GB"],
                   rows)

    rows = []
    for p in [1000, 2000, 4000]:
        r = spawn("time", 400, p, 40, 10, 2, 5)
        rows.append([400, r["n_planes"], r["n_obs"], r["s_per_iter"], r["s_per_accepted"], r["peak_gb"]])
    markdown_table("Time per iteration vs planes (400 scans, window 40)",
                   ["scans", "planes", "obs", "s/iter", "s/accepted iter", "peak GB"], rows)

    rows = []
    for pts in [10, 100, 1000]:
        r = spawn("time", 200, 1000, 20, pts, 2, 5)
        rows.append([pts, r["n_obs"], r["build_s"], r["s_per_iter"], r["s_per_accepted"]])
    markdown_table("Time per iteration vs points per observation (200 scans, 1000 planes): must stay flat",
                   ["points/obs", "obs", "build problem s", "s/iter", "s/accepted iter"], rows)

    if not args.quick:
        r = spawn("time", 1000, 5000, 40, 10, 2, 5)
        markdown_table("Target: 1000 poses x 5000 planes x 40 observations/plane (target <= 2 s/iter, <= 4 GB)",
                       ["obs", "setup s", "s/iter", "s/accepted iter", "peak GB"],
                       [[r["n_obs"], r["setup_s"], r["s_per_iter"], r["s_per_accepted"], r["peak_gb"]]])


if __name__ == "__main__":
    main()
