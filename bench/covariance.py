"""Benchmark of the per-scan pose covariance (`pa_cli.adjust.covariance`). Prints tables.

1. Monte Carlo on `pa simulate` office and street: the same poses with new range noise per draw
   (`--seed` of the simulator changes only the noise), exact association
   (`build_problem_from_labels`), each draw solved from the true poses with pose 0 fixed (the
   covariance's gauge). Errors e = (omega, rho) with T_est = [[Exp(omega), rho], [0, 1]] T_true.
   NEES = e^T Sigma^-1 e (6 on average when Sigma is right); per-axis 1-sigma in
   (omega rad, scan-origin displacement m), predicted (mean of the draws' Sigma) over empirical
   (standard deviation over the draws), on the scan of median predicted position sigma and as
   the median over scans. Noise models: `range` (the default when the problem has range clusters,
   as `build_problem_from_labels` and the association give it: each observation's variance from
   its residual, spread over its points as noise along the beam plus an isotropic part, their split
   measured from the data (its mean share over the draws in the row's name), sandwich form),
   `per-observation` (the default without range clusters: one variance per observation),
   `per-plane` (one variance per plane) and `uniform` (2 sigma^2 H^-1 with
   sigma^2 = cost / (points - dof)).
2. Time on the synthetic 1000-scan problem of bench/solver.py (5000 planes, window 40): the
   covariance against one Newton iteration (`timing`); then the same problem with SHARED_PLANES
   more planes seen by every scan (a ground: H's pair form is dense, the covariance takes them as
   feature nodes). The synthetic problem keeps no points; its range clusters are its clusters over
   (10 m)^2 (the work does not depend on the values).
3. The factor 2 of the cost without 1/2, by Monte Carlo with i.i.d. noise (`factor_of_two`).
4. Correlated noise (`--realistic`): the synthetic scene with an offset shared by each observation's
   points (`correlated`: the shared variance's estimate against the truth, NEES with it and with the
   points taken as independent), and the Monte Carlo of 1. on scenes with realistic noise: hall and
   office with 2 cm isotropic point noise, street with `--realistic` (seeds from 3000).
5. The whole pipeline on issue 35's hall (`--pipeline-hall`): per seed, `pa simulate hall --path sharp
   --scans 101 --point-noise-m 0.02`, the truth perturbed by 1 deg / 0.1 m (`pa perturb`), `pa refine
   --config indoor` from it (detected planes, registered motions, the covariance it writes). Against
   the truth, the gauge scan's pose aligned: NEES / 6 of the poses, and of the positions alone (the
   position difference against `position_covariance_m2`) NEES / 3 and the share within 3 sigma
   (chi-square, 3 degrees of freedom, 99.73 %).

    PYTHONPATH=. python bench/covariance.py                # 50 draws each, ~5 min on 2 cores
    PYTHONPATH=. python bench/covariance.py --draws 10 --skip-timing
    PYTHONPATH=. python bench/covariance.py --timing-only       # the time table alone (normal priority)
    PYTHONPATH=. python bench/covariance.py --problem P.npz POSES  # the time table of a saved problem
    PYTHONPATH=. python bench/covariance.py --realistic --draws 8 --scans 30  # 4., ~10 min
    PYTHONPATH=. python bench/covariance.py --pipeline-hall 51 52 53 54 55 56 --keep DIR  # 5., ~1 min a seed
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import markdown_table, run_pa

SHARED_PLANES = 3  # planes seen by every scan in the second timing problem (a ground and two long facades)


REALISTIC_SCENES = {"hall, 2 cm point noise": ("hall", {"point_noise_m": 0.02}),
                    "office, 2 cm point noise": ("office", {"point_noise_m": 0.02}),
                    "street --realistic": ("street", {"realistic": True})}
REALISTIC_FIRST_SEED = 3000


def monte_carlo(scene: str, draws: int, scans: int, options: dict | None = None, first_seed: int = 1000
                ) -> list[list]:
    from pa_cli.adjust import solve
    from pa_cli.adjust.covariance import nees, origin_jacobian, pose_covariance, tangent_error
    from pa_cli.config import SolverConfig
    from pa_cli.simulate import SimOptions, build_problem_from_labels, simulate_sequence

    tight = SolverConfig(cost_tolerance=1e-14, gradient_tolerance=1e-12, step_tolerance=1e-12)
    errors, times, shares = [], [], []
    covs: dict[str, list[np.ndarray]] = {"range (default)": [], "per-observation": [], "per-plane": [],
                                         "uniform": []}
    for draw in range(draws):
        seq = simulate_sequence(SimOptions(scene=scene, scans=scans, seed=first_seed + draw, **(options or {})))
        problem = build_problem_from_labels(seq)
        T_est = solve(problem, seq.T_world_scan, tight).T_world_scan
        t0 = time.perf_counter()
        cov = pose_covariance(problem, T_est)
        times.append(time.perf_counter() - t0)
        assert cov.noise_model == "range"
        shares.append(cov.isotropic_share)
        covs["range (default)"].append(cov.covariance[1:])
        covs["per-observation"].append(pose_covariance(problem, T_est, noise_model="observation").covariance[1:])
        covs["per-plane"].append(pose_covariance(problem, T_est, noise_model="plane").covariance[1:])
        covs["uniform"].append(pose_covariance(problem, T_est, point_sigma_m=cov.point_sigma_m).covariance[1:])
        errors.append(tangent_error(T_est, seq.T_world_scan)[1:])
    errors = np.array(errors)
    T = seq.T_world_scan[1:]
    J = np.zeros((len(T), 6, 6))
    J[:, :3, :3] = np.eye(3)
    J[:, 3:] = origin_jacobian(T)
    empirical = np.einsum("nij,dnj->dni", J, errors).std(axis=0)
    rows = []
    for model, c in covs.items():
        c = np.array(c)
        value = nees(errors, c)
        predicted = np.sqrt(np.einsum("nii->ni", J @ c.mean(0) @ J.transpose(0, 2, 1)))
        ratio = predicted / empirical
        median_scan = np.argsort(np.linalg.norm(predicted[:, 3:], axis=1))[len(T) // 2]
        label = f"{model}, isotropic share {np.mean(shares):.2f}" if model.startswith("range") else model
        rows.append([scene, label, draws, len(T) + 1, problem.n_planes, value.mean(), value.mean() / 6,
                     " ".join(f"{r:.2f}" for r in ratio[median_scan]),
                     " ".join(f"{r:.2f}" for r in np.median(ratio, axis=0)),
                     f"{predicted[median_scan, 3:].max() * 1e3:.2f} / "
                     f"{np.rad2deg(predicted[median_scan, :3].max()) * 1e3:.2f}",
                     np.median(times)])
    return rows


def factor_of_two(draws: int) -> list[list]:
    """i.i.d. noise of 1 cm along the plane normals (pa_testing/synthetic_problems.py, 30 scans, the same
    scene with new noise per draw): NEES of 2 sigma^2 H^-1 (sigma given), of sigma^2 H^-1 (the
    same errors, half the covariance) and of the default per-observation estimate."""
    from pa_cli.adjust import solve
    from pa_cli.adjust.covariance import nees, pose_covariance, tangent_error
    from pa_cli.config import SolverConfig
    from pa_testing.synthetic_problems import make_scene

    tight = SolverConfig(cost_tolerance=1e-14, gradient_tolerance=1e-12, step_tolerance=1e-12)
    given, residual, sigmas = [], [], []
    for draw in range(draws):
        problem, T_true = make_scene(30, 120, 8, points_per_observation=30, noise_m=0.01, seed=3,
                                     noise_seed=2000 + draw)
        T_est = solve(problem, T_true, tight).T_world_scan
        e = tangent_error(T_est, T_true)[1:]
        given.append(nees(e, pose_covariance(problem, T_est, point_sigma_m=0.01).covariance[1:]))
        cov = pose_covariance(problem, T_est)
        residual.append(nees(e, cov.covariance[1:]))
        sigmas.append(cov.point_sigma_m)
    given_mean = float(np.mean(given))
    return [["2 sigma^2 H^-1, sigma = 0.01 m given", draws, given_mean],
            ["sigma^2 H^-1 (without the factor 2)", draws, 2.0 * given_mean],
            [f"per-observation residual (global sigma {np.mean(sigmas):.5f} m)", draws, float(np.mean(residual))]]


def correlated(draws: int, cases: tuple[tuple[float, float], ...] = ((0.0, 0.0), (0.0, 0.002), (0.005, 0.002),
                                                                     (0.01, np.deg2rad(0.1)))) -> list[list]:
    """The synthetic scene (12 scans, 40 planes, 30 points per observation over 6 m x 6 m, 5 mm white
    noise) with an offset of sigma sigma_c (m) and a tilt of sigma sigma_t (rad per in-plane axis) shared
    by each observation's points (`cases`), new noise per draw: the estimated shared variances (means over
    draws) against the truth, and the NEES of the default covariance and of the same with the shared
    variances set to 0 (points independent)."""
    import dataclasses

    from pa_cli.adjust import covariance, solve
    from pa_cli.adjust.covariance import nees, pose_covariance, tangent_error
    from pa_cli.config import SolverConfig
    from pa_testing.synthetic_problems import make_scene

    tight = SolverConfig(cost_tolerance=1e-14, gradient_tolerance=1e-12, step_tolerance=1e-12)
    estimate = covariance.correlated_noise_variances
    rows = []
    for sigma_c, sigma_t in cases:
        with_shared, independent, shared, tilt = [], [], [], []
        for draw in range(draws):
            problem, T_true = make_scene(12, 40, 6, points_per_observation=30, noise_m=0.005, seed=3,
                                         noise_seed=4000 + draw, shared_noise_m=sigma_c, shared_tilt_rad=sigma_t)
            T_est = solve(problem, T_true, tight).T_world_scan
            e = tangent_error(T_est, T_true)[1:]
            values = []

            def spy(*args, values=values):
                values.append(estimate(*args))
                return values[-1]

            def without(*args):
                noise = estimate(*args)
                return dataclasses.replace(noise, shared_m2=0.0 * noise.shared_m2, tilt_rad2=0.0 * noise.tilt_rad2)

            try:
                covariance.correlated_noise_variances = spy
                with_shared.append(nees(e, pose_covariance(problem, T_est).covariance[1:]))
                covariance.correlated_noise_variances = without
                independent.append(nees(e, pose_covariance(problem, T_est).covariance[1:]))
            finally:
                covariance.correlated_noise_variances = estimate
            shared.append(float(values[0].shared_m2.mean()))
            tilt.append(float(values[0].tilt_rad2.mean()))
        rows.append([f"{sigma_c * 1e3:g}", f"{sigma_t * 1e3:.3g}", draws,
                     f"{np.mean(shared) * 1e6:.3g} / {sigma_c**2 * 1e6:.3g}",
                     f"{np.mean(tilt) * 1e6:.3g} / {sigma_t**2 * 1e6:.3g}",
                     np.mean(with_shared) / 6, np.mean(independent) / 6])
    return rows


def timing_problem(shared_planes: int):
    """The synthetic 1,000-scan problem of bench/solver.py (5,000 planes, each seen by a window of
    40 scans) and its true poses; with `shared_planes` > 0 also that many planes seen by every scan
    (a ground or floor: the pair form of H is then dense). Range clusters: the points' clusters over
    a range of 10 m."""
    import dataclasses

    from pa_cli.core.problem import make_problem
    from pa_testing.synthetic_problems import make_scene

    problem, T_gt = make_scene(1000, 5000, 40, points_per_observation=10, noise_m=0.01, seed=0)
    if shared_planes:
        shared, T_same = make_scene(1000, shared_planes, 1000, points_per_observation=10, noise_m=0.01, seed=0)
        assert np.array_equal(T_same, T_gt)  # the same seed draws the same trajectory first
        problem = make_problem(np.concatenate([problem.plane_index, shared.plane_index + problem.n_planes]),
                               np.concatenate([problem.scan_index, shared.scan_index]),
                               np.concatenate([problem.clusters, shared.clusters]), n_scans=1000, T_world_scan=T_gt)
    return dataclasses.replace(problem, range_clusters=problem.clusters / 10.0**2), T_gt


def timing(shared_planes: int = 0, repeats: int = 5, saved: tuple[str, str] | None = None) -> list[list]:
    """Median wall and process CPU times on `timing_problem(shared_planes)` (or on a saved problem
    `saved` = (PROBLEM.npz, POSES) from `pa refine --save-problem`, solved from those poses, without
    the refinement's odometry factors), measured in turn in one process (the machine's load
    changes): one accepted Newton iteration (linearise, damped solve, cost of the new poses), the
    covariance as `pa refine` and `pa adjust --covariance` run it (with the solver's model,
    `SolveResult.model`, whose last linearisation is at the solution; range, per-observation and
    given sigma), the range model without the solver's model, the selected inversion of H alone
    (its pair form: only on the synthetic problem without shared planes), and SuperLU solves of
    every column of H^-1 (extrapolated from 300 columns; the same); the 1-minute load average
    before and after."""
    import os

    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    from pa_cli.adjust import solve
    from pa_cli.adjust.covariance import pose_covariance
    from pa_cli.adjust.selected_inverse import analyse, diagonal_blocks_of_inverse
    from pa_cli.config import SolverConfig
    from pa_cli.core.geometry import retract_left

    if saved is None:
        problem, T_gt = timing_problem(shared_planes)
    else:
        from pa_cli.io.problem import load_problem
        from pa_cli.io.trajectory import read_trajectory

        problem, T_gt = load_problem(saved[0]), read_trajectory(saved[1]).T_world_scan
        shared_planes = -1  # no pair-form-only cases
    result = solve(problem, T_gt, SolverConfig())
    T, model = result.T_world_scan, result.model

    def newton_iteration() -> None:
        lin = model.linearize(T)  # at the solution, as the solver's last linearisation
        step, _ = lin.solve(1e-4)
        model.cost(retract_left(T, step))

    def inversion() -> None:
        diagonal_blocks_of_inverse(H, analyse(H))

    cases = {"Newton iteration": newton_iteration,
             "covariance, range noise (pa refine's default)": lambda: pose_covariance(problem, T, model=model),
             "covariance, per-observation noise": lambda: pose_covariance(problem, T, model=model,
                                                                          noise_model="observation"),
             "covariance, given sigma": lambda: pose_covariance(problem, T, model=model, point_sigma_m=0.01),
             "covariance, range noise, without the solver's model": lambda: pose_covariance(problem, T)}
    if not shared_planes:
        H = model.linearize(T).H.pose_hessian()
        cases["selected inversion of H (analyse + numeric)"] = inversion
    wall: dict[str, list[float]] = {name: [] for name in cases}
    cpu: dict[str, list[float]] = {name: [] for name in cases}
    for run in cases.values():  # compile and warm up
        run()
    load_before = os.getloadavg()[0]
    for _ in range(repeats):
        for name, run in cases.items():
            t0, c0 = time.perf_counter(), time.process_time()
            run()
            wall[name].append(time.perf_counter() - t0)
            cpu[name].append(time.process_time() - c0)
    load_after = os.getloadavg()[0]
    wall_it, cpu_it = float(np.median(wall["Newton iteration"])), float(np.median(cpu["Newton iteration"]))
    rows = [[name, float(np.median(wall[name])), float(np.median(wall[name])) / wall_it,
             float(np.median(cpu[name])), float(np.median(cpu[name])) / cpu_it] for name in cases]
    if not shared_planes:
        t0 = time.perf_counter()
        lu = splu(H, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        lu.solve(sp.eye(H.shape[0], 300, format="csc").toarray())
        superlu_s = (time.perf_counter() - t0) * H.shape[0] / 300
        rows.append(["SuperLU solves of all columns (extrapolated)", superlu_s, superlu_s / wall_it, "", ""])
    rows.append([f"load average (1 min) before / after: {load_before:.1f} / {load_after:.1f}", "", "", "", ""])
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--draws", type=int, default=50)
    ap.add_argument("--scans", type=int, default=60)
    ap.add_argument("--skip-timing", action="store_true")
    ap.add_argument("--timing-only", action="store_true")
    ap.add_argument("--realistic", action="store_true", help="only the correlated-noise tables (4.)")
    ap.add_argument("--problem", nargs=2, metavar=("PROBLEM.npz", "POSES"),
                    help="time a saved problem (pa refine --save-problem) from these poses instead")
    ap.add_argument("--pipeline-hall", type=int, nargs="+", metavar="SEED", help="only the table of 5., these seeds")
    ap.add_argument("--keep", type=Path, default=None, help="5.: keep the data and outputs in this folder")
    args = ap.parse_args()
    if args.pipeline_hall:
        with tempfile.TemporaryDirectory() as tmp:
            pipeline_hall(args.pipeline_hall, args.keep or Path(tmp))
        return
    if args.problem:
        markdown_table(f"Time on {args.problem[0]} from {args.problem[1]} (acceptance: covariance <= one Newton "
                       "iteration)", ["what", "median wall s", "x Newton iteration (wall)", "median CPU s",
                                      "x Newton iteration (CPU)"], timing(saved=tuple(args.problem)))
        return
    if args.realistic:
        realistic_tables(args.draws, args.scans)
        return
    if not args.timing_only:
        monte_carlo_tables(args.draws, args.scans)
    if not args.skip_timing:
        header = ["what", "median wall s", "x Newton iteration (wall)", "median CPU s", "x Newton iteration (CPU)"]
        markdown_table("Time on the synthetic 1000-scan problem of bench/solver.py (5000 planes, window 40; "
                       "acceptance: covariance <= one Newton iteration)", header, timing())
        markdown_table(f"The same problem with {SHARED_PLANES} more planes seen by all 1000 scans (a ground: "
                       "the pair form of H is dense, the covariance takes them as feature nodes)", header,
                       timing(SHARED_PLANES))


def realistic_tables(draws: int, scans: int) -> None:
    """The tables of 4.: correlated noise on the synthetic scene, the Monte Carlo on realistic noise."""
    markdown_table("Errors shared by an observation's points (synthetic, 5 mm white over 30 points; acceptance: "
                   "NEES/6 in [0.5, 2])", ["shared offset sigma mm", "shared tilt sigma mrad", "draws",
                                           "estimated / true offset variance mm^2",
                                           "estimated / true tilt variance mrad^2", "NEES / 6",
                                           "NEES / 6, points independent"], correlated(max(draws, 20)))
    rows = []
    for name, (scene, options) in REALISTIC_SCENES.items():
        for row in monte_carlo(scene, draws, scans, options, REALISTIC_FIRST_SEED):
            rows.append([name, *row[1:]])
    markdown_table("Monte Carlo on realistic noise (acceptance: NEES/6 in [0.5, 2])",
                   ["scene", "noise model", "draws", "scans", "planes", "mean NEES", "NEES / 6",
                    "pred/emp, median scan (wx wy wz px py pz)", "pred/emp, median over scans",
                    "median scan 1-sigma pos mm / rot mdeg", "covariance s"], rows)


def pipeline_hall(seeds: list[int], work: Path) -> None:
    """The table of 5.: `pa refine` on the noisy 101-scan hall from the perturbed truth, its covariance
    against the truth."""
    from pa_cli.adjust.covariance import nees, tangent_error
    from pa_cli.core.geometry import rigid_inverse
    from pa_cli.io.trajectory import read_trajectory
    from pa_cli.refine.consistency import CHI2_3DOF_3SIGMA

    rows, per_draw = [], []
    for seed in seeds:
        data, out = work / f"hall{seed}", work / f"hall{seed}_refined.ply"
        if not data.exists():
            run_pa("simulate", "hall", data, "--path", "sharp", "--scans", 101, "--point-noise-m", 0.02, "--seed", seed)
            run_pa("perturb", data / "gt_poses_kitti.txt", "--rot-deg", 1, "--trans-m", 0.1, "--seed", seed,
                   "--out", data / "start_kitti.txt")
        run_pa("refine", data / "scans", "--poses", data / "start_kitti.txt", "--gt", data / "gt_poses_kitti.txt",
               "--config", "indoor", "--out", out, "--force", "-q")
        report = json.loads(out.with_name(f"{out.stem}_report.json").read_text())
        cov = np.load(out.with_name(f"{out.stem}_covariance.npz"))
        T, gauge = cov["T_world_scan"], int(cov["gauge_pose"])
        T_true = read_trajectory(data / "gt_poses_kitti.txt").T_world_scan
        T_true = T[gauge] @ rigid_inverse(T_true[gauge:gauge + 1])[0] @ T_true
        free = np.arange(len(T)) != gauge
        pose_nees = nees(tangent_error(T, T_true)[free], cov["covariance"][free])
        d_m = (T[:, :3, 3] - T_true[:, :3, 3])[free]
        position_nees = np.einsum("ni,ni->n", d_m, np.linalg.solve(cov["position_covariance_m2"][free],
                                                                    d_m[..., None])[..., 0])
        per_draw.append(pose_nees.mean() / 6)
        ate_m = report["gt"]["initial"]["ate_rmse_m"], report["gt"]["refined"]["ate_rmse_m"]
        rows.append([seed, f"{ate_m[0]:.4f} -> {ate_m[1]:.5f}",
                     f"{per_draw[-1]:.2f}", f"{position_nees.mean() / 3:.2f}",
                     f"{np.mean(position_nees <= CHI2_3DOF_3SIGMA):.0%}",
                     f"{1000 * np.median(np.linalg.norm(d_m, axis=1)):.2f}", report["quality"]["verdict"]])
    rows.append(["mean", "", f"{np.mean(per_draw):.2f}", "", "", "", ""])
    markdown_table("pa refine on the 101-scan hall, 2 cm point noise, from the truth perturbed by 1 deg / 0.1 m "
                   "(acceptance: NEES/6 in [0.5, 2])",
                   ["seed", "ATE start -> refined m", "NEES / 6", "position NEES / 3", "positions within 3 sigma",
                    "median position error mm", "verdict"], rows)


def monte_carlo_tables(draws: int, scans: int) -> None:
    """The Monte Carlo table of both scenes and the factor-2 table."""
    rows = [row for scene in ("office", "street") for row in monte_carlo(scene, draws, scans)]
    markdown_table("Monte Carlo: predicted vs empirical pose covariance (acceptance: NEES/6 in [0.7, 1.4], "
                   "per-axis ratio in [0.7, 1.3] on the median scan)",
                   ["scene", "noise model", "draws", "scans", "planes", "mean NEES", "NEES / 6",
                    "pred/emp, median scan (wx wy wz px py pz)", "pred/emp, median over scans",
                    "median scan 1-sigma pos mm / rot mdeg", "covariance s"], rows)
    markdown_table("Factor 2: i.i.d. point-to-plane noise (NEES should be 6)", ["covariance", "draws", "mean NEES"],
                   factor_of_two(draws))


if __name__ == "__main__":
    main()
