"""EM-PCA: a truncated SVD of a BTF matrix streamed over its column blocks (Roweis 1998).

The thesis fits each material's BTF with EM-PCA before merging eigenspaces
(paper 1, §4.1: "we first use EM-PCA to obtain approximate truncated SVDs of
the single BTFs"). Roweis' zero-noise EM algorithm alternates, for
``B = [B_1, ..., B_J]`` of shape ``(n_lv, n_tx)`` and a basis ``C`` of
shape ``(n_lv, l)``,

.. math::

   X_j = (C^T C)^{-1} C^T B_j \\quad \\text{(E-step)}, \\qquad
   C \\leftarrow \\Big(\\sum_j B_j X_j^T\\Big)\\Big(\\sum_j X_j X_j^T\\Big)^{-1} \\quad \\text{(M-step)},

one pass over the data per iteration, holding only ``(n_lv, l)`` and
``(l, l)`` accumulators. Since :math:`\\sum_j B_j X_j^T = B B^T C (C^T C)^{-1}`,
each iteration maps span(C) to span(B B^T C): EM-PCA is block power
iteration on the Gram matrix, and :func:`block_power_iteration` implements it
once for this module and the randomized SVD of :mod:`btfcore.model.truncated_svd`.

References
----------
.. [1] S. Roweis, "EM algorithms for PCA and SPCA", NIPS 10, 1998.
.. [2] The thesis, App. paper 1 (den Brok et al.) §4.1.1: 200 eigen-ABRDFs
   for log Y and 100 each for U/Y and V/Y.
.. [3] N. Halko, P.-G. Martinsson and J. A. Tropp, "Finding structure with
   randomness", SIAM Review 53(2), 2011, §4.5 (subspace iteration) and
   §5.5 (Rayleigh-Ritz).
"""

from __future__ import annotations

import warnings

import numpy as np

from btfcore import BtfWarning
from btfcore.model._lowrank import RANK_RTOL, Blocks, BlockSource, TruncatedSVD, as_block_source, check_int, check_k, \
    check_rank, fix_signs, for_each_block, largest_angle, nystrom, orthonormalise, ritz

__all__ = ["CRITERIA", "block_power_iteration", "check_iteration_args", "empca"]

#: Convergence criteria of :func:`empca`.
CRITERIA: tuple[str, ...] = ("angle", "energy")
#: What :func:`block_power_iteration` returns from its last pass.
FINAL_STEPS: tuple[str, ...] = ("ritz", "nystrom")


