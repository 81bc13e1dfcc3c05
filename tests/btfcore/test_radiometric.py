"""Radiometric correction: LED gains from a white standard and the camera colour matrix (thesis §1.1.3)."""

from __future__ import annotations

import numpy as np
import pytest

from btfcore.capture.radiometric import (
    WHITE_TOLERANCES,
    apply_colour_matrix,
    apply_led_calibration,
    fit_colour_matrix,
    led_calibration,
    white_standard_problems,
    white_standard_statistics,
    white_texture_statistics,
)
from btfcore.dome import get_device
from btfcore.simulate.materials import MATERIAL_CLASSES, make_material, white_standard
from btfcore.simulate.render import horizon_map, render_view

SHAPE = (16, 16)


@pytest.fixture(scope="module")
def tiny():
    return get_device("tiny", texture_shape=SHAPE)


def _capture(maps, device, views, horizon=None):
    """Single-LED radiance of some (turntable, camera) views as the dome measures it: truth x LED gain.

    Returns truth and measured as (n_leds, n_views, H, W, 3).
    """
    truth = np.stack([render_view(maps, device.view_dir(t, c), device.light_dirs(t), horizon)
                      for t, c in views], axis=1)
    measured = truth * device.led_rgb_gain[:, None, None, None, :].astype(np.float32)
    return truth, measured


VIEWS = [(0, 0), (1, 1), (2, 2), (0, 3)]


def test_white_standard_recovers_the_led_gains_noise_free(tiny):
    _, white = _capture(white_standard(SHAPE), tiny, VIEWS)
    gain = led_calibration(white, tiny.light_dirs(1), albedo=0.99)
    assert gain.shape == (tiny.n_leds, 3) and gain.dtype == np.float64
    rel = np.abs(gain / tiny.led_rgb_gain - 1)
    assert rel.max() < 0.005
    assert rel.max() < 1e-5                                    # in fact exact to float32 rounding
    # the gains really vary (the test is not trivially passed by ones)
    assert np.ptp(tiny.led_rgb_gain) > 0.05


def test_white_standard_calibration_is_robust_to_noise_and_specks(tiny):
    _, white = _capture(white_standard(SHAPE), tiny, VIEWS)
    rng = np.random.default_rng(8)
    noisy = white * (1 + 0.02 * rng.standard_normal(white.shape))
    specks = rng.random(white.shape[:-1]) < 0.05               # 5% dust / hot pixels, all channels
    noisy[specks] *= rng.choice([0.0, 20.0], size=(int(specks.sum()), 1))
    gain = led_calibration(noisy, tiny.light_dirs(0))
    assert np.abs(gain / tiny.led_rgb_gain - 1).max() < 0.005
    # a mask that leaves out the specky border
    mask = np.zeros(white.shape[1:-1], bool)
    mask[:, 2:-2, 2:-2] = True
    gain_m = led_calibration(noisy, tiny.light_dirs(0), mask=mask)
    assert np.abs(gain_m / tiny.led_rgb_gain - 1).max() < 0.005


