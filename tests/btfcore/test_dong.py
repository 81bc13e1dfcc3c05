"""Dong et al.'s regularised up-sampling and its eigentexture form (btfcore.superres.dong), SR paper §3.4."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from btfcore.superres.dong import DEFAULT_ALPHA, alpha_errors, choose_alpha, dong_eigentextures, dong_upsample, \
    gaussian_psf
from btfcore.superres.scaling import area_downsample, bicubic_upsample

LAPLACIAN = np.array([[0.0, 1.0, 0.0], [1.0, -4.0, 1.0], [0.0, 1.0, 0.0]])


def _operators(f: int, psf: np.ndarray):
    """D, D^T, P and L of eq. (4) in the image domain, reflective boundaries, independent of the solver."""
    def blur(x):
        return ndimage.correlate1d(ndimage.correlate1d(x, psf, axis=0, mode="reflect"), psf, axis=1, mode="reflect")

    def down(x):
        return x.reshape(x.shape[0] // f, f, x.shape[1] // f, f).mean(axis=(1, 3))

    def down_t(y):
        return np.repeat(np.repeat(y, f, axis=0), f, axis=1) / f**2

    def laplacian(x):
        return ndimage.correlate(x, LAPLACIAN, mode="reflect")

    return down, down_t, blur, laplacian


def _smooth_textures(n: int, size: int, seed: int = 0, noise: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Seeded smooth synthetic textures (n, size, size) and their area down-sampled images (plus noise)."""
    rng = np.random.default_rng(seed)
    high = np.stack([ndimage.gaussian_filter(rng.standard_normal((size, size)), s, mode="wrap")
                     for s in np.linspace(1.5, 4.0, n)])
    high = 0.5 + 0.2 * high / high.std(axis=(1, 2), keepdims=True)
    low = area_downsample(high)
    return high, low + noise * 0.5 * rng.standard_normal(low.shape)


def _relative(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean(np.linalg.norm((a - b).reshape(len(b), -1), axis=1)
                         / np.linalg.norm(b.reshape(len(b), -1), axis=1)))


@pytest.mark.parametrize("factor, psf_sigma, psf_size, alpha, shape", [
    (2, 0.0, None, 1e-2, (13, 17)),
    (2, 1.5, 9, 1e-3, (12, 10)),
    (3, 1.0, None, 0.1, (7, 9)),
])
def test_solution_satisfies_the_normal_equations(factor, psf_sigma, psf_size, alpha, shape) -> None:
    y = np.random.default_rng(3).standard_normal((2,) + shape)
    x = dong_upsample(y, factor=factor, alpha=alpha, psf_sigma=psf_sigma, psf_size=psf_size).astype(np.float64)
    assert x.shape == (2, factor * shape[0], factor * shape[1]) and x.dtype == np.float64
    down, down_t, blur, laplacian = _operators(factor, gaussian_psf(psf_sigma, psf_size))
    for xi, yi in zip(x, y):
        lhs = blur(down_t(down(blur(xi)))) + alpha * laplacian(laplacian(xi))    # P^T D^T D P x + a L^T L x
        rhs = blur(down_t(yi))
        assert np.linalg.norm(lhs - rhs) <= 1e-6 * np.linalg.norm(rhs)         # float32 output rounding


def test_small_alpha_reproduces_the_data() -> None:
    y = np.random.default_rng(4).random((3, 10, 14))
    down, _, blur, _ = _operators(2, gaussian_psf(0.0))
    x = dong_upsample(y, alpha=1e-8).astype(np.float64)
    assert max(np.abs(down(blur(xi)) - yi).max() for xi, yi in zip(x, y)) < 1e-5
    x = dong_upsample(y, alpha=1e-8, psf_sigma=0.7, psf_size=5).astype(np.float64)
    down, _, blur, _ = _operators(2, gaussian_psf(0.7, 5))
    assert max(np.abs(down(blur(xi)) - yi).max() for xi, yi in zip(x, y)) < 1e-3


def test_large_alpha_tends_to_the_smooth_constant_image() -> None:
    y = np.random.default_rng(5).random((2, 8, 8))
    stds = [dong_upsample(y, alpha=a)[0].std() for a in (1e-2, 1.0, 1e2, 1e6)]
    assert all(s1 > s2 for s1, s2 in zip(stds, stds[1:]))
    x = dong_upsample(y, alpha=1e8)
    assert np.allclose(x, y.mean(axis=(1, 2))[:, None, None], atol=1e-5)


def test_the_mean_is_kept_and_constants_are_exact() -> None:
    y = np.random.default_rng(6).random((2, 9, 11))
    assert np.allclose(dong_upsample(y).mean(axis=(1, 2)), y.mean(axis=(1, 2)), atol=1e-6)
    assert np.allclose(dong_upsample(np.full((1, 5, 6), 3.25), psf_sigma=1.0), 3.25, atol=1e-5)


def test_dong_beats_nearest_and_bicubic_on_smooth_textures() -> None:
    """Measured: mean relative error 0.98 % for Dong, 1.87 % bicubic, 7.36 % nearest neighbour (24 textures,
    64 x 64, correlation lengths 1.5-4 px, no noise)."""
    high, low = _smooth_textures(24, 64)
    dong = _relative(dong_upsample(low), high)
    bicubic = _relative(bicubic_upsample(low), high)
    nearest = _relative(np.repeat(np.repeat(low, 2, axis=1), 2, axis=2), high)
    assert dong < 0.6 * bicubic and bicubic < 0.5 * nearest


