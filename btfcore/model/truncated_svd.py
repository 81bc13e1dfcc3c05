"""Truncated SVD of a BTF matrix streamed over column blocks: Gram route, randomized, EM-PCA.

The per-material bases of the model database (stage 8, docs/architecture.md,
"Stages"; paper 1 (den Brok et al.), §4.1) are the leading left singular vectors ``U`` and values
``sigma`` of ``B`` (``(n_lv, n_tx)``, rows light/view pairs). Three methods
read ``B`` as column blocks, never whole, and accumulate in float64:

* ``'gram'``: :math:`G = \\sum_j B_j B_j^T` and its top-k eigenpairs. Exact to
  float64 rounding and one pass, but ``G`` takes :math:`8 n_{lv}^2` bytes and
  the pass costs :math:`n_{lv}^2 n_{tx} / 2` multiply-adds (in float64).
* ``'randomized'``: Halko et al.'s range finder with ``oversample`` extra
  vectors (default ``max(10, 5 k // 8)``) and ``n_iter`` power iterations
  (default 3), re-orthonormalised every pass
  (docs/architecture.md, "Pitfalls": plain power iterations lose accuracy in
  float32), ending in the Nyström step of the Gram matrix ([4]_) in place of Alg. 4.4's last
  product: ``n_iter + 1`` passes, ``2 n_iter + 1`` products.
* ``'empca'``: :func:`btfcore.model.empca.empca`, iterated to a tolerance.

``'auto'`` picks ``'gram'`` when ``G`` fits ``memory_bytes`` and its pass costs
no more arithmetic than the randomized passes, else ``'randomized'``
(:func:`choose_method`).

References
----------
.. [1] N. Halko, P.-G. Martinsson and J. A. Tropp, "Finding structure with
   randomness: probabilistic algorithms for constructing approximate matrix
   decompositions", SIAM Review 53(2), 2011, Alg. 4.4 and 5.1.
.. [2] S. Roweis, "EM algorithms for PCA and SPCA", NIPS 10, 1998.
.. [3] The thesis, App. paper 1 (den Brok et al.), §4.1.
.. [4] J. A. Tropp, A. Yurtsever, M. Udell and V. Cevher, "Fixed-rank
   approximation of a positive-semidefinite matrix from streaming data",
   NeurIPS 2017, Alg. 3 (the shifted Nyström step); Halko et al. [1]_, §5.4.
"""

from __future__ import annotations

import numpy as np
from scipy import linalg

from btfcore.model._lowrank import RANK_RTOL, Blocks, TruncatedSVD, as_block_source, check_int, check_k, check_rank, \
    fix_signs, for_each_block
from btfcore.model.empca import block_power_iteration, check_iteration_args, empca

__all__ = ["METHODS", "TruncatedSVD", "choose_method", "column_blocks", "default_oversample", "truncated_svd"]

#: Methods of :func:`truncated_svd`.
METHODS: tuple[str, ...] = ("auto", "gram", "randomized", "empca")


def column_blocks(B: np.ndarray, width: int) -> list[np.ndarray]:
    """Split an in-memory ``(n_lv, n_tx)`` matrix into column blocks (views) of ``width`` columns."""
    check_int(width, "width")
    return [B[:, i:i + width] for i in range(0, B.shape[1], width)]


