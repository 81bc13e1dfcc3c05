"""A camera dome that is not ideal: LED drift, one shutter per multiplexed capture, camera gain,
registration error and hot pixels (docs/simulator-physics.md, "A dome that is not ideal").

The virtual dome is ideal by default: every LED emits exactly its calibrated intensity in every
shot, every image lands on the same pixels, each illumination pattern gets its own exposure and the
sensor has no defect that its dark frames do not show. Real domes have all four problems. This
module holds the effects as pure numerics on arrays, shared by the raw-image simulator
(:mod:`tasks.simulate`) and the acquisition evaluation's measurements in BTF space
(:mod:`btfcore.acquisition.nonideal_measurement`):

* **LED drift** (:func:`led_drift_factors`): each LED's intensity in each *shot* (one illumination
  pattern at one turntable position, seen by every camera at once) is its nominal intensity times
  an independent lognormal factor of mean 1 and log-standard deviation ``led_drift``.
* **One shutter per multiplexed capture** (:func:`metered_maximum`): all S-matrix patterns of a
  view share one exposure, metered on the median pattern (the brightest value of the median
  pattern image sits at the operator's fill level); brighter patterns saturate where they exceed
  the full scale, darker ones are under-exposed. VMV paper §5.1: "with multiplexed illumination,
  only a single exposure step was needed" (leather, wood; two for cloth).
* **Camera gain** (:func:`gain_factor`, :func:`full_scale_at_gain`, :func:`sensor_at_gain`): single-
  light shots at ``single_gain_db`` and multiplexed ones at ``multiplex_gain_db`` (VMV §5.1: 10 dB
  and 0 dB). A gain of ``G`` dB amplifies the charge by ``10**(G/20)`` before the ADC, so the ADC's
  range ends at ``full_well / 10**(G/20)`` electrons: fewer electrons per image, more photon noise.
* **Registration error** (:func:`registration_shifts`, :func:`shift_images`): every image is shifted
  by a sub-pixel offset ``(d_row, d_col)`` drawn from :math:`\\mathcal N(0, \\sigma^2)` per axis,
  clipped to :data:`MAX_SHIFT_PX` (bilinear resampling, edges replicated).
* **Hot pixels** (:func:`hot_pixel_mask`): a fixed fraction of each camera's pixels reads the
  sensor's white level in every frame of a capture, and the calibration's dark frames (taken
  before they went bad) do not show them.

All draws come from generators the caller seeds; with :data:`IDEAL` nothing is drawn and every
function is the identity. Pure numpy / scipy: no I/O.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage

from btfcore.dome import SensorSpec

__all__ = ["IDEAL", "MAX_SHIFT_PX", "PRESETS", "DomeNonIdeality", "full_scale_at_gain", "gain_factor",
           "hot_pixel_mask", "led_drift_factors", "metered_maximum", "parse_non_ideal", "registration_shifts",
           "sensor_at_gain", "shift_images"]

#: Largest registration offset along an axis, pixels: a bilinear shift then reads only the pixel's
#: neighbours, so the evaluation's bands of texture rows need a halo of one row.
MAX_SHIFT_PX = 1.0


@dataclass(frozen=True)
class DomeNonIdeality:
    """Which non-idealities a simulated dome has, and how strong they are (all off by default).

    Parameters
    ----------
    led_drift : float
        Log-standard deviation of each LED's intensity per shot (relative standard deviation
        :math:`\\sqrt{e^{\\sigma^2} - 1} \\approx \\sigma` for small values), >= 0.
    multiplex_single_exposure : bool
        The S-matrix patterns of a view share one exposure, metered on the median pattern
        (:func:`metered_maximum`); ``False``: every pattern gets its own.
    single_gain_db, multiplex_gain_db : float
        Camera gain of the single-light and of the multiplexed shots, dB, in [0, 40].
    registration_sd_px : float
        Standard deviation of each image's sub-pixel offset per axis, camera pixels, in [0, 1].
    hot_pixel_fraction : float
        Fraction of each camera's pixels stuck at the white level, in [0, 0.01].
    """

    led_drift: float = 0.0
    multiplex_single_exposure: bool = False
    single_gain_db: float = 0.0
    multiplex_gain_db: float = 0.0
    registration_sd_px: float = 0.0
    hot_pixel_fraction: float = 0.0

    def __post_init__(self) -> None:
        problems = []
        for name, lo, hi in (("led_drift", 0.0, 0.5), ("single_gain_db", 0.0, 40.0), ("multiplex_gain_db", 0.0, 40.0),
                             ("registration_sd_px", 0.0, MAX_SHIFT_PX), ("hot_pixel_fraction", 0.0, 0.01)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not lo <= float(value) <= hi:
                problems.append(f"{name} must be a number in [{lo:g}, {hi:g}], got {value!r}")
        if not isinstance(self.multiplex_single_exposure, bool):
            problems.append(f"multiplex_single_exposure must be true or false, got {self.multiplex_single_exposure!r}")
        if problems:
            raise ValueError("invalid dome non-ideality: " + "; ".join(problems))

    @property
    def is_ideal(self) -> bool:
        """Whether no effect is on (the simulator's and the evaluation's outputs are those of the ideal dome)."""
        return self == IDEAL

    def to_json(self) -> dict[str, Any]:
        """Plain-JSON dict of the fields."""
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> DomeNonIdeality:
        """The inverse of :meth:`to_json` (unknown keys raise ``ValueError``)."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"unknown dome non-ideality {', '.join(unknown)}; choose from {', '.join(sorted(names))}")
        return cls(**d)


