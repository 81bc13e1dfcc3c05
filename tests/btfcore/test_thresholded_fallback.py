"""The thresholded de-noising (VMV §4.1) falls back to the projection in the directions its reduced basis
no longer determines (docs/demultiplex-resample.md, "Thresholded fallback")."""

from __future__ import annotations

import numpy as np
import pytest

from btfcore.acquisition.hadamard import multiplexing_patterns
from btfcore.acquisition.reconstruct import (
    THRESHOLD_FALLBACK_MARGIN,
    apply,
    solve_operator,
    texture_variance,
    threshold_rows,
)
from btfcore.capture.demultiplex import demultiplex_operator

N_LIGHTS, N_TX, K = 11, 4000, 3


def scene(seed: int, lonely: float, outlier_row: int | None = None, outlier_gain: float = 20.0):
    """One view under 11 lights: a diffuse and a textured term on every light plus, with ``lonely`` > 0,
    a highlight almost only under light 0 (the brightest, as a specular lobe); demultiplexed S-matrix
    noise (photon noise through the order-11 S-matrix: equal per light), ``outlier_row`` with
    ``outlier_gain`` times the noise. Returns the truth, its (k = 3) basis and the noisy demultiplexed BTF."""
    rng = np.random.default_rng(seed)
    truth = np.outer(rng.uniform(0.5, 1.0, N_LIGHTS), rng.uniform(0.5, 1.5, N_TX))
    truth += np.outer(rng.uniform(0.5, 1.0, N_LIGHTS), rng.uniform(0.0, 0.3, N_TX))
    lobe = 0.02 * rng.uniform(size=N_LIGHTS)
    lobe[0] = 1.0
    truth += np.outer(lobe, lonely * rng.gamma(2.0, 1.0, N_TX))
    U = np.linalg.svd(truth, full_matrices=False)[0][:, :K]
    S = multiplexing_patterns(N_LIGHTS)
    P = demultiplex_operator(S)
    measured = S @ truth + 0.03 * rng.standard_normal((N_LIGHTS, N_TX))
    demux = P @ measured
    if outlier_row is not None:
        demux[outlier_row] += (outlier_gain - 1) * 0.03 * rng.standard_normal(N_TX)
    return truth, U, demux


def error(estimate, truth) -> float:
    return float(np.linalg.norm(estimate - truth) / np.linalg.norm(truth))


def plain_thresholded(U, demux):
    """VMV §4.1 without the fallback: U U~^+ B~."""
    kept, _ = threshold_rows(texture_variance(demux))
    return U @ (np.linalg.pinv(U[kept]) @ demux[kept])


@pytest.mark.parametrize("seed", range(4))
def test_dropping_the_brightest_light_falls_back_to_the_projection(seed):
    truth, U, demux = scene(seed, lonely=0.5)
    var = texture_variance(demux)
    op = solve_operator(U, method="thresholded", variance=var, dtype=np.float64)
    assert op.dropped.tolist() == [0] and op.fallback == 1        # the highlight's direction
    kept = np.setdiff1d(np.arange(N_LIGHTS), op.dropped)
    s_red = np.linalg.svd(U[kept], compute_uv=False)
    assert s_red[0] / s_red[-1] > THRESHOLD_FALLBACK_MARGIN          # measured 75
    proj = apply(solve_operator(U, method="projection", dtype=np.float64), demux)
    # measured over seeds 0-3: plain thresholded 30-60x the projection's error, the fallback 1.00-1.02x
    assert error(plain_thresholded(U, demux), truth) > 10 * error(proj, truth)
    assert error(apply(op, demux), truth) < 1.05 * error(proj, truth)
    assert op.condition < 2.0


@pytest.mark.parametrize("seed", range(4))
def test_a_noise_outlier_is_dropped_without_a_fallback(seed):
    truth, U, demux = scene(seed, lonely=0.0, outlier_row=5)
    op = solve_operator(U, method="thresholded", variance=texture_variance(demux), dtype=np.float64)
    assert op.dropped.tolist() == [5] and op.fallback == 0
    np.testing.assert_allclose(apply(op, demux), plain_thresholded(U, demux), rtol=1e-9, atol=1e-12)
    proj = apply(solve_operator(U, method="projection", dtype=np.float64), demux)
    assert error(apply(op, demux), truth) < 0.5 * error(proj, truth)   # what the thresholding is for


def test_the_fallback_is_exact_on_data_in_the_basis_span_and_ignores_dropped_rows_elsewhere():
    truth, U, _ = scene(0, lonely=0.5)
    B = U @ np.random.default_rng(9).normal(size=(K, 50))
    variance = np.ones(N_LIGHTS)
    variance[0] = 10.0
    op = solve_operator(U, method="thresholded", variance=variance, dtype=np.float64)
    assert op.fallback == 1
    np.testing.assert_allclose(apply(op, B), B, atol=1e-12)           # no bias
    # the well-determined directions do not see the dropped row: a change there moves only the fallback's
    noisy = B.copy()
    noisy[0] += 100.0
    Q, s, Wt = np.linalg.svd(U[1:], full_matrices=False)
    good = s * THRESHOLD_FALLBACK_MARGIN >= s[0]
    coef = op.coefficients
    np.testing.assert_allclose(Wt[good] @ coef @ noisy, Wt[good] @ coef @ B, atol=1e-9)


def test_the_multiplexed_operator_falls_back_too():
    truth, U, demux = scene(1, lonely=0.5)
    S = multiplexing_patterns(N_LIGHTS)
    measured = np.linalg.solve(demultiplex_operator(S), demux)        # back to the multiplexed images
    op = solve_operator(U, method="thresholded", variance=texture_variance(demux), patterns=S, dtype=np.float64)
    assert op.fallback == 1
    plain = solve_operator(U, method="thresholded", variance=texture_variance(demux), dtype=np.float64)
    np.testing.assert_allclose(apply(op, measured), apply(plain, demux), rtol=1e-8, atol=1e-10)
