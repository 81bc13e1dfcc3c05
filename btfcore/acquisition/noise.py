"""A sensor-like measurement-noise model for simulated acquisitions in BTF space.

The acquisition evaluation (stage 12, ``docs/evaluation.md``) simulates
sparse and multiplexed measurements directly from a ground-truth BTF instead
of through the raw-image simulator. Each measured image (one camera, one
illumination pattern, all texels and channels of the texture) is one exposure:

1. **Exposure.** The operator sets the shutter so that the brightest value of
   the image sits at ``fill`` of the sensor's full well (an ideal auto exposure:
   the longest unsaturated shot of a bracket). The image's gain is then
   :math:`g = \\mathrm{fill} \\cdot \\mathrm{FW} / \\max(x)` electrons per unit
   radiance. A multiplexed pattern with ``m`` LEDs on is about ``m`` times as
   bright, so it gets a ``m`` times shorter exposure and the same electron
   count at its brightest texel.
2. **Photon (shot) noise.** The collected charge is Poisson with mean
   :math:`g x` electrons.
3. **Read noise.** Gaussian, standard deviation ``read_noise_e`` electrons.
4. **Full well.** The charge is clipped at ``full_well_e`` (only reached by
   noise above ``fill``).
5. The value reported is the charge divided by :math:`g` (radiance units), so
   the measurement is unbiased: mean :math:`x` and variance
   :math:`x / g + \\sigma_r^2 / g^2` (ignoring the clip).

Pure numerics: no I/O, seeds given by the caller.

References
----------
.. [1] The thesis, VMV paper §3.2 (Illumination multiplexing): photon noise
   "strongly counteracts" the multiplexing advantage [HS79, SNB07].
.. [2] Y. Y. Schechner, S. K. Nayar and P. N. Belhumeur, "Multiplexing for optimal
   lighting", IEEE TPAMI 29(8), 2007 (photon + read noise of multiplexed images).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["SensorNoise", "bracket_gain", "exposure_gain", "expose", "noise_moments"]


@dataclass(frozen=True)
class SensorNoise:
    """Parameters of the measurement-noise model.

    Parameters
    ----------
    full_well_e : float
        Full-well capacity, electrons (> 0).
    read_noise_e : float
        Read-noise standard deviation, electrons (>= 0).
    fill : float
        Fraction of the full well the brightest value of each image is exposed
        to, in (0, 1].
    """

    full_well_e: float = 5500.0
    read_noise_e: float = 3.0
    fill: float = 0.8

    def __post_init__(self) -> None:
        if not (np.isfinite(self.full_well_e) and self.full_well_e > 0):
            raise ValueError(f"SensorNoise.full_well_e must be > 0 electrons, got {self.full_well_e}")
        if not (np.isfinite(self.read_noise_e) and self.read_noise_e >= 0):
            raise ValueError(f"SensorNoise.read_noise_e must be >= 0 electrons, got {self.read_noise_e}")
        if not (0 < self.fill <= 1):
            raise ValueError(f"SensorNoise.fill must lie in (0, 1], got {self.fill}")


def exposure_gain(image_max: np.ndarray, noise: SensorNoise) -> np.ndarray:
    """Electrons per unit radiance of each image, from its brightest value.

    Parameters
    ----------
    image_max : (n_images,) array_like
        Brightest (noise-free) value of each image, > 0.
    noise : SensorNoise

    Returns
    -------
    gain : (n_images,) ndarray of float64
        :math:`g_i = \\mathrm{fill} \\cdot \\mathrm{FW} / \\max_i`.

    Raises
    ------
    ValueError
        For a non-positive or non-finite maximum (names the image index): an
        all-black image cannot be exposed; drop it from the measurement.
    """
    m = np.asarray(image_max, dtype=np.float64)
    bad = np.flatnonzero(~(np.isfinite(m) & (m > 0)))
    if bad.size:
        i = int(bad[0])
        raise ValueError(f"image {i} has brightest value {float(m.ravel()[i])!r}; an image must have a positive, finite "
                         "maximum to be exposed (remove black images from the measurement)")
    return noise.fill * noise.full_well_e / m                                # eq. g = fill FW / max


def bracket_gain(image_max: np.ndarray, exposure_times: np.ndarray, saturation_dn: float,
                 e_per_dn: float) -> np.ndarray:
    """Electrons per unit of each HDR-merged image (DN/s) from the bracket it was captured with.

    :func:`exposure_gain` assumes an ideal auto exposure that fills the well to a fraction at the
    image's brightest value; a real capture read its brightest pixel from the longest exposure of its
    bracket that did not saturate there (the HDR merge takes each pixel from its unsaturated frames,
    docs/hdr.md), so that frame's electrons per DN/s are the image's gain. Darker pixels may come from
    longer frames, with less relative noise than this gain gives them: the model errs on the safe side.

    Parameters
    ----------
    image_max : (n_images,) array_like
        Brightest value of each image in DN/s, > 0.
    exposure_times : (n_images, n_exp) array_like
        Exposure times of each image's bracket, seconds; 0 marks a frame not taken.
    saturation_dn : float
        DN above the black level at which a frame saturates (white level minus black level).
    e_per_dn : float
        Electrons per DN.

    Returns
    -------
    gain : (n_images,) ndarray of float64
        :math:`g_i = t^*_i` ``e_per_dn``, :math:`t^*_i` the longest exposure at which the image's brightest
        value stays within ``saturation_dn``; the shortest one where every frame saturates there.

    Raises
    ------
    ValueError
        For a non-positive maximum or an image without any exposure time (names the image).
    """
    m = np.asarray(image_max, dtype=np.float64)
    t = np.asarray(exposure_times, dtype=np.float64).reshape(len(m), -1)
    taken = t > 0
    bad = np.flatnonzero(~(np.isfinite(m) & (m > 0)) | ~taken.any(axis=1))
    if bad.size:
        i = int(bad[0])
        raise ValueError(f"image {i}: brightest value {float(m[i])!r}, exposure times {t[i].tolist()}; an image needs "
                         "a positive brightest value and at least one exposure time")
    fits = taken & (m[:, None] * t <= saturation_dn)
    longest = np.where(fits, t, 0.0).max(axis=1)
    shortest = np.where(taken, t, np.inf).min(axis=1)
    return np.where(longest > 0, longest, shortest) * float(e_per_dn)          # eq. g = t* e/DN


def expose(signal: np.ndarray, gain: np.ndarray, noise: SensorNoise, rng: np.random.Generator,
           out_dtype: np.dtype = np.float32) -> np.ndarray:
    """A noisy measurement of ``signal`` (rows = images) in radiance units.

    Parameters
    ----------
    signal : (n_images, ...) array_like
        Noise-free radiance, >= 0 (negative values are clipped to 0).
    gain : (n_images,) array_like
        Electrons per unit radiance of each image (:func:`exposure_gain`).
    noise : SensorNoise
    rng : numpy.random.Generator
    out_dtype : dtype

    Returns
    -------
    measured : (n_images, ...) ndarray
        :math:`\\min(\\mathrm{Poisson}(g x) + \\mathcal N(0, \\sigma_r^2), \\mathrm{FW}) / g`.
    """
    x = np.maximum(np.asarray(signal, dtype=np.float64), 0.0)
    g = np.asarray(gain, dtype=np.float64).reshape((-1,) + (1,) * (x.ndim - 1))
    if g.shape[0] != x.shape[0]:
        raise ValueError(f"gain has {g.shape[0]} entries but signal has {x.shape[0]} images")
    electrons = rng.poisson(x * g).astype(np.float64)                      # photon noise
    if noise.read_noise_e > 0:
        electrons += rng.normal(0.0, noise.read_noise_e, size=x.shape)    # read noise
    np.minimum(electrons, noise.full_well_e, out=electrons)               # full well
    return (electrons / g).astype(out_dtype)


def noise_moments(signal: np.ndarray, gain: np.ndarray, noise: SensorNoise) -> tuple[np.ndarray, np.ndarray]:
    """Mean and variance of :func:`expose` (without the full-well clip).

    Returns
    -------
    mean, variance : ndarray
        :math:`x` and :math:`x / g + \\sigma_r^2 / g^2`.
    """
    x = np.maximum(np.asarray(signal, dtype=np.float64), 0.0)
    g = np.asarray(gain, dtype=np.float64).reshape((-1,) + (1,) * (x.ndim - 1))
    return x, x / g + noise.read_noise_e ** 2 / g ** 2
