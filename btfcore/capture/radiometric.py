"""Radiometric correction: per-LED intensity/colour and the camera colour matrix.

The LEDs of a dome differ in intensity and colour, and the camera's colour
filters are not the target colour space. Before rectified radiance maps are
stacked into a BTF they are "corrected radiometrically using the calibration
data obtained beforehand" (thesis §1.1.3; App. "Multiplexed acquisition"
§4.1 and VMV paper §5.1: "We use LED calibration data in order to account for variations in the LEDs'
spectra").

* **LED calibration.** A flat Lambertian white standard of albedo ``a`` lit
  by LED ``l`` from polar angle :math:`\\theta_l` reflects
  :math:`a/\\pi \\cos\\theta_l` per unit irradiance (the simulator's BTF
  convention, docs/decisions.md "What a BTF value is"). The measured value is
  that times the LED's RGB gain :math:`g_{l,c}`; :func:`led_calibration`
  estimates the gain as a median over texels and views and
  :func:`apply_led_calibration` divides it out.
* **Colour matrix.** A 3x3 (or 3x4 affine) matrix maps camera RGB to the
  target space (:func:`apply_colour_matrix`); :func:`fit_colour_matrix`
  fits one to colour-checker patches by least squares.
* **Is it a white standard?** Before its gains calibrate anything, the
  capture must look like one: flat in brightness and in chromaticity across
  texels under each LED, and of one chromaticity under an LED from every
  view (:func:`white_texture_statistics`, :func:`white_standard_statistics`,
  tolerances :data:`WHITE_TOLERANCES`; docs/reconstruction.md, "Is the white
  standard a white standard?").

On a multiplexed capture the LED gains act on the single-LED images, so the
calibration is applied *after* demultiplexing (and the white standard's own
multiplexed capture is demultiplexed first).

References
----------
.. [1] The thesis, §1.1.3, and App. "Multiplexed acquisition" (paper 2) §4.1;
   VMV paper §5.1.
.. [2] C. Schwartz, R. Sarlette, M. Weinmann, M. Rump and R. Klein, "Design
   and implementation of practical bidirectional texture function
   measurement devices focusing on the developments at the University of
   Bonn", Sensors 14(5), 2014 (dome calibration).
"""

from __future__ import annotations

import math
import warnings

import numpy as np

__all__ = [
    "MIN_COS_THETA",
    "WHITE_BORDER_FRACTION",
    "WHITE_MAX_TEXELS",
    "WHITE_TOLERANCES",
    "apply_colour_matrix",
    "apply_led_calibration",
    "as_colour_matrix",
    "fit_colour_matrix",
    "led_calibration",
    "white_standard_problems",
    "white_standard_statistics",
    "white_texture_statistics",
]

#: LEDs closer to the horizon than this cosine (about 89.4 deg) cannot be calibrated on a flat standard.
MIN_COS_THETA = 0.01

#: Share of each texture side left out at each border before the white-standard statistics: the
#: rectified border texels mix the sample's edge with its surroundings (on the simulated white they read
#: 0.6-1.1 of the centre at the grazing camera), which says nothing about the target itself.
WHITE_BORDER_FRACTION = 1 / 8

#: At most about this many texels of a texture enter the white-standard statistics (every ``step``-th
#: row and column): percentiles of 4096 samples are within noise of all of them, and a bonn-dome2 view
#: (198 textures of 128 x 128) costs a quarter of the time.
WHITE_MAX_TEXELS = 4096

