"""Relative-error weighted bases by alternating least squares (paper 4, eqs. 5-9).

Paper 4 fits a rank-``c`` model :math:`D \\approx U V` of one material's BTF
``D`` (rows = light/view pairs, columns = texels x channels) under per-entry
weights ``W``, :math:`W = 1/D` entry-wise, so that the fit minimises the
*relative* error instead of the absolute one (eq. 5). There is no closed form,
so ``U`` and ``V`` are found by alternating least squares: with ``U`` fixed
every column of ``V`` is a small weighted least-squares problem (eq. 7), with
``V`` fixed every row of ``U`` is one (eq. 8). Per-material bases are merged
into one basis for the database by an SVD (eq. 9).

The per-texel and per-row solves are batched as matrix products: the normal
matrices of all texels, :math:`G_x = U^T \\operatorname{diag}(W_{:,x})^2 U`,
are one GEMM of :math:`(W^{\\odot 2})^T` against the products of pairs of
``U``'s columns, followed by one batched Cholesky solve (DESIGN §5: the GEMM
runs near the machine's peak; the small solves are the rest).

References
----------
.. [1] The thesis (``reference/000_07a399c75a6bdea8.txt``), paper 4
   ("sparse and multiplexed acquisition"), §4.1-4.2, eqs. (5)-(9), lines
   1300-1345.
.. [2] R. Ruiters, M. Rump and R. Klein, "Parallelized matrix factorization
   for fast BTF compression", EGPGV 2009 (relative-error weights).
.. [3] T. G. Kolda and B. W. Bader, "Tensor decompositions and
   applications", SIAM Review 51(3), 2009 (alternating least squares).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

__all__ = [
    "ALS_BACKENDS",
    "CHUNK_BYTES",
    "WEIGHT_FLOOR_FRACTION",
    "ALSResult",
    "als_basis",
    "merge_als_bases",
    "relative_error_weights",
]

#: Backends of :func:`als_basis`; ``'auto'`` is ``'torch'``.
ALS_BACKENDS: tuple[str, ...] = ("auto", "numpy", "torch")
#: Default weight floor of :func:`relative_error_weights`, as a fraction of the median non-zero ``|D|``.
WEIGHT_FLOOR_FRACTION = 1e-3
#: Working-memory budget of one chunk of texels (or rows) in :func:`als_basis`, in bytes.
CHUNK_BYTES = 256 * 2**20


# --------------------------------------------------------------------------- validation


def _check_matrix(x: Any, name: str) -> np.ndarray:
    a = np.asarray(x)
    if a.ndim != 2 or a.shape[0] == 0 or a.shape[1] == 0:
        raise ValueError(f"{name} must be a non-empty 2-D (n_lv, n_tx) matrix, got shape {a.shape}")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"{name} must be real numbers, got dtype {a.dtype}")
    finite = np.isfinite(a)
    if not finite.all():
        i, j = (int(v) for v in np.unravel_index(int(np.argmin(finite)), a.shape))
        raise ValueError(
            f"{name} contains NaN or Inf: {name}[{i}, {j}] = {float(a[i, j])!r} "
            f"({int(a.size - finite.sum())} non-finite values in all); fix or mask them first"
        )
    return a


def _float_dtype(dtype: Any, a: np.ndarray) -> np.dtype:
    if dtype is None:
        return np.dtype(np.float32 if a.dtype == np.float32 else np.float64)
    dt = np.dtype(dtype)
    if dt not in (np.float32, np.float64):
        raise ValueError(f"dtype must be float32 or float64, got {dt}")
    return dt


def _default_floor(absD: np.ndarray) -> float:
    nonzero = absD[absD > 0]
    if nonzero.size == 0:
        raise ValueError("D is all zero: relative weights 1/|D| need a scale, pass floor explicitly")
    return WEIGHT_FLOOR_FRACTION * float(np.median(nonzero))


# --------------------------------------------------------------------------- weights


def relative_error_weights(D: np.ndarray, floor: float | None = None) -> np.ndarray:
    """Per-entry weights that turn the L2 error into the relative error.

    Parameters
    ----------
    D : (n_lv, n_tx) array_like
        One material's BTF matrix (rows light/view pairs, columns texels x
        channels), finite.
    floor : float, optional
        Smallest ``|D|`` taken at face value (absolute, > 0). Default:
        ``WEIGHT_FLOOR_FRACTION * median(|D| over its non-zero entries)``,
        i.e. ``1e-3`` of a typical value.

    Returns
    -------
    W : (n_lv, n_tx) ndarray
        :math:`W = 1 / \\max(|D|, floor)`, float32 for float32 ``D`` and float64
        otherwise.

    Raises
    ------
    ValueError
        On a non-2-D ``D``, NaN/Inf in it (names the index), a non-positive
        ``floor``, or an all-zero ``D`` without ``floor``.

    Notes
    -----
    Paper 4 takes ``W`` "as the entry-wise inverse of D" (§4.1, eq. 5), which
    is undefined at zeros (cast shadows, clipped black level) and lets
    near-zero entries, whose value is mostly sensor noise, dominate the fit.
    The floor caps any entry's weight at 1000 times that of a typical entry:
    values 1000x darker than the median sit at the read-noise and
    quantisation level of HDR-merged captures, so their relative error is
    not meaningful, and the cap bounds the spread of the squared weights (and
    so the conditioning of the normal matrices of eqs. 7-8) to about
    :math:`10^6` relative to typical entries. The median of the *non-zero*
    entries is used because zeros can be a large share of a BTF and the
    median ignores specular highlights.
    """
    a = _check_matrix(D, "D")
    dt = _float_dtype(None, a)
    absD = np.abs(a.astype(dt, copy=False))
    if floor is None:
        floor = _default_floor(absD)
    elif not (np.isfinite(floor) and floor > 0):
        raise ValueError(f"floor must be a positive finite number, got {floor!r}")
    return (1.0 / np.maximum(absD, dt.type(floor))).astype(dt, copy=False)  # eq. (5): W = 1/D


# --------------------------------------------------------------------------- backends


class _NumpyOps:
    """Array operations of the numpy (reference) backend."""

    name, device, xp = "numpy", "cpu", np

    def __init__(self, dtype: np.dtype) -> None:
        self.dtype = dtype

    def asarray(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(x, dtype=self.dtype if x.dtype.kind == "f" else None)

    def zeros(self, shape: tuple[int, ...]) -> np.ndarray:
        return np.zeros(shape, self.dtype)

    def numpy(self, x: np.ndarray) -> np.ndarray:
        return x

    def addmm_(self, C: np.ndarray, A: np.ndarray, B: np.ndarray) -> None:
        C += A @ B

    def solve_spd(self, G: np.ndarray, R: np.ndarray) -> np.ndarray:
        try:
            np.linalg.cholesky(G)                               # SPD test of the whole batch
        except np.linalg.LinAlgError:
            c = G.shape[-1]
            trace = np.trace(G, axis1=1, axis2=2)
            bad = np.linalg.eigvalsh(G)[:, 0] <= c * np.finfo(self.dtype).eps * trace
            G[bad] += _ridge(trace[bad], c, self.dtype)[:, None, None] * np.eye(c, dtype=self.dtype)
        return np.linalg.solve(G, R[..., None])[..., 0]


class _TorchOps:
    """Array operations of the torch backend (CUDA when present, else CPU)."""

    name = "torch"

    def __init__(self, dtype: np.dtype, device: Any) -> None:
        import torch

        self.torch = self.xp = torch
        self.dtype = dtype
        self.tdtype = torch.float32 if dtype == np.float32 else torch.float64
        if device is None:
            device = "cuda" if torch.cuda.is_available() else "cpu"
        self.device = str(torch.device(device))

    def asarray(self, x: np.ndarray) -> Any:
        t = self.torch.as_tensor(x, device=self.device)            # no copy for a matching CPU array
        return t.to(self.tdtype) if t.is_floating_point() else t

    def zeros(self, shape: tuple[int, ...]) -> Any:
        return self.torch.zeros(shape, dtype=self.tdtype, device=self.device)

    def numpy(self, x: Any) -> np.ndarray:
        return x.cpu().numpy()

    def addmm_(self, C: Any, A: Any, B: Any) -> None:
        C.addmm_(A, B)

    def solve_spd(self, G: Any, R: Any) -> Any:
        torch = self.torch
        L, info = torch.linalg.cholesky_ex(G)
        bad = info > 0
        if bool(bad.any()):
            c = G.shape[-1]
            Gb = G[bad]
            lam = _ridge(Gb.diagonal(dim1=1, dim2=2).sum(-1), c, self.dtype)
            Gb += lam[:, None, None] * torch.eye(c, dtype=G.dtype, device=G.device)
            L[bad] = torch.linalg.cholesky(Gb)
        return torch.cholesky_solve(R[..., None], L)[..., 0]


def _ridge(trace: Any, c: int, dtype: np.dtype) -> Any:
    """Ridge for a numerically singular normal matrix: sqrt(eps) times its mean eigenvalue (+ tiny)."""
    info = np.finfo(dtype)
    return float(np.sqrt(info.eps)) * trace / c + float(info.tiny)


def _ops(backend: str, device: Any, dtype: np.dtype) -> _NumpyOps | _TorchOps:
    if backend not in ALS_BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose one of {ALS_BACKENDS}")
    if backend == "numpy":
        if device not in (None, "cpu"):
            raise ValueError(f"the numpy backend runs on the CPU only, got device={device!r}")
        return _NumpyOps(dtype)
    return _TorchOps(dtype, device)


# --------------------------------------------------------------------------- ALS


@dataclass(frozen=True)
class ALSResult:
    """A relative-error weighted rank-``c`` model :math:`D \\approx U \\operatorname{diag}(\\sigma) V`.

    Attributes
    ----------
    U : (n_lv, c) ndarray
        Basis: the columns of the fitted ``U``, normalised to unit length
        (not orthogonal), in order of decreasing ``sigma``.
    sigma : (c,) ndarray
        Products of the column norms of ``U`` and the row norms of ``V``
        (paper 4, §4.2).
    V : (c, n_tx) ndarray
        Coefficients, rows normalised to unit length.
    objective : (iterations + 1,) ndarray of float64
        :math:`\\|W \\odot (UV - D)\\|_F^2` after the first solve for ``V``
        and after each further iteration (eq. 5).
    iterations : int
        Updates of ``U`` done.
    converged : bool
        Whether the relative decrease of the objective fell below ``tol``.
    backend, device : str
        Where it ran (``'numpy'``/``'torch'``, ``'cpu'``/``'cuda:0'``...).
    """

    U: np.ndarray
    sigma: np.ndarray
    V: np.ndarray
    objective: np.ndarray
    iterations: int
    converged: bool
    backend: str
    device: str


def _chunk_size(per_item_floats: int, itemsize: int, n: int) -> int:
    return int(min(n, max(1, CHUNK_BYTES // (itemsize * per_item_floats))))


def _solve_packed(ops: _NumpyOps | _TorchOps, Gp: Any, R: Any, iu: Any, ju: Any, c: int, step: int) -> Any:
    """Solve the normal equations ``G_i x_i = R_i`` given the packed upper triangles of the ``G_i``."""
    n = Gp.shape[0]
    out = ops.zeros((n, c))
    for s in range(0, n, step):
        m = min(step, n - s)
        G = ops.zeros((m, c, c))
        G[:, iu, ju] = Gp[s:s + m]
        G[:, ju, iu] = Gp[s:s + m]
        out[s:s + m] = ops.solve_spd(G, R[s:s + m])
    return out


def als_basis(
    D: np.ndarray,
    c: int,
    W: np.ndarray | None = None,
    *,
    n_iter: int = 100,
    tol: float = 1e-6,
    seed: int = 0,
    backend: str = "auto",
    device: Any = None,
    dtype: Any = None,
    chunk_texels: int | None = None,
) -> ALSResult:
    """Rank-``c`` basis of one material under per-entry weights, by alternating least squares.

    Parameters
    ----------
    D : (n_lv, n_tx) array_like
        One material's BTF matrix (rows light/view pairs, columns texels x
        channels), finite.
    c : int
        Rank of the model, ``1 <= c <= min(n_lv, n_tx)``.
    W : (n_lv, n_tx) array_like, optional
        Non-negative finite weights; default
        :func:`relative_error_weights(D) <relative_error_weights>`, computed
        chunk by chunk. A zero column (row) leaves that texel (row) unfitted.
    n_iter : int
        Most updates of ``U`` (each followed by one of ``V``).
    tol : float
        Stop when the relative decrease of the objective in one iteration is
        below ``tol`` (an increase, only possible by rounding, also stops).
    seed : int
        Seed of the initial ``U``, uniform in :math:`(-1/2, 1/2)`.
    backend : {'auto', 'numpy', 'torch'}
        ``'torch'`` (and ``'auto'``) runs on ``device``; ``'numpy'`` is the
        CPU reference. The CPU GEMMs use as many threads as the caller
        configured (``torch.set_num_threads``, ``OMP_NUM_THREADS``).
    device : str or torch.device, optional
        Torch device; default ``'cuda'`` when available, else ``'cpu'``.
    dtype : {float32, float64}, optional
        Working precision; default float32 for float32 ``D``, else float64.
    chunk_texels : int, optional
        Texels (and rows) per batched solve; default from a working-memory
        budget of :data:`CHUNK_BYTES`. The result does not depend on it
        beyond rounding.

    Returns
    -------
    ALSResult
        ``U`` (n_lv, c), ``sigma`` (c,), ``V`` (c, n_tx) with
        :math:`D \\approx U \\operatorname{diag}(\\sigma) V`, and the history
        of the objective.

    Raises
    ------
    ValueError
        On ``c`` outside ``[1, min(n_lv, n_tx)]``, NaN/Inf in ``D`` or ``W``
        or a negative weight (names the index), ``W`` of another shape than
        ``D``, or an unknown backend or dtype.

    Notes
    -----
    Minimises (paper 4, eq. 5)

    .. math:: \\|W \\odot (U V - D)\\|_F^2

    from :math:`U_{ij} \\sim \\mathcal{U}(-1/2, 1/2)`, alternating the exact
    minimisers (eqs. 7 and 8)

    .. math::
        V_{:,x} = (U^T \\operatorname{diag}(W_{:,x})^2 U)^{-1}
                  U^T \\operatorname{diag}(W_{:,x})^2 D_{:,x}, \\qquad
        U_{l,:} = (V \\operatorname{diag}(W_{l,:})^2 V^T)^{-1}
                  V \\operatorname{diag}(W_{l,:})^2 D_{l,:}^T,

    so the objective never increases. For a chunk of texels, the packed
    normal matrices are :math:`(W^{\\odot 2})^T P` with ``P`` the
    :math:`c(c+1)/2` products :math:`U_{:,i} \\odot U_{:,j}, i \\le j` (one
    GEMM), the right-hand sides :math:`(W^{\\odot 2} \\odot D)^T U` (another),
    and the systems are solved by one batched Cholesky factorisation; the
    rows' systems are accumulated over the same chunks from the new ``V``
    (so each iteration reads ``D`` once). A normal matrix that is not
    numerically positive definite (a zero column of ``W``; ``c`` above the
    data's rank) gets a ridge of :math:`\\sqrt{\\epsilon}` times its mean
    eigenvalue, only then. Working memory: the chunk (about
    ``itemsize * (3 n_lv + 2.5 c^2)`` bytes a texel, within
    :data:`CHUNK_BYTES`) plus ``n_lv * c(c+1)/2`` accumulated entries for
    the rows' systems. The method is not guaranteed to find the global
    minimum (paper 4, §4.2).
    """
    a = _check_matrix(D, "D")
    n_lv, n_tx = a.shape
    if isinstance(c, bool) or not isinstance(c, (int, np.integer)) or not 1 <= c <= min(n_lv, n_tx):
        raise ValueError(f"c must be an integer in [1, min(n_lv, n_tx)] = [1, {min(n_lv, n_tx)}], got {c!r}")
    c = int(c)
    if W is not None:
        W = _check_matrix(W, "W")
        if W.shape != a.shape:
            raise ValueError(f"W has shape {W.shape}, D has shape {a.shape}: they must match")
        neg = np.argwhere(W < 0)
        if neg.size:
            i, j = (int(v) for v in neg[0])
            raise ValueError(f"W must be non-negative: W[{i}, {j}] = {float(W[i, j])!r} ({len(neg)} negative)")
    if n_iter < 0 or not tol >= 0:
        raise ValueError(f"n_iter must be >= 0 and tol >= 0, got n_iter={n_iter!r}, tol={tol!r}")
    if chunk_texels is not None and chunk_texels < 1:
        raise ValueError(f"chunk_texels must be a positive integer, got {chunk_texels!r}")
    dt = _float_dtype(dtype, a)
    ops = _ops(backend, device, dt)

    floor = None if W is not None else _default_floor(np.abs(a))
    Dx = ops.asarray(a.astype(dt, copy=False))
    Wx = None if W is None else ops.asarray(W)
    iu_np, ju_np = np.triu_indices(c)
    iu, ju = ops.asarray(iu_np), ops.asarray(ju_np)
    n_pack = len(iu_np)
    step = chunk_texels or _chunk_size(3 * n_lv + n_pack + 2 * c * c, dt.itemsize, n_tx)
    row_step = chunk_texels or _chunk_size(n_pack + 2 * c * c, dt.itemsize, n_lv)

    U = ops.asarray(np.random.default_rng(seed).uniform(-0.5, 0.5, (n_lv, c)))
    V = ops.zeros((c, n_tx))
    xp, bufs = ops.xp, [ops.zeros((n_lv * step,)) for _ in range(3)]   # reused: first touch is slow
    history: list[float] = []
    converged = False
    for it in range(n_iter + 1):
        P = U[:, iu] * U[:, ju]                                   # (n_lv, c(c+1)/2) column products
        Gr, Rr = ops.zeros((n_lv, n_pack)), ops.zeros((n_lv, c))
        obj = 0.0
        for s in range(0, n_tx, step):
            sl = slice(s, min(s + step, n_tx))
            Dc = Dx[:, sl]
            W2, WD2, res = (b[: Dc.shape[0] * Dc.shape[1]].reshape(Dc.shape) for b in bufs)
            if Wx is not None:
                xp.square(Wx[:, sl], out=W2)
            else:                                                 # eq. (5): W = 1/D, floored
                xp.clip(xp.abs(Dc, out=W2), min=floor, out=W2)
                xp.reciprocal(xp.square(W2, out=W2), out=W2)
            xp.multiply(W2, Dc, out=WD2)
            Gp = W2.T @ P                                         # eq. (7): U^T diag(W_:,x)^2 U, all x
            Vc = _solve_packed(ops, Gp, WD2.T @ U, iu, ju, c, Gp.shape[0]).T   # eq. (7)
            V[:, sl] = Vc
            xp.subtract(xp.matmul(U, Vc, out=res), Dc, out=res)
            obj += float(xp.multiply(xp.square(res, out=res), W2, out=res).sum())   # eq. (5)
            if it < n_iter:
                ops.addmm_(Gr, W2, (Vc[iu] * Vc[ju]).T)           # eq. (8): V diag(W_l,:)^2 V^T, all l
                ops.addmm_(Rr, WD2, Vc.T)
        history.append(obj)
        if it == n_iter:
            break
        if it > 0:
            prev = history[-2]
            if obj == 0.0 or (prev - obj) < tol * prev:
                converged = True
                break
        U = _solve_packed(ops, Gr, Rr, iu, ju, c, row_step)       # eq. (8)

    U_np, V_np = ops.numpy(U).astype(dt, copy=False), ops.numpy(V).astype(dt, copy=False)
    nu, nv = np.linalg.norm(U_np, axis=0), np.linalg.norm(V_np, axis=1)
    order = np.argsort(-(nu * nv), kind="stable")
    nu, nv = nu[order], nv[order]
    return ALSResult(
        U=U_np[:, order] / np.where(nu > 0, nu, 1),
        sigma=(nu * nv).astype(dt),                               # Sigma: column norms of U x row norms of V
        V=V_np[order] / np.where(nv > 0, nv, 1)[:, None],
        objective=np.asarray(history),
        iterations=len(history) - 1,
        converged=converged,
        backend=ops.name,
        device=ops.device,
    )


# --------------------------------------------------------------------------- merging


def merge_als_bases(
    bases: Sequence[ALSResult | tuple[np.ndarray, np.ndarray]], k: int
) -> tuple[np.ndarray, np.ndarray]:
    """Merge per-material bases into one basis of the database (paper 4, eq. 9).

    Parameters
    ----------
    bases : sequence of ALSResult or (U_i, sigma_i)
        Per-material bases, ``U_i`` (n_lv, c_i) and ``sigma_i`` (c_i,), all
        over the same light/view sampling (same ``n_lv``).
    k : int
        Size of the merged basis, ``1 <= k <= min(n_lv, sum c_i)``.

    Returns
    -------
    U : (n_lv, k) ndarray of float64
        Orthonormal merged basis.
    sigma : (k,) ndarray of float64
        Its singular values, decreasing.

    Raises
    ------
    ValueError
        On an empty list, mismatched ``n_lv`` or ``sigma`` lengths, NaN/Inf
        (names the basis), or ``k`` out of range.

    Notes
    -----
    .. math:: U \\Sigma V^T = (U^{(1)} \\Sigma^{(1)}, \\dots, U^{(n)} \\Sigma^{(n)})

    truncated to ``k`` (eq. 9), "cheap when the database is relatively
    small". General eigenspace merging (:mod:`btfcore.eigenspace_merging`)
    can take this over for large databases.
    """
    if len(bases) == 0:
        raise ValueError("bases is empty: pass at least one (U, sigma) pair")
    blocks = []
    for i, b in enumerate(bases):
        U_i, s_i = (b.U, b.sigma) if isinstance(b, ALSResult) else b
        U_i = _check_matrix(U_i, f"bases[{i}].U").astype(np.float64)
        s_i = np.asarray(s_i, dtype=np.float64)
        if s_i.shape != (U_i.shape[1],) or not np.isfinite(s_i).all():
            raise ValueError(f"bases[{i}]: sigma must be {U_i.shape[1]} finite values, got shape {s_i.shape}")
        if blocks and U_i.shape[0] != blocks[0].shape[0]:
            raise ValueError(
                f"bases[{i}] has {U_i.shape[0]} rows, bases[0] has {blocks[0].shape[0]}: "
                f"merging needs the same light/view sampling"
            )
        blocks.append(U_i * s_i)
    A = np.hstack(blocks)
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 1 <= k <= min(A.shape):
        raise ValueError(f"k must be an integer in [1, min(n_lv, sum c_i)] = [1, {min(A.shape)}], got {k!r}")
    U, s, _ = np.linalg.svd(A, full_matrices=False)               # eq. (9)
    return U[:, :k], s[:k]
