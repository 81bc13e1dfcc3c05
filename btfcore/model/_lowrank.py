"""Shared pieces of the low-rank modules: the result type, block streaming and validation.

Used by :mod:`btfcore.model.empca`, :mod:`btfcore.model.truncated_svd` and
:mod:`btfcore.model.eigenspace_merging`. A BTF matrix ``B`` is ``(n_lv, n_tx)``
(docs/architecture.md, "Matrix convention") and reaches these modules as a *block source*: a callable that
returns a fresh iterator over column blocks ``B[:, cols_j]`` of shape
``(n_lv, m_j)`` on every call, so that iterative methods can make several
passes without holding ``B`` (the tasks layer streams Zarr chunks through
it; btfcore itself never does I/O).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, Union

import numpy as np
from scipy import linalg

__all__ = ["BlockSource", "RankError", "TruncatedSVD"]

#: A re-iterable source of ``(n_lv, m_j)`` column blocks of ``B``.
BlockSource = Callable[[], Iterable[np.ndarray]]
#: What the public functions accept as blocks: a source, a list of blocks, or one matrix.
Blocks = Union[BlockSource, Sequence[np.ndarray], np.ndarray]

#: Default relative threshold below which a singular value counts as zero (see :func:`check_rank`).
RANK_RTOL = 1e-5


@dataclass(frozen=True)
class TruncatedSVD:
    """A rank-k left eigenspace model ``(U, sigma)`` of a BTF matrix ``B``.

    Attributes
    ----------
    U : (n_lv, k) ndarray of float64
        Orthonormal left singular vectors (the basis), columns ordered by
        decreasing ``sigma``; the sign of each column makes its entry of
        largest magnitude positive. Read-only.
    sigma : (k,) ndarray of float64
        Singular values, decreasing. Read-only.
    method : str
        ``'gram'``, ``'randomized'``, ``'empca'`` or ``'merge'``: what computed it.
    settings : dict
        Every parameter that determined the result (JSON-serialisable Python
        scalars), for the tasks layer to store beside ``U`` and ``sigma``.
    iterations : int
        Passes over the data (1 for the Gram route; merged models: 0).
    change : float
        The final convergence measure: the largest principal angle (radians)
        between the last two iterates' rank-k subspaces, or the change of
        their captured energy relative to the residual energy
        (``settings['criterion']``); 0.0 where the method is direct.
    converged : bool
        Whether ``change`` fell below the tolerance (always True for direct methods).
    norm_sq : float
        :math:`\\|B\\|_F^2`, accumulated in the same passes (for merged models
        the sum over the inputs).
    rows_id : str or None
        Optional fingerprint of the light/view sampling of ``B``'s rows;
        merging refuses models whose ids differ.
    """

    U: np.ndarray
    sigma: np.ndarray
    method: str
    settings: dict[str, Any] = field(default_factory=dict)
    iterations: int = 1
    change: float = 0.0
    converged: bool = True
    norm_sq: float = 0.0
    rows_id: str | None = None

    def __post_init__(self) -> None:
        for a in (self.U, self.sigma):
            a.setflags(write=False)

    @property
    def k(self) -> int:
        """Number of basis vectors."""
        return int(self.sigma.size)

    @property
    def energy_captured(self) -> float:
        """:math:`\\sum_i \\sigma_i^2 / \\|B\\|_F^2`, the fraction of the energy the basis captures."""
        return float(np.sum(self.sigma**2) / self.norm_sq) if self.norm_sq > 0 else 0.0


# --------------------------------------------------------------------------- validation


def check_finite(a: np.ndarray, name: str, col0: int | None = None) -> None:
    """Raise a ValueError naming the first NaN/Inf of ``a``; ``col0``: ``a`` is ``B[:, col0:]``, name B's entry too."""
    finite = np.isfinite(a)
    if not finite.all():
        idx = tuple(int(v) for v in np.argwhere(~finite)[0])
        where = "" if col0 is None else f", i.e. B[{idx[0]}, {col0 + idx[1]}]"
        raise ValueError(
            f"{name}{list(idx)} = {float(a[idx])!r}{where}: {name} must be finite "
            f"({int(a.size - finite.sum())} NaN/Inf values in it); fix or mask them first"
        )


