"""Property-based tests (Hypothesis) of invariants the pipeline relies on."""

from __future__ import annotations

import json

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from btfcore.acquisition.hadamard import is_s_matrix_order, s_matrix, smallest_s_matrix_order
from btfcore.simulate.render import downsample2
from btfcore.simulate.sensor import bayer_channel_index, mosaic
from btfcore.render.tonemap import tonemap
from tasks.stores import to_json_attr

VALID_ORDERS = [n for n in range(3, 200) if is_s_matrix_order(n)]


@given(st.sampled_from(VALID_ORDERS))
def test_s_matrix_is_an_optimal_binary_multiplexing_code(n):
    S = s_matrix(n).astype(np.int64)
    assert set(np.unique(S)) == {0, 1}
    assert (S.sum(axis=1) == (n + 1) // 2).all()
    # S^T S = (n+1)/4 (I + J): every LED is on in (n+1)/2 patterns and every
    # pair of LEDs shares (n+1)/4 patterns (Harwit & Sloane).
    np.testing.assert_array_equal(4 * S.T @ S, (n + 1) * (np.eye(n, dtype=np.int64) + 1))


@given(st.integers(2, 400))
def test_smallest_order_covers_the_leds(n_leds):
    n = smallest_s_matrix_order(n_leds)
    assert n >= n_leds and is_s_matrix_order(n)
    assert not any(is_s_matrix_order(m) for m in range(n_leds, n))


@given(st.sampled_from(["RGGB", "BGGR", "GRBG", "GBRG"]), st.integers(1, 8), st.integers(1, 8))
def test_every_bayer_block_has_one_red_two_green_one_blue(pattern, half_rows, half_cols):
    index = bayer_channel_index(pattern, (2 * half_rows, 2 * half_cols))
    blocks = index.reshape(half_rows, 2, half_cols, 2).transpose(0, 2, 1, 3).reshape(-1, 4)
    for block in blocks:
        assert sorted(block.tolist()) == [0, 1, 1, 2]


@given(st.sampled_from(["RGGB", "BGGR", "GRBG", "GBRG"]),
       hnp.arrays(np.float64, (6, 8, 3), elements=st.floats(0, 1e3)))
def test_mosaic_picks_the_pixel_channel(pattern, rgb):
    raw = mosaic(rgb, pattern)
    index = bayer_channel_index(pattern, rgb.shape[:2])
    np.testing.assert_array_equal(raw, np.take_along_axis(rgb, index[..., None].astype(np.intp), 2)[..., 0])


@given(hnp.arrays(np.float64, st.tuples(st.integers(1, 3), st.integers(1, 6).map(lambda v: 2 * v),
                                        st.integers(1, 6).map(lambda v: 2 * v), st.just(3)),
                  elements=st.floats(0, 1e4)))
def test_downsample2_preserves_the_mean(btf):
    small = downsample2(btf)
    assert small.shape == (btf.shape[0], btf.shape[1] // 2, btf.shape[2] // 2, 3)
    np.testing.assert_allclose(small.mean(axis=(1, 2)), btf.mean(axis=(1, 2)), rtol=1e-9, atol=1e-9)


@given(hnp.arrays(np.float64, 32, elements=st.floats(0, 1e6)))
def test_tonemap_is_monotonic(values):
    order = np.argsort(values, kind="stable")
    mapped = tonemap(values, white=1.0)[order].astype(int)
    assert (np.diff(mapped) >= 0).all()


json_leaves = st.one_of(st.integers(-2**31, 2**31), st.floats(allow_nan=False, allow_infinity=False),
                        st.booleans(), st.text(max_size=5), st.none(),
                        st.integers(0, 255).map(np.uint8), st.floats(-1e6, 1e6).map(np.float32))


@settings(max_examples=50)
@given(st.recursive(json_leaves, lambda inner: st.one_of(st.lists(inner, max_size=3),
                                                          st.dictionaries(st.text(max_size=4), inner, max_size=3)),
                    max_leaves=12))
def test_store_attributes_become_plain_json(value):
    converted = to_json_attr(value)
    assert json.loads(json.dumps(converted, allow_nan=False)) == converted
