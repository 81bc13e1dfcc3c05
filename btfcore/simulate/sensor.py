"""A linear raw camera sensor: Bayer mosaic, photon and read noise, dark current, saturation.

Units: radiance in BTF units (the simulator's ground truth), time in seconds,
charge in electrons (e-), raw values in digital numbers (DN).

Model (per raw pixel ``p`` of colour filter ``ch(p)``, exposure time ``t``):

.. math::
    \\lambda_p &= k_{ch(p)} \\, L_{p, ch(p)} \\, t + D_p \\, t \\\\
    e_p &= \\min(\\mathrm{Poisson}(\\lambda_p), e_{fw}) + \\mathcal{N}(0, \\sigma_r^2) \\\\
    \\mathrm{DN}_p &= \\mathrm{clip}(\\mathrm{round}(\\min(e_p, e_{fw}) / g + b), 0, W)

with the sensitivity :math:`k` (e-/s per unit radiance, per filter colour),
the optional Gaussian PSF applied to :math:`L` per colour plane before the
mosaic, the dark-current map :math:`D` (e-/s), the full well
:math:`e_{fw}`, the read noise :math:`\\sigma_r`, the gain :math:`g` (e-/DN),
the black level :math:`b` and the white level
:math:`W = \\min(2^{bits} - 1, b + \\lfloor e_{fw} / g \\rfloor)`. The signal is
clipped at the full well once in the pixel (charge) and once in the readout
(the ADC range ends at the full well), so every saturated pixel reads exactly
``W`` and nothing exceeds it.

References
----------
.. [1] EMVA Standard 1288, Release 4.0 (2021): linear camera model,
   photon transfer (variance of DN = (mean DN - black) / gain + read noise).
.. [2] Thesis 1.1.3 (HDR from exposure brackets, dark frames) and the SR
   paper 5.1.1 (Robertson et al. merging).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy import ndimage

from btfcore.dome import BAYER_PATTERNS, SensorSpec

__all__ = [
    "BracketReport",
    "CAMERA",
    "GAUSSIAN_PHOTON_THRESHOLD_E",
    "SensorModel",
    "WELL_EXPOSED",
    "apply_psf",
    "bayer_channel_index",
    "choose_bracket",
    "dark_current_map",
    "dark_frames",
    "expected_dn",
    "expose",
    "mosaic",
    "signal_rate",
]

#: Fractions of the sensor's range ``(white - black)`` between which a pixel
#: counts as well exposed (noise-free), used by :func:`choose_bracket`.
WELL_EXPOSED: tuple[float, float] = (0.01, 0.9)

#: Mean electron count at and above which Poisson + read noise is drawn as one
#: Gaussian of the same mean and variance (the Poisson skewness
#: ``1/sqrt(lambda) <= 0.1`` is neglected; exact Poisson draws cost ~55 ns each
#: and dominated the exposure time); below it the Poisson count is exact.
GAUSSIAN_PHOTON_THRESHOLD_E: float = 100.0

_CHANNEL = {"R": 0, "G": 1, "B": 2}


@dataclass(frozen=True)
class SensorModel:
    """Which of the sensor's effects a simulated exposure has (the floors of the demo's report).

    Attributes
    ----------
    noise : bool
        Photon (and dark-current shot) noise, read noise and rounding to whole DN. ``False``:
        every frame is its noise-free mean, :func:`expected_dn` exactly (float64, not rounded).
    mosaic : bool
        The Bayer colour-filter array: each raw pixel measures one colour. ``False``: an ideal
        full-RGB sensor whose every pixel measures R, G and B (frames get a trailing axis of 3,
        which ingest merges per channel and does not demosaic).

    The default is the camera the dome has; ``SensorModel(noise=False)`` is a noise-free
    capture and ``SensorModel(noise=False, mosaic=False)`` a noise-free full-RGB one
    (docs/simulator-physics.md, "Error floors").
    """

    noise: bool = True
    mosaic: bool = True


#: The dome's camera: noisy Bayer frames.
CAMERA = SensorModel()


# --------------------------------------------------------------------------- mosaic


def _pattern_channels(pattern: str) -> np.ndarray:
    if pattern not in BAYER_PATTERNS:
        raise ValueError(f"unknown Bayer pattern {pattern!r}; choose one of {', '.join(BAYER_PATTERNS)}")
    return np.array([_CHANNEL[ch] for ch in pattern], dtype=np.int8).reshape(2, 2)


def bayer_channel_index(pattern: str, shape: tuple[int, int]) -> np.ndarray:
    """Colour filter of every raw pixel.

    Parameters
    ----------
    pattern : {'RGGB', 'BGGR', 'GRBG', 'GBRG'}
        The 2x2 top-left block, read row-major.
    shape : (2,) tuple of int
        ``(rows, cols)`` of the raw frame.

    Returns
    -------
    index : (rows, cols) ndarray of int8
        0 = R, 1 = G, 2 = B.
    """
    block = _pattern_channels(pattern)
    rows, cols = (int(v) for v in shape)
    return np.tile(block, ((rows + 1) // 2, (cols + 1) // 2))[:rows, :cols].copy()


def mosaic(rgb: np.ndarray, pattern: str) -> np.ndarray:
    """Keep each raw pixel's own colour channel.

    Parameters
    ----------
    rgb : (..., rows, cols, 3) ndarray
        Colour planes.
    pattern : {'RGGB', 'BGGR', 'GRBG', 'GBRG'}
        Bayer layout.

    Returns
    -------
    raw : (..., rows, cols) ndarray
        Same dtype as ``rgb``; ``raw[..., i, j] = rgb[..., i, j, ch(i, j)]``.
    """
    return _mosaic_scaled(np.asarray(rgb), pattern, None)


def _mosaic_scaled(rgb: np.ndarray, pattern: str, scale, dtype=None) -> np.ndarray:
    """mosaic(rgb) * scale[ch], with four strided copies (no gather)."""
    if rgb.ndim < 3 or rgb.shape[-1] != 3:
        raise ValueError(f"expected (..., rows, cols, 3) colour planes, got shape {rgb.shape}")
    block = _pattern_channels(pattern)
    out = np.empty(rgb.shape[:-1], dtype=dtype or rgb.dtype)
    for r0 in (0, 1):
        for c0 in (0, 1):
            ch = int(block[r0, c0])
            src = rgb[..., r0::2, c0::2, ch]
            if scale is None:
                out[..., r0::2, c0::2] = src
            else:
                np.multiply(src, scale[ch], out=out[..., r0::2, c0::2])
    return out


def apply_psf(radiance_rgb: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian point-spread function per colour plane.

    Parameters
    ----------
    radiance_rgb : (..., rows, cols, 3) ndarray
        Radiance planes.
    sigma_px : float
        Standard deviation in raw pixels; 0 returns the input unchanged.

    Returns
    -------
    blurred : (..., rows, cols, 3) ndarray
        Same dtype. Borders are mirrored (``mode='reflect'``), which keeps
        the frame's mean.
    """
    if sigma_px <= 0:
        return radiance_rgb
    sigma = [0.0] * radiance_rgb.ndim
    sigma[-3] = sigma[-2] = float(sigma_px)
    return ndimage.gaussian_filter(radiance_rgb, sigma=sigma, mode="reflect", truncate=4.0)