def test_material_radiance_corrected_back_to_the_truth(tiny, sources):
    _, white = _capture(white_standard(SHAPE), tiny, VIEWS)
    gain = led_calibration(white, tiny.light_dirs(0))
    maps = make_material("leather", 3, SHAPE, sources)
    truth, measured = _capture(maps, tiny, VIEWS, horizon_map(maps.height))
    assert np.abs(measured / np.maximum(truth, 1e-12) - 1)[truth > 1e-6].max() > 0.05   # uncorrected is off
    corrected = apply_led_calibration(measured, gain)
    assert corrected.dtype == np.float32 and corrected.shape == truth.shape
    rel = np.linalg.norm(corrected - truth) / np.linalg.norm(truth)
    assert rel < 0.005
    lit = truth > 1e-4
    assert np.abs(corrected[lit] / truth[lit] - 1).max() < 1e-4
    # in place
    buf = measured.copy()
    out = apply_led_calibration(buf, gain, out=buf)
    assert out is buf
    np.testing.assert_array_equal(buf, corrected)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_colour_matrix(dtype):
    rng = np.random.default_rng(9)
    rgb = rng.uniform(size=(5, 4, 3)).astype(dtype)
    np.testing.assert_array_equal(apply_colour_matrix(rgb, np.eye(3)), rgb)
    M = np.array([[1.6, -0.4, -0.2], [-0.3, 1.5, -0.2], [0.0, -0.5, 1.5]])
    out = apply_colour_matrix(rgb, M)
    assert out.dtype == dtype and out.shape == rgb.shape
    np.testing.assert_allclose(out, np.einsum("ij,...j->...i", M, rgb.astype(np.float64)),
                               rtol=1e-6 if dtype == np.float32 else 1e-14)
    np.testing.assert_allclose(apply_colour_matrix(out, np.linalg.inv(M)), rgb, atol=1e-5)
    A = np.concatenate([M, [[0.01], [-0.02], [0.03]]], axis=1)
    np.testing.assert_allclose(apply_colour_matrix(rgb, A) - out, np.broadcast_to([0.01, -0.02, 0.03], out.shape),
                               atol=1e-6)


@pytest.mark.parametrize("affine", [False, True])
def test_fit_colour_matrix_recovers_a_known_matrix(affine):
    rng = np.random.default_rng(10)
    M = np.array([[1.6, -0.4, -0.2], [-0.3, 1.5, -0.2], [0.0, -0.5, 1.5]])
    if affine:
        M = np.concatenate([M, [[0.01], [-0.02], [0.03]]], axis=1)
    camera = rng.uniform(0.02, 0.9, size=(24, 3))             # 24 ColorChecker-like patches
    reference = apply_colour_matrix(camera, M)
    fitted = fit_colour_matrix(camera, reference, affine=affine)
    np.testing.assert_allclose(fitted, M, atol=1e-12)
    with pytest.raises(ValueError, match="rank 1"):
        fit_colour_matrix(np.ones((5, 3)), np.ones((5, 3)))


def test_bad_input(tiny):
    _, white = _capture(white_standard(SHAPE), tiny, VIEWS[:1])
    dirs = tiny.light_dirs(0)
    bad = white.copy()
    bad[3, 0, 5, 6, 1] = np.nan
    with pytest.raises(ValueError, match=r"white\[3, 0, 5, 6, 1\]"):
        led_calibration(bad, dirs)
    low = dirs.copy()
    low[4] = [1.0, 0.0, 0.0]
    with pytest.raises(ValueError, match="LED 4 is at or below the horizon"):
        led_calibration(white, low)
    dead = white.copy()
    dead[7] = 0.0
    with pytest.raises(ValueError, match="LED 7 channel 0 has gain 0"):
        led_calibration(dead, dirs)
    with pytest.raises(ValueError, match=r"light_dirs must be \(16, 3\)"):
        led_calibration(white, dirs[:15])
    with pytest.raises(ValueError, match="mask selects no texel"):
        led_calibration(white, dirs, mask=np.zeros(white.shape[1:-1], bool))
    gain = np.ones((16, 3))
    gain[2, 1] = np.inf
    with pytest.raises(ValueError, match=r"gain\[2, 1\]"):
        apply_led_calibration(white, gain)
    gain[2, 1] = -1.0
    with pytest.raises(ValueError, match=r"gain\[2, 1\] = -1.0 must be > 0"):
        apply_led_calibration(white, gain)
    with pytest.raises(ValueError, match=r"gain must be \(n_leds, C\)"):
        apply_led_calibration(white, np.ones((15, 3)))
    M = np.eye(3)
    M[1, 2] = np.nan
    with pytest.raises(ValueError, match=r"matrix\[1, 2\]"):
        apply_colour_matrix(np.ones((2, 3)), M)
    with pytest.raises(ValueError, match=r"\(3, 3\) or \(3, 4\)"):
        apply_colour_matrix(np.ones((2, 3)), np.eye(4))
    with pytest.raises(ValueError, match="3 channels"):
        apply_colour_matrix(np.ones((2, 4)), np.eye(3))


