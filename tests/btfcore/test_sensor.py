"""Sensor model: photon transfer, saturation, Bayer layouts, dark current, read noise, PSF, brackets."""

from __future__ import annotations

import numpy as np
import pytest

from btfcore.dome import BAYER_PATTERNS, SensorSpec
from btfcore.simulate.sensor import (
    WELL_EXPOSED,
    SensorModel,
    apply_psf,
    bayer_channel_index,
    choose_bracket,
    dark_current_map,
    dark_frames,
    expected_dn,
    expose,
    mosaic,
)

SHAPE = (256, 256)


def _flat_field(spec: SensorSpec, electrons: float, t: float, shape=SHAPE) -> np.ndarray:
    """Radiance giving every raw pixel (whatever its filter) the same mean electron count."""
    per_channel = electrons / (np.asarray(spec.sensitivity_rgb) * t)
    return np.broadcast_to(per_channel, shape + (3,)).astype(np.float64)


@pytest.mark.parametrize("electrons", [40.0, 400.0, 2500.0])   # exact Poisson and the Gaussian branch
def test_photon_transfer_variance(electrons):
    spec = SensorSpec(read_noise_e=0.0, dark_current_e_per_s=0.0, gain_e_per_dn=1.5)
    t = 0.01
    raw = expose(_flat_field(spec, electrons, t), t, spec, None, np.random.default_rng(1))
    dn = raw.astype(np.float64)
    mean, var = dn.mean(), dn.var()
    # reference: Poisson electrons -> mean = black + e/g, var = e/g^2 = (mean - black)/g; + 1/12 for rounding
    assert abs(mean - (spec.black_level + electrons / spec.gain_e_per_dn)) < 0.05 + 1e-3 * electrons
    expected_var = (mean - spec.black_level) / spec.gain_e_per_dn + 1.0 / 12.0
    assert abs(var / expected_var - 1) < 0.03, (var, expected_var)


def test_photon_transfer_with_read_noise_per_channel():
    spec = SensorSpec(read_noise_e=6.0, dark_current_e_per_s=0.0, gain_e_per_dn=2.0)
    t, e = 0.02, 900.0
    raw = expose(_flat_field(spec, e, t), t, spec, None, np.random.default_rng(2)).astype(np.float64)
    ch = bayer_channel_index(spec.bayer_pattern, SHAPE)
    for k in range(3):
        v = raw[ch == k]
        ref = (v.mean() - spec.black_level) / spec.gain_e_per_dn + (6.0 / 2.0) ** 2 + 1 / 12
        assert abs(v.var() / ref - 1) < 0.05, (k, v.var(), ref)


def test_mean_matches_expected_dn():
    spec = SensorSpec()
    rng = np.random.default_rng(3)
    rad = rng.uniform(0.0, 0.2, SHAPE + (3,))
    t = 0.05
    dmap = dark_current_map(spec, SHAPE, rng)
    raw = expose(rad, t, spec, dmap, rng).astype(np.float64)
    ref = expected_dn(rad, t, spec, dmap)
    assert abs((raw - ref).mean()) < 0.05
    # independent reference of the noise-free model
    ch = bayer_channel_index(spec.bayer_pattern, SHAPE)
    k = np.asarray(spec.sensitivity_rgb)[ch]
    lam = np.take_along_axis(rad, ch[..., None].astype(np.int64), axis=-1)[..., 0] * k * t + dmap * t
    np.testing.assert_allclose(ref, np.minimum(spec.black_level + np.minimum(lam, spec.full_well_e) / spec.gain_e_per_dn,
                                               spec.white_level))


def test_saturation_clips_at_white_level():
    spec = SensorSpec()
    rng = np.random.default_rng(4)
    # from dark to 5x full well
    rad = np.exp(rng.uniform(np.log(1e-4), np.log(5.0), SHAPE + (3,)))
    raw = expose(rad, 0.02, spec, None, rng)
    assert raw.dtype == np.uint16
    assert raw.max() == spec.white_level
    lam = expected_dn(rad, 0.02, spec, np.zeros(SHAPE))
    well_above = lam >= spec.white_level                       # noise-free at or beyond saturation
    deep = (expected_dn(rad / 1.2, 0.02, spec, np.zeros(SHAPE)) >= spec.white_level)   # >= 1.2x full well
    assert (raw[deep] == spec.white_level).all()                # saturated pixels read exactly white
    assert well_above.sum() > 1000 and (raw <= spec.white_level).all()
    # an ADC that clips first: 10 bits
    spec10 = SensorSpec(bit_depth=10, black_level=16)
    raw10 = expose(rad, 0.02, spec10, None, rng)
    assert raw10.max() == 1023 == spec10.white_level


