"""The acquisition evaluation's measurements under a dome that is not ideal (docs/evaluation.md,
"Claims under a dome that is not ideal").

:mod:`btfcore.acquisition.band_evaluation` measures a band of texture rows of the noise-free truth
as an ideal dome would: single-light images and S-matrix patterns formed from the nominal LED
intensities, each image exposed to its own fill level (:mod:`btfcore.acquisition.noise`). This
module applies the effects of :class:`btfcore.simulate.nonideal.DomeNonIdeality` to the same
measurements, with the simulator's functions, in BTF space:

* **LED drift**: a single-light shot (turntable position, LED) and a multiplexed shot (turntable
  position, pattern) light each LED with its own factor, shared by the cameras that shoot at once;
  demultiplexing still assumes the nominal patterns;
* **one shutter per multiplexed capture** and **camera gain**: the view's patterns share the gain
  metered on the median pattern (:func:`nonideal_gains`); single-light images are read at
  ``single_gain_db``, multiplexed ones at ``multiplex_gain_db`` (:func:`noises_at_gains`); the full-
  well clip of :func:`btfcore.acquisition.noise.expose` is the saturation;
* **registration error**: every image is shifted by its own offset, camera pixels converted to
  texels per view (``texels_per_px``); a band reads one row of halo on each side
  (:func:`registration_halo`), so bands measure every row alike;
* **a strategy's own patterns** (issue 20's designed patterns, the subsampled S-matrix rows): their
  shots drift and are shifted like the S-matrix's, with their own draws (:meth:`DomeDraws.for_patterns`),
  and are exposed like them (:func:`multiplexed_gains`, :func:`nonideal_patterns`);
* **hot pixels**: a stuck pixel is diluted over the texel it falls in: a fraction
  ``min(1, f / a)`` of each view's texels, with ``a = texels_per_px**2`` the texel's share of one
  pixel, reads ``(1 - a) x + a * FW / g`` in every image of the view (``FW / g``: the image's
  saturated value).

The effects' draws (:func:`draw_effects`) are whole arrays seeded per held-out material (hot
pixels per dome), so every band sees the same ones. Pure numerics, no I/O.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from btfcore.acquisition.band_evaluation import Gains, Measured, Moments, _expose_rows, demultiplex_views
from btfcore.acquisition.noise import SensorNoise, exposure_gain
from btfcore.acquisition.strategies import Geometry
from btfcore.simulate.nonideal import (
    DomeNonIdeality,
    full_scale_at_gain,
    hot_pixel_mask,
    led_drift_factors,
    metered_maximum,
    registration_shifts,
    shift_images,
)

__all__ = ["DomeDraws", "draw_effects", "measure_band_nonideal", "multiplexed_gains", "nonideal_gains",
           "nonideal_moments", "nonideal_multiplexed", "nonideal_patterns", "nonideal_single", "noises_at_gains",
           "registration_halo"]

#: Seed word of the hot pixels: a property of the dome's cameras, the same for every material.
HOT_PIXEL_SEED = 20151275


@dataclass(frozen=True)
class DomeDraws:
    """The non-ideal dome's draws for one held-out material's acquisition.

    Attributes
    ----------
    single_drift : (n_turn, n_leds) ndarray
        LED factor of each single-light shot.
    mux_drift : (n_turn, n_p, n_leds) ndarray
        LED factors of each multiplexed shot.
    single_shift : (n_lv, 2) ndarray
        Offset of each single-light image, texels.
    mux_shift : (n_views * n_p, 2) ndarray
        Offset of each multiplexed image, texels.
    hot : (n_views, height, width) ndarray of bool
        Texels holding a hot pixel.
    hot_share : (n_views,) ndarray
        Share ``a`` of a hot texel's value that is the stuck pixel.
    dome : DomeNonIdeality
        The dome they were drawn for.
    texels_per_px : (n_views,) ndarray
        Texels per camera pixel of each view.
    seed : tuple of int
        The material's seed words.
    """

    single_drift: np.ndarray
    mux_drift: np.ndarray
    single_shift: np.ndarray
    mux_shift: np.ndarray
    hot: np.ndarray
    hot_share: np.ndarray
    dome: DomeNonIdeality
    texels_per_px: np.ndarray
    seed: tuple[int, ...]

    def for_patterns(self, n_patterns: int, word: int) -> DomeDraws:
        """The draws of another set of ``n_patterns`` multiplexed shots per view (a strategy's own
        patterns, :func:`nonideal_patterns`): their LED factors and offsets from ``seed + [4, word]``,
        the single-light draws and the cameras' hot pixels unchanged."""
        n_turn, _, n_leds = self.mux_drift.shape
        n_views = len(self.texels_per_px)
        rng = np.random.default_rng([*self.seed, 4, int(word)])
        drift = led_drift_factors(self.dome.led_drift, rng, (n_turn, int(n_patterns), n_leds))
        shift = registration_shifts(self.dome.registration_sd_px, rng, n_views * int(n_patterns))
        return replace(self, mux_drift=drift, mux_shift=shift * np.repeat(self.texels_per_px, n_patterns)[:, None])


