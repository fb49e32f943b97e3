"""The vector 6x6 block product `nn6` against numpy, on the array layouts the factorisations pass."""

import numba
import numpy as np
import pytest

from pa_cli.adjust._block6 import nn6


@numba.njit
def _product(C, A, B, alpha):
    nn6(C, A, B, alpha)


@numba.njit
def _product_transposed(C, A, B, alpha):
    nn6(C, A.T, B, alpha)


@numba.njit
def _product_of_blocks(blocks, c, a, b, alpha):
    nn6(blocks[c], blocks[a].T, blocks[b], alpha)


@pytest.mark.parametrize("alpha", [1.0, -1.0, 0.37])
def test_product_matches_numpy(alpha):
    rng = np.random.default_rng(7)
    A, B, C = (rng.standard_normal((6, 6)) for _ in range(3))
    expected = C + alpha * A @ B
    _product(C, A, B, alpha)
    np.testing.assert_allclose(C, expected, rtol=0, atol=1e-14)


def test_transposed_operand_matches_numpy():
    rng = np.random.default_rng(8)
    A, B, C = (rng.standard_normal((6, 6)) for _ in range(3))
    expected = C - A.T @ B
    _product_transposed(C, A, B, -1.0)
    np.testing.assert_allclose(C, expected, rtol=0, atol=1e-14)


def test_strided_first_operand_matches_numpy():
    rng = np.random.default_rng(11)
    big, B, C = rng.standard_normal((12, 18)), rng.standard_normal((6, 6)), rng.standard_normal((6, 6))
    A = big[::2, ::3]  # neither C nor F contiguous: read through its strides
    expected = C + 0.5 * A @ B
    _product(C, A, B, 0.5)
    np.testing.assert_allclose(C, expected, rtol=0, atol=1e-14)


def test_blocks_of_a_stack_change_only_the_target():
    rng = np.random.default_rng(9)
    blocks = rng.standard_normal((5, 6, 6))
    before = blocks.copy()
    _product_of_blocks(blocks, 3, 1, 4, 2.5)
    np.testing.assert_allclose(blocks[3], before[3] + 2.5 * before[1].T @ before[4], rtol=0, atol=1e-13)
    np.testing.assert_array_equal(np.delete(blocks, 3, axis=0), np.delete(before, 3, axis=0))


def test_non_contiguous_target_is_refused_at_compile_time():
    rng = np.random.default_rng(10)
    A, B = rng.standard_normal((6, 6)), rng.standard_normal((6, 6))
    C = np.zeros((6, 12))[:, ::2]  # strided: the vector stores would be wrong
    with pytest.raises(numba.TypingError):
        _product(C, A, B, 1.0)
