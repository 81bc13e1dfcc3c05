"""Colour models of the Bonn DFMF format and its dynamic-range reduction.

A DFMF file (``!DFMF08FCR``) factorises each of three *decorrelated*
channels on its own; an ``int32`` in the file names the colour model that
turns the decoded channels back into linear RGB. The decode formulas below
are those of btflib's ``undecorrelate.m`` (cgbonn/btflib,
``matlab/@btf/private/undecorrelate.m``) with its default
:data:`DRR_EPS` ``= 1e-5``; the encodes are their exact inverses, so that
``decode_colour(*encode_colour(rgb, m), ...)`` returns ``rgb`` to float32
rounding on the model's domain. docs/bonn-formats.md, "Colour models and
decoding (btfcore.bonn)", lists every model, its formulas and how btf.hh
(btf-extractor) differs.

Notation: ``c = (c0, c1, c2)`` are the stored channels, ``eps`` is
:data:`DRR_EPS`, and the YUV matrix of btflib (:data:`RGB_FROM_YUV`) is

.. math::

    R = Y + 1.13983 V, \\quad G = Y - 0.39465 U - 0.5806 V, \\quad B = Y + 2.03211 U.

Models 0 and 12 act on every channel alike and accept any channel count (a
multispectral DFMF); the others need exactly 3 channels.

Decoding order of a whole texel value (btflib ``btf.m``, ``decode_texel`` and
``decode_abrdf``): colour model first (:func:`decode_colour`), then the FMF12
dynamic-range flag (:func:`restore_dynamic_range`), then the division by
:math:`\\cos\\theta_l` when the cosine flag is set.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "COLOUR_MODELS",
    "DRR_EPS",
    "RGB_FROM_YCOCG",
    "RGB_FROM_YUV",
    "UNSUPPORTED_COLOUR_MODELS",
    "UnknownColourModelError",
    "YCOCG_FROM_RGB",
    "YUV_FROM_RGB",
    "decode_colour",
    "encode_colour",
    "reduce_dynamic_range",
    "restore_dynamic_range",
]

#: btflib's eps of the log colour models and of the dynamic-range reduction (``drr_eps`` default).
DRR_EPS: float = 1e-5

#: Model id -> name (btflib's comment names in ``undecorrelate.m``), every id decode/encode support.
COLOUR_MODELS: dict[int, str] = {
    0: "rgb",                # SIMPLE aka RGB
    1: "yuv",                # YUV
    3: "pca",                # PCA (colour_mean + colour_transformation_matrix)
    4: "ycocg",              # YCoCg
    9: "ylog_uv",            # Ylog_UV
    10: "ylog_ulog_vlog",    # Ylog_Ulog_Vlog
    11: "ylog_udivy_vdivy",  # Ylog_UdivY_VdivY
    12: "log_rgb",           # log(RGB) aka SIMPLE_LOG
}

#: Ids btflib knows that this module does not decode, with the reason.
UNSUPPORTED_COLOUR_MODELS: dict[int, str] = {
    2: "Lab (btflib calls MATLAB's makecform('lab2srgb'): gamma-encoded sRGB, not linear RGB)",
    5: "SPECTRAL (chromaticity-normalised spectral channels)",
    6: "SPECTRAL_LINEAR (spectral channels relative to their mean)",
}

#: btflib's ``mat_YUV2RGB``: ``rgb = yuv @ RGB_FROM_YUV.T`` (read-only, float64).
RGB_FROM_YUV = np.array([[1.0, 0.0, 1.13983],
                         [1.0, -0.39465, -0.5806],
                         [1.0, 2.03211, 0.0]])
#: Exact float64 inverse of :data:`RGB_FROM_YUV`: ``yuv = rgb @ YUV_FROM_RGB.T`` (first row ~ BT.601 luma).
YUV_FROM_RGB = np.linalg.inv(RGB_FROM_YUV)
#: btflib's ``mat_YCoCg2RGB``: R = Y + Co - Cg, G = Y + Cg, B = Y - Co - Cg.
RGB_FROM_YCOCG = np.array([[1.0, 1.0, -1.0],
                           [1.0, 0.0, 1.0],
                           [1.0, -1.0, -1.0]])
#: Exact inverse of :data:`RGB_FROM_YCOCG`: Y = R/4 + G/2 + B/4, Co = (R - B)/2, Cg = -R/4 + G/2 - B/4.
YCOCG_FROM_RGB = np.linalg.inv(RGB_FROM_YCOCG)
for _m in (RGB_FROM_YUV, YUV_FROM_RGB, RGB_FROM_YCOCG, YCOCG_FROM_RGB):
    _m.setflags(write=False)
del _m

_LOG_EPS = float(np.log(DRR_EPS))


class UnknownColourModelError(ValueError):
    """A colour model id that :func:`decode_colour` / :func:`encode_colour` do not support.

    The message lists :data:`COLOUR_MODELS`; ``model`` holds the offending id.
    """

    def __init__(self, model: object, detail: str = "") -> None:
        self.model = model
        supported = ", ".join(f"{k} {v}" for k, v in COLOUR_MODELS.items())
        why = f" ({detail})" if detail else ""
        super().__init__(
            f"colour model {model!r} is not supported{why}; supported colour models: {supported}. "
            f"Re-export the file with one of these (e.g. 0 rgb or 11 ylog_udivy_vdivy)"
        )

    def __reduce__(self):  # picklable across processes (Dask workers)
        return (_rebuild_unknown, (self.model, str(self)))


def _rebuild_unknown(model: object, message: str) -> UnknownColourModelError:
    err = UnknownColourModelError.__new__(UnknownColourModelError)
    ValueError.__init__(err, message)
    err.model = model
    return err


def _check_model(model: object) -> int:
    if isinstance(model, (bool, np.bool_)) or not isinstance(model, (int, np.integer)):
        raise UnknownColourModelError(model, "the id must be an integer")
    m = int(model)
    if m in UNSUPPORTED_COLOUR_MODELS:
        raise UnknownColourModelError(m, f"btflib's {UNSUPPORTED_COLOUR_MODELS[m]}")
    if m not in COLOUR_MODELS:
        raise UnknownColourModelError(m)
    return m


def _channels_of(x: np.ndarray, model: int, name: str) -> None:
    if x.ndim < 1:
        raise ValueError(f"{name} must have channels on its last axis, got a scalar")
    if model not in (0, 12) and x.shape[-1] != 3:
        raise ValueError(f"{name} must have 3 channels on its last axis for colour model {model} "
                         f"({COLOUR_MODELS[model]}), got shape {x.shape}")


def _mix(x: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """``x @ matrix.T`` over the last axis of a (..., 3) array, in x's dtype."""
    flat = x.reshape(-1, 3)
    return np.matmul(flat, matrix.T.astype(x.dtype, copy=False)).reshape(x.shape)


