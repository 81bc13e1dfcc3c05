"""A dome that is not ideal (btfcore.simulate.nonideal, btfcore.acquisition.nonideal_measurement): each effect
does what it says, statistically and seeded; the ideal dome is the identity."""

from __future__ import annotations

import numpy as np
import pytest

from btfcore.acquisition.band_evaluation import image_maxima, measure_band, noisy_patterns
from btfcore.acquisition.hadamard import multiplexing_patterns
from btfcore.acquisition.noise import SensorNoise, exposure_gain
from btfcore.acquisition.nonideal_measurement import (
    draw_effects,
    measure_band_nonideal,
    multiplexed_gains,
    nonideal_gains,
    nonideal_multiplexed,
    nonideal_patterns,
    nonideal_single,
    noises_at_gains,
    registration_halo,
)
from btfcore.acquisition.strategies import Geometry
from btfcore.dome import SensorSpec
from btfcore.simulate.nonideal import (
    IDEAL,
    MAX_SHIFT_PX,
    PRESETS,
    DomeNonIdeality,
    full_scale_at_gain,
    gain_factor,
    hot_pixel_mask,
    led_drift_factors,
    metered_maximum,
    parse_non_ideal,
    registration_shifts,
    sensor_at_gain,
    shift_images,
)
from btfcore.simulate.sensor import expected_dn, expose


def test_defaults_are_ideal_and_draw_nothing():
    assert DomeNonIdeality().is_ideal and PRESETS["ideal"] is IDEAL and not PRESETS["realistic"].is_ideal
    rng = np.random.default_rng(0)
    state = rng.bit_generator.state
    assert np.array_equal(led_drift_factors(0.0, rng, (3, 4)), np.ones((3, 4)))
    assert np.array_equal(registration_shifts(0.0, rng, 5), np.zeros((5, 2)))
    assert not hot_pixel_mask(0.0, rng, (8, 8)).any()
    assert rng.bit_generator.state == state                       # the ideal dome consumes no random numbers
    images = np.random.default_rng(1).random((3, 6, 7, 3)).astype(np.float32)
    assert np.array_equal(shift_images(images, np.zeros((3, 2))), images)
    spec = SensorSpec()
    assert sensor_at_gain(spec, 0.0) is spec


def test_led_drift_is_lognormal_with_mean_one_and_the_relative_sd():
    f = led_drift_factors(0.05, np.random.default_rng(2), (200_000,))
    assert f.min() > 0
    assert abs(f.mean() - 1) < 5e-4                               # 3 sd of the mean: 0.05 / sqrt(2e5) * 3
    assert abs(f.std() - np.sqrt(np.exp(0.05 ** 2) - 1)) < 1e-3
    assert np.array_equal(f, led_drift_factors(0.05, np.random.default_rng(2), (200_000,)))   # seeded


def test_registration_shifts_are_normal_clipped_and_move_the_content():
    d = registration_shifts(0.2, np.random.default_rng(3), 100_000)
    assert abs(d.std() - 0.2) < 0.003 and abs(d.mean()) < 0.003
    assert np.abs(registration_shifts(5.0, np.random.default_rng(3), 1000)).max() <= MAX_SHIFT_PX
    # a linear ramp moves by exactly the offset (bilinear is exact on linear images), edges replicated
    rows, cols = np.mgrid[0:10, 0:12].astype(np.float64)
    img = np.stack([rows, cols], axis=-1)[None]
    out = shift_images(img, np.array([[0.25, -0.5]]))[0]
    np.testing.assert_allclose(out[2:-2, 2:-2, 0], rows[2:-2, 2:-2] - 0.25)
    np.testing.assert_allclose(out[2:-2, 2:-2, 1], cols[2:-2, 2:-2] + 0.5)
    assert np.array_equal(out[:, -1, 1], np.full(10, 11.0))       # the edge is replicated
    with pytest.raises(ValueError, match="within"):
        shift_images(img, np.array([[1.5, 0.0]]))


def test_a_band_of_shifted_rows_equals_the_whole_shifted_image():
    rng = np.random.default_rng(4)
    img = rng.random((5, 13, 9, 3))
    d = registration_shifts(0.6, rng, 5)
    whole = shift_images(img, d)
    for r0, r1 in ((0, 4), (4, 9), (9, 13), (6, 7)):
        ext = registration_halo(r0, r1, 13)
        band = shift_images(img[:, ext], d)[:, r0 - ext.start:r1 - ext.start]
        np.testing.assert_allclose(band, whole[:, r0:r1], rtol=0, atol=1e-12)