def signal_rate(radiance_rgb: np.ndarray, spec: SensorSpec, psf: bool = True, mosaic: bool = True) -> np.ndarray:
    """Photo-electron rate of every raw pixel.

    Parameters
    ----------
    radiance_rgb : (..., rows, cols, 3) ndarray
        Radiance in BTF units.
    spec : SensorSpec
        Sensor.
    psf : bool
        Apply the sensor's PSF (if ``spec.psf_sigma_px > 0``).
    mosaic : bool
        Bayer filters (the camera); ``False``: a full-RGB sensor (:class:`SensorModel`).

    Returns
    -------
    rate : (..., rows, cols) or, without ``mosaic``, (..., rows, cols, 3) ndarray of float64
        ``k_ch(p) * L_p,ch(p)`` in e-/s (every channel's ``k_ch L_p,ch`` without ``mosaic``).
    """
    rad = np.asarray(radiance_rgb)
    if psf and spec.psf_sigma_px > 0:
        rad = apply_psf(rad, spec.psf_sigma_px)
    if not mosaic:
        return rad * np.asarray(spec.sensitivity_rgb, dtype=np.float64)                  # eq. k L, per channel
    return _mosaic_scaled(rad, spec.bayer_pattern, np.asarray(spec.sensitivity_rgb), dtype=np.float64)  # eq. k L


