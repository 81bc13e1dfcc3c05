"""Colour transforms that reduce the dynamic range of a BTF before model fitting.

* **YUV** (:func:`rgb_to_yuv`, :func:`yuv_to_rgb`): the linear BT.601
  analogue YUV of OpenCV's ``COLOR_RGB2YUV`` without its 0.5 offset.
* **Log YUV** (:func:`to_log_yuv`, :func:`from_log_yuv`): den Brok et al.
  fit their linear models to :math:`(\\log Y, U/Y, V/Y)`, "converting the
  measured HDR RGB data to YUV color space, dividing the U and V values by
  the corresponding Y value and applying log to the Y values" (paper 1,
  §3.1).
* **Luminance** (:func:`luminance`, :data:`REC709_LUMA`): relative luminance
  Y of linear RGB with the ITU-R BT.709 (sRGB primaries) weights, the one
  definition used by the simulator, the renderer, the reports and the
  ingest's error against the truth.
* **Nielsen et al.'s mapping** (:func:`nielsen_map`, :func:`nielsen_unmap`,
  with :func:`cos_weight` and :func:`reference_abrdf`): the log of each
  ABRDF relative to the median ABRDF, cosine-weighted (paper 4, eq. (3)).

Colour functions take channels on the last axis, ``(..., 3)``; a BTF matrix
``B`` of shape ``(n_lv, n_tx * 3)`` (columns texel-major, channel fastest:
docs/architecture.md, "Matrix convention") is passed as ``B.reshape(n_lv, -1, 3)``, a view. Every function
keeps float32 as float32 and computes everything else in float64, and refuses
NaN and Inf with the index of the first one.

References
----------
.. [1] The thesis, App. paper 1 (den Brok et al.): D. den Brok, H. C.
   Steinhausen, M. B. Hullin and R. Klein, "Patch-based sparse reconstruction
   of material BTFs", Journal of WSCG 22, 2014, §3.1; App. paper 4, D. den
   Brok, M. Weinmann and R. Klein, "Rapid material capture through sparse and
   multiplexed measurements", Computers & Graphics 73, 2018, §3.3, eq. (3).
.. [2] J. B. Nielsen, H. W. Jensen and R. Ramamoorthi, "On optimal, minimal
   BRDF sampling for reflectance acquisition", ACM TOG 34(6), 2015.
.. [3] ITU-R Recommendation BT.601 (luma weights); OpenCV ``cvtColor``
   documentation, "RGB <-> YUV" (the U and V scale factors 0.492, 0.877).
.. [4] ITU-R Recommendation BT.709, item 3.2 (relative luminance of linear
   R, G, B with sRGB primaries: 0.2126, 0.7152, 0.0722).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "LOG_YUV_EPS",
    "NIELSEN_EPS",
    "REC709_LUMA",
    "RGB_FROM_YUV",
    "YUV_FROM_RGB",
    "cos_weight",
    "from_log_yuv",
    "log_luminance",
    "luminance",
    "nielsen_map",
    "nielsen_unmap",
    "reference_abrdf",
    "rgb_to_yuv",
    "to_log_yuv",
    "yuv_to_rgb",
]

#: Rows give Y, U, V from linear (R, G, B): BT.601 luma, U = 0.492 (B - Y), V = 0.877 (R - Y).
YUV_FROM_RGB = np.array([[0.299, 0.587, 0.114],
                         [-0.492 * 0.299, -0.492 * 0.587, 0.492 * (1.0 - 0.114)],
                         [0.877 * (1.0 - 0.299), -0.877 * 0.587, -0.877 * 0.114]])
#: Relative luminance weights of linear (R, G, B), ITU-R BT.709 [4] (read-only).
REC709_LUMA = np.array([0.2126, 0.7152, 0.0722])
REC709_LUMA.setflags(write=False)
#: Exact inverse of :data:`YUV_FROM_RGB` (its first column is all ones: R = G = B = Y where U = V = 0).
RGB_FROM_YUV = np.linalg.inv(YUV_FROM_RGB)
#: Default floor of Y in :func:`to_log_yuv`, absolute, in the BTF's units (calibrated BTF: reflectance * cos).
LOG_YUV_EPS = 1e-4
#: Nielsen et al.'s offset and cosine floor (paper 4 §3.3, after eq. (3)).
NIELSEN_EPS = 1e-4


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Relative luminance of linear RGB, ``rgb @ REC709_LUMA`` (ITU-R BT.709 [4]).

    Parameters
    ----------
    rgb : (..., 3) array_like
        Linear RGB, channels on the last axis.

    Returns
    -------
    y : (...) ndarray
        :math:`Y = 0.2126 R + 0.7152 G + 0.0722 B`, in numpy's promotion of the
        input's dtype with float64 (float32 input gives float64).
    """
    return np.asarray(rgb) @ REC709_LUMA


