"""Reconstruction: exact recovery in span(U) for every method, Tikhonov limits, chunking, thresholding,
ABTF bands, the block structure of eq. (10), and bad input."""

from __future__ import annotations

import numpy as np
import pytest

from btfcore.model.abtf import blend_patches, patch_matrix
from btfcore.capture.demultiplex import demultiplex
from btfcore.acquisition.hadamard import multiplexing_patterns
from btfcore.acquisition.reconstruct import (
    LAMBDA_ALS,
    LAMBDA_NIELSEN,
    abtf_halo,
    abtf_operator,
    apply,
    coefficients,
    measure,
    measurement_matrix,
    reconstruct,
    reconstruct_abtf,
    solve_operator,
    texture_variance,
    threshold_rows,
)

N_VIEWS, N_LIGHTS, K = 4, 10, 6
N_LV = N_VIEWS * N_LIGHTS


def _basis(n_lv=N_LV, k=K, seed=0):
    rng = np.random.default_rng(seed)
    U = np.linalg.qr(rng.standard_normal((n_lv, k)))[0]
    sigma = np.sort(rng.uniform(1.0, 50.0, k))[::-1]
    return U, sigma


def _in_span(U, n_tx=50, seed=1):
    C = np.random.default_rng(seed).standard_normal((U.shape[1], n_tx))
    return U @ C, C


def _tol(dtype):
    return {"rtol": 0, "atol": 1e-10} if dtype == np.float64 else {"rtol": 0, "atol": 2e-4}


# --------------------------------------------------------------------------- exact recovery


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("fused", [None, True, False])
def test_sparse_pinv_recovers_span(dtype, fused):
    U, _ = _basis()
    B, C = _in_span(U)
    rows = np.random.default_rng(2).choice(N_LV, 15, replace=False)
    op = solve_operator(U, rows=rows, fused=fused, dtype=dtype)
    assert op.dtype == dtype and op.n_meas == 15 and op.n_out == N_LV
    got = apply(op, B[rows].astype(dtype))
    assert got.dtype == dtype
    np.testing.assert_allclose(got, B, **_tol(dtype))
    np.testing.assert_allclose(coefficients(op, B[rows]), C, **_tol(dtype))


def test_fused_choice_follows_flops():
    U, _ = _basis(n_lv=200, k=4)
    assert solve_operator(U, rows=np.arange(20)).fused is None          # 200*20 > 4*220
    U, _ = _basis(n_lv=40, k=30)
    assert solve_operator(U, rows=np.arange(35)).fused is not None      # 40*35 <= 30*75


def test_pinv_equals_paper1_eq3():
    U, _ = _basis()
    rows = np.arange(0, N_LV, 3)
    M = measurement_matrix(N_LV, rows=rows)
    op = solve_operator(U, rows=rows, dtype=np.float64)
    np.testing.assert_allclose(op.coefficients, np.linalg.pinv(M @ U), atol=1e-12)   # (M U)^+


@pytest.mark.parametrize("with_rows", [False, True])
@pytest.mark.parametrize("lam", [0.0, 1e-9])
def test_direct_recovers_span(with_rows, lam):
    U, sigma = _basis()
    B, _ = _in_span(U)
    S = multiplexing_patterns(N_LIGHTS)                                 # (11, 10)
    n_mux = N_VIEWS * S.shape[0]
    rows = np.random.default_rng(3).choice(n_mux, 12, replace=False) if with_rows else None
    y = measure(B, rows=rows, patterns=S)
    op = solve_operator(U, sigma, method="direct", patterns=S, rows=rows, lam=lam, dtype=np.float64)
    assert op.n_meas == (12 if with_rows else n_mux)
    np.testing.assert_allclose(apply(op, y), B, atol=1e-7 if lam else 1e-10)