def check_int(v: Any, name: str, minimum: int = 1) -> int:
    """Validate an integer argument ``>= minimum``."""
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {v!r}")
    return int(v)


def check_k(k: Any, n_lv: int, n_cols: int | None = None, what: str = "B") -> int:
    """Validate the number of basis vectors against ``min(n_lv, n_cols)`` of the matrix ``what``."""
    check_int(k, "k")
    limit = n_lv if n_cols is None else min(n_lv, n_cols)
    if k > limit:
        shape = f"({n_lv}, {'...' if n_cols is None else n_cols})"
        raise ValueError(f"k={k} exceeds min(rows, columns) = {limit} of {what} {shape}; pass k <= {limit}")
    return int(k)


class RankError(ValueError):
    """``k`` exceeds the numerical rank of the data; ``rank`` is the rank found (callers that chose
    ``k`` themselves, not the user, may retry with it)."""

    def __init__(self, message: str, k: int, rank: int) -> None:
        super().__init__(message)
        self.k, self.rank = k, rank


def check_rank(sigma: np.ndarray, k: int, shape: str, rank_rtol: float) -> None:
    """Refuse ``k`` above the numerical rank: the number of ``sigma`` above ``rank_rtol * sigma[0]``.

    ``sigma`` holds the leading singular values found (decreasing). A value
    at or below the threshold is numerically zero: float32 data holds no
    information there, and the Gram route resolves singular values only to
    about :math:`\\sqrt{n_{lv} \\epsilon}\\, \\sigma_1`.
    """
    rank = int(np.count_nonzero(sigma > rank_rtol * sigma[0])) if sigma.size and sigma[0] > 0 else 0
    if rank < k:
        raise RankError(
            f"k={k} exceeds the numerical rank {rank} of {shape} (singular values at or below "
            f"rank_rtol={rank_rtol:g} x sigma_1 count as zero); pass k <= {rank}", k, rank)


# --------------------------------------------------------------------------- streaming


def as_block_source(blocks: Blocks) -> BlockSource:
    """Normalise ``blocks`` to a callable returning a fresh iterator of column blocks."""
    if callable(blocks):
        return blocks
    if isinstance(blocks, np.ndarray):
        return lambda: (blocks,)
    if isinstance(blocks, (list, tuple)):
        return lambda: iter(blocks)
    raise ValueError(
        f"blocks must be a callable returning a fresh iterator of (n_lv, m) arrays on every call, "
        f"a list of such arrays or one array; got {type(blocks).__name__} (a generator can be read "
        f"only once: wrap it as `lambda: make_generator()`)"
    )


def _as_block(b: Any, j: int, n_lv: int) -> np.ndarray:
    b = np.asarray(b)
    if b.ndim != 2 or b.shape[0] != n_lv:
        raise ValueError(f"blocks[{j}] has shape {b.shape}: every block must be (n_lv={n_lv}, m)")
    if b.dtype.kind not in "biuf":
        raise ValueError(f"blocks[{j}] has dtype {b.dtype}: B must be real")
    return b if b.dtype in (np.float32, np.float64) else b.astype(np.float64)