def draw_effects(dome: DomeNonIdeality, geometry: Geometry, n_patterns: int, texels_per_px: np.ndarray,
                 seed: Sequence[int]) -> DomeDraws:
    """Draw every effect of ``dome`` for one acquisition.

    Parameters
    ----------
    dome : DomeNonIdeality
    geometry : Geometry
    n_patterns : int
        S-matrix patterns per view.
    texels_per_px : (n_views,) array_like
        Texels per camera pixel of each view (the rectification's scale).
    seed : sequence of int
        The material's seed words: drift from ``seed + [2]``, offsets from ``seed + [3]``; the hot
        pixels from ``[seed[0], HOT_PIXEL_SEED]`` (the dome's, shared by its materials).
    """
    n_views, n_p = geometry.n_views, int(n_patterns)
    scale = np.asarray(texels_per_px, dtype=np.float64).reshape(n_views)
    rng = np.random.default_rng([*seed, 2])
    single_drift = led_drift_factors(dome.led_drift, rng, (geometry.n_turn, geometry.n_leds))
    mux_drift = led_drift_factors(dome.led_drift, rng, (geometry.n_turn, n_p, geometry.n_leds))
    rng = np.random.default_rng([*seed, 3])
    single_shift = registration_shifts(dome.registration_sd_px, rng, geometry.n_lv)
    mux_shift = registration_shifts(dome.registration_sd_px, rng, n_views * n_p)
    single_shift = single_shift * np.repeat(scale, geometry.n_leds)[:, None]           # px -> texels
    mux_shift = mux_shift * np.repeat(scale, n_p)[:, None]
    share = np.minimum(scale ** 2, 1.0)                                                  # eq. a = texel's share
    hot = np.stack([hot_pixel_mask(min(1.0, dome.hot_pixel_fraction / share[v]) if dome.hot_pixel_fraction else 0.0,
                                   np.random.default_rng([int(seed[0]), HOT_PIXEL_SEED, v]),
                                   (geometry.height, geometry.width)) for v in range(n_views)])
    return DomeDraws(single_drift, mux_drift, single_shift, mux_shift, hot, share, dome, scale,
                     tuple(int(x) for x in seed))


def noises_at_gains(noise: SensorNoise, dome: DomeNonIdeality) -> tuple[SensorNoise, SensorNoise]:
    """The noise models of the single-light and of the multiplexed images at their camera gains."""
    return (replace(noise, full_well_e=full_scale_at_gain(noise.full_well_e, dome.single_gain_db)),
            replace(noise, full_well_e=full_scale_at_gain(noise.full_well_e, dome.multiplex_gain_db)))


def nonideal_gains(maxima: Gains, noises: tuple[SensorNoise, SensorNoise], dome: DomeNonIdeality,
                   n_views: int) -> Gains:
    """Exposure gains (electrons per unit radiance) of the single-light and the multiplexed images.

    Parameters
    ----------
    maxima : ((n_lv,), (n_views * n_p,)) ndarrays
        Brightest noise-free value of every image (:func:`~btfcore.acquisition.band_evaluation.image_maxima`).

    Returns
    -------
    gains : ((n_lv,), (n_views * n_p,)) ndarrays
        :func:`~btfcore.acquisition.noise.exposure_gain` of each image; with
        ``multiplex_single_exposure`` every pattern of a view gets the gain metered on the view's
        median pattern (:func:`btfcore.simulate.nonideal.metered_maximum`).
    """
    return exposure_gain(maxima[0], noises[0]), multiplexed_gains(maxima[1], noises[1], dome, n_views)