def test_choose_alpha_picks_the_least_error() -> None:
    """With Dong et al.'s PSF and 1 % noise the error is U-shaped in alpha (measured: 11.8, 6.3, 3.4, 3.1 and
    5.5 % for alpha 1e-5 .. 1e-1 on these smooth textures)."""
    high, _ = _smooth_textures(8, 48, seed=2)
    psf = gaussian_psf(1.5, 9)
    rng = np.random.default_rng(8)
    blurred = np.stack([ndimage.correlate1d(ndimage.correlate1d(x, psf, axis=0, mode="reflect"), psf, axis=1,
                                            mode="reflect") for x in high])
    low = area_downsample(blurred) + 0.005 * rng.standard_normal((8, 24, 24))
    alphas = [1e-5, 1e-4, 1e-3, 1e-2, 1e-1]
    errors = alpha_errors(low, high, alphas, psf_sigma=1.5, psf_size=9)
    best = choose_alpha(low, high, alphas, psf_sigma=1.5, psf_size=9)
    assert best == alphas[int(np.argmin(errors))]
    assert best in (1e-4, 1e-3, 1e-2) and errors[0] > errors.min() and errors[-1] > errors.min()
    assert DEFAULT_ALPHA == 1e-3


def _btf(n_lv: int, h: int, w: int, seed: int = 0, rank: int | None = None) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if rank is None:
        return rng.random((n_lv, h, w, 3)).astype(np.float32)
    spectrum = 2.0 ** -np.arange(rank)                                        # clear gaps
    U = np.linalg.qr(rng.standard_normal((n_lv, rank)))[0]
    V = np.linalg.qr(rng.standard_normal((h * w * 3, rank)))[0].T
    return ((U * spectrum) @ V).reshape(n_lv, h, w, 3)


def _per_texture(B: np.ndarray, **kw) -> np.ndarray:
    n_lv, h, w, C = B.shape
    planes = np.moveaxis(B, 3, 1).reshape(-1, h, w)
    up = dong_upsample(planes, **kw)
    return np.moveaxis(up.reshape(n_lv, C, 2 * h, 2 * w), 1, 3)


def test_full_rank_eigentextures_equal_per_texture_upsampling() -> None:
    B = _btf(12, 8, 10)
    out = dong_eigentextures(B, rank=500, alpha=1e-2, psf_sigma=0.8)               # rank clipped to 12
    assert out.shape == (12, 16, 20, 3) and out.dtype == np.float32
    assert np.allclose(out, _per_texture(B, alpha=1e-2, psf_sigma=0.8), atol=1e-5)


def test_low_rank_eigentextures_upsample_the_rank_k_approximation() -> None:
    B = _btf(16, 6, 8, seed=1, rank=10)
    k = 4
    U = np.linalg.svd(B.reshape(16, -1), full_matrices=False)[0][:, :k]
    approx = (U @ (U.T @ B.reshape(16, -1))).reshape(B.shape)
    assert np.allclose(dong_eigentextures(B, rank=k), _per_texture(approx), atol=1e-6)


def test_rank_above_the_numerical_rank_keeps_the_data() -> None:
    B = _btf(10, 6, 6, seed=2, rank=3)
    assert np.allclose(dong_eigentextures(B, rank=10), _per_texture(B), atol=1e-6)
    assert not dong_eigentextures(np.zeros((4, 3, 3, 3)), rank=2).any()


@pytest.mark.parametrize("kwargs, name", [
    ({"rank": 0}, "rank"), ({"rank": 2.5}, "rank"), ({"alpha": 0.0}, "alpha"), ({"alpha": float("nan")}, "alpha"),
    ({"factor": 0}, "factor"), ({"psf_sigma": -1.0}, "psf_sigma"), ({"psf_sigma": 1.0, "psf_size": 4}, "psf_size"),
    ({"psf_sigma": 3.0, "psf_size": 41}, "psf_size"),
])
def test_bad_arguments_are_refused_by_name(kwargs, name) -> None:
    with pytest.raises(ValueError, match=name):
        dong_eigentextures(_btf(4, 5, 5), **kwargs)


def test_bad_btf_is_refused_by_name() -> None:
    with pytest.raises(ValueError, match="B must be a BTF"):
        dong_eigentextures(np.ones((4, 5, 5)))
    B = _btf(4, 5, 5)
    B[1, 2, 3, 0] = np.nan
    with pytest.raises(ValueError, match=r"B holds 1 NaN .* \(1, 2, 3, 0\)"):
        dong_eigentextures(B)


def test_bad_images_are_refused_by_name() -> None:
    with pytest.raises(ValueError, match="images"):
        dong_upsample(np.ones((2, 4, 4, 3)))
    y = np.ones((2, 4, 4))
    y[0, 0, 0] = np.inf
    with pytest.raises(ValueError, match="images holds 1 NaN or infinite"):
        dong_upsample(y)
    with pytest.raises(ValueError, match="high must be"):
        choose_alpha(np.ones((2, 4, 4)), np.ones((2, 4, 4)), [1e-3])
    with pytest.raises(ValueError, match="alphas is empty"):
        choose_alpha(np.ones((2, 4, 4)), np.ones((2, 8, 8)), [])
