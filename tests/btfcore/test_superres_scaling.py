"""Area down-sampling and bicubic up-sampling (btfcore.superres.scaling): shapes, exactness, errors."""

from __future__ import annotations

import numpy as np
import pytest

from btfcore.superres.scaling import area_downsample, bicubic_upsample


@pytest.mark.parametrize("shape, factor, expected", [
    ((3, 8, 6), 2, (3, 4, 3)),
    ((2, 9, 7, 3), 2, (2, 4, 3, 3)),          # an odd last row and column are dropped
    ((1, 9, 12), 3, (1, 3, 4)),
    ((2, 5, 5), 1, (2, 5, 5)),
])
def test_area_downsample_shapes_and_dtype(shape, factor, expected) -> None:
    out = area_downsample(np.ones(shape, np.float64), factor)
    assert out.shape == expected and out.dtype == np.float32


def test_area_downsample_is_the_exact_block_mean() -> None:
    rng = np.random.default_rng(0)
    x = rng.random((2, 6, 9, 3))
    out = area_downsample(x, 3)
    assert np.allclose(out[1, 1, 2], x[1, 3:6, 6:9].mean(axis=(0, 1)), atol=1e-7)
    assert np.array_equal(area_downsample(np.full((1, 4, 4), 7.5), 2), np.full((1, 2, 2), 7.5, np.float32))


def test_area_downsample_of_a_ramp_samples_it_at_the_block_centres() -> None:
    """Pixel-centre convention: low-res pixel i sits at high-res coordinate f i + (f - 1) / 2."""
    f = 2
    rows, cols = np.mgrid[0:8, 0:10].astype(np.float64)
    ramp = (0.25 * rows + 0.5 * cols + 1.0)[None]
    out = area_downsample(ramp, f)
    lr_rows, lr_cols = np.mgrid[0:4, 0:5].astype(np.float64)
    expected = 0.25 * (f * lr_rows + (f - 1) / 2) + 0.5 * (f * lr_cols + (f - 1) / 2) + 1.0
    assert np.allclose(out[0], expected, atol=1e-6)


def test_area_downsample_accepts_integers() -> None:
    out = area_downsample(np.arange(16, dtype=np.uint16).reshape(1, 4, 4), 2)
    assert np.allclose(out[0], [[2.5, 4.5], [10.5, 12.5]])


@pytest.mark.parametrize("shape, factor", [((2, 5, 4), 2), ((1, 3, 3, 3), 3), ((1, 2, 2), 1)])
def test_bicubic_upsample_shapes_and_constant(shape, factor) -> None:
    out = bicubic_upsample(np.full(shape, 0.3), factor)
    assert out.dtype == np.float32
    assert out.shape == (shape[0], factor * shape[1], factor * shape[2]) + shape[3:]
    assert np.allclose(out, 0.3, atol=1e-6)


def test_bicubic_upsample_follows_the_pixel_centre_convention_on_a_ramp() -> None:
    """Each low-res pixel's f x f block is centred on it: away from the border the block means of the
    up-sampled ramp give the ramp back (OpenCV's cubic, a = -0.75, is symmetric but not linear-exact)."""
    lr = np.arange(12, dtype=np.float32)[None, None, :].repeat(6, axis=1)      # (1, 6, 12), value = column
    for f in (2, 3):
        back = area_downsample(bicubic_upsample(lr, f), f)
        assert np.allclose(back[0, :, 2:-2], lr[0, :, 2:-2], atol=1e-5)


def test_bicubic_upsample_treats_channels_independently() -> None:
    rng = np.random.default_rng(1)
    x = rng.random((2, 5, 7, 3)).astype(np.float32)
    out = bicubic_upsample(x)
    assert np.array_equal(out[..., 1], bicubic_upsample(x[..., 1]))


@pytest.mark.parametrize("fn", [area_downsample, bicubic_upsample])
@pytest.mark.parametrize("factor", [0, -1, 1.5, True])
def test_bad_factor_is_refused(fn, factor) -> None:
    with pytest.raises(ValueError, match="factor"):
        fn(np.ones((1, 4, 4)), factor)


@pytest.mark.parametrize("fn", [area_downsample, bicubic_upsample])
@pytest.mark.parametrize("shape", [(4, 4), (1, 2, 2, 2, 2), (0, 4, 4)])
def test_bad_stacks_are_refused(fn, shape) -> None:
    with pytest.raises(ValueError, match="images"):
        fn(np.ones(shape), 2)


def test_images_smaller_than_the_factor_are_refused() -> None:
    with pytest.raises(ValueError, match="smaller than the factor 3"):
        area_downsample(np.ones((2, 2, 8)), 3)