def for_each_block(
    source: BlockSource, n_lv: int, visit: Callable[[np.ndarray], None], n_cols: int | None = None,
    norm: bool = True,
) -> tuple[float, int]:
    """One pass over the data: validate each block, call ``visit(block)``, return ``(||B||_F^2, n_tx)``.

    A NaN/Inf raises a ValueError naming the block, its index and B's column.
    ``n_cols`` (from an earlier pass) must match this pass' column count. ``norm=False`` (a later pass
    over blocks an earlier one validated) skips the norm and the NaN/Inf test and returns NaN for the norm.

    The norm is summed per row in the block's dtype and over rows in float64 (:func:`squared_norm`).
    """
    norm_sq, col = (0.0 if norm else float("nan")), 0
    for j, raw in enumerate(source()):
        b = _as_block(raw, j, n_lv)
        if norm:
            e = squared_norm(b)
            if not np.isfinite(e):
                check_finite(b, f"blocks[{j}]", col)
                raise ValueError(f"blocks[{j}] is too large: its squared norm overflows float64")
            norm_sq += e
        visit(b)
        col += b.shape[1]
    if col == 0 or (n_cols is not None and col != n_cols):
        raise ValueError(
            f"blocks gave {col} columns in this pass" + (f" but {n_cols} in the first" if n_cols else "")
            + ": the source must return a fresh iterator over the same non-empty blocks on every call"
        )
    return norm_sq, col


def squared_norm(b: np.ndarray) -> float:
    """:math:`\\|b\\|_F^2` of a float32 or float64 ``(n, m)`` block: row sums in its dtype, their sum in float64.

    Float32 row sums of a 26,136 x 4,992 Gaussian band were 2.5e-8 off the float64 sum (bound: ``m``
    times float32's epsilon); even where the basis captures 99.99 % of the energy, that moves the
    residual :math:`\\|B\\|^2 - \\sum \\sigma^2` by 2.5e-4 of itself. Converting the band to float64
    took 1.22 s instead of 0.27 s (docs/benchmarks.md, 2026-12-05). A row that overflows float32
    (entries above 1.8e19) is summed again in float64, so only a float64 overflow or a NaN/Inf gives a
    non-finite result.
    """
    rows = np.einsum("ij,ij->i", b, b)
    if not np.all(np.isfinite(rows)) and b.dtype != np.float64:
        rows = np.einsum("ij,ij->i", b, b, dtype=np.float64)
    return float(rows.sum(dtype=np.float64))


# --------------------------------------------------------------------------- small dense steps


def orthonormalise(S: np.ndarray) -> np.ndarray:
    """An orthonormal basis ``Q`` of span(``S``) (``(n, m)``, ``n >= m``, float64) by CholeskyQR2.

    Twice :math:`R = \\mathrm{chol}(S^T S)`, :math:`S \\leftarrow S R^{-1}`: GEMMs and a small
    triangular inverse, where LAPACK's Householder QR of a tall, narrow matrix runs far below the GEMM
    rate (1.13 s against 0.49 s with the check below, 26,136 x 384 on 2 cores). The second pass restores
    orthogonality to rounding while ``cond(S) < 1/sqrt(eps)`` (Fukaya et al., 2014); if a Cholesky
    factorisation fails or ``||Q^T Q - I||`` stays above ``1e-10``, Householder QR is used instead.
    Column signs may differ from :func:`numpy.linalg.qr`'s.
    """
    Q = S
    try:
        for _ in range(2):
            R = np.linalg.cholesky(Q.T @ Q).T                       # Q^T Q = R^T R
            Q = Q @ linalg.solve_triangular(R, np.eye(R.shape[0]))  # Q R^-1 as one GEMM
    except np.linalg.LinAlgError:
        return np.linalg.qr(S)[0]
    if not np.all(np.isfinite(Q)) or np.abs(Q.T @ Q - np.eye(Q.shape[1])).max() > 1e-10:
        return np.linalg.qr(S)[0]
    return Q


def fix_signs(U: np.ndarray) -> np.ndarray:
    """Flip columns so that each one's entry of largest magnitude is positive (a deterministic sign)."""
    s = np.sign(U[np.argmax(np.abs(U), axis=0), np.arange(U.shape[1])])
    return U * np.where(s == 0, 1.0, s)


def largest_angle(U: np.ndarray, V: np.ndarray) -> float:
    """Largest principal angle (radians) between the spans of two orthonormal bases of equal size.

    ``arccos`` of the smallest singular value of ``U^T V``: one small GEMM and
    SVD, resolving angles down to about ``sqrt(eps)`` = 1.5e-8 rad.
    """
    c = np.linalg.svd(U.T @ V, compute_uv=False)
    return float(np.arccos(min(float(c[-1]), 1.0)))


