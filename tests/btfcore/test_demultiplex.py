"""Demultiplexing of S-matrix captures and its noise (thesis §3.1; App. "Multiplexed acquisition" 3.3)."""

from __future__ import annotations

import numpy as np
import pytest

from btfcore.capture.demultiplex import (
    demultiplex,
    demultiplex_operator,
    demultiplexed_noise_std,
    noise_gain,
    s_matrix_inverse,
    snr_gain,
)
from btfcore.acquisition.hadamard import is_s_matrix_order, multiplexing_patterns, s_matrix

ORDERS = [n for n in range(200) if is_s_matrix_order(n)]


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


# --------------------------------------------------------------------------- S-matrix bars


@pytest.mark.parametrize("n", ORDERS)
def test_s_matrix_identities_and_closed_form_inverse(n):
    assert len(ORDERS) == 24 and ORDERS[-1] == 199
    S = s_matrix(n).astype(np.int64)
    I, J = np.eye(n, dtype=np.int64), np.ones((n, n), dtype=np.int64)
    # S S^T = ((n+1)/4)(I + J), exactly in integers (and S^T S, the Gram of the columns)
    np.testing.assert_array_equal(S @ S.T, (n + 1) // 4 * (I + J))
    np.testing.assert_array_equal(S.T @ S, (n + 1) // 4 * (I + J))
    # S^-1 = (2/(n+1))(2 S^T - J): exact in integers as (n+1) S^-1 S = 2 (2 S^T - J) S = (n+1) I ...
    np.testing.assert_array_equal((2 * S.T - J) @ S, (n + 1) // 2 * I)
    # ... and in floats, from the module
    Si = s_matrix_inverse(S)
    np.testing.assert_allclose(Si, 2.0 / (n + 1) * (2 * S.T - J), rtol=0, atol=0)
    np.testing.assert_allclose(Si @ S, np.eye(n), atol=1e-12)
    np.testing.assert_allclose(S @ Si, np.eye(n), atol=1e-12)
    # the operator of the full S-matrix is the closed form, and equals the pseudo-inverse
    np.testing.assert_array_equal(demultiplex_operator(S), Si)
    np.testing.assert_allclose(demultiplex_operator(S, method="pinv"), Si, atol=1e-12)


@pytest.mark.parametrize("n", ORDERS)
def test_snr_gain_of_s_matrices_is_harwit_sloane(n):
    # tr[(S^T S)^-1] = 4 n^2 / (n+1)^2  =>  sqrt(n_i / tr) = (n+1) / (2 sqrt n) ~ sqrt(n)/2 (VMV 3.3)
    assert snr_gain(s_matrix(n)) == pytest.approx((n + 1) / (2 * np.sqrt(n)), rel=1e-12)


def test_snr_gain_reference_designs():
    # single-light acquisition: no gain
    assert snr_gain(np.eye(16)) == pytest.approx(1.0, rel=1e-12)
    # thesis §3.1: "all light sources but a single one" (M := J - I) gives "a ratio very close to 1"
    n = 16
    M = np.ones((n, n)) - np.eye(n)
    tr = n / (n - 1) + n * (n - 2) ** 2 / (n - 1) ** 2      # entries of M^-1 = J/(n-1) - I, squared and summed
    assert snr_gain(M) == pytest.approx(np.sqrt(n / tr), rel=1e-12)
    assert 1.0 < snr_gain(M) < 1.05
    # thesis §3.1: the gain tends to sqrt(n)/2 for large n
    assert snr_gain(s_matrix(199)) / (np.sqrt(199) / 2) == pytest.approx(1.0, abs=0.01)


@pytest.mark.parametrize("dtype,tol", [(np.float64, 1e-12), (np.float32, 2e-5)])
@pytest.mark.parametrize("n_leds", [198, 150, 16, 5])
def test_truncated_s_matrix_demultiplexes_exactly(n_leds, dtype, tol):
    M = multiplexing_patterns(n_leds)                        # e.g. 199 x 198
    rng = np.random.default_rng(n_leds)
    truth = rng.uniform(0.0, 1.0, size=(n_leds, 6, 5, 3))   # (LEDs, rows, cols, RGB)
    measured = np.einsum("il,l...->i...", M.astype(np.float64), truth).astype(dtype)
    single = demultiplex(measured, M)
    assert single.shape == truth.shape and single.dtype == dtype
    np.testing.assert_allclose(single, truth, rtol=0, atol=tol * max(1.0, M.shape[0] / 8))
    # closed form of the truncated S-matrix == numerical pseudo-inverse
    np.testing.assert_allclose(demultiplex_operator(M), np.linalg.pinv(M.astype(np.float64)), atol=1e-12)
    np.testing.assert_allclose(demultiplex(measured, M, method="pinv"), single, rtol=0, atol=tol * 10)


def test_general_full_rank_patterns_and_integer_input():
    rng = np.random.default_rng(3)
    M = rng.integers(0, 2, size=(12, 9))
    while np.linalg.matrix_rank(M) < 9:
        M = rng.integers(0, 2, size=(12, 9))
    truth = rng.uniform(size=(9, 40))
    np.testing.assert_allclose(demultiplex(M @ truth, M.astype(bool)), truth, atol=1e-10)
    counts = rng.integers(0, 1000, size=(9, 7))
    out = demultiplex(M @ counts, M)
    assert out.dtype == np.float64
    np.testing.assert_allclose(out, counts, atol=1e-9)


def test_single_led_patterns_in_any_order_are_inverted_by_their_transpose():
    rng = np.random.default_rng(5)
    M = np.eye(9)[rng.permutation(9)]
    P = demultiplex_operator(M)
    np.testing.assert_array_equal(P, M.T)
    np.testing.assert_array_equal(P, demultiplex_operator(M, method="pinv").round(12))
    single = rng.uniform(0, 1, (9, 4, 3))
    np.testing.assert_allclose(demultiplex(M @ single.reshape(9, -1), M).reshape(single.shape), single,
                               rtol=1e-12)


def test_one_matrix_product_per_chunk_matches_per_pixel_lstsq():
    M = s_matrix(23)[:, :20]
    rng = np.random.default_rng(5)
    y = rng.normal(size=(23, 4, 3))
    ref = np.linalg.lstsq(M.astype(float), y.reshape(23, -1), rcond=None)[0].reshape(20, 4, 3)
    np.testing.assert_allclose(demultiplex(y, M), ref, atol=1e-12)


# --------------------------------------------------------------------------- noise: Monte Carlo vs formula


@pytest.mark.parametrize("n", [7, 31, 199])
def test_signal_independent_noise_gain_matches_formula(n):
    S = s_matrix(n)
    rng = np.random.default_rng([11, n])
    n_px = max(200, 60_000 // n)
    truth = rng.uniform(10.0, 100.0, size=(n, n_px))
    sigma = 2.0
    single = truth + rng.normal(0.0, sigma, size=truth.shape)
    multiplexed = S @ truth + rng.normal(0.0, sigma, size=truth.shape)
    demux = demultiplex(multiplexed, S)
    measured = _rms(single - truth) / _rms(demux - truth)
    assert measured == pytest.approx(snr_gain(S), rel=0.10)
    assert measured == pytest.approx(snr_gain(S), rel=0.03)       # in fact much closer
    # per-LED std prediction (the same for every LED of an S-matrix)
    np.testing.assert_allclose(demultiplexed_noise_std(S, read_noise=sigma),
                               sigma * 2 * np.sqrt(n) / (n + 1), rtol=1e-12)


def test_signal_independent_noise_gain_of_truncated_s_matrix():
    M = multiplexing_patterns(198)                            # 199 x 198, least squares
    rng = np.random.default_rng(17)
    truth = rng.uniform(10.0, 100.0, size=(198, 400))
    demux = demultiplex(M @ truth + rng.normal(size=(199, 400)), M)
    single_err = rng.normal(size=truth.shape)
    measured = _rms(single_err) / _rms(demux - truth)
    assert measured == pytest.approx(snr_gain(M), rel=0.10)
    assert snr_gain(M) == pytest.approx(snr_gain(s_matrix(199)), rel=0.01)


def _poisson_capture(rng, M, truth, read_noise):
    """A noisy capture: photons of the pattern's summed light (Poisson), then read noise."""
    mean = M.astype(np.float64) @ truth
    return rng.poisson(mean).astype(np.float64) + rng.normal(0.0, read_noise, size=mean.shape)


@pytest.mark.parametrize("n,read_noise,level", [(7, 5.0, 20.0), (31, 5.0, 20.0), (31, 3.0, 400.0),
                                                (199, 10.0, 5.0), (199, 2.0, 200.0)])
def test_photon_noise_gain_matches_signal_dependent_prediction(n, read_noise, level):
    S = s_matrix(n)
    rng = np.random.default_rng([23, n, int(level)])
    n_px = max(300, 80_000 // n)
    truth = level * rng.uniform(0.2, 1.8, size=(n, n_px))    # photo-electrons per LED and pixel
    single = _poisson_capture(rng, np.eye(n), truth, read_noise)
    demux = demultiplex(_poisson_capture(rng, S, truth, read_noise), S)
    measured = _rms(single - truth) / _rms(demux - truth)
    predicted = noise_gain(S, truth, read_noise=read_noise)
    assert measured == pytest.approx(predicted, rel=0.15)
    assert measured == pytest.approx(predicted, rel=0.05)        # in fact much closer
    # photon noise shrinks the advantage below the signal-independent formula
    assert predicted < snr_gain(S)
    # per-LED std: Monte Carlo over pixels vs the prediction, LED by LED
    std_pred = np.sqrt(np.mean(demultiplexed_noise_std(S, truth, read_noise=read_noise) ** 2, axis=1))
    std_meas = np.sqrt(np.mean((demux - truth) ** 2, axis=1))
    np.testing.assert_allclose(std_meas, std_pred, rtol=0.15)


@pytest.mark.parametrize("n", [7, 31, 199])
def test_photon_noise_closed_form_for_s_matrices(n):
    S = s_matrix(n)
    sigma = 4.0
    for x in (0.0, 1.0, 16.0, 1e3, 1e6):
        # g^2 = (n+1)^2/(4n) (sigma^2 + x) / (sigma^2 + (n+1)/2 x): each multiplexed image holds the
        # light of (n+1)/2 LEDs, so its photon noise grows by sqrt((n+1)/2)
        want = np.sqrt((n + 1) ** 2 / (4 * n) * (sigma**2 + x) / (sigma**2 + (n + 1) / 2 * x))
        assert noise_gain(S, np.full((n, 2), x), read_noise=sigma) == pytest.approx(want, rel=1e-12)
    gains = [noise_gain(S, np.full(n, x), read_noise=sigma) for x in np.geomspace(1e-6, 1e7, 12)]
    assert np.all(np.diff(gains) < 0)                         # more light -> less multiplexing advantage
    assert gains[0] == pytest.approx(snr_gain(S), rel=1e-3)
    # thesis §3.1: photon noise degrades the S-matrix SNR by 1/sqrt(2) in the worst case
    assert gains[-1] == pytest.approx(np.sqrt((n + 1) / (2 * n)), rel=1e-3)
    assert gains[-1] >= 1 / np.sqrt(2) - 1e-12


def test_photon_dominated_monte_carlo_thesis_worst_cases():
    rng = np.random.default_rng(29)
    # S-matrix, photon noise only: demultiplexed noise is ~sqrt(2) x single-light noise (thesis §3.1)
    n = 31
    S = s_matrix(n)
    truth = rng.uniform(500.0, 1500.0, size=(n, 3000))
    single = _poisson_capture(rng, np.eye(n), truth, 0.0)
    demux = demultiplex(_poisson_capture(rng, S, truth, 0.0), S)
    measured = _rms(single - truth) / _rms(demux - truth)
    assert measured == pytest.approx(np.sqrt((n + 1) / (2 * n)), rel=0.15)
    assert measured < 1.0
    # "all but one LED" patterns: SNR drops by about 1/sqrt(n_i) (thesis ch. 3.1)
    n = 16
    M = (np.ones((n, n)) - np.eye(n)).astype(np.uint8)
    truth = rng.uniform(500.0, 1500.0, size=(n, 3000))
    single = _poisson_capture(rng, np.eye(n), truth, 0.0)
    demux = demultiplex(_poisson_capture(rng, M, truth, 0.0), M)
    measured = _rms(single - truth) / _rms(demux - truth)
    assert measured == pytest.approx(noise_gain(M, truth, read_noise=0.0), rel=0.15)
    assert measured == pytest.approx(1 / np.sqrt(n), rel=0.15)


# --------------------------------------------------------------------------- bad input


def test_non_binary_pattern_names_the_index():
    M = s_matrix(7).astype(np.float64)
    M[2, 3] = 0.5
    with pytest.raises(ValueError, match=r"patterns\[2, 3\] = 0\.5"):
        demultiplex(np.zeros((7, 4)), M)
    M[2, 3] = np.nan
    with pytest.raises(ValueError, match=r"\[2, 3\]"):
        demultiplex_operator(M)
    with pytest.raises(ValueError, match=r"S\[0, 1\]"):
        s_matrix_inverse(np.array([[1, 2, 0], [1, 0, 1], [0, 1, 1]]))


def test_order_that_does_not_exist():
    with pytest.raises(ValueError, match="order 9"):
        s_matrix(9)
    with pytest.raises(ValueError, match="order 9"):
        s_matrix_inverse(np.ones((9, 9)))
    with pytest.raises(ValueError, match="not an S-matrix of order 7"):
        s_matrix_inverse(np.eye(7))
    with pytest.raises(ValueError, match="square"):
        s_matrix_inverse(s_matrix(7)[:, :6])


def test_nan_in_measurements_names_the_index():
    M = s_matrix(7)
    y = np.ones((7, 5, 3))
    y[4, 2, 1] = np.nan
    with pytest.raises(ValueError, match=r"measured\[4, 2, 1\]"):
        demultiplex(y, M)
    y[4, 2, 1] = np.inf
    with pytest.raises(ValueError, match=r"measured\[4, 2, 1\]"):
        demultiplex(y.astype(np.float32), M)


def test_rank_deficient_patterns_name_the_rank():
    with pytest.raises(ValueError, match="rank 1 < 5"):
        demultiplex_operator(np.ones((5, 5)))                  # all LEDs at once (thesis §3.1: singular)
    with pytest.raises(ValueError, match="rank at most 4"):
        demultiplex_operator(np.ones((4, 6)))
    M = s_matrix(7)[:, :4].copy()
    M[:, 3] = M[:, 2]
    with pytest.raises(ValueError, match="rank 3 < 4"):
        snr_gain(M)


def test_shape_and_method_errors():
    M = s_matrix(7)
    with pytest.raises(ValueError, match="first axis must be the 7 patterns"):
        demultiplex(np.ones((6, 3)), M)
    with pytest.raises(ValueError, match="unknown demultiplexing method"):
        demultiplex(np.ones((7, 3)), M, method="svd")
    with pytest.raises(ValueError, match="must be >= 0"):
        demultiplexed_noise_std(M, -np.ones(7))
    with pytest.raises(ValueError, match=r"signal\[2\]"):
        demultiplexed_noise_std(M, np.array([1, 1, np.nan, 1, 1, 1, 1.0]))
