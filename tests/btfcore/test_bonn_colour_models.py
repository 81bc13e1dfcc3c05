"""Colour models of the Bonn DFMF format (btfcore.bonn.colour_models) against btflib's formulas."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from btfcore.bonn import (
    COLOUR_MODELS,
    DRR_EPS,
    UnknownColourModelError,
    decode_colour,
    encode_colour,
    reduce_dynamic_range,
    restore_dynamic_range,
)
from btfcore.bonn.colour_models import RGB_FROM_YUV, YUV_FROM_RGB

F32 = float(np.finfo(np.float32).eps)


def _hdr(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Positive HDR RGB, log-uniform in [1e-3, 1e3] per channel (float64)."""
    return np.exp(rng.uniform(np.log(1e-3), np.log(1e3), shape + (3,)))


def _btflib_undecorrelate(values: np.ndarray, model: int, mean=None, matrix=None) -> tuple[np.ndarray, np.ndarray]:
    """The test's own float64 transcription of btflib's undecorrelate.m (rows of values are pixels).

    Returns the RGB and, per pixel, the largest magnitude before the final linear step (the scale
    of a float32 implementation's rounding).
    """
    eps = 1e-5
    yuv2rgb = np.array([[1, 0, 1.13983], [1, -0.39465, -0.5806], [1, 2.03211, 0]])
    ycocg2rgb = np.array([[1, 1, -1], [1, 0, 1], [1, -1, -1]])
    v = np.array(values, dtype=np.float64).reshape(-1, 3)
    if model in (9, 10, 11):
        v[:, 0] = np.exp(v[:, 0]) - eps
    if model == 10:
        v[:, 1:] = np.sign(v[:, 1:]) * np.exp(np.abs(v[:, 1:]) + np.log(eps))
    elif model == 11:
        v[:, 1] = v[:, 1] * (v[:, 0] + eps)
        v[:, 2] = v[:, 2] * (v[:, 0] + eps)
    elif model == 12:
        v = np.exp(v) - eps
    pre = np.abs(v).max(axis=1) + eps
    if model in (1, 9, 10, 11):
        v = v @ yuv2rgb.T
    elif model == 3:
        v = v @ np.asarray(matrix, np.float64) + np.asarray(mean, np.float64)
        pre = pre + np.abs(np.asarray(mean, np.float64)).max()
    elif model == 4:
        v = v @ ycocg2rgb.T
    shape = np.shape(values)
    return v.reshape(shape), pre.reshape(shape[:-1] + (1,))


def _round_trip_error(rgb: np.ndarray, model: int) -> np.ndarray:
    """|decode(encode(rgb)) - rgb| in units of float32 eps times the pixel's scale."""
    c, mean, matrix = encode_colour(rgb, model)
    assert c.dtype == np.float32 and c.shape == rgb.shape
    assert mean.dtype == np.float32 and mean.shape == (3,)
    assert matrix.dtype == np.float32 and matrix.shape == (3, 3)
    back = decode_colour(c, model, mean, matrix)
    assert back.dtype == np.float32 and back.shape == rgb.shape
    scale = np.abs(rgb).max(axis=-1, keepdims=True)
    if model == 3:  # the channels are rgb - mean: their rounding scales with the mean
        scale = np.maximum(scale, np.abs(mean).max())
    return np.abs(back.astype(np.float64) - rgb) / (scale * F32)


def test_every_btflib_model_of_the_brief_is_supported() -> None:
    assert {0, 1, 3, 4, 9, 10, 11, 12} <= set(COLOUR_MODELS)
    assert DRR_EPS == 1e-5


def test_yuv_matrix_is_btflibs_and_its_inverse_is_exact() -> None:
    np.testing.assert_array_equal(RGB_FROM_YUV, [[1, 0, 1.13983], [1, -0.39465, -0.5806], [1, 2.03211, 0]])
    np.testing.assert_allclose(YUV_FROM_RGB @ RGB_FROM_YUV, np.eye(3), atol=1e-15)
    # its luma row is BT.601's to the precision of btflib's constants
    np.testing.assert_allclose(YUV_FROM_RGB[0], [0.299, 0.587, 0.114], atol=2e-5)