def block_power_iteration(
    source: BlockSource,
    n_lv: int,
    k: int,
    n_basis: int,
    *,
    max_iter: int,
    tol: float | None,
    criterion: str = "angle",
    seed: int = 0,
    rank_rtol: float = RANK_RTOL,
    final: str = "ritz",
) -> tuple[np.ndarray, np.ndarray, int, float, bool, float]:
    """EM-PCA / subspace iteration with ``n_basis >= k`` vectors and a Rayleigh-Ritz step per pass.

    Parameters
    ----------
    source : callable
        Returns a fresh iterator over the ``(n_lv, m_j)`` column blocks of ``B``.
    n_lv, k, n_basis : int
        Rows of ``B``, basis vectors kept and basis vectors iterated.
    max_iter : int
        Most passes over the data.
    tol : float or None
        Stop when the change (see ``criterion``) falls below it; None runs
        exactly ``max_iter`` passes.
    criterion : {'angle', 'energy'}
        'angle': the largest principal angle (radians) between the rank-k
        Ritz subspaces of two successive passes; 'energy': the change of
        their captured energy :math:`E = \\sum_{i \\le k} \\sigma_i^2`
        relative to the residual energy :math:`\\|B\\|_F^2 - E` (relative to
        E itself it would stop far too early on data whose basis captures
        99.99% of the energy, as BTFs do).
    seed : int
        Seed of the Gaussian start: ``C`` ``(n_lv, n_basis)``, or, with ``tol=None`` and
        ``max_iter > 1``, :math:`\\Omega` ``(n_tx, n_basis)`` (see Notes).
    rank_rtol : float
        Singular values at or below ``rank_rtol * sigma_1`` count as zero.
    final : {'ritz', 'nystrom'}
        The result: the Ritz basis of the last pass' ``C`` (EM-PCA), or the eigenvectors of the
        Nyström approximation from that ``C`` and the last pass' ``S = B B^T C``
        (:func:`btfcore.model._lowrank.nystrom`: half a power iteration more for no pass; only with
        ``tol=None``, where the last pass is known in advance).

    Returns
    -------
    U : (n_lv, k) ndarray of float64
    sigma : (k,) ndarray of float64
    iterations : int
        Passes made.
    change : float
        The last change (inf after a single pass).
    converged : bool
        ``change < tol`` (True when ``tol`` is None).
    norm_sq : float
        :math:`\\|B\\|_F^2`.

    Raises
    ------
    ValueError
        If ``k`` exceeds ``min(n_lv, n_tx)`` or the numerical rank found, or a block is bad.

    Notes
    -----
    Each pass computes, with ``C`` orthonormal (so :math:`C^T C = I`), the
    E-step :math:`X_j = C^T B_j` and the M-step sums
    :math:`S = \\sum_j B_j X_j^T` and :math:`T = \\sum_j X_j X_j^T = C^T S`
    (Roweis 1998) in float64, with the products in the blocks' dtype.
    :math:`T = C^T B B^T C` is the Rayleigh-Ritz matrix of span(C): its
    eigenpairs give the current estimates of U and sigma without an extra
    pass. The M-step's :math:`S T^{-1}` only mixes the columns of S, so the
    next C is the orthonormalised S (which also works when the data's rank
    is below ``n_basis``); re-orthonormalising every pass keeps float32
    products accurate (docs/architecture.md, "Pitfalls"). At convergence the result is the Ritz
    basis of the last pass' C.

    A fixed pass count (``tol=None``, ``max_iter > 1``) starts as Halko et al.'s Alg. 4.4 does: pass 1
    forms :math:`S = B \\Omega` (one product, no Ritz step; :math:`\\Omega` drawn block by block in
    column order, the same however the columns are blocked), where a start from ``C`` costs two
    (docs/decisions.md, "the randomized basis starts from B Omega").
    """
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {CRITERIA}, got {criterion!r}")
    if final not in FINAL_STEPS or (final == "nystrom" and tol is not None):
        raise ValueError(f"final must be one of {FINAL_STEPS} ('nystrom' with tol=None), got {final!r}")
    eps = float(np.finfo(np.float64).eps)                         # of the products: float32 if a block is
    rng = np.random.default_rng(seed)
    # a fixed pass count that has a later pass starts from S = B Omega (one product), else from C
    C = None if tol is None and max_iter > 1 else orthonormalise(rng.standard_normal((n_lv, n_basis)))
    n_cols, prev, change, it = None, None, np.inf, 0
    S = np.empty((n_lv, n_basis))
    products: dict[np.dtype, np.ndarray] = {}
    for it in range(1, max_iter + 1):
        pass_norm_sq, n_cols, pass_eps = _accumulate(source, n_lv, C, rng, S, products, n_cols, it == 1)
        eps = max(eps, pass_eps)
        if it == 1:                                                 # the blocks are the same every pass
            check_k(k, n_lv, n_cols)
            norm_sq = pass_norm_sq
        if C is None or (tol is None and it < max_iter - 1):        # a fixed pass count: the result's change needs
            C = orthonormalise(S)                                   # only the last two passes' Ritz bases
            continue
        V, sigma = ritz(C, C.T @ S)                                 # T = sum_j X_j X_j^T = C^T S; Rayleigh-Ritz
        # compare only the Ritz vectors above the rank threshold: beyond the rank they are arbitrary
        kk = min(k, int(np.count_nonzero(sigma > rank_rtol * sigma[0]))) if sigma[0] > 0 else 0
        if prev is not None and kk > 0:
            if criterion == "angle":
                change = largest_angle(V[:, :kk], prev[0][:, :kk])
            else:                                                   # relative to the residual energy
                energy = float(np.sum(sigma[:k] ** 2))
                change = abs(energy - prev[1]) / max(norm_sq - energy, 1e-12 * norm_sq)
        prev = (V, float(np.sum(sigma[:k] ** 2)))
        if tol is not None and change < tol:
            break
        if it < max_iter:                                           # the last pass' S is not iterated on
            C = orthonormalise(S)                                   # M-step C = S T^-1, orthonormalised
    if final == "nystrom":                                          # from the last pass' C and S = B B^T C
        V, sigma = nystrom(C, S, eps, k)
    check_rank(sigma, k, f"B ({n_lv}, {n_cols})", rank_rtol)
    converged = tol is None or change < tol
    return fix_signs(V[:, :k]), sigma[:k].copy(), it, change, converged, norm_sq


def _accumulate(source: BlockSource, n_lv: int, C: np.ndarray | None, rng: np.random.Generator, S: np.ndarray,
                products: dict[np.dtype, np.ndarray], n_cols: int | None, norm: bool) -> tuple[float, int, float]:
    """One pass of :func:`block_power_iteration`: ``S = sum_j B_j X_j^T`` with ``X_j = C^T B_j``, or with
    ``X_j^T = Omega_j`` drawn from ``rng`` where ``C`` is None; ``(||B||^2, n_tx, eps of the products)``.

    ``products`` keeps one ``(n_lv, l)`` buffer per dtype for ``B_j X_j^T``: a fresh one per block
    costs its page faults."""
    S[...] = 0.0
    n_basis = S.shape[1]
    cast = {} if C is None else {np.dtype(np.float64): C, np.dtype(np.float32): C.astype(np.float32)}
    eps = 0.0

    def visit(b: np.ndarray) -> None:
        nonlocal eps
        eps = max(eps, float(np.finfo(b.dtype).eps))
        out = products.get(b.dtype)
        if out is None:
            out = products[b.dtype] = np.empty((n_lv, n_basis), b.dtype)
        if C is None:                                               # Omega_j: the rows of a Gaussian (n_tx, l) for
            X_T = rng.standard_normal((b.shape[1], n_basis), dtype=b.dtype)    # B_j's columns, in order
        else:
            X_T = (cast[b.dtype].T @ b).T                           # E-step X_j = (C^T C)^-1 C^T B_j  (Roweis §3)
        S[...] += np.matmul(b, X_T, out=out)                        # M-step numerator sum_j B_j X_j^T

    norm_sq, n_cols = for_each_block(source, n_lv, visit, n_cols, norm=norm)
    return norm_sq, n_cols, eps


