"""S-matrices by the quadratic residue construction (thesis, App. "Multiplexed acquisition" 3.1)."""

from __future__ import annotations

import numpy as np
import pytest

from btfcore.acquisition.hadamard import is_s_matrix_order, multiplexing_patterns, s_matrix, smallest_s_matrix_order

VALID = [3, 7, 11, 19, 23, 31, 43, 47, 59, 67, 71, 79, 83, 103, 107, 127, 131, 139, 151, 163, 167, 179, 191, 199]


def test_valid_orders_are_the_primes_3_mod_4():
    # reference list typed in from the sequence of primes p = 3 (mod 4) (OEIS A002145)
    assert [n for n in range(200) if is_s_matrix_order(n)] == VALID


@pytest.mark.parametrize("n", [3, 7, 11, 19, 23, 43, 47, 199])
def test_s_matrix_identities(n):
    S = s_matrix(n)
    assert S.shape == (n, n) and S.dtype == np.uint8
    assert set(np.unique(S)) == {0, 1}
    Si = S.astype(np.int64)
    # (n + 1) / 2 lights per pattern and per light
    np.testing.assert_array_equal(Si.sum(axis=1), (n + 1) // 2)
    np.testing.assert_array_equal(Si.sum(axis=0), (n + 1) // 2)
    # S^T S = (n + 1)/4 (I + J), exactly, in integers
    np.testing.assert_array_equal(Si.T @ Si, (n + 1) // 4 * (np.eye(n, dtype=np.int64) + 1))
    # closed-form inverse S^-1 = 2/(n+1) (2 S^T - J)
    inv = 2.0 / (n + 1) * (2 * Si.T - 1)
    np.testing.assert_allclose(inv @ Si, np.eye(n), atol=1e-12)
    # rows are cyclic left shifts of row 0
    for i in (1, n // 2, n - 1):
        np.testing.assert_array_equal(S[i], np.roll(S[0], -i))


def test_first_row_holds_the_quadratic_residues():
    # order 7: squares of 0..3 mod 7 are {0, 1, 4, 2}
    np.testing.assert_array_equal(s_matrix(7)[0], [1, 1, 1, 0, 1, 0, 0])
    np.testing.assert_array_equal(s_matrix(3), [[1, 1, 0], [1, 0, 1], [0, 1, 1]])


def test_smallest_order():
    assert smallest_s_matrix_order(198) == 199
    assert smallest_s_matrix_order(199) == 199
    assert smallest_s_matrix_order(16) == 19
    assert smallest_s_matrix_order(44) == 47
    assert smallest_s_matrix_order(1) == 3
    with pytest.raises(ValueError):
        smallest_s_matrix_order(0)


@pytest.mark.parametrize("n, near", [(8, "7 or 11"), (13, "11 or 19"), (15, "11 or 19"), (49, "47 or 59"), (2, "3")])
def test_invalid_orders_name_the_nearest_valid_ones(n, near):
    with pytest.raises(ValueError, match=f"nearest valid orders: {near}"):
        s_matrix(n)


def test_non_integer_order_is_refused():
    with pytest.raises(ValueError):
        s_matrix(7.0)


@pytest.mark.parametrize("n_leds", [16, 198, 151, 2])
def test_multiplexing_patterns_truncate_columns_keep_rows(n_leds):
    P = multiplexing_patterns(n_leds)
    n = smallest_s_matrix_order(n_leds)
    assert P.shape == (n, n_leds) and P.dtype == np.uint8
    np.testing.assert_array_equal(P, s_matrix(n)[:, :n_leds])
    assert (P.sum(axis=1) >= 1).all()
    # full column rank: single-LED signals are recoverable in the least-squares sense
    assert np.linalg.matrix_rank(P.astype(np.float64)) == n_leds
    x = np.random.default_rng(0).uniform(0.1, 2.0, n_leds)
    x_hat = np.linalg.lstsq(P.astype(np.float64), P @ x, rcond=None)[0]
    np.testing.assert_allclose(x_hat, x, rtol=1e-9)


def test_single_led_cannot_be_multiplexed():
    with pytest.raises(ValueError, match="at least 2 lights"):
        multiplexing_patterns(1)
