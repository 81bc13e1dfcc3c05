"""ABTF patches: p x p neighbouring ABRDFs stacked into one column.

Den Brok et al. fit linear models not only to ABRDFs (columns of ``B``) but
to *apparent BTFs* (ABTFs), "vectors of stacked discrete ABRDFs belonging to
the same neighborhood", which capture interreflections and shadows cast from
neighbouring texels (paper 1, §3.3). Bases are fitted to non-overlapping
3 x 3 patches ("1764 ABTFs per material" of 128 x 128 texels) and a BTF is
projected through *all* its 3 x 3 patches, then rebuilt by "blending the
patches, all texels weighted equally" (§4.1.2).

* :func:`patch_matrix` stacks the patches of a texture-shaped BTF,
* :func:`blend_patches` blends all (overlapping) patches back to texels,
* :func:`patch_grid` counts patches and :func:`patch_rows` says which
  texture rows a band of patch rows reads, so that a large BTF can be
  patched band by band with the same result as a whole.

A BTF matrix ``B`` of shape ``(n_lv, h * w * C)`` (columns flattened
row, column, channel: docs/architecture.md, "Matrix convention") is passed as ``B.reshape(n_lv, h, w, C)``.

References
----------
.. [1] The thesis, App. paper 1 (den Brok et al.): D. den Brok, H. C.
   Steinhausen, M. B. Hullin and R. Klein, "Patch-based sparse reconstruction
   of material BTFs", Journal of WSCG 22, 2014, §3.3, §3.4 and §4.1.2.
.. [2] M. Varma and A. Zisserman, "A statistical approach to material
   classification using image patch exemplars", IEEE TPAMI 31(11), 2009
   (3 x 3 patches).
"""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from btfcore.model.colour import _as_float

__all__ = ["blend_patches", "patch_grid", "patch_matrix", "patch_rows"]


def _patch_size(p: int) -> int:
    if not isinstance(p, (int, np.integer)) or p < 1:
        raise ValueError(f"patch size p must be an integer >= 1, got {p!r}")
    return int(p)


def patch_grid(h: int, w: int, p: int = 3, *, overlap: bool) -> tuple[int, int]:
    """Number of patch rows and columns of an ``h x w`` texture.

    Parameters
    ----------
    h, w : int
        Texture rows and columns, each at least ``p``.
    p : int
        Patch size.
    overlap : bool
        ``True``: every p x p window (stride 1); ``False``: the maximal
        non-overlapping tiling anchored at texel (0, 0) (stride p).

    Returns
    -------
    ny, nx : int
        ``h - p + 1, w - p + 1`` with overlap, ``h // p, w // p`` without
        (128 x 128 texels, p = 3: 42 x 42 = 1764 patches, paper 1, §4.1.2).

    Raises
    ------
    ValueError
        If ``p`` is not a positive integer or exceeds ``h`` or ``w``.
    """
    p = _patch_size(p)
    s = 1 if overlap else p
    if h < p or w < p:
        raise ValueError(f"a {h} x {w} texture has no {p} x {p} patch; use a texture of at least p x p texels")
    return (h - p) // s + 1, (w - p) // s + 1


def patch_rows(start: int, stop: int, p: int = 3, *, overlap: bool) -> slice:
    """Texture rows that the patch rows ``start:stop`` read (the band plus its halo).

    Parameters
    ----------
    start, stop : int
        Patch rows ``0 <= start < stop`` (stop may exceed the grid; the
        slice then runs off the texture and is clipped like any slice).
    p : int
    overlap : bool
        As for :func:`patch_matrix`.

    Returns
    -------
    rows : slice
        ``slice(start * s, (stop - 1) * s + p)`` with stride ``s`` (1 or p),
        so that ``patch_matrix(B[:, rows], p, overlap=o)`` equals the
        columns ``start * nx * C : stop * nx * C`` of
        ``patch_matrix(B, p, overlap=o)``: patching band by band and
        concatenating the columns in band order is patching the whole.

    Raises
    ------
    ValueError
        On ``start < 0`` or ``stop <= start``, or a bad ``p``.
    """
    p = _patch_size(p)
    s = 1 if overlap else p
    if not 0 <= start < stop:
        raise ValueError(f"patch rows must satisfy 0 <= start < stop, got start={start}, stop={stop}")
    return slice(start * s, (stop - 1) * s + p)