def test_direct_block_structure_is_kron_over_views():
    """Eq. (10)'s S M: the patterns act on each view's lights, rows view-major, pattern fastest."""
    S = multiplexing_patterns(N_LIGHTS)
    G = measurement_matrix(N_LV, patterns=S)
    for v in range(N_VIEWS):
        for i in range(S.shape[0]):
            want = np.zeros(N_LV)
            want[v * N_LIGHTS:(v + 1) * N_LIGHTS] = S[i]
            np.testing.assert_array_equal(G[v * S.shape[0] + i], want)
    rows = np.array([5, 0, 40, 17])
    U, sigma = _basis()
    B, _ = _in_span(U)
    np.testing.assert_allclose(measure(B, rows=rows, patterns=S), G[rows] @ B, atol=1e-12)
    op = solve_operator(U, sigma, method="direct", patterns=S, rows=np.arange(44), lam=2.0, dtype=np.float64)
    A = G @ U
    want = np.linalg.solve(A.T @ A + (2.0 / sigma) ** 2 * np.eye(K), A.T)       # eq. (10), R = lam Sigma^-1
    np.testing.assert_allclose(op.coefficients, want, atol=1e-12)


@pytest.mark.parametrize("demux_inside", [False, True])
def test_projection_recovers_span(demux_inside):
    U, _ = _basis()
    B, _ = _in_span(U)
    S = multiplexing_patterns(N_LIGHTS)
    y = measure(B, patterns=S)
    if demux_inside:
        op = solve_operator(U, method="projection", patterns=S, dtype=np.float64)
        got = apply(op, y)
    else:
        demux = demultiplex(y.reshape(N_VIEWS, S.shape[0], -1).transpose(1, 0, 2), S)   # per view
        demux = demux.transpose(1, 0, 2).reshape(N_LV, -1)
        op = solve_operator(U, method="projection", dtype=np.float64)
        np.testing.assert_allclose(op.coefficients, U.T)              # VMV §4.1: U (U^T B_demux)
        got = apply(op, demux)
    np.testing.assert_allclose(got, B, atol=1e-10)


def test_projection_of_noise_is_orthogonal_projection():
    U, _ = _basis()
    X = np.random.default_rng(4).standard_normal((N_LV, 30))
    got = reconstruct(U, X, method="projection")
    np.testing.assert_allclose(got, U @ (U.T @ X), atol=1e-12)


@pytest.mark.parametrize("demux_inside", [False, True])
def test_thresholded_recovers_span_and_ignores_dropped_rows(demux_inside):
    U, _ = _basis()
    B, _ = _in_span(U)
    S = multiplexing_patterns(N_LIGHTS)
    var = texture_variance(B)
    op = solve_operator(U, method="thresholded", variance=var, patterns=S if demux_inside else None,
                        dtype=np.float64)
    assert op.dropped.size == 4                                       # 40 rows: above the 9th decile
    if demux_inside:
        np.testing.assert_allclose(apply(op, measure(B, patterns=S)), B, atol=1e-10)
    else:
        np.testing.assert_allclose(apply(op, B), B, atol=1e-10)
        corrupted = B.copy()
        corrupted[op.dropped] += 1e3                                  # outlier textures: no influence
        np.testing.assert_allclose(apply(op, corrupted), B, atol=1e-8)
        np.testing.assert_array_equal(op.coefficients[:, op.dropped], 0.0)


def test_threshold_drops_exactly_the_rows_above_the_9th_decile():
    v = np.random.default_rng(5).lognormal(0, 2, 137)
    kept, dropped = threshold_rows(v)
    q = np.quantile(v, 0.9)
    np.testing.assert_array_equal(dropped, np.flatnonzero(v > q))
    np.testing.assert_array_equal(kept, np.flatnonzero(v <= q))
    assert dropped.size == 14                                         # sorted positions 123..136 > 0.9 * 136
    assert np.all(v[dropped] > v[kept].max())
    v = np.arange(10.0)                                               # 9th decile of 0..9 = 8.1
    np.testing.assert_array_equal(threshold_rows(v)[1], [9])
    np.testing.assert_array_equal(threshold_rows(v, 5)[1], [5, 6, 7, 8, 9])


def test_texture_variance_streams_blocks():
    B = np.random.default_rng(6).lognormal(0, 1, (9, 8, 5, 3)).astype(np.float32)
    want = B.reshape(9, -1).astype(np.float64).var(axis=1)
    np.testing.assert_allclose(texture_variance(B), want, rtol=1e-12)
    flat = B.reshape(9, -1)
    blocks = [flat[:, :7], flat[:, 7:8], flat[:, 8:64], flat[:, 64:]]
    np.testing.assert_allclose(texture_variance(iter(blocks)), want, rtol=1e-10)


# --------------------------------------------------------------------------- Tikhonov