#: Largest values of the white-standard statistics of :func:`white_standard_statistics` that pass.
#: Measured on ``btf simulate`` + ``btf ingest`` stores (docs/reconstruction.md, "Is the white standard
#: a white standard?", has the table): the simulated white standard (tiny dome at 8, 32 and 64 texels,
#: bonn-dome2 at 128) reads at most 0.033 / 0.026 / 0.0015; the six material classes at 32 texels and
#: more (6 materials per class on tiny, a leather on bonn-dome2) at least 0.29 (leather) / 0.20
#: (leather) / 0.027 (stone; metal excepted, 0.003). Each tolerance lies a factor >= 3 above the white
#: and >= 2 below the materials; every material fails at least two of the three. At 8 texels (textures
#: averaged down to 6 x 6 inner texels) the colour statistics of some materials fall to the white's;
#: ``brightness_spread`` (>= 0.18) still refuses them all.
#:
#: * ``brightness_spread`` -- median over LED x view textures of (P95 - P5) of the texels' channel sum
#:   less its plane (slopes from the medians of the halves, so specks do not tilt it), over P50 of the
#:   channel sum: a flat Lambertian target is uniform under every LED up to noise and a smooth
#:   fall-off (a real dome's LEDs at 0.65 m light a 5 cm sample up to about +-8 % unevenly, which the
#:   plane removes); texture, relief, shadows and highlights are not. 0.10.
#: * ``chromaticity_spread`` -- the same median of max over channels of (P95 - P5) / P50 of the texels'
#:   chromaticity (channel / channel sum): under one LED the LED's colour and the camera's sensitivity
#:   scale every texel alike, so a neutral target has one chromaticity; a coloured, patterned material
#:   does not. 0.08.
#: * ``view_chromaticity_deviation`` -- how much an LED's colour relative to the other LEDs changes with
#:   the view (max over LEDs of a median over views, in log units): a Lambertian target's colour does not
#:   depend on the light/view configuration, a glossy coloured one's moves toward its highlights'.
#:   Per-LED colours (the gains being measured) and per-camera colours (a real dome's cameras differ)
#:   cancel out exactly, so neither can fail it. 0.006.
#:
#: An absolute neutrality test (R = G = B) would be wrong: the camera's raw RGB of a white is not
#: neutral (the simulated camera's sensitivities are 3 : 5 : 2.5), which is what the gains correct. A
#: flat, uniformly coloured Lambertian card passes all three: without an absolute colour reference it
#: cannot be told from a white under coloured LEDs (the colour matrix of a colour chart corrects that).
WHITE_TOLERANCES: dict[str, float] = {
    "brightness_spread": 0.10,
    "chromaticity_spread": 0.08,
    "view_chromaticity_deviation": 0.006,
}


def _check_finite(x: np.ndarray, name: str) -> None:
    finite = np.isfinite(x)
    if not finite.all():
        idx = tuple(int(v) for v in np.unravel_index(int(np.argmin(finite)), x.shape))
        raise ValueError(
            f"{name} contains NaN or Inf: {name}{list(idx)} = {float(x[idx])!r} "
            f"({int(x.size - finite.sum())} non-finite values in all)"
        )


def _float_dtype(x: np.ndarray) -> type:
    return np.float32 if x.dtype == np.float32 else np.float64


