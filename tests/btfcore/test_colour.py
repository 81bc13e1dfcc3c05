"""Colour transforms: reference values from OpenCV and colour-science, thesis eq. (3) by hand, bad input."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from btfcore.model.colour import (
    cos_weight,
    from_log_yuv,
    log_luminance,
    nielsen_map,
    nielsen_unmap,
    reference_abrdf,
    rgb_to_yuv,
    to_log_yuv,
    yuv_to_rgb,
)


def assert_close_per_pixel(actual, desired, tol):
    """|actual - desired| <= tol * the largest |channel| of each pixel (rounding of a 3 x 3 transform)."""
    bound = tol * np.abs(desired).max(axis=-1, keepdims=True)
    assert actual.shape == desired.shape and (np.abs(actual - desired) <= bound).all()


@pytest.fixture
def rgb():
    """Seeded HDR RGB over five decades, shaped like a texture."""
    rng = np.random.default_rng(11)
    return rng.uniform(0.0, 1.0, (6, 7, 3)) * 10.0 ** rng.uniform(-3, 2, (6, 7, 1))


def test_yuv_matches_opencv_without_its_offset(rgb):
    x = rgb.astype(np.float32)
    ref = cv2.cvtColor(x, cv2.COLOR_RGB2YUV)
    ref[..., 1:] -= 0.5                                             # OpenCV adds 0.5 to U and V of float images
    np.testing.assert_allclose(rgb_to_yuv(x), ref, rtol=0, atol=2e-6 * np.abs(x).max())


def test_yuv_matches_colour_science_bt601(rgb):
    colour = pytest.importorskip("colour")
    ycbcr = colour.RGB_to_YCbCr(rgb, K=colour.WEIGHTS_YCBCR["ITU-R BT.601"], out_legal=False)
    # Cb = (B - Y) / (2 (1 - Kb)), Cr = (R - Y) / (2 (1 - Kr)); U = 0.492 (B - Y), V = 0.877 (R - Y)
    want = ycbcr * np.array([1.0, 0.492 * 2 * (1 - 0.114), 0.877 * 2 * (1 - 0.299)])
    np.testing.assert_allclose(rgb_to_yuv(rgb), want, rtol=1e-12, atol=1e-12 * np.abs(rgb).max())


def test_yuv_of_primaries_by_hand():
    yuv = rgb_to_yuv(np.eye(3))
    np.testing.assert_allclose(yuv[0], [0.299, -0.492 * 0.299, 0.877 * 0.701], rtol=1e-15)
    np.testing.assert_allclose(rgb_to_yuv([2.0, 2.0, 2.0]), [2.0, 0.0, 0.0], atol=1e-15)  # grey: no chroma


@pytest.mark.parametrize("dtype, tol", [(np.float32, 1e-6), (np.float64, 1e-14)])
def test_yuv_round_trip_keeps_the_dtype(rgb, dtype, tol):
    x = rgb.astype(dtype)
    back = yuv_to_rgb(rgb_to_yuv(x))
    assert rgb_to_yuv(x).dtype == back.dtype == dtype
    assert_close_per_pixel(back, x, tol)


def test_integer_input_becomes_float64():
    assert rgb_to_yuv(np.array([[1, 2, 3]], np.uint16)).dtype == np.float64


@pytest.mark.parametrize("dtype, tol", [(np.float32, 2e-6), (np.float64, 1e-13)])
def test_log_yuv_round_trip_is_exact_above_eps(rgb, dtype, tol):
    x = rgb.astype(dtype)
    eps = 1e-4
    assert (rgb_to_yuv(x)[..., 0] >= eps).all()
    t = to_log_yuv(x, eps)
    assert t.dtype == from_log_yuv(t).dtype == dtype
    assert_close_per_pixel(from_log_yuv(t), x, tol)


def test_log_yuv_by_hand():
    np.testing.assert_allclose(to_log_yuv([1.0, 1.0, 1.0]), [0.0, 0.0, 0.0], atol=1e-15)
    red = to_log_yuv([1.0, 0.0, 0.0])
    np.testing.assert_allclose(red, [math.log(0.299), -0.492, 0.877 * 0.701 / 0.299], rtol=1e-14)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_log_luminance_is_the_log_y_channel_of_log_yuv(rgb, dtype):
    x = np.concatenate([rgb, -rgb[:1]]).astype(dtype)        # a row below the floor too
    got = log_luminance(x, 1e-3)
    assert got.dtype == dtype and got.shape == x.shape[:-1]
    np.testing.assert_allclose(got, to_log_yuv(x, 1e-3)[..., 0], rtol=0, atol=4 * np.finfo(dtype).eps * 10)


def test_log_yuv_below_eps_adds_grey_and_keeps_chroma():
    eps = 1e-3
    rgb = np.array([[0.0, 0.0, 0.0], [1e-4, 0.0, 2e-4], [-0.01, 0.001, -0.005], [0.5, -0.4, 0.1]])
    y, u, v = np.moveaxis(rgb_to_yuv(rgb), -1, 0)
    assert (y < eps).all()
    t = to_log_yuv(rgb, eps)
    assert np.isfinite(t).all()
    np.testing.assert_allclose(t[:, 0], math.log(eps), rtol=1e-15)
    np.testing.assert_allclose(t[:, 1:], np.stack([u, v], -1) / eps, rtol=1e-12)
    np.testing.assert_allclose(from_log_yuv(t), rgb + (eps - y)[:, None], rtol=0, atol=1e-13)


def test_from_log_yuv_maps_any_log_y_to_positive_y():
    assert rgb_to_yuv(from_log_yuv([[-50.0, 0.1, -0.2]]))[0, 0] > 0


def test_cos_weight_by_hand():
    light = np.array([[0, 0, 1], [1, 0, 1], [1, 0, -0.2], [0, 3, 0]], float)
    view = np.array([[1, 0, 0], [1, 0, 0], [0, 1, -1], [0, 0, 2]], float)
    np.testing.assert_allclose(cos_weight(light, view), [1.0, math.sqrt(0.5), 1e-4, 1.0], rtol=1e-15)
    np.testing.assert_allclose(cos_weight(light[2:3], view[2:3], eps=0.05), [0.05])


def test_nielsen_eq3_by_hand():
    B = np.array([[0.5, 0.0, 2.0], [0.2, 1.0, 0.0]])
    cosw = np.array([0.5, 1e-4])
    ref = np.array([0.25, 0.2])
    want = [[math.log(0.2501 / 0.1251), math.log(0.0001 / 0.1251), math.log(1.0001 / 0.1251)],
            [math.log(0.00012 / 0.00012), math.log(0.0002 / 0.00012), math.log(0.0001 / 0.00012)]]
    np.testing.assert_allclose(nielsen_map(B, cosw, ref), want, rtol=1e-12)
    np.testing.assert_allclose(nielsen_unmap(nielsen_map(B, cosw, ref), cosw, ref), B, rtol=0, atol=1e-12)


def test_reference_abrdf_is_the_median_per_channel():
    # 3 texels x 2 channels: channel 0 holds 1, 5, 3 (median 3); channel 1 holds 10, 0, 40 (median 10)
    B = np.array([[1.0, 10.0, 5.0, 0.0, 3.0, 40.0], [2.0, 2.0, 2.0, 2.0, 2.0, 2.0]], np.float32)
    ref = reference_abrdf(B, n_channels=2)
    assert ref.dtype == np.float32
    np.testing.assert_array_equal(ref, [[3.0, 10.0], [2.0, 2.0]])
    np.testing.assert_array_equal(reference_abrdf(B), [[4.0], [2.0]])   # one channel: median of all 6 values


@pytest.mark.parametrize("dtype, tol", [(np.float32, 1e-5), (np.float64, 1e-12)])
def test_nielsen_channels_and_round_trip(dtype, tol):
    rng = np.random.default_rng(5)
    n_lv, n_tex = 9, 21                                          # odd: the median is a sample
    B = (rng.lognormal(-2, 2, (n_lv, n_tex * 3))).astype(dtype)
    cosw = cos_weight(rng.normal(size=(n_lv, 3)), rng.normal(size=(n_lv, 3)))
    ref = reference_abrdf(B, n_channels=3)
    X = nielsen_map(B, cosw, ref)
    assert X.dtype == dtype and X.shape == B.shape
    for c in range(3):                                              # column j uses channel j % 3
        np.testing.assert_allclose(X[:, c::3], nielsen_map(B[:, c::3], cosw, ref[:, c]), rtol=1e-6)
    np.testing.assert_allclose(np.median(X.reshape(n_lv, -1, 3), axis=1), 0.0, atol=10 * tol)  # median ABRDF -> 0
    scale = np.abs(B) + 1e-4 / cosw[:, None]
    np.testing.assert_array_less(np.abs(nielsen_unmap(X, cosw, ref) - B), 4 * tol * scale)


@pytest.mark.parametrize("call, match", [
    (lambda: rgb_to_yuv(np.ones((2, 4))), "3 channels on its last axis"),
    (lambda: rgb_to_yuv([[1, 2, 3], [4, np.nan, 6]]), r"rgb\[1, 1\] = nan is not finite \(1 NaN/Inf"),
    (lambda: yuv_to_rgb(np.full(3, np.inf)), r"yuv\[0\] = inf"),
    (lambda: rgb_to_yuv(np.array(["a", "b", "c"])), "real numbers"),
    (lambda: to_log_yuv([1, 1, 1], eps=0), "eps must be a finite number > 0"),
    (lambda: to_log_yuv([1, 1, 1], eps=-1e-3), "eps must be"),
    (lambda: from_log_yuv(np.array([[0, 0, 0], [100, 0, 0]], np.float32)), r"x\[1, 0\] = 100.0 is log Y >= 88.7"),
    (lambda: cos_weight(np.ones((3, 3)), np.ones((4, 3))), "same number of rows"),
    (lambda: cos_weight(np.ones((3, 2)), np.ones((3, 2))), r"light_dir must be \(n_lv, 3\)"),
    (lambda: cos_weight(np.ones((2, 3)), np.array([[0, 0, 1], [0, 0, 0]])), r"view_dir\[1\] has zero length"),
    (lambda: reference_abrdf(np.ones((2, 7)), n_channels=3), "must divide B's 7 columns"),
    (lambda: nielsen_map(np.ones((2, 6)), np.ones(3), np.ones(2)), r"cosw must be \(2,\)"),
    (lambda: nielsen_map(np.ones((2, 6)), np.array([1.0, 0.0]), np.ones(2)), r"cosw\[1\] = 0.0 must be > 0"),
    (lambda: nielsen_map(np.ones((2, 6)), np.ones(2), np.ones((2, 4))), "C dividing B's 6 columns"),
    (lambda: nielsen_map(np.array([[1.0, -0.5]]), np.ones(1), np.ones(1)), r"B\[0, 1\] = -0.5 .* clip B at 0"),
    (lambda: nielsen_map(np.ones((1, 2)), np.ones(1), -np.ones(1)), r"rho_ref\[0, 0\]"),
    (lambda: nielsen_map(np.array([[1.0, np.inf]]), np.ones(1), np.ones(1)), r"B\[0, 1\] = inf"),
    (lambda: nielsen_unmap(np.ones((1, 2)), np.ones(1), np.ones(1), eps=np.nan), "eps must be"),
])
def test_bad_input_is_refused_with_the_index(call, match):
    with pytest.raises(ValueError, match=match):
        call()
