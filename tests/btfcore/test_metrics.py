"""Error measures: hand values, loop reimplementations of SR eqs. (8)-(10), OpenCV's PSNR, bad input."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from btfcore.model.colour import to_log_yuv
from btfcore.metrics import mpsnr, mre, mrmse, psnr, relative_error, texture_errors


def _pair(shape, dtype=np.float64, seed=0):
    rng = np.random.default_rng(seed)
    B = rng.lognormal(-1, 1, shape).astype(dtype)
    return B, (B * (1 + 0.1 * rng.standard_normal(shape))).astype(dtype)


def test_hand_values():
    B = np.array([[3.0, 4.0], [1.0, 0.0]])                            # 2 textures of 2 texels
    B_hat = np.array([[3.0, 0.0], [1.0, 1.0]])
    assert relative_error(B, B_hat) == pytest.approx(math.sqrt(17) / math.sqrt(26))
    assert mrmse(B, B_hat) == pytest.approx((4 / math.sqrt(2) + 1 / math.sqrt(2)) / 2)
    assert mre(B, B_hat) == pytest.approx((4 / 5 * 100 + 1 / 1 * 100) / 2)
    want = (20 * math.log10(4 / (4 / math.sqrt(2))) + 20 * math.log10(1 / (1 / math.sqrt(2)))) / 2
    assert mpsnr(B, B_hat) == pytest.approx(want)
    assert psnr(np.array([0.0, 2.0]), np.array([1.0, 2.0])) == pytest.approx(10 * math.log10(4 / 0.5))
    assert psnr(np.array([0.0, 2.0]), np.array([1.0, 2.0]), peak=1.0) == pytest.approx(10 * math.log10(2))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("shape", [(6, 5, 4), (6, 5, 4, 3), (6, 20)])
def test_against_loops_of_eqs_8_to_10(shape, dtype):
    B, B_hat = _pair(shape, dtype)
    n = shape[0]
    wh = shape[1] * shape[2] if len(shape) >= 3 else shape[1]
    rmse, ps, re = [], [], []
    for i in range(n):                                               # SR paper, eqs. (8)-(10), row by row
        d = [float(a) - float(b) for a, b in zip(B[i].ravel(), B_hat[i].ravel())]
        e = math.sqrt(sum(x * x for x in d))
        r = math.sqrt(sum(float(x) ** 2 for x in B[i].ravel()))
        rmse.append(e / math.sqrt(wh))
        ps.append(20 * math.log10(float(B[i].max()) / (e / math.sqrt(wh))))
        re.append(e / r * 100)
    assert mrmse(B, B_hat) == pytest.approx(sum(rmse) / n, rel=1e-12)
    assert mpsnr(B, B_hat) == pytest.approx(sum(ps) / n, rel=1e-12)
    assert mre(B, B_hat) == pytest.approx(sum(re) / n, rel=1e-12)
    np.testing.assert_allclose(mre(B, B_hat, per_texture=True), re, rtol=1e-12)
    err, ref = texture_errors(B, B_hat)
    assert err.shape == ref.shape == (n,)


def test_n_texels_for_flattened_channels():
    B, B_hat = _pair((4, 5, 6, 3))
    flat, flat_hat = B.reshape(4, -1), B_hat.reshape(4, -1)
    assert mrmse(flat, flat_hat, n_texels=30) == pytest.approx(mrmse(B, B_hat), rel=1e-14)
    assert mpsnr(flat, flat_hat, n_texels=30) == pytest.approx(mpsnr(B, B_hat), rel=1e-14)
    # literal eq. (8): the norm over 3 channels / sqrt(texels) is sqrt(3) x the RMSE per value
    assert mrmse(B, B_hat) == pytest.approx(math.sqrt(3) * mrmse(flat, flat_hat), rel=1e-12)


def test_relative_error_on_log_y():
    B, B_hat = _pair((5, 8, 3))
    y, y_hat = to_log_yuv(B)[..., 0], to_log_yuv(B_hat)[..., 0]
    want = np.linalg.norm(y_hat - y) / np.linalg.norm(y)
    assert relative_error(B, B_hat, space="log_y") == pytest.approx(want, rel=1e-12)
    assert relative_error(B, B) == 0.0


@pytest.mark.parametrize("peak", [None, 255.0])
def test_psnr_matches_opencv(peak):
    rng = np.random.default_rng(3)
    a = rng.integers(0, 256, (32, 24, 3)).astype(np.uint8)
    b = np.clip(a.astype(int) + rng.integers(-9, 10, a.shape), 0, 255).astype(np.uint8)
    R = float(a.max()) if peak is None else peak
    assert psnr(a, b, peak) == pytest.approx(cv2.PSNR(a, b, R), rel=1e-12)
    fa, fb = a.astype(np.float64) / 255, b.astype(np.float64) / 255
    assert psnr(fa, fb, 1.0) == pytest.approx(cv2.PSNR(fa, fb, 1.0), rel=1e-12)
    assert psnr(a, a) == math.inf


def test_exact_reconstruction():
    B, _ = _pair((3, 4, 4))
    assert mrmse(B, B) == 0.0 and mre(B, B) == 0.0
    assert mpsnr(B, B) == math.inf


def test_errors():
    B, B_hat = _pair((3, 4, 4))
    with pytest.raises(ValueError, match="must match"):
        mrmse(B, B_hat[:2])
    bad = B_hat.copy()
    bad[1, 2, 3] = np.nan
    with pytest.raises(ValueError, match=r"B_hat\[1, 2, 3\]"):
        mre(B, bad)
    Z = B.copy()
    Z[2] = 0.0
    with pytest.raises(ValueError, match="texture 2 of B is all zero"):
        mre(Z, B_hat)
    with pytest.raises(ValueError, match=r"texture 2 of B has maximum 0.0"):
        mpsnr(Z, B_hat)
    with pytest.raises(ValueError, match="space must be"):
        relative_error(B, B_hat, space="log")
    with pytest.raises(ValueError, match="undefined"):
        relative_error(np.zeros(3), np.ones(3))
    with pytest.raises(ValueError, match="peak"):
        psnr(-B, B_hat)