@pytest.mark.parametrize("model", [0, 1, 3, 4, 9, 11, 12])
def test_round_trip_on_positive_hdr_data(model: int) -> None:
    rgb = _hdr(np.random.default_rng(model), (128, 96))
    err = _round_trip_error(rgb, model)
    assert err.max() <= 16, f"model {model}: round trip off by {err.max():.1f} float32 eps of the pixel scale"


def test_round_trip_model_10_outside_its_dead_zone_and_inside_it() -> None:
    """Model 10 decodes |U| as 0 or >= eps: exact outside (-eps, eps), nearest value inside."""
    rng = np.random.default_rng(10)
    rgb = _hdr(rng, (128, 96))
    yuv = rgb @ YUV_FROM_RGB.T
    outside = (np.abs(yuv[..., 1:]) >= DRR_EPS).all(axis=-1)
    err = _round_trip_error(rgb, 10)
    assert outside.mean() > 0.9
    # c1 = log(|U| / eps) reaches ~18 in float32: a few ulps of 18 relative to U
    assert err[outside].max() <= 64
    # everywhere: absolute error below eps/2 per YUV channel, times the largest YUV->RGB coefficient
    c, _, _ = encode_colour(rgb, 10)
    back = decode_colour(c, 10).astype(np.float64)
    bound = 2.04 * DRR_EPS / 2 + 64 * F32 * np.abs(rgb).max(axis=-1, keepdims=True)
    assert (np.abs(back - rgb) <= bound).all()


def test_model_10_rounds_small_chroma_to_nearest_representable_value() -> None:
    yuv = np.array([[1e-4, 0.25 * DRR_EPS, -0.75 * DRR_EPS],
                    [1e-4, 3 * DRR_EPS, -2 * DRR_EPS],
                    [1e-4, 0.0, 0.0]])  # small Y: float32 rounding of RGB (~1e-11) well below eps
    c, _, _ = encode_colour(yuv @ RGB_FROM_YUV.T, 10)
    np.testing.assert_allclose(c[1, 1:], [np.log(3), -np.log(2)], rtol=1e-6)
    back_yuv = decode_colour(c, 10).astype(np.float64) @ YUV_FROM_RGB.T
    np.testing.assert_allclose(back_yuv[:, 1:], [[0.0, -DRR_EPS], [3 * DRR_EPS, -2 * DRR_EPS], [0.0, 0.0]],
                               atol=1e-10)


@settings(max_examples=60, deadline=None)
@given(rgb=hnp.arrays(np.float64, hnp.array_shapes(min_dims=1, max_dims=3, max_side=6).map(lambda s: s + (3,)),
                      elements=st.floats(1e-3, 1e3)),
       model=st.sampled_from([0, 1, 3, 4, 9, 11, 12]))
def test_round_trip_property(rgb: np.ndarray, model: int) -> None:
    err = _round_trip_error(rgb, model)
    assert err.max() <= 16


@settings(max_examples=60, deadline=None)
@given(c=hnp.arrays(np.float32, st.integers(1, 20).map(lambda n: (n, 3)), elements=st.floats(-6, 6, width=32)),
       model=st.sampled_from(sorted(COLOUR_MODELS)))
def test_decode_matches_a_float64_transcription_of_btflib(c: np.ndarray, model: int) -> None:
    rng = np.random.default_rng(3)
    mean = rng.uniform(0, 1, 3).astype(np.float32)
    matrix = np.linalg.qr(rng.standard_normal((3, 3)))[0].astype(np.float32)
    ref, scale = _btflib_undecorrelate(c, model, mean, matrix)
    got = decode_colour(c, model, mean, matrix).astype(np.float64)
    err = np.abs(got - ref) / (scale * F32)
    # float32 arithmetic; model 10 adds log(eps) = -11.5 to |c| before exp: ulps of 11.5 + 6
    assert err.max() <= (64 if model == 10 else 16)


