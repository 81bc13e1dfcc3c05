"""Property-based tests (Hypothesis) of the colour transforms and ABTF patches (btfcore.model.colour, btfcore.model.abtf)."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from btfcore.model.abtf import blend_patches, patch_grid, patch_matrix, patch_rows
from btfcore.model.colour import from_log_yuv, nielsen_map, nielsen_unmap, rgb_to_yuv, to_log_yuv, yuv_to_rgb

pixels = st.integers(1, 6).map(lambda n: (n, 3))
radiance = st.floats(-1e6, 1e6, allow_subnormal=False)


@given(hnp.arrays(np.float64, pixels, elements=radiance))
def test_yuv_round_trip(rgb):
    bound = 1e-14 * np.abs(rgb).max(axis=-1, keepdims=True)
    assert (np.abs(yuv_to_rgb(rgb_to_yuv(rgb)) - rgb) <= bound).all()


@given(hnp.arrays(np.float64, pixels, elements=radiance), st.floats(1e-8, 1e2))
def test_log_yuv_round_trip_above_eps_and_grey_below(rgb, eps):
    y = rgb_to_yuv(rgb)[:, 0]
    want = rgb + np.maximum(eps - y, 0.0)[:, None]                 # exact where Y >= eps, grey added below
    bound = 1e-12 * (np.abs(rgb).max(axis=-1, keepdims=True) + eps)   # U, V carry the rounding of |rgb|
    assert (np.abs(from_log_yuv(to_log_yuv(rgb, eps)) - want) <= bound).all()


@given(hnp.arrays(np.float64, st.tuples(st.integers(1, 4), st.integers(1, 5)), elements=st.floats(0, 1e4)),
       st.floats(1e-4, 1.0), st.floats(0, 10.0), st.floats(1e-6, 1e-2))
def test_nielsen_round_trip(B, cosw, rho_ref, eps):
    n_lv = B.shape[0]
    cw, ref = np.full(n_lv, cosw), np.full(n_lv, rho_ref)
    back = nielsen_unmap(nielsen_map(B, cw, ref, eps), cw, ref, eps)
    assert (np.abs(back - B) <= 1e-12 * (B + eps / cosw)).all()


textures = st.tuples(st.integers(1, 3), st.integers(1, 4), st.integers(0, 5), st.integers(0, 5),
                     st.sampled_from([(), (1,), (3,)]))


@given(textures, st.sampled_from([np.float32, np.float64]), st.integers(0, 2**32 - 1))
def test_blending_all_patches_gives_back_the_btf(dims, dtype, seed):
    n_lv, p, extra_h, extra_w, channels = dims
    B = np.random.default_rng(seed).normal(size=(n_lv, p + extra_h, p + extra_w) + channels).astype(dtype)
    np.testing.assert_array_equal(blend_patches(patch_matrix(B, p, overlap=True), B.shape, p), B)


@given(textures, st.booleans(), st.integers(1, 4), st.integers(0, 2**32 - 1))
def test_band_by_band_patching_equals_whole(dims, overlap, band, seed):
    n_lv, p, extra_h, extra_w, channels = dims
    B = np.random.default_rng(seed).normal(size=(n_lv, p + extra_h, p + extra_w) + channels)
    ny, _ = patch_grid(B.shape[1], B.shape[2], p, overlap=overlap)
    parts = [patch_matrix(B[:, patch_rows(a, a + band, p, overlap=overlap)], p, overlap=overlap)
             for a in range(0, ny, band)]                           # the last band may run off the texture
    np.testing.assert_array_equal(np.concatenate(parts, axis=1), patch_matrix(B, p, overlap=overlap))
