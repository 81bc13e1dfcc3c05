"""Decoding and computing the factorisations of the Bonn DFMF/FMF formats.

A factorised BTF stores, per channel ``c``, a left factor ``U[c]``
``(n_rows, K_c)`` (rows: light/view pairs ``l + n_l * v``) and a right factor
``SxV[c]`` ``(n_tx, K_c)`` (texels ``x + width * y``, singular values
multiplied in), so that the stored channel is

.. math::

    B_c[i, j] = \\sum_k U_c[i, k] \\, SxV_c[j, k], \\qquad B_c = U_c \\, SxV_c^T .

:func:`decode_textures` evaluates a block of rows x texels of all channels at
once in float32; :func:`factorise` computes an exact truncated SVD for the writers.

How the decode stays at GEMM speed
----------------------------------
The result is channel-interleaved, ``(n_sel_rows, n_sel_tx, n_ch)``, while each
channel's product is its own GEMM. Writing a per-channel product into
``out[..., c]`` (stride ``n_ch``) is a strided copy that, in numpy, costs about
as much as a K = 64 GEMM (0.60 ns per value against 0.61). Two routes:

* Small total rank: *one* GEMM per texel tile that writes straight into ``out``:

  .. math::

      out[:, j_0{:}j_1, :].\\mathrm{reshape}(n_r, -1) = [U_0 \\, U_1 \\, U_2] \\; W^T,

  where row ``t * n_ch + c`` of ``W`` holds ``SxV_c[t]`` in column block ``c`` and
  zeros elsewhere. That multiplies ``n_ch`` times the useful flops, i.e. it wastes
  ``(n_ch - 1) sum(K_c)`` multiply-adds per output value, which costs little while
  the GEMM is bound by writing its output.
* Beyond :data:`BLOCK_DIAGONAL_MAX_WASTE` wasted multiply-adds (``sum K_c > 48`` for
  RGB): per-channel GEMMs of 1024 x 1024 tiles into buffers, interleaved into ``out``
  by OpenCV's vectorised ``cv2.merge`` (0.28 ns per value), on as many Python threads
  as BLAS would use, each with BLAS held to one thread.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
from scipy import linalg

__all__ = ["BLOCK_DIAGONAL_MAX_WASTE", "decode_textures", "factorise"]

#: Largest ``(n_ch - 1) * sum(K_c)`` (multiply-adds wasted per output value) decoded by one
#: block-structured GEMM per texel tile (see the module notes): ``sum(K_c) <= 48`` for RGB. Measured on the
#: 2-core development VM (6,561 rows x 4,096 texels, ratio to the same plain GEMMs, one / two BLAS threads):
#: K_c = 8: block 0.58 / 0.44, per-channel 0.51 / 0.23; K_c = 16: 0.51 / 0.60 against 0.51 / 0.59;
#: K_c = 32: 0.44 / 0.45 against 0.55 / 0.62; K_c = 64: 0.43 / 0.40 against 0.66 / 0.64.
BLOCK_DIAGONAL_MAX_WASTE = 96
#: Bytes of the block-structured right factor ``W`` of one texel tile (and of the row block of the
#: fallback buffer for a strided ``out``). Measured (6,561 rows, 4,096-texel bands, K = 16 and 64): tiles of
#: 16 MiB ran 1.1-1.2x faster than 1 MiB ones (fewer, wider GEMMs; OpenBLAS splits them better).
_TILE_BYTES = 16 << 20
#: Rows and texels of a tile of the per-channel route (4 MiB per channel). Measured on the development VM
#: (6,561 rows x 4,096 texels, K = 64, one BLAS thread): 1024 x 1024 tiles 0.62-0.63 of the GEMM rate,
#: 256 x 1024 0.59-0.61, 128 x 256 0.55-0.56.
_MERGE_TILE = 1024
#: Most channels ``cv2.merge`` interleaves (OpenCV's CV_CN_MAX).
_CV_MAX_CHANNELS = 512


def _blas_threads() -> int:
    """Threads the BLAS behind numpy runs now (threadpoolctl, ~0.1 ms; 1 when it cannot tell)."""
    try:
        from threadpoolctl import threadpool_info
        counts = [int(i.get("num_threads") or 1) for i in threadpool_info() if i.get("user_api") == "blas"]
    except Exception:  # threadpoolctl missing or unable to inspect this BLAS: assume one thread
        return 1
    return max(counts, default=1)


def _selection(index, n: int, name: str) -> tuple[object, int]:
    """Normalise a slice or an int index array; return it and the selected count."""
    if isinstance(index, slice):
        return index, len(range(*index.indices(n)))
    idx = np.asarray(index)
    if idx.ndim == 0:
        raise ValueError(f"{name} must be a slice or a 1-D integer index array, got the scalar {index!r}; "
                         f"wrap it as [{index!r}]")
    if idx.ndim != 1 or (idx.size and idx.dtype.kind not in "iu"):
        raise ValueError(f"{name} must be a slice or a 1-D integer index array, got dtype {idx.dtype} "
                         f"shape {idx.shape}")
    idx = idx.astype(np.intp, copy=False)
    if idx.size and (int(idx.min()) < -n or int(idx.max()) >= n):
        bad = idx[(idx < -n) | (idx >= n)][0]
        raise IndexError(f"{name} index {int(bad)} is out of bounds for {n} entries")
    return idx, int(idx.size)


def _take(a: np.ndarray, index, start: int, stop: int) -> np.ndarray:
    """Entries ``start:stop`` of the selection ``index`` of ``a``'s rows, reading only those rows."""
    if isinstance(index, slice):
        r0, _, step = index.indices(a.shape[0])
        return a[r0 + start * step: r0 + stop * step: step] if step > 0 else a[index][start:stop]
    return a[index[start:stop]]