def multiplexed_gains(maxima: np.ndarray, noise: SensorNoise, dome: DomeNonIdeality, n_views: int) -> np.ndarray:
    """Exposure gains ``(n_views * m,)`` of multiplexed images (``m`` patterns per view, view-major) from
    their brightest values: each its own (auto exposure), or with ``multiplex_single_exposure`` the
    gain metered on the view's median pattern (:func:`btfcore.simulate.nonideal.metered_maximum`);
    ``noise`` at the multiplexed images' camera gain (:func:`noises_at_gains`)."""
    mux = np.asarray(maxima, dtype=np.float64)
    if dome.multiplex_single_exposure:
        per_view = mux.reshape(int(n_views), -1)
        mux = np.broadcast_to(metered_maximum(per_view, axis=1), per_view.shape).reshape(-1)
    return exposure_gain(mux, noise)


def registration_halo(r0: int, r1: int, height: int) -> slice:
    """Texture rows a band ``r0:r1`` of shifted images reads: one more on each side (clipped)."""
    return slice(max(0, r0 - 1), min(height, r1 + 1))


def _crop_shifted(images: np.ndarray, shifts: np.ndarray, e0: int, r0: int, r1: int) -> np.ndarray:
    return shift_images(images, shifts)[:, r0 - e0:r1 - e0] if np.any(shifts) else images[:, r0 - e0:r1 - e0]


def nonideal_single(truth_ext: np.ndarray, e0: int, r0: int, r1: int, geometry: Geometry,
                    draws: DomeDraws) -> np.ndarray:
    """Noise-free single-light images of texture rows r0:r1 as the non-ideal dome forms them.

    Parameters
    ----------
    truth_ext : (n_lv, rows, w, 3) ndarray
        Truth of texture rows ``e0 : e0 + rows``, covering :func:`registration_halo` of r0:r1.

    Returns
    -------
    signal : (n_lv, r1 - r0, w, 3) ndarray of float32
        Each image times its shot's LED factor, shifted by its offset.
    """
    drift = np.repeat(draws.single_drift[:, None, :], geometry.n_cam, axis=1).reshape(-1)   # (n_lv,) (t, c, l)
    x = truth_ext * drift.astype(np.float32)[:, None, None, None]
    return _crop_shifted(x, draws.single_shift, e0, r0, r1)


def nonideal_multiplexed(truth_ext: np.ndarray, e0: int, r0: int, r1: int, patterns: np.ndarray,
                         geometry: Geometry, draws: DomeDraws) -> np.ndarray:
    """Noise-free multiplexed images ``(n_views * n_p, r1 - r0, w, 3)`` as the non-ideal dome forms them.

    Pattern ``p`` of view ``(t, c)`` sums the view's single-LED truth with weights
    ``patterns[p, l] * mux_drift[t, p, l]`` (light superposes before the sensor), then the image is
    shifted by its offset.
    """
    n_views, n_leds = geometry.n_views, geometry.n_leds
    p = np.asarray(patterns, dtype=np.float32)
    weights = p[None] * draws.mux_drift.astype(np.float32)                                # (n_turn, n_p, n_leds)
    weights = np.repeat(weights[:, None], geometry.n_cam, axis=1).reshape(n_views, *p.shape)
    tail = truth_ext.shape[1:]
    b = truth_ext.reshape(n_views, n_leds, -1)
    mux = np.matmul(weights, b).reshape((n_views * p.shape[0],) + tail)                    # eq. sum_l w B_l
    return _crop_shifted(mux, draws.mux_shift, e0, r0, r1)


