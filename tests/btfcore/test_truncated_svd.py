"""Truncated SVD of a BTF matrix over column blocks: Gram route, randomized, EM-PCA, 'auto'."""

from __future__ import annotations

import json

import numpy as np
import pytest
from _lowrank_cases import assert_meets_bars, decaying, exact_svd, orthonormal, uneven_blocks

from btfcore.model.truncated_svd import choose_method, column_blocks, truncated_svd

K = 20
ITERATIVE = ["randomized", "empca"]


def _rank12(n_lv: int = 200, n_tx: int = 1000) -> np.ndarray:
    rng = np.random.default_rng(5)
    return (orthonormal(rng, n_lv, 12) * np.geomspace(10, 1, 12)) @ orthonormal(rng, n_tx, 12).T


def test_gram_route_is_exact():
    B = decaying()
    Ue, se = exact_svd()
    res = truncated_svd(column_blocks(B, 700), B.shape[0], K, "gram")
    assert res.method == "gram" and res.iterations == 1 and res.converged
    np.testing.assert_allclose(res.sigma, se[:K], rtol=1e-10)
    assert np.linalg.norm(res.U @ res.U.T - Ue[:, :K] @ Ue[:, :K].T, 2) < 1e-10
    assert res.energy_captured == pytest.approx(np.sum(se[:K] ** 2) / np.sum(se**2), rel=1e-12)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("method", ["gram", *ITERATIVE])
def test_every_method_meets_the_bars(method, dtype):
    B = decaying().astype(dtype)
    res = truncated_svd(uneven_blocks(B), B.shape[0], K, method)
    assert res.method == method and res.settings["method"] == method
    assert_meets_bars(res, B, K)


@pytest.mark.parametrize("method", ["gram", *ITERATIVE])
def test_streaming_equals_in_memory(method):
    """One in-memory block, many uneven blocks and a callable streaming them give the same model."""
    B = decaying()
    one = truncated_svd(B, B.shape[0], K, method)
    for blocks in (uneven_blocks(B, seed=1), lambda: (B[:, i:i + 333] for i in range(0, B.shape[1], 333))):
        res = truncated_svd(blocks, B.shape[0], K, method)
        assert res.iterations == one.iterations
        np.testing.assert_allclose(res.U, one.U, atol=1e-9)
        np.testing.assert_allclose(res.sigma, one.sigma, rtol=1e-11)
        np.testing.assert_allclose(res.norm_sq, one.norm_sq, rtol=1e-12)


def test_auto_chooses_by_shape_and_memory_and_says_which():
    assert choose_method(192, 32, memory_bytes=2**31) == "gram"               # the tiny dome
    assert choose_method(26136, 256, memory_bytes=2**31) == "randomized"      # the thesis' dome
    assert choose_method(2912, 256, memory_bytes=2**31) == "gram"             # l = 416, 7 products: 2912 rows
    assert choose_method(2913, 256, memory_bytes=2**31) == "randomized"
    assert choose_method(192, 32, memory_bytes=8 * 192**2 - 1) == "randomized"
    B = decaying(100, 2000)
    small = truncated_svd(B, 100, 10)
    assert small.method == "gram" and small.settings["requested"] == "auto"
    tight = truncated_svd(B, 100, 10, memory_bytes=8 * 100**2 - 1)
    assert tight.method == "randomized" and tight.settings["n_iter"] == 3 and tight.settings["oversample"] == 10
    np.testing.assert_allclose(tight.sigma, small.sigma, rtol=1e-6)


@pytest.mark.parametrize("method", ["gram", *ITERATIVE])
def test_k_above_size_or_numerical_rank_is_refused(method):
    B = _rank12()
    assert truncated_svd(B, 200, 12, method).k == 12
    with pytest.raises(ValueError, match=r"k=13 exceeds the numerical rank 12 of B \(200, 1000\)"):
        truncated_svd(B, 200, 13, method, max_iter=10)
    with pytest.raises(ValueError, match=r"k=201 exceeds min\(rows, columns\) = 200"):
        truncated_svd(B, 200, 201, method)
    with pytest.raises(ValueError, match=r"k=60 exceeds min\(rows, columns\) = 50 of B \(200, 50\)"):
        truncated_svd(B[:, :50], 200, 60, method)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("method", ["gram", *ITERATIVE])
