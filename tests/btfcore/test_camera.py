"""Projection of textures into the ROI: positions, rectification round trip, foreshortening, anti-aliasing."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy import ndimage

from btfcore.simulate.camera import holder_radiance, render_frame, sample_corners_px, sample_mask
from btfcore.dome import get_device


def _checker(n_tex: int, squares: int, lo=0.2, hi=1.0) -> np.ndarray:
    i = np.arange(n_tex) * squares // n_tex
    board = np.where((i[:, None] + i[None, :]) % 2 == 0, hi, lo)
    return np.repeat(board[..., None], 3, axis=-1).astype(np.float32)


def _project(device, t, c, xy):
    """Reference pinhole projection K (R Rz(a) X + t) of sample-plane points (n, 2) -> (col, row)."""
    a = np.deg2rad(device.turntable_angle_deg[t])
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    X = np.c_[xy, np.zeros(len(xy))] @ Rz.T
    q = (X @ device.camera_R[c].T + device.camera_t[c]) @ device.camera_K[c].T
    return q[:, :2] / q[:, 2:]


def _smooth_texture(rng, n, sigma):
    tex = ndimage.gaussian_filter(rng.random((n, n, 3)), sigma=(sigma, sigma, 0), mode="wrap")
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    return (0.05 + tex).astype(np.float32)


def _texture_to_roi(device, t, c, shape):
    """Homography of texture pixels (col, row) of an (h, w) grid -> ROI pixels."""
    h, w = shape
    s = device.sample_size_m
    T = np.array([[s / w, 0, -s / 2 + s / (2 * w)], [0, -s / h, s / 2 - s / (2 * h)], [0, 0, 1]])
    return device.homography(t, c) @ T


def _psnr(a, b):
    return 10 * np.log10(max(a.max(), b.max()) ** 2 / np.mean((a - b) ** 2))


@pytest.mark.parametrize("t", [0, 1])
def test_frontal_checkerboard_lands_where_the_homography_puts_it(t):
    d = get_device("tiny")
    squares, n2 = 8, 64                                   # 2x texture of tiny is 64x64
    tex = _checker(n2, squares)
    bg = np.array([[0.03, 0.04, 0.05]], dtype=np.float32)
    frame = render_frame(tex[None], bg, d.homography(t, 0), d.roi_shape, d.sample_size_m)[0]
    assert frame.shape == d.roi_shape + (3,) and frame.dtype == np.float32
    s = d.sample_size_m
    # centres of every checker square, in sample-plane metres (row 0 = +y)
    k = (np.arange(squares) + 0.5) / squares
    xs, ys = np.meshgrid((k - 0.5) * s, (0.5 - k) * s)
    value = np.where((np.arange(squares)[:, None] + np.arange(squares)[None, :]) % 2 == 0, 1.0, 0.2)
    px = np.rint(_project(d, t, 0, np.c_[xs.ravel(), ys.ravel()])).astype(int)
    got = frame[px[:, 1], px[:, 0], 0]
    np.testing.assert_allclose(got, value.ravel(), atol=1e-5)
    # outside the sample: the holder
    np.testing.assert_allclose(frame[0, 0], bg[0], atol=1e-7)
    np.testing.assert_allclose(frame[-1, -1], bg[0], atol=1e-7)
    # frontal: the sample's +x axis points down the image, +y to the right
    o = _project(d, 0, 0, np.array([[0.0, 0.0], [0.01, 0.0], [0.0, 0.01]]))
    assert o[1, 1] > o[0, 1] + 5 and abs(o[1, 0] - o[0, 0]) < 1e-6
    assert o[2, 0] > o[0, 0] + 5


def test_rectification_round_trip():
    d = get_device("bonn-dome2")
    h, w = d.texture_shape
    rng = np.random.default_rng(0)
    tex2 = _smooth_texture(rng, 2 * h, sigma=4.0)
    truth = tex2.reshape(h, 2, w, 2, 3).mean(axis=(1, 3))         # ground truth at 1x
    bg = np.full((1, 3), 0.02, np.float32)
    psnr = {}
    for c in (0, 5, 10):                                           # theta 0, 37.5, 75 deg
        frame = render_frame(tex2[None], bg, d.homography(1, c), d.roi_shape, d.sample_size_m)[0]
        M = np.linalg.inv(_texture_to_roi(d, 1, c, (h, w)))        # ROI -> texture grid
        back = cv2.warpPerspective(frame, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        inner = (slice(2, -2), slice(2, -2))
        psnr[c] = _psnr(back[inner], truth[inner])
    print("rectification PSNR (dB) at theta 0 / 37.5 / 75:", {k: round(v, 1) for k, v in psnr.items()})
    assert psnr[0] > 30
    assert psnr[5] > 30
    assert psnr[10] > 20          # grazing: 128 texel rows from ~55 pixel rows


def test_foreshortening_and_area_antialiasing_at_grazing_view():
    d = get_device("tiny")
    ones = np.ones((1, 64, 64, 3), np.float32)
    zero_bg = np.zeros((1, 3), np.float32)
    for c, theta in ((0, 0.0), (3, 75.0)):
        frame = render_frame(ones, zero_bg, d.homography(0, c), d.roi_shape, d.sample_size_m, supersample=5)[0, ..., 0]
        corners = sample_corners_px(d.homography(0, c), d.sample_size_m)
        np.testing.assert_allclose(corners, _project(d, 0, c, corners * 0 + np.array(
            [[-1, -1], [1, -1], [1, 1], [-1, 1]]) * d.sample_size_m / 2))
        x, y = corners[:, 0], corners[:, 1]
        area = 0.5 * abs(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1)))      # shoelace
        # coverage integrates to the polygon's area (edges resolved by 5x5 sub-pixels)
        assert abs(frame.sum() - area) < 0.01 * area + 0.5, (frame.sum(), area)
        rows = np.flatnonzero(frame.max(axis=1) > 0.5)
        cols = np.flatnonzero(frame.max(axis=0) > 0.5)
        ratio = (np.ptp(rows) + 1) / (np.ptp(cols) + 1)
        assert abs(ratio - np.cos(np.deg2rad(theta))) < 0.06, (theta, ratio)
        # partially covered edge pixels lie strictly between holder and sample (the frontal
        # square's edges fall exactly on pixel borders: no partial pixels there)
        partial = (frame > 0.02) & (frame < 0.98)
        assert (partial.sum() > 20) == (theta > 0), partial.sum()
    # foreshortened quad at 75 deg: ~48 px wide, ~12 px high
    assert 10 <= np.ptp(rows) + 1 <= 15 and 46 <= np.ptp(cols) + 1 <= 52


def test_sample_mask_matches_polygon_test():
    d = get_device("tiny")
    for t, c in ((0, 0), (1, 2), (2, 3)):
        mask = sample_mask(d, t, c)
        poly = sample_corners_px(d.homography(t, c), d.sample_size_m).astype(np.float32)
        rows, cols = d.roi_shape
        ref = np.array([[cv2.pointPolygonTest(poly, (float(j), float(i)), True) for j in range(cols)]
                        for i in range(rows)])
        sure = np.abs(ref) > 1e-3
        np.testing.assert_array_equal(mask[sure], ref[sure] > 0)
        assert mask.sum() > 50


def test_vectorised_over_illuminations_and_out_buffer():
    d = get_device("tiny")
    rng = np.random.default_rng(1)
    tex = rng.random((5, 64, 64, 3)).astype(np.float32)
    bg = rng.random((5, 3)).astype(np.float32)
    H = d.homography(2, 1)
    frames = render_frame(tex, bg, H, d.roi_shape, d.sample_size_m)
    assert frames.shape == (5,) + d.roi_shape + (3,)
    for i in (0, 4):
        np.testing.assert_array_equal(frames[i], render_frame(tex[i:i + 1], bg[i:i + 1], H, d.roi_shape,
                                                              d.sample_size_m)[0])
    buf = np.full_like(frames, np.nan)
    out = render_frame(tex.astype(np.float64), bg, H, d.roi_shape, d.sample_size_m, out=buf)
    assert out is buf
    np.testing.assert_allclose(buf, frames, atol=1e-6)
    # linear in the texture: light superposes
    both = render_frame(tex[:2].sum(0, keepdims=True), bg[:2].sum(0, keepdims=True), H, d.roi_shape, d.sample_size_m)
    np.testing.assert_allclose(both[0], frames[0] + frames[1], rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError):
        render_frame(tex, bg[:2], H, d.roi_shape, d.sample_size_m)


def test_holder_radiance():
    L = np.array([[0, 0, 1.0], [np.sin(1.0), 0, np.cos(1.0)], [1.0, 0, 0], [0, 0.6, -0.8]])
    np.testing.assert_allclose(holder_radiance(L), 0.1 / np.pi * np.array([1, np.cos(1.0), 0, 0]))
    np.testing.assert_allclose(holder_radiance(L, albedo=0.5)[0], 0.5 / np.pi)