def decode_textures(U: Sequence[np.ndarray], SxV: Sequence[np.ndarray], rows, texels=slice(None),
                    out: np.ndarray | None = None) -> np.ndarray:
    """Evaluate the factor product of every channel on a block of rows and texels, in float32.

    Scratch memory besides ``out``: the selected rows of ``U`` in float32
    (``n_sel_rows * sum(K_c) * 4`` bytes) and at most 16 MiB of texel tiles.

    Parameters
    ----------
    U : sequence of n_ch arrays (n_rows, K_c)
        Left factors, any float dtype (float16 memmap views included; only the
        selected rows are read).
    SxV : sequence of n_ch arrays (n_tx, K_c)
        Right factors with the singular values multiplied in, same ``K_c`` as
        ``U[c]``; only the selected texels are read, one tile at a time.
    rows : slice or 1-D int array
        Rows (light/view pairs) to decode, ``n_sel_rows`` of them.
    texels : slice or 1-D int array, default all
        Texel columns to decode, ``n_sel_tx`` of them.
    out : (n_sel_rows, n_sel_tx, n_ch) ndarray of float32, optional
        Written in place and returned.

    Returns
    -------
    (n_sel_rows, n_sel_tx, n_ch) ndarray of float32
        ``[..., c] = U[c][rows] @ SxV[c][texels].T``, computed with float32
        GEMMs (float64 factors are rounded to float32 first).

    Raises
    ------
    ValueError
        Mismatched channel counts or ranks, a non-2-D factor, a bad selection, or
        an ``out`` of the wrong shape or dtype.
    """
    U = [u if isinstance(u, np.ndarray) else np.asarray(u) for u in U]
    SxV = [s if isinstance(s, np.ndarray) else np.asarray(s) for s in SxV]
    n_ch = len(U)
    if n_ch == 0 or len(SxV) != n_ch:
        raise ValueError(f"U and SxV need one factor per channel and the same count, got {len(U)} and {len(SxV)}")
    for c in range(n_ch):
        if np.ndim(U[c]) != 2 or np.ndim(SxV[c]) != 2:
            raise ValueError(f"channel {c}: U and SxV must be 2-D, got shapes {np.shape(U[c])} and {np.shape(SxV[c])}")
        if U[c].shape[1] != SxV[c].shape[1]:
            raise ValueError(f"channel {c}: U has {U[c].shape[1]} components but SxV has {SxV[c].shape[1]}")
        if U[c].shape[0] != U[0].shape[0] or SxV[c].shape[0] != SxV[0].shape[0]:
            raise ValueError(f"channel {c}: factor shapes {U[c].shape}, {SxV[c].shape} differ from channel 0's "
                             f"{U[0].shape}, {SxV[0].shape} in rows or texels")
    rows, n_r = _selection(rows, U[0].shape[0], "rows")
    texels, n_t = _selection(texels, SxV[0].shape[0], "texels")
    shape = (n_r, n_t, n_ch)
    if out is None:
        out = np.empty(shape, np.float32)
    elif not isinstance(out, np.ndarray) or out.shape != shape or out.dtype != np.float32:
        raise ValueError(f"out must be a float32 array of shape {shape}, got "
                         f"{getattr(out, 'dtype', type(out).__name__)} {getattr(out, 'shape', '')}")
    if out.size == 0:
        return out
    ks = [int(U[c].shape[1]) for c in range(n_ch)]
    if sum(ks) == 0:
        out[...] = 0.0
        return out
    # the selected rows of every channel, side by side, in float32: (n_r, sum K_c), small
    offsets = np.concatenate([[0], np.cumsum(ks)])
    u_all = np.empty((n_r, offsets[-1]), np.float32)
    for c in range(n_ch):
        u_all[:, offsets[c]:offsets[c + 1]] = _take(U[c], rows, 0, n_r)
    if (n_ch - 1) * sum(ks) <= BLOCK_DIAGONAL_MAX_WASTE:
        _decode_block_diagonal(u_all, offsets, SxV, texels, n_t, out)
    else:
        _decode_per_channel(u_all, offsets, SxV, texels, n_t, out)
    return out