@pytest.mark.parametrize("pattern", BAYER_PATTERNS)
def test_bayer_layouts(pattern):
    spec = SensorSpec(bayer_pattern=pattern, read_noise_e=0.0, dark_current_e_per_s=0.0)
    shape = (6, 8)
    names = "RGB"
    for k in range(3):
        rad = np.zeros(shape + (3,))
        rad[..., k] = 0.5
        raw = expose(rad, 0.005, spec, None, np.random.default_rng(k))
        lit = raw > spec.black_level + 20
        # reference: the pattern string read row-major over the 2x2 block
        ref = np.array([[pattern[2 * (i % 2) + (j % 2)] == names[k] for j in range(shape[1])]
                        for i in range(shape[0])])
        np.testing.assert_array_equal(lit, ref, err_msg=f"{pattern} channel {names[k]}")
    idx = bayer_channel_index(pattern, (3, 5))
    assert idx.dtype == np.int8 and idx.shape == (3, 5)
    assert "RGB"[idx[0, 0]] == pattern[0] and "RGB"[idx[1, 1]] == pattern[3]
    rgb = np.random.default_rng(0).random((2, 3, 5, 3))
    m = mosaic(rgb, pattern)
    assert m.shape == (2, 3, 5)
    np.testing.assert_array_equal(m, np.take_along_axis(rgb, np.broadcast_to(idx[..., None], (2, 3, 5, 1))
                                                        .astype(np.int64), -1)[..., 0])
    with pytest.raises(ValueError):
        bayer_channel_index("RGBG", (2, 2))


def test_dark_current_map():
    spec = SensorSpec(dark_current_e_per_s=5.0)
    a = dark_current_map(spec, SHAPE, np.random.default_rng(5))
    b = dark_current_map(spec, SHAPE, np.random.default_rng(5))
    np.testing.assert_array_equal(a, b)
    assert abs(a.mean() - 5.0) < 1e-9
    assert (a > 0).all()
    hot = a > 10 * np.median(a)
    assert 5 <= hot.sum() <= 200
    # lognormal body: log-spread close to the default sigma 0.4
    assert 0.3 < np.log(a[~hot]).std() < 0.5
    assert not np.array_equal(a, dark_current_map(spec, SHAPE, np.random.default_rng(6)))
    assert (dark_current_map(SensorSpec(dark_current_e_per_s=0.0), SHAPE, np.random.default_rng(5)) == 0).all()


def test_dark_frames_mean_and_read_noise():
    spec = SensorSpec()
    rng = np.random.default_rng(7)
    dmap = dark_current_map(spec, SHAPE, rng)
    times = np.array([1e-3, 1.0, 10.0])
    frames = dark_frames(spec, dmap, times, SHAPE, rng)
    assert frames.shape == (3,) + SHAPE and frames.dtype == np.uint16
    for k, t in enumerate(times):
        # black + D t / g, hot pixels clipped at the full well in the long exposure
        ref = spec.black_level + np.minimum(dmap * t, spec.full_well_e).mean() / spec.gain_e_per_dn
        assert abs(frames[k].mean() - ref) < 0.05, (t, frames[k].mean(), ref)
    # hot pixels show up in the long dark frame
    hot = dmap > 10 * np.median(dmap)
    assert frames[2][hot].mean() > frames[2][~hot].mean() + 50
    # read noise alone (no dark current): std = read_noise / gain (+ rounding)
    quiet = SensorSpec(dark_current_e_per_s=0.0, read_noise_e=3.0, gain_e_per_dn=1.5)
    f = dark_frames(quiet, None, [1e-3], SHAPE, rng).astype(np.float64)
    ref_std = np.sqrt((3.0 / 1.5) ** 2 + 1 / 12)
    assert abs(f.std() / ref_std - 1) < 0.03
    assert abs(f.mean() - quiet.black_level) < 0.03