def decode_colour(channels: np.ndarray, model: int, mean: np.ndarray | None = None,
                  matrix: np.ndarray | None = None) -> np.ndarray:
    """Stored DFMF channels -> linear RGB (btflib ``undecorrelate``).

    Parameters
    ----------
    channels : (..., n_ch) array_like
        The decoded factor product, channels last, as stored (float16, float32
        or float64). ``n_ch`` is 3 except for models 0 and 12 (any count).
    model : int
        Colour model id, a key of :data:`COLOUR_MODELS`.
    mean : (3,) array_like, optional
        ``colour_mean`` of the file; used (and required) by model 3 only.
    matrix : (3, 3) array_like, optional
        ``colour_transformation_matrix`` of the file, as stored (row-major);
        used (and required) by model 3 only.

    Returns
    -------
    rgb : (..., n_ch) ndarray of float32
        Linear RGB. Computed in float32 (float64 when ``channels`` is
        float64), always a new array. Per model, with ``eps = DRR_EPS``:

        * 0 rgb: ``rgb = c``.
        * 1 yuv: ``rgb = c @ RGB_FROM_YUV.T``.
        * 3 pca: ``rgb = c @ matrix + mean``.
        * 4 ycocg: ``rgb = c @ RGB_FROM_YCOCG.T``.
        * 9 ylog_uv: ``Y = exp(c0) - eps``, ``U = c1``, ``V = c2``, then YUV.
        * 10 ylog_ulog_vlog: ``Y = exp(c0) - eps``,
          ``U = sign(c1) exp(|c1| + log eps)``, ``V`` likewise, then YUV.
        * 11 ylog_udivy_vdivy: ``Y = exp(c0) - eps``, ``U = c1 (Y + eps)``,
          ``V = c2 (Y + eps)``, then YUV.
        * 12 log_rgb: ``rgb = exp(c) - eps``.

    Raises
    ------
    UnknownColourModelError
        For an id not in :data:`COLOUR_MODELS` (the message lists them).
    ValueError
        For a wrong channel count, or model 3 without ``mean``/``matrix``.
    """
    m = _check_model(model)
    c = np.asarray(channels)
    if c.dtype.kind not in "iuf":
        raise ValueError(f"channels must hold real numbers, got dtype {c.dtype}")
    _channels_of(c, m, "channels")
    work = np.float64 if c.dtype == np.float64 else np.float32
    x = np.array(c, dtype=work, copy=True)  # never alias the caller's (or a memmap's) buffer
    if m == 0:  # btflib undecorrelate: SIMPLE aka RGB
        pass
    elif m == 1:  # btflib undecorrelate: YUV
        x = _mix(x, RGB_FROM_YUV)
    elif m == 3:  # btflib undecorrelate: PCA, values * color_transformation_matrix + color_mean
        if mean is None or matrix is None:
            raise ValueError("colour model 3 (pca) needs the file's colour_mean (3,) and "
                             "colour_transformation_matrix (3, 3); pass mean= and matrix=")
        mu = np.asarray(mean, dtype=np.float64).reshape(-1)
        mt = np.asarray(matrix, dtype=np.float64)
        if mu.shape != (3,) or mt.shape != (3, 3):
            raise ValueError(f"colour model 3 (pca) needs mean of shape (3,) and matrix of shape (3, 3), "
                             f"got {mu.shape} and {mt.shape}")
        x = _mix(x, mt.T)
        x += mu.astype(work)
    elif m == 4:  # btflib undecorrelate: YCoCg
        x = _mix(x, RGB_FROM_YCOCG)
    elif m in (9, 10, 11):
        # exp into a fresh contiguous array: numpy's in-place exp on a strided column is ~10x slower
        x[..., 0] = np.exp(x[..., 0])
        y = x[..., 0]
        y -= work(DRR_EPS)  # btflib undecorrelate: Y = exp(c0) - eps (models 9, 10, 11)
        # one channel at a time: numpy loops over a (..., 2) slice two elements at a time (~6x slower)
        if m == 10:  # btflib undecorrelate: Ylog_Ulog_Vlog, sign(c) .* exp(|c| + log(eps))
            for j in (1, 2):
                col = x[..., j]
                s = np.sign(col)
                np.abs(col, out=col)
                col += work(_LOG_EPS)
                col[...] = np.exp(col)
                col *= s
        elif m == 11:  # btflib undecorrelate: Ylog_UdivY_VdivY, U = c1 .* (Y + eps), V = c2 .* (Y + eps)
            scale = y + work(DRR_EPS)
            x[..., 1] *= scale
            x[..., 2] *= scale
        x = _mix(x, RGB_FROM_YUV)  # btflib undecorrelate: mat_YUV2RGB
    elif m == 12:  # btflib undecorrelate: log(RGB) aka SIMPLE_LOG, exp(values) - eps
        np.exp(x, out=x)
        x -= work(DRR_EPS)
    return x.astype(np.float32, copy=False)