def default_oversample(k: int) -> int:
    """Default oversampling of 'randomized': ``max(10, 5 k // 8)``.

    BTF spectra end in a slowly decaying noise floor, where the range finder's
    accuracy depends on :math:`\\sigma_{k+p}/\\sigma_k` more than on the number of
    passes: on a 26,136 x 8,192 float32 low-rank + noise matrix with k = 256,
    p = 64 with q = 3 (5 passes) gave 6e-5 excess error where p = 10 with
    q = 4 (6 passes, the same arithmetic) gave 8e-4. At the thesis' scale
    (26,136 x 49,152, power-law spectrum i^-0.75, benchmarks/bench_model_svd.py)
    p = 64, q = 3 gave 0.110 % excess error, just over issue 4's 0.1 % bar,
    and p = 128, q = 3 gave 0.021 % in 71-77 s: hence k // 2. (Those runs
    made 5 passes and ended in Rayleigh-Ritz; with the Nyström end the same
    q = 3, p = 128 made 4 passes at 0.0214 %, 57 s on a 206 GFLOP/s host.)
    Since the first pass forms ``B Omega`` (one product instead of two), q = 3 makes 7 products: with
    p = 128 at 0.045 % in 43.6 s, with p = 160 (5 k // 8) at 0.021 % in 46.5 s, so 5 k // 8 keeps the
    accuracy for 8 % more arithmetic than k // 2 (docs/benchmarks.md, 2026-12-05 09:17). With a flat
    noise floor under the spectrum, as BTFs have, power iterations gain more than oversampling: at
    equal arithmetic q = 2 with twice the oversampling had 2-3x the excess error of q = 3
    (docs/decisions.md, "Randomized basis: the first pass sketches B Omega").
    """
    return max(10, 5 * k // 8)


def choose_method(n_lv: int, k: int, *, memory_bytes: int, oversample: int | None = None, n_iter: int = 3) -> str:
    """The rule of ``method='auto'``: ``'gram'`` or ``'randomized'``.

    ``'gram'`` when :math:`8 n_{lv}^2 \\le` ``memory_bytes`` (the float64 Gram
    matrix) and :math:`n_{lv} \\le (2 q + 1) l`, ``l = k + oversample``,
    ``q = n_iter``: its one float64 pass of :math:`n_{lv}^2 n_{tx} / 2`
    multiply-adds (a symmetric rank-k update, at about half the float32
    rate) then costs no more than the randomized method's :math:`2 q + 1`
    products of :math:`n_{lv} n_{tx} l` multiply-adds each. Otherwise ``'randomized'`` (predictable cost, unlike EM-PCA's
    data-dependent number of passes). For the thesis' dome (26,136 rows,
    k = 256) this is randomized; for the tiny test dome (192 rows), gram.
    """
    l = min(k + (default_oversample(k) if oversample is None else oversample), n_lv)
    return "gram" if 8 * n_lv**2 <= memory_bytes and n_lv <= (2 * n_iter + 1) * l else "randomized"


def truncated_svd(
    blocks: Blocks,
    n_lv: int,
    k: int,
    method: str = "auto",
    *,
    rows_id: str | None = None,
    seed: int = 0,
    rank_rtol: float = RANK_RTOL,
    memory_bytes: int = 2**31,
    oversample: int | None = None,
    n_iter: int = 3,
    tol: float = 1e-4,
    max_iter: int = 100,
    criterion: str = "angle",
) -> TruncatedSVD:
    """Leading ``k`` left singular vectors and values of ``B``, read as column blocks.

    Parameters
    ----------
    blocks : callable, list of (n_lv, m_j) ndarray or (n_lv, n_tx) ndarray
        The matrix ``B``: preferably a callable returning a fresh iterator
        over its column blocks on every call (one call per pass). Blocks may
        have any widths; float32 blocks stay float32 in the products of the
        iterative methods, all sums are float64.
    n_lv : int
        Rows of ``B`` (light/view pairs).
    k : int
        Basis vectors; at most ``min(n_lv, n_tx)`` and the numerical rank.
    method : {'auto', 'gram', 'randomized', 'empca'}
        See the module docstring; ``'auto'`` follows :func:`choose_method`.
    rows_id : str, optional
        Fingerprint of the light/view sampling, stored for merging.
    seed : int
        Seed of the random start ('randomized', 'empca').
    rank_rtol : float
        Singular values at or below ``rank_rtol * sigma_1`` count as zero.
    memory_bytes : int
        Memory the Gram matrix may take (``'auto'`` only).
    oversample : int, optional
        Extra vectors iterated beyond ``k``; default
        :func:`default_oversample` for 'randomized' and 'auto', 0 (Roweis'
        method) for 'empca'.
    n_iter : int
        Power iterations ``q`` of 'randomized': ``q + 1`` passes over the data.
    tol, max_iter, criterion :
        Convergence of 'empca' (:func:`btfcore.model.empca.empca`).

    Returns
    -------
    TruncatedSVD
        ``U`` (n_lv, k), ``sigma`` (k,), the ``method`` used (never
        'auto'), ``settings`` (every argument that shaped the result, as
        JSON-serialisable scalars), ``iterations`` (passes), ``change``,
        ``converged``, ``norm_sq`` and the property ``energy_captured``
        :math:`= \\sum \\sigma_i^2 / \\|B\\|_F^2`.

    Raises
    ------
    ValueError
        If ``k`` exceeds ``min(n_lv, n_tx)`` or the numerical rank found
        (names k, the shape and the rank), a block is malformed or holds
        NaN/Inf (names the block, the index and B's column), or an argument
        is out of range.

    Notes
    -----
    Gram route: :math:`G = B B^T = \\sum_j B_j B_j^T` (float64 products),
    :math:`G = U \\Lambda U^T`, :math:`\\sigma = \\sqrt{\\lambda}`; eigenvectors
    have errors about :math:`\\epsilon \\lambda_1 / \\text{gap}`, and
    singular values below about :math:`\\sqrt{n_{lv}\\epsilon}\\,\\sigma_1` are
    not resolved.

    Randomized: Halko et al.'s Alg. 4.4 (randomized subspace iteration). The first pass forms
    :math:`Y = B \\Omega` (one product; :math:`\\Omega` a Gaussian :math:`(n_{tx}, l)` drawn row by
    row in column order, so that the result does not depend on how the columns are blocked); each
    later pass forms :math:`Y = B (B^T Q)` block by block from :math:`Q = \\mathrm{orth}(Y)`. The
    last pass' ``Q`` and ``Y`` give U and sigma by the Nyström approximation
    :math:`Y (Q^T Y)^{-1} Y^T` of ``G`` (Halko et al. §5.4, shifted as in [4]_,
    :func:`btfcore.model._lowrank.nystrom`): the left singular vectors of ``B``
    restricted to the right subspace :math:`B^T Q`, half a power iteration
    beyond the Rayleigh-Ritz basis of span(Q), in place of Alg. 4.4's final product
    :math:`Q^T B`. With ``n_iter`` = q that is ``q + 1`` passes and ``2q + 1`` products
    (``n_iter`` = 0: one pass from a Gaussian :math:`(n_{lv}, l)` start, two products). This is
    :func:`btfcore.model.empca.block_power_iteration` with a fixed pass count and
    ``final='nystrom'``.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    check_int(n_iter, "n_iter", 0)
    check_int(memory_bytes, "memory_bytes", 0)
    p = default_oversample(k) if oversample is None else oversample
    n_basis = check_iteration_args(n_lv, k, p, tol)
    used = choose_method(n_lv, k, memory_bytes=memory_bytes, oversample=p, n_iter=n_iter) \
        if method == "auto" else method
    source = as_block_source(blocks)
    settings = dict(method=used, requested=method, k=int(k), n_lv=int(n_lv), seed=int(seed),
                    rank_rtol=float(rank_rtol), memory_bytes=int(memory_bytes))
    if used == "empca":
        res = empca(source, n_lv, k, tol=tol, max_iter=max_iter, criterion=criterion, oversample=oversample or 0,
                    seed=seed, rank_rtol=rank_rtol, rows_id=rows_id)
        return TruncatedSVD(res.U, res.sigma, used, {**res.settings, **settings}, res.iterations, res.change,
                            res.converged, res.norm_sq, rows_id)
    if used == "randomized":
        U, sigma, it, change, _, norm_sq = block_power_iteration(
            source, n_lv, k, n_basis, max_iter=n_iter + 1, tol=None, seed=seed, rank_rtol=rank_rtol,
            final="nystrom")
        settings.update(oversample=int(p), n_iter=int(n_iter))
        return TruncatedSVD(U, sigma, used, settings, it, change, True, norm_sq, rows_id)
    U, sigma, norm_sq = _gram(source, n_lv, k, rank_rtol)
    return TruncatedSVD(U, sigma, used, settings, 1, 0.0, True, norm_sq, rows_id)


def _gram(source, n_lv: int, k: int, rank_rtol: float) -> tuple[np.ndarray, np.ndarray, float]:
    """The Gram route: one pass accumulating ``G = sum_j B_j B_j^T`` in float64, then eigh."""
    G = np.zeros((n_lv, n_lv))

    def visit(b: np.ndarray) -> None:
        b64 = b.astype(np.float64, copy=False)
        G[...] += b64 @ b64.T                                        # G = sum_j B_j B_j^T (syrk)

    norm_sq, n_cols = for_each_block(source, n_lv, visit)
    check_k(k, n_lv, n_cols)
    lam, W = linalg.eigh(G, subset_by_index=[n_lv - k, n_lv - 1], overwrite_a=True)   # B B^T = U Sigma^2 U^T
    sigma = np.sqrt(np.maximum(lam[::-1], 0.0))
    check_rank(sigma, k, f"B ({n_lv}, {n_cols})", rank_rtol)
    return fix_signs(W[:, ::-1]), sigma, norm_sq