def test_tikhonov_tends_to_pinv_as_lambda_vanishes():
    U, sigma = _basis()
    rows = np.random.default_rng(7).choice(N_LV, 10, replace=False)
    pinv = solve_operator(U, rows=rows, dtype=np.float64).coefficients
    diffs = [np.abs(solve_operator(U, sigma, method="tikhonov", rows=rows, lam=lam, dtype=np.float64).coefficients
                    - pinv).max() for lam in (1e-2, 1e-4, 1e-6)]
    assert diffs[0] > diffs[1] > diffs[2] and diffs[2] < 1e-9
    zero = solve_operator(U, sigma, method="tikhonov", rows=rows, lam=0.0, dtype=np.float64)
    np.testing.assert_allclose(zero.coefficients, pinv, atol=1e-12)


def test_tikhonov_shrinks_coefficients_as_lambda_grows():
    U, sigma = _basis()
    rng = np.random.default_rng(8)
    rows = rng.choice(N_LV, 10, replace=False)
    y = rng.standard_normal((10, 40))
    norms = [np.linalg.norm(coefficients(solve_operator(U, sigma, method="tikhonov", rows=rows, lam=lam,
                                                        dtype=np.float64), y))
             for lam in (0.0, 1.0, 10.0, 100.0, 1e4)]
    assert all(a > b for a, b in zip(norms, norms[1:]))
    assert norms[-1] < 1e-2 * norms[0]


def test_tikhonov_is_the_normal_equation_of_eq_10_and_shrinks_small_sigma_most():
    U, sigma = _basis()
    rows = np.arange(0, N_LV, 4)
    lam = 5.0
    op = solve_operator(U, sigma, method="tikhonov", rows=rows, lam=lam, dtype=np.float64)
    A = U[rows]
    R = lam * np.diag(1.0 / sigma)                                    # paper 4: R = lambda Sigma^-1
    np.testing.assert_allclose(op.coefficients, np.linalg.solve(A.T @ A + R.T @ R, A.T), atol=1e-12)
    # an orthonormal full measurement: coefficient i shrinks by sigma_i^2 / (sigma_i^2 + lam^2)
    full = solve_operator(U, sigma, method="tikhonov", lam=lam, dtype=np.float64)
    np.testing.assert_allclose(full.coefficients @ U, np.diag(sigma**2 / (sigma**2 + lam**2)), atol=1e-12)


def test_tikhonov_solves_under_determined_systems():
    U, sigma = _basis()
    rows = np.array([1, 7, 30])                                       # 3 rows < k = 6
    op = solve_operator(U, sigma, method="tikhonov", rows=rows, lam=LAMBDA_ALS, dtype=np.float64)
    assert np.all(np.isfinite(op.coefficients)) and np.isfinite(op.condition)
    assert LAMBDA_NIELSEN == 40.0


# --------------------------------------------------------------------------- chunking


@pytest.mark.parametrize("method", ["pinv", "direct", "projection"])
@pytest.mark.parametrize("fused", [True, False])
def test_chunked_apply_equals_whole(method, fused):
    U, sigma = _basis()
    rng = np.random.default_rng(9)
    S = multiplexing_patterns(N_LIGHTS)
    kw = {"pinv": {"rows": rng.choice(N_LV, 12, replace=False)},
          "direct": {"patterns": S, "lam": 0.3},
          "projection": {}}[method]
    op = solve_operator(U, sigma, method=method, fused=fused, **kw)
    y = rng.standard_normal((op.n_meas, 77)).astype(np.float32)
    whole = apply(op, y)
    chunks = np.concatenate([apply(op, y[:, a:b]) for a, b in [(0, 10), (10, 11), (11, 64), (64, 77)]], axis=1)
    np.testing.assert_allclose(chunks, whole, rtol=1e-5, atol=1e-5)
    out = np.empty((op.n_out, 13), np.float32)
    assert apply(op, y[:, :13], out=out) is not None
    np.testing.assert_allclose(out, whole[:, :13], rtol=1e-5, atol=1e-5)
    assert apply(op, y.reshape(op.n_meas, 7, 11)).shape == (N_LV, 7, 11)
    done: list[slice] = []                                            # in row parts, each handed over when done
    parts = np.full((op.n_out, 77), np.nan, np.float32)

    def finished(rows: slice) -> None:
        np.testing.assert_allclose(parts[rows], whole.reshape(op.n_out, 77)[rows], rtol=1e-5, atol=1e-5)
        assert np.isnan(parts[rows.stop:]).all()                      # the rows after it are not computed yet
        done.append(rows)

    assert apply(op, y.reshape(op.n_meas, 7, 11), out=parts, part_rows=5, on_rows=finished).shape == (N_LV, 7, 11)
    assert [(r.start, r.stop) for r in done] == [(a, min(a + 5, op.n_out)) for a in range(0, op.n_out, 5)]


