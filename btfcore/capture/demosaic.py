"""Demosaicing of floating-point (HDR) Bayer colour-filter-array images.

Two linear methods, each named after its source as in colour-demosaicing:

* :func:`demosaicing_CFA_Bayer_bilinear` -- bilinear interpolation of each
  colour plane from its own samples;
* :func:`demosaicing_CFA_Bayer_Malvar2004` -- the gradient-corrected linear
  interpolation of Malvar, He & Cutler (2004): bilinear interpolation plus a
  Laplacian correction from the pixel's own colour, as four 5x5 filters.

:func:`demosaic` dispatches by name (:data:`DEMOSAICING_METHODS`). Both
methods are linear and keep the input's scale: no clipping to ``[0, 1]``, so
they apply to merged HDR radiance in the Bayer domain (stage 3,
docs/architecture.md, "Stages").

Layouts (``pattern``) name the 2x2 top-left block of the mosaic read
row-major, as :func:`btfcore.simulate.sensor.bayer_channel_index` does:
``'RGGB'`` has R at ``(0, 0)``, G at ``(0, 1)`` and ``(1, 0)``, B at ``(1, 1)``.

Borders
-------
``border='reflect'`` (default) extends the mosaic by half-sample symmetric
reflection (``d c b a | a b c d``), as ``scipy.ndimage.convolve`` does in
colour-demosaicing, so that both methods reproduce
``colour_demosaicing.demosaicing_CFA_Bayer_bilinear`` and
``demosaicing_CFA_Bayer_Malvar2004`` on every pixel, the border included.
That reflection swaps the colour parity of the mirrored rows and columns: on
the outermost one (bilinear) or two (Malvar) pixel rows and columns it mixes
colours or over-weights samples (bilinear R/B there is up to 1.5x too
bright). ``border='mirror'`` reflects about the edge pixel (``c b | a b c``),
which keeps the Bayer parity and makes the border estimates interpolations of
the right colour. In the pipeline the sample lies at least two pixels inside
the region of interest, so the choice does not reach the BTF.

References
----------
.. [1] H. S. Malvar, L.-W. He and R. Cutler, "High-quality linear
   interpolation for demosaicing of Bayer-patterned color images", Proc.
   IEEE ICASSP 2004, vol. 3, pp. 485-488.
.. [2] O. Losson, L. Macaire and Y. Yang, "Comparison of color demosaicing
   methods", Advances in Imaging and Electron Physics 162 (2010), 173-265
   (bilinear interpolation).
.. [3] Colour Developers, colour-demosaicing 0.2 (BSD-3-Clause): the
   reference implementation the tests compare against.
"""

from __future__ import annotations

from typing import Callable

import cv2
import numpy as np

from btfcore.dome import BAYER_PATTERNS

__all__ = [
    "DEMOSAICING_METHODS",
    "demosaic",
    "demosaicing_CFA_Bayer_Malvar2004",
    "demosaicing_CFA_Bayer_bilinear",
]

#: Border names -> OpenCV modes: 'reflect' is numpy's 'symmetric' (d c b a | a b c d), 'mirror' numpy's
#: 'reflect' (c b | a b c).
_BORDERS = {"reflect": cv2.BORDER_REFLECT, "mirror": cv2.BORDER_REFLECT_101}

# ----------------------------------------------------------------------------- kernels
# Malvar et al. (2004), Fig. 2, in units of 1/8 (the paper's alpha = 1/2, beta = 5/8, gamma = 3/4).

#: G at R or B sites: bilinear G plus alpha times the R (B) Laplacian.
_K_G_AT_RB = np.array([[0, 0, -1, 0, 0],
                       [0, 0, 2, 0, 0],
                       [-1, 2, 4, 2, -1],
                       [0, 0, 2, 0, 0],
                       [0, 0, -1, 0, 0]], dtype=np.float64) / 8