#: The ideal dome (the default everywhere).
IDEAL = DomeNonIdeality()

#: Named presets of ``btf simulate --non-ideal`` and ``btf evaluate acquisition --non-ideal``.
#: "realistic": VMV §5.1's gains (10 dB single-light, 0 dB multiplexed) and single exposure step of
#: the multiplexed captures; 1 % LED drift per shot, 0.1 px registration error and 1e-4 hot pixels
#: are this project's choice of typical values (docs/simulator-physics.md, "A dome that is not ideal").
PRESETS: dict[str, DomeNonIdeality] = {
    "ideal": IDEAL,
    "realistic": DomeNonIdeality(led_drift=0.01, multiplex_single_exposure=True, single_gain_db=10.0,
                                 multiplex_gain_db=0.0, registration_sd_px=0.1, hot_pixel_fraction=1e-4),
}


def parse_non_ideal(text: str) -> DomeNonIdeality:
    """A :class:`DomeNonIdeality` from ``PRESET[,FIELD=VALUE...]`` or ``FIELD=VALUE[,...]``.

    Examples: ``realistic``, ``realistic,led_drift=0.02``, ``registration_sd_px=0.3,hot_pixel_fraction=0``.
    A field given alone starts from the ideal dome.

    Raises
    ------
    ValueError
        For an unknown preset or field or a value out of range (the message lists the choices).
    """
    parts = [p.strip() for p in str(text).split(",") if p.strip()]
    if not parts:
        raise ValueError(f"give a preset ({', '.join(PRESETS)}) and/or FIELD=VALUE pairs")
    base, overrides = IDEAL, {}
    names = {f.name: f.type for f in dataclasses.fields(DomeNonIdeality)}
    for i, part in enumerate(parts):
        if "=" not in part:
            if i or part not in PRESETS:
                raise ValueError(f"{part!r} is no preset; give one of {', '.join(PRESETS)} first, then FIELD=VALUE "
                                 f"pairs with FIELD one of {', '.join(names)}")
            base = PRESETS[part]
            continue
        name, value = (s.strip() for s in part.split("=", 1))
        if name not in names:
            raise ValueError(f"unknown dome non-ideality {name!r}; choose from {', '.join(names)}")
        if name == "multiplex_single_exposure":
            if value.lower() not in ("true", "false", "1", "0", "yes", "no", "on", "off"):
                raise ValueError(f"{name} must be true or false, got {value!r}")
            overrides[name] = value.lower() in ("true", "1", "yes", "on")
        else:
            try:
                overrides[name] = float(value)
            except ValueError:
                raise ValueError(f"{name} must be a number, got {value!r}") from None
    return dataclasses.replace(base, **overrides)


# --------------------------------------------------------------------------- LED drift


