"""Measure, reconstruct and score one band of texture rows: the numerics of the acquisition evaluation.

The evaluation (``docs/evaluation.md``) works on bands of texture rows of a
noise-free truth BTF ``(n_lv, rows, w, 3)`` (linear RGB, rows
``(turntable, camera, light)``, the light fastest):

* **measurements**: single-light rows and S-matrix patterns per view summed
  from the linear truth (light superposes before the sensor), each image
  exposed by :func:`btfcore.acquisition.noise.expose`; every texture row's
  noise has its own seeded generator, so bands and halos see the same
  measurement (:func:`noisy_rows`, :func:`measure_band`); a strategy with its
  own patterns (source ``'patterns'``) is measured with them and its own gains
  (:func:`noisy_patterns`);
* **demultiplexing** per view by least squares (VMV §3.2,
  :func:`demultiplex_views`) and the per-texture variance of the result
  reduced over bands (:func:`demultiplexed_moments`, :func:`moments_variance`;
  the thresholded de-noising, VMV §4.1);
* **reconstruction** of one strategy (:mod:`btfcore.acquisition.strategies`)
  on one band (:func:`reconstruct_band`), and of every strategy with its
  **noise-free floor**, the same strategy on the noise-free counterpart of its
  measurement (:func:`noise_free_band`, :func:`reconstruct_strategies`);
* **scores**: sums of the relative L2 on log Y (paper 1 §4.1.1) and of the
  per-texture errors of mRMSE, mPSNR and mRE (SR paper eqs. 8-10) per band
  (:func:`score_band`), reduced over bands and finished by
  :func:`finish_scores` to the values :mod:`btfcore.metrics` gives on the
  whole BTF;
* **flags**: whether a strategy's result on one material has diverged
  (:func:`divergence`, left out of the means) or its operator is
  ill-conditioned (:func:`conditioning`, shown with the reason), the one
  definition the claims, tables and report use (docs/evaluation.md,
  "Diverged and ill-conditioned results").
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from btfcore.acquisition.noise import SensorNoise, exposure_gain, expose
from btfcore.acquisition.reconstruct import apply, measure, reconstruct_abtf
from btfcore.acquisition.strategies import FLOOR_COMPUTED, Geometry, Strategy
from btfcore.capture.demultiplex import demultiplex_operator
from btfcore.model.colour import LOG_YUV_EPS, from_log_yuv, log_luminance, to_log_yuv

__all__ = ["CHROMA_MAX", "DIVERGED_MRE_PERCENT", "DIVERGED_REL_L2_LOG_Y", "ILL_CONDITIONED", "LOG_Y_MAX",
           "BandScores", "BandTruth", "combine_moments", "conditioning", "demultiplex_views",
           "demultiplexed_moments", "divergence", "finish_scores", "floor_name", "image_maxima", "measure_band",
           "moments_variance", "noise_free_band", "noisy_multiplexed", "noisy_patterns", "noisy_rows", "noisy_single",
           "pattern_maxima", "reconstruct_band", "reconstruct_strategies", "score_band", "with_pattern_gains"]

#: Range a log-space reconstruction is clipped to before it is mapped back to RGB: log Y in
#: [log eps, LOG_Y_MAX] (an unregularised solve can extrapolate to exp overflow), U/Y and V/Y in
#: [-CHROMA_MAX, CHROMA_MAX]. Far outside any truth value, so the errors stay those of the solve.
LOG_Y_MAX = 20.0
CHROMA_MAX = 5.0

#: Gains of the single-light and of the multiplexed images, ``((n_lv,), (n_views * n_p,))``.
Gains = tuple[np.ndarray, np.ndarray]


# --------------------------------------------------------------------------- measurements


def demultiplex_views(measured: np.ndarray, patterns: np.ndarray, geometry: Geometry,
                      P: np.ndarray | None = None) -> np.ndarray:
    """Least-squares demultiplexing of every view (VMV §3.2).

    Parameters
    ----------
    measured : (n_views * n_p, ...) ndarray
        Every view under every pattern, view-major.
    patterns : (n_p, n_leds) ndarray
    geometry : Geometry
    P : (n_leds, n_p) ndarray, optional
        :func:`btfcore.capture.demultiplex.demultiplex_operator` of ``patterns``.

    Returns
    -------
    single : (n_lv, ...) ndarray
    """
    P = demultiplex_operator(patterns) if P is None else P
    tail = measured.shape[1:]
    m = measured.reshape(geometry.n_views, patterns.shape[0], -1)
    return np.matmul(P.astype(np.float32)[None], m).reshape((geometry.n_lv,) + tail)


def image_maxima(truth: np.ndarray, patterns: np.ndarray) -> Gains:
    """Brightest noise-free value of every single-light ``(n_lv,)`` and multiplexed ``(n_views * n_p,)`` image."""
    n = truth.shape[0]
    mux = measure(truth, patterns=patterns)                                   # (I_views (x) M) B
    return truth.reshape(n, -1).max(axis=1), mux.reshape(-1, truth[0].size).max(axis=1)


def _expose_rows(signal: np.ndarray, r0: int, gain: np.ndarray, noise: SensorNoise, seed: Sequence[int],
                 kind: int) -> np.ndarray:
    """Noisy ``signal`` (texture rows ``r0 : r0 + len`` on axis 1); row ``r``'s noise comes from ``seed + [kind, r]``."""
    out = np.empty_like(signal)
    for i in range(signal.shape[1]):
        out[:, i] = expose(signal[:, i], gain, noise, np.random.default_rng([*seed, kind, r0 + i]))
    return out