# --------------------------------------------------------------------------- ABTF patches


def _low_rank_texture(n_lv=10, h=9, w=8, C=2, r=2, seed=10):
    """B(l, y, x, c) = sum_j a_j(l) t_j(y, x, c): every p x p patch lies in the span of e_d (x) a_j."""
    rng = np.random.default_rng(seed)
    a = rng.standard_normal((n_lv, r))
    t = rng.standard_normal((r, h, w, C))
    return np.einsum("lr,ryxc->lyxc", a, t)


def _patch_basis(B, p=3):
    P = patch_matrix(B, p, overlap=True)
    Q, s, _ = np.linalg.svd(P, full_matrices=False)
    k = int(np.sum(s > 1e-10 * s[0]))
    return Q[:, :k], s[:k]


def test_abtf_recovers_span_and_equals_blend_patches():
    B = _low_rank_texture()
    Up, sp = _patch_basis(B)
    assert Up.shape[1] == 18                                          # p^2 r
    rows = np.array([0, 4, 7])
    op = abtf_operator(Up, rows, p=3, dtype=np.float64)
    got = reconstruct_abtf(op, B[rows])
    np.testing.assert_allclose(got, B, atol=1e-9)
    cols = apply(op, patch_matrix(B[rows], 3, overlap=True))          # U (S_patch U)^+ S_patch B_patch
    np.testing.assert_allclose(got, blend_patches(cols, B.shape, 3), atol=1e-12)
    tik = abtf_operator(Up, rows, p=3, sigma=sp, method="tikhonov", lam=1e-9, dtype=np.float64)
    np.testing.assert_allclose(reconstruct_abtf(tik, B[rows]), B, atol=1e-7)


def test_abtf_equals_blend_patches_off_span_and_3d():
    rng = np.random.default_rng(11)
    B = rng.lognormal(0, 1, (6, 7, 9))                                # not in span: blending matters
    Up = np.linalg.qr(rng.standard_normal((9 * 6, 8)))[0]
    op = abtf_operator(Up, [1, 3, 5], p=3, dtype=np.float64)
    got = reconstruct_abtf(op, B[[1, 3, 5]])
    assert got.shape == B.shape
    cols = apply(op, patch_matrix(B[[1, 3, 5]], 3, overlap=True))
    np.testing.assert_allclose(got, blend_patches(cols, B.shape, 3), atol=1e-12)


@pytest.mark.parametrize("bands", [[(0, 3), (3, 4), (4, 11)], [(0, 1), (1, 10), (10, 11)], [(0, 11)]])
def test_abtf_bands_equal_whole(bands):
    rng = np.random.default_rng(12)
    B = rng.lognormal(0, 1, (5, 11, 6, 3)).astype(np.float32)
    Up = np.linalg.qr(rng.standard_normal((9 * 5, 7)))[0]
    rows = [0, 2, 4]
    op = abtf_operator(Up, rows, p=3)
    whole = reconstruct_abtf(op, B[rows])
    assert whole.dtype == np.float32
    parts = [reconstruct_abtf(op, B[rows][:, abtf_halo(a, b, 11, 3)], out_rows=(a, b), height=11) for a, b in bands]
    np.testing.assert_allclose(np.concatenate(parts, axis=1), whole, rtol=1e-5, atol=1e-5)


# --------------------------------------------------------------------------- errors