# --------------------------------------------------------------------------- validation


def _as_float(x, name: str, ndim: tuple[int, ...] | None = None) -> np.ndarray:
    """``x`` as a float ndarray (float32 kept, other reals as float64), refusing NaN/Inf by index."""
    a = np.asarray(x)
    if a.dtype.kind not in "iuf":
        raise ValueError(f"{name} must hold real numbers, got dtype {a.dtype}")
    if ndim is not None and a.ndim not in ndim:
        raise ValueError(f"{name} must have {' or '.join(map(str, ndim))} dimensions, got shape {a.shape}")
    if a.dtype not in (np.float32, np.float64):
        a = a.astype(np.float64)
    finite = np.isfinite(a)
    if not finite.all():
        idx = [int(i) for i in np.unravel_index(int(np.argmin(finite)), a.shape)]
        raise ValueError(
            f"{name}{idx} = {a[tuple(idx)]} is not finite ({a.size - int(finite.sum())} NaN/Inf values in all); "
            f"repair or mask them (e.g. re-merge the exposures of that texel) before this step"
        )
    return a


def _as_rgb(x, name: str) -> np.ndarray:
    a = _as_float(x, name)
    if a.ndim < 1 or a.shape[-1] != 3:
        raise ValueError(f"{name} must have 3 channels on its last axis, got shape {a.shape}")
    return a


def _positive(value: float, name: str) -> float:
    v = float(value)
    if not (v > 0.0 and np.isfinite(v)):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return v


# --------------------------------------------------------------------------- YUV


def rgb_to_yuv(rgb: np.ndarray) -> np.ndarray:
    """Linear RGB to linear YUV (BT.601 luma, analogue U and V scaling).

    Parameters
    ----------
    rgb : (..., 3) array_like
        Linear (HDR) RGB, channels last; any sign.

    Returns
    -------
    yuv : (..., 3) ndarray
        float32 for float32 input, float64 otherwise.

    Raises
    ------
    ValueError
        If the last axis is not 3 or on NaN/Inf (names the first index).

    Notes
    -----
    .. math::
        Y = 0.299 R + 0.587 G + 0.114 B, \\quad U = 0.492 (B - Y), \\quad V = 0.877 (R - Y)

    (BT.601 luma weights; the analogue-PAL chroma factors
    :math:`0.436 / 0.886` and :math:`0.615 / 0.701` rounded to three digits,
    as in OpenCV's ``COLOR_RGB2YUV``, which adds 0.5 to U and V for float
    images). The transform is linear and has no offset, so it commutes with
    scaling the radiance, and grey (R = G = B) has U = V = 0.
    """
    x = _as_rgb(rgb, "rgb")
    return x @ YUV_FROM_RGB.T.astype(x.dtype)                      # eq. (Y, U, V) = M (R, G, B)