def noisy_single(truth: np.ndarray, r0: int, gains: Gains, noise: SensorNoise, seed: Sequence[int]) -> np.ndarray:
    """Noisy single-light measurement ``(n_lv, rows, w, 3)`` of texture rows ``r0 : r0 + rows``."""
    return _expose_rows(truth, r0, gains[0], noise, seed, 0)


def noisy_multiplexed(truth: np.ndarray, r0: int, gains: Gains, patterns: np.ndarray, noise: SensorNoise,
                      seed: Sequence[int]) -> np.ndarray:
    """Noisy multiplexed measurement ``(n_views * n_p, rows, w, 3)`` (every view under every pattern).

    Light superposes, so the multiplexed radiance is formed from the linear,
    noise-free truth; the noise comes afterwards (docs/evaluation.md, "Noise model").
    """
    return _expose_rows(measure(truth, patterns=patterns), r0, gains[1], noise, seed, 1)


def pattern_maxima(truth: np.ndarray, strategies: Sequence[Strategy]) -> dict[str, np.ndarray]:
    """Brightest noise-free value ``(n_views * m,)`` of every image of each strategy with its own patterns."""
    return {s.name: measure(truth, patterns=s.patterns).reshape(-1, truth[0].size).max(axis=1)
            for s in strategies if s.source == "patterns"}


def with_pattern_gains(strategies: Sequence[Strategy], maxima: Sequence[dict[str, np.ndarray]],
                       noise: SensorNoise, gains_of: Callable[[np.ndarray], np.ndarray] | None = None
                       ) -> list[Strategy]:
    """The strategies, those with their own patterns given their images' gains from the maxima of every band
    (:func:`pattern_maxima`): ``gains_of(maxima)`` (``(n_views * m,)`` each), by default each image's auto
    exposure to ``noise.fill`` (:func:`btfcore.acquisition.noise.exposure_gain`)."""
    gains_of = gains_of or (lambda mx: exposure_gain(mx, noise))
    out = []
    for s in strategies:
        if s.source == "patterns":
            s = dataclasses.replace(s, gains=gains_of(np.max([m[s.name] for m in maxima], axis=0)))
        out.append(s)
    return out


