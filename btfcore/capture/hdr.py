"""HDR merging of exposure brackets: linear raw sensors and non-linear (LDR) devices.

Three estimators, one dispatcher (:func:`merge`):

* ``'linear'`` -- :func:`merge_linear`: Bayer-domain raw frames of a linear
  sensor. Dark-frame (or black-level) subtraction, saturated and near-black
  samples excluded, inverse-variance (noise-optimal) weights from the
  exposure time, the gain and the read noise (Granados et al. 2010,
  Hasinoff et al. 2010). Output in DN per second.
* ``'debevec'`` -- :func:`merge_response` with ``method='debevec'``: 8-bit
  images through a calibrated inverse response, hat weights, averaged in the
  log domain (Debevec & Malik 1997). Response from :func:`response_debevec`.
* ``'robertson'`` -- :func:`merge_response` with ``method='robertson'``:
  8-bit images through a calibrated inverse response, Robertson's weights,
  maximum-likelihood average in the linear domain (Robertson, Borman &
  Stevenson 2003). Response from :func:`response_robertson`.

Everything is pure numerics on arrays (no I/O); ``docs/hdr.md`` has the
formulas, the choices and the measured comparison with OpenCV.

References
----------
.. [1] P. E. Debevec and J. Malik, "Recovering high dynamic range radiance
   maps from photographs", SIGGRAPH 1997, pp. 369-378.
.. [2] M. A. Robertson, S. Borman and R. L. Stevenson, "Estimation-theoretic
   approach to dynamic range enhancement using multiple exposures",
   J. Electronic Imaging 12(2), 2003, pp. 219-228.
.. [3] M. Granados, B. Ajdin, M. Wand, C. Theobalt, H.-P. Seidel and
   H. P. A. Lensch, "Optimal HDR reconstruction with linear digital
   cameras", CVPR 2010, pp. 215-222.
.. [4] S. W. Hasinoff, F. Durand and W. T. Freeman, "Noise-optimal capture
   for high dynamic range photography", CVPR 2010, pp. 553-560.
.. [5] EMVA Standard 1288, Release 4.0 (2021): the linear camera model
   (variance in DN^2 = signal / gain + (read noise / gain)^2 + 1/12).
.. [6] M. D. Grossberg and S. K. Nayar, "Determining the camera response
   from images: what is knowable?", IEEE TPAMI 25(11), 2003, pp. 1455-1467.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Literal, NamedTuple

import numpy as np
from scipy.linalg import cho_factor, cho_solve

__all__ = [
    "LDR_SIZE",
    "MERGE_METHODS",
    "RESPONSE_METHODS",
    "dark_per_exposure",
    "merge",
    "merge_linear",
    "linear_merger",
    "calibrate_response",
    "exposure_ratios",
    "merge_response",
    "response_debevec",
    "response_robertson",
    "weights_debevec",
    "weights_robertson",
]

#: Number of code values of an 8-bit LDR image.
LDR_SIZE: int = 256

#: Methods of :func:`merge`.
MERGE_METHODS: tuple[str, ...] = ("linear", "debevec", "robertson")

#: Calibration methods of :func:`calibrate_response` (the merge of an LDR capture uses the same name).
RESPONSE_METHODS: tuple[str, ...] = ("debevec", "robertson")


# --------------------------------------------------------------------------- validation


def _check_times(exposure_time: Any, n_exp: int | None, name: str = "exposure_time") -> np.ndarray:
    """1-D float64 exposure times: finite, > 0, non-decreasing; ``n_exp`` long when given."""
    t = np.asarray(exposure_time, dtype=np.float64)
    if t.ndim != 1 or t.size == 0:
        raise ValueError(f"{name} must be a non-empty 1-D array of seconds, got shape {t.shape}")
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise ValueError(f"{name}[{bad[0]}] is {t[bad[0]]}: exposure times must be finite seconds")
    bad = np.flatnonzero(t <= 0)
    if bad.size:
        raise ValueError(f"{name}[{bad[0]}] = {t[bad[0]]} s: exposure times must be > 0")
    bad = np.flatnonzero(np.diff(t) < 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise ValueError(f"{name} is not monotonic: {name}[{i}] = {t[i]} s is shorter than {name}[{i - 1}] = "
                         f"{t[i - 1]} s; sort the bracket (frames and times together) by exposure time")
    if n_exp is not None and t.size != n_exp:
        raise ValueError(f"{name} has {t.size} entries but the frames hold {n_exp} exposures along axis 0")
    return t


def _index(mask: np.ndarray) -> tuple[tuple[int, ...], str]:
    """First True index of ``mask`` and its text, e.g. ``[1, 2, 3]``."""
    idx = tuple(int(v) for v in np.argwhere(mask)[0])
    return idx, "[" + ", ".join(str(i) for i in idx) + "]"


def _check_finite(a: np.ndarray, name: str) -> None:
    if a.dtype.kind in "fc" and not np.all(np.isfinite(a)):
        idx, text = _index(~np.isfinite(a))
        raise ValueError(f"{name}{text} is {a[idx]}: {name} must be finite (no NaN or Inf)")


def _check_scalar(value: Any, name: str, *, positive: bool = False, nonneg: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(v) or (positive and v <= 0) or (nonneg and v < 0):
        cond = "> 0" if positive else (">= 0" if nonneg else "finite")
        raise ValueError(f"{name} must be finite and {cond}, got {value!r}")
    return v


def _broadcast(value: Any, shape: tuple[int, ...], name: str, dtype) -> np.ndarray:
    a = np.asarray(value, dtype=dtype)
    _check_finite(a, name)
    if a.ndim == 0:
        return a
    try:
        if np.broadcast_shapes(a.shape, shape) != tuple(shape):
            raise ValueError
    except ValueError:
        raise ValueError(f"{name} has shape {a.shape}, which does not broadcast to the shape {tuple(shape)} "
                         f"it applies to") from None
    return a


# --------------------------------------------------------------------------- linear sensors


def dark_per_exposure(dark_frames: np.ndarray, dark_exposure_time: Any, exposure_time: Any, *,
                      black_level: float | np.ndarray, fit_offset: bool = False) -> np.ndarray:
    """Dark frame for every exposure of a bracket from dark frames of other exposure times.

    Parameters
    ----------
    dark_frames : (n_dark, ...) ndarray
        Raw frames taken with the shutter closed (DN, black level included),
        e.g. a capture store's ``dark_frames[c]``.
    dark_exposure_time : (n_dark,) array_like
        Their exposure times, seconds, non-decreasing.
    exposure_time : (n_exp,) array_like
        The bracket's exposure times, seconds.
    black_level : float or (...) ndarray
        Black level, DN (per pixel or scalar).
    fit_offset : bool
        Also fit a per-pixel offset (a black level that differs per pixel);
        needs at least two distinct dark exposure times.

    Returns
    -------
    dark : (n_exp, ...) ndarray of float64
        Mean dark raw value per exposure and pixel, DN, black level included
        -- what :func:`merge_linear` takes as ``dark``.

    Notes
    -----
    A dark pixel's mean value grows linearly with time (dark current
    :math:`D_p` in DN/s). Least squares per pixel through the black level:

    .. math::
        \\hat D_p = \\frac{\\sum_d t_d (y_{d,p} - b_p)}{\\sum_d t_d^2}, \\qquad
        \\mathrm{dark}_{k,p} = b_p + \\hat D_p t_k,

    or with ``fit_offset`` the ordinary straight-line fit
    :math:`y_{d,p} \\approx o_p + D_p t_d`.
    """
    td = _check_times(dark_exposure_time, None, "dark_exposure_time")
    t = _check_times(exposure_time, None)
    frames = np.asarray(dark_frames)
    if frames.ndim < 1 or frames.shape[0] != td.size:
        raise ValueError(f"dark_frames has {frames.shape[0] if frames.ndim else 0} frames along axis 0 but "
                         f"dark_exposure_time has {td.size} entries")
    _check_finite(frames, "dark_frames")
    y = frames.astype(np.float64)
    tt = td.reshape((-1,) + (1,) * (y.ndim - 1))
    tk = t.reshape((-1,) + (1,) * (y.ndim - 1))
    if fit_offset:
        if np.unique(td).size < 2:
            raise ValueError("fit_offset needs dark frames of at least two different exposure times")
        tm = td.mean()
        ym = y.mean(axis=0)
        rate = np.sum((tt - tm) * (y - ym), axis=0) / np.sum((td - tm) ** 2)      # eq. straight-line slope
        return ym + rate * (tk - tm)
    b = _broadcast(black_level, y.shape[1:], "black_level", np.float64)
    rate = np.sum(tt * (y - b), axis=0) / np.sum(td**2)                          # eq. D = sum t (y - b) / sum t^2
    return b + rate * tk                                                         # eq. dark_k = b + D t_k


def merge_linear(frames: np.ndarray, exposure_time: Any, *, black_level: float | np.ndarray,
                 white_level: float, gain_e_per_dn: float | None = None, read_noise_e: float | None = None,
                 dark: np.ndarray | None = None, saturation_margin: float = 0.98,
                 min_signal_dn: float | None = None, n_iter: int = 1,
                 dtype: type | np.dtype = np.float32) -> tuple[np.ndarray, np.ndarray]:
    """Noise-optimal HDR merge of a linear sensor's exposure bracket (Bayer or any domain).

    Parameters
    ----------
    frames : (n_exp, ...) ndarray of uint16 or float
        Raw values, DN, black level included; axis 0 is the exposure, sorted
        by ``exposure_time``. Works per sample, so a Bayer mosaic needs no
        special treatment.
    exposure_time : (n_exp,) array_like
        Seconds; finite, > 0, non-decreasing.
    black_level : float or (...) ndarray
        DN offset of a dark pixel; scalar or broadcastable to ``frames.shape[1:]``
        (e.g. a per-CFA-channel black level tiled over the mosaic). Ignored
        for the subtraction when ``dark`` is given.
    white_level : float
        Raw value at which the sensor saturates, DN.
    gain_e_per_dn : float or None
        Electrons per DN. ``None``: photon-noise-limited weights
        :math:`w_k \\propto t_k` (the estimate is then
        :math:`\\sum_k x_k / \\sum_k t_k`).
    read_noise_e : float or None
        Read noise, electrons (needs ``gain_e_per_dn``); ``None`` means 0.
    dark : (n_exp, ...) ndarray or None
        Mean dark frame for every exposure, DN, **black level included** (the
        average of shutter-closed frames at the same exposure time, or
        :func:`dark_per_exposure`); broadcastable to ``frames.shape``. It
        replaces the black level in the subtraction and removes dark current
        and hot pixels; ``dark - black_level`` counts as dark signal in the
        noise model. ``None``: only the black level is subtracted.
    saturation_margin : float
        A sample with ``raw >= saturation_margin * white_level`` counts as
        saturated and is excluded; in (0, 1].
    min_signal_dn : float or None
        A sample whose dark-subtracted value is below this (DN) counts as
        near-black; it is excluded while the pixel has a better sample.
        ``None``: twice the read noise in DN (``2 * read_noise_e /
        gain_e_per_dn``, at least 1 DN), or 2 DN when the noise is unknown.
    n_iter : int
        Re-weighting passes after the first (photon-limited) estimate, >= 1.
    dtype : numpy dtype
        Floating type of the computation and the output.

    Returns
    -------
    radiance : (...) ndarray of ``dtype``
        Dark-subtracted signal rate, **DN per second** (multiply by
        ``gain_e_per_dn`` for electrons per second). Finite everywhere (no
        NaN or Inf); unbiased, so pixels below the noise floor may be slightly
        negative.
    valid : (...) ndarray of bool
        The pixel has at least one sample that is neither saturated nor
        near-black. Where ``False``: if every sample is saturated, the
        radiance is the shortest exposure's clipped value over its time (a
        lower bound); if every unsaturated sample is near-black, it is the
        weighted estimate from those samples (dominated by the longest
        exposure, the best one available).

    Raises
    ------
    ValueError
        Shapes that do not match, non-finite or non-monotonic exposure times,
        NaN/Inf in the frames, the dark frames or the black level, invalid
        noise parameters; the message names the argument and the index.

    Notes
    -----
    With :math:`y_k` the raw value of exposure :math:`k`, :math:`d_k` the dark
    frame (or the black level :math:`b`), :math:`g` the gain (e-/DN) and
    :math:`\\sigma_r` the read noise (e-), each unsaturated sample is an
    unbiased estimate of the rate :math:`r` (DN/s):

    .. math::
        x_k = y_k - d_k, \\qquad E[x_k / t_k] = r.

    Its variance (photon + dark shot noise, read noise, quantisation; [3], [5]) is

    .. math::
        \\sigma_k^2 = \\frac{r t_k + (d_k - b)}{g} + \\frac{\\sigma_r^2}{g^2} + \\frac{1}{12}
        \\quad [\\mathrm{DN}^2],

    so the minimum-variance unbiased linear combination of the
    :math:`x_k / t_k` over the used samples :math:`S` is ([3], [4])

    .. math::
        \\hat r = \\frac{\\sum_{k \\in S} w_k \\, x_k / t_k}{\\sum_{k \\in S} w_k},
        \\qquad w_k = \\frac{t_k^2}{\\sigma_k^2}.

    The unknown :math:`r` in :math:`\\sigma_k^2` is replaced by a first
    estimate, the photon-limited maximum likelihood
    :math:`\\hat r_0 = \\sum_S x_k / \\sum_S t_k`, and then by the previous
    pass's :math:`\\hat r` (``n_iter`` passes). A sample is *saturated* if
    :math:`y_k \\ge m W` and *near-black* if :math:`x_k < x_{min}`; the
    quantisation term is used for integer frames only.
    """
    y = np.asarray(frames)
    if y.ndim < 1:
        raise ValueError("frames must be (n_exp, ...), got a scalar")
    return linear_merger(y.shape[1:], y.dtype, black_level=black_level, white_level=white_level,
                         gain_e_per_dn=gain_e_per_dn, read_noise_e=read_noise_e,
                         saturation_margin=saturation_margin, min_signal_dn=min_signal_dn, n_iter=n_iter,
                         dtype=dtype)(y, exposure_time, dark)


def linear_merger(frame_shape: tuple[int, ...], frames_dtype: Any, *, black_level: float | np.ndarray,
                  white_level: float, gain_e_per_dn: float | None = None, read_noise_e: float | None = None,
                  saturation_margin: float = 0.98, min_signal_dn: float | None = None, n_iter: int = 1,
                  dtype: type | np.dtype = np.float32) -> Callable[..., tuple[np.ndarray, np.ndarray]]:
    """:func:`merge_linear` with the sensor's settings checked once, for many brackets of one frame shape.

    A view's 198 images share their sensor, black level and frame shape; checking those once instead of
    per bracket saved 22 ms of a view's 0.16 s of merging (docs/benchmarks.md, 2026-12-05).

    Parameters
    ----------
    frame_shape : tuple of int
        ``frames.shape[1:]`` of every bracket.
    frames_dtype : dtype
        Their dtype (integer or float raw values).
    black_level, white_level, gain_e_per_dn, read_noise_e, saturation_margin, min_signal_dn, n_iter, dtype
        As :func:`merge_linear`.

    Returns
    -------
    merge : callable
        ``merge(frames, exposure_time, dark=None, check_finite=True) -> (rate, valid)``, :func:`merge_linear`
        of one bracket ``(n_exp, *frame_shape)``; ``check_finite=False`` skips the NaN/Inf scans of
        ``frames`` and ``dark`` (for a caller that checked them once, as ``scipy.linalg``'s
        ``check_finite``).

    Raises
    ------
    ValueError
        As :func:`merge_linear`: at once for the settings, at each call for the bracket.
    """
    kind = np.dtype(frames_dtype).kind
    if kind not in "uif":
        raise ValueError(f"frames must be integer or float raw values, got dtype {np.dtype(frames_dtype)}")
    shape = tuple(int(n) for n in frame_shape)
    black, params = _linear_params(shape, kind, black_level, white_level, gain_e_per_dn, read_noise_e,
                                   saturation_margin, min_signal_dn, n_iter, dtype)

    def merge(frames: np.ndarray, exposure_time: Any, dark: np.ndarray | None = None,
              check_finite: bool = True) -> tuple[np.ndarray, np.ndarray]:
        y = np.asarray(frames)
        if y.ndim < 1 or y.shape[1:] != shape or y.dtype.kind != kind:
            raise ValueError(f"frames must be (n_exp, {', '.join(map(str, shape))}) of dtype kind {kind!r} "
                             f"(the merger's), got {y.dtype} {y.shape}")
        t = _check_times(exposure_time, y.shape[0])
        if check_finite:
            _check_finite(y, "frames")
        d = None if dark is None else _check_dark(dark, y, check_finite)
        return _merge_linear_blocks(y, black, d, params._replace(t=t.astype(params.dtype).reshape(-1, 1)))

    return merge


def _linear_params(frame_shape: tuple[int, ...], frames_kind: str, black_level: float | np.ndarray,
                   white_level: float, gain_e_per_dn: float | None, read_noise_e: float | None,
                   saturation_margin: float, min_signal_dn: float | None, n_iter: int,
                   dtype: type | np.dtype) -> tuple[np.ndarray, _LinearParams]:
    """:func:`merge_linear`'s black level, broadcast to a frame, and its checked noise model and thresholds
    (the exposure times ``t`` are set per bracket)."""
    dtype = np.dtype(dtype)
    if dtype.kind != "f":
        raise ValueError(f"dtype must be a floating type, got {dtype}")
    black = _broadcast(black_level, frame_shape, "black_level", dtype)
    white = _check_scalar(white_level, "white_level", positive=True)
    if np.any(black >= white):
        raise ValueError(f"black_level (max {float(np.max(black))}) must be below white_level {white}")
    margin = _check_scalar(saturation_margin, "saturation_margin", positive=True)
    if margin > 1:
        raise ValueError(f"saturation_margin must be in (0, 1], got {saturation_margin}")
    gain = None if gain_e_per_dn is None else _check_scalar(gain_e_per_dn, "gain_e_per_dn", positive=True)
    if read_noise_e is not None and gain is None:
        raise ValueError("read_noise_e needs gain_e_per_dn (electrons -> DN); give both or neither")
    read_e = 0.0 if read_noise_e is None else _check_scalar(read_noise_e, "read_noise_e", nonneg=True)
    read_dn2 = (read_e / gain) ** 2 if gain is not None else 0.0
    if min_signal_dn is None:
        min_sig = max(2.0 * read_e / gain, 1.0) if (gain is not None and read_noise_e is not None) else 2.0
    else:
        min_sig = _check_scalar(min_signal_dn, "min_signal_dn")
    if int(n_iter) < 1:
        raise ValueError(f"n_iter must be >= 1, got {n_iter}")
    params = _LinearParams(
        t=None, thr=dtype.type(margin * white), min_sig=dtype.type(min_sig),
        inv_g=None if gain is None else dtype.type(1.0 / gain),
        const=dtype.type(max(read_dn2 + (1.0 / 12.0 if frames_kind in "ui" else 0.0), 1e-6)),  # > 0: no 0/0
        n_iter=int(n_iter),
        dtype=dtype)
    return black, params


def _check_dark(dark: np.ndarray, y: np.ndarray, check_finite: bool = True) -> np.ndarray:
    """``dark`` as an array, checked: numeric, finite (with ``check_finite``), one frame per exposure of ``y``
    (or one for all)."""
    n_exp = y.shape[0]
    d = np.asarray(dark)
    if d.dtype.kind not in "uif":
        raise ValueError(f"dark must be numeric, got dtype {d.dtype}")
    if check_finite:
        _check_finite(d, "dark")
    if d.ndim == y.ndim and d.shape[0] not in (1, n_exp):
        raise ValueError(f"dark has {d.shape[0]} exposures along axis 0, the frames {n_exp}: give one "
                         f"dark frame per exposure (dark_per_exposure makes them)")
    try:
        if np.broadcast_shapes(d.shape, y.shape) != y.shape:
            raise ValueError
    except ValueError:
        raise ValueError(f"dark has shape {d.shape}, the frames {y.shape}: give one dark frame per "
                         f"exposure (n_exp, ...) or use dark_per_exposure") from None
    return d


#: Samples (exposures x pixels) merged at once by :func:`merge_linear`: a block's temporaries stay in
#: the CPU cache (several times faster than whole-frame numpy passes).
_BLOCK_SAMPLES: int = 1 << 16


def _merge_linear_blocks(y: np.ndarray, black: np.ndarray, d: np.ndarray | None,
                         params: _LinearParams) -> tuple[np.ndarray, np.ndarray]:
    """:func:`merge_linear` over blocks of pixels that stay in the CPU cache (every step is per pixel)."""
    n_exp, pix_shape, dtype = y.shape[0], y.shape[1:], params.dtype
    n_pix = int(np.prod(pix_shape, dtype=np.int64))
    y2 = y.reshape(n_exp, n_pix)
    b2 = black.reshape(1, -1) if black.ndim == 0 else np.broadcast_to(black, pix_shape).reshape(1, n_pix)
    d2 = None if d is None else np.broadcast_to(d, y.shape).reshape(n_exp, n_pix)
    rate = np.empty(n_pix, dtype=dtype)
    valid = np.empty(n_pix, dtype=bool)
    step = max(1, _BLOCK_SAMPLES // n_exp)
    for lo in range(0, n_pix, step):
        hi = min(lo + step, n_pix)
        bb = b2 if b2.shape[1] == 1 else b2[:, lo:hi]
        _merge_linear_block(y2[:, lo:hi], bb, None if d2 is None else d2[:, lo:hi], params,
                            rate[lo:hi], valid[lo:hi])
    return rate.reshape(pix_shape), valid.reshape(pix_shape)


class _LinearParams(NamedTuple):
    t: np.ndarray | None     # (n_exp, 1) exposure times, set per bracket
    thr: Any                 # saturation threshold, DN (raw)
    min_sig: Any             # near-black threshold, DN (dark-subtracted)
    inv_g: Any               # 1 / gain or None
    const: Any               # read noise^2 + quantisation, DN^2
    n_iter: int
    dtype: np.dtype


def _merge_linear_block(y: np.ndarray, black: np.ndarray, dark: np.ndarray | None, p: _LinearParams,
                        out: np.ndarray, valid_out: np.ndarray) -> None:
    """merge_linear on (n_exp, B) samples; writes (B,) rate and valid."""
    dtype = p.dtype
    zero = dtype.type(0)
    x = np.empty(y.shape, dtype=dtype)
    x[...] = y                      # then subtracted in place: one pass less than a mixed-type subtract
    np.subtract(x, dark if dark is not None else black, out=x, dtype=dtype)     # eq. x_k = y_k - d_k (or - b)
    # eq. not saturated, y_k < m W: on integer frames compared as integers (exact, and a cheaper pass)
    usable = y < (np.ceil(p.thr) if y.dtype.kind in "ui" else p.thr)
    good = x >= p.min_sig                                                        # eq. x_k >= x_min
    good &= usable
    valid = np.any(good, axis=0)
    if valid.all():                                                              # the usual case
        used, any_used = good, None
    else:
        used = np.where(valid, good, usable)                                     # S: good, else unsaturated
        any_used = np.any(used, axis=0)
    fallback = None if any_used is None else x[0] / p.t[0]
    ts = used.astype(dtype)                     # masks as 0/1 factors: 5x faster than np.where here
    xs = np.multiply(x, ts, out=x)
    ts *= p.t
    den = ts.sum(axis=0)
    rate = xs.sum(axis=0)
    if any_used is not None:
        den[~any_used] = 1
    rate /= den                                                                  # eq. r0 = sum x / sum t
    if p.inv_g is not None:
        # signal-independent variance: dark signal / g + sigma_r^2 / g^2 + 1/12, DN^2
        if dark is not None:
            floor = np.subtract(dark, black, dtype=dtype)
            np.maximum(floor, zero, out=floor)
            floor *= p.inv_g                                                     # eq. dark / g
            floor += p.const                                                     # eq. + sigma_r^2/g^2 + 1/12
        else:
            floor = p.const
        var = np.empty_like(xs)
        for _ in range(p.n_iter):
            np.maximum(rate, zero, out=rate)
            np.multiply(p.t, rate * p.inv_g, out=var)                            # eq. r t_k / g
            var += floor
            np.divide(ts, var, out=var)                                          # eq. w_k / t_k = t_k / sigma_k^2
            den = np.einsum("ij,ij->j", var, ts)                                 # eq. sum w_k
            rate = np.einsum("ij,ij->j", var, xs)                                # eq. sum w_k x_k / t_k
            if any_used is not None:
                den[~any_used] = 1
            rate /= den
    if any_used is None:
        out[...] = rate
    else:
        # every sample saturated: the clipped value of the shortest exposure over its time (lower bound)
        out[...] = np.where(any_used, rate, fallback)
    valid_out[...] = valid


# --------------------------------------------------------------------------- LDR devices


def weights_debevec(n_codes: int = LDR_SIZE) -> np.ndarray:
    """Debevec & Malik's hat weighting function of ``n_codes`` code values.

    Parameters
    ----------
    n_codes : int
        Number of code values: 256 for 8-bit images (default), 65536 for 16-bit ones.

    Returns
    -------
    w : (n_codes,) ndarray of float64
        :math:`w(z) = z - Z_{min}` for :math:`z \\le (Z_{max} - 1)/2` and
        :math:`Z_{max} - z` above ([1] eq. 4, with :math:`Z_{min} = 0,
        Z_{max} = n_{codes} - 1`); zero at both ends. For 16-bit codes it is
        the 8-bit hat stretched by 257 (so weights are on the same scale).
    """
    z = np.arange(n_codes, dtype=np.float64)
    w = np.where(z <= (n_codes - 1) / 2, z, (n_codes - 1) - z)                 # eq. (4) of [1]
    return w * ((LDR_SIZE - 1) / (n_codes - 1))


def weights_robertson(n_codes: int = LDR_SIZE) -> np.ndarray:
    """Robertson et al.'s Gaussian-like weighting function of ``n_codes`` code values.

    Parameters
    ----------
    n_codes : int
        Number of code values: 256 for 8-bit images (default), 65536 for 16-bit ones.

    Returns
    -------
    w : (n_codes,) ndarray of float64
        :math:`w(z) = (e^{4} e^{-(z/q - 2)^2} - 1) / (e^{4} - 1)` with
        :math:`q = (n_{codes} - 1)/4`: a Gaussian of the code value centred in
        the middle ([2] Sec. 3.2), shifted and scaled so that it is exactly 1
        there and 0 at both ends (the variant OpenCV uses).
    """
    q = (n_codes - 1) / 4.0
    z = np.arange(n_codes, dtype=np.float64) / q - 2.0
    e4 = np.exp(4.0)
    return np.maximum((e4 * np.exp(-z * z) - 1.0) / (e4 - 1.0), 0.0)           # eq. Gaussian weights of [2]


def _check_ldr(images: Any, exposure_time: Any, name: str = "images", *,
               allow_16bit: bool = False) -> tuple[np.ndarray, np.ndarray]:
    z = np.asarray(images)
    if z.dtype != np.uint8 and not (allow_16bit and z.dtype == np.uint16):
        kinds = "8-bit (uint8) or 16-bit (uint16)" if allow_16bit else "8-bit (uint8)"
        raise ValueError(f"{name} must be {kinds} LDR images, got dtype {z.dtype}; use merge_linear for "
                         f"linear raw frames")
    if z.ndim < 2:
        raise ValueError(f"{name} must be (n_exp, ...), got shape {z.shape}")
    t = _check_times(exposure_time, z.shape[0])
    return z, t


def _channels_last(z: np.ndarray, channel_axis: int | None) -> np.ndarray:
    """(n_exp, n_pix, C) view of images with an optional colour axis."""
    if channel_axis is None:
        return z.reshape(z.shape[0], -1, 1)
    ax = channel_axis % z.ndim
    if ax == 0:
        raise ValueError("channel_axis cannot be axis 0 (the exposure axis)")
    z = np.moveaxis(z, ax, -1)
    return z.reshape(z.shape[0], -1, z.shape[-1])


#: :func:`_debevec_samples` first looks for one pixel per brightness bin among this many random pixels
#: per sample (a bin missed there, i.e. a rare brightness, is then searched among all pixels).
_SUBSET_PER_SAMPLE: int = 8


def _debevec_samples(level: np.ndarray, max_level: int, n_samples: int, rng: np.random.Generator) -> np.ndarray:
    """Pixel indices stratified over the scene's brightness ``level`` (codes summed over the bracket).

    ``n_samples`` equal-width bins of ``level`` (or one per level when there
    are fewer levels); one pixel drawn uniformly from every non-empty bin,
    the rest at random. The bins are found in a random subset of the
    pixels first (the first hit of a bin in a random order is a uniform draw
    from it); only the bins it misses, the rare brightnesses, are looked up
    among all pixels. Cost: a few passes over ``level``, no sort of all pixels.
    """
    n_pix = level.size
    if n_pix <= n_samples:
        return np.arange(n_pix)
    if max_level + 1 <= n_samples:                                               # one bin per level
        bins, n_bins = level, max_level + 1
    else:
        lo, hi = int(level.min()), int(level.max())
        span = hi - lo + 1
        if span <= n_samples:
            bins, n_bins = level, hi + 1                                         # (bins below lo stay empty)
        else:
            bins, n_bins = ((level.astype(np.int64) - lo) * n_samples) // span, n_samples
    sub = rng.integers(0, n_pix, size=_SUBSET_PER_SAMPLE * n_samples)           # i.i.d. uniform pixels
    first = np.full(n_bins, sub.size, dtype=np.intp)
    np.minimum.at(first, bins[sub], np.arange(sub.size))                         # first hit of every bin
    hit = np.flatnonzero(first < sub.size)
    chosen = [sub[first[hit]]]
    missing = np.ones(n_bins, dtype=bool)
    missing[hit] = False
    cand = np.flatnonzero(missing.take(bins))                                    # pixels of the bins not hit
    if cand.size:                                                                # rare bins: among all pixels
        cb = bins[cand]
        order = np.argsort(cb, kind="stable")                                    # grouped by bin
        cnt = np.bincount(cb, minlength=n_bins)
        cnt = cnt[cnt > 0]
        pick = np.cumsum(cnt) - cnt + (rng.random(cnt.size) * cnt).astype(np.int64)
        chosen.append(cand[order[pick]])
    chosen = np.concatenate(chosen)
    need = n_samples - chosen.size
    if need > 0:                                                                 # fill the rest at random
        extra = rng.choice(n_pix, size=min(n_pix, need + chosen.size), replace=False)
        chosen = np.concatenate([chosen, extra[~np.isin(extra, chosen, kind="table")][:need]])
    return np.sort(chosen)


def _debevec_solve(zs: np.ndarray, log_t: np.ndarray, w: np.ndarray, lam: float) -> np.ndarray:
    """Debevec & Malik's least squares for ``g`` with the log irradiances eliminated.

    ``zs`` is (N, P) codes. The minimiser over :math:`\\ln E_i` for a fixed
    :math:`g` is the weighted mean :math:`\\ln E_i = \\sum_j a_{ij} (g(Z_{ij}) -
    \\ln t_j) / A_i` with :math:`a_{ij} = w(Z_{ij})^2`, :math:`A_i = \\sum_j a_{ij}`;
    substituting it leaves a quadratic in the 256 values of :math:`g` (the
    Schur complement), assembled with ``bincount`` over the code pairs of
    each pixel, plus the smoothness term; :math:`g(128) = 0` removes one
    unknown. Same minimiser as the paper's (N + 256)-unknown system, at a
    cost linear in N.
    """
    zs = np.asarray(zs, dtype=np.intp)
    p = zs.shape[1]
    a = w[zs] ** 2                                                               # a_ij = w(Z_ij)^2
    big_a = a.sum(axis=1)
    keep = big_a > 0
    zs, a, big_a = zs[keep], a[keep], big_a[keep]
    c = a @ log_t                                                                # c_i = sum_j a_ij ln t_j
    size = LDR_SIZE
    h = np.diag(np.bincount(zs.ravel(), weights=a.ravel(), minlength=size).astype(np.float64))  # sum a g^2
    b = np.bincount(zs.ravel(), weights=(a * log_t).ravel(), minlength=size).astype(np.float64)
    inv = 1.0 / big_a
    pair = (zs[:, :, None] * size + zs[:, None, :]).ravel()                      # every (j, k) code pair of a pixel
    cross = (a[:, :, None] * a[:, None, :] * inv[:, None, None]).ravel()
    h -= np.bincount(pair, weights=cross, minlength=size * size).reshape(size, size)  # - (sum_j a_ij g_ij)^2 / A_i
    b -= np.bincount(zs.ravel(), weights=(a * (c * inv)[:, None]).ravel(), minlength=size)
    zz = np.arange(1, size - 1)
    d = np.zeros((size - 2, size))
    d[np.arange(size - 2), zz - 1] = 1.0                                         # eq. g'' = g(z-1) - 2 g(z) + g(z+1)
    d[np.arange(size - 2), zz] = -2.0
    d[np.arange(size - 2), zz + 1] = 1.0
    d *= (lam * np.sqrt(zs.shape[0]) * w[zz])[:, None]                           # eq. lambda sqrt(N) w(z) g''(z)
    h += d.T @ d
    free = np.arange(size) != size // 2                                          # eq. g(128) = 0
    g = np.zeros(size)
    hf, bf = h[np.ix_(free, free)], b[free]
    try:                                                                         # positive definite: Cholesky
        g[free] = cho_solve(cho_factor(hf, check_finite=False), bf, check_finite=False)
    except np.linalg.LinAlgError:                                                # codes the data and smoothness miss
        g[free] = np.linalg.lstsq(hf, bf, rcond=None)[0]
    return g


def response_debevec(images: np.ndarray, exposure_time: Any, *, n_samples: int | None = 4096,
                     smoothness: float = 10.0, rng: np.random.Generator | int | None = None,
                     channel_axis: int | None = None) -> np.ndarray:
    """Log inverse camera response by Debevec & Malik's least-squares solve.

    Parameters
    ----------
    images : (n_exp, ...) ndarray of uint8
        An exposure bracket of a static scene, sorted by exposure time.
    exposure_time : (n_exp,) array_like
        Seconds; finite, > 0, non-decreasing.
    n_samples : int or None
        Pixels used per channel, stratified over the scene's brightness (one
        random pixel per bin of the code values summed over the bracket,
        the rest at random); ``None`` uses every pixel. The cost is linear in
        the number of samples (the irradiances are eliminated, see Notes).
    smoothness : float
        :math:`\\lambda`, weight of the second-derivative penalty **per
        sample** (see Notes); the result does not drift with ``n_samples``.
    rng : numpy.random.Generator or int or None
        Source of the sample choice (seed it for reproducibility).
    channel_axis : int or None
        Axis of colour channels (one curve per channel); ``None`` pools all
        values into one curve.

    Returns
    -------
    g : (256,) or (256, C) ndarray of float64
        :math:`g(z) = \\ln f^{-1}(z)`, the log exposure (irradiance x time,
        relative) that produces code :math:`z`; :math:`g(128) = 0`. Pass
        ``np.exp(g)`` to :func:`merge_response`.

    Notes
    -----
    With :math:`Z_{ij}` the code of sample pixel :math:`i` in exposure
    :math:`j` and the hat weights :math:`w` (:func:`weights_debevec`),
    minimise over :math:`g` and the log irradiances :math:`\\ln E_i` ([1] eq. 3)

    .. math::
        \\sum_{i,j} \\{w(Z_{ij}) [g(Z_{ij}) - \\ln E_i - \\ln t_j]\\}^2
        + \\lambda^2 N \\sum_{z=1}^{254} [w(z) g''(z)]^2,
        \\qquad g(128) = 0,

    with :math:`g''(z) = g(z-1) - 2 g(z) + g(z+1)` and :math:`N` the number
    of samples with a non-zero weight. The paper's ``gsolve.m`` (and OpenCV's
    ``CalibrateDebevec``) put :math:`\\lambda w(z)` in the smoothness rows,
    i.e. :math:`\\lambda^2` without :math:`N`: the balance then shifts to the
    data as samples are added. Here :math:`\\lambda = 10` with any
    :math:`N` behaves like ``gsolve`` with :math:`\\lambda = 10 \\sqrt{N}`.

    For fixed :math:`g` the optimal :math:`\\ln E_i` is a weighted mean, so
    it is eliminated and the remaining 255 unknowns are solved densely (the
    same minimiser as the paper's (N + 256)-unknown system).

    A bracket with one constant ratio between exposure times (e.g. 1/8, 1,
    8 s) leaves :math:`g` ambiguous up to a function periodic in
    :math:`\\ln`-exposure with that ratio's period [6]; only the smoothness
    term chooses among them. Brackets with unequal ratios are identified by
    the data.

    References
    ----------
    .. [6] M. D. Grossberg and S. K. Nayar, "Determining the camera response
       from images: what is knowable?", IEEE TPAMI 25(11), 2003.
    """
    z, t = _check_ldr(images, exposure_time)
    if n_samples is not None and int(n_samples) < 1:
        raise ValueError(f"n_samples must be >= 1 or None (all pixels), got {n_samples}")
    lam = _check_scalar(smoothness, "smoothness", nonneg=True)
    rng = np.random.default_rng(rng)
    zc = _channels_last(z, channel_axis)                                         # (P, n_pix, C)
    n_exp, _, n_ch = zc.shape
    w = weights_debevec()
    log_t = np.log(t)
    out = np.empty((LDR_SIZE, n_ch))
    level = None                                                                 # (n_pix, C) summed codes
    if n_samples is not None:
        level = zc[0].astype(np.int32 if n_exp > 257 else np.uint16)
        for j in range(1, n_exp):
            level += zc[j]
    for c in range(n_ch):
        if level is None:
            zs = zc[:, :, c]
        else:
            zs = zc[:, _debevec_samples(level[:, c], (LDR_SIZE - 1) * n_exp, int(n_samples), rng), c]
        out[:, c] = _debevec_solve(zs.T, log_t, w, lam)
    return out[:, 0] if channel_axis is None else out


def response_robertson(images: np.ndarray, exposure_time: Any, *, max_iter: int = 30,
                       threshold: float = 0.01, channel_axis: int | None = None) -> np.ndarray:
    """Inverse camera response by Robertson, Borman & Stevenson's iteration.

    Parameters
    ----------
    images : (n_exp, ...) ndarray of uint8
        An exposure bracket of a static scene, sorted by exposure time.
    exposure_time : (n_exp,) array_like
        Seconds; finite, > 0, non-decreasing.
    max_iter : int
        Most iterations.
    threshold : float
        Stop when the mean absolute change of the (normalised) response is
        below this.
    channel_axis : int or None
        Axis of colour channels (one curve per channel); ``None`` pools all
        values into one curve.

    Returns
    -------
    response : (256,) or (256, C) ndarray of float64
        :math:`I(z) = f^{-1}(z)`, linear exposure (relative) per code value,
        normalised to :math:`I(128) = 1`. Codes never observed are linearly
        interpolated between observed neighbours.

    Notes
    -----
    Starting from the linear response, alternate ([2] eqs. 9-10)

    .. math::
        \\hat E_i = \\frac{\\sum_j w(Z_{ij}) t_j I(Z_{ij})}{\\sum_j w(Z_{ij}) t_j^2},
        \\qquad
        I(m) = \\frac{1}{|\\Omega_m|} \\sum_{(i,j) \\in \\Omega_m} t_j \\hat E_i,

    with :math:`\\Omega_m = \\{(i, j): Z_{ij} = m\\}` over all pixels (those
    with a zero weight sum are left out of the update) and Robertson's
    weights (:func:`weights_robertson`); then :math:`I \\leftarrow I / I(128)`.
    Each pass gathers :math:`w t_j I` per exposure from a 256-entry table and
    accumulates :math:`t_j \\hat E_i` per code with ``bincount``.
    """
    z, t = _check_ldr(images, exposure_time)
    if int(max_iter) < 1:
        raise ValueError(f"max_iter must be >= 1, got {max_iter}")
    thr = _check_scalar(threshold, "threshold", nonneg=True)
    zc = _channels_last(z, channel_axis)                                         # (P, n_pix, C)
    n_exp, n_pix, n_ch = zc.shape
    w = weights_robertson()
    codes = np.arange(LDR_SIZE, dtype=np.float64)
    out = np.empty((LDR_SIZE, n_ch))
    for c in range(n_ch):
        zi = zc[:, :, c]
        den = np.zeros(n_pix)
        for j in range(n_exp):
            den += (w * (t[j] * t[j])).take(zi[j])                               # eq. sum w t^2
        ok = den > 0
        zj = [zi[j, ok].astype(np.intp) for j in range(n_exp)]                   # samples of pixels with weight
        inv_den = 1.0 / den[ok]
        count = sum(np.bincount(q, minlength=LDR_SIZE) for q in zj).astype(np.float64)
        seen = count > 0
        resp = codes / (LDR_SIZE // 2)
        if not seen.any():                                                       # nothing well exposed
            out[:, c] = resp
            continue
        for _ in range(int(max_iter)):
            num = np.zeros(inv_den.size)
            for j in range(n_exp):
                num += (w * t[j] * resp).take(zj[j])                             # eq. sum w t I (a table per exposure)
            e = num * inv_den                                                    # eq. E_i
            new = sum(t[j] * np.bincount(zj[j], weights=e, minlength=LDR_SIZE) for j in range(n_exp))
            new[seen] /= count[seen]                                             # eq. I(m) = mean t_j E_i
            if not seen.all():
                new[~seen] = np.interp(codes[~seen], codes[seen], new[seen])
            mid = new[LDR_SIZE // 2]
            if mid > 0:
                new /= mid                                                       # eq. I(128) = 1
            diff = float(np.mean(np.abs(new - resp)))
            resp = new
            if diff < thr:
                break
        out[:, c] = resp
    return out[:, 0] if channel_axis is None else out


def merge_response(images: np.ndarray, exposure_time: Any, response: np.ndarray | None = None, *,
                   method: Literal["debevec", "robertson"] = "debevec",
                   channel_weights: Literal["each", "mean"] = "each", return_valid: bool = False,
                   dtype: type | np.dtype = np.float32) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """HDR merge of 8-bit images through a calibrated inverse camera response.

    Parameters
    ----------
    images : (n_exp, ...) ndarray of uint8 or uint16
        An exposure bracket, sorted by exposure time; with a ``(256, C)``
        response the last axis holds the ``C`` colour channels. 16-bit
        images need a ``(65536,)`` or ``(65536, C)`` response (the weights
        are stretched to 65536 codes, :func:`weights_debevec`).
    exposure_time : (n_exp,) array_like
        Seconds; finite, > 0, non-decreasing.
    response : (256,) or (256, C) ndarray or None
        Linear inverse response :math:`I(z) = f^{-1}(z) \\ge 0` (relative
        exposure per code): :func:`response_robertson`'s output,
        ``np.exp(response_debevec(...))`` or :func:`calibrate_response`'s
        (65536 entries for 16-bit images). ``None``: linear, :math:`I(z) = z / 128`.
    method : {'debevec', 'robertson'}
        Weights and averaging (see Notes).
    channel_weights : {'each', 'mean'}
        ``'each'``: every colour channel weighted by its own code (the
        papers). ``'mean'``: the weights averaged over the channels of the
        pixel, as OpenCV's ``MergeDebevec`` does (a saturated channel then
        keeps the weight of the others); needs a ``(256, C)`` response or
        ``C = 1``. For comparisons; ``'each'`` is the better estimate.
    return_valid : bool
        Also return the valid mask.
    dtype : numpy dtype
        Floating type of the output (and of the accumulation).

    Returns
    -------
    radiance : (...) ndarray of ``dtype``
        Relative irradiance per second, in the response's units per second;
        finite everywhere.
    valid : (...) ndarray of bool
        Only with ``return_valid``: at least one sample with a non-zero
        weight (neither 0 nor 255). Elsewhere the radiance comes from the
        shortest exposure if it reads above mid-grey (saturated pixel, a lower
        bound) and from the longest one otherwise (black pixel).

    Notes
    -----
    Debevec & Malik ([1] eq. 6), hat weights :math:`w` (:func:`weights_debevec`),
    averaged in the log domain:

    .. math::
        \\ln \\hat E = \\frac{\\sum_j w(Z_j) (\\ln I(Z_j) - \\ln t_j)}{\\sum_j w(Z_j)}.

    Robertson et al. ([2] eq. 9), weights :math:`w` (:func:`weights_robertson`),
    the maximum-likelihood estimate in the linear domain:

    .. math::
        \\hat E = \\frac{\\sum_j w(Z_j) t_j I(Z_j)}{\\sum_j w(Z_j) t_j^2}.

    Both are sums over the exposures of a per-code table: exposure
    :math:`j` adds :math:`w(z) a_j(z)` to the numerator and :math:`w(z) b_j`
    to the denominator (Debevec: :math:`a_j = \\ln I - \\ln t_j, b_j = 1`;
    Robertson: :math:`a_j = t_j I, b_j = t_j^2`). The two products are
    tabulated per code value and channel once (256 x C entries per
    exposure) and gathered together as one complex number per sample, in
    blocks of pixels that stay in the CPU cache: no per-pixel arithmetic but
    the sums, the division and (Debevec) the exponential.

    Zero responses are raised to the smallest positive value before the log.
    The hat :math:`w(z) = z` / :math:`255 - z` is OpenCV's (version 4.x and
    later); with ``channel_weights='mean'`` the Debevec merge equals
    OpenCV's ``MergeDebevec`` to float32 rounding where a weight is
    non-zero (``docs/hdr.md``).
    """
    if method not in ("debevec", "robertson"):
        raise ValueError(f"method must be 'debevec' or 'robertson', got {method!r}")
    if channel_weights not in ("each", "mean"):
        raise ValueError(f"channel_weights must be 'each' or 'mean', got {channel_weights!r}")
    z, t = _check_ldr(images, exposure_time, allow_16bit=True)
    n_codes = int(np.iinfo(z.dtype).max) + 1                                     # 256 or 65536
    dtype = np.dtype(dtype)
    if dtype.kind != "f":
        raise ValueError(f"dtype must be a floating type, got {dtype}")
    if response is None:
        resp = np.arange(n_codes, dtype=np.float64) / (n_codes // 2)
    else:
        resp = np.asarray(response, dtype=np.float64)
        if resp.ndim not in (1, 2) or resp.shape[0] != n_codes:
            raise ValueError(f"response must be ({n_codes},) or ({n_codes}, C) for {z.dtype} images, got shape "
                             f"{resp.shape}")
        _check_finite(resp, "response")
        if np.any(resp < 0):
            raise ValueError(f"response{_index(resp < 0)[1]} < 0: an inverse response is non-negative")
        if resp.ndim == 2 and (z.ndim < 3 or z.shape[-1] != resp.shape[1]):
            raise ValueError(f"a ({n_codes}, {resp.shape[1]}) response needs images (n_exp, ..., {resp.shape[1]}), "
                             f"got shape {z.shape}")
    if resp.ndim == 1:
        resp = resp[:, None]
    n_ch = resp.shape[1]
    if channel_weights == "mean" and n_ch == 1 and z.ndim >= 3 and z.shape[-1] > 1:
        raise ValueError("channel_weights='mean' needs a (256, C) response for images with C channels last; "
                         "repeat the (256,) response C times")
    tab = resp.T                                                                 # (C, 256)
    if method == "debevec":
        w = weights_debevec(n_codes)
        pos = tab[tab > 0]
        log_i = np.log(np.maximum(tab, pos.min() if pos.size else 1.0))
        a = log_i[None] - np.log(t)[:, None, None]                               # eq. a_j = ln I - ln t_j
        b = np.ones_like(t)
        fallback = np.exp(a)                                                     # I(z) / t_j
    else:
        w = weights_robertson(n_codes)
        a = t[:, None, None] * tab[None]                                         # eq. a_j = t_j I
        b = t * t                                                                # eq. b_j = t_j^2
        fallback = tab[None] / t[:, None, None]
    rad, valid = _merge_tables(z, w, a.reshape(t.size, -1), b, fallback.reshape(t.size, -1), n_ch,
                               method == "debevec", channel_weights == "mean", dtype)
    return (rad, valid) if return_valid else rad


#: Pixel values (exposures x pixels x channels) merged at once by :func:`merge_response`.
_BLOCK_LDR: int = 1 << 15


def _merge_tables(z: np.ndarray, w: np.ndarray, a: np.ndarray, b: np.ndarray, fallback: np.ndarray, n_ch: int,
                  log_domain: bool, mean_weights: bool, dtype: np.dtype) -> tuple[np.ndarray, np.ndarray]:
    """:func:`merge_response`'s sums through per-code tables, in blocks.

    ``a`` is (P, C * 256) (channel-major), ``b`` (P,), ``fallback`` (P, C * 256)
    the value a single sample gives; ``w`` (256,) the weights.
    """
    n_exp = z.shape[0]
    zf = z.reshape(n_exp, -1)
    n = zf.shape[1]
    cdt = np.complex64 if dtype.itemsize <= 4 else np.complex128
    wt = np.tile(w, n_ch)                                                        # (C * 256,)
    if mean_weights:
        a_t = a.astype(dtype)
        w_t = wt.astype(dtype)
    else:
        tables = (wt * a + 1j * (wt[None] * b[:, None])).astype(cdt)             # eq. w a_j + i w b_j
    n_codes = w.size
    offs = np.arange(n_ch, dtype=np.intp) * n_codes if n_ch > 1 else None
    rad = np.empty(n, dtype=dtype)
    valid = np.empty(n, dtype=bool)
    step = max(n_ch, (_BLOCK_LDR // n_exp) // n_ch * n_ch)
    for lo in range(0, n, step):
        hi = min(lo + step, n)
        zb = zf[:, lo:hi]
        idx = zb if offs is None else (zb.reshape(n_exp, -1, n_ch) + offs).reshape(n_exp, -1)
        if mean_weights:
            num = np.zeros(hi - lo, dtype=dtype)
            den = np.zeros(hi - lo, dtype=dtype)
            for j in range(n_exp):
                om = w_t.take(idx[j]).reshape(-1, n_ch).mean(axis=1, keepdims=True)  # channel-mean weight
                om = np.broadcast_to(om, (om.shape[0], n_ch)).reshape(-1)
                num += om * a_t[j].take(idx[j])
                den += om * dtype.type(b[j])
        else:
            acc = tables[0].take(idx[0])
            for j in range(1, n_exp):
                acc += tables[j].take(idx[j])                                    # eq. sum_j w a_j, sum_j w b_j
            num, den = acc.real, acc.imag
        ok = den > 0
        out = rad[lo:hi]
        all_ok = bool(ok.all())
        np.divide(num, den, out=out, where=ok)
        if not all_ok:
            out[~ok] = 0                                                         # set below (no exp of garbage)
        if log_domain:
            np.exp(out, out=out)
        valid[lo:hi] = ok
        if not all_ok:
            bad = np.flatnonzero(~ok)
            first = zb[0, bad] > (n_codes - 1) / 2                              # saturated: shortest exposure
            out[bad] = np.where(first, fallback[0].take(idx[0, bad]), fallback[-1].take(idx[-1, bad]))
    return rad.reshape(z.shape[1:]), valid.reshape(z.shape[1:])


# --------------------------------------------------------------------------- LDR cameras: calibration, consistency


def calibrate_response(images: np.ndarray, exposure_time: Any, *, method: str = "debevec",
                       rng: np.random.Generator | int | None = 0, n_samples: int = 4096,
                       smoothness: float = 1.0) -> np.ndarray:
    """Linear inverse response of a colour LDR camera, per channel, from an exposure bracket.

    Parameters
    ----------
    images : (n_exp, ..., C) ndarray of uint8 or uint16
        An exposure bracket of a static scene (or several brackets with the
        same times, stacked along the pixel axes), sorted by exposure time;
        the last axis holds the ``C`` colour channels.
    exposure_time : (n_exp,) array_like
        Seconds; finite, > 0, non-decreasing.
    method : {'debevec', 'robertson'}
        :func:`response_debevec` (``np.exp`` of it) or :func:`response_robertson`.
    rng : numpy.random.Generator or int or None
        Sample choice of the Debevec solve (seeded: the same curve every run).
    n_samples, smoothness : int, float
        Of :func:`response_debevec`. The smoothness is 1 here, not 10: on a
        seeded gamma-2.2 bracket (1/60, 1/15, 1/4, 1 s, 1 % noise) λ = 10
        bent the curve by 20-150 % below code 10 and the merged radiance of
        the darker half of the pixels was 16 % off at the 90th percentile;
        λ = 1 gave 3 %, near the 2 % of the true response (docs/hdr.md).

    Returns
    -------
    response : (n_codes, C) ndarray of float64
        :math:`I(z) = f^{-1}(z)`, relative exposure per code (``n_codes`` 256
        or 65536), 1 at the middle code; the ``response`` of :func:`merge_response`.

    Notes
    -----
    16-bit images are calibrated on their top 8 bits (``z >> 8``: a dense
    Debevec system of 65535 unknowns is out of reach, and a camera's curve
    is smooth on that scale); the 256-code curve is then interpolated in
    :math:`\\ln I` at the centres of the 256-code bins (code
    :math:`256 b + 127.5` for bin :math:`b`) to every 16-bit code, held
    constant beyond the first and last centre (codes whose merge weight is
    almost 0).
    """
    if method not in RESPONSE_METHODS:
        raise ValueError(f"unknown response calibration {method!r}; choose one of {', '.join(RESPONSE_METHODS)}")
    z, t = _check_ldr(images, exposure_time, allow_16bit=True)
    if z.ndim < 3:
        raise ValueError(f"images must be (n_exp, ..., C) with colour channels last, got shape {z.shape}")
    z8 = z if z.dtype == np.uint8 else (z >> 8).astype(np.uint8)
    if method == "debevec":
        log_r = response_debevec(z8, t, n_samples=n_samples, smoothness=smoothness, rng=rng, channel_axis=-1)
    else:
        r = response_robertson(z8, t, channel_axis=-1)
        pos = r[r > 0]
        log_r = np.log(np.maximum(r, pos.min() if pos.size else 1.0))
    if z.dtype == np.uint8:
        return np.exp(log_r)
    centres = np.arange(LDR_SIZE) * 256.0 + 127.5
    codes = np.arange(1 << 16, dtype=np.float64)
    log16 = np.stack([np.interp(codes, centres, log_r[:, c]) for c in range(log_r.shape[1])], axis=1)
    return np.exp(log16 - log16[1 << 15])                                      # I(32768) = 1


def exposure_ratios(signal: np.ndarray, usable: np.ndarray, exposure_time: Any, *,
                    min_pixels: int = 64) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Measured brightness ratio of consecutive frames of a bracket, against the ratio of their times.

    Parameters
    ----------
    signal : (n_exp, ...) ndarray of float
        The bracket linearised: dark-subtracted raw values of a linear
        sensor, or :math:`I(z)` of an LDR camera; sorted by exposure time.
    usable : (n_exp, ...) ndarray of bool
        Samples neither saturated nor in the noise (e.g. at least 2 % of the
        white level and below the saturation margin).
    exposure_time : (n_exp,) array_like
        Seconds; finite, > 0, non-decreasing.
    min_pixels : int
        Fewest samples usable in both frames for a ratio to be measured.

    Returns
    -------
    measured : (n_exp - 1,) ndarray of float64
        :math:`\\operatorname{median}_p\\, s_{j+1}(p) / s_j(p)` over the samples
        usable in both frames; NaN where fewer than ``min_pixels`` are.
    expected : (n_exp - 1,) ndarray of float64
        :math:`t_{j+1} / t_j`.
    n_pixels : (n_exp - 1,) ndarray of int64
        Samples the medians were taken over.

    Notes
    -----
    A static scene under a steady light gives :math:`s_j(p) = r(p)\\, t_j`
    plus noise, so every pixel's ratio estimates :math:`t_{j+1}/t_j`; the
    median ignores the few pixels that moved, clipped or are hot. The same
    frame labelled with two times reads 1 against the times' ratio, a
    flickering light the ratio of the two light levels times the expected
    one, and a wrong manifest time the wrong factor.
    """
    s = np.asarray(signal)
    ok = np.asarray(usable, dtype=bool)
    if s.shape != ok.shape or s.ndim < 1:
        raise ValueError(f"signal {s.shape} and usable {ok.shape} must be the same (n_exp, ...) shape")
    t = _check_times(exposure_time, s.shape[0])
    n = s.shape[0] - 1
    measured, n_px = np.full(n, np.nan), np.zeros(n, dtype=np.int64)
    flat, okf = s.reshape(s.shape[0], -1), ok.reshape(s.shape[0], -1)
    for j in range(n):
        both = okf[j] & okf[j + 1] & (flat[j] > 0)
        n_px[j] = int(both.sum())
        if n_px[j] >= max(int(min_pixels), 1):
            measured[j] = float(np.median(flat[j + 1][both].astype(np.float64) / flat[j][both]))
    return measured, t[1:] / t[:-1], n_px


# --------------------------------------------------------------------------- dispatcher


def merge(frames: np.ndarray, exposure_time: Any, *, method: str = "linear",
          **kwargs: Any) -> tuple[np.ndarray, np.ndarray]:
    """Merge an exposure bracket with the chosen method.

    Parameters
    ----------
    frames : (n_exp, ...) ndarray
        Raw frames (``'linear'``) or 8-bit images (``'debevec'``, ``'robertson'``).
    exposure_time : (n_exp,) array_like
        Seconds.
    method : {'linear', 'debevec', 'robertson'}
        :func:`merge_linear` or :func:`merge_response` with that method.
    **kwargs
        Passed on (``black_level``, ``white_level``, ... for ``'linear'``;
        ``response`` for the others).

    Returns
    -------
    radiance : (...) ndarray
        Merged radiance (units of the method).
    valid : (...) ndarray of bool
        Pixels with at least one usable sample.
    """
    if method == "linear":
        return merge_linear(frames, exposure_time, **kwargs)
    if method in ("debevec", "robertson"):
        return merge_response(frames, exposure_time, method=method, return_valid=True, **kwargs)
    raise ValueError(f"unknown HDR merge method {method!r}; choose one of {', '.join(MERGE_METHODS)}")