def _expose(signal: np.ndarray, r0: int, gain: np.ndarray, noise: SensorNoise, seed: Sequence[int], kind: int,
            draws: DomeDraws, per_view: int) -> np.ndarray:
    """Exposed ``signal`` (rows r0: on axis 1, ``per_view`` images per view) with the views' hot texels."""
    out = _expose_rows(signal, r0, gain, noise, seed, kind)
    hot = draws.hot[:, r0:r0 + signal.shape[1]]
    if hot.any():
        v = np.repeat(np.arange(hot.shape[0]), per_view)                                  # view of every image
        a = draws.hot_share[v].astype(np.float32)[:, None, None]
        stuck = (noise.full_well_e / np.asarray(gain, dtype=np.float64)).astype(np.float32)   # saturated value
        mixed = (1 - a)[..., None] * out + (a * stuck[:, None, None])[..., None]          # eq. (1 - a) x + a FW / g
        out = np.where(hot[v][..., None], mixed, out)
    return out


def measure_band_nonideal(truth_ext: np.ndarray, e0: int, g0: int, g1: int, r0: int, r1: int, gains: Gains,
                          noises: tuple[SensorNoise, SensorNoise], patterns: np.ndarray, geometry: Geometry,
                          draws: DomeDraws, seed: Sequence[int]) -> Measured:
    """:func:`~btfcore.acquisition.band_evaluation.measure_band` under a non-ideal dome.

    Parameters
    ----------
    truth_ext : (n_lv, rows, w, 3) ndarray
        Truth of texture rows ``e0 : e0 + rows``, covering :func:`registration_halo` of the
        reconstruction's halo ``g0:g1`` (which covers the band r0:r1).

    Returns
    -------
    truth, single_halo, mux, demux : ndarray
        The truth of rows r0:r1, the noisy single-light rows g0:g1, the noisy multiplexed rows r0:r1
        and those demultiplexed with the nominal patterns.
    """
    single = _expose(nonideal_single(truth_ext, e0, g0, g1, geometry, draws), g0, gains[0], noises[0], seed, 0,
                     draws, geometry.n_leds)
    mux = _expose(nonideal_multiplexed(truth_ext, e0, r0, r1, patterns, geometry, draws), r0, gains[1], noises[1],
                  seed, 1, draws, np.asarray(patterns).shape[0])
    return truth_ext[:, r0 - e0:r1 - e0], single, mux, demultiplex_views(mux, patterns, geometry)


def nonideal_patterns(truth_ext: np.ndarray, e0: int, r0: int, r1: int, gains: np.ndarray, patterns: np.ndarray,
                      noise: SensorNoise, geometry: Geometry, draws: DomeDraws, seed: Sequence[int]) -> np.ndarray:
    """:func:`~btfcore.acquisition.band_evaluation.noisy_patterns` under a non-ideal dome: every view of
    texture rows r0:r1 under a strategy's own ``patterns`` ``(m, n_leds)``, ``(n_views * m, r1 - r0, w, 3)``.

    ``draws`` are that strategy's (:meth:`DomeDraws.for_patterns`): each shot's LED factors and each
    image's offset; ``gains`` from :func:`multiplexed_gains`, ``noise`` at the multiplexed camera gain;
    the views' hot texels as in every image. The noise of texture row ``r`` comes from ``seed + [2, r]``.
    """
    m = np.asarray(patterns).shape[0]
    return _expose(nonideal_multiplexed(truth_ext, e0, r0, r1, patterns, geometry, draws), r0, gains, noise, seed, 2,
                   draws, m)


def nonideal_moments(truth_ext: np.ndarray, e0: int, r0: int, r1: int, gains: Gains,
                     noises: tuple[SensorNoise, SensorNoise], patterns: np.ndarray, geometry: Geometry,
                     draws: DomeDraws, seed: Sequence[int]) -> Moments:
    """:func:`~btfcore.acquisition.band_evaluation.demultiplexed_moments` of rows r0:r1 under a non-ideal dome."""
    mux = _expose(nonideal_multiplexed(truth_ext, e0, r0, r1, patterns, geometry, draws), r0, gains[1], noises[1],
                  seed, 1, draws, np.asarray(patterns).shape[0])
    x = demultiplex_views(mux, patterns, geometry).astype(np.float64).reshape(geometry.n_lv, -1)
    mean = x.mean(axis=1)
    return np.float64(x.shape[1]), mean, ((x - mean[:, None]) ** 2).sum(axis=1)
