"""The augmented damped system: same step as the dense pose Hessian, inertia detected."""

from __future__ import annotations

import numpy as np
import pytest

from pa_cli.adjust.linalg import DIAG_FLOOR, HessianPattern, damped_solve
from pa_cli.adjust.newton import NewtonModel
from pa_cli.core.problem import make_problem
from pa_testing.synthetic_problems import make_scene, perturb
from tests.unit.adjust.test_adjust_newton import _PairTerm, dense_hessian, random_problem


def mixed_problem():
    """Planes seen by 2 to 7 of 7 scans (some pair blocks, some auxiliary unknowns), random poses."""
    problem, T, _ = random_problem(11, n_scans=7, n_planes=9)
    rng = np.random.default_rng(3)
    seen_by = {i: rng.choice(7, size=2 + i % 6, replace=False) for i in range(9)}
    keep = np.array([s in seen_by[p] for p, s in zip(problem.plane_index, problem.scan_index, strict=True)])
    sub = make_problem(problem.plane_index[keep], problem.scan_index[keep], problem.clusters[keep], n_scans=7)
    assert set(np.bincount(sub.plane_index)) == {2, 3, 4, 5, 6, 7}
    return sub, T


def model_with(problem, pair_max_scans, fixed=1, terms=(), blocks=False):
    model = NewtonModel(problem, fixed_pose=fixed, terms=terms)
    extra = np.concatenate([t.pose_pairs() for t in terms]) if terms else None
    model.pattern = HessianPattern(problem.plane_index, problem.scan_index, problem.n_scans, fixed,
                                   model.feature_cost.starts, extra, pair_max_scans=pair_max_scans, blocks=blocks)
    return model


def dense_damped(H, mu):
    d = np.abs(np.diag(H))
    return H + mu * np.diag(np.maximum(d, DIAG_FLOOR * d.max()))