def test_known_values() -> None:
    grey = np.full((4, 3), 0.5) * np.array([[1.0], [2.0], [1e-3], [1e3]])
    yuv, _, _ = encode_colour(grey, 1)
    np.testing.assert_allclose(yuv[:, 0], grey[:, 0], rtol=1e-6)
    assert (np.abs(yuv[:, 1:]) <= 1e-6 * grey[:, :1]).all(), "grey has no chroma"
    ycocg, _, _ = encode_colour(grey, 4)
    np.testing.assert_allclose(ycocg, np.c_[grey[:, 0], np.zeros((4, 2))], rtol=1e-7, atol=1e-12)
    c11, _, _ = encode_colour(grey, 11)
    np.testing.assert_allclose(c11[:, 0], np.log(grey[:, 0] + 1e-5), rtol=1e-6)
    np.testing.assert_allclose(c11[:, 1:], 0.0, atol=1e-6)
    # hand-computed decodes: Y = exp(c0) - eps, U = c1 (Y + eps) with btflib's YUV constants
    y, u = 2.0, 0.5 * (2.0 + 1e-5)
    got = decode_colour(np.array([np.log(2.0 + 1e-5), 0.5, 0.0], np.float32), 11)
    np.testing.assert_allclose(got, [y, y - 0.39465 * u, y + 2.03211 * u], rtol=1e-6)
    np.testing.assert_allclose(decode_colour(np.zeros(3, np.float32), 11), [1 - 1e-5] * 3, rtol=1e-7)
    np.testing.assert_allclose(decode_colour(np.zeros(3, np.float32), 10), [1 - 1e-5] * 3, rtol=1e-7)
    got = decode_colour(np.array([0.0, np.log(2.0), -np.log(3.0)], np.float32), 10)
    np.testing.assert_allclose(got, [1 - 1e-5 - 1.13983 * 3e-5, 1 - 1e-5 - 0.39465 * 2e-5 + 0.5806 * 3e-5,
                                     1 - 1e-5 + 2.03211 * 2e-5], rtol=1e-6)
    np.testing.assert_allclose(decode_colour(np.full(3, np.log(1.0 + 1e-5), np.float32), 12), 1.0, rtol=1e-6)
    np.testing.assert_allclose(decode_colour(np.array([1.0, 0.0, 1.0], np.float32), 1), [2.13983, 0.4194, 1.0],
                               rtol=1e-6)


def test_pca_model_decorrelates_and_needs_mean_and_matrix() -> None:
    rng = np.random.default_rng(7)
    base = _hdr(rng, (500,))
    rgb = base * 0.1 + base.mean(axis=-1, keepdims=True)  # strongly correlated channels
    c, mean, matrix = encode_colour(rgb, 3)
    np.testing.assert_allclose(mean, rgb.mean(axis=0), rtol=1e-6)
    np.testing.assert_allclose(matrix.astype(np.float64) @ matrix.T, np.eye(3), atol=1e-6)
    cov = np.cov(c.astype(np.float64), rowvar=False)
    assert np.all(np.diff(np.diag(cov)) <= 0), "components by decreasing variance"
    np.testing.assert_allclose(cov - np.diag(np.diag(cov)), 0.0, atol=1e-4 * cov[0, 0])
    rows = np.arange(3)
    assert (matrix[rows, np.argmax(np.abs(matrix), axis=1)] > 0).all()
    with pytest.raises(ValueError, match="colour_mean"):
        decode_colour(c, 3)
    with pytest.raises(ValueError, match=r"shape \(3, 3\)"):
        decode_colour(c, 3, mean, matrix[:2])


def test_models_other_than_pca_return_btflibs_default_mean_and_matrix() -> None:
    rgb = _hdr(np.random.default_rng(1), (10,))
    for model in (0, 1, 4, 9, 10, 11, 12):
        _, mean, matrix = encode_colour(rgb, model)
        np.testing.assert_array_equal(mean, np.zeros(3))
        np.testing.assert_array_equal(matrix, np.eye(3))
        # and decoding ignores whatever mean/matrix the file holds
        c, _, _ = encode_colour(rgb, model)
        np.testing.assert_array_equal(decode_colour(c, model), decode_colour(c, model, np.ones(3), 2 * np.eye(3)))


