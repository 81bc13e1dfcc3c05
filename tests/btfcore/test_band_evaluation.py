"""Numerics of the acquisition evaluation on arrays (btfcore.acquisition.band_evaluation, .strategies, .noise):
noise model, multiplexed exposures, the strategy registry, per-texture variance and scores reduced over bands."""

from __future__ import annotations

import types

import numpy as np
import pytest

from btfcore.acquisition.band_evaluation import (
    BandScores,
    BandTruth,
    demultiplexed_moments,
    finish_scores,
    image_maxima,
    moments_variance,
    noisy_rows,
    score_band,
)
from btfcore.acquisition.hadamard import multiplexing_patterns
from btfcore.acquisition.noise import SensorNoise, bracket_gain, expose, exposure_gain, noise_moments
from btfcore.acquisition.reconstruct import measure, texture_variance
from btfcore.acquisition.strategies import (
    REGISTRY,
    THESIS_N_S,
    Geometry,
    StrategyBases,
    build_strategies,
    scaled_pairs,
    strategy_names,
)
from btfcore.metrics import mpsnr, mre, mrmse, relative_error

# --------------------------------------------------------------------------- the noise model


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_noise_has_the_stated_mean_and_variance(dtype):
    noise = SensorNoise(full_well_e=5500.0, read_noise_e=3.0, fill=0.8)
    signal = np.array([0.5, 0.05, 0.002], dtype)[:, None] * np.ones((3, 40000), dtype)   # 3 images
    gain = exposure_gain(np.array([0.5, 0.5, 0.5]), noise)                              # one exposure
    assert np.allclose(gain * 0.5, 0.8 * 5500.0)                                         # max at fill * FW
    x = expose(signal, gain, noise, np.random.default_rng(3), out_dtype=np.float64)
    mean, var = noise_moments(signal, gain, noise)
    n = signal.shape[1]
    for i in range(3):
        se = np.sqrt(var[i, 0] / n)
        assert abs(x[i].mean() - mean[i, 0]) < 5 * se                                    # unbiased
        assert abs(x[i].var() / var[i, 0] - 1) < 5 * np.sqrt(2 / n) + 0.01               # photon + read
    # photon noise dominates bright images, read noise dark ones
    assert var[0, 0] > 0.99 * signal[0, 0] / gain[0]
    assert var[2, 0] > 3.0 ** 2 / gain[2] ** 2


def test_exposure_refuses_a_black_image():
    with pytest.raises(ValueError, match="image 1 has brightest value 0.0"):
        exposure_gain(np.array([1.0, 0.0]), SensorNoise())


def test_a_bracket_gives_the_gain_of_its_longest_unsaturated_frame():
    times = np.array([[0.001, 0.004, 0.016], [0.001, 0.004, 0.016], [0.001, 0.004, 0.016], [0.002, 0.0, 0.0]])
    image_max = np.array([100.0, 1000.0, 1e7, 10.0])          # DN/s
    gain = bracket_gain(image_max, times, saturation_dn=4000.0, e_per_dn=1.5)
    # 100 DN/s fits the 16 ms frame (1.6 DN), 1000 DN/s too (16 DN); 1e7 DN/s saturates every frame: the shortest
    np.testing.assert_allclose(gain, [0.016 * 1.5, 0.016 * 1.5, 0.001 * 1.5, 0.002 * 1.5])
    gain = bracket_gain(np.array([400e3]), times[:1], saturation_dn=4000.0, e_per_dn=1.5)   # 4 ms: 1,600 DN
    np.testing.assert_allclose(gain, [0.004 * 1.5])
    with pytest.raises(ValueError, match="image 1: .* at least one exposure time"):
        bracket_gain(np.array([1.0, 1.0]), np.array([[0.1], [0.0]]), 4000.0, 1.5)


def test_multiplexed_images_get_shorter_exposures():
    rng = np.random.default_rng(0)
    g = Geometry(1, 2, 7, 4, 4)
    truth = rng.uniform(0.1, 1.0, (g.n_lv, 4, 4, 3)).astype(np.float32)
    p = multiplexing_patterns(7)
    mux = measure(truth, patterns=p)
    noise = SensorNoise()
    g_single = exposure_gain(truth.reshape(g.n_lv, -1).max(1), noise)
    g_mux = exposure_gain(mux.reshape(len(mux), -1).max(1), noise)
    assert g_mux.max() < g_single.min()          # brighter patterns, shorter exposures (fewer e- per unit)


# --------------------------------------------------------------------------- bands