def test_too_few_samples_names_counts_and_remedy():
    U, _ = _basis()
    with pytest.raises(ValueError, match=r"5 measured rows for k=6 .*tikhonov"):
        solve_operator(U, rows=np.arange(5))
    with pytest.raises(ValueError, match=r"3 measured rows for k=6"):
        solve_operator(U, method="direct", patterns=multiplexing_patterns(N_LIGHTS), rows=[0, 1, 2])
    with pytest.raises(ValueError, match=r"rows of U.*fewer|9 measured rows for k=18|measured rows"):
        abtf_operator(np.linalg.qr(np.random.default_rng(0).standard_normal((90, 18)))[0], [0], p=3)


def test_rank_deficient_sampled_rows():
    U, _ = _basis()
    U = U.copy()
    U[:8, 3] = 0.0                                                    # column 3 invisible on rows 0..7
    with pytest.raises(ValueError, match=r"rank 5 < k=6"):
        solve_operator(U, rows=np.arange(8))
    S = multiplexing_patterns(N_LIGHTS).copy()
    S[:, 2] = S[:, 1]                                                 # lights 1 and 2 inseparable
    U2 = np.zeros((N_LV, 2))
    U2[1::N_LIGHTS, 0] = 1.0                                          # basis vector: light 1 in every view
    U2[2::N_LIGHTS, 1] = 1.0                                          # light 2 in every view
    with pytest.raises(ValueError, match=r"S M U .*rank 1 < k=2.*patterns themselves have rank 9 < 10"):
        solve_operator(U2 / 2.0, method="direct", patterns=S)
    with pytest.raises(ValueError, match="rank-deficient"):
        solve_operator(_basis()[0], method="projection", patterns=S)


def test_bad_input_messages():
    U, sigma = _basis()
    with pytest.raises(ValueError, match="unknown reconstruction method"):
        solve_operator(U, method="lsq")
    with pytest.raises(ValueError, match=r"rows\[1\] = 40 is outside"):
        solve_operator(U, rows=[0, 40, 2, 3, 4, 5, 6])
    with pytest.raises(ValueError, match=r"rows\[2\] = 0 repeats rows\[0\]"):
        solve_operator(U, rows=[0, 1, 0, 3, 4, 5, 6])
    with pytest.raises(ValueError, match="needs lam"):
        solve_operator(U, sigma, method="tikhonov")
    with pytest.raises(ValueError, match="sigma"):
        solve_operator(U, method="tikhonov", lam=1.0)
    with pytest.raises(ValueError, match=r"sigma\[5\] = 0.0"):
        solve_operator(U, np.r_[sigma[:5], 0.0], method="tikhonov", lam=1.0)
    with pytest.raises(ValueError, match=r"sigma has shape \(5,\)"):
        solve_operator(U, sigma[:5], method="tikhonov", lam=1.0)
    with pytest.raises(ValueError, match="use method='direct'"):
        solve_operator(U, method="pinv", patterns=multiplexing_patterns(N_LIGHTS))
    with pytest.raises(ValueError, match="not a multiple of the 7 lights"):
        solve_operator(U, method="direct", patterns=multiplexing_patterns(7))
    with pytest.raises(ValueError, match="takes no rows"):
        solve_operator(U, method="projection", rows=[1, 2])
    with pytest.raises(ValueError, match="needs variance"):
        solve_operator(U, method="thresholded")
    with pytest.raises(ValueError, match="no regulariser"):
        solve_operator(U, method="pinv", lam=1.0)
    bad = U.copy()
    bad[3, 2] = np.nan
    with pytest.raises(ValueError, match=r"U\[3, 2\]"):
        solve_operator(bad)
    op = solve_operator(U, rows=np.arange(10))
    y = np.ones((10, 4), np.float32)
    y[7, 1] = np.inf
    with pytest.raises(ValueError, match=r"measured\[7, 1\]"):
        apply(op, y)
    with pytest.raises(ValueError, match="first axis must be the operator's 10"):
        apply(op, np.ones((9, 4)))
    with pytest.raises(ValueError, match="out must be"):
        apply(op, np.ones((10, 4)), out=np.empty((N_LV, 4)))
    with pytest.raises(ValueError, match="not an ABTF operator"):
        reconstruct_abtf(op, np.ones((10, 4, 4)))
    Up = np.linalg.qr(np.random.default_rng(0).standard_normal((45, 4)))[0]
    aop = abtf_operator(Up, [0, 1], p=3)
    with pytest.raises(ValueError, match="need rows 0:5"):
        reconstruct_abtf(aop, np.ones((2, 4, 6)), out_rows=(0, 3), height=9)
    with pytest.raises(ValueError, match="not a multiple of p"):
        abtf_operator(Up[:44], [0, 1], p=3)