@pytest.mark.parametrize("model", [7, 2, 5, 6, -1, 13, "1", 1.0, True, None])
def test_unknown_model_error_lists_supported_ids(model) -> None:
    c = np.zeros((2, 3), np.float32)
    for call in (lambda: decode_colour(c, model), lambda: encode_colour(c + 1, model)):
        with pytest.raises(UnknownColourModelError) as info:
            call()
        msg = str(info.value)
        assert isinstance(info.value, ValueError)
        for k, name in COLOUR_MODELS.items():
            assert f"{k} {name}" in msg
    err = pickle.loads(pickle.dumps(info.value))
    assert isinstance(err, UnknownColourModelError) and str(err) == msg and err.model == info.value.model


def test_btflib_models_not_decoded_here_say_why() -> None:
    with pytest.raises(UnknownColourModelError, match="Lab"):
        decode_colour(np.zeros(3, np.float32), 2)


@pytest.mark.parametrize(("model", "bad", "where"), [
    (11, [[1.0, 1.0, 1.0], [-1.0, -1.0, -1.0]], "[1]"),
    (9, [[-1.0, -1.0, -1.0]], "[0]"),
    (12, [[1.0, 1.0, 1.0], [1.0, -0.5, 1.0]], "[1, 1]"),
])
def test_encode_refuses_rgb_outside_the_models_domain(model: int, bad, where: str) -> None:
    with pytest.raises(ValueError, match=r"cannot encode") as info:
        encode_colour(np.array(bad), model)
    assert where in str(info.value)


def test_encode_refuses_non_finite_and_wrong_channel_counts() -> None:
    rgb = np.ones((3, 3))
    rgb[2, 1] = np.nan
    with pytest.raises(ValueError, match=r"rgb\[2, 1\]"):
        encode_colour(rgb, 0)
    with pytest.raises(ValueError, match="3 channels"):
        encode_colour(np.ones((4, 5)), 1)
    with pytest.raises(ValueError, match="3 channels"):
        decode_colour(np.ones((4, 2), np.float32), 11)


def test_models_0_and_12_take_any_channel_count() -> None:
    x = np.exp(np.random.default_rng(2).uniform(-5, 5, (6, 5)))
    for model in (0, 12):
        c, _, _ = encode_colour(x, model)
        assert c.shape == (6, 5)
        np.testing.assert_allclose(decode_colour(c, model), x, rtol=4 * F32 * 6)


def test_decode_leaves_its_input_alone_and_reads_read_only_float16() -> None:
    c = np.random.default_rng(5).uniform(-2, 2, (8, 8, 3)).astype(np.float16)
    c.setflags(write=False)
    before = c.copy()
    for model in sorted(COLOUR_MODELS):
        out = decode_colour(c, model, np.zeros(3), np.eye(3))
        assert out.dtype == np.float32 and out.shape == c.shape
        assert not np.shares_memory(out, c)
    np.testing.assert_array_equal(c, before)
    # float16 is computed in float32: same answer as the float32 copy
    np.testing.assert_array_equal(decode_colour(c, 11), decode_colour(c.astype(np.float32), 11))


def test_dynamic_range_reduction_and_restore() -> None:
    x = np.array([0.0, 1.0, 1e-3, 1e3, -0.5e-5])
    y = reduce_dynamic_range(x)
    np.testing.assert_allclose(y, np.log(x + 1e-5), rtol=1e-15)
    np.testing.assert_allclose(restore_dynamic_range(y), x, rtol=1e-12, atol=1e-17)
    np.testing.assert_allclose(restore_dynamic_range(np.zeros(2)), 1 - 1e-5, rtol=1e-15)
    y32 = reduce_dynamic_range(x.astype(np.float32))
    assert y32.dtype == np.float32
    assert restore_dynamic_range(y32.astype(np.float16)).dtype == np.float32
    np.testing.assert_allclose(restore_dynamic_range(y32), x, rtol=1e-6, atol=1e-9)
    with pytest.raises(ValueError, match=r"x\[1\]"):
        reduce_dynamic_range(np.array([1.0, -1e-5, -2.0]))
