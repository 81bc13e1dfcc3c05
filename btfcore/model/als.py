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
``U``'s columns, followed by one batched Cholesky solve (docs/architecture.md,
"Pitfalls": the GEMM runs near the machine's peak; the small solves are the rest).

Out of core (:func:`als_basis` on a block source): ``V`` is needed only
within the pass that solves it (for the objective and the rows' systems),
so for a block source it is not kept: the working memory is one block (on
the device) and its chunk, independent of ``n_tx``, and the result's
``sigma`` comes from row norms of ``V`` accumulated in the last pass. An
in-memory ``D`` keeps ``V`` (``c * n_tx`` values) and returns it. For the
same data, chunks and ``floor``, a block source gives the in-memory result
(same chunks, same order of accumulation). The default ``floor`` of a block
source is estimated from every block's non-zero ``|D|``: all of them when
the block has at most :data:`FLOOR_SAMPLE`, else that many drawn with a
fixed seed and weighted by the entries they stand for; the weighted median
is the exact one when no block was subsampled. The floor only sets the
scale below which weights stop growing (1e-3 of a typical value), which
needs no more precision than such a sample gives (2e-4 relative on the
tests' data).

References
----------
.. [1] The thesis, App. paper 4 ("Rapid material capture through sparse and
   multiplexed measurements"), §4.1-4.2, eqs. (5)-(9).
.. [2] R. Ruiters, M. Rump and R. Klein, "Parallelized matrix factorization
   for fast BTF compression", EGPGV 2009 (relative-error weights).
.. [3] T. G. Kolda and B. W. Bader, "Tensor decompositions and
   applications", SIAM Review 51(3), 2009 (alternating least squares).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from btfcore.model._lowrank import Blocks, BlockSource, _as_block, as_block_source, check_finite, for_each_block

__all__ = [
    "ALS_BACKENDS",
    "CHUNK_BYTES",
    "FLOOR_SAMPLE",
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
#: Non-zero ``|D|`` per block that estimate a block source's default weight floor in :func:`als_basis`.
FLOOR_SAMPLE = 1 << 16
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


def _float_dtype(dtype: Any, data_dtype: np.dtype) -> np.dtype:
    if dtype is None:
        return np.dtype(np.float32 if data_dtype == np.float32 else np.float64)
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
    dt = _float_dtype(None, a.dtype)
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
    lower_only = False                      # solve_spd's LU solve reads the whole normal matrix

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

    def put_columns(self, G: np.ndarray, index: np.ndarray, values: np.ndarray) -> None:
        G[:, index] = values

    def cpu_threads(self) -> int:
        return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1

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

    def put_columns(self, G: Any, index: Any, values: Any) -> None:
        G.index_copy_(1, index, values)                         # 0.044 s against 0.073 s for G[:, index] = ...

    def cpu_threads(self) -> int:
        return self.torch.get_num_threads()

    lower_only = True                       # cholesky_ex (LAPACK potrf, uplo L) reads the lower triangle only

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
        y = torch.linalg.solve_triangular(L, R[..., None], upper=False)      # L L^T x = R: half the time of
        return torch.linalg.solve_triangular(L.mT, y, upper=True)[..., 0]    # cholesky_solve on the CPU


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
    V : (c, n_tx) ndarray or None
        Coefficients, rows normalised to unit length; ``None`` when ``D``
        came as a block source (it is not kept, see :func:`als_basis`).
    objective : (iterations + 1,) ndarray of float64
        :math:`\\|W \\odot (UV - D)\\|_F^2` after the first solve for ``V``
        and after each further iteration (eq. 5).
    iterations : int
        Updates of ``U`` done.
    converged : bool
        Whether the relative decrease of the objective fell below ``tol``.
    backend, device : str
        Where it ran (``'numpy'``/``'torch'``, ``'cpu'``/``'cuda:0'``...).
    norm_sq : float
        :math:`\\|D\\|_F^2` in float64 (from the first pass over a block source).
    floor : float or None
        Weight floor of the default weights :math:`1/\\max(|D|, floor)`; None for given ``W``.
    """

    U: np.ndarray
    sigma: np.ndarray
    V: np.ndarray | None
    objective: np.ndarray
    iterations: int
    converged: bool
    backend: str
    device: str
    norm_sq: float = 0.0
    floor: float | None = None


#: Normal systems factorised at a time on the CPU: a batch of 256 64 x 64 systems (4 MB) stays in the cache;
#: scattering, factorising and solving 20,480 of them took 0.39-0.45 s in batches of 32-1,024 (256: 0.41 s)
#: against 0.72 s in one batch (torch, 2 threads; docs/benchmarks.md, 2026-12-05).
CPU_SOLVE_BATCH = 256

#: Threads that share a CPU solve's batches; None: torch's intra-op thread count, or the CPUs this
#: process may use for the numpy backend.
CPU_SOLVE_THREADS: int | None = None


def _per_texel_floats(n_lv: int, c: int) -> int:
    """Working floats of one texel column in a V-step chunk: its ``W^2``, ``W^2 D`` and residual
    columns, its packed normal matrix, its solve."""
    return 3 * n_lv + c * (c + 1) // 2 + 2 * c * c


def _chunk_size(per_item_floats: int, itemsize: int, n: int, budget: int) -> int:
    return int(min(n, max(1, budget // (itemsize * per_item_floats))))


def _solve_packed(ops: _NumpyOps | _TorchOps, Gp: Any, R: Any, iu: Any, ju: Any, c: int, step: int) -> Any:
    """Solve the normal equations ``G_i x_i = R_i`` given the packed upper triangles of the ``G_i``,
    at most ``step`` systems at a time (:data:`CPU_SOLVE_BATCH` on the CPU).

    On the CPU the batches are shared among :data:`CPU_SOLVE_THREADS` threads, each with its own reused buffer:
    torch and numpy factorise a batch one small matrix after another on one core (LAPACK ``potrf`` /
    ``gesv`` per system), so a second thread nearly halves the time (20,480 64 x 64 systems, scatter
    included: 0.29-0.34 s against 0.39-0.65 s on two cores; docs/benchmarks.md, 2026-12-05)."""
    n = Gp.shape[0]
    out = ops.zeros((n, c))
    threads = 1
    if ops.device == "cpu":
        step = min(step, CPU_SOLVE_BATCH)
        threads = max(1, min(CPU_SOLVE_THREADS or ops.cpu_threads(), -(-n // step)))
    lower, upper = ju * c + iu, iu * c + ju                         # flat indices of (ju, iu) and (iu, ju)

    def batches(first: int) -> None:
        buf = ops.zeros((min(step, n), c * c))      # reused: the lower triangle (and the upper) is overwritten
        for s in range(first * step, n, threads * step):
            m = min(step, n - s)
            G = buf[:m]
            ops.put_columns(G, lower, Gp[s:s + m])                  # the lower triangle (iu <= ju)
            if not ops.lower_only:
                ops.put_columns(G, upper, Gp[s:s + m])
            out[s:s + m] = ops.solve_spd(G.reshape(m, c, c), R[s:s + m])

    if threads == 1:
        batches(0)
    else:
        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(batches, range(threads)))             # list(): a thread's exception is raised here
    return out


def _is_block_source(D: Any) -> bool:
    """Whether ``D`` is a block source (callable, list/tuple of 2-D arrays) rather than one matrix.
    An iterator counts as one, so that :func:`as_block_source` refuses it with its advice."""
    if callable(D) or isinstance(D, Iterator):
        return True
    return isinstance(D, (list, tuple)) and len(D) > 0 and all(isinstance(b, np.ndarray) and b.ndim == 2 for b in D)


class _Sweep:
    """One pass of the V-step (eq. 7) over chunks of ``D``'s columns with ``U`` fixed, accumulating the
    objective (eq. 5), the squared row norms of ``V`` and, when ``u_step``, the rows' normal equations (eq. 8)."""

    def __init__(self, ops: _NumpyOps | _TorchOps, U: Any, iu: Any, ju: Any, floor: float | None,
                 chunk_texels: int | None, chunk_bytes: int, bufs: list, u_step: bool) -> None:
        n_lv, c = U.shape
        self.ops, self.U, self.iu, self.ju, self.floor, self.bufs = ops, U, iu, ju, floor, bufs
        self.chunk_texels, self.chunk_bytes = chunk_texels, chunk_bytes
        self.per_texel = _per_texel_floats(n_lv, c)
        self.P = U[:, iu] * U[:, ju]                               # (n_lv, c(c+1)/2) column products
        self.obj, self.nv2 = 0.0, ops.zeros((c,))
        self.Gr, self.Rr = (ops.zeros((n_lv, len(iu))), ops.zeros((n_lv, c))) if u_step else (None, None)

    def block(self, Dx: Any, Wx: Any = None, V: Any = None) -> None:
        """V-step over one block ``Dx`` (on the device) in chunks; ``Wx``: its weights (default
        :math:`1/\\max(|D|, floor)`); its coefficients are written to ``V`` (same columns) when given."""
        ops, xp, U, c = self.ops, self.ops.xp, self.U, self.U.shape[1]
        n_lv, m = Dx.shape
        step = min(m, self.chunk_texels) if self.chunk_texels else _chunk_size(self.per_texel, ops.dtype.itemsize, m,
                                                                                self.chunk_bytes)
        if self.bufs[0].shape[0] < n_lv * step:                    # grown once, then reused: first touch is slow
            self.bufs[:] = [ops.zeros((n_lv * step,)) for _ in range(3)]
        for s in range(0, m, step):
            sl = slice(s, min(s + step, m))
            Dc = Dx[:, sl]
            W2, WD2, res = (b[: Dc.shape[0] * Dc.shape[1]].reshape(Dc.shape) for b in self.bufs)
            if Wx is not None:
                xp.square(Wx[:, sl], out=W2)
            else:                               # eq. (5): W^2 = 1/max(|D|, floor)^2 = 1/max(D^2, floor^2)
                xp.clip(xp.square(Dc, out=W2), min=float(ops.dtype.type(self.floor) ** 2), out=W2)
                xp.reciprocal(W2, out=W2)
            xp.multiply(W2, Dc, out=WD2)
            Gp = W2.T @ self.P                                    # eq. (7): U^T diag(W_:,x)^2 U, all x
            Vc = _solve_packed(ops, Gp, WD2.T @ U, self.iu, self.ju, c, Gp.shape[0]).T   # eq. (7)
            if V is not None:
                V[:, sl] = Vc
            self.nv2 += (Vc * Vc).sum(1)
            xp.subtract(xp.matmul(U, Vc, out=res), Dc, out=res)
            self.obj += float(xp.multiply(xp.square(res, out=res), W2, out=res).sum())   # eq. (5)
            if self.Gr is not None:
                ops.addmm_(self.Gr, W2, _pair_products(ops, Vc).T)       # eq. (8): V diag(W_l,:)^2 V^T, all l
                ops.addmm_(self.Rr, WD2, Vc.T)


def _pair_products(ops: _NumpyOps | _TorchOps, X: Any) -> Any:
    """``X[iu] * X[ju]`` ``(c (c + 1) / 2, m)`` for ``iu, ju = triu_indices(c)`` and ``X`` ``(c, m)``, row
    ``i`` times rows ``i..c-1`` at a time, the same values as the gather ``X[iu] * X[ju]``, which read the
    solve's transposed output row by strided row: 2.3 ms against 9.5 ms for c = 64 and 2,974 texels (torch,
    2 threads; 40 ms of a 2.7 s iteration of ``benchmarks/bench_als.py``, within its spread)."""
    xp, c = ops.xp, X.shape[0]
    X = X.contiguous() if ops.name == "torch" else np.ascontiguousarray(X)
    out = ops.zeros((c * (c + 1) // 2, X.shape[1])) if ops.name == "numpy" else \
        ops.torch.empty((c * (c + 1) // 2, X.shape[1]), dtype=X.dtype, device=X.device)
    start = 0
    for i in range(c):
        xp.multiply(X[i:], X[i:i + 1], out=out[start:start + c - i])
        start += c - i
    return out


def _scan_blocks(source: BlockSource, floor: float | None) -> tuple[int, int | None, np.dtype, float]:
    """``(n_lv, n_tx, dtype, floor)`` of a block source. With ``floor`` given only the first block is
    read (``n_tx`` is then None); without, one whole pass validates the blocks and estimates the
    default floor from them (:func:`_estimated_floor`)."""
    n_lv: int | None = None
    n_tx, samples, weights = 0, [], []
    rng = np.random.default_rng(0)
    for j, raw in enumerate(source()):
        if n_lv is None:
            n_lv = np.shape(raw)[0] if np.ndim(raw) == 2 else None
        b = _as_block(raw, j, n_lv)
        if j == 0:
            dt = b.dtype
            if floor is not None:
                return int(b.shape[0]), None, dt, floor
        check_finite(b, f"blocks[{j}]", n_tx)
        nonzero = np.abs(b[b != 0])
        if nonzero.size > FLOOR_SAMPLE:
            weights.append(nonzero.size / FLOOR_SAMPLE)
            nonzero = nonzero[rng.integers(0, nonzero.size, FLOOR_SAMPLE)]
        else:
            weights.append(1.0)
        samples.append(nonzero)
        n_tx += b.shape[1]
    if n_lv is None or n_tx == 0:
        raise ValueError("blocks gave no columns: the source must return a fresh iterator over the same non-empty "
                         "blocks on every call")
    return int(n_lv), n_tx, dt, _estimated_floor(samples, weights)


def _estimated_floor(samples: list[np.ndarray], weights: list[float]) -> float:
    """:data:`WEIGHT_FLOOR_FRACTION` times the median of the blocks' non-zero ``|D|``, each block's
    sample weighted by the entries it stands for: the exact median when no block was subsampled."""
    if all(w == 1.0 for w in weights):
        return _default_floor(np.concatenate(samples))
    values = np.concatenate(samples)
    w = np.concatenate([np.full(s.size, wi) for s, wi in zip(samples, weights)])
    order = np.argsort(values, kind="stable")
    cum = np.cumsum(w[order])
    return WEIGHT_FLOOR_FRACTION * float(values[order][np.searchsorted(cum, cum[-1] / 2)])


def als_basis(
    D: np.ndarray | Blocks,
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
    chunk_bytes: int = CHUNK_BYTES,
    floor: float | None = None,
) -> ALSResult:
    """Rank-``c`` basis of one material under per-entry weights, by alternating least squares.

    Parameters
    ----------
    D : (n_lv, n_tx) array_like, or a block source
        One material's BTF matrix (rows light/view pairs, columns texels x
        channels), finite: in memory, or out of core as its column blocks,
        i.e. a callable returning a fresh iterator over ``(n_lv, m_j)``
        blocks on every call, or a list/tuple of such arrays (the
        convention of :mod:`btfcore.model.truncated_svd`). A block source is read
        once per iteration plus once more for the default ``floor``.
    c : int
        Rank of the model, ``1 <= c <= min(n_lv, n_tx)``.
    W : (n_lv, n_tx) array_like, optional
        Non-negative finite weights, for an in-memory ``D`` only; default
        :func:`relative_error_weights(D, floor) <relative_error_weights>`,
        computed chunk by chunk (for a block source always so, block by
        block with one ``floor`` for all). A zero column (row) leaves that
        texel (row) unfitted.
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
        Working precision; default float32 for float32 ``D`` (for a block
        source: its first block), else float64.
    chunk_texels : int, optional
        Texels (and rows) per batched solve; default from the working-memory
        budget ``chunk_bytes``. The result does not depend on it beyond
        rounding. A block source's blocks are chunked one by one.
    chunk_bytes : int
        Working-memory budget of one chunk's solve (default
        :data:`CHUNK_BYTES`); ignored when ``chunk_texels`` is given. A
        caller on a memory-limited worker passes a fraction of its limit.
    floor : float, optional
        Weight floor of the default weights (absolute, > 0); not with ``W``.
        Default ``WEIGHT_FLOOR_FRACTION`` times the median non-zero
        ``|D|``: exact for an in-memory ``D``; for a block source estimated
        in a first pass (:data:`FLOOR_SAMPLE`, module docstring). Passing it saves that
        pass.

    Returns
    -------
    ALSResult
        ``U`` (n_lv, c), ``sigma`` (c,), ``V`` (c, n_tx) with
        :math:`D \\approx U \\operatorname{diag}(\\sigma) V` (``V`` is None
        for a block source), the history of the objective and
        :math:`\\|D\\|_F^2`.

    Raises
    ------
    ValueError
        On ``c`` outside ``[1, min(n_lv, n_tx)]``, NaN/Inf in ``D`` or ``W``
        or a negative weight (names the index; for a block source the
        block and ``D``'s column), ``W`` of another shape than ``D``, ``W``
        or ``floor`` together or ``W`` with a block source, a block source
        whose passes differ in their columns, or an unknown backend or dtype.

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

    so the objective never increases. A chunk of texels is solved with two
    GEMMs and one batched Cholesky factorisation (module docstring; the
    right-hand sides are :math:`(W^{\\odot 2} \\odot D)^T U`); the
    rows' systems are accumulated over the same chunks from the new ``V``
    (so each iteration reads ``D`` once). A normal matrix that is not
    numerically positive definite (a zero column of ``W``; ``c`` above the
    data's rank) gets a ridge of :math:`\\sqrt{\\epsilon}` times its mean
    eigenvalue, only then. Working memory: the chunk (about
    ``itemsize * (3 n_lv + 2.5 c^2)`` bytes a texel, within
    ``chunk_bytes``) plus ``n_lv * c(c+1)/2`` accumulated entries for
    the rows' systems. The method is not guaranteed to find the global
    minimum (paper 4, §4.2). A block source is fitted out of core as the
    module docstring describes (the in-memory result, without ``V``).
    """
    source, a, W, shape, raw_dtype, floor = _checked_inputs(D, c, W, n_iter, tol, chunk_texels, chunk_bytes, floor)
    c = int(c)
    ops = _ops(backend, device, _float_dtype(dtype, raw_dtype))
    data = _InMemory(ops, a, W, floor, c) if source is None else _Streamed(ops, source, shape, floor, c)
    U, sweep, history, converged = _alternate(ops, data, c, n_iter, tol, seed, chunk_texels, chunk_bytes)
    return _als_result(ops, data, U, sweep, history, converged)


def _checked_inputs(
    D: Any, c: Any, W: Any, n_iter: int, tol: float, chunk_texels: int | None, chunk_bytes: int, floor: float | None,
) -> tuple[BlockSource | None, np.ndarray | None, np.ndarray | None, tuple[int, int | None], np.dtype, float | None]:
    """:func:`als_basis`'s inputs, checked: ``(source, a, W, (n_lv, n_tx), dtype of D, floor)``; ``source`` is
    None for an in-memory ``D`` (then ``a`` is it), ``a`` None for a block source (``n_tx`` None when unread)."""
    if n_iter < 0 or not tol >= 0:
        raise ValueError(f"n_iter must be >= 0 and tol >= 0, got n_iter={n_iter!r}, tol={tol!r}")
    if chunk_bytes < 1:
        raise ValueError(f"chunk_bytes must be a positive integer, got {chunk_bytes!r}")
    if chunk_texels is not None and chunk_texels < 1:
        raise ValueError(f"chunk_texels must be a positive integer, got {chunk_texels!r}")
    if floor is not None and not (np.isfinite(floor) and floor > 0):
        raise ValueError(f"floor must be a positive finite number, got {floor!r}")
    if floor is not None and W is not None:
        raise ValueError("floor sets the default weights: pass W or floor, not both")
    floor = None if floor is None else float(floor)
    source = as_block_source(D) if _is_block_source(D) else None
    if source is not None:
        if W is not None:
            raise ValueError("W needs an in-memory D: a block source is weighted by relative_error_weights(block, "
                             "floor) block by block")
        n_lv, n_tx, raw_dtype, floor = _scan_blocks(source, floor)
        a = None
    else:
        a = _check_matrix(D, "D")
        (n_lv, n_tx), raw_dtype = a.shape, a.dtype
    _check_c(c, n_lv, n_tx)
    if W is not None:
        W = _check_matrix(W, "W")
        if W.shape != a.shape:
            raise ValueError(f"W has shape {W.shape}, D has shape {a.shape}: they must match")
        neg = np.argwhere(W < 0)
        if neg.size:
            i, j = (int(v) for v in neg[0])
            raise ValueError(f"W must be non-negative: W[{i}, {j}] = {float(W[i, j])!r} ({len(neg)} negative)")
    return source, a, W, (n_lv, n_tx), raw_dtype, floor


class _InMemory:
    """An in-memory ``D`` (and ``W``) on the device, for :func:`_alternate`; keeps ``V`` (c, n_tx)."""

    def __init__(self, ops: _NumpyOps | _TorchOps, a: np.ndarray, W: np.ndarray | None, floor: float | None,
                 c: int) -> None:
        self.n_lv, self.n_tx = a.shape
        self.floor = None if W is not None else floor or _default_floor(np.abs(a))
        self.norm_sq = float(np.einsum("ij,ij->", a, a, dtype=np.float64))
        self.Dx = ops.asarray(a.astype(ops.dtype, copy=False))
        self.Wx = None if W is None else ops.asarray(W)
        self.V = ops.zeros((c, self.n_tx))

    def v_pass(self, sweep: _Sweep, it: int) -> None:
        """One :class:`_Sweep` over all of ``D``, writing ``V``."""
        sweep.block(self.Dx, self.Wx, self.V)


class _Streamed:
    """A block source for :func:`_alternate`, read once per pass (one block on the device at a time); ``V`` is
    not kept (None), and ``norm_sq`` and ``n_tx`` are known from the first pass on."""

    def __init__(self, ops: _NumpyOps | _TorchOps, source: BlockSource, shape: tuple[int, int | None],
                 floor: float | None, c: int) -> None:
        self.ops, self.source, self.floor, self.c = ops, source, floor, c
        self.n_lv, self.n_tx = shape
        self.norm_sq: float | None = None
        self.V = None

    def v_pass(self, sweep: _Sweep, it: int) -> None:
        """One :class:`_Sweep` over the blocks; the first pass also counts the columns, checks ``c`` and takes
        the norm and the NaN/Inf test (:func:`btfcore.model._lowrank.squared_norm`, a pass over every block
        that later passes over the same blocks need not repeat)."""
        ops, dt = self.ops, self.ops.dtype
        pass_norm_sq, cols = for_each_block(
            self.source, self.n_lv, lambda b: sweep.block(ops.asarray(b.astype(dt, copy=False))), self.n_tx,
            norm=it == 0)
        if it == 0:
            self.norm_sq, self.n_tx = pass_norm_sq, cols
            _check_c(self.c, self.n_lv, self.n_tx)


def _alternate(ops: _NumpyOps | _TorchOps, data: _InMemory | _Streamed, c: int, n_iter: int, tol: float, seed: int,
               chunk_texels: int | None, chunk_bytes: int) -> tuple[Any, _Sweep, list[float], bool]:
    """Alternating least squares from a seeded random ``U`` (paper 4, eqs. 7 and 8):
    ``(U, the last V-pass, the objective of every pass, converged)``."""
    n_lv = data.n_lv
    iu_np, ju_np = np.triu_indices(c)
    iu, ju = ops.asarray(iu_np), ops.asarray(ju_np)
    row_step = chunk_texels or _chunk_size(len(iu_np) + 2 * c * c, ops.dtype.itemsize, n_lv, chunk_bytes)

    U = ops.asarray(np.random.default_rng(seed).uniform(-0.5, 0.5, (n_lv, c)))
    bufs = [ops.zeros((0,))] * 3
    history: list[float] = []
    converged = False
    for it in range(n_iter + 1):
        sweep = _Sweep(ops, U, iu, ju, data.floor, chunk_texels, chunk_bytes, bufs, u_step=it < n_iter)
        data.v_pass(sweep, it)                                    # eq. (7)
        history.append(sweep.obj)
        if it == n_iter:
            break
        if it > 0:
            prev = history[-2]
            if sweep.obj == 0.0 or (prev - sweep.obj) < tol * prev:
                converged = True
                break
        U = _solve_packed(ops, sweep.Gr, sweep.Rr, iu, ju, c, row_step)   # eq. (8)
    return U, sweep, history, converged


def _als_result(ops: _NumpyOps | _TorchOps, data: _InMemory | _Streamed, U: Any, sweep: _Sweep,
                history: list[float], converged: bool) -> ALSResult:
    """The fit as an :class:`ALSResult`: unit columns of ``U`` and rows of ``V``, their norms' products as
    ``sigma``, in decreasing order."""
    dt = ops.dtype
    U_np = ops.numpy(U).astype(dt, copy=False)
    V_np = None if data.V is None else ops.numpy(data.V).astype(dt, copy=False)
    nu = np.linalg.norm(U_np, axis=0)
    nv = np.sqrt(ops.numpy(sweep.nv2)).astype(dt) if V_np is None else np.linalg.norm(V_np, axis=1)
    order = np.argsort(-(nu * nv), kind="stable")
    nu, nv = nu[order], nv[order]
    return ALSResult(
        U=U_np[:, order] / np.where(nu > 0, nu, 1),
        sigma=(nu * nv).astype(dt),                               # Sigma: column norms of U x row norms of V
        V=None if V_np is None else V_np[order] / np.where(nv > 0, nv, 1)[:, None],
        objective=np.asarray(history),
        iterations=len(history) - 1,
        converged=converged,
        backend=ops.name,
        device=ops.device,
        norm_sq=data.norm_sq,
        floor=data.floor,
    )


def _check_c(c: Any, n_lv: int, n_tx: int | None) -> None:
    limit = n_lv if n_tx is None else min(n_lv, n_tx)
    if isinstance(c, bool) or not isinstance(c, (int, np.integer)) or not 1 <= c <= limit:
        raise ValueError(f"c must be an integer in [1, min(n_lv, n_tx)] = [1, {limit}], got {c!r}")


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
    small". General eigenspace merging (:mod:`btfcore.model.eigenspace_merging`)
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