# --------------------------------------------------------------------------- dark current


def dark_current_map(spec: SensorSpec, shape: tuple[int, int], rng: np.random.Generator,
                     *, sigma: float = 0.4, hot_fraction: float = 5e-4,
                     hot_factor: tuple[float, float] = (20.0, 200.0)) -> np.ndarray:
    """Per-pixel dark current (fixed-pattern noise) of one sensor.

    Parameters
    ----------
    spec : SensorSpec
        ``dark_current_e_per_s`` is the mean of the map.
    shape : (2,) tuple of int
        ``(rows, cols)``.
    rng : numpy.random.Generator
        Source of the pattern (one seed per physical camera).
    sigma : float
        Log-standard deviation of the lognormal spread.
    hot_fraction : float
        Fraction of hot pixels (at least one pixel when ``> 0``).
    hot_factor : (2,) tuple of float
        Hot pixels have ``hot_factor[0]..hot_factor[1]`` times the typical rate.

    Returns
    -------
    dark : (rows, cols) ndarray of float64
        e-/s; its mean equals ``spec.dark_current_e_per_s`` exactly.

    Notes
    -----
    .. math:: D_p \\propto \\exp(\\sigma z_p - \\sigma^2/2), \\quad z_p \\sim \\mathcal{N}(0, 1)

    times a uniform factor for the hot pixels, rescaled to the spec's mean.
    """
    rows, cols = (int(v) for v in shape)
    mean = float(spec.dark_current_e_per_s)
    dark = np.exp(sigma * rng.standard_normal((rows, cols)) - 0.5 * sigma**2)   # eq. lognormal, mean 1
    n_hot = max(1, int(round(hot_fraction * rows * cols))) if hot_fraction > 0 else 0
    if n_hot:
        hot = rng.choice(rows * cols, size=min(n_hot, rows * cols), replace=False)
        dark.flat[hot] *= rng.uniform(hot_factor[0], hot_factor[1], size=hot.size)
    if mean == 0:
        return np.zeros((rows, cols))
    return dark * (mean / dark.mean())


# --------------------------------------------------------------------------- exposure


def _readout(lam: np.ndarray, spec: SensorSpec, rng: np.random.Generator, out: np.ndarray) -> None:
    """Noisy DN of mean photo+dark electrons ``lam`` (1-D float64) into ``out`` (uint16)."""
    fw, sr = float(spec.full_well_e), float(spec.read_noise_e)
    z = rng.standard_normal(lam.shape)
    small = np.flatnonzero(lam < GAUSSIAN_PHOTON_THRESHOLD_E)
    e = np.sqrt(lam + sr * sr)
    e *= z
    e += lam                                            # eq. Gaussian photon + read noise (large lambda)
    if small.size:
        es = np.minimum(rng.poisson(lam[small]), fw).astype(np.float64)   # eq. Poisson, full-well clip
        if sr > 0:
            es += sr * z[small]                         # eq. read noise
        e[small] = es
    # The ADC range ends at the full well: e >= e_fw gives e/g + b >= white, so the
    # clip to the white level below is the readout clip (eq. min(e, e_fw)).
    e *= 1.0 / float(spec.gain_e_per_dn)
    e += float(spec.black_level)                        # eq. DN = e / g + b
    np.rint(e, out=e)
    np.clip(e, 0, spec.white_level, out=e)
    out[...] = e


def _dark_rate(spec: SensorSpec, dark_map, shape) -> np.ndarray | float:
    if dark_map is None:
        return float(spec.dark_current_e_per_s)
    dark = np.asarray(dark_map, dtype=np.float64)
    if dark.shape != tuple(shape):
        raise ValueError(f"dark_map has shape {dark.shape}, the frames {tuple(shape)}")
    return dark


