"""Solve operators for a general measurement matrix ``G`` (a plan capture's ``G B``).

:func:`btfcore.acquisition.reconstruct.solve_operator` describes a measurement by a row
selection and one pattern matrix shared by every view. A capture executed from
an acquisition plan has a measurement matrix ``G`` ``(n_meas, n_lv)`` of any
shape: per turntable position its own patterns (bootstrapping quadrants,
S-matrices over the LEDs selected there), a subset of cameras, single lights
and patterns mixed. This module builds the same :class:`SolveOperator` from
``G`` itself, with :math:`A = G U`:

``'pinv'``
    :math:`R = A^\\dagger` (paper 1, eq. (3)); single-light rows only.
``'tikhonov'``
    :math:`\\arg\\min_C \\|A C - y\\|^2 + \\|\\lambda \\Sigma^{-1} C\\|^2`
    (paper 4, eq. (10)); single-light rows only.
``'direct'``
    The same solve for multiplexed (or mixed) rows, never demultiplexed
    (paper 4, eq. (10) with :math:`S M` replaced by ``G``); ``lam`` defaults to 0.
``'projection'``, ``'thresholded'``
    Demultiplex with :math:`G^\\dagger` (``G`` must have full column rank),
    then VMV §4.1's projection :math:`U U^T` or the 9th-decile thresholded
    fit, folded into one operator :math:`R\\, G^\\dagger`.

References
----------
.. [1] The thesis, App. paper 1 (den Brok et al.), eq. (3); VMV paper §4.1;
   paper 4, eqs. (4), (10).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import DTypeLike
from scipy import sparse
from scipy.sparse.csgraph import connected_components

from btfcore.acquisition.reconstruct import (
    RECONSTRUCTION_METHODS,
    THRESHOLD_DECILE,
    SolveOperator,
    _as_basis,
    _as_lam,
    _as_sigma,
    _denoise_operator,
    _finish,
    _regularised_solve,
)

__all__ = ["as_sparse_G", "demultiplexing_matrix", "is_single_light", "measurement_solve_operator",
           "single_light_rows"]


def as_sparse_G(G) -> sparse.csr_matrix:
    """``G`` (dense or scipy.sparse) as a float64 CSR matrix without stored zeros.

    A dome's ``G`` is mostly zeros (a row measures one LED, or one pattern's
    LEDs, of one view), so every function here works on this form.
    """
    g = sparse.csr_matrix(G, dtype=np.float64)
    g.eliminate_zeros()
    g.sort_indices()
    return g


def _as_G(G, n_lv: int) -> sparse.csr_matrix:
    if not sparse.issparse(G) and np.ndim(G) != 2:
        raise ValueError(f"G has shape {np.shape(G)}; it must be (n_meas, {n_lv}): one row per measured texture, "
                         "one column per light/view pair of the basis")
    g = as_sparse_G(G)
    if g.shape[1] != n_lv or g.shape[0] == 0:
        raise ValueError(f"G has shape {g.shape}; it must be (n_meas, {n_lv}): one row per measured texture, one "
                         "column per light/view pair of the basis")
    bad = np.flatnonzero(~np.isfinite(g.data))
    if bad.size:
        row = int(np.searchsorted(g.indptr, bad[0], side="right") - 1)
        raise ValueError(f"G[{row}, {int(g.indices[bad[0]])}] = {float(g.data[bad[0]])!r}: G must be finite "
                         f"({bad.size} NaN/Inf values in it); fix or mask them first")
    empty = np.flatnonzero(g.getnnz(axis=1) == 0)
    if empty.size:
        raise ValueError(f"G row {int(empty[0])} is all zero: a measurement of nothing; drop the row")
    return g


def is_single_light(G) -> bool:
    """Whether every row of ``G`` (dense or sparse) measures one light/view pair with weight 1 (a sparse
    single-light capture)."""
    g = as_sparse_G(G)
    return bool(g.getnnz(axis=1).max(initial=0) == 1 and np.all(g.data == 1))


def single_light_rows(G) -> np.ndarray:
    """The light/view pair each row of a single-light ``G`` (dense or sparse) measures, ``(n_meas,)`` int64.

    Raises
    ------
    ValueError
        If a row mixes several pairs (a multiplexed row), naming it.
    """
    g = as_sparse_G(G)
    counts = g.getnnz(axis=1)
    off = np.repeat(np.arange(g.shape[0]), counts)[g.data != 1]                # rows with a weight other than 1
    bad = np.flatnonzero((counts != 1) | np.isin(np.arange(g.shape[0]), off))
    if bad.size:
        r = int(bad[0])
        raise ValueError(f"G row {r} measures {int(counts[r])} light/view pairs with weights "
                         f"{np.unique(g[r].data).tolist()}: not a single-light measurement")
    return g.indices.astype(np.int64)


def _times_basis(g: sparse.csr_matrix, u: np.ndarray) -> np.ndarray:
    """``G U`` through the sparse ``G``: a dome's row measures one LED or one pattern's LEDs of one view, so
    the product costs ``nnz(G) k`` instead of ``n_meas n_lv k`` (at the thesis' scale 0.2 GFLOP, not 235)."""
    return np.asarray(g @ u)


def demultiplexing_matrix(G: np.ndarray | sparse.spmatrix) -> sparse.csr_matrix:
    """:math:`G^\\dagger` as a sparse matrix, block by block.

    Parameters
    ----------
    G : (n_meas, n_lv) array_like
        Measurement matrix with full column rank (every light/view pair
        recoverable: a full single-light or S-matrix capture).

    Returns
    -------
    P : (n_lv, n_meas) scipy.sparse.csr_matrix
        :math:`G^\\dagger`, computed on each connected block of ``G`` (the rows
        and columns that share non-zeros, e.g. one view's patterns and LEDs),
        so that a dome's ``G`` costs one small pseudo-inverse per view.

    Raises
    ------
    ValueError
        If a block has fewer rows than columns or is rank-deficient, naming
        its first light/view column: the measurement does not determine it.
    """
    g = as_sparse_G(G)                                                   # a dome's G is mostly zeros
    n_meas, n_lv = g.shape
    nz = g.astype(bool).astype(np.int8)
    graph = sparse.bmat([[None, nz], [nz.T, None]], format="csr")      # rows and columns as one graph
    n_comp, label = connected_components(graph, directed=False)
    order = np.argsort(label, kind="stable")
    starts = np.searchsorted(label[order], np.arange(n_comp + 1))
    out_rows, out_cols, out_vals = [], [], []
    for comp in range(n_comp):
        members = order[starts[comp]:starts[comp + 1]]
        r, c = members[members < n_meas], members[members >= n_meas] - n_meas
        if not c.size:
            continue
        block = g[r][:, c].toarray()
        if r.size < c.size or np.linalg.matrix_rank(block) < c.size:
            raise ValueError(
                f"G does not determine light/view pair {int(c[0])} (its block: {r.size} measured rows for {c.size} "
                f"pairs, rank {np.linalg.matrix_rank(block) if r.size else 0}): it cannot be demultiplexed; use "
                "method 'direct' (or 'pinv'/'tikhonov'), which fit the basis to the measurement as it is")
        out_rows.append(np.repeat(c, r.size))
        out_cols.append(np.tile(r, c.size))
        out_vals.append(np.linalg.pinv(block).ravel())                   # block of G^+ (c x r)
    if not out_rows:
        return sparse.csr_matrix((n_lv, n_meas))
    return sparse.csr_matrix((np.concatenate(out_vals), (np.concatenate(out_rows), np.concatenate(out_cols))),
                             shape=(n_lv, n_meas))


def measurement_solve_operator(
    U: np.ndarray,
    G: np.ndarray,
    sigma: np.ndarray | None = None,
    *,
    method: str = "pinv",
    lam: float | None = None,
    variance: np.ndarray | None = None,
    decile: float = THRESHOLD_DECILE,
    fused: bool | None = None,
    dtype: DTypeLike = np.float32,
) -> SolveOperator:
    """Reconstruction operator of a basis for a general measurement matrix.

    Parameters
    ----------
    U : (n_lv, k) array_like
        Basis; its rows are the columns of ``G``.
    G : (n_meas, n_lv) array_like or scipy.sparse matrix
        Measurement matrix: measured textures ``y = G B`` (used as a sparse
        matrix: a dome's rows have one or a pattern's few non-zeros).
    sigma : (k,) array_like, optional
        Singular values of ``U``; needed when ``lam > 0``.
    method : {'pinv', 'tikhonov', 'direct', 'projection', 'thresholded'}
        See the module docstring.
    lam : float, optional
        :math:`\\lambda` of :math:`\\lambda \\Sigma^{-1}` (``'tikhonov'`` needs
        it, ``'direct'`` defaults to 0).
    variance : (n_lv,) array_like, optional
        ``'thresholded'``: per-texture variance of the demultiplexed BTF
        :math:`G^\\dagger y` (:func:`btfcore.acquisition.reconstruct.texture_variance`).
    decile : float
        ``'thresholded'``: rows above this decile are left out.
    fused : bool, optional
        As :func:`btfcore.acquisition.reconstruct.solve_operator`.
    dtype : float32 or float64

    Returns
    -------
    operator : SolveOperator
        :func:`btfcore.acquisition.reconstruct.apply` maps measured ``(n_meas, m)`` to ``(n_lv, m)``.

    Raises
    ------
    ValueError
        Unknown method; multiplexed rows with ``'pinv'``/``'tikhonov'``
        (use ``'direct'``); fewer measured rows than basis vectors without
        regularisation (suggests ``'tikhonov'``); a rank-deficient ``G U``;
        a ``G`` that cannot be demultiplexed for ``'projection'``/``'thresholded'``.

    Notes
    -----
    With :math:`A = G U`, ``'pinv'``, ``'tikhonov'`` and ``'direct'`` are the
    regularised solve of :func:`btfcore.acquisition.reconstruct.solve_operator`
    (:math:`C = \\Sigma W \\operatorname{diag}(s/(s^2+\\lambda^2)) Q^T y` with
    :math:`A\\Sigma = Q S W^T`; :math:`A^\\dagger` for :math:`\\lambda = 0`).
    For ``G = S (I \\otimes M)`` they equal ``solve_operator(U, sigma,
    rows=..., patterns=M)``.
    """
    if method not in RECONSTRUCTION_METHODS:
        raise ValueError(f"unknown reconstruction method {method!r}; choose one of {RECONSTRUCTION_METHODS}")
    u = _as_basis(U)
    n_lv, k = u.shape
    g = _as_G(G, n_lv)
    lam_v = _as_lam(lam, method)
    s = _as_sigma(sigma, k) if lam_v > 0 else None
    kw: dict = {"method": method, "lam": lam_v}
    if method in ("pinv", "tikhonov"):
        if not is_single_light(g):
            raise ValueError(f"method={method!r} is for single-light (sparse) measurements and G has multiplexed "
                             "rows; use method='direct' (paper 4, eq. 10), which fits the basis to the multiplexed "
                             "measurement without demultiplexing")
        hint = (f"measure at least k={k} rows, use fewer basis vectors, or use method='tikhonov' with lam > 0 "
                "(e.g. --method tikhonov --lam 0.01 for an ALS basis, 40 for a log basis)")
        R, cond = _regularised_solve(_times_basis(g, u), s, lam_v, "G U", hint)
        return _finish(R, u, fused, dtype, condition=cond, **kw)
    if method == "direct":
        hint = f"measure at least k={k} rows, use fewer basis vectors, or regularise with lam > 0 (paper 4: 0.01)"
        R, cond = _regularised_solve(_times_basis(g, u), s, lam_v, "G U", hint)
        return _finish(R, u, fused, dtype, condition=cond, **kw)
    P = demultiplexing_matrix(g)                                      # (n_lv, n_meas): B_demux = G^+ y
    R, dropped, cond, n_fallback = _denoise_operator(u, method, variance, decile)
    if cond is not None:
        kw["condition"] = cond
    if n_fallback:
        kw["fallback"] = n_fallback
    R = (P.T @ R.T).T                                                 # de-noise G^+ y: R G^+
    return _finish(np.ascontiguousarray(R), u, fused, dtype, dropped=dropped, **kw)