def test_hot_pixel_mask_has_the_fraction_and_is_seeded():
    m = hot_pixel_mask(1e-3, np.random.default_rng(5), (200, 300))
    assert m.sum() == 60 and np.array_equal(m, hot_pixel_mask(1e-3, np.random.default_rng(5), (200, 300)))
    assert hot_pixel_mask(1e-9, np.random.default_rng(5), (4, 4)).sum() == 1       # at least one


def test_gain_keeps_the_white_level_and_shrinks_the_full_scale():
    spec = SensorSpec()
    at10 = sensor_at_gain(spec, 10.0)
    assert at10.white_level == spec.white_level
    assert gain_factor(10.0) == pytest.approx(3.1623, rel=1e-4)
    assert at10.gain_e_per_dn == pytest.approx(spec.gain_e_per_dn / gain_factor(10.0))
    assert full_scale_at_gain(5500.0, 10.0) == pytest.approx(5500.0 / 3.1623, rel=1e-4)
    # a frame at 10 dB reads the DN of a 0 dB frame of gain_factor times the shutter time
    rad = np.full((1, 4, 4, 3), 1e-3)
    np.testing.assert_allclose(expected_dn(rad, 0.1, at10), expected_dn(rad, 0.1 * gain_factor(10.0), spec),
                               rtol=1e-9)
    # and has the photon noise of the fewer electrons it collected: variance in DN^2 per DN of signal
    # is 1 / gain (photon transfer), so sqrt(3.16) times the relative noise of the same DN at 0 dB
    rng = np.random.default_rng(6)
    big = np.full((1, 100, 100, 3), 2e-3)
    f0 = expose(big, 0.5, spec, None, rng, psf=False)[..., 0::2, 1::2].astype(np.float64) - spec.black_level
    f10 = (expose(big, 0.5 / gain_factor(10.0), at10, None, rng, psf=False)[..., 0::2, 1::2].astype(np.float64)
           - spec.black_level)                                     # the green pixels of an RGGB mosaic
    assert abs(f0.mean() / f10.mean() - 1) < 0.01
    assert f10.var() / f0.var() == pytest.approx(gain_factor(10.0), rel=0.1)


def test_metered_maximum_is_the_median_pattern():
    m = np.array([[1.0, 5.0, 2.0], [4.0, 4.0, 10.0]])
    np.testing.assert_array_equal(metered_maximum(m, axis=1), [[2.0], [4.0]])


def test_parse_presets_and_overrides_and_refusals():
    assert parse_non_ideal("realistic") == PRESETS["realistic"]
    d = parse_non_ideal("realistic, led_drift=0.02, multiplex_single_exposure=false")
    assert d.led_drift == 0.02 and not d.multiplex_single_exposure and d.single_gain_db == 10.0
    assert parse_non_ideal("registration_sd_px=0.3") == DomeNonIdeality(registration_sd_px=0.3)
    for bad, what in (("fancy", "no preset"), ("led_drift=x", "must be a number"), ("colour=1", "unknown"),
                      ("led_drift=2", r"\[0, 0.5\]"), ("", "give a preset")):
        with pytest.raises(ValueError, match=what):
            parse_non_ideal(bad)
    assert DomeNonIdeality.from_json(PRESETS["realistic"].to_json()) == PRESETS["realistic"]


# --------------------------------------------------------------------------- the evaluation's measurements


GEO = Geometry(2, 3, 7, 10, 6)                  # 2 turntable positions x 3 cameras x 7 LEDs, 10 x 6 texels


def _truth(seed: int = 7) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (0.05 + rng.random((GEO.n_lv, GEO.height, GEO.width, 3))).astype(np.float32)