def expose(radiance_rgb: np.ndarray, exposure_time, spec: SensorSpec, dark_map: np.ndarray | None,
           rng: np.random.Generator, psf: bool = True, model: SensorModel = CAMERA) -> np.ndarray:
    """Raw frames of a linear sensor exposed to a radiance image.

    Parameters
    ----------
    radiance_rgb : (..., rows, cols, 3) ndarray
        Radiance reaching each raw pixel, BTF units (float32 or float64).
    exposure_time : float or (...) array_like
        Seconds; broadcast against the leading dimensions of ``radiance_rgb``
        (e.g. radiance ``(n, 1, rows, cols, 3)`` with times ``(n, n_exp)``
        gives ``(n, n_exp, rows, cols)`` frames).
    spec : SensorSpec
        Sensor.
    dark_map : (rows, cols) ndarray or None
        Dark current per pixel, e-/s (:func:`dark_current_map`); ``None``
        uses the spec's mean everywhere.
    rng : numpy.random.Generator
        Noise source; the result is a deterministic function of its state.
    psf : bool
        Apply the Gaussian PSF when ``spec.psf_sigma_px > 0``.
    model : SensorModel
        The camera (noisy Bayer frames, default), a noise-free one or a full-RGB one.

    Returns
    -------
    raw : (*broadcast(lead, t.shape), rows, cols) ndarray of uint16
        Values in ``[0, spec.white_level]``. Without ``model.mosaic`` the frames have a trailing
        axis of 3 (R, G, B of every pixel); without ``model.noise`` they are :func:`expected_dn`
        exactly (float64, not rounded) and ``rng`` is not used.

    Notes
    -----
    Per pixel, with :math:`\\lambda = k L t + D t`,

    .. math::
        e = \\min(\\min(\\mathrm{Poisson}(\\lambda), e_{fw}) + \\mathcal{N}(0, \\sigma_r^2), e_{fw}),
        \\quad \\mathrm{DN} = \\mathrm{clip}(\\mathrm{round}(e / g + b), 0, W).

    For :math:`\\lambda \\ge` :data:`GAUSSIAN_PHOTON_THRESHOLD_E` the photon
    count plus read noise is drawn as :math:`\\mathcal{N}(\\lambda, \\lambda +
    \\sigma_r^2)` (same mean and variance, skewness
    :math:`\\lambda^{-1/2} \\le 0.1` neglected; several times faster). The frames are drawn one
    after the other in C order of the leading dimensions.
    """
    rad = np.asarray(radiance_rgb)
    if rad.ndim < 3 or rad.shape[-1] != 3:
        raise ValueError(f"radiance_rgb must be (..., rows, cols, 3), got shape {rad.shape}")
    if not np.all(np.isfinite(rad)) or rad.min(initial=0.0) < 0:
        raise ValueError("radiance_rgb must be finite and >= 0")
    t = np.asarray(exposure_time, dtype=np.float64)
    if not np.all(np.isfinite(t)) or np.any(t <= 0):
        raise ValueError(f"exposure times must be finite and > 0, got {t}")
    if not model.noise:
        return expected_dn(rad, t, spec, dark_map, psf, mosaic=model.mosaic)
    if psf and spec.psf_sigma_px > 0:
        rad = apply_psf(rad, spec.psf_sigma_px)
    dark = _dark_rate(spec, dark_map, rad.shape[-3:-1])
    if model.mosaic:
        rate = _mosaic_scaled(rad, spec.bayer_pattern, np.asarray(spec.sensitivity_rgb, dtype=np.float32),
                              dtype=np.float32)                # eq. k L, (..., rows, cols) e-/s
        shape = rad.shape[-3:-1]
    else:                                                      # every pixel measures R, G and B
        rate = (rad * np.asarray(spec.sensitivity_rgb, dtype=np.float32)).astype(np.float32, copy=False)
        shape = rad.shape[-3:]
        dark = np.asarray(dark)[..., None] if np.ndim(dark) else dark
    lead = np.broadcast_shapes(rate.shape[:-len(shape)], t.shape)
    rate_b = np.broadcast_to(rate, lead + shape)
    t_b = np.broadcast_to(t, lead)
    out = np.empty(lead + shape, dtype=np.uint16)
    lam = np.empty(shape, dtype=np.float64)
    for idx in np.ndindex(*lead):
        ti = float(t_b[idx])
        np.multiply(rate_b[idx], ti, out=lam)                  # eq. k L t
        lam += dark * ti                                       # eq. + D t
        _readout(lam.reshape(-1), spec, rng, out[idx].reshape(-1))
    return out