#: R (B) at a G site whose row holds R (B): horizontal neighbours plus beta times the G Laplacian.
_K_ROW = np.array([[0, 0, 0.5, 0, 0],
                   [0, -1, 0, -1, 0],
                   [-1, 4, 5, 4, -1],
                   [0, -1, 0, -1, 0],
                   [0, 0, 0.5, 0, 0]], dtype=np.float64) / 8
#: R (B) at a G site whose column holds R (B): the transpose.
_K_COL = _K_ROW.T.copy()
#: R at B sites and B at R sites: diagonal neighbours plus gamma times the B (R) Laplacian.
_K_DIAG = np.array([[0, 0, -1.5, 0, 0],
                    [0, 2, 0, 2, 0],
                    [-1.5, 0, 6, 0, -1.5],
                    [0, 2, 0, 2, 0],
                    [0, 0, -1.5, 0, 0]], dtype=np.float64) / 8
#: Bilinear kernels (Losson et al. 2010) applied to the zero-filled colour planes.
_K_BILINEAR_G = np.array([[0, 1, 0], [1, 4, 1], [0, 1, 0]], dtype=np.float64) / 4
_K_BILINEAR_RB = np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]], dtype=np.float64) / 4


def _prepare(cfa: np.ndarray, pattern: str, border: str, min_size: int,
             check_finite: bool = True) -> tuple[np.ndarray, str, str]:
    arr = np.asarray(cfa)
    if arr.ndim < 2:
        raise ValueError(f"cfa must be (..., H, W), got shape {arr.shape}")
    if arr.dtype.kind not in "fiu" and arr.dtype != np.bool_:
        raise TypeError(f"cfa must be a real numeric array, got dtype {arr.dtype}")
    if arr.dtype not in (np.float32, np.float64):
        arr = arr.astype(np.float64)
    if min(arr.shape[-2:]) < min_size:
        raise ValueError(f"cfa must be at least {min_size}x{min_size} pixels, got {arr.shape[-2:]}")
    pat = str(pattern).upper()
    if pat not in BAYER_PATTERNS:
        raise ValueError(f"unknown Bayer pattern {pattern!r}; choose one of {', '.join(BAYER_PATTERNS)}")
    if border not in _BORDERS:
        raise ValueError(f"unknown border {border!r}; choose one of {', '.join(_BORDERS)}")
    bad = ~np.isfinite(arr) if check_finite else None
    if bad is not None and bad.any():
        idx = tuple(int(v) for v in np.argwhere(bad)[0])
        raise ValueError(f"cfa contains NaN or Inf ({int(bad.sum())} values), first at index {idx}; "
                         "mask or repair those raw values (e.g. from the HDR merge) before demosaicing")
    return arr, pat, border