# --------------------------------------------------------------------------- ill-conditioned solves warn


def _basis_with_a_lonely_vector(n: int = 30, eps: float = 1e-8, seed: int = 3) -> np.ndarray:
    """(n, 2) orthonormal U whose second vector lives almost only on row 0 (as the brightest light)."""
    rng = np.random.default_rng(seed)
    X = np.stack([rng.uniform(0.5, 1.0, n), eps * rng.normal(size=n)], axis=1)
    X[0, 1] = 1.0
    return np.linalg.qr(X)[0]


def test_ill_conditioned_pinv_and_thresholded_solves_warn_with_the_figure_and_the_fix():
    from btfcore import ILL_CONDITIONED_SOLVE, IllConditionedWarning

    U = _basis_with_a_lonely_vector()
    # without row 0 the second vector is ~1e-8: kappa ~ 1e8 > ILL_CONDITIONED_SOLVE
    with pytest.warns(IllConditionedWarning, match=r"condition number of M U is [0-9.]+e\+0[7-9] > 1e\+06.*"
                                                  r"regularise \(method='tikhonov'"):
        op = solve_operator(U, method="pinv", rows=np.arange(1, 30))
    assert op.condition > ILL_CONDITIONED_SOLVE
    variance = np.ones(30)
    variance[0] = 100.0                                       # the brightest row is the one dropped
    # thresholded: U~ is ~1e8 worse conditioned than U, so it falls back to the projection in that direction
    # (the fix, no warning; tests/btfcore/test_thresholded_fallback.py); an ill-conditioned U itself warns
    op = solve_operator(U, method="thresholded", variance=variance)
    assert op.dropped.tolist() == [0] and op.fallback == 1 and op.condition < 10
    with pytest.warns(IllConditionedWarning, match=r"U~ \(U without the dropped rows\).*method='projection'"):
        solve_operator(np.random.default_rng(1).normal(size=(30, 2)) * [1.0, 1e-7], method="thresholded",
                       variance=variance)
    # regularised: the fix, no warning (pyproject turns BtfWarning into errors)
    op = solve_operator(U, np.ones(2), method="tikhonov", rows=np.arange(1, 30), lam=0.01)
    assert op.condition < ILL_CONDITIONED_SOLVE


def test_warn_false_leaves_the_condition_number_to_the_caller():
    import warnings

    from btfcore import ILL_CONDITIONED_SOLVE, IllConditionedWarning

    U = _basis_with_a_lonely_vector()
    variance = np.ones(30)
    variance[0] = 100.0
    with warnings.catch_warnings():
        warnings.simplefilter("error", IllConditionedWarning)
        op = solve_operator(U, method="pinv", rows=np.arange(1, 30), warn=False)
        assert op.condition > ILL_CONDITIONED_SOLVE                  # reported, not warned
        op = solve_operator(np.random.default_rng(1).normal(size=(30, 2)) * [1.0, 1e-7], method="thresholded",
                            variance=variance, warn=False)
        assert op.condition > ILL_CONDITIONED_SOLVE
        Up = np.tile(U, (9, 1))                                       # a 3x3 patch basis of the same rows
        op = abtf_operator(Up, np.arange(1, 30), p=3, warn=False)
        assert op.condition > ILL_CONDITIONED_SOLVE
    with pytest.warns(IllConditionedWarning, match="S_patch U_patch"):
        abtf_operator(Up, np.arange(1, 30), p=3)                      # the default still warns


def test_well_conditioned_solves_do_not_warn():
    import warnings

    from btfcore import IllConditionedWarning

    U = _basis_with_a_lonely_vector()
    with warnings.catch_warnings():
        warnings.simplefilter("error", IllConditionedWarning)
        op = solve_operator(U, method="pinv", rows=np.arange(0, 30, 2))  # row 0 kept
        assert op.condition < 1e3
        variance = np.ones(30)
        variance[5] = 100.0
        op = solve_operator(U, method="thresholded", variance=variance)
        assert op.dropped.tolist() == [5] and op.condition < 1e3
        demultiplex(np.ones((19, 4)), multiplexing_patterns(16)[:, :12], method="pinv")
