"""Rectification (issue 3, item 5): homography conventions, operators, and the checker-target bars.

Bars: registration error on a simulated checker target < 0.1 texel; PSNR against
the ground-truth texture reported per view elevation (run with ``-s`` to see
the tables, copied to docs/demosaic-rectify.md); the anti-aliased method beats
plain bilinear at the 75-degree view.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy import ndimage

from btfcore.capture.rectify import (
    RECTIFY_METHODS,
    apply_rectification,
    auto_supersample,
    box_widths,
    check_sample_in_frame,
    rectification_matrix,
    rectify,
    registration_error,
    support_window,
    texel_to_sample,
    texture_homography,
)
from btfcore.simulate.camera import render_frame, sample_corners_px
from btfcore.dome import get_device

S_M = 0.05
BACKGROUND = np.full((1, 3), 0.01, dtype=np.float32)


# ----------------------------------------------------------------------------- targets


def checker(n: int, square: int, smooth: float = 0.0) -> np.ndarray:
    """(n, n, 3) float32 checker of ``square``-texel squares; optionally Gaussian-smoothed edges."""
    k = np.arange(n) // square
    c = ((k[:, None] + k[None, :]) % 2).astype(np.float64)
    if smooth > 0:
        c = ndimage.gaussian_filter(c, smooth, mode="wrap")
    t = 0.05 + 0.75 * c
    return np.stack([t, 0.7 * t + 0.02, 0.5 * t + 0.05], axis=-1).astype(np.float32)


def fine_texture(n: int, seed: int = 0) -> np.ndarray:
    """(n, n, 3) float32 texture with detail down to its own texel (lightly smoothed white noise)."""
    rng = np.random.default_rng(seed)
    x = ndimage.gaussian_filter(rng.standard_normal((n, n, 3)), (1.0, 1.0, 0), mode="wrap")
    x = (x - x.min()) / (x.max() - x.min())
    return (0.05 + 0.75 * x).astype(np.float32)


def box_down(t: np.ndarray, k: int) -> np.ndarray:
    """Texel-area mean of a k-times finer texture (the ground truth at texture resolution)."""
    h, w = t.shape[0] // k, t.shape[1] // k
    return t.reshape(h, k, w, k, -1).mean(axis=(1, 3))


def psnr(a: np.ndarray, ref: np.ndarray) -> float:
    return float(10 * np.log10(ref.max() ** 2 / np.mean((np.asarray(a, np.float64) - ref) ** 2)))


def elevation_deg(device, t: int, c: int) -> float:
    return float(np.degrees(np.arccos(np.clip(device.view_dir(t, c)[2], -1, 1))))


def shift_h(H: np.ndarray, device, delta_texels) -> np.ndarray:
    """H of the sample displaced by ``delta`` = (dj, di) texels on the turntable."""
    h, w = device.texture_shape
    T = np.eye(3)
    T[0, 2] = delta_texels[0] * device.sample_size_m / w
    T[1, 2] = -delta_texels[1] * device.sample_size_m / h
    return H @ T


DEVICES = {
    "tiny": lambda: get_device("tiny"),
    "bonn-dome2": lambda: get_device("bonn-dome2", texture_shape=(64, 64), turntable_angle_deg=[0.0, 30.0, 120.0]),
}


def _tiles(device) -> int:
    return max(1, device.texture_shape[0] // 32)          # 32-texel tiles (a multiple of the checker period)


# ----------------------------------------------------------------------------- conventions


def test_texel_to_sample_matches_the_device_convention():
    h, w = 4, 6
    T = texel_to_sample((h, w), S_M)
    i, j = np.mgrid[0:h, 0:w]
    xy = np.einsum("ab,bhw->ahw", T, np.stack([j, i, np.ones_like(i)]).astype(float))
    np.testing.assert_allclose(xy[0], ((j + 0.5) / w - 0.5) * S_M, atol=1e-15)
    np.testing.assert_allclose(xy[1], (0.5 - (i + 0.5) / h) * S_M, atol=1e-15)
    assert xy[1, 0, 0] > 0                                  # row 0 is +y


def test_texture_homography_maps_texel_centres_and_corners_like_device_projection():
    d = get_device("tiny")
    h, w = d.texture_shape
    for t, c in [(0, 0), (1, 2), (2, 3)]:
        G = texture_homography(d.homography(t, c), (h, w), d.sample_size_m)
        j = np.array([0.0, w - 1, 3.0, -0.5, w - 0.5])
        i = np.array([0.0, h - 1, 7.0, -0.5, h - 0.5])
        q = G @ np.stack([j, i, np.ones_like(j)])
        px = (q[:2] / q[2]).T
        x = ((j + 0.5) / w - 0.5) * d.sample_size_m
        y = (0.5 - (i + 0.5) / h) * d.sample_size_m
        expect = d.project(np.stack([x, y, np.zeros_like(x)], axis=1), t, c)
        np.testing.assert_allclose(px, expect, atol=1e-9)
    # the texture's outer corners are the sample's corners
    G = texture_homography(d.homography(0, 1), (h, w), d.sample_size_m)
    q = G @ np.array([[-0.5, w - 0.5, w - 0.5, -0.5], [h - 0.5, h - 0.5, -0.5, -0.5], [1, 1, 1, 1]])
    np.testing.assert_allclose((q[:2] / q[2]).T, sample_corners_px(d.homography(0, 1), d.sample_size_m), atol=1e-9)


# ----------------------------------------------------------------------------- bad input


def _frontal_h(px_per_m: float = 2000.0, centre=(50.0, 50.0)) -> np.ndarray:
    return np.array([[px_per_m, 0, centre[0]], [0, -px_per_m, centre[1]], [0, 0, 1.0]])


def test_sample_outside_the_frame_is_refused_with_the_distance():
    H = _frontal_h(centre=(40.0, 50.0))                     # sample spans cols -10..90 of a 101-px frame
    with pytest.raises(ValueError, match=r"outside the 101x101 image by up to 9\.50 px.*left of the frame"):
        check_sample_in_frame(H, (101, 101), S_M)
    for method in RECTIFY_METHODS:
        with pytest.raises(ValueError, match="9.50 px left"):
            rectify(np.zeros((101, 101)), H, (8, 8), S_M, method=method)
    check_sample_in_frame(_frontal_h(), (101, 101), S_M)    # exactly fits: corners at -0.5 and 100.5


def test_sample_behind_the_camera_is_refused():
    H = _frontal_h()
    H[2] = [60.0, 0.0, 1.0]                                 # w changes sign across the sample
    with pytest.raises(ValueError, match="not entirely in front of the camera"):
        check_sample_in_frame(H, (101, 101), S_M)


@pytest.mark.parametrize("bad, match", [
    (dict(method="nearest"), "valid methods: supersample, area, bilinear"),
    (dict(texture_shape=(0, 4)), "texture_shape must be positive"),
    (dict(sample_size_m=-1.0), "sample_size_m must be finite"),
    (dict(H=np.full((3, 3), np.nan)), "NaN or Inf"),
    (dict(H=np.zeros((3, 3))), "singular"),
    (dict(supersample=0), "supersample must be >= 1"),
    (dict(box=1.5), "box must be a width in"),
])
def test_bad_arguments_raise(bad, match):
    kw = dict(H=_frontal_h(), texture_shape=(8, 8), sample_size_m=S_M)
    kw.update(bad)
    with pytest.raises(ValueError, match=match):
        rectify(np.ones((101, 101)), **kw)


def test_nan_in_image_is_reported_with_its_index():
    img = np.ones((101, 101, 3), dtype=np.float32)
    img[7, 9, 2] = np.nan
    with pytest.raises(ValueError, match=r"first at index \(7, 9, 2\)"):
        rectify(img, _frontal_h(), (8, 8), S_M)


def test_apply_rectification_check_finite_false_skips_the_scan():
    """As the view chain calls it once per block of images it made itself: the same texture, and a NaN is
    not looked for (it reaches the texels that read it) instead of being named."""
    d = get_device("bonn-dome2")
    A = rectification_matrix(d.homography(0, 3), d.roi_shape, d.texture_shape, d.sample_size_m)
    img = np.random.default_rng(0).random((*d.roi_shape, 6), dtype=np.float32)
    np.testing.assert_array_equal(apply_rectification(A, img, d.texture_shape, check_finite=False),
                                  apply_rectification(A, img, d.texture_shape))
    img[d.roi_shape[0] // 2, d.roi_shape[1] // 2, 4] = np.nan
    with pytest.raises(ValueError, match="NaN or Inf"):
        apply_rectification(A, img, d.texture_shape)
    assert np.isnan(apply_rectification(A, img, d.texture_shape, check_finite=False)[..., 4]).any()


# ----------------------------------------------------------------------------- operators


@pytest.mark.parametrize("method", RECTIFY_METHODS)
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_constant_image_gives_constant_texture(method, dtype):
    d = get_device("tiny")
    H = d.homography(1, 3)
    img = np.full(d.roi_shape + (3,), 1234.5, dtype=dtype)       # HDR value > 1
    tex = rectify(img, H, d.texture_shape, d.sample_size_m, method=method)
    assert tex.dtype == np.float32 and tex.shape == d.texture_shape + (3,)
    np.testing.assert_allclose(tex, 1234.5, rtol=1e-6)


@pytest.mark.parametrize("method", ["supersample", "area"])
def test_operator_rows_are_convex_weights(method):
    d = get_device("tiny")
    A = rectification_matrix(d.homography(0, 3), d.roi_shape, d.texture_shape, d.sample_size_m, method=method)
    assert A.shape == (d.texture_shape[0] * d.texture_shape[1], d.roi_shape[0] * d.roi_shape[1])
    np.testing.assert_allclose(np.asarray(A.sum(axis=1)).ravel(), 1.0, atol=1e-12)
    assert A.data.min() >= -1e-12


@pytest.mark.parametrize("box", [None, 1.0])
def test_supersample_reproduces_a_linear_image_under_an_affine_view(box):
    """For an affine map, the mean of a linear function over a centred box is its value at the centre."""
    H = np.array([[1600.0, 500.0, 60.0], [-300.0, -1500.0, 55.0], [0, 0, 1.0]])
    r, c = np.mgrid[0:120, 0:130].astype(np.float64)
    img = 3.0 + 0.25 * c - 0.5 * r
    h, w = 10, 12
    tex = rectify(img, H, (h, w), S_M, supersample=5, box=box)
    G = texture_homography(H, (h, w), S_M)
    i, j = np.mgrid[0:h, 0:w]
    q = np.einsum("ab,bhw->ahw", G, np.stack([j, i, np.ones_like(i)]).astype(float))
    np.testing.assert_allclose(tex, 3.0 + 0.25 * q[0] / q[2] - 0.5 * q[1] / q[2], rtol=2e-6)


def test_area_weights_equal_a_brute_force_footprint_integral():
    """Exact box-pixel overlap areas against 400x400 point sampling of each texel (Jacobian-weighted)."""
    H = np.array([[2000.0, 300, 70], [100, -1500.0, 60], [3, 5, 1]])
    shape, (h, w) = (130, 130), (6, 6)
    A = rectification_matrix(H, shape, (h, w), S_M, method="area").toarray()
    G = texture_homography(H, (h, w), S_M)
    n = 400
    o = (np.arange(n) + 0.5) / n - 0.5
    B = np.zeros_like(A)
    for k in range(h * w):
        i0, j0 = divmod(k, w)
        J, I = np.meshgrid(j0 + o, i0 + o)
        den = G[2, 0] * J + G[2, 1] * I + G[2, 2]
        col = (G[0, 0] * J + G[0, 1] * I + G[0, 2]) / den
        row = (G[1, 0] * J + G[1, 1] * I + G[1, 2]) / den
        jac = 1.0 / np.abs(den) ** 3                                  # |det dq/d(j,i)| up to a constant
        pix = np.rint(row).astype(int) * shape[1] + np.rint(col).astype(int)
        B[k] = np.bincount(pix.ravel(), weights=jac.ravel(), minlength=A.shape[1])
        B[k] /= B[k].sum()
    assert np.abs(A - B).max() < 1e-3


def test_bilinear_method_is_the_single_lookup_supersample():
    d = get_device("tiny")
    H = d.homography(2, 2)
    img = np.random.default_rng(3).uniform(0, 5, d.roi_shape + (3,)).astype(np.float32)
    cv = rectify(img, H, d.texture_shape, d.sample_size_m, method="bilinear")
    exact = rectify(img, H, d.texture_shape, d.sample_size_m, supersample=1)
    # OpenCV quantises bilinear weights to 1/32 pixel: at most 1/64 of a neighbour difference
    assert np.abs(cv - exact).max() < 5.0 / 32


def test_many_channels_and_the_reusable_operator():
    d = get_device("tiny")
    H = d.homography(0, 2)
    rng = np.random.default_rng(4)
    stack = rng.uniform(0, 100, d.roi_shape + (7,))
    A = rectification_matrix(H, d.roi_shape, d.texture_shape, d.sample_size_m)
    tex = apply_rectification(A, stack, d.texture_shape)
    assert tex.shape == d.texture_shape + (7,)
    for k in (0, 6):
        np.testing.assert_allclose(tex[..., k], rectify(stack[..., k], H, d.texture_shape, d.sample_size_m),
                                   rtol=1e-5)
    wide = rectify(stack, H, d.texture_shape, d.sample_size_m, method="bilinear")   # > 4 channels through OpenCV
    np.testing.assert_allclose(wide[..., 5], rectify(stack[..., 5], H, d.texture_shape, d.sample_size_m,
                                                     method="bilinear"), rtol=1e-6)


@pytest.mark.parametrize("method", RECTIFY_METHODS)
@pytest.mark.parametrize("c", [0, 3])
def test_support_window_holds_every_pixel_the_operator_reads(method, c):
    d = get_device("bonn-dome2")
    A = rectification_matrix(d.homography(0, c), d.roi_shape, d.texture_shape, d.sample_size_m, method=method)
    rows, cols, Aw = support_window(A, d.roi_shape, margin=2, align=2)
    assert rows.start % 2 == 0 and cols.start % 2 == 0                  # Bayer layout kept
    n = (rows.stop - rows.start) * (cols.stop - cols.start)
    assert Aw.shape == (A.shape[0], n) and Aw.nnz == A.nnz
    assert n < 0.6 * d.roi_shape[0] * d.roi_shape[1]                   # the frame is larger than the sample
    image = np.random.default_rng(c).uniform(0, 1, d.roi_shape + (3,))
    np.testing.assert_array_equal(apply_rectification(Aw, image[rows, cols], d.texture_shape),
                                  apply_rectification(A, image, d.texture_shape))
    # the margin is really there: pixels of the window that the operator does not read
    used = np.zeros(n, bool)
    used[Aw.indices] = True
    used = used.reshape(rows.stop - rows.start, -1)
    assert not used[:2].any() and not used[:, :2].any()
    with pytest.raises(ValueError, match="columns"):
        support_window(A, (10, 10))


def test_automatic_supersampling_follows_the_footprint():
    d = get_device("bonn-dome2", texture_shape=(64, 64))
    s = d.sample_size_m
    frontal = auto_supersample(d.homography(0, 0), d.texture_shape, s)
    grazing = auto_supersample(d.homography(0, 10), d.texture_shape, s)
    assert frontal[0] == frontal[1] >= 4                    # ~3 px per texel on both axes
    assert grazing[1] == 1 and grazing[0] >= 4              # the 75-degree view magnifies along j (sample x)
    assert auto_supersample(d.homography(0, 0), d.texture_shape, s, box=1.0, cap=5) == (5, 5)
    b = box_widths(d.homography(0, 10), d.texture_shape, s)
    assert b.shape == (64, 64, 2) and b[..., 0].max() == 0 and 0.8 < b[..., 1].min() <= 1
    assert auto_supersample(get_device("tiny").homography(0, 0), (32, 32), s) == (1, 1)   # 1.5 px per texel


# ----------------------------------------------------------------------------- registration measurement


def test_registration_error_measures_known_shifts():
    """Calibration of the measurement itself on a band-limited texture (exact Fourier shifts)."""
    tex = ndimage.gaussian_filter(np.random.default_rng(0).standard_normal((64, 64)), 1.5, mode="wrap")
    for d in [(0.3, -0.2), (-0.07, 0.45), (1.25, 0.0)]:
        moved = np.fft.ifft2(ndimage.fourier_shift(np.fft.fft2(tex), (d[1], d[0]))).real
        err, shifts = registration_error(moved, tex, tiles=2)
        np.testing.assert_allclose(shifts.reshape(-1, 2).mean(axis=0), d, atol=0.02)
        assert abs(err - np.hypot(*d)) < 0.05


def test_registration_error_sees_a_displaced_sample_and_a_wrong_texel_convention():
    d = get_device("bonn-dome2", texture_shape=(64, 64), turntable_angle_deg=[30.0])
    h, w = d.texture_shape
    t2 = checker(2 * h, 8, smooth=1.0)
    truth = box_down(t2, 2)
    H = d.homography(0, 4)
    delta = (0.3, -0.2)
    frame = render_frame(t2[None], BACKGROUND, shift_h(H, d, delta), d.roi_shape, d.sample_size_m)[0]
    _, shifts = registration_error(rectify(frame, H, (h, w), d.sample_size_m), truth, tiles=2)
    np.testing.assert_allclose(shifts.reshape(-1, 2), np.tile(delta, (4, 1)), atol=0.05)
    # a texture homography with texel centres on integer corners (half a texel off) is caught
    frame = render_frame(t2[None], BACKGROUND, H, d.roi_shape, d.sample_size_m)[0]
    wrong = shift_h(H, d, (-0.5, -0.5))
    err, _ = registration_error(rectify(frame, wrong, (h, w), d.sample_size_m), truth, tiles=2)
    assert 0.6 < err < 0.8


def test_phase_correlation_is_unreliable_on_a_blurred_grazing_view():
    """Why registration_error whitens nothing by default: cv2-style phase correlation on the sharp checker at
    the 75-degree view of `tiny` lands far from the (geometrically exact) answer; cross-correlation does not."""
    d = get_device("tiny")
    h, w = d.texture_shape
    t2 = checker(2 * h, 8)
    H = d.homography(0, 3)
    frame = render_frame(t2[None], BACKGROUND, H, d.roi_shape, d.sample_size_m)[0]
    tex = rectify(frame, H, (h, w), d.sample_size_m, method="area")
    truth = box_down(t2, 2)
    xcorr, _ = registration_error(tex, truth, tiles=1)
    phase, _ = registration_error(tex, truth, tiles=2, whiten=True)
    (dx, dy), _ = cv2.phaseCorrelate(truth.mean(-1).astype(np.float64), tex.mean(-1).astype(np.float64))
    assert xcorr < 0.1 < min(phase, np.hypot(dx, dy))


# ----------------------------------------------------------------------------- the bars on the checker target


def _views(device):
    return [(t, c) for t in range(device.n_turn) for c in range(device.n_cam)]


@pytest.mark.parametrize("name", sorted(DEVICES))
def test_checker_registration_below_a_tenth_of_a_texel(name):
    """Sharp checker (4-texel squares, 2x ground truth) at the device's own views, and an edge-smoothed checker
    with the sample displaced by a random sub-texel offset per view (known to the rectifier)."""
    d = DEVICES[name]()
    h, w = d.texture_shape
    rng = np.random.default_rng(11)
    rows = []
    for smooth in (0.0, 1.0):
        t2 = checker(2 * h, 8, smooth)
        truth = box_down(t2, 2)
        for t, c in _views(d):
            H = d.homography(t, c)
            if smooth:
                H = shift_h(H, d, rng.uniform(-0.5, 0.5, 2))
            frame = render_frame(t2[None], BACKGROUND, H, d.roi_shape, d.sample_size_m)[0]
            for method in RECTIFY_METHODS:
                tex = rectify(frame, H, (h, w), d.sample_size_m, method=method)
                err, _ = registration_error(tex, truth, tiles=_tiles(d))
                rows.append((smooth, elevation_deg(d, t, c), method, err))
    print(f"\n{name}: worst registration error (texels) per elevation, over turntable positions")
    for smooth in (0.0, 1.0):
        print(" ", "sharp checker, device views" if not smooth else "smoothed checker, random sub-texel offsets")
        for elev in sorted({r[1] for r in rows}):
            errs = {m: max(r[3] for r in rows if r[0] == smooth and r[1] == elev and r[2] == m)
                    for m in RECTIFY_METHODS}
            print(f"    {elev:5.1f} deg  " + "  ".join(f"{m} {e:.3f}" for m, e in errs.items()))
    worst = max(rows, key=lambda r: r[3])
    assert worst[3] < 0.1, f"registration error {worst[3]:.3f} texel at {worst}"


@pytest.mark.parametrize("name", sorted(DEVICES))
def test_psnr_per_view_elevation(name):
    """PSNR against the ground-truth texture, per elevation (mean over turntable positions), three targets:
    the 2x sharp checker, a fine-detail texture at 8x (detail below the texel: aliasing), and the same
    with sensor-like noise."""
    d = DEVICES[name]()
    h, w = d.texture_shape
    rng = np.random.default_rng(5)
    targets = {"checker 2x": checker(2 * h, 8), "fine 8x": fine_texture(8 * h)}
    table: dict[tuple[str, float, str], list[float]] = {}
    for t, c in _views(d):
        H = d.homography(t, c)
        elev = elevation_deg(d, t, c)
        for tname, tk in targets.items():
            truth = box_down(tk, tk.shape[0] // h)
            frame = render_frame(tk[None], BACKGROUND, H, d.roi_shape, d.sample_size_m)[0]
            variants = {tname: frame}
            if tname == "fine 8x":   # photon-like noise, 3 % at a radiance of 0.3
                variants["fine 8x + noise"] = frame + 0.03 * np.sqrt(0.3 * frame) * rng.standard_normal(
                    frame.shape).astype(np.float32)
            for vname, img in variants.items():
                for method in RECTIFY_METHODS:
                    tex = rectify(img, H, (h, w), d.sample_size_m, method=method)
                    table.setdefault((vname, round(elev, 1), method), []).append(psnr(tex, truth))
    print(f"\n{name} ({h}x{w} texels): PSNR dB vs ground truth, mean over turntable positions")
    print("  target            elev   " + "  ".join(f"{m:>11s}" for m in RECTIFY_METHODS))
    for vname in ("checker 2x", "fine 8x", "fine 8x + noise"):
        for elev in sorted({k[1] for k in table}):
            vals = [np.mean(table[(vname, elev, m)]) for m in RECTIFY_METHODS]
            print(f"  {vname:16s} {elev:5.1f}   " + "  ".join(f"{v:11.2f}" for v in vals))
    mean = {k: float(np.mean(v)) for k, v in table.items()}
    top = max(k[1] for k in table)
    if name == "bonn-dome2":
        assert abs(top - 75.0) < 1e-6
        for vname in ("fine 8x", "fine 8x + noise"):
            # the bar: anti-aliased beats plain bilinear at the 75-degree view ...
            for method in ("supersample", "area"):
                assert mean[(vname, top, method)] > mean[(vname, top, "bilinear")] + 0.5, (vname, method)
            # ... and by far at the views where a texel covers ~3 pixels
            assert mean[(vname, 0.0, "supersample")] > mean[(vname, 0.0, "bilinear")] + 8.0
    else:
        # tiny: 1.5 px per texel, the view magnifies at 75 deg; filtering changes little there
        assert mean[("fine 8x + noise", top, "supersample")] >= mean[("fine 8x + noise", top, "bilinear")] - 0.2