def test_nan_or_inf_names_the_block_and_index(method, bad):
    blocks = [b.astype(np.float32) for b in column_blocks(decaying(), 1000)]
    blocks[2][5, 7] = bad
    with pytest.raises(ValueError, match=r"blocks\[2\]\[5, 7\] = -?(nan|inf), i\.e\. B\[5, 2007\]"):
        truncated_svd(blocks, 500, K, method)


def test_malformed_sources_are_refused():
    B = decaying()
    with pytest.raises(ValueError, match="fresh iterator"):
        truncated_svd((b for b in [B]), 500, K)                              # a one-shot generator
    once = iter([B])
    with pytest.raises(ValueError, match="0 columns in this pass but 4000 in the first"):
        truncated_svd(lambda: once, 500, K, "randomized")
    with pytest.raises(ValueError, match=r"blocks\[1\] has shape \(499, 10\)"):
        truncated_svd([B, B[1:, :10]], 500, K)
    with pytest.raises(ValueError, match="method must be one of"):
        truncated_svd(B, 500, K, "lanczos")


def test_settings_are_json_scalars():
    res = truncated_svd(decaying(), 500, K, "randomized", oversample=6, n_iter=3, seed=2, rows_id="s")
    assert json.loads(json.dumps(res.settings, allow_nan=False)) == res.settings
    assert res.settings == dict(method="randomized", requested="randomized", k=K, n_lv=500, seed=2,
                                rank_rtol=1e-5, memory_bytes=2**31, oversample=6, n_iter=3)
    assert res.iterations == 4 and res.rows_id == "s"          # n_iter + 1 passes