def led_calibration(
    white: np.ndarray,
    light_dirs: np.ndarray,
    albedo: float = 0.99,
    *,
    mask: np.ndarray | None = None,
) -> np.ndarray:
    """Per-LED RGB gain from a capture of a flat Lambertian white standard.

    Parameters
    ----------
    white : (n_leds, ..., C) array_like
        Linear, demosaicked, rectified radiance of the white standard, one
        image per LED (demultiplexed if captured multiplexed); the middle
        axes are anything (texel rows and columns, views). ``C`` is
        usually 3 (RGB).
    light_dirs : (n_leds, 3) array_like
        Direction from the sample to each LED in the sample frame (only the
        polar angle matters, so any turntable position will do).
    albedo : float
        Albedo of the standard in (0, 1] (the simulator's standard: 0.99).
    mask : (...) array_like of bool, optional
        Texels (and views) to use, shaped like ``white.shape[1:-1]``: leave
        out the sample holder, dust, specks.

    Returns
    -------
    gain : (n_leds, C) ndarray of float64
        Radiance of each LED and channel relative to a unit-irradiance
        white light.

    Raises
    ------
    ValueError
        On NaN/Inf in ``white`` or ``light_dirs`` (names the index), an LED
        at or below the horizon (names the LED), a non-positive gain (a
        dead LED or a missing frame; names the LED and channel), or shapes
        that do not fit.

    Notes
    -----
    A white standard of albedo :math:`a` lit by LED :math:`l` reflects

    .. math:: W_{l,x,c} = \\frac{a}{\\pi} \\cos\\theta_l \\; g_{l,c}

    at every texel :math:`x` and every view (Lambertian: independent of the
    view). The estimate is the median over texels and views,

    .. math:: \\hat g_{l,c} = \\operatorname{median}_x
              \\frac{W_{l,x,c}}{(a/\\pi) \\cos\\theta_l},

    which ignores specks, hot pixels and a few mis-registered border texels
    (up to half of the samples). Noise-free data of the simulator is
    recovered to float32 rounding.
    """
    w = np.asarray(white)
    if not (np.issubdtype(w.dtype, np.floating) or np.issubdtype(w.dtype, np.integer)):
        raise ValueError(f"white must be real numbers, got dtype {w.dtype}")
    if w.ndim < 2:
        raise ValueError(f"white must be (n_leds, ..., C), got shape {w.shape}")
    n_leds, n_ch = w.shape[0], w.shape[-1]
    d = np.asarray(light_dirs, dtype=np.float64)
    if d.shape != (n_leds, 3):
        raise ValueError(f"light_dirs must be ({n_leds}, 3) for {n_leds} LED images, got shape {d.shape}")
    _check_finite(d, "light_dirs")
    albedo = float(albedo)
    if not (0.0 < albedo <= 1.0):
        raise ValueError(f"albedo must lie in (0, 1], got {albedo!r}")
    _check_finite(w, "white")
    norm = np.linalg.norm(d, axis=1)
    cos_t = d[:, 2] / np.where(norm > 0, norm, 1.0)
    low = np.flatnonzero(~(cos_t > MIN_COS_THETA))
    if low.size:
        led = int(low[0])
        raise ValueError(
            f"LED {led} is at or below the horizon of the white standard (cos theta = {cos_t[led]:.4f} <= "
            f"{MIN_COS_THETA}); a flat standard cannot calibrate LEDs {low.tolist()}"
        )
    flat = w.reshape(n_leds, -1, n_ch).astype(np.float64)
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.shape != w.shape[1:-1]:
            raise ValueError(f"mask must have shape {w.shape[1:-1]} (white's middle axes), got {m.shape}")
        if not m.any():
            raise ValueError("mask selects no texel")
        flat = flat[:, m.ravel()]
    expected = albedo / np.pi * cos_t                               # eq. a/pi cos(theta_l)  (§1.1.3)
    gain = np.median(flat, axis=1) / expected[:, None]              # eq. g = median_x W / (a/pi cos theta)
    bad = np.argwhere(~(gain > 0))
    if bad.size:
        led, c = (int(v) for v in bad[0])
        raise ValueError(
            f"LED {led} channel {c} has gain {gain[led, c]:.3g} <= 0 on the white standard: a dead LED, a "
            f"missing or black frame, or an over-subtracted dark frame"
        )
    return gain


def _row_percentiles(a: np.ndarray, qs: tuple[float, ...]) -> np.ndarray:
    """Percentiles over the last axis of ``a`` (n, m) or (n, C, m) leaving out NaN (a texel NaN in any
    channel); NaN for an empty row. Shape ``(len(qs), n[, C])``, float64; one vectorised call when nothing
    is NaN."""
    bad = np.isnan(a) if a.ndim == 2 else np.isnan(a).any(axis=1)    # (n, m)
    if not bad.any():
        return np.percentile(a, qs, axis=-1).astype(np.float64)
    out = np.full((len(qs),) + a.shape[:-1], np.nan)
    for i in range(a.shape[0]):
        keep = a[i][..., ~bad[i]]
        if keep.shape[-1]:
            out[:, i] = np.percentile(keep, qs, axis=-1)
    return out


def _detrended(y: np.ndarray, *, rows: int, cols: int) -> np.ndarray:
    """``y`` (n, rows * cols) less its plane ``b u + c v`` over the texture (``u``, ``v`` in [-1, 1]),
    per row: a smooth fall-off of the irradiance across the sample (a real dome's LEDs are at a finite
    distance) is not a texture. Each slope is the difference of the medians of the two halves over the
    distance of their centres, exact for a plane on the symmetric grid and not tilted by specks (a
    least-squares plane is: one speck of 20x among 144 texels tilts it by 0.4). NaN texels are left out.
    """
    v, u = np.meshgrid(np.linspace(-1, 1, rows), np.linspace(-1, 1, cols), indexing="ij")
    out = y.astype(np.float64)
    for coord in (u.ravel(), v.ravel()):
        hi, lo = coord > 0, coord < 0
        if not hi.any():
            continue                                                 # one column or row: no slope
        med_hi, med_lo = _row_percentiles(out[:, hi], (50,))[0], _row_percentiles(out[:, lo], (50,))[0]
        slope = (med_hi - med_lo) / (coord[hi].mean() - coord[lo].mean())
        out -= slope[:, None] * coord                                 # eq. y - b u - c v
    return out