def _truth(rng, g: Geometry) -> np.ndarray:
    return rng.uniform(0.01, 1.0, (g.n_lv, g.height, g.width, 3)).astype(np.float32)


def test_each_texture_row_is_measured_alike_in_every_band():
    rng = np.random.default_rng(1)
    g = Geometry(1, 2, 7, 6, 4)
    truth, p, noise = _truth(rng, g), multiplexing_patterns(7), SensorNoise()
    maxima = image_maxima(truth, p)
    gains = (exposure_gain(maxima[0], noise), exposure_gain(maxima[1], noise))
    single, mux = noisy_rows(truth, 0, gains, p, g, noise, (0, 3))
    band_single, band_mux = noisy_rows(truth[:, 2:5], 2, gains, p, g, noise, (0, 3))
    np.testing.assert_array_equal(band_single, single[:, 2:5])
    np.testing.assert_array_equal(band_mux, mux[:, 2:5])
    # and the variance of the demultiplexed rows reduced over bands is that of the whole texture
    whole = demultiplexed_moments(truth, 0, gains, p, g, noise, (0, 3))
    parts = [demultiplexed_moments(truth[:, a:b], a, gains, p, g, noise, (0, 3)) for a, b in ((0, 1), (1, 4), (4, 6))]
    np.testing.assert_allclose(moments_variance(parts), moments_variance([whole]), rtol=1e-9)
    from btfcore.acquisition.band_evaluation import demultiplex_views
    x = demultiplex_views(mux, p, g).reshape(g.n_lv, -1)
    np.testing.assert_allclose(moments_variance(parts), texture_variance(x), rtol=1e-6)


def test_band_scores_equal_the_metrics_of_the_whole_btf():
    rng = np.random.default_rng(2)
    g = Geometry(1, 2, 7, 5, 4)
    truth = _truth(rng, g)
    recon = (truth * rng.uniform(0.8, 1.2, truth.shape)).astype(np.float32)
    total = BandScores()
    for a, b in ((0, 2), (2, 3), (3, 5)):
        total = total.add(score_band(BandTruth.of(truth[:, a:b]), recon[:, a:b]))
    got = finish_scores(total, truth.reshape(g.n_lv, -1).max(1))
    assert got["rel_l2_log_y"] == pytest.approx(relative_error(truth, recon, space="log_y"), rel=1e-6)
    assert got["mrmse"] == pytest.approx(mrmse(truth, recon), rel=1e-6)
    assert got["mpsnr"] == pytest.approx(mpsnr(truth, recon), rel=1e-6)
    assert got["mre"] == pytest.approx(mre(truth, recon), rel=1e-6)


# --------------------------------------------------------------------------- the strategy registry


def _basis(rng, n: int, k: int):
    q, _ = np.linalg.qr(rng.standard_normal((n, k)))
    return types.SimpleNamespace(U=q.astype(np.float32), sigma=np.linspace(20, 1, k).astype(np.float32))


def test_build_strategies_makes_the_registry_in_its_order():
    from btfcore.dome import get_device

    device = get_device("tiny", texture_shape=(8, 8))
    g = Geometry(device.n_turn, device.n_cam, device.n_leds, 8, 8)
    light, view, _ = device.lv_directions()
    rng = np.random.default_rng(3)
    n = g.n_lv
    bases = StrategyBases({c: _basis(rng, n, 24) for c in ("log_y", "u_y", "v_y")}, _basis(rng, 9 * n, 12),
                          _basis(rng, n, 10), _basis(rng, n, 8))
    patterns = multiplexing_patterns(g.n_leds)
    strategies, sampling = build_strategies(bases, g, light, view, rng.uniform(0, 1, n), patterns, 7,
                                            sampling_steps=50)
    assert [s.name for s in strategies] == strategy_names() == [spec.name for spec in REGISTRY]
    assert len(set(strategy_names())) == len(REGISTRY)
    for s, spec in zip(strategies, REGISTRY):
        assert (s.space, s.source) == (spec.space, spec.source), s.name
        assert (not s.operators) == (s.name == "demultiplexed"), s.name
        assert list(s.operators) in ([], ["rgb"], ["log_y", "u_y", "v_y"]), s.name
    by = {s.name: s for s in strategies}
    # ABRDF and ABTF share the sampling; ABTF replaces only the log Y operator by the patch operator
    np.testing.assert_array_equal(by["abrdf-optimized"].rows, by["abtf-optimized"].rows)
    assert by["abtf-pmap7"].operators["log_y"].patch_size == 3 and by["abtf-pmap7"].operators["u_y"] is \
        by["abrdf-pmap7"].operators["u_y"]
    n_pairs = g.n_turn * g.n_leds
    for n_thesis in THESIS_N_S:
        count = sampling["paper4"]["counts"][str(n_thesis)]
        assert count["n_s"] == scaled_pairs(n_thesis, n_pairs)
        assert count["n_meas"] == count["n_s"] * g.n_cam == len(by[f"sparse-pinv-n{n_thesis}"].rows)
    assert sampling["paper1"]["n_samples"] == len(by["abrdf-pmap7"].rows)