def _power_law(n_lv: int, n_tx: int, rank: int, spectrum: np.ndarray, seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return ((orthonormal(rng, n_lv, rank) * spectrum) @ orthonormal(rng, n_tx, rank).T).astype(np.float32)


def _excess(U: np.ndarray, B: np.ndarray, k: int) -> float:
    """Projection error of span(U) over the optimal rank-k error, minus 1 (B's own float64 spectrum)."""
    B64 = B.astype(np.float64)
    s2 = np.linalg.svd(B64, compute_uv=False) ** 2
    err2 = max(float(np.sum(s2) - np.sum((np.linalg.qr(U)[0].T @ B64) ** 2)), 0.0)
    return float(np.sqrt(err2 / np.sum(s2[k:]))) - 1


@pytest.mark.parametrize("spectrum", ["power law", "steep"])
def test_the_nystrom_step_gains_half_a_power_iteration_for_no_pass(spectrum):
    """The randomized method's last step (Halko et al. §5.4, shifted as in Tropp et al. 2017) against the
    Rayleigh-Ritz basis of the same last pass. On a slowly decaying spectrum (the thesis-scale benchmark's
    i^-0.75) it must be clearly more accurate at equal passes and as accurate as Rayleigh-Ritz with one
    pass more; on a steep one with a float32 floor (BTF-like: 99.99 % of the energy in a few vectors) it
    must not amplify the products' rounding in the directions of tiny eigenvalues that it divides by."""
    from btfcore.model.empca import block_power_iteration

    rank, k, l = 400, 32, 48
    s = np.arange(1, rank + 1) ** -0.75 if spectrum == "power law" else np.exp(-np.arange(rank) / 6.0) + 1e-7
    B = _power_law(600, 2400, rank, s)
    excess = {}
    for final in ("ritz", "nystrom"):
        for passes in (3, 4):
            U, *_ = block_power_iteration(lambda: column_blocks(B, 700), 600, k, l, max_iter=passes, tol=None,
                                          final=final)
            excess[final, passes] = _excess(U, B, k)
    if spectrum == "power law":
        assert excess["nystrom", 3] < 0.5 * excess["ritz", 3], excess
        assert excess["nystrom", 3] < 1.5 * excess["ritz", 4], excess
    else:
        assert max(excess["nystrom", 3], excess["nystrom", 4]) < 1e-6, excess
    res = truncated_svd(lambda: column_blocks(B, 700), 600, k, "randomized", oversample=l - k, n_iter=2)
    assert res.iterations == 3 and _excess(res.U, B, k) == pytest.approx(excess["nystrom", 3], abs=1e-9)


def test_nystrom_step_on_data_of_lower_rank_than_its_vectors():
    """Rank 12 with 20 + 10 vectors: C^T S is singular but for the shift; the 12 are exact."""
    B = _rank12()
    res = truncated_svd(B, 200, 12, "randomized", oversample=18)
    np.testing.assert_allclose(res.sigma, np.geomspace(10, 1, 12), rtol=1e-9)


def test_the_first_pass_sketches_b_omega_in_one_product():
    """Halko et al.'s Alg. 4.4 start: pass 1 forms B Omega with Omega (n_tx, l) Gaussian from the seed, row
    by row in column order; the next pass forms B B^T orth(B Omega) and the Nyström step ends it. Written
    out here with numpy, it must give the library's basis (uneven blocks: Omega does not depend on them)."""
    from btfcore.model._lowrank import nystrom, orthonormalise

    B = decaying()
    n_lv, n_tx = B.shape
    l, seed = K + 12, 7
    Omega = np.random.default_rng(seed).standard_normal((n_tx, l))
    C = orthonormalise(B @ Omega)
    U, sigma = nystrom(C, B @ (B.T @ C), float(np.finfo(np.float64).eps), K)
    res = truncated_svd(uneven_blocks(B, seed=2), n_lv, K, "randomized", n_iter=1, oversample=l - K, seed=seed)
    assert res.iterations == 2
    np.testing.assert_allclose(np.abs(res.U.T @ U), np.eye(K), atol=1e-9)     # equal up to column signs
    np.testing.assert_allclose(res.sigma, sigma[:K], rtol=1e-10)


@pytest.mark.parametrize("steep", [False, True])
def test_nystrom_eigenvectors_from_the_small_gram_matrix_are_checked(steep, monkeypatch):
    """The Nyström step's eigenvectors come from the l x l Gram matrix of E where that is accurate, and from
    the SVD of E where the spectrum at k is too steep for it (1e-16 of the largest eigenvalue): both
    orthonormal to 1e-10 and spanning what the SVD of E spans."""
    from scipy import linalg

    from btfcore.model._lowrank import nystrom, orthonormalise

    rng = np.random.default_rng(4)
    n, l, k = 900, 60, 40
    s = np.exp(-np.arange(l) * 1.0) if steep else np.arange(1, l + 1) ** -0.75
    Q = orthonormalise(rng.standard_normal((n, l)))
    C = orthonormalise(Q + 0.3 * rng.standard_normal((n, l)) / np.sqrt(n))
    S = Q @ (s[:, None] ** 2 * (Q.T @ C))                                   # S = G C, G = Q diag(s^2) Q^T
    if not steep:                                 # the Gram route alone: no SVD of the tall E
        svd = np.linalg.svd
        monkeypatch.setattr(np.linalg, "svd", lambda a, *args, **kw: pytest.fail("SVD of E") if a.shape[0] == n
                            else svd(a, *args, **kw))
    U, sigma = nystrom(C, S, 1e-16, k)
    monkeypatch.undo()
    assert U.shape == (n, k)
    assert np.abs(U.T @ U - np.eye(k)).max() < 1e-10
    nu = 1e-16 * np.linalg.norm(S)
    Y = S + nu * C
    E = linalg.solve_triangular(np.linalg.cholesky(C.T @ Y), Y.T, lower=True).T
    Ue, se, _ = np.linalg.svd(E, full_matrices=False)
    np.testing.assert_allclose(sigma[:k], np.sqrt(np.maximum(se[:k] ** 2 - nu, 0)), rtol=1e-6, atol=1e-8)  # sqrt(eps)
    good = se[:k] > 1e-6 * se[0]                  # directions the data resolves
    np.testing.assert_allclose(np.abs(np.sum(U[:, good] * Ue[:, :k][:, good], axis=0)), 1.0, atol=1e-8)


def test_squared_norm_of_float32_blocks_sums_rows_in_float32_and_overflows_in_float64():
    """||B||^2 from float32 row sums: within 1e-6 of float64 on a wide block; rows whose float32 squares
    overflow are summed in float64, so only a float64 overflow gives inf."""
    from btfcore.model._lowrank import squared_norm

    b = np.random.default_rng(0).standard_normal((300, 5000)).astype(np.float32)
    exact = float(np.sum(b.astype(np.float64) ** 2))
    assert squared_norm(b) == pytest.approx(exact, rel=1e-6)
    b[7, 11] = 3e19                                          # its square overflows float32, not float64
    assert squared_norm(b) == pytest.approx(float(np.sum(b.astype(np.float64) ** 2)), rel=1e-6)
    assert squared_norm(np.full((2, 2), 1e200)) == np.inf