def empca(
    blocks: Blocks,
    n_lv: int,
    k: int,
    *,
    tol: float = 1e-4,
    max_iter: int = 100,
    criterion: str = "angle",
    oversample: int = 0,
    seed: int = 0,
    rank_rtol: float = RANK_RTOL,
    rows_id: str | None = None,
) -> TruncatedSVD:
    """Truncated SVD ``B ~ U diag(sigma) V^T`` of one BTF matrix by EM-PCA, streamed over column blocks.

    Parameters
    ----------
    blocks : callable, list of (n_lv, m_j) ndarray or (n_lv, n_tx) ndarray
        ``B`` (rows light/view pairs, columns texels) in column blocks. A
        callable is called once per pass and must return a fresh iterator
        over the same blocks; float32 blocks are multiplied in float32 and
        the sums kept in float64.
    n_lv : int
        Rows of ``B``.
    k : int
        Basis vectors to return. This fits one matrix: per colour channel
        the caller loops, e.g. k = 200 for log Y and 100 each for U/Y and
        V/Y as in the thesis (paper 1, §4.1.1).
    tol : float
        Convergence tolerance on ``criterion``.
    max_iter : int
        Most passes over the data.
    criterion : {'angle', 'energy'}
        Largest principal angle (radians) between successive rank-k
        subspaces, or the change of their captured energy relative to the
        residual energy (see :func:`block_power_iteration`).
    oversample : int
        Extra basis vectors iterated beyond ``k`` (Roweis' method has 0);
        they speed up convergence when :math:`\\sigma_{k+1}/\\sigma_k` is near 1.
    seed : int
        Seed of the random start; results are deterministic given it.
    rank_rtol : float
        Singular values at or below ``rank_rtol * sigma_1`` count as zero
        when checking ``k`` against the numerical rank.
    rows_id : str, optional
        Fingerprint of the light/view sampling, stored for merging.

    Returns
    -------
    TruncatedSVD
        ``method='empca'``; ``iterations``, ``change`` and ``converged``
        report the convergence.

    Raises
    ------
    ValueError
        If ``k`` exceeds ``min(n_lv, n_tx)`` or the numerical rank found
        (names k, the shape and the rank), a block has the wrong shape or a
        NaN/Inf (names the block, the index and B's column), or a parameter
        is out of range.

    Warns
    -----
    BtfWarning
        If ``max_iter`` passes end before ``change < tol``.

    Notes
    -----
    See the module docstring and :func:`block_power_iteration`. The change
    between successive iterates underestimates the distance to the exact
    subspace by a factor of about :math:`1 - (\\sigma_{l+1}/\\sigma_k)^2`,
    ``l = k + oversample``.
    """
    n_basis = check_iteration_args(n_lv, k, oversample, tol)
    check_int(max_iter, "max_iter")
    U, sigma, it, change, converged, norm_sq = block_power_iteration(
        as_block_source(blocks), n_lv, k, n_basis, max_iter=max_iter, tol=tol, criterion=criterion,
        seed=seed, rank_rtol=rank_rtol)
    if not converged:
        warnings.warn(f"EM-PCA stopped after max_iter={max_iter} passes with {criterion} change "
                      f"{change:.3g} >= tol={tol:g}; raise max_iter or oversample", BtfWarning, stacklevel=2)
    settings = dict(method="empca", k=int(k), n_lv=int(n_lv), tol=float(tol), max_iter=int(max_iter),
                    criterion=criterion, oversample=int(oversample), seed=int(seed), rank_rtol=float(rank_rtol))
    return TruncatedSVD(U, sigma, "empca", settings, it, change, converged, norm_sq, rows_id)


def check_iteration_args(n_lv: int, k: int, oversample: int, tol: float | None) -> int:
    """Validate the arguments shared by the iterative methods; return ``min(k + oversample, n_lv)``."""
    check_k(k, check_int(n_lv, "n_lv"))
    if tol is not None and not tol > 0:
        raise ValueError(f"tol must be positive, got {tol!r}")
    return min(k + check_int(oversample, "oversample", 0), n_lv)