def expected_dn(radiance_rgb: np.ndarray, exposure_time, spec: SensorSpec,
                dark_map: np.ndarray | None = None, psf: bool = True, mosaic: bool = True) -> np.ndarray:
    """Noise-free mean raw value (the model of :func:`expose` without noise or rounding).

    Parameters
    ----------
    radiance_rgb : (..., rows, cols, 3) ndarray
        Radiance in BTF units.
    exposure_time : float or (...) array_like
        Seconds, broadcast as in :func:`expose`.
    spec : SensorSpec
        Sensor.
    dark_map : (rows, cols) ndarray or None
        Dark current, e-/s; ``None`` uses the spec's mean (pass zeros for the
        signal alone).
    psf : bool
        Apply the PSF.
    mosaic : bool
        Bayer filters; ``False``: a full-RGB sensor, frames with a trailing axis of 3.

    Returns
    -------
    dn : (*broadcast(lead, t.shape), rows, cols) ndarray of float64
        ``min(black + min(lambda, e_fw) / gain, white)`` (``(..., rows, cols, 3)`` without ``mosaic``).
    """
    rad = np.asarray(radiance_rgb)
    t = np.asarray(exposure_time, dtype=np.float64)
    rate = signal_rate(rad, spec, psf, mosaic)
    dark = _dark_rate(spec, dark_map, rad.shape[-3:-1])
    pixel_axes = 2 if mosaic else 3
    if not mosaic and np.ndim(dark):
        dark = np.asarray(dark)[..., None]
    tt = t.reshape(t.shape + (1,) * pixel_axes)
    lam = rate * tt + dark * tt                                                    # eq. lambda
    dn = spec.black_level + np.minimum(lam, spec.full_well_e) / spec.gain_e_per_dn  # eq. DN
    return np.minimum(dn, spec.white_level)


def dark_frames(spec: SensorSpec, dark_map: np.ndarray | None, exposure_times, shape: tuple[int, int],
                rng: np.random.Generator, model: SensorModel = CAMERA) -> np.ndarray:
    """Raw frames with the shutter closed (calibration dark frames).

    Parameters
    ----------
    spec : SensorSpec
        Sensor.
    dark_map : (rows, cols) ndarray or None
        Dark current, e-/s.
    exposure_times : (n_dark,) array_like
        Seconds.
    shape : (2,) tuple of int
        ``(rows, cols)``.
    rng : numpy.random.Generator
        Noise source.
    model : SensorModel
        Without ``model.noise`` the frames are their mean exactly (float64) and ``rng`` is not used.
        The dark current does not depend on the colour filter, so one dark frame serves a full-RGB
        sensor's three channels.

    Returns
    -------
    dark : (n_dark, rows, cols) ndarray of uint16
        Mean ``black + D t / gain``, read noise ``read_noise_e / gain`` DN.
    """
    times = np.asarray(exposure_times, dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(times)) or np.any(times <= 0):
        raise ValueError(f"dark exposure times must be finite and > 0, got {times}")
    shape = tuple(int(v) for v in shape)
    dark = np.broadcast_to(_dark_rate(spec, dark_map, shape), shape)
    if not model.noise:
        lam = dark[None] * times[:, None, None]                                  # eq. lambda = D t
        return np.minimum(spec.black_level + np.minimum(lam, spec.full_well_e) / spec.gain_e_per_dn,
                          spec.white_level)
    out = np.empty((times.size,) + shape, dtype=np.uint16)
    for k, tk in enumerate(times):
        _readout((dark * tk).reshape(-1), spec, rng, out[k].reshape(-1))     # eq. lambda = D t
    return out


# --------------------------------------------------------------------------- bracketing


class BracketReport(NamedTuple):
    """How :func:`choose_bracket` chose each bracket (arrays over the frames).

    Attributes
    ----------
    ratio : (n,) ndarray of float64
        Step between consecutive exposure times.
    ratio_needed : (n,) ndarray of float64
        Step that would bring the darkest masked pixel to ``lo`` of full scale
        (``inf`` for a frame without signal).
    capped : (n,) ndarray of bool
        ``ratio_needed > max_ratio``: the scene's dynamic range is too wide
        for the bracket; its darkest pixels stay below ``lo``.
    time_limited : (n,) ndarray of bool
        The longest exposure was cut to ``max_time_s`` (a very dark frame).
    dynamic_range : (n,) ndarray of float64
        Brightest / darkest positive signal rate in the mask.
    underexposed_fraction : (n,) ndarray of float64
        Masked pixels below ``WELL_EXPOSED[0]`` of full scale in every frame
        (noise-free), including pixels without any signal.
    """

    ratio: np.ndarray
    ratio_needed: np.ndarray
    capped: np.ndarray
    time_limited: np.ndarray
    dynamic_range: np.ndarray
    underexposed_fraction: np.ndarray