def yuv_to_rgb(yuv: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rgb_to_yuv`.

    Parameters
    ----------
    yuv : (..., 3) array_like

    Returns
    -------
    rgb : (..., 3) ndarray
        float32 for float32 input, float64 otherwise. Exact to float
        rounding: ``yuv_to_rgb(rgb_to_yuv(x)) == x`` up to a few ulps of
        ``max(|R|, |G|, |B|)`` of each pixel.

    Raises
    ------
    ValueError
        As :func:`rgb_to_yuv`.

    Notes
    -----
    Uses the inverse matrix computed in float64 (:data:`RGB_FROM_YUV`), not
    OpenCV's four rounded constants, whose round trip is off by about 1e-4.
    """
    x = _as_rgb(yuv, "yuv")
    return x @ RGB_FROM_YUV.T.astype(x.dtype)                      # eq. (R, G, B) = M^-1 (Y, U, V)


# --------------------------------------------------------------------------- log YUV


def to_log_yuv(rgb: np.ndarray, eps: float = LOG_YUV_EPS) -> np.ndarray:
    """Linear RGB to :math:`(\\log Y, U/Y, V/Y)` with Y floored at ``eps``.

    Parameters
    ----------
    rgb : (..., 3) array_like
        Linear HDR RGB, channels last.
    eps : float
        Floor of Y, > 0, absolute (in the units of ``rgb``). The default
        1e-4 suits calibrated BTFs (reflectance times cosine, a white
        standard at normal incidence is about 0.3); for other units pass
        e.g. ``1e-4 * np.median(Y)`` of the whole material. It is absolute
        so that every chunk of a material is transformed alike.

    Returns
    -------
    x : (..., 3) ndarray
        ``x[..., 0] = log(max(Y, eps))``, ``x[..., 1:] = (U, V) / max(Y, eps)``;
        float32 for float32 input, float64 otherwise.

    Raises
    ------
    ValueError
        If the last axis is not 3, on NaN/Inf (names the first index), or if
        ``eps`` is not a finite number > 0.

    Notes
    -----
    Paper 1, §3.1: "converting the measured HDR RGB data to YUV color space,
    dividing the U and V values by the corresponding Y value and applying
    log to the Y values". With :math:`\\tilde Y = \\max(Y, \\varepsilon)`,

    .. math:: x = (\\log \\tilde Y,\\; U / \\tilde Y,\\; V / \\tilde Y).

    Where :math:`Y \\ge \\varepsilon` :func:`from_log_yuv` inverts this to
    float rounding. Where :math:`Y < \\varepsilon` (dark or shadowed texels,
    noise below zero) the luminance is lost and the chroma is kept:
    the round trip returns :math:`\\mathrm{rgb} + (\\varepsilon - Y)(1, 1, 1)`,
    i.e. grey is added until :math:`Y = \\varepsilon`, and U and V are
    unchanged. Dividing by :math:`\\tilde Y` instead of Y bounds the
    chromaticities of near-black texels by :math:`|U| / \\varepsilon`.
    """
    e = _positive(eps, "eps")
    yuv = rgb_to_yuv(rgb)
    y = np.maximum(yuv[..., :1], e)                                 # Y~ = max(Y, eps)
    yuv[..., 1:] /= y                                               # eq. (U/Y, V/Y)  (paper 1, §3.1)
    yuv[..., :1] = np.log(y)                                        # eq. log Y  (paper 1, §3.1)
    return yuv


def log_luminance(rgb: np.ndarray, eps: float = LOG_YUV_EPS) -> np.ndarray:
    """The log Y channel of :func:`to_log_yuv` alone, without forming U and V.

    Parameters
    ----------
    rgb : (..., 3) array_like
        Linear HDR RGB, channels last.
    eps : float
        Floor of Y, as in :func:`to_log_yuv`.

    Returns
    -------
    log_y : (...) ndarray
        :math:`\\log \\max(Y, \\varepsilon)`; float32 for float32 input,
        float64 otherwise. Equal to ``to_log_yuv(rgb, eps)[..., 0]``.

    Raises
    ------
    ValueError
        As :func:`to_log_yuv`.

    Notes
    -----
    Paper 1, §3.1 (log Y), the channel the thesis' errors are computed on
    (paper 1 Table 1, VMV Table 1).
    """
    e = _positive(eps, "eps")
    x = _as_rgb(rgb, "rgb")
    y = x @ YUV_FROM_RGB[0].astype(x.dtype)                         # eq. Y = 0.299 R + 0.587 G + 0.114 B
    return np.log(np.maximum(y, x.dtype.type(e)))                   # eq. log Y~  (paper 1, §3.1)


def from_log_yuv(x: np.ndarray) -> np.ndarray:
    """Inverse of :func:`to_log_yuv`: :math:`(\\log Y, U/Y, V/Y)` to linear RGB.

    Parameters
    ----------
    x : (..., 3) array_like
        Log Y, U/Y, V/Y; e.g. a model's reconstruction.

    Returns
    -------
    rgb : (..., 3) ndarray
        Linear RGB, in the dtype of ``x`` if float32, else float64.

    Raises
    ------
    ValueError
        On a last axis other than 3, NaN/Inf (names the first index), or a
        log Y whose exp overflows the dtype (names the index).

    Notes
    -----
    :math:`Y = e^{x_0}`, :math:`(U, V) = (x_1, x_2)\\, Y`, then
    :func:`yuv_to_rgb`. The floor ``eps`` of :func:`to_log_yuv` is not
    needed here: every log Y, including one below :math:`\\log\\varepsilon`
    that a model may produce, maps back to a positive Y.
    """
    a = _as_rgb(x, "x")
    big = np.log(np.finfo(a.dtype).max)
    if a.size and a[..., 0].max() >= big:
        idx = [int(i) for i in np.unravel_index(int(np.argmax(a[..., 0])), a.shape[:-1])]
        raise ValueError(f"x{idx + [0]} = {a[tuple(idx) + (0,)]} is log Y >= {big:.1f}: exp overflows {a.dtype}")
    yuv = np.empty_like(a)
    yuv[..., :1] = np.exp(a[..., :1])                               # eq. Y = exp(log Y)
    yuv[..., 1:] = a[..., 1:] * yuv[..., :1]                        # eq. (U, V) = (U/Y, V/Y) Y
    return yuv @ RGB_FROM_YUV.T.astype(a.dtype)


# --------------------------------------------------------------------------- Nielsen et al.


def cos_weight(light_dir: np.ndarray, view_dir: np.ndarray, eps: float = NIELSEN_EPS) -> np.ndarray:
    """Nielsen et al.'s cosine weight of each light/view pair.

    Parameters
    ----------
    light_dir, view_dir : (n_lv, 3) array_like
        Light and view direction of each row of ``B`` in the sample frame
        (z = surface normal), e.g. the BTF store's ``light_dir`` and
        ``view_dir``; normalised here.
    eps : float
        Floor, > 0 (paper 4: 1e-4).

    Returns
    -------
    cosw : (n_lv,) ndarray of float64
        :math:`\\max(\\cos\\vartheta_i, \\cos\\vartheta_o, \\varepsilon)`.

    Raises
    ------
    ValueError
        On shapes that are not ``(n_lv, 3)`` alike, NaN/Inf or a zero-length
        direction (names the row), or a bad ``eps``.

    Notes
    -----
    Paper 4, below eq. (3):
    :math:`\\cos_\\mathrm{weight} := \\max\\{\\cos\\vartheta_i, \\cos\\vartheta_o, \\varepsilon\\}`.
    """
    e = _positive(eps, "eps")
    cos = []
    for name, d in (("light_dir", light_dir), ("view_dir", view_dir)):
        a = _as_float(d, name, ndim=(2,)).astype(np.float64)
        if a.shape[1] != 3:
            raise ValueError(f"{name} must be (n_lv, 3), got shape {a.shape}")
        norm = np.linalg.norm(a, axis=1)
        if not (norm > 0).all():
            raise ValueError(f"{name}[{int(np.argmin(norm))}] has zero length; every row needs a direction")
        cos.append(a[:, 2] / norm)
    if cos[0].shape != cos[1].shape:
        raise ValueError(f"light_dir and view_dir must have the same number of rows, got {len(cos[0])} and "
                         f"{len(cos[1])}")
    return np.maximum(np.maximum(cos[0], cos[1]), e)               # eq. max{cos t_i, cos t_o, eps}  (paper 4)


def reference_abrdf(B: np.ndarray, n_channels: int = 1) -> np.ndarray:
    """The median ABRDF of a BTF, per channel.

    Parameters
    ----------
    B : (n_lv, n_tx) array_like
        BTF matrix; columns texel-major with ``n_channels`` channels fastest
        (column ``t * n_channels + c`` is texel ``t``, channel ``c``).
    n_channels : int
        Channels per texel (3 for an RGB BTF, 1 for one channel).

    Returns
    -------
    rho_ref : (n_lv, n_channels) ndarray
        Median over texels of each row and channel; float32 for float32
        input, float64 otherwise.

    Raises
    ------
    ValueError
        On NaN/Inf (names the index), or if ``n_channels`` does not divide
        the number of columns.

    Notes
    -----
    Paper 4, eq. (3): "ϱ_ref a reference (A)BRDF, taken as the median
    (A)BRDF". The median is taken entry by entry (per light/view pair and
    channel), not as a medoid column. It needs whole rows, so a streaming
    caller chunks ``B`` by rows here.
    """
    b = _as_float(B, "B", ndim=(2,))
    c = int(n_channels)
    if c < 1 or b.shape[1] % c or b.shape[1] == 0:
        raise ValueError(f"n_channels = {n_channels} must divide B's {b.shape[1]} columns (texels x channels)")
    return np.median(b.reshape(b.shape[0], -1, c), axis=1)          # eq. rho_ref = median ABRDF


def _nielsen_operands(B, cosw, rho_ref, eps: float, name: str):
    """Validated ``(b3, cw, den, eps)``: B as (n_lv, n_tx / C, C), cosw (n_lv, 1, 1), rho_ref cosw + eps (n_lv, 1, C)."""
    e = _positive(eps, "eps")
    b = _as_float(B, name, ndim=(2,))
    n_lv = b.shape[0]
    cw = _as_float(cosw, "cosw", ndim=(1,))
    if cw.shape != (n_lv,):
        raise ValueError(f"cosw must be ({n_lv},), one weight per row of {name}, got shape {cw.shape}")
    if not (cw > 0).all():
        i = int(np.argmin(cw > 0))
        raise ValueError(f"cosw[{i}] = {cw[i]} must be > 0; compute it with cos_weight")
    ref = _as_float(rho_ref, "rho_ref", ndim=(1, 2))
    ref = ref.reshape(ref.shape[0], -1)
    if ref.shape[0] != n_lv or b.shape[1] % ref.shape[1]:
        raise ValueError(f"rho_ref must be ({n_lv},) or ({n_lv}, C) with C dividing {name}'s {b.shape[1]} columns, "
                         f"got shape {np.shape(rho_ref)}")
    cw = cw.astype(b.dtype)[:, None, None]
    den = ref.astype(b.dtype)[:, None, :] * cw + e                   # eq. rho_ref cosw + eps
    if not (den > 0).all():
        i, _, c = np.unravel_index(int(np.argmin(den > 0)), den.shape)
        raise ValueError(f"rho_ref[{i}, {c}] * cosw[{i}] + eps <= 0: the reference ABRDF must be > -eps / cosw")
    return b.reshape(n_lv, -1, ref.shape[1]), cw, den, e


def nielsen_map(B: np.ndarray, cosw: np.ndarray, rho_ref: np.ndarray, eps: float = NIELSEN_EPS) -> np.ndarray:
    """Nielsen et al.'s log mapping of a BTF relative to its median ABRDF.

    Parameters
    ----------
    B : (n_lv, n_tx) array_like
        BTF matrix, linear; columns texel-major, channels fastest.
    cosw : (n_lv,) array_like
        :func:`cos_weight` of each row, > 0.
    rho_ref : (n_lv,) or (n_lv, C) array_like
        Reference ABRDF (:func:`reference_abrdf`); with ``C`` channels,
        column ``j`` of ``B`` uses channel ``j % C``.
    eps : float
        Offset, > 0 (paper 4: 1e-4).

    Returns
    -------
    X : (n_lv, n_tx) ndarray
        float32 for float32 ``B``, float64 otherwise.

    Raises
    ------
    ValueError
        On NaN/Inf (names the argument and index), mismatched shapes, or a
        value with :math:`\\varrho \\cos_w + \\varepsilon \\le 0` (names the
        index of ``B``; clip ``B`` at 0 first).

    Notes
    -----
    Paper 4, eq. (3):

    .. math:: \\varrho \\mapsto \\log\\left(\\frac{\\varrho \\cos_\\mathrm{weight} + \\varepsilon}
              {\\varrho_\\mathrm{ref} \\cos_\\mathrm{weight} + \\varepsilon}\\right)

    It is defined for :math:`\\varrho > -\\varepsilon / \\cos_w`, which is
    exactly the range of :func:`nielsen_unmap`, so slightly negative noise
    is kept. The round trip is exact to float rounding relative to
    :math:`|\\varrho| + \\varepsilon / \\cos_w`.
    """
    b3, cw, den, e = _nielsen_operands(B, cosw, rho_ref, eps, "B")
    num = b3 * cw + e                                               # eq. rho cosw + eps
    if not (num > 0).all():
        b = b3.reshape(b3.shape[0], -1)
        i, j = np.unravel_index(int(np.argmin(num > 0)), b.shape)
        raise ValueError(f"B[{i}, {j}] = {b[i, j]} is <= -eps / cosw[{i}] and has no log; clip B at 0 first")
    return np.log(num / den).reshape(b3.shape[0], -1)               # eq. (3)


def nielsen_unmap(X: np.ndarray, cosw: np.ndarray, rho_ref: np.ndarray, eps: float = NIELSEN_EPS) -> np.ndarray:
    """Inverse of :func:`nielsen_map`.

    Parameters
    ----------
    X : (n_lv, n_tx) array_like
        Mapped values (e.g. a model's reconstruction).
    cosw, rho_ref, eps
        As given to :func:`nielsen_map`.

    Returns
    -------
    B : (n_lv, n_tx) ndarray
        :math:`\\varrho = ((\\varrho_\\mathrm{ref} \\cos_w + \\varepsilon) e^X - \\varepsilon) / \\cos_w`,
        always :math:`> -\\varepsilon / \\cos_w`; float32 for float32 ``X``,
        float64 otherwise.

    Raises
    ------
    ValueError
        As :func:`nielsen_map` (NaN/Inf, shapes, bad ``rho_ref``).
    """
    x3, cw, den, e = _nielsen_operands(X, cosw, rho_ref, eps, "X")
    return ((den * np.exp(x3) - e) / cw).reshape(x3.shape[0], -1)  # eq. (3) solved for rho