def test_evaluation_single_exposure_gain_and_saturation():
    truth = _truth()
    for led in (5, 6):                                              # two LEDs give highlights: the patterns
        truth[led::GEO.n_leds] *= 10                                # with both are 1.7 x the median pattern
    patterns = multiplexing_patterns(GEO.n_leds)
    noise = SensorNoise()
    maxima = image_maxima(truth, patterns)
    dome = DomeNonIdeality(multiplex_single_exposure=True, single_gain_db=10.0)
    noises = noises_at_gains(noise, dome)
    assert noises[0].full_well_e == pytest.approx(5500 / gain_factor(10.0)) and noises[1] == noise
    g_single, g_mux = nonideal_gains(maxima, noises, dome, GEO.n_views)
    np.testing.assert_allclose(g_single, exposure_gain(maxima[0], noises[0]))
    per_view = g_mux.reshape(GEO.n_views, -1)
    assert np.all(per_view == per_view[:, :1])                      # one exposure per multiplexed capture
    np.testing.assert_allclose(per_view[:, 0], noise.fill * noise.full_well_e
                               / np.median(maxima[1].reshape(GEO.n_views, -1), axis=1))
    # the brighter half of the patterns saturates at their brightest texels; the darker is under-exposed
    draws = draw_effects(dome, GEO, patterns.shape[0], np.ones(GEO.n_views), (0, 1))
    _, _, mux, _ = measure_band_nonideal(truth, 0, 0, GEO.height, 0, GEO.height, (g_single, g_mux), noises,
                                         patterns, GEO, draws, (0, 1))
    sat = noise.full_well_e / g_mux
    clipped = (mux.reshape(len(g_mux), -1) >= sat[:, None] * (1 - 1e-6)).any(axis=1)
    bright = maxima[1] * g_mux > noise.full_well_e * 1.05
    assert bright.any() and np.array_equal(clipped[bright], np.ones(bright.sum(), bool))
    assert not clipped[maxima[1] * g_mux < noise.full_well_e * 0.9].any()


def test_evaluation_measurements_of_the_ideal_dome_are_the_ideal_ones():
    truth = _truth()
    patterns = multiplexing_patterns(GEO.n_leds)
    noise = SensorNoise()
    maxima = image_maxima(truth, patterns)
    gains = (exposure_gain(maxima[0], noise), exposure_gain(maxima[1], noise))
    np.testing.assert_array_equal(nonideal_gains(maxima, (noise, noise), IDEAL, GEO.n_views)[0], gains[0])
    draws = draw_effects(IDEAL, GEO, patterns.shape[0], np.ones(GEO.n_views), (0, 1))
    a = measure_band(truth, 0, 2, 7, gains, patterns, GEO, noise, (0, 1))
    b = measure_band_nonideal(truth, 0, 0, GEO.height, 2, 7, gains, (noise, noise), patterns, GEO, draws, (0, 1))
    for x, y in zip(a[:1] + a[2:], b[:1] + b[2:]):
        np.testing.assert_allclose(x, y, rtol=2e-6, atol=1e-6)
    np.testing.assert_array_equal(a[1], b[1][:, 0:GEO.height])


def test_a_strategys_own_patterns_under_the_dome():
    """Designed patterns' shots (issue 20) drift, shift and share one exposure per view like the S-matrix's,
    with their own draws; under the ideal dome they are measured as the ideal dome measures them."""
    truth = _truth()
    rng = np.random.default_rng(3)
    own = (rng.random((5, GEO.n_leds)) < 0.3).astype(np.float64)
    own[:, 0] = 1.0                                                          # never an empty pattern
    noise = SensorNoise()
    maxima = noisy_patterns(truth, 0, None, own, None, None).reshape(GEO.n_views * 5, -1).max(axis=1)
    gains = multiplexed_gains(maxima, noise, IDEAL, GEO.n_views)
    np.testing.assert_array_equal(gains, exposure_gain(maxima, noise))      # the ideal dome: auto exposure
    draws = draw_effects(IDEAL, GEO, 15, np.ones(GEO.n_views), (0, 1)).for_patterns(5, 7)
    np.testing.assert_allclose(nonideal_patterns(truth, 0, 2, 7, gains, own, noise, GEO, draws, (0, 1)),
                               noisy_patterns(truth[:, 2:7], 2, gains, own, noise, (0, 1)), rtol=2e-6, atol=1e-6)
    dome = DomeNonIdeality(led_drift=0.05, registration_sd_px=0.4, multiplex_single_exposure=True,
                           hot_pixel_fraction=0.01)
    base = draw_effects(dome, GEO, 15, np.full(GEO.n_views, 0.5), (0, 1))
    draws = base.for_patterns(5, 7)
    assert draws.mux_drift.shape == (GEO.n_turn, 5, GEO.n_leds) and draws.mux_shift.shape == (GEO.n_views * 5, 2)
    assert np.array_equal(draws.hot, base.hot) and np.array_equal(draws.single_drift, base.single_drift)
    assert np.array_equal(base.for_patterns(5, 7).mux_drift, draws.mux_drift)          # seeded by the word
    assert not np.array_equal(base.for_patterns(5, 8).mux_drift, draws.mux_drift)
    assert np.abs(draws.mux_shift).max() <= 0.5 * MAX_SHIFT_PX                         # px -> texels
    gains = multiplexed_gains(maxima, noise, dome, GEO.n_views).reshape(GEO.n_views, -1)
    assert np.all(gains == gains[:, :1])                                                # one exposure per view
    # a band with its one-row registration halo measures its rows as the whole texture does
    whole = nonideal_patterns(truth, 0, 0, GEO.height, gains.reshape(-1), own, noise, GEO, draws, (0, 1))
    ext = registration_halo(3, 6, GEO.height)
    band = nonideal_patterns(truth[:, ext], ext.start, 3, 6, gains.reshape(-1), own, noise, GEO, draws, (0, 1))
    np.testing.assert_allclose(band, whole[:, 3:6], rtol=1e-6)
    nominal = noisy_patterns(truth, 0, None, own, None, None)
    drifted = nonideal_multiplexed(truth, 0, 0, GEO.height, own, GEO, base.for_patterns(5, 7))
    assert not np.allclose(drifted, nominal, rtol=1e-3)