def _flatten(arr: np.ndarray, out: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """``arr`` as ``(n, H, W)`` and the ``(n, H, W, 3)`` output: a view of ``out`` or a new array."""
    flat = arr.reshape((-1,) + arr.shape[-2:])
    if out is None:
        return flat, np.empty(flat.shape + (3,), dtype=arr.dtype)
    if not isinstance(out, np.ndarray) or out.shape != arr.shape + (3,) or out.dtype != arr.dtype:
        raise ValueError(f"out must be a {arr.dtype} array of shape {arr.shape + (3,)}, got "
                         f"{getattr(out, 'dtype', type(out).__name__)} {getattr(out, 'shape', '')}")
    view = out.reshape(flat.shape + (3,))
    if not np.shares_memory(view, out):
        raise ValueError("out must be reshapeable to (n, H, W, 3) without a copy (e.g. C-contiguous)")
    return flat, view


def _sites(pattern: str) -> dict[str, list[tuple[int, int]]]:
    """Parity offsets ``(r0, c0)`` of each filter colour in the 2x2 block."""
    sites: dict[str, list[tuple[int, int]]] = {"R": [], "G": [], "B": []}
    for k, ch in enumerate(pattern):
        sites[ch].append(divmod(k, 2))
    return sites


# ----------------------------------------------------------------------------- methods


def demosaicing_CFA_Bayer_bilinear(cfa: np.ndarray, pattern: str = "RGGB", *, border: str = "reflect",
                                   out: np.ndarray | None = None, check_finite: bool = True) -> np.ndarray:
    """Bilinear demosaicing of a Bayer mosaic.

    Parameters
    ----------
    cfa : (..., H, W) ndarray
        Linear Bayer mosaic (any scale, HDR values > 1 allowed); leading axes
        are a batch. float32 stays float32, anything else becomes float64.
    pattern : {'RGGB', 'BGGR', 'GRBG', 'GBRG'}
        The 2x2 top-left block of the mosaic, read row-major.
    border : {'reflect', 'mirror'}
        Border extension (module docstring): ``'reflect'`` reproduces
        colour-demosaicing everywhere, ``'mirror'`` keeps the Bayer parity.
    out : (..., H, W, 3) ndarray, optional
        Buffer of the result's dtype to write into, C-contiguous or a strided view
        that reshapes without a copy (e.g. three channels of a wider stack); reuse it
        across calls: first-touch of new memory is slow (docs/architecture.md, "Pitfalls").
    check_finite : bool
        Scan ``cfa`` for NaN and Inf (default); ``False`` for a caller that made sure of it, as
        :mod:`scipy.linalg`'s ``check_finite`` (the view chain: its frames are checked once per view).

    Returns
    -------
    rgb : (..., H, W, 3) ndarray
        Same float dtype as the (converted) input, not clipped.

    Raises
    ------
    ValueError
        Unknown pattern or border, fewer than 2x2 pixels, NaN or Inf in ``cfa``
        (the message gives the first index).

    Notes
    -----
    With :math:`m_c` the indicator of the sites of colour :math:`c` and
    :math:`*` the 2-D convolution,

    .. math::
        \\hat G = (m_G \\, x) * \\tfrac14 \\begin{pmatrix} 0&1&0\\\\1&4&1\\\\0&1&0 \\end{pmatrix},
        \\qquad
        \\hat R = (m_R \\, x) * \\tfrac14 \\begin{pmatrix} 1&2&1\\\\2&4&2\\\\1&2&1 \\end{pmatrix}

    and :math:`\\hat B` like :math:`\\hat R`. At its own sites a colour keeps
    the measured value (with ``border='reflect'``, not on the outermost rows
    and columns, as in colour-demosaicing). Accumulation is in float64.

    References
    ----------
    .. [1] O. Losson, L. Macaire and Y. Yang, "Comparison of color demosaicing
       methods", Advances in Imaging and Electron Physics 162 (2010), 173-265.
    .. [2] H. S. Malvar, L.-W. He and R. Cutler, "High-quality linear
       interpolation for demosaicing of Bayer-patterned color images", Proc.
       IEEE ICASSP 2004 (bilinear interpolation as the baseline).

    Examples
    --------
    >>> cfa = np.full((4, 4), 2.0)
    >>> demosaicing_CFA_Bayer_bilinear(cfa, border="mirror")[1, 1]
    array([2., 2., 2.])
    """
    arr, pat, border = _prepare(cfa, pattern, border, 2, check_finite)
    flat, res = _flatten(arr, out)
    sites = _sites(pat)
    plane = np.empty(flat.shape[1:], dtype=np.float64)
    for f in range(flat.shape[0]):
        for ch, kernel in (("R", _K_BILINEAR_RB), ("G", _K_BILINEAR_G), ("B", _K_BILINEAR_RB)):
            plane.fill(0.0)
            for r0, c0 in sites[ch]:
                plane[r0::2, c0::2] = flat[f, r0::2, c0::2]                          # eq. m_c x
            # own sites too: the kernel returns the sample there (not on a 'reflect' border)
            res[f, ..., _CH[ch]] = cv2.filter2D(plane, -1, kernel, borderType=_BORDERS[border])   # eq. *K
    return res.reshape(arr.shape + (3,)) if out is None else out


def demosaicing_CFA_Bayer_Malvar2004(cfa: np.ndarray, pattern: str = "RGGB", *, border: str = "reflect",
                                     out: np.ndarray | None = None, check_finite: bool = True) -> np.ndarray:
    """Gradient-corrected linear demosaicing of Malvar, He & Cutler (2004).

    Parameters
    ----------
    cfa : (..., H, W) ndarray
        Linear Bayer mosaic (any scale, HDR values > 1 allowed); leading axes
        are a batch. float32 stays float32, anything else becomes float64.
    pattern : {'RGGB', 'BGGR', 'GRBG', 'GBRG'}
        The 2x2 top-left block of the mosaic, read row-major.
    border : {'reflect', 'mirror'}
        Border extension (module docstring): ``'reflect'`` reproduces
        colour-demosaicing everywhere, ``'mirror'`` keeps the Bayer parity.
    out : (..., H, W, 3) ndarray, optional
        Buffer of the result's dtype to write into, C-contiguous or a strided view
        that reshapes without a copy (e.g. three channels of a wider stack); reuse it
        across calls: first-touch of new memory is slow (docs/architecture.md, "Pitfalls").
    check_finite : bool
        Scan ``cfa`` for NaN and Inf (default); ``False`` for a caller that made sure of it, as
        :mod:`scipy.linalg`'s ``check_finite`` (the view chain: its frames are checked once per view).

    Returns
    -------
    rgb : (..., H, W, 3) ndarray
        Same float dtype as the (converted) input, not clipped: like every
        filter with negative taps it can undershoot (even below 0) next to
        strong edges.

    Raises
    ------
    ValueError
        Unknown pattern or border, fewer than 3x3 pixels, NaN or Inf in ``cfa``
        (the message gives the first index).

    Notes
    -----
    Each missing value is the bilinear estimate corrected by a scaled discrete
    Laplacian of the colour measured at that site [1]_ (eqs. 2-4):

    .. math::
        \\hat g(i, j) &= \\hat g_B(i, j) + \\alpha \\, \\Delta_R(i, j) \\\\
        \\hat r(i, j) &= \\hat r_B(i, j) + \\beta \\, \\Delta_G(i, j) \\\\
        \\hat r(i, j) &= \\hat r_B(i, j) + \\gamma \\, \\Delta_B(i, j)

    (first line at R sites, likewise at B sites; second line at G sites;
    third at B sites; B symmetrically), with the gains
    :math:`\\alpha = 1/2, \\beta = 5/8, \\gamma = 3/4` that minimise the
    mean-square error on the Kodak set. Folded into one 5x5 filter each (the
    paper's Fig. 2, in units of 1/8):

    .. math::
        K_{G@RB} = \\tfrac18 \\begin{pmatrix}
            0&0&-1&0&0\\\\0&0&2&0&0\\\\-1&2&4&2&-1\\\\0&0&2&0&0\\\\0&0&-1&0&0\\end{pmatrix},
        \\quad
        K_{row} = \\tfrac18 \\begin{pmatrix}
            0&0&\\tfrac12&0&0\\\\0&-1&0&-1&0\\\\-1&4&5&4&-1\\\\0&-1&0&-1&0\\\\0&0&\\tfrac12&0&0\\end{pmatrix},
        \\quad
        K_{col} = K_{row}^T,
        \\quad
        K_{diag} = \\tfrac18 \\begin{pmatrix}
            0&0&-\\tfrac32&0&0\\\\0&2&0&2&0\\\\-\\tfrac32&0&6&0&-\\tfrac32\\\\0&2&0&2&0\\\\0&0&-\\tfrac32&0&0\\end{pmatrix}

    :math:`K_{row}` gives R (B) at a G site in an R (B) row, :math:`K_{col}`
    at a G site in an R (B) column and :math:`K_{diag}` R at B sites and B at
    R sites. Every filter sums to one, so a constant image is reproduced
    exactly. Each filter runs over the whole frame in float64
    (``cv2.filter2D``, vectorised) and is read at the sites that need it.

    References
    ----------
    .. [1] H. S. Malvar, L.-W. He and R. Cutler, "High-quality linear
       interpolation for demosaicing of Bayer-patterned color images", Proc.
       IEEE ICASSP 2004, vol. 3, pp. 485-488.

    Examples
    --------
    >>> cfa = np.full((6, 6), 3.5)
    >>> demosaicing_CFA_Bayer_Malvar2004(cfa, "GRBG")[2, 3]
    array([3.5, 3.5, 3.5])
    """
    arr, pat, border = _prepare(cfa, pattern, border, 3, check_finite)
    flat, res = _flatten(arr, out)
    kernels = {"G@RB": _K_G_AT_RB, "row": _K_ROW, "col": _K_COL, "diag": _K_DIAG}
    for f in range(flat.shape[0]):
        image = flat[f].astype(np.float64)        # accumulated in float64, as the reference does
        # each filter over the whole frame by OpenCV (vectorised float64), read at the sites that need it
        est = {name: cv2.filter2D(image, -1, k, borderType=_BORDERS[border]) for name, k in kernels.items()}
        dst = res[f]
        for k, ch in enumerate(pat):
            site = (slice(k // 2, None, 2), slice(k % 2, None, 2))
            dst[site + (_CH[ch],)] = flat[f][site]                            # measured colour kept
            if ch == "G":
                # the other pixel of this row holds R or B; that colour is interpolated along the row
                row_ch = pat[2 * (k // 2) + (1 - k % 2)]
                col_ch = "B" if row_ch == "R" else "R"
                dst[site + (_CH[row_ch],)] = est["row"][site]                 # eq. r = r_B + beta lap(G), row
                dst[site + (_CH[col_ch],)] = est["col"][site]                 # eq. r = r_B + beta lap(G), column
            else:
                other = "B" if ch == "R" else "R"
                dst[site + (_CH["G"],)] = est["G@RB"][site]                   # eq. g = g_B + alpha lap(R)
                dst[site + (_CH[other],)] = est["diag"][site]                 # eq. b = b_B + gamma lap(R)
    return res.reshape(arr.shape + (3,)) if out is None else out


_CH = {"R": 0, "G": 1, "B": 2}

#: Demosaicing methods by name, for :func:`demosaic`.
DEMOSAICING_METHODS: dict[str, Callable[..., np.ndarray]] = {
    "bilinear": demosaicing_CFA_Bayer_bilinear,
    "malvar2004": demosaicing_CFA_Bayer_Malvar2004,
}


def demosaic(cfa: np.ndarray, pattern: str = "RGGB", method: str = "malvar2004", *,
             border: str = "reflect", out: np.ndarray | None = None, check_finite: bool = True) -> np.ndarray:
    """Demosaic a Bayer mosaic with a method chosen by name.

    Parameters
    ----------
    cfa : (..., H, W) ndarray
        Linear Bayer mosaic; leading axes are a batch.
    pattern : {'RGGB', 'BGGR', 'GRBG', 'GBRG'}
        The 2x2 top-left block of the mosaic, read row-major.
    method : {'malvar2004', 'bilinear'}
        Key of :data:`DEMOSAICING_METHODS` (case-insensitive).
    border : {'reflect', 'mirror'}
        Border extension, see :func:`demosaicing_CFA_Bayer_Malvar2004`.
    out : (..., H, W, 3) ndarray, optional
        Buffer to write the result into.
    check_finite : bool
        Scan ``cfa`` for NaN and Inf (default), as the methods do.

    Returns
    -------
    rgb : (..., H, W, 3) ndarray
        float32 for float32 input, float64 otherwise.

    Raises
    ------
    ValueError
        Unknown method (the message lists the valid ones), or any error of
        the method itself.

    References
    ----------
    .. [1] H. S. Malvar, L.-W. He and R. Cutler, "High-quality linear
       interpolation for demosaicing of Bayer-patterned color images", Proc.
       IEEE ICASSP 2004, vol. 3, pp. 485-488.
    """
    key = str(method).lower()
    if key not in DEMOSAICING_METHODS:
        raise ValueError(f"unknown demosaicing method {method!r}; valid methods: {', '.join(DEMOSAICING_METHODS)}")
    return DEMOSAICING_METHODS[key](cfa, pattern, border=border, out=out, check_finite=check_finite)