def nystrom(C: np.ndarray, S: np.ndarray, eps: float, k: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Eigenpairs of the Nyström approximation of :math:`G = B B^T` from ``C`` and ``S = G C``.

    With ``C`` ``(n, l)`` orthonormal, :math:`\\hat G = S (C^T S)^{-1} S^T` (Halko et al. 2011, §5.4) is
    the best PSD approximation of ``G`` that ``S`` determines. Its eigenvectors are the left singular
    vectors of :math:`S (C^T S)^{-1/2}`, i.e. of :math:`B Q_W` with :math:`Q_W` an orthonormal basis of
    :math:`W = B^T C`, whose Gram matrix is :math:`W^T W = C^T S`: the rank-``l`` approximation whose
    right subspace is ``B^T C``, half a power iteration beyond the Rayleigh-Ritz basis of span(C) (its
    vectors are :math:`B B^T C`, not ``C``), with no further pass over ``B``.

    Stabilised as in Tropp et al. 2017 (Alg. 3): a shift :math:`\\nu =` ``eps`` :math:`\\|S\\|_F` is
    added (:math:`S + \\nu C`) so that the Cholesky factor of :math:`C^T S + \\nu I` exists although
    ``S`` carries rounding (float32 products), and subtracted from the eigenvalues again; directions at
    the rounding level are damped instead of amplified. Falls back to :func:`ritz` if the Cholesky
    factorisation fails anyway.

    The leading ``k`` eigenvectors are :math:`E W_k \\Lambda_k^{-1/2}` from the eigenpairs of the small
    :math:`E^T E` (``E`` as in the code): 0.25 s against 0.82 s for LAPACK's SVD of a 26,136 x 416 ``E``
    on 2 cores. Its orthogonality error grows like :math:`\\epsilon \\lambda_1 / \\lambda_k`, so the
    result is checked (:math:`\\|U_k^T U_k - I\\|_{max} \\le 10^{-10}`, as :func:`orthonormalise` is)
    and the SVD of ``E`` used where the check fails (estimated: eigenvalues below about 1e-6 of the
    largest at ``k``).

    Returns
    -------
    U : (n, k) ndarray
        Eigenvectors of :math:`\\hat G`, decreasing (all ``l`` where ``k`` is None, and after the
        fallback to :func:`ritz`).
    sigma : (l,) ndarray
        :math:`\\sqrt{\\lambda}` of its eigenvalues, decreasing.
    """
    nu = eps * float(np.linalg.norm(S))
    Y = S + nu * C
    H = C.T @ Y
    try:
        L = np.linalg.cholesky((H + H.T) / 2)                      # C^T Y = L L^T
    except np.linalg.LinAlgError:
        return ritz(C, C.T @ S)
    E = linalg.solve_triangular(L, Y.T, lower=True).T              # Y L^-T: E E^T = Y (C^T Y)^-1 Y^T
    kk = E.shape[1] if k is None else min(k, E.shape[1])
    lam, W = linalg.eigh(E.T @ E)                                  # E = U diag(sqrt(lam)) W^T
    lam, W = lam[::-1], W[:, ::-1]
    if lam[kk - 1] > 0:
        U = E @ (W[:, :kk] / np.sqrt(lam[:kk]))
        if np.abs(U.T @ U - np.eye(kk)).max() <= 1e-10:
            return U, np.sqrt(np.maximum(lam - nu, 0.0))
    U, s, _ = np.linalg.svd(E, full_matrices=False)
    return U[:, :kk], np.sqrt(np.maximum(s ** 2 - nu, 0.0))


def ritz(Q: np.ndarray, H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rayleigh-Ritz on span(Q): ``H = Q^T (B B^T) Q`` -> all Ritz vectors ``Q W`` and ``sigma`` (decreasing)."""
    lam, W = linalg.eigh((H + H.T) / 2)
    order = np.argsort(lam)[::-1]
    return Q @ W[:, order], np.sqrt(np.maximum(lam[order], 0.0))