@pytest.mark.parametrize("blocks", [False, True])
@pytest.mark.parametrize("pair_max_scans", [0, 3, 100])
def test_augmented_step_equals_dense_pair_step(pair_max_scans, blocks):
    problem, T = mixed_problem()
    term = _PairTerm(7, [(0, 1), (5, 3)], seed=2)
    term.diag = np.einsum("nij,nkj->nik", term.diag, term.diag)  # PSD diagonal blocks
    fixed = 1
    _, g, H = dense_hessian(problem, T, eigen_gap_tolerance=1e-6)
    term.add_to(H)
    keep = np.array([a for a in range(42) if a // 6 != fixed])
    H, g = H[np.ix_(keep, keep)], g[keep]
    model = model_with(problem, pair_max_scans, fixed, [term], blocks)
    assert model.pattern.n_aux_features == int(np.sum(np.bincount(problem.plane_index) > pair_max_scans))
    lin = model.linearize(T)
    np.testing.assert_allclose(lin.H.h_diag, np.diag(H), rtol=1e-12, atol=1e-12 * np.abs(H).max())
    mu = 10.0
    assert np.linalg.eigvalsh(dense_damped(H, mu)).min() > 0
    x = damped_solve(lin.H, lin.g, mu)
    x_ref = np.linalg.solve(dense_damped(H, mu), -g)
    assert np.abs(x - x_ref).max() <= 1e-9 * np.abs(x_ref).max()


@pytest.mark.parametrize("blocks", [False, True])
@pytest.mark.parametrize("pair_max_scans", [0, 100])
def test_non_positive_definite_damped_system_is_refused(pair_max_scans, blocks):
    """damped_solve returns None exactly when H + mu D has a non-positive eigenvalue."""
    problem, T_true = mixed_problem()
    T = perturb(T_true, 0.3, 1.0, seed=4)  # far from the optimum: H indefinite
    _, _, H = dense_hessian(problem, T, eigen_gap_tolerance=1e-6)
    keep = np.array([a for a in range(42) if a // 6 != 1])
    H = H[np.ix_(keep, keep)]
    lin = model_with(problem, pair_max_scans, blocks=blocks).linearize(T)
    outcomes = []
    for mu in 10.0 ** np.arange(-6, 4):
        positive = np.linalg.eigvalsh(dense_damped(H, mu)).min() > 0
        solved = damped_solve(lin.H, lin.g, mu) is not None
        assert solved == positive, mu
        outcomes.append(positive)
    assert any(outcomes) and not all(outcomes)  # both cases occur: random thick planes, indefinite H


def test_blocks_of_planes_give_the_single_pass_pieces(monkeypatch):
    """The plane cost and the centred Hessian pieces computed in blocks of a few planes equal, to the
    bit, those of one pass over all observations; the blocks cover every plane once, in order."""
    from pa_cli.adjust import newton

    problem, T_gt = make_scene(40, 60, 6, points_per_observation=8, noise_m=0.01, seed=5)
    T = perturb(T_gt, 0.02, 0.2, seed=6)
    T[:, :3, 3] += 3000.0  # far from the origin: the centring matters
    starts = np.searchsorted(problem.plane_index, np.arange(problem.n_planes + 1))
    chunks = newton.plane_chunks(starts, 25)
    assert len(chunks) > 5
    assert [c[0] for c in chunks] == [0] + [c[1] for c in chunks[:-1]] and chunks[-1][1] == problem.n_planes
    assert newton.plane_chunks(starts, 10**9) == [(0, problem.n_planes)]

    def linearization(chunk_observations):
        monkeypatch.setattr(newton, "CHUNK_OBSERVATIONS", chunk_observations)
        model = NewtonModel(problem, fixed_pose=0, centred=True)
        (_, cost), = model.feature_cost.parts
        cost.chunks = newton.plane_chunks(cost.starts, chunk_observations)
        return model.cost(T), model.linearize(T)

    cost_one, one = linearization(10**9)
    cost_blocks, blocks = linearization(25)
    assert cost_blocks == cost_one
    assert blocks.cost == one.cost and np.array_equal(blocks.g, one.g)
    for name in ("A", "A_gn", "Bt", "Bt_gn", "gradient"):
        assert np.array_equal(getattr(blocks._der, name), getattr(one._der, name)), name
    assert np.array_equal(blocks.H.data, one.H.data)


def test_reused_arrays_are_handed_out_only_when_nobody_holds_them():
    from pa_cli.adjust.newton import ReusedArrays

    pool = ReusedArrays(max_sets=2)
    shapes = [(5, 6, 6), (5, 3, 6)]
    first = pool.get(shapes)
    second = pool.get(shapes)
    assert not any(a is b for a, b in zip(first, second, strict=True))  # the first set is still held
    first_ids = [id(a) for a in first]
    del first
    again = pool.get(shapes)
    assert [id(a) for a in again] == first_ids  # released: the same arrays again
    view = again[1][2:]
    del again
    third = pool.get(shapes)
    assert view.base is not None and not any(a is view.base for a in third)  # a view still holds its array
    assert [a.shape for a in pool.get([(2, 6, 6)])] == [(2, 6, 6)]  # other shapes: a new set


def test_pair_form_rule_counts_distinct_scan_pairs_as_brute_force():
    """`pair_form_is_smaller` against the distinct scan pairs sharing a feature counted one by one,
    on feature-scan incidences decided by each of its bounds and by the exact count."""
    from pa_cli.adjust.linalg import pair_form_is_smaller

    rng = np.random.default_rng(12)
    decided = set()
    for trial in range(300):
        n_scans, n_features = int(rng.integers(2, 30)), int(rng.integers(1, 25))
        width = int(rng.integers(2, n_scans + 1))
        observations = set()
        for i in range(n_features):  # each feature seen by a window of scans, some by all
            k = n_scans if rng.random() < 0.1 else int(rng.integers(2, width + 1))
            first = int(rng.integers(0, n_scans - k + 1))
            observations |= {(i, j) for j in range(first, first + k)}
        plane_index, scan_index = np.array(sorted(observations)).T
        pairs = {(a, b) for i in range(n_features) for a in scan_index[plane_index == i]
                 for b in scan_index[plane_index == i] if a < b}
        rank = int(rng.choice([3, 4]))
        expected = 36 * len(pairs) <= 6 * rank * len(plane_index)
        assert pair_form_is_smaller(plane_index, scan_index, n_scans, n_features, rank) == expected, trial
        k = np.bincount(plane_index)
        largest, total = (k * (k - 1) // 2).max(), (k * (k - 1) // 2).sum()
        decided.add("largest" if 36 * largest > 6 * rank * len(plane_index) else
                    "total" if 36 * min(total, n_scans * (n_scans - 1) // 2) <= 6 * rank * len(plane_index) else
                    "counted")
    assert decided == {"largest", "total", "counted"}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_block_ldl_solves_as_dense_and_refuses_what_is_not_positive_definite(seed):
    """`BlockLDL` on a random sparse symmetric matrix whose unknowns form blocks of 6 and of 1-4 (the rest
    of such a block padded): its solve equals numpy's dense one, refactorisation of new values on the
    same pattern included, and a matrix with a negative eigenvalue is refused (False) exactly when the
    dense eigenvalues say so."""
    import scipy.sparse as sp

    from pa_cli.adjust.selected_inverse import BlockLDL

    rng = np.random.default_rng(seed)
    sizes = [6] * 9 + list(rng.integers(1, 5, size=7))
    node = np.repeat(np.arange(len(sizes)), sizes)
    offset = np.concatenate([np.arange(k) for k in sizes])
    n = len(node)
    coupled = rng.random((len(sizes), len(sizes))) < 0.25  # a sparse block pattern
    mask = coupled[node][:, node] | np.equal.outer(node, node)
    mask = np.triu(mask | mask.T)
    factor = None
    for shift in (2.0, 0.1, None):  # positive definite, barely, and with a negative eigenvalue
        A = rng.normal(size=(n, n)) * (mask | mask.T)
        A = (A + A.T) / 2  # symmetric, on the pattern
        eig = np.linalg.eigvalsh(A)
        M = A + ((eig.max() + eig.min()) / -2 if shift is None else shift - eig.min()) * np.eye(n)
        upper = sp.csc_matrix(np.triu(M) * mask)
        upper.sort_indices()
        if factor is None:
            factor = BlockLDL(upper.indptr, upper.indices, node, offset, len(sizes))
        is_pd = np.linalg.eigvalsh(M).min() > 0
        assert is_pd == (shift is not None)
        assert factor.factorise(upper.data) == is_pd
        if is_pd:
            rhs = rng.normal(size=n)
            x = factor.solve(rhs)
            x_ref = np.linalg.solve(M, rhs)
            assert np.abs(x - x_ref).max() <= 1e-10 * np.abs(x_ref).max()


def test_newton_solve_with_the_block_factorisation_equals_the_qdldl_one(monkeypatch):
    """The whole damped Newton loop (exact Hessian, Gauss-Newton fallback where it is indefinite) with every
    system factorised in blocks reaches the optimum of the QDLDL one in the same iterations (default
    tolerances), and the same poses when both are iterated to machine precision: within 1e-8, as far as the
    optimum fixes them (QDLDL alone, from starts 1e-9 rad / m apart, ends 2e-9 to 6e-9 apart here)."""
    from pa_cli.adjust import linalg, solve
    from pa_cli.config import SolverConfig

    problem, T_gt = make_scene(40, 60, 8, points_per_observation=10, noise_m=0.01, seed=7)
    T0 = perturb(T_gt, np.deg2rad(2.0), 0.2, seed=8)
    tight = SolverConfig(cost_tolerance=0.0, gradient_tolerance=0.0, step_tolerance=1e-13, max_iterations=30)
    results = {}
    for name, threshold in (("qdldl", 10**9), ("blocks", 0)):
        monkeypatch.setattr(linalg, "BLOCK_MIN_UNKNOWNS", threshold)
        results[name] = solve(problem, T0, SolverConfig()), solve(problem, T0, tight)
    (a, a_tight), (b, b_tight) = results["qdldl"], results["blocks"]
    assert a.report["converged"] and b.report["converged"]
    assert a.report["iterations"] == b.report["iterations"]
    assert a.report["cost_final_m2"] < 0.01 * a.report["cost_initial_m2"]
    assert abs(a.report["cost_final_m2"] - b.report["cost_final_m2"]) <= 1e-12 * a.report["cost_final_m2"]
    assert np.abs(a_tight.T_world_scan - b_tight.T_world_scan).max() <= 1e-8