def noisy_patterns(truth: np.ndarray, r0: int, gains: np.ndarray | None, patterns: np.ndarray, noise: SensorNoise | None,
                   seed: Sequence[int] | None) -> np.ndarray:
    """Every view of texture rows ``r0 : r0 + len`` under ``patterns`` ``(m, n_leds)``, ``(n_views * m, rows, w, 3)``.

    Each image is exposed with its own gain of ``gains`` ``(n_views * m,)`` (from its maximum, as the
    S-matrix images); the noise of texture row ``r`` comes from ``seed + [2, r]``. ``noise=None``: the
    noise-free images (a floor).
    """
    mux = measure(truth, patterns=patterns)                                  # (I_views (x) M) B
    if noise is None:
        return mux
    return _expose_rows(mux, r0, gains, noise, seed, 2)


def noisy_rows(truth: np.ndarray, r0: int, gains: Gains, patterns: np.ndarray, geometry: Geometry,
               noise: SensorNoise, seed: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """Noisy single-light and multiplexed measurements of texture rows ``r0 : r0 + len``.

    The noise of texture row ``r`` is drawn from its own generator
    (``seed + [kind, r]``), so a row is measured alike in every band and halo
    that contains it. ``geometry`` must describe ``truth``'s rows.
    """
    if truth.shape[0] != geometry.n_lv:
        raise ValueError(f"truth has {truth.shape[0]} rows, the geometry {geometry.n_lv} light/view pairs")
    return noisy_single(truth, r0, gains, noise, seed), noisy_multiplexed(truth, r0, gains, patterns, noise, seed)


def measure_band(truth_halo: np.ndarray, g0: int, r0: int, r1: int, gains: Gains, patterns: np.ndarray,
                 geometry: Geometry, noise: SensorNoise, seed: Sequence[int]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The measurements one band's reconstructions read.

    Parameters
    ----------
    truth_halo : (n_lv, halo rows, w, 3) ndarray
        Truth of texture rows ``g0 : g0 + halo rows`` (the band r0:r1 and its ABTF halo).

    Returns
    -------
    truth, single_halo, mux, demux : ndarray
        The truth of rows r0:r1, the noisy single-light rows of the halo,
        the noisy multiplexed rows of r0:r1 and those demultiplexed.
    """
    single = noisy_single(truth_halo, g0, gains, noise, seed)
    truth = truth_halo[:, r0 - g0:r1 - g0]
    mux = noisy_multiplexed(truth, r0, gains, patterns, noise, seed)       # each row's noise is the row's own
    return truth, single, mux, demultiplex_views(mux, patterns, geometry)


#: What one band's reconstructions read: ``(truth, single_halo, mux, demux)`` as :func:`measure_band` returns.
Measured = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def noise_free_band(truth_halo: np.ndarray, g0: int, r0: int, r1: int, patterns: np.ndarray,
                    geometry: Geometry) -> Measured:
    """The noise-free counterparts of :func:`measure_band`'s measurements: what the floors read.

    The single-light rows are the truth's own; the multiplexed images are the
    truth's through the same patterns (:func:`btfcore.acquisition.reconstruct.measure`),
    demultiplexed by the same least squares (:func:`demultiplex_views`).

    Parameters
    ----------
    truth_halo : (n_lv, halo rows, w, 3) ndarray
        Truth of texture rows ``g0 : g0 + halo rows``.

    Returns
    -------
    truth, single_halo, mux, demux : ndarray
        As :func:`measure_band`, without noise.
    """
    truth = truth_halo[:, r0 - g0:r1 - g0]
    mux = measure(truth, patterns=patterns)                                 # (I_views (x) M) B
    return truth, truth_halo, mux, demultiplex_views(mux, patterns, geometry)


def floor_name(strategy: str) -> str:
    """The key of a strategy's noise-free floor among a band's scores (:func:`reconstruct_strategies`)."""
    return f"{strategy}/noise-free"


def reconstruct_strategies(strategies: Sequence[Strategy], r0: int, r1: int, truth_halo: np.ndarray, g0: int,
                           geometry: Geometry, measured: Measured, noise_free: Measured | None = None,
                           noise: SensorNoise | None = None, seed: Sequence[int] | None = None,
                           measure_own: Callable[[Strategy], np.ndarray] | None = None
                           ) -> Iterator[tuple[Strategy, np.ndarray, np.ndarray | None]]:
    """Every strategy's reconstruction of texture rows r0:r1 and, with ``noise_free``, its noise-free floor.

    The floor is the same strategy (its sampling, basis, solver,
    regularisation and, for the thresholded de-noising, the textures it
    drops) applied to the noise-free measurement: what the sampling, basis
    and solver give with perfect measurements. Computed only for strategies
    whose ``floor`` is :data:`~btfcore.acquisition.strategies.FLOOR_COMPUTED`
    (the others' floors are known: zero, or their own error).

    Parameters
    ----------
    strategies : sequence of Strategy
    r0, r1 : int
        The band's texture rows.
    truth_halo : (n_lv, halo rows, w, 3) ndarray
        Truth of texture rows ``g0 : g0 + halo rows`` (the band and its ABTF halo).
    geometry : Geometry
    measured : tuple
        :func:`measure_band` of the band.
    noise_free : tuple, optional
        :func:`noise_free_band` of the band (None: no floors).
    noise, seed : SensorNoise, sequence of int, optional
        Measure the strategies with their own patterns (source ``'patterns'``,
        :func:`noisy_patterns`); they need both.
    measure_own : callable, optional
        ``measure_own(strategy)``: such a strategy's measured images of rows r0:r1 instead
        (a non-ideal dome's, :func:`btfcore.acquisition.nonideal_measurement.nonideal_patterns`);
        its floor still measures the ideal dome's noise-free images.

    Yields
    ------
    strategy, reconstruction, floor : Strategy, (n_lv, r1 - r0, w, 3) ndarray, same or None
        float32 linear RGB, one strategy at a time (a band holds at most two reconstructions).
    """
    _, single, mux, demux = measured
    caches: tuple[dict[str, np.ndarray], dict[str, np.ndarray]] = ({}, {})
    own_rows = truth_halo[:, r0 - g0:r1 - g0]
    for strategy in strategies:
        own = None
        if strategy.source == "patterns":
            if strategy.patterns is None or strategy.gains is None:
                raise ValueError(f"strategy {strategy.name} measures with its own patterns: it needs its patterns "
                                 "and its images' gains (with_pattern_gains)")
            if measure_own is not None:
                own = measure_own(strategy)
            elif noise is None or seed is None:
                raise ValueError(f"strategy {strategy.name} measures with its own patterns: pass noise and seed")
            else:
                own = noisy_patterns(own_rows, r0, strategy.gains, strategy.patterns, noise, seed)
        recon = reconstruct_band(strategy, r0, r1, geometry.height, truth_halo, single, mux, g0, geometry, demux,
                                 caches[0], own)
        floor = None
        if noise_free is not None and strategy.floor == FLOOR_COMPUTED:
            _, single0, mux0, demux0 = noise_free
            own0 = noisy_patterns(own_rows, r0, None, strategy.patterns, None, None) if own is not None else None
            floor = np.asarray(reconstruct_band(strategy, r0, r1, geometry.height, truth_halo, single0, mux0, g0,
                                                geometry, demux0, caches[1], own0), dtype=np.float32)
        yield strategy, np.asarray(recon, dtype=np.float32), floor


# --------------------------------------------------------------------------- per-texture variance over bands


Moments = tuple[np.ndarray, np.ndarray, np.ndarray]


def combine_moments(a: Moments, b: Moments) -> Moments:
    """Chan, Golub and LeVeque's pairwise combination of (count, mean, M2)."""
    na, ma, qa = a
    nb, mb, qb = b
    n = na + nb
    d = mb - ma
    return n, ma + d * nb / n, qa + qb + d * d * na * nb / n


def demultiplexed_moments(truth: np.ndarray, r0: int, gains: Gains, patterns: np.ndarray, geometry: Geometry,
                          noise: SensorNoise, seed: Sequence[int]) -> Moments:
    """(count, mean ``(n_lv,)``, M2 ``(n_lv,)``) of the linear demultiplexed RGB of texture rows ``r0 : r0 + len``."""
    mux = noisy_multiplexed(truth, r0, gains, patterns, noise, seed)
    x = demultiplex_views(mux, patterns, geometry).astype(np.float64).reshape(geometry.n_lv, -1)   # (n_lv, m)
    mean = x.mean(axis=1)
    return np.float64(x.shape[1]), mean, ((x - mean[:, None]) ** 2).sum(axis=1)


def moments_variance(parts: Sequence[Moments]) -> np.ndarray:
    """Population variance ``(n_lv,)`` per texture of the bands' :func:`demultiplexed_moments`."""
    acc = parts[0]
    for p in parts[1:]:
        acc = combine_moments(acc, p)
    n, _, m2 = acc
    return m2 / n


# --------------------------------------------------------------------------- reconstruction


def _to_rgb(x: np.ndarray) -> np.ndarray:
    """``from_log_yuv`` of a log-space reconstruction clipped to :data:`LOG_Y_MAX` / :data:`CHROMA_MAX`."""
    x = np.array(x, dtype=np.float32)
    np.clip(x[..., 0], np.log(LOG_YUV_EPS), LOG_Y_MAX, out=x[..., 0])
    np.clip(x[..., 1:], -CHROMA_MAX, CHROMA_MAX, out=x[..., 1:])
    return from_log_yuv(x)


def reconstruct_band(strategy: Strategy, r0: int, r1: int, height: int, truth_halo: np.ndarray,
                     single_halo: np.ndarray, mux: np.ndarray, g0: int, geometry: Geometry,
                     demux: np.ndarray, log_cache: dict[str, np.ndarray] | None = None,
                     own: np.ndarray | None = None) -> np.ndarray:
    """One strategy's reconstruction of texture rows r0:r1, linear RGB ``(n_lv, r1 - r0, w, 3)``.

    ``truth_halo`` and ``single_halo`` hold texture rows ``g0 : g0 + len`` (the ABTF halo);
    ``mux`` (the multiplexed measurement) and ``demux`` (it demultiplexed) rows r0:r1 only.
    ``log_cache`` keeps the log-space conversion of a whole source between the strategies of a band.
    ``own``: a strategy's measurement with its own patterns (source ``'patterns'``), rows r0:r1
    (:func:`noisy_patterns`).
    """
    log_cache = {} if log_cache is None else log_cache
    a, b = r0 - g0, r1 - g0
    n_lv, w = geometry.n_lv, geometry.width
    if strategy.space == "linear":
        op = strategy.operators["rgb"]
        if strategy.source == "single":
            y = single_halo[strategy.rows, a:b]
        elif strategy.source == "patterns":
            if own is None:
                raise ValueError(f"strategy {strategy.name} measures with its own patterns: pass its images (own)")
            y = own
        elif strategy.source == "demux":
            y = demux
        else:
            y = mux if strategy.rows is None else mux[strategy.rows]
        out = apply(op, y.reshape(y.shape[0], -1))
        return out.reshape(n_lv, r1 - r0, w, 3)
    if strategy.source == "demux":
        if not strategy.operators:
            return np.maximum(demux, 0.0)                                  # plain demultiplexing
        x_band = to_log_yuv(demux)
        x = np.stack([apply(op, x_band[..., i].reshape(n_lv, -1)).reshape(n_lv, r1 - r0, w)
                      for i, op in enumerate(strategy.operators.values())], axis=-1)
        return _to_rgb(x)
    source = truth_halo if strategy.source == "truth" else single_halo
    if strategy.rows is None or len(strategy.rows) == len(source):
        if strategy.source not in log_cache:                                   # every row: convert once per band
            log_cache[strategy.source] = to_log_yuv(source)
        x_all = log_cache[strategy.source]
        x_all = x_all if strategy.rows is None else x_all[strategy.rows]
    else:
        x_all = to_log_yuv(source[strategy.rows])                              # (n_meas, halo rows, w, 3)
    chans = []
    for i, op in enumerate(strategy.operators.values()):                     # log Y, U/Y, V/Y
        if op.patch_size is not None:                                          # ABTF: band with its halo
            chans.append(reconstruct_abtf(op, x_all[..., i], out_rows=(r0, r1), height=height))
        else:
            chans.append(apply(op, x_all[:, a:b, :, i].reshape(x_all.shape[0], -1)).reshape(n_lv, r1 - r0, w))
    return _to_rgb(np.stack(chans, axis=-1))


# --------------------------------------------------------------------------- scores


@dataclass
class BandScores:
    """Error sums of one strategy over some texels, reduced over bands."""

    sse_log_y: float = 0.0
    ss_log_y: float = 0.0
    sse_rows: np.ndarray | None = None      # (n_lv,) per-texture squared error, linear RGB
    ss_rows: np.ndarray | None = None       # (n_lv,) per-texture squared norm of the truth
    n_texels: int = 0

    def add(self, other: BandScores) -> BandScores:
        if self.sse_rows is None:
            return other
        return BandScores(self.sse_log_y + other.sse_log_y, self.ss_log_y + other.ss_log_y,
                          self.sse_rows + other.sse_rows, self.ss_rows + other.ss_rows,
                          self.n_texels + other.n_texels)


@dataclass(frozen=True)
class BandTruth:
    """The truth's terms of :func:`score_band`, computed once per band for every strategy."""

    rgb: np.ndarray            # (n_lv, rows, w, 3) linear RGB
    log_y: np.ndarray          # (n_lv, rows, w) float64 log Y
    ss_rows: np.ndarray        # (n_lv,) squared norm of each texture

    @classmethod
    def of(cls, truth: np.ndarray) -> BandTruth:
        t = truth.reshape(truth.shape[0], -1).astype(np.float64)
        return cls(truth, log_luminance(truth).astype(np.float64), np.einsum("ij,ij->i", t, t))


def score_band(ref: BandTruth, recon: np.ndarray) -> BandScores:
    """Sums for relative L2 on log Y and the per-texture errors of mRMSE / mPSNR / mRE of one band."""
    t = ref.rgb
    d = (recon.astype(np.float64) - t).reshape(t.shape[0], -1)
    e = log_luminance(recon).astype(np.float64) - ref.log_y
    return BandScores(float(np.vdot(e, e)), float(np.vdot(ref.log_y, ref.log_y)), np.einsum("ij,ij->i", d, d),
                      ref.ss_rows, int(t.shape[1] * t.shape[2]))


def finish_scores(s: BandScores, row_max: np.ndarray) -> dict[str, float]:
    """Relative L2 on log Y (paper 1 §4.1.1) and SR eqs. (8)-(10) from the band sums.

    ``row_max`` ``(n_lv,)`` is the brightest truth value of every texture
    (the peak of eq. 9). Equal to :func:`btfcore.metrics.relative_error`
    (``space='log_y'``), :func:`~btfcore.metrics.mrmse`,
    :func:`~btfcore.metrics.mpsnr` and :func:`~btfcore.metrics.mre` of the
    whole BTF (tested).
    """
    rmse = np.sqrt(s.sse_rows) / np.sqrt(s.n_texels)                          # eq. (8) term
    with np.errstate(divide="ignore"):
        psnr = 20 * np.log10(row_max / rmse)                                 # eq. (9) term
    return {"rel_l2_log_y": float(np.sqrt(s.sse_log_y / s.ss_log_y)), "mrmse": float(np.mean(rmse)),
            "mpsnr": float(np.mean(psnr)), "mre": float(np.mean(np.sqrt(s.sse_rows / s.ss_rows)) * 100)}


# --------------------------------------------------------------------------- flags


#: A result has diverged when its mRE (SR paper eq. 10) exceeds this, per cent: the reconstruction's
#: per-texture error is 100 times the truth's norm (a log-space solve that extrapolated to exp overflow
#: gives 1e8 - 1e12 %; the worst genuine results, plain demultiplexing of dark metal, about 1e3 %).
DIVERGED_MRE_PERCENT = 1e4
#: ... or when its relative L2 error of log Y (paper 1 §4.1.1) exceeds this: worse than predicting log Y = 0.
DIVERGED_REL_L2_LOG_Y = 1.0
#: An operator is ill-conditioned when the condition number of its (sampled, regularised) basis rows
#: exceeds this: noise is amplified up to this factor.
ILL_CONDITIONED = 1e6


def _condition(info: dict) -> float | None:
    """The condition number a strategy reports (``kappa_log_y`` of the log Y operator, else ``condition``)."""
    value = info.get("kappa_log_y", info.get("condition"))
    return None if value is None else float(value)


def divergence(scores: dict[str, float], info: dict | None = None) -> str | None:
    """Why one strategy's result on one material has diverged, or None when it has not.

    Diverged: a score that is not finite, mRE above :data:`DIVERGED_MRE_PERCENT` or a
    relative L2 error of log Y above :data:`DIVERGED_REL_L2_LOG_Y`. The reason names the
    offending scores and, from ``info`` (the strategy's report), the condition number of its
    operator and its samples against its basis vectors.

    Parameters
    ----------
    scores : dict
        :func:`finish_scores` (``rel_l2_log_y`` a fraction, ``mpsnr`` dB, ``mre`` %).
    info : dict, optional
        The strategy's ``info`` (``k``, ``n_meas``, ``condition`` or ``kappa_log_y``).
    """
    bad = [f"{name} is not finite" for name, v in scores.items() if not np.isfinite(v)]
    if np.isfinite(scores.get("mre", 0.0)) and scores.get("mre", 0.0) > DIVERGED_MRE_PERCENT:
        bad.append(f"mRE {scores['mre']:.3g} % > {DIVERGED_MRE_PERCENT:,.0f} %")
    rel = scores.get("rel_l2_log_y", 0.0)
    if np.isfinite(rel) and rel > DIVERGED_REL_L2_LOG_Y:
        bad.append(f"log Y relative L2 {100 * rel:.3g} % > {100 * DIVERGED_REL_L2_LOG_Y:.0f} %")
    if not bad:
        return None
    context = _operator_text(info or {})
    return "diverged: " + "; ".join(bad) + (f" ({context})" if context else "")


def conditioning(info: dict | None) -> str | None:
    """Why a strategy's operator is ill-conditioned (condition number above :data:`ILL_CONDITIONED`,
    or fewer samples than basis vectors), or None."""
    info = info or {}
    cond, k, n = _condition(info), info.get("k"), info.get("n_meas")
    bad = []
    if cond is not None and (not np.isfinite(cond) or cond > ILL_CONDITIONED):
        bad.append(f"condition number {cond:.3g} > {ILL_CONDITIONED:.0e}")
    if k is not None and n is not None and int(n) < int(k):
        bad.append(f"{int(n)} samples below the basis rank {int(k)}")
    return ("ill-conditioned: " + "; ".join(bad)) if bad else None


def _operator_text(info: dict) -> str:
    cond, k, n = _condition(info), info.get("k"), info.get("n_meas")
    parts = []
    if cond is not None:
        parts.append(f"condition number of the sampled basis rows {cond:.3g}")
    if k is not None and n is not None:
        parts.append(f"{int(k)} basis vectors from {int(n)} samples")
    return ", ".join(parts)