def test_evaluation_drift_and_registration_and_hot_pixels():
    truth = _truth()
    patterns = multiplexing_patterns(GEO.n_leds)
    dome = DomeNonIdeality(led_drift=0.05)
    draws = draw_effects(dome, GEO, patterns.shape[0], np.ones(GEO.n_views), (0, 1))
    single = nonideal_single(truth, 0, 0, GEO.height, GEO, draws)
    ratio = (single / truth)[:, 0, 0, 0].reshape(GEO.n_turn, GEO.n_cam, GEO.n_leds)
    np.testing.assert_allclose(ratio, np.repeat(draws.single_drift[:, None], GEO.n_cam, axis=1), rtol=1e-6)
    np.testing.assert_allclose(ratio[:, 0], ratio[:, 1], rtol=1e-6)   # the cameras of a shot see one drift
    mux = nonideal_multiplexed(truth, 0, 0, GEO.height, patterns, GEO, draws)
    nominal = np.einsum("pl,vlx->vpx", patterns, truth.reshape(GEO.n_views, GEO.n_leds, -1))
    rel = mux.reshape(nominal.shape) / nominal - 1
    assert 0.002 < rel.std() < 0.05                                   # a pattern of ~4 LEDs drifts by ~5 % / 2
    # registration: a band with its one-row halo equals the whole image
    dome = DomeNonIdeality(registration_sd_px=0.4)
    draws = draw_effects(dome, GEO, patterns.shape[0], np.full(GEO.n_views, 0.5), (0, 1))
    assert np.abs(draws.single_shift).max() <= 0.5 * MAX_SHIFT_PX     # px -> texels
    whole = nonideal_multiplexed(truth, 0, 0, GEO.height, patterns, GEO, draws)
    ext = registration_halo(3, 6, GEO.height)
    band = nonideal_multiplexed(truth[:, ext], ext.start, 3, 6, patterns, GEO, draws)
    np.testing.assert_allclose(band, whole[:, 3:6], rtol=1e-6)
    # hot pixels: a fixed set of texels per view, raised towards the saturated value in every image
    dome = DomeNonIdeality(hot_pixel_fraction=0.01)
    draws = draw_effects(dome, GEO, patterns.shape[0], np.full(GEO.n_views, 0.5), (0, 1))
    assert draws.hot_share[0] == 0.25 and draws.hot.sum() == GEO.n_views * round(0.04 * GEO.height * GEO.width)
    noise = SensorNoise(read_noise_e=0.0)
    maxima = image_maxima(truth, patterns)
    gains = (exposure_gain(maxima[0], noise), exposure_gain(maxima[1], noise))
    _, single, _, _ = measure_band_nonideal(truth, 0, 0, GEO.height, 0, GEO.height, gains, (noise, noise), patterns,
                                            GEO, draws, (0, 1))
    hot = np.repeat(draws.hot, GEO.n_leds, axis=0)
    excess = (single - truth).mean(axis=-1)
    assert excess[hot].mean() > 0.2 * (noise.full_well_e / gains[0]).mean() * 0.25 * 0.5
    assert abs(excess[~hot].mean()) < 0.01