# --------------------------------------------------------------------------- is it a white standard? (issue 13)

ALL_VIEWS = [(t, c) for t in range(3) for c in range(4)]


def _white_stats(measured):
    """The white-standard statistics of (n_leds, n_views, H, W, 3), one view at a time as the store is read."""
    per_view = [white_texture_statistics(measured[:, v]) for v in range(measured.shape[1])]
    return white_standard_statistics(*(np.array(z) for z in zip(*per_view)))


def test_a_real_domes_white_standard_passes_the_check(tiny):
    """LED colours, per-camera colours, a +-8 % near-field fall-off, noise, specks and invalid texels are
    what a real white standard shows: none of them fails it."""
    _, white = _capture(white_standard(SHAPE), tiny, ALL_VIEWS)
    assert white_standard_problems(_white_stats(white)) == []
    rng = np.random.default_rng(3)
    v, u = np.mgrid[-1:1:16j, -1:1:16j]
    fall_off = (1 + 0.08 * (0.6 * u + 0.8 * v))[None, None, :, :, None]
    camera = np.exp(rng.normal(0, 0.05, (1, len(ALL_VIEWS), 1, 1, 3)))
    real = white * fall_off * camera * (1 + 0.01 * rng.standard_normal(white.shape))
    real[rng.random(real.shape[:-1]) < 0.01] *= 20.0                 # specks
    real[:, :, 5, 7] = np.nan                                       # an invalid texel in every texture
    real[2, 0] = np.nan                                             # and a whole invalid texture
    stats = _white_stats(real)
    assert white_standard_problems(stats) == [], stats
    for name, value in stats.items():                               # with a margin
        assert value < WHITE_TOLERANCES[name] / 2, (name, value)


@pytest.mark.parametrize("cls", MATERIAL_CLASSES)
def test_a_material_is_not_a_white_standard(tiny, sources, cls):
    maps = make_material(cls, 3, SHAPE, sources)
    _, measured = _capture(maps, tiny, ALL_VIEWS, horizon_map(maps.height))
    problems = white_standard_problems(_white_stats(measured))
    assert "brightness_spread" in [p[0] for p in problems], problems
    name, value, tol = next(p for p in problems if p[0] == "brightness_spread")
    assert value > 2 * tol and tol == WHITE_TOLERANCES[name]


def test_white_statistics_of_invalid_textures():
    """A texture without a valid texel (or black) is no white standard: inf, which fails; the colour
    statistic is not fooled by a coloured target under one LED colour."""
    white = np.ones((4, 8, 8, 3), np.float32)
    white[1] = np.nan
    white[2] = 0.0
    spread, chroma_spread, chromaticity = white_texture_statistics(white)
    np.testing.assert_array_equal(spread, [0, np.inf, np.inf, 0])
    np.testing.assert_array_equal(chroma_spread, [0, np.inf, np.inf, 0])
    np.testing.assert_allclose(chromaticity[[0, 3]], 1 / 3)
    stats = white_standard_statistics(spread[None], chroma_spread[None], chromaticity[None])
    assert [p[0] for p in white_standard_problems(stats)] == ["brightness_spread", "chromaticity_spread"]
    nothing = white_standard_statistics(np.full((1, 2), np.inf), np.full((1, 2), np.inf), np.full((1, 2, 3), np.nan))
    assert len(white_standard_problems(nothing)) == 3
    # two colours side by side under every LED: flat in brightness, not in colour
    patches = np.ones((4, 8, 8, 3), np.float32)
    patches[:, :, :4] = [1.5, 1.0, 0.5]
    spread, chroma_spread, _ = white_texture_statistics(patches)
    assert (chroma_spread > 0.5).all()
    with pytest.raises(ValueError, match=r"white must be \(n_leds, h, w, C\)"):
        white_texture_statistics(white[0])