def patch_matrix(B: np.ndarray, p: int = 3, *, overlap: bool) -> np.ndarray:
    """Stack the p x p patches of a BTF into ABTF columns.

    Parameters
    ----------
    B : (n_lv, h, w, C) or (n_lv, h, w) array_like
        BTF with its texels on a grid (``h, w >= p``).
    p : int
        Patch size (paper 1: 3).
    overlap : bool
        ``False`` for fitting: the maximal non-overlapping tiling anchored at
        texel (0, 0) (the last ``h % p`` rows and ``w % p`` columns are left
        out); ``True`` for projection: every p x p window, stride 1.

    Returns
    -------
    P : (p * p * n_lv, ny * nx * C) ndarray
        ``ny, nx = patch_grid(h, w, p, overlap=overlap)``; ``C = 1`` for 3-D
        ``B``. Column ``(iy * nx + ix) * C + c`` is channel ``c`` of the
        patch whose top-left texel is ``(iy * s, ix * s)`` (``s`` = 1 with
        overlap, p without), so channel ``c``'s ABTFs are ``P[:, c::C]``.
        Row ``(dy * p + dx) * n_lv + l`` is light/view pair ``l`` of the
        patch's texel ``(dy, dx)``: p² blocks of ``n_lv`` rows, one texel's
        ABRDF each, in row-major order over the patch. float32 for float32
        input, float64 otherwise.

    Raises
    ------
    ValueError
        On another number of dimensions, NaN/Inf (names the index), a bad
        ``p`` or a texture smaller than p x p.

    Notes
    -----
    Paper 1, §3.3, writes the measurement matrix of ABTFs as
    :math:`\\mathbf{1}_{p^2} \\otimes \\mathbf{M}`. With the row order above
    that is the identity: ``np.kron(np.eye(p * p), M) @ P`` is the block
    diagonal ``M`` applied to each texel's ABRDF, i.e. the patch matrix of
    ``M`` applied to ``B`` (the tests check this). The all-ones vector
    cannot be meant (``kron(ones((p*p, 1)), M)`` has ``n_lv`` columns, not
    :math:`p^2 n_{lv}`), nor the all-ones matrix (it would sum the texels'
    measurements); :math:`\\mathbf{1}` is the identity, and
    :math:`\\mathbf{I} \\otimes \\mathbf{M}` (not
    :math:`\\mathbf{M} \\otimes \\mathbf{I}`) because blocks are texels and
    rows within a block are light/view pairs.
    """
    b = _as_float(B, "B", ndim=(3, 4))
    b4 = b[..., None] if b.ndim == 3 else b
    n_lv, h, w, c = b4.shape
    p = _patch_size(p)
    patch_grid(h, w, p, overlap=overlap)
    s = 1 if overlap else p
    win = sliding_window_view(b4, (p, p), axis=(1, 2))[:, ::s, ::s]    # (n_lv, ny, nx, C, p, p), a view
    ny, nx = win.shape[1:3]
    return win.transpose(4, 5, 0, 1, 2, 3).reshape(p * p * n_lv, ny * nx * c)  # rows (dy, dx, l), cols (iy, ix, c)


def blend_patches(columns: np.ndarray, texture_shape: tuple[int, ...], p: int = 3) -> np.ndarray:
    """Blend all overlapping p x p patches back to texels, every patch weighted equally.

    Parameters
    ----------
    columns : (p * p * n_lv, ny * nx * C) array_like
        ABTF columns of *every* window (``patch_matrix(..., overlap=True)``
        layout), e.g. a basis reconstruction ``U @ (U.T @ P)``.
    texture_shape : tuple
        ``(n_lv, h, w, C)`` or ``(n_lv, h, w)``: the shape of the ``B`` that
        was patched.
    p : int
        Patch size.

    Returns
    -------
    B : texture_shape ndarray
        Each texel is the mean of its values in all patches that contain it;
        float32 for float32 input, float64 otherwise.

    Raises
    ------
    ValueError
        If ``columns`` is not shaped as the overlapping patches of
        ``texture_shape`` (non-overlapping patches leave texels uncovered
        and cannot be blended), or on NaN/Inf (names the index).

    Notes
    -----
    Paper 1, §4.1.2: "blending the patches, all texels weighted equally".
    Border rule: an interior texel lies in :math:`p^2` patches; texel row
    ``k`` counted from the top or bottom border lies in
    ``min(k + 1, p, ny)`` patch rows only (columns alike), and averages
    just the patches it lies in (a corner texel is its single patch's
    value). The mean is computed as the last covering
    patch's value plus the mean deviation from it, so that identical
    patches blend back to exactly that value (``blend_patches(patch_matrix(
    B, p, overlap=True), B.shape, p) == B`` bit for bit; a plain sum over
    count is not exact: ``(x + x + x) / 3 != x`` for a third of all floats).
    """
    shape = tuple(int(v) for v in texture_shape)
    if len(shape) not in (3, 4):
        raise ValueError(f"texture_shape must be (n_lv, h, w) or (n_lv, h, w, C), got {texture_shape!r}")
    n_lv, h, w = shape[:3]
    c = shape[3] if len(shape) == 4 else 1
    p = _patch_size(p)
    ny, nx = patch_grid(h, w, p, overlap=True)
    cols = _as_float(columns, "columns", ndim=(2,))
    if cols.shape != (p * p * n_lv, ny * nx * c):
        raise ValueError(f"columns must be ({p * p * n_lv}, {ny * nx * c}), the overlapping {p} x {p} patches of "
                         f"a {shape} texture (patch_matrix(..., overlap=True)), got shape {cols.shape}")
    win = cols.reshape(p, p, n_lv, ny, nx, c)
    offsets = [(dy, dx) for dy in range(p) for dx in range(p)]
    ref = np.empty((n_lv, h, w, c), cols.dtype)
    for dy, dx in offsets:                                          # every texel: some patch that covers it
        ref[:, dy:dy + ny, dx:dx + nx] = win[dy, dx]
    dev = np.zeros_like(ref)
    for dy, dx in offsets:
        dev[:, dy:dy + ny, dx:dx + nx] += win[dy, dx] - ref[:, dy:dy + ny, dx:dx + nx]
    count = np.outer(np.convolve(np.ones(ny), np.ones(p)), np.convolve(np.ones(nx), np.ones(p)))
    return (ref + dev / count.astype(cols.dtype)[:, :, None]).reshape(shape)  # eq. mean over covering patches