def _first_bad(mask: np.ndarray) -> tuple[int, ...]:
    return tuple(int(i) for i in np.unravel_index(int(np.argmax(mask)), mask.shape))


def _require(ok: np.ndarray, what: str, model: int, values: np.ndarray) -> None:
    bad = ~ok
    if bad.any():
        idx = _first_bad(bad)
        raise ValueError(
            f"colour model {model} ({COLOUR_MODELS[model]}) cannot encode this RGB: {what} "
            f"({int(bad.sum())} values; first at index {list(idx)}: {values[idx]!r}); "
            f"clip the data to that domain or choose colour model 0 (rgb) or 1 (yuv)"
        )


def encode_colour(rgb: np.ndarray, model: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear RGB -> stored DFMF channels: the exact inverse of :func:`decode_colour`.

    Parameters
    ----------
    rgb : (..., n_ch) array_like
        Linear RGB (any real dtype; computed in float64), finite. ``n_ch`` is 3
        except for models 0 and 12.
    model : int
        Colour model id, a key of :data:`COLOUR_MODELS`.

    Returns
    -------
    channels : (..., n_ch) ndarray of float32
        With ``(Y, U, V) = rgb @ YUV_FROM_RGB.T`` and ``eps = DRR_EPS``:

        * 0: ``c = rgb``; 1: ``c = (Y, U, V)``; 4: ``c = rgb @ YCOCG_FROM_RGB.T``.
        * 3: ``c = (rgb - mean) @ inv(matrix)``, the principal components of the
          pixels (float32-rounded mean and matrix, as a file stores them).
        * 9: ``c = (log(Y + eps), U, V)``; needs ``Y > -eps``.
        * 10: ``c0 = log(Y + eps)``, ``c1 = sign(U) log(|U| / eps)`` (and V);
          needs ``Y > -eps``. The decode's ``|U|`` is 0 or at least ``eps``:
          ``|U| < eps / 2`` encodes as 0, ``eps / 2 <= |U| < eps`` as
          ``sign(U) * tiny`` (decodes to ``sign(U) eps``), an absolute error
          below ``eps / 2``. The sign is carried by ``c1`` itself, so this model
          is invertible up to that rounding.
        * 11: ``c = (log(Y + eps), U / (Y + eps), V / (Y + eps))``; needs ``Y > -eps``.
        * 12: ``c = log(rgb + eps)``; needs ``rgb > -eps``.
    mean : (3,) ndarray of float32
        The PCA mean for model 3, zeros otherwise (btflib's default).
    matrix : (3, 3) ndarray of float32
        The PCA matrix for model 3 (rows the principal axes by decreasing
        variance, each row's largest-magnitude entry positive), identity otherwise.

    Raises
    ------
    UnknownColourModelError
        For an id not in :data:`COLOUR_MODELS`.
    ValueError
        For NaN/Inf, a wrong channel count, or RGB outside the model's domain
        (the message gives the first offending index).
    """
    m = _check_model(model)
    a = np.asarray(rgb)
    if a.dtype.kind not in "iuf":
        raise ValueError(f"rgb must hold real numbers, got dtype {a.dtype}")
    _channels_of(a, m, "rgb")
    x = a.astype(np.float64)
    finite = np.isfinite(x)
    if not finite.all():
        idx = _first_bad(~finite)
        raise ValueError(f"rgb{list(idx)} = {x[idx]} is not finite ({int((~finite).sum())} NaN/Inf values); "
                         f"repair or mask them before encoding")
    mean = np.zeros(3, np.float32)
    matrix = np.eye(3, dtype=np.float32)
    if m == 0:  # inverse of btflib undecorrelate SIMPLE aka RGB
        c = x
    elif m == 1:  # inverse of btflib undecorrelate YUV: exact float64 inverse of mat_YUV2RGB
        c = _mix(x, YUV_FROM_RGB)
    elif m == 3:  # inverse of btflib undecorrelate PCA
        c, mean, matrix = _pca(x)
    elif m == 4:  # inverse of btflib undecorrelate YCoCg
        c = _mix(x, YCOCG_FROM_RGB)
    elif m in (9, 10, 11):  # inverse of btflib undecorrelate Ylog_UV, Ylog_Ulog_Vlog, Ylog_UdivY_VdivY
        c = _mix(x, YUV_FROM_RGB)
        y = c[..., 0]
        _require(y > -DRR_EPS, f"luminance Y must exceed -eps = {-DRR_EPS:g} (log Y)", m, y)
        yeps = y + DRR_EPS
        if m == 10:  # c1 = sign(U) log(|U| / eps), nearest decodable value inside (-eps, eps)
            uv = c[..., 1:]
            mag = np.abs(uv)
            code = np.zeros_like(uv)
            big = mag >= DRR_EPS
            code[big] = np.log(mag[big] / DRR_EPS)
            code[(mag >= DRR_EPS / 2) & ~big] = np.finfo(np.float32).tiny
            c[..., 1:] = np.sign(uv) * code
        elif m == 11:  # c1 = U / (Y + eps), c2 = V / (Y + eps)
            c[..., 1:] /= yeps[..., None]
        c[..., 0] = np.log(yeps)  # c0 = log(Y + eps)
    else:  # inverse of btflib undecorrelate log(RGB) aka SIMPLE_LOG: c = log(rgb + eps)
        _require(x > -DRR_EPS, f"every channel must exceed -eps = {-DRR_EPS:g} (log RGB)", m, x)
        c = np.log(x + DRR_EPS)
    return c.astype(np.float32), mean, matrix


def _pca(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Model 3: channels, mean (3,) float32, matrix (3, 3) float32 with ``rgb = c @ matrix + mean``."""
    flat = x.reshape(-1, 3)
    mean64 = flat.mean(axis=0) if flat.shape[0] else np.zeros(3)
    cov = np.cov(flat - mean64, rowvar=False, bias=True) if flat.shape[0] > 1 else np.zeros((3, 3))
    lam, vec = np.linalg.eigh(cov)
    axes = vec[:, np.argsort(lam)[::-1]].T  # rows: principal axes, decreasing variance
    s = np.sign(axes[np.arange(3), np.argmax(np.abs(axes), axis=1)])
    axes = axes * np.where(s == 0, 1.0, s)[:, None]
    mean = mean64.astype(np.float32)
    matrix = axes.astype(np.float32)
    # invert the float32 matrix a file will hold, so decode(encode(x)) == x to float32 rounding
    c = (x - mean.astype(np.float64)) @ np.linalg.inv(matrix.astype(np.float64))
    return c, mean, matrix


def restore_dynamic_range(x: np.ndarray) -> np.ndarray:
    """Undo the FMF12 dynamic-range reduction: ``exp(x) - DRR_EPS`` (btflib ``restore_dynamic_range``).

    Parameters
    ----------
    x : (...) array_like
        Reduced values (float16/float32 computed in float32, float64 in float64).

    Returns
    -------
    (...) ndarray
        ``exp(x) - DRR_EPS``, float32 (float64 for float64 input), a new array.
    """
    a = np.asarray(x)
    out = np.exp(a, dtype=np.float64 if a.dtype == np.float64 else np.float32)
    out -= out.dtype.type(DRR_EPS)
    return out


def reduce_dynamic_range(x: np.ndarray) -> np.ndarray:
    """The FMF12 dynamic-range reduction: ``log(x + DRR_EPS)``, inverse of :func:`restore_dynamic_range`.

    Parameters
    ----------
    x : (...) array_like
        Linear values, all ``> -DRR_EPS``.

    Returns
    -------
    (...) ndarray
        ``log(x + DRR_EPS)``, float32 (float64 for float64 input), a new array.

    Raises
    ------
    ValueError
        Where some ``x <= -DRR_EPS`` or is NaN (the message gives the first index).
    """
    a = np.asarray(x)
    work = np.float64 if a.dtype == np.float64 else np.float32
    y = a.astype(np.float64) + DRR_EPS
    ok = y > 0
    if not ok.all():
        idx = _first_bad(~ok) if a.ndim else ()
        raise ValueError(f"reduce_dynamic_range needs x > -{DRR_EPS:g}; x{list(idx)} = {a[idx]!r} "
                         f"({int((~ok).sum())} values); clip negative noise before the log")
    return np.log(y).astype(work)
