"""Relative-error weighted ALS bases and their merge (paper 4, eqs. 5-9; issue 4, item 5 and the ALS bars)."""

from __future__ import annotations

import numpy as np
import pytest

from btfcore.model.als import FLOOR_SAMPLE, WEIGHT_FLOOR_FRACTION, ALSResult, als_basis, merge_als_bases, relative_error_weights

N_LV, N_TX = 300, 2000


def _positive_rank_c(c: int, seed: int = 0) -> np.ndarray:
    """Positive (N_LV, N_TX) data of exact rank c with a dynamic range of about 1e3."""
    rng = np.random.default_rng(seed)
    return np.exp(rng.normal(0, 1.0, (N_LV, c))) @ rng.uniform(0.05, 1.0, (c, N_TX))


def _noisy(c: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    D = _positive_rank_c(c, seed)
    return D * (1 + 0.05 * rng.standard_normal(D.shape))


def _weighted_error(r: ALSResult, D: np.ndarray, W: np.ndarray) -> float:
    return float(np.sum((W * (r.U * r.sigma @ r.V - D)) ** 2))


# --------------------------------------------------------------------------- weights


def test_relative_error_weights_floor():
    D = np.array([[2.0, 0.0, -4.0], [1e-9, 1.0, 3.0]])
    floor = 1e-3 * np.median([2.0, 4.0, 1e-9, 1.0, 3.0])
    np.testing.assert_allclose(relative_error_weights(D), 1 / np.maximum(np.abs(D), floor))
    np.testing.assert_allclose(relative_error_weights(D, floor=0.5)[1], [2.0, 1.0, 1 / 3])
    assert relative_error_weights(D.astype(np.float32)).dtype == np.float32
    with pytest.raises(ValueError, match="all zero"):
        relative_error_weights(np.zeros((2, 2)))
    with pytest.raises(ValueError, match=r"D\[1, 0\]"):
        relative_error_weights(np.array([[1.0, 2.0], [np.inf, 1.0]]))


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_default_weights_equal_the_explicit_ones(backend):
    """The V-step forms the default W^2 as 1/max(D^2, floor^2) in place: the fit equals one given
    relative_error_weights(D, floor) in float32, with values below the floor and of both signs (to
    float32 rounding: the weights differ by an ulp, which the huge weights of the floored row amplify)."""
    D = _noisy(8).astype(np.float32)
    D[0, :5] = [0.0, -1e-9, 1e-9, -0.5, 0.0]
    default = als_basis(D, 4, n_iter=5, tol=0.0, backend=backend)
    given = als_basis(D, 4, relative_error_weights(D, floor=default.floor), n_iter=5, tol=0.0, backend=backend)
    np.testing.assert_allclose(default.objective, given.objective, rtol=1e-5)
    model = default.U * default.sigma @ default.V
    assert np.linalg.norm(model - given.U * given.sigma @ given.V) < 1e-4 * np.linalg.norm(model)


# --------------------------------------------------------------------------- ALS bars


def test_objective_never_increases():
    D = _noisy(8)
    r = als_basis(D, 6, n_iter=40, tol=0.0, backend="numpy")
    obj = r.objective
    assert len(obj) == r.iterations + 1 and r.iterations >= 20
    assert np.all(np.diff(obj) <= 1e-12 * obj[0]), np.diff(obj).max() / obj[0]
    assert obj[-1] < obj[1] < 0.02 * obj[0]
    # the history is the objective of eq. (5) with the default relative weights
    assert _weighted_error(r, D, relative_error_weights(D)) == pytest.approx(obj[-1], rel=1e-9)


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_exact_rank_c_is_recovered(backend):
    D = _positive_rank_c(8)
    r = als_basis(D, 8, n_iter=100, tol=1e-12, backend=backend)
    rel = np.linalg.norm(r.U * r.sigma @ r.V - D) / np.linalg.norm(D)
    W = relative_error_weights(D)
    rel_w = np.sqrt(_weighted_error(r, D, W)) / np.linalg.norm(W * D)
    assert rel < 1e-4 and rel_w < 1e-4, (rel, rel_w)
    np.testing.assert_allclose(np.linalg.norm(r.U, axis=0), 1.0, rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(r.V, axis=1), 1.0, rtol=1e-12)
    assert np.all(np.diff(r.sigma) <= 0)


@pytest.mark.parametrize("c", [1, 2, 12])
def test_unit_weights_agree_with_the_svd(c):
    D = _noisy(12, seed=2)
    r = als_basis(D, c, np.ones_like(D), n_iter=300, tol=1e-13, backend="numpy")
    s = np.linalg.svd(D, compute_uv=False)
    optimal = np.sqrt(np.sum(s[c:] ** 2))
    err = np.linalg.norm(r.U * r.sigma @ r.V - D)
    assert abs(err / optimal - 1) < 1e-4, err / optimal - 1


@pytest.mark.parametrize("dtype, rtol", [(np.float64, 1e-9), (np.float32, 2e-3)])
def test_numpy_and_torch_backends_agree(dtype, rtol):
    D = _noisy(8, seed=3).astype(dtype)
    a = als_basis(D, 6, n_iter=5, tol=0.0, backend="numpy")
    b = als_basis(D, 6, n_iter=5, tol=0.0, backend="torch", device="cpu")
    assert (a.backend, b.backend, b.device) == ("numpy", "torch", "cpu")
    assert a.U.dtype == b.U.dtype == dtype
    np.testing.assert_allclose(b.objective, a.objective, rtol=rtol)
    np.testing.assert_allclose(b.U * b.sigma @ b.V, a.U * a.sigma @ a.V, rtol=rtol, atol=rtol * np.abs(D).max())


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_chunked_equals_unchunked(backend):
    D = _noisy(8, seed=4)
    whole = als_basis(D, 6, n_iter=5, tol=0.0, backend=backend)
    for chunk in (1, 333) if backend == "numpy" else (333,):
        part = als_basis(D, 6, n_iter=5, tol=0.0, backend=backend, chunk_texels=chunk)
        np.testing.assert_allclose(part.objective, whole.objective, rtol=1e-10)
        np.testing.assert_allclose(part.U, whole.U, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(part.V, whole.V, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_unfitted_texel_and_rank_deficiency_take_the_ridge(backend):
    D = _positive_rank_c(3)
    W = relative_error_weights(D)
    W[:, 5] = 0.0                                 # texel 5 is ignored: its normal matrix is zero
    r = als_basis(D, 5, W, n_iter=20, backend=backend)   # c = 5 above the rank 3: singular systems
    assert np.isfinite(r.U).all() and np.isfinite(r.V).all()
    np.testing.assert_array_equal(r.V[:, 5], 0.0)
    assert np.all(np.diff(r.objective) <= 1e-9 * r.objective[0])
    assert np.linalg.norm(W * (r.U * r.sigma @ r.V - D)) < 1e-5 * np.linalg.norm(W * D)


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_normal_systems_solved_in_small_batches_equal_one_batch(backend, monkeypatch):
    """The CPU factorises CPU_SOLVE_BATCH systems at a time into one reused buffer per thread (a
    cache-sized batch): batches of 7 shared among 1 and 3 threads, which split the ridge's singular
    systems across batches and threads and leave a short last one, give what one batch gives."""
    import btfcore.model.als as als

    D = _positive_rank_c(3)
    W = relative_error_weights(D)
    W[:, 5] = 0.0
    runs = []
    for batch, threads in ((10**6, 1), (7, 1), (7, 3)):
        monkeypatch.setattr(als, "CPU_SOLVE_BATCH", batch)
        monkeypatch.setattr(als, "CPU_SOLVE_THREADS", threads)
        runs.append(als_basis(D, 5, W, n_iter=4, tol=0.0, backend=backend))
    for run in runs[1:]:
        np.testing.assert_allclose(run.objective, runs[0].objective, rtol=1e-10)
        np.testing.assert_allclose(run.U, runs[0].U, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(run.V, runs[0].V, rtol=1e-8, atol=1e-10)


def test_a_failing_solve_in_a_thread_is_raised(monkeypatch):
    """An error in one of the solving threads reaches the caller, not a lost thread."""
    import btfcore.model.als as als

    monkeypatch.setattr(als, "CPU_SOLVE_BATCH", 7)
    monkeypatch.setattr(als, "CPU_SOLVE_THREADS", 3)

    def broken(self, G, R):
        raise FloatingPointError("solve failed")

    monkeypatch.setattr(als._NumpyOps, "solve_spd", broken)
    with pytest.raises(FloatingPointError, match="solve failed"):
        als_basis(_positive_rank_c(3), 3, n_iter=2, backend="numpy")


# --------------------------------------------------------------------------- out of core


def _column_blocks(D: np.ndarray, width: int) -> list[np.ndarray]:
    return [D[:, s:s + width] for s in range(0, D.shape[1], width)]


def _counted(blocks: list[np.ndarray], calls: list[int]):
    """A callable block source of contiguous copies of ``blocks`` that counts its passes."""
    def source():
        calls.append(1)
        return (np.ascontiguousarray(b) for b in blocks)
    return source


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_block_source_equals_in_memory(backend):
    D = _noisy(8, seed=6)
    width = 200                          # 60000 non-zero values a block <= FLOOR_SAMPLE: the exact default floor
    assert D[:, :width].size <= FLOOR_SAMPLE
    whole = als_basis(D, 6, n_iter=6, tol=0.0, backend=backend, chunk_texels=width)
    blocks, calls = _column_blocks(D, width), []
    results = [als_basis(blocks, 6, n_iter=6, tol=0.0, backend=backend),
               als_basis(tuple(blocks), 6, n_iter=6, tol=0.0, backend=backend),
               als_basis(_counted(blocks, calls), 6, n_iter=6, tol=0.0, backend=backend)]
    assert len(calls) == 1 + 7                                   # the floor's pass and one per V-step
    assert whole.norm_sq == pytest.approx(float(np.sum(D ** 2)), rel=1e-12)
    for r in results:
        assert r.V is None and r.iterations == whole.iterations == 6
        assert r.floor == whole.floor
        np.testing.assert_allclose(r.objective, whole.objective, rtol=1e-10)
        np.testing.assert_allclose(r.U, whole.U, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(r.sigma, whole.sigma, rtol=1e-10)
        assert r.norm_sq == pytest.approx(whole.norm_sq, rel=1e-12)


def test_block_source_with_a_given_floor_and_an_estimated_one():
    D = _noisy(8, seed=7).astype(np.float32)
    blocks, calls = _column_blocks(D, 700), []                    # 210000 values a block: subsampled
    exact_floor = WEIGHT_FLOOR_FRACTION * float(np.median(np.abs(D[D != 0])))
    # the estimated default floor is within a few per cent of the exact one (here 2e-4)
    estimated = als_basis(blocks, 4, n_iter=0, backend="numpy")
    assert estimated.floor == pytest.approx(exact_floor, rel=0.03)
    assert estimated.U.dtype == np.float32
    # with one given floor, in memory and streamed agree (chunks = blocks); no pass for the floor
    whole = als_basis(D, 4, n_iter=4, tol=0.0, backend="numpy", chunk_texels=700, floor=exact_floor)
    streamed = als_basis(_counted(blocks, calls), 4, n_iter=4, tol=0.0, backend="numpy", floor=exact_floor)
    assert len(calls) == 1 + 5                                   # the first block's look and one per V-step
    np.testing.assert_allclose(streamed.objective, whole.objective, rtol=1e-6)
    np.testing.assert_allclose(streamed.U, whole.U, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(streamed.sigma, whole.sigma, rtol=1e-5)        # float32 row norms, summed per chunk
    # the default in-memory weights are relative_error_weights(D) with that floor
    np.testing.assert_allclose(als_basis(D, 4, relative_error_weights(D), n_iter=4, tol=0.0, backend="numpy").objective,
                               whole.objective, rtol=1e-5)


def test_bad_block_sources_are_refused():
    D = _positive_rank_c(3)[:20, :30]
    blocks = _column_blocks(D, 10)
    with pytest.raises(ValueError, match="W needs an in-memory D"):
        als_basis(blocks, 2, np.ones_like(D))
    with pytest.raises(ValueError, match="pass W or floor"):
        als_basis(D, 2, np.ones_like(D), floor=1.0)
    with pytest.raises(ValueError, match="generator can be read only once"):
        als_basis(iter(blocks), 2)
    bad = [b.copy() for b in blocks]
    bad[1][4, 7] = np.nan
    with pytest.raises(ValueError, match=r"blocks\[1\]\[4, 7\] = nan, i.e. B\[4, 17\]"):
        als_basis(bad, 2)
    with pytest.raises(ValueError, match=r"blocks\[1\] has shape \(19, 10\)"):
        als_basis([blocks[0], blocks[1][:19]], 2)
    with pytest.raises(ValueError, match=r"c must be .* \[1, 20\]"):
        als_basis(blocks, 21)
    with pytest.raises(ValueError, match=r"c must be .* \[1, 10\]"):     # n_tx found in the first pass
        als_basis([blocks[0]], 12, floor=1e-3)
    passes = []

    def shrinking():                                             # a source that loses a block after one pass
        passes.append(1)
        return iter(blocks if len(passes) == 1 else blocks[:2])
    with pytest.raises(ValueError, match="20 columns in this pass but 30 in the first"):
        als_basis(shrinking, 2)


# --------------------------------------------------------------------------- merging (eq. 9)


def test_merge_of_svds_is_the_svd_of_the_concatenation():
    rng = np.random.default_rng(5)
    basis = np.linalg.qr(rng.standard_normal((N_LV, 10)))[0]
    Ds = [basis @ rng.standard_normal((10, 400)) for _ in range(3)]   # three materials, one 10-dim row space
    svds = [np.linalg.svd(Di, full_matrices=False)[:2] for Di in Ds]
    U, sigma = merge_als_bases([(Ui[:, :10], si[:10]) for Ui, si in svds], 10)
    Uc, sc, _ = np.linalg.svd(np.hstack(Ds), full_matrices=False)
    np.testing.assert_allclose(sigma, sc[:10], rtol=1e-6)
    np.testing.assert_allclose(np.abs(U.T @ Uc[:, :10]), np.eye(10), atol=1e-6)
    # ALS bases (non-orthogonal columns) merge to the same 10-dim subspace
    results = [als_basis(Di, 10, np.ones_like(Di), n_iter=20, backend="numpy") for Di in Ds]
    U, sigma = merge_als_bases(results, 10)
    assert np.linalg.svd(U.T @ basis, compute_uv=False).min() > 1 - 1e-10   # cos of the largest principal angle
    assert merge_als_bases(results, 4)[0].shape == (N_LV, 4)


# --------------------------------------------------------------------------- bad input


def test_bad_input_is_refused_with_the_index():
    D = _positive_rank_c(3)[:20, :30]
    with pytest.raises(ValueError, match=r"c must be .* \[1, 20\]"):
        als_basis(D, 21)
    with pytest.raises(ValueError, match="c must be"):
        als_basis(D, 0)
    bad = D.copy()
    bad[4, 7] = np.nan
    with pytest.raises(ValueError, match=r"D contains NaN or Inf: D\[4, 7\]"):
        als_basis(bad, 2)
    W = np.ones_like(D)
    W[2, 3] = np.inf
    with pytest.raises(ValueError, match=r"W contains NaN or Inf: W\[2, 3\]"):
        als_basis(D, 2, W)
    W[2, 3] = -1.0
    with pytest.raises(ValueError, match=r"non-negative: W\[2, 3\]"):
        als_basis(D, 2, W)
    with pytest.raises(ValueError, match="W has shape"):
        als_basis(D, 2, np.ones((20, 29)))
    with pytest.raises(ValueError, match="unknown backend"):
        als_basis(D, 2, backend="jax")
    with pytest.raises(ValueError, match="numpy backend runs on the CPU"):
        als_basis(D, 2, backend="numpy", device="cuda")
    with pytest.raises(ValueError, match=r"bases\[1\] has 19 rows"):
        merge_als_bases([(np.eye(20, 2), np.ones(2)), (np.eye(19, 2), np.ones(2))], 2)
    with pytest.raises(ValueError, match=r"k must be .* \[1, 4\]"):
        merge_als_bases([(np.eye(20, 2), np.ones(2))] * 2, 5)
    with pytest.raises(ValueError, match=r"bases\[0\].U contains NaN"):
        merge_als_bases([(np.full((3, 2), np.nan), np.ones(2))], 1)


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_pair_products_equal_the_gathered_rows(backend):
    from btfcore.model import als

    ops = als._ops(backend, "cpu", np.dtype(np.float32))
    X = ops.asarray(np.random.default_rng(4).standard_normal((37, 5), dtype=np.float32)).T   # a transposed view
    iu, ju = np.triu_indices(5)
    expected = ops.numpy(X)[iu] * ops.numpy(X)[ju]
    np.testing.assert_array_equal(ops.numpy(als._pair_products(ops, X)), expected)