def _masked_rates(rad: np.ndarray, spec: SensorSpec, mask: np.ndarray | None, psf: bool) -> np.ndarray:
    """Photo-electron rates (e-/s) of the raw pixels that matter, ``(n, n_masked)`` for ``(n, rows, cols, 3)``
    radiance: all pixels without ``mask``, NaN at the unmasked ones of a per-frame (3-D) ``mask``."""
    n = rad.shape[0]
    if psf and spec.psf_sigma_px > 0:
        rad = apply_psf(rad, spec.psf_sigma_px)
    rate = _mosaic_scaled(rad, spec.bayer_pattern, np.asarray(spec.sensitivity_rgb, dtype=np.float32),
                          dtype=np.float32)                                # (n, rows, cols) e-/s
    if mask is None:
        return rate.reshape(n, -1)
    m = np.asarray(mask, dtype=bool)
    if m.ndim == 2:
        return rate[:, m]                                                  # (n, n_masked)
    m = np.broadcast_to(m, rate.shape)
    return np.where(m, rate, np.nan).reshape(n, -1)


def _rate_range(vals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Largest and smallest positive rate of each frame's ``(n, n_masked)`` rates, float64 (0 and inf if none)."""
    n = vals.shape[0]
    with np.errstate(invalid="ignore"):
        r_max = np.nanmax(np.where(vals > 0, vals, 0), axis=1, initial=0.0).astype(np.float64) \
            if vals.size else np.zeros(n)
        r_min = np.nanmin(np.where(vals > 0, vals, np.inf), axis=1, initial=np.inf).astype(np.float64) \
            if vals.size else np.full(n, np.inf)
    return r_max, r_min


def choose_bracket(radiance_rgb: np.ndarray, spec: SensorSpec, mask: np.ndarray | None = None, *,
                   hi: float = 0.8, lo: float = 0.05, min_ratio: float = 2.0, max_ratio: float | None = None,
                   max_time_s: float = 10.0, psf: bool = True, return_report: bool = False):
    """Exposure bracket an operator would choose for a frame.

    Parameters
    ----------
    radiance_rgb : (rows, cols, 3) or (n, rows, cols, 3) ndarray
        Radiance of one frame or a stack of frames.
    spec : SensorSpec
        Sensor; ``spec.n_exposures`` is the bracket length.
    mask : (rows, cols) or (n, rows, cols) ndarray of bool, optional
        Pixels that matter (e.g. :func:`btfcore.simulate.camera.sample_mask`);
        all pixels when omitted.
    hi : float
        Fraction of full scale the brightest masked pixel reaches in the
        shortest exposure.
    lo : float
        Fraction of full scale the darkest masked pixel should reach in the
        longest exposure.
    min_ratio : float
        Smallest step between consecutive exposures.
    max_ratio : float, optional
        Largest step; default ``WELL_EXPOSED[1] / WELL_EXPOSED[0]`` (90), the
        widest step that leaves no gap between consecutive frames' well-exposed
        ranges.
    max_time_s : float
        Longest exposure the operator accepts (also the longest exposure of a
        frame whose mask receives no light at all).
    psf : bool
        Judge the blurred image (as the sensor sees it).
    return_report : bool
        Also return a :class:`BracketReport`.

    Returns
    -------
    times : (n_exp,) or (n, n_exp) ndarray of float64
        Strictly increasing exposure times, seconds.
    report : BracketReport
        Only with ``return_report=True``.

    Notes
    -----
    Let :math:`r_{max}, r_{min}` be the largest and the smallest positive
    photo-electron rate (e-/s, :func:`signal_rate`) of the masked raw pixels,
    :math:`F = (W - b) g` the full scale in electrons, :math:`n` the bracket
    length and :math:`T` = ``max_time_s``. Then

    .. math::
        t_1 = h F / r_{max}, \\qquad
        \\rho^* = \\left(\\frac{l}{h} \\frac{r_{max}}{r_{min}}\\right)^{1/(n-1)}, \\qquad
        \\rho = \\min(\\max(\\rho^*, \\rho_{min}), \\rho_{max}), \\qquad
        t_k = t_1 \\rho^{k-1}.

    The shortest exposure never clips the brightest pixel; the longest brings
    the darkest one to :math:`l` of full scale. As long as
    :math:`\\rho \\le \\rho_{max} = u / v` with :math:`(v, u)` =
    :data:`WELL_EXPOSED`, every masked pixel with signal lies within
    :math:`[v, u]` of full scale in at least one frame (noise-free).

    Limits, in this order:

    * the dynamic range is too wide for the bracket (:math:`\\rho^* >
      \\rho_{max}`): the step is capped at :math:`\\rho_{max}` and the shortest
      exposure is kept, so highlights stay unclipped and the darkest pixels
      are recorded below :math:`v` (noisier, never lost to saturation);
      reported as ``capped``;
    * the longest exposure would exceed :math:`T`: the step shrinks to
      :math:`\\max(\\rho_{min}, (T/t_1)^{1/(n-1)})`, and if even that is too
      long, :math:`t_n = T` and :math:`t_k = T \\rho_{min}^{k-n}` (a frame too
      dark to fill the well); reported as ``time_limited``.

    Both leave some masked pixels under-exposed; ``underexposed_fraction``
    counts them. Dark current is not part of the rule (the operator judges
    the signal).
    """
    rad = np.asarray(radiance_rgb)
    single = rad.ndim == 3
    if single:
        rad = rad[None]
    if rad.ndim != 4 or rad.shape[-1] != 3:
        raise ValueError(f"radiance_rgb must be (rows, cols, 3) or (n, rows, cols, 3), got {np.shape(radiance_rgb)}")
    n_exp = int(spec.n_exposures)
    v, u = WELL_EXPOSED
    max_ratio = u / v if max_ratio is None else float(max_ratio)
    if not (0 < lo < hi <= 1) or min_ratio <= 1 or max_ratio < min_ratio or not max_time_s > 0:
        raise ValueError(f"need 0 < lo < hi <= 1, 1 < min_ratio <= max_ratio and max_time_s > 0, got lo={lo}, "
                         f"hi={hi}, min_ratio={min_ratio}, max_ratio={max_ratio}, max_time_s={max_time_s}")
    n = rad.shape[0]
    vals = _masked_rates(rad, spec, mask, psf)                             # (n, n_masked) e-/s
    r_max, r_min = _rate_range(vals)
    lit = np.isfinite(r_min) & (r_max > 0)
    full = (spec.white_level - spec.black_level) * spec.gain_e_per_dn      # eq. F = (W - b) g
    dyn = np.where(lit, r_max / np.where(lit, r_min, 1.0), np.inf)
    with np.errstate(divide="ignore"):
        t1 = np.where(lit, hi * full / np.where(lit, r_max, 1.0), np.inf)  # eq. t_1 = h F / r_max
    k = n_exp - 1
    need = (lo / hi * dyn) ** (1.0 / k) if k else np.ones(n)               # eq. rho*
    ratio = np.clip(need, min_ratio, max_ratio)                            # eq. rho
    if k:
        with np.errstate(divide="ignore", over="ignore"):
            too_long = t1 * ratio**k > max_time_s * (1 + 1e-12)
            ratio = np.where(too_long, np.maximum(min_ratio, (max_time_s / t1) ** (1.0 / k)), ratio)
    else:
        too_long = t1 > max_time_s
    t1 = np.minimum(t1, max_time_s / ratio**k)                             # eq. t_n <= T
    times = t1[:, None] * ratio[:, None] ** np.arange(n_exp)               # eq. t_k = t_1 rho^(k-1)
    if not return_report:
        return times[0] if single else times
    n_mask = np.maximum(np.sum(np.isfinite(vals), axis=1), 1)
    with np.errstate(invalid="ignore"):
        under = np.sum(vals * (times[:, -1:] / full) < v, axis=1) / n_mask  # brightest frame of each pixel
    report = BracketReport(ratio=ratio, ratio_needed=need, capped=need > max_ratio, time_limited=too_long,
                           dynamic_range=dyn, underexposed_fraction=under.astype(np.float64))
    if single:
        report = BracketReport(*(np.asarray(a)[0] for a in report))
    return (times[0] if single else times), report