def _decode_block_diagonal(u_all, offsets, SxV, texels, n_t, out) -> None:
    """One GEMM per texel tile, written straight into ``out`` (see the module notes)."""
    n_r, k_sum = u_all.shape
    n_ch = len(SxV)
    tile = min(n_t, int(np.clip(_TILE_BYTES // (4 * n_ch * k_sum), 64, 16384)))
    w = np.zeros((tile, n_ch, k_sum), np.float32)
    direct = out.strides[2] == 4 and out.strides[1] == 4 * n_ch
    r_blk = n_r if direct else max(1, min(n_r, _TILE_BYTES // (4 * n_ch * tile)))
    buf = None if direct else np.empty((r_blk, tile * n_ch), np.float32)
    for t0 in range(0, n_t, tile):
        t1 = min(n_t, t0 + tile)
        n = t1 - t0
        for c in range(n_ch):  # zero blocks stay zero: each channel writes only its own block
            w[:n, c, offsets[c]:offsets[c + 1]] = _take(SxV[c], texels, t0, t1)
        wt = w[:n].reshape(n * n_ch, k_sum).T
        if direct:  # (n_r, n * n_ch) view with unit inner stride: BLAS writes in place (ldc = row stride)
            np.matmul(u_all, wt, out=out[:, t0:t1].reshape(n_r, n * n_ch))
            continue
        for r0 in range(0, n_r, r_blk):  # a strided out: through a bounded buffer
            r1 = min(n_r, r0 + r_blk)
            np.matmul(u_all[r0:r1], wt, out=buf[:r1 - r0, :n * n_ch])
            out[r0:r1, t0:t1] = buf[:r1 - r0, :n * n_ch].reshape(r1 - r0, n, n_ch)


def _decode_per_channel(u_all, offsets, SxV, texels, n_t, out) -> None:
    """Per-channel GEMMs of a tile into buffers, then OpenCV's vectorised interleave into ``out``.

    Tiles of :data:`_MERGE_TILE` rows x texels: each channel's product of a tile goes into its own
    buffer, then ``cv2.merge`` interleaves them into the tile of ``out`` (0.28 ns per value on the
    development VM, against 0.60 for numpy's strided ``block[..., c] = tile``). While BLAS runs several
    threads, as many Python threads (both calls release the GIL) each take a share of the rows with BLAS
    held to one thread for the call: the merge then runs on every core too.
    """
    n_r = u_all.shape[0]
    threads = _blas_threads()
    parts = max(1, min(threads, -(-n_r // _MERGE_TILE)))
    bounds = [(n_r * i // parts, n_r * (i + 1) // parts) for i in range(parts)]
    if parts == 1:
        _decode_rows_per_channel(u_all, offsets, SxV, texels, n_t, out, 0, n_r)
        return
    from concurrent.futures import ThreadPoolExecutor
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1, user_api="blas"), ThreadPoolExecutor(parts) as pool:
        jobs = [pool.submit(_decode_rows_per_channel, u_all, offsets, SxV, texels, n_t, out, r_lo, r_hi)
                for r_lo, r_hi in bounds]
        for job in jobs:
            job.result()


def _decode_rows_per_channel(u_all, offsets, SxV, texels, n_t, out, r_lo: int, r_hi: int) -> None:
    """Rows ``r_lo:r_hi`` of :func:`_decode_per_channel`, one thread's share."""
    n_ch = len(SxV)
    tile = _MERGE_TILE
    buf = np.empty((n_ch, min(tile, r_hi - r_lo) * min(tile, n_t)), np.float32)
    interleaved = out.strides[2] == 4 and out.strides[1] == 4 * n_ch
    for t0 in range(0, n_t, tile):
        t1 = min(n_t, t0 + tile)
        # aligned float32 copies: numpy's matmul skips BLAS on the unaligned float32 views of a memory map
        right = [np.require(_take(SxV[c], texels, t0, t1), np.float32, ["C", "A"]).T for c in range(n_ch)]
        for r0 in range(r_lo, r_hi, tile):
            r1 = min(r_hi, r0 + tile)
            n = (r1 - r0) * (t1 - t0)
            tiles = [buf[c, :n].reshape(r1 - r0, t1 - t0) for c in range(n_ch)]
            for c in range(n_ch):
                np.matmul(u_all[r0:r1, offsets[c]:offsets[c + 1]], right[c], out=tiles[c])
            block = out[r0:r1, t0:t1]
            merged = cv2.merge(tiles, dst=block) if interleaved and n_ch <= _CV_MAX_CHANNELS else None
            if merged is None or not np.shares_memory(merged, block):   # OpenCV could not write in place
                for c in range(n_ch):
                    block[..., c] = tiles[c]


def factorise(B: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact rank-``k`` truncated SVD of one channel, in the factors a DFMF/FMF file stores.

    Parameters
    ----------
    B : (n_rows, n_tx) array_like
        One channel's matrix (rows light/view pairs, columns texels), finite.
        Computed in float64 with a full thin SVD (LAPACK ``gesdd``, ``gesvd`` if
        that fails to converge): memory ``~ 8 (n_rows n_tx + min(n_rows, n_tx)
        (n_rows + n_tx))`` bytes. For matrices beyond memory use
        :func:`btfcore.model.truncated_svd.truncated_svd` over column blocks.
    k : int
        Number of components, ``>= 1``; clipped to ``min(n_rows, n_tx)``.

    Returns
    -------
    S : (k,) ndarray of float64
        The leading singular values, decreasing.
    U : (n_rows, k) ndarray of float64
        Orthonormal columns; each column's entry of largest magnitude is positive.
    SxV : (n_tx, k) ndarray of float64
        ``V * S`` (sign-matched to ``U``), so ``U @ SxV.T`` is the best rank-k
        approximation of ``B`` (Eckart-Young: squared Frobenius error
        ``sum(sigma[k:] ** 2)``).

    Raises
    ------
    ValueError
        ``k < 1``, ``B`` not 2-D or empty, or ``B`` not finite.
    """
    if isinstance(k, (bool, np.bool_)) or not isinstance(k, (int, np.integer)) or int(k) < 1:
        raise ValueError(f"k must be an integer >= 1, got {k!r}")
    a = np.asarray(B)
    if a.ndim != 2 or a.size == 0:
        raise ValueError(f"B must be a non-empty 2-D (n_rows, n_tx) matrix, got shape {a.shape}")
    if a.dtype.kind not in "iuf":
        raise ValueError(f"B must hold real numbers, got dtype {a.dtype}")
    a = np.asarray(a, dtype=np.float64)
    if not np.isfinite(a).all():
        idx = [int(i) for i in np.unravel_index(int(np.argmin(np.isfinite(a))), a.shape)]
        raise ValueError(f"B{idx} = {a[tuple(idx)]} is not finite; repair or mask NaN/Inf before factorising")
    k = min(int(k), *a.shape)
    try:
        u, s, vt = linalg.svd(a, full_matrices=False, lapack_driver="gesdd", check_finite=False)
    except linalg.LinAlgError:
        u, s, vt = linalg.svd(a, full_matrices=False, lapack_driver="gesvd", check_finite=False)
    u = u[:, :k]
    v = vt[:k].T
    sign = np.sign(u[np.argmax(np.abs(u), axis=0), np.arange(k)])
    sign[sign == 0] = 1.0
    u = u * sign
    sxv = v * (sign * s[:k])
    return s[:k].copy(), np.ascontiguousarray(u), np.ascontiguousarray(sxv)