def test_psf_preserves_the_mean_and_blurs():
    rng = np.random.default_rng(8)
    img = rng.random((2, 64, 80, 3)).astype(np.float32)
    out = apply_psf(img, 1.5)
    assert out.shape == img.shape and out.dtype == np.float32
    np.testing.assert_allclose(out.mean(axis=(1, 2)), img.mean(axis=(1, 2)), rtol=1e-5)
    assert out.std() < 0.5 * img.std()
    # a point spreads as a Gaussian of the given sigma, each colour plane on its own
    point = np.zeros((1, 41, 41, 3))
    point[0, 20, 20, 1] = 1.0
    p = apply_psf(point, 2.0)[0]
    assert p[..., 0].max() == 0 and p[..., 2].max() == 0
    r = np.arange(41) - 20
    var = (p[..., 1].sum(axis=0) * r**2).sum() / p[..., 1].sum()
    assert abs(np.sqrt(var) - 2.0) < 0.05
    # expose with the PSF: same mean signal, less pixel-to-pixel contrast
    spec = SensorSpec(psf_sigma_px=1.2, read_noise_e=0.0, dark_current_e_per_s=0.0)
    rad = rng.uniform(0.0, 0.1, (64, 64, 3))
    sharp = expected_dn(rad, 0.05, spec, psf=False)
    blurred = expected_dn(rad, 0.05, spec)
    assert abs(blurred.mean() / sharp.mean() - 1) < 0.01
    assert blurred.std() < 0.7 * sharp.std()
    noisy = expose(rad, 0.05, spec, None, rng).astype(np.float64)
    assert abs(noisy.mean() - blurred.mean()) < 0.2


def test_expose_broadcasting_and_determinism():
    spec = SensorSpec()
    rng = np.random.default_rng(9)
    rad = rng.uniform(0, 0.1, (3, 1, 16, 20, 3)).astype(np.float32)
    times = np.array([[1e-3, 1e-2], [2e-3, 2e-2], [3e-3, 3e-2]])
    a = expose(rad, times, spec, None, np.random.default_rng(10))
    b = expose(rad, times, spec, None, np.random.default_rng(10))
    c = expose(rad, times, spec, None, np.random.default_rng(11))
    assert a.shape == (3, 2, 16, 20)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    # the longer exposure of the same radiance is brighter
    assert (a[:, 1].mean(axis=(1, 2)) > a[:, 0].mean(axis=(1, 2))).all()
    with pytest.raises(ValueError):
        expose(rad, -1.0, spec, None, rng)
    with pytest.raises(ValueError):
        expose(rad * np.nan, 1.0, spec, None, rng)


def test_noise_free_frames_are_the_expected_values_exactly():
    spec = SensorSpec()
    rng = np.random.default_rng(12)
    rad = rng.uniform(0, 0.3, (2, 1, 16, 20, 3))
    times = np.array([[1e-2, 1e-1], [2e-2, 5.0]])                   # the last one saturates
    dark = dark_current_map(spec, (16, 20), rng)
    frames = expose(rad, times, spec, dark, None, model=SensorModel(noise=False))
    assert frames.dtype == np.float64 and frames.shape == (2, 2, 16, 20)
    np.testing.assert_array_equal(frames, expected_dn(rad, times, spec, dark))
    assert frames.max() == spec.white_level
    darks = dark_frames(spec, dark, [1e-2, 1.0], (16, 20), None, SensorModel(noise=False))
    np.testing.assert_array_equal(darks, expected_dn(np.zeros((2, 16, 20, 3)), np.array([1e-2, 1.0]), spec, dark))


def test_full_rgb_frames_measure_every_channel_at_every_pixel():
    spec = SensorSpec(bayer_pattern="GRBG")
    rng = np.random.default_rng(13)
    rad = rng.uniform(0, 0.03, (16, 20, 3))                          # below saturation
    full = expose(rad, 0.05, spec, None, None, model=SensorModel(noise=False, mosaic=False))
    bayer = expose(rad, 0.05, spec, None, None, model=SensorModel(noise=False))
    assert full.shape == (16, 20, 3)                                 # nothing to demosaic
    np.testing.assert_array_equal(mosaic(full, spec.bayer_pattern), bayer)
    np.testing.assert_allclose(full - spec.black_level,
                               rad * np.asarray(spec.sensitivity_rgb) * 0.05 / spec.gain_e_per_dn
                               + spec.dark_current_e_per_s * 0.05 / spec.gain_e_per_dn, rtol=1e-12)
    noisy = expose(rad, 0.05, spec, None, np.random.default_rng(1), model=SensorModel(mosaic=False))
    assert noisy.dtype == np.uint16 and noisy.shape == (16, 20, 3)
    # the mean over 960 noisy pixels
    assert abs(noisy.mean() - full.mean()) < 2.0 and not np.array_equal(noisy, np.rint(full))


