"""The two-start bench's pure helpers (bench/robust.py `starts`), against brute force."""

import numpy as np
from scipy.spatial.transform import Rotation

from bench.robust import CHI2_3DOF_3SIGMA, position_mahalanobis_sq, share_within, verdict_direction


def _poses(rng: np.random.Generator, n: int) -> np.ndarray:
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=rng).as_matrix()
    T[:, :3, 3] = rng.normal(0.0, 20.0, (n, 3))
    return T


def _covariances(rng: np.random.Generator, n: int) -> np.ndarray:
    A = rng.normal(0.0, 0.01, (n, 3, 3))
    return A @ A.transpose(0, 2, 1) + 1e-6 * np.eye(3)


def test_mahalanobis_matches_a_loop_with_explicit_inverses():
    rng = np.random.default_rng(3)
    T_a, T_b = _poses(rng, 8), _poses(rng, 8)
    cov_a, cov_b = _covariances(rng, 8), _covariances(rng, 8)
    cov_a[2] = cov_b[2] = 0.0  # the gauge scan
    G = _poses(rng, 1)[0]
    got = position_mahalanobis_sq(T_a, cov_a, T_b, cov_b, G, gauge=2)
    for k in range(8):
        if k == 2:
            assert np.isnan(got[k])
            continue
        d = T_b[k, :3, 3] - (G @ T_a[k])[:3, 3]
        expected = d @ np.linalg.inv(cov_b[k] + G[:3, :3] @ cov_a[k] @ G[:3, :3].T) @ d
        assert np.isclose(got[k], expected, rtol=1e-9)


def test_a_run_in_another_world_frame_put_on_at_the_gauge_gives_the_same_distances():
    """Run a's world frame is arbitrary (KISS-ICP's first scan, the truth's): moving it and its
    covariances by a rigid H and putting it back on b at the gauge leaves every distance unchanged."""
    rng = np.random.default_rng(4)
    T_a, cov_a, cov_b = _poses(rng, 6), _covariances(rng, 6), _covariances(rng, 6)
    T_b = T_a.copy()
    T_b[:, :3, 3] += rng.normal(0.0, 0.01, (6, 3))
    T_b[0] = T_a[0]
    H = _poses(rng, 1)[0]
    direct = position_mahalanobis_sq(T_a, cov_a, T_b, cov_b, np.eye(4), gauge=0)
    T_moved = H @ T_a
    cov_moved = H[:3, :3] @ cov_a @ H[:3, :3].T
    G = T_b[0] @ np.linalg.inv(T_moved[0])
    moved = position_mahalanobis_sq(T_moved, cov_moved, T_b, cov_b, G, gauge=0)
    np.testing.assert_allclose(moved[1:], direct[1:], rtol=1e-8)


def test_share_within_counts_the_threshold_and_skips_nan():
    assert share_within(np.array([np.nan, 1.0, CHI2_3DOF_3SIGMA, 20.0, 3.0])) == 0.75


def test_verdict_direction_is_improved_exactly_when_the_measure_fell():
    assert verdict_direction("improved", 1.0, 0.5)
    assert not verdict_direction("improved", 1.0, 1.5)
    assert not verdict_direction("uncertain", 1.0, 0.5)
    assert verdict_direction("degraded", 1.0, 1.5)