def white_texture_statistics(
    white: np.ndarray, border: float = WHITE_BORDER_FRACTION,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-LED flatness and chromaticity of one view of a white-standard capture.

    Parameters
    ----------
    white : (n_leds, h, w, C) array_like
        Linear radiance of the white standard seen from one view, one
        texture per LED (a view chunk of an ingested BTF store).
    border : float
        Share of each side left out at each border, in [0, 0.5). Of the
        rest every ``step``-th row and column is used, ``step`` the smallest
        that keeps at most :data:`WHITE_MAX_TEXELS` texels.

    Returns
    -------
    brightness_spread : (n_leds,) ndarray of float64
        (P95 - P5) of the channel sum less its plane over the texture
        (robust slopes: medians of the halves), over P50 of the channel sum.
    chromaticity_spread : (n_leds,) ndarray of float64
        Max over channels of (P95 - P5) / P50 over texels of the chromaticity
        (each channel over the channel sum).
    chromaticity : (n_leds, C) ndarray of float64
        Median over texels of the chromaticity, normalised to sum 1.

    Notes
    -----
    Invalid texels are left out: a non-finite channel (all statistics), a
    channel sum <= 0 (chromaticity). A texture with no valid texel, or a
    P50 <= 0, gives ``inf`` (it is not a white standard). One pass over the
    chunk; no statistic needs another view.
    """
    x = np.asarray(white)
    if x.ndim != 4:
        raise ValueError(f"white must be (n_leds, h, w, C) for one view, got shape {x.shape}")
    if not 0 <= border < 0.5:
        raise ValueError(f"border must lie in [0, 0.5), got {border!r}")
    n, h, w, C = x.shape
    bh, bw = int(h * border), int(w * border)
    step = max(1, math.ceil(math.sqrt((h - 2 * bh) * (w - 2 * bw) / WHITE_MAX_TEXELS)))
    dtype = np.float32 if x.dtype == np.float32 else np.float64
    x = np.ascontiguousarray(np.moveaxis(x[:, bh:h - bh:step, bw:w - bw:step], -1, 1),
                             dtype=dtype).reshape(n, C, -1)          # (n, C, m)
    y = x.sum(axis=1)                                                # (n, m); NaN/Inf where a channel is
    ok = np.isfinite(y)
    y[~ok] = np.nan
    with np.errstate(invalid="ignore", divide="ignore"):
        q = x / y[:, None]                                           # eq. chromaticity x_c / sum_c x_c
    q[np.broadcast_to(~(y > 0)[:, None], q.shape)] = np.nan          # no colour where nothing is reflected
    p50 = _row_percentiles(y, (50,))[0]                               # (n,)
    residual = _detrended(y, rows=len(range(bh, h - bh, step)), cols=len(range(bw, w - bw, step)))
    p5, p95 = _row_percentiles(residual, (5, 95))                    # (n,) each
    c5, c50, c95 = _row_percentiles(q, (5, 50, 95))                  # (n, C) each
    with np.errstate(invalid="ignore", divide="ignore"):
        spread = np.where(p50 > 0, (p95 - p5) / p50, np.inf)         # eq. (P95 - P5)(y - plane) / P50(y)
        chroma_spread = np.where((c50 > 0).all(axis=-1), np.max((c95 - c5) / c50, axis=-1), np.inf)
        chromaticity = c50 / c50.sum(axis=-1, keepdims=True)
    return np.where(np.isnan(spread), np.inf, spread), np.where(np.isnan(chroma_spread), np.inf, chroma_spread), \
        chromaticity


def white_standard_statistics(
    brightness_spread: np.ndarray, chromaticity_spread: np.ndarray, chromaticity: np.ndarray,
) -> dict[str, float]:
    """The three white-standard statistics of a capture from its per-view ones.

    Parameters
    ----------
    brightness_spread, chromaticity_spread : (n_views, n_leds) array_like
        :func:`white_texture_statistics` of every view.
    chromaticity : (n_views, n_leds, C) array_like
        Likewise.

    Returns
    -------
    stats : dict
        ``brightness_spread`` and ``chromaticity_spread`` (median over LED x
        view textures: a few bad frames do not decide), and
        ``view_chromaticity_deviation``: with :math:`L_{v,l,c}` the log of
        the chromaticity less its mean over channels and less its median
        over the view's LEDs, the max over LEDs of the median over views of
        :math:`\\max_c |L_{v,l,c} - \\operatorname{median}_v L_{v,l,c}|`. It
        is unchanged by any per-LED colour (the gains being measured) and any
        per-view colour (a real dome's cameras differ), so only a colour
        that changes with the light/view configuration fails it. Compare
        with :data:`WHITE_TOLERANCES`; ``inf`` where undefined.
    """
    s = np.asarray(brightness_spread, dtype=np.float64)
    cs = np.asarray(chromaticity_spread, dtype=np.float64)
    m = np.asarray(chromaticity, dtype=np.float64)
    if s.ndim != 2 or cs.shape != s.shape or m.shape[:2] != s.shape:
        raise ValueError(f"statistics must be (n_views, n_leds) and (n_views, n_leds, C), got {s.shape}, "
                         f"{cs.shape} and {m.shape}")
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)             # all-NaN slices: textures without colour
        L = np.log(np.where(m > 0, m, np.nan))
        L = L - L.mean(axis=-1, keepdims=True)                       # eq. log chromaticity, free of scale
        L = L - np.nanmedian(L, axis=1, keepdims=True)               # eq. relative to the view's median LED
        dev = np.abs(L - np.nanmedian(L, axis=0)).max(axis=-1)       # eq. max_c |L_vlc - median_v L_vlc|
        per_led = np.nanmedian(dev, axis=0)                          # invalid textures left out
    view_dev = float(np.nanmax(per_led)) if np.isfinite(per_led).any() else np.inf
    return {"brightness_spread": float(np.median(s)), "chromaticity_spread": float(np.median(cs)),
            "view_chromaticity_deviation": view_dev}


def white_standard_problems(stats: dict[str, float],
                            tolerances: dict[str, float] | None = None) -> list[tuple[str, float, float]]:
    """``(statistic, measured, tolerance)`` of each statistic above its tolerance (``[]``: a white standard).

    Parameters
    ----------
    stats : dict
        From :func:`white_standard_statistics`.
    tolerances : dict, optional
        Default :data:`WHITE_TOLERANCES`.
    """
    tol = WHITE_TOLERANCES if tolerances is None else tolerances
    return [(name, float(stats[name]), float(t)) for name, t in tol.items()
            if not float(stats[name]) <= t]                          # NaN fails too


def apply_led_calibration(
    radiance: np.ndarray,
    gain: np.ndarray,
    *,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """Divide each single-LED image by its LED's RGB gain.

    Parameters
    ----------
    radiance : (n_leds, ..., C) ndarray of float
        One image per LED (single-light or demultiplexed), channels last.
    gain : (n_leds, C) array_like
        From :func:`led_calibration`; finite and > 0.
    out : (n_leds, ..., C) ndarray, optional
        Output buffer (may be ``radiance`` itself).

    Returns
    -------
    corrected : (n_leds, ..., C) ndarray
        :math:`W_{l,x,c} / g_{l,c}`; float32 for float32 input, float64
        otherwise.

    Raises
    ------
    ValueError
        On mismatched shapes, or a gain that is NaN/Inf or <= 0 (names the
        LED and channel).
    """
    x = np.asarray(radiance)
    g = np.asarray(gain, dtype=np.float64)
    if x.ndim < 2 or g.shape != (x.shape[0], x.shape[-1]):
        raise ValueError(
            f"gain must be (n_leds, C) = ({x.shape[0] if x.ndim else '?'}, {x.shape[-1] if x.ndim else '?'}) "
            f"for radiance of shape {x.shape}, got {g.shape}"
        )
    _check_finite(g, "gain")
    bad = np.argwhere(g <= 0)
    if bad.size:
        led, c = (int(v) for v in bad[0])
        raise ValueError(f"gain[{led}, {c}] = {float(g[led, c])!r} must be > 0")
    dtype = _float_dtype(x)
    inv = (1.0 / g).astype(dtype).reshape((x.shape[0],) + (1,) * (x.ndim - 2) + (x.shape[-1],))
    return np.multiply(x, inv, out=out, dtype=dtype)                # eq. B = W / g_l


def as_colour_matrix(matrix: np.ndarray) -> np.ndarray:
    """A colour matrix checked for shape (3, 3) or (3, 4) and finiteness, as float64.

    Parameters
    ----------
    matrix : (3, 3) or (3, 4) array_like

    Returns
    -------
    matrix : (3, 3) or (3, 4) ndarray of float64

    Raises
    ------
    ValueError
        On another shape or NaN/Inf (names the index).
    """
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape not in ((3, 3), (3, 4)):
        raise ValueError(f"colour matrix must be (3, 3) or (3, 4) (affine), got shape {m.shape}")
    _check_finite(m, "matrix")
    return m


def apply_colour_matrix(rgb: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """Apply a camera colour-correction matrix.

    Parameters
    ----------
    rgb : (..., 3) ndarray of float
        Linear camera RGB, channels last.
    matrix : (3, 3) or (3, 4) array_like
        Linear map, or affine map with the offset in the last column.

    Returns
    -------
    out : (..., 3) ndarray
        :math:`M_{:, :3}\\, rgb + M_{:, 3}` per pixel; float32 for float32
        input, float64 otherwise.

    Raises
    ------
    ValueError
        On a wrong shape or NaN/Inf in the matrix (names the index).
    """
    x = np.asarray(rgb)
    if x.ndim < 1 or x.shape[-1] != 3:
        raise ValueError(f"rgb must have 3 channels on its last axis, got shape {x.shape}")
    m = as_colour_matrix(matrix)
    dtype = _float_dtype(x)
    out = x.astype(dtype, copy=False) @ m[:, :3].T.astype(dtype)    # eq. rgb' = M rgb
    if m.shape[1] == 4:
        out += m[:, 3].astype(dtype)                                # eq. rgb' = M rgb + o
    return out


def fit_colour_matrix(measured: np.ndarray, reference: np.ndarray, *, affine: bool = False) -> np.ndarray:
    """Least-squares colour matrix from patches of a colour target.

    Parameters
    ----------
    measured : (n, 3) array_like
        Linear camera RGB of ``n`` patches (e.g. the 24 of a ColorChecker).
    reference : (n, 3) array_like
        Their known linear values in the target space.
    affine : bool
        Fit a (3, 4) affine map (offset in the last column) instead of (3, 3).

    Returns
    -------
    matrix : (3, 3) or (3, 4) ndarray of float64
        Minimises :math:`\\sum_k \\|M\\, m_k (+ o) - r_k\\|^2`; use with
        :func:`apply_colour_matrix`.

    Raises
    ------
    ValueError
        On NaN/Inf (names the index), mismatched shapes, or too few or
        degenerate patches.
    """
    m = np.asarray(measured, dtype=np.float64)
    r = np.asarray(reference, dtype=np.float64)
    if m.ndim != 2 or m.shape[1] != 3 or r.shape != m.shape:
        raise ValueError(f"measured and reference must both be (n, 3), got {m.shape} and {r.shape}")
    _check_finite(m, "measured")
    _check_finite(r, "reference")
    A = np.concatenate([m, np.ones((len(m), 1))], axis=1) if affine else m
    if len(A) < A.shape[1] or np.linalg.matrix_rank(A) < A.shape[1]:
        raise ValueError(
            f"{len(m)} patches of rank {np.linalg.matrix_rank(A)} cannot determine a "
            f"{'3x4 affine' if affine else '3x3'} colour matrix; need {A.shape[1]} independent colours"
        )
    X = np.linalg.lstsq(A, r, rcond=None)[0]                         # eq. min ||A X - R||_F
    return X.T