# --------------------------------------------------------------------------- noise-free floors


def test_the_floor_is_the_strategy_on_noise_free_input_and_below_the_noisy_error():
    """A strategy's floor equals the same strategy (same operators) run on noise-free single-light rows and
    multiplexed images of the truth, and on average it is at most the noisy error."""
    from btfcore.acquisition.band_evaluation import (
        floor_name,
        measure_band,
        noise_free_band,
        pattern_maxima,
        reconstruct_band,
        reconstruct_strategies,
        with_pattern_gains,
    )
    from btfcore.acquisition.strategies import FLOOR_COMPUTED, floor_kinds
    from btfcore.dome import get_device

    device = get_device("tiny", texture_shape=(6, 6))
    g = Geometry(device.n_turn, device.n_cam, device.n_leds, 6, 6)
    light, view, _ = device.lv_directions()
    rng = np.random.default_rng(11)
    n = g.n_lv
    # a positive truth in the span of the linear basis (a constant column and 7 random ones), so that the
    # linear strategies reach it without noise
    q, _ = np.linalg.qr(np.column_stack([np.ones(n), rng.standard_normal((n, 7))]))
    linear = types.SimpleNamespace(U=q.astype(np.float32), sigma=np.linspace(20, 1, 8).astype(np.float32))
    coeff = rng.uniform(-0.5, 0.5, (8, g.height * g.width * 3))
    coeff[0] = np.sqrt(n) * np.sign(q[0, 0])                                    # a mean of 1
    truth = (q @ coeff).reshape(n, g.height, g.width, 3).astype(np.float32)
    assert truth.min() > 0
    bases = StrategyBases({c: _basis(rng, n, 24) for c in ("log_y", "u_y", "v_y")}, _basis(rng, 9 * n, 12),
                          linear, linear)
    patterns = multiplexing_patterns(g.n_leds)
    noise = SensorNoise(full_well_e=300.0, read_noise_e=3.0, fill=0.8)          # a noisy sensor
    maxima = image_maxima(truth, patterns)
    gains = (exposure_gain(maxima[0], noise), exposure_gain(maxima[1], noise))
    strategies, _ = build_strategies(bases, g, light, view, rng.uniform(0, 1, n), patterns, 7, sampling_steps=50)
    strategies = with_pattern_gains(strategies, [pattern_maxima(truth, strategies)], noise)
    measured = measure_band(truth, 0, 0, g.height, gains, patterns, g, noise, (0, 1))
    noise_free = noise_free_band(truth, 0, 0, g.height, patterns, g)
    row_max = truth.reshape(n, -1).max(1)
    ref = BandTruth.of(truth)
    noisy_err, floor_err = [], []
    for s, recon, floor in reconstruct_strategies(strategies, 0, g.height, truth, 0, g, measured, noise_free, noise,
                                                  (0, 1)):
        if floor_kinds()[s.name] != FLOOR_COMPUTED:
            assert floor is None, s.name                       # known floors (exact, or the truth's) not computed
            continue
        # the same strategy run by hand on noise-free inputs: single-light rows = the truth, multiplexed images
        # = the truth through the patterns, demultiplexed = the truth (S-matrix demultiplexing is exact)
        own = measure(truth, patterns=s.patterns) if s.source == "patterns" else None
        by_hand = reconstruct_band(s, 0, g.height, g.height, truth, truth, measure(truth, patterns=patterns), 0, g,
                                   truth, None, own)
        np.testing.assert_allclose(floor, by_hand, rtol=1e-3, atol=1e-4 * float(truth.max()), err_msg=s.name)
        noisy_err.append(finish_scores(score_band(ref, recon), row_max)["rel_l2_log_y"])
        floor_err.append(finish_scores(score_band(ref, floor), row_max)["rel_l2_log_y"])
    assert len(floor_err) == sum(k == FLOOR_COMPUTED for k in floor_kinds().values()) == len(REGISTRY) - 3
    assert np.mean(floor_err) <= np.mean(noisy_err)
    assert floor_name("sparse-pinv-n100") != "sparse-pinv-n100"