def led_drift_factors(sd: float, rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Each LED's intensity in each shot relative to its nominal intensity.

    Parameters
    ----------
    sd : float
        Log-standard deviation (:attr:`DomeNonIdeality.led_drift`); 0 gives ones (no draw).
    rng : numpy.random.Generator
    shape : tuple of int
        E.g. ``(n_shots, n_leds)``.

    Returns
    -------
    factors : ndarray of float64, ``shape``
        :math:`\\exp(\\sigma z - \\sigma^2 / 2)`, :math:`z \\sim \\mathcal N(0, 1)`: lognormal, mean 1.
    """
    if sd <= 0:
        return np.ones(shape)
    return np.exp(sd * rng.standard_normal(shape) - 0.5 * sd * sd)          # eq. lognormal, mean 1


# --------------------------------------------------------------------------- exposure and gain


def metered_maximum(pattern_maxima: np.ndarray, axis: int = -1) -> np.ndarray:
    """The brightest value the single exposure of a multiplexed capture is metered on.

    Parameters
    ----------
    pattern_maxima : ndarray
        Brightest noise-free value (or photo-electron rate) of every pattern image; ``axis`` runs
        over the patterns of one capture.
    axis : int

    Returns
    -------
    metered : ndarray
        The median over ``axis`` (kept as a length-1 axis, so it broadcasts against the input): the
        exposure puts the median pattern's brightest value at the operator's fill level, so a
        pattern brighter than ``1 / fill`` times that saturates at its brightest pixels.
    """
    return np.median(np.asarray(pattern_maxima, dtype=np.float64), axis=axis, keepdims=True)


def gain_factor(gain_db: float) -> float:
    """Linear amplification of a camera gain in dB, :math:`10^{G/20}` (10 dB: 3.16)."""
    return float(10.0 ** (float(gain_db) / 20.0))


def full_scale_at_gain(full_well_e: float, gain_db: float) -> float:
    """Electrons at which the ADC saturates at ``gain_db``: ``full_well_e / gain_factor(gain_db)``."""
    return float(full_well_e) / gain_factor(gain_db)


def sensor_at_gain(spec: SensorSpec, gain_db: float) -> SensorSpec:
    """The sensor as its frames are read at ``gain_db``: fewer electrons per DN, the same white level.

    ``gain_e_per_dn`` is divided by :func:`gain_factor`; ``full_well_e`` becomes the electrons at
    the (unchanged) white level, so :attr:`SensorSpec.white_level` and the raw range stay those of
    the store. At 0 dB the spec itself is returned. A frame exposed for ``t`` seconds at this gain
    has the DN of a 0 dB frame of ``t * gain_factor`` seconds (without its noise): the simulator
    records that product as the frame's exposure time, the linear scale the HDR merge divides by.
    """
    if gain_db == 0:
        return spec
    g = spec.gain_e_per_dn / gain_factor(gain_db)
    span = spec.white_level - int(spec.black_level)
    return spec.replace(gain_e_per_dn=g, full_well_e=(span + 0.5) * g)  # floor(fw / g) = span: same white level


# --------------------------------------------------------------------------- registration


def registration_shifts(sd_px: float, rng: np.random.Generator, n_images: int) -> np.ndarray:
    """Sub-pixel offset of every image.

    Returns
    -------
    shifts : (n_images, 2) ndarray of float64
        ``(d_row, d_col)`` in pixels, :math:`\\mathcal N(0, \\sigma^2)` per axis clipped to
        ``[-MAX_SHIFT_PX, MAX_SHIFT_PX]``; zeros (no draw) when ``sd_px`` is 0.
    """
    if sd_px <= 0:
        return np.zeros((int(n_images), 2))
    return np.clip(sd_px * rng.standard_normal((int(n_images), 2)), -MAX_SHIFT_PX, MAX_SHIFT_PX)


def shift_images(images: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """Images displaced by sub-pixel offsets (bilinear, edges replicated).

    Parameters
    ----------
    images : (n, rows, cols, ...) ndarray
        One image per leading index; trailing axes (colour) are not shifted.
    shifts : (n, 2) array_like
        ``(d_row, d_col)`` of each image, pixels, ``|d| <= MAX_SHIFT_PX``; the content moves by
        ``+d``: ``out[r, c] = in(r - d_row, c - d_col)``.

    Returns
    -------
    shifted : ndarray, same shape and dtype
        An image whose offset is zero is copied unchanged. Output row ``r`` reads input rows
        ``r - 1 .. r + 1`` only, so shifting rows ``a - 1 : b + 1`` and keeping ``a : b`` equals
        shifting the whole image (the evaluation's bands rely on it).
    """
    x = np.asarray(images)
    d = np.asarray(shifts, dtype=np.float64)
    if x.ndim < 3 or d.shape != (x.shape[0], 2):
        raise ValueError(f"images must be (n, rows, cols, ...) with shifts (n, 2), got {x.shape} and {d.shape}")
    if np.any(np.abs(d) > MAX_SHIFT_PX + 1e-12):
        raise ValueError(f"registration offsets must lie within +-{MAX_SHIFT_PX} px")
    out = np.array(x, copy=True)
    tail = (0.0,) * (x.ndim - 3)
    for i in np.flatnonzero(np.any(d != 0, axis=1)):
        out[i] = ndimage.shift(x[i], (d[i, 0], d[i, 1], *tail), order=1, mode="nearest", prefilter=False)
    return out


# --------------------------------------------------------------------------- hot pixels


def hot_pixel_mask(fraction: float, rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Pixels stuck at the white level (fixed per camera).

    Returns
    -------
    mask : ndarray of bool, ``shape``
        ``round(fraction * size)`` pixels (at least one when ``fraction > 0``) chosen uniformly
        without replacement; all False (no draw) when ``fraction`` is 0.
    """
    size = int(math.prod(shape))
    mask = np.zeros(size, dtype=bool)
    if fraction > 0 and size:
        mask[rng.choice(size, size=min(size, max(1, int(round(fraction * size)))), replace=False)] = True
    return mask.reshape(shape)