def _hdr_image(rng, shape, dynamic_range):
    """Smooth-ish random HDR radiance spanning ``dynamic_range`` per pixel and channel."""
    base = rng.uniform(0, 1, shape + (3,))
    base[: shape[0] // 3] = np.sort(base[: shape[0] // 3], axis=1)      # some structure
    return 1e-3 * dynamic_range ** base


@pytest.mark.parametrize("n_exp", [3, 4, 5])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_bracket_exposes_every_masked_pixel_well(n_exp, seed):
    rng = np.random.default_rng(seed)
    spec = SensorSpec(n_exposures=n_exp, bayer_pattern=BAYER_PATTERNS[seed])
    rad = _hdr_image(rng, (48, 64), 1e4)
    mask = np.zeros((48, 64), bool)
    mask[4:44, 8:60] = True
    rad[~mask] *= 1e3                                 # outside the mask: ignored (would saturate)
    times, report = choose_bracket(rad, spec, mask=mask, return_report=True)
    assert times.shape == (n_exp,)
    assert (np.diff(times) > 0).all()
    ratio = times[1:] / times[:-1]
    assert (ratio >= 2.0 - 1e-9).all() and np.allclose(ratio, ratio[0])
    assert not report.capped and report.underexposed_fraction == 0
    dn = expected_dn(rad, times, spec, np.zeros((48, 64)))     # (n_exp, rows, cols), noise-free
    level = (dn - spec.black_level) / (spec.white_level - spec.black_level)
    lo, hi = WELL_EXPOSED
    well = ((level >= lo) & (level <= hi)).any(axis=0)
    assert well[mask].all()
    # the brightest masked pixel sits at 80 % in the shortest frame, the darkest reaches >= 5 % in the longest
    assert abs(level[0][mask].max() - 0.8) < 1e-6
    assert level[-1][mask].min() >= 0.05 - 1e-6


def test_bracket_small_range_uses_min_ratio_and_batches():
    spec = SensorSpec(n_exposures=3)
    rng = np.random.default_rng(12)
    flat = np.full((2, 16, 16, 3), 0.05)
    flat[1] *= 10
    flat += rng.uniform(0, 1e-3, flat.shape)
    times = choose_bracket(flat, spec)
    assert times.shape == (2, 3)
    np.testing.assert_allclose(times[:, 1] / times[:, 0], 2.0)
    np.testing.assert_allclose(times[0] / times[1], 10.0, rtol=0.05)
    for i in range(2):
        np.testing.assert_allclose(choose_bracket(flat[i], spec), times[i])


def test_bracket_too_wide_is_capped_and_reported():
    spec = SensorSpec(n_exposures=3)
    rng = np.random.default_rng(13)
    rad = _hdr_image(rng, (32, 32), 1e8)
    times, report = choose_bracket(rad, spec, return_report=True)
    assert report.capped
    np.testing.assert_allclose(times[1:] / times[:-1], WELL_EXPOSED[1] / WELL_EXPOSED[0])
    dn = expected_dn(rad, times, spec, np.zeros((32, 32)))
    level = (dn - spec.black_level) / (spec.white_level - spec.black_level)
    assert abs(level[0].max() - 0.8) < 1e-6                 # highlights are kept unclipped
    under = (level[-1] < WELL_EXPOSED[0]).mean()
    assert 0 < under < 1 and abs(report.underexposed_fraction - under) < 1e-12
    assert report.dynamic_range > 1e7


def test_bracket_without_signal():
    spec = SensorSpec(n_exposures=4)
    times, report = choose_bracket(np.zeros((8, 8, 3)), spec, return_report=True)
    assert np.isfinite(times).all() and (np.diff(times) > 0).all()
    assert times[-1] == pytest.approx(10.0)
    assert report.underexposed_fraction == 1.0


def test_bracket_respects_the_longest_exposure():
    spec = SensorSpec(n_exposures=4)
    rng = np.random.default_rng(14)
    # a dim frame (grazing light) with deep shadows: the unlimited rule would ask for hours
    rad = 1e-4 * 1e4 ** rng.uniform(0, 1, (32, 32, 3))
    rad[:8] *= 1e-6
    t_free, free = choose_bracket(rad, spec, max_time_s=1e9, return_report=True)
    assert t_free[-1] > 1e3 and not free.time_limited
    times, report = choose_bracket(rad, spec, return_report=True)
    assert report.time_limited and times[-1] == pytest.approx(10.0)
    assert (times[1:] / times[:-1] >= 2.0 - 1e-12).all()
    np.testing.assert_allclose(times[0], t_free[0])          # highlights still exposed at 80 %
    # so dark that even the brightest pixel needs more than the limit: t_n = limit, steps of 2
    times, report = choose_bracket(rad * 1e-4, spec, return_report=True)
    np.testing.assert_allclose(times, 10.0 * 2.0 ** np.arange(-3, 1))
    assert report.time_limited and report.underexposed_fraction > 0.2
