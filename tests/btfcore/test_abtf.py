"""ABTF patches: stacking order, the thesis' counts, kron(I, M), rank, blending, band-wise patching, bad input."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from btfcore.model.abtf import blend_patches, patch_grid, patch_matrix, patch_rows


def _btf(shape, dtype=np.float64, seed=0):
    return np.random.default_rng(seed).lognormal(-2, 1, shape).astype(dtype)


@pytest.mark.parametrize("overlap, count", [(False, 1764), (True, 126 * 126)])
def test_column_counts_of_the_thesis(overlap, count):
    assert np.prod(patch_grid(128, 128, 3, overlap=overlap)) == count      # paper 1, §4.1.2: 1764 per material
    P = patch_matrix(np.zeros((2, 128, 128, 3), np.float32), 3, overlap=overlap)
    assert P.shape == (9 * 2, count * 3) and P.dtype == np.float32


@pytest.mark.parametrize("overlap", [False, True])
@pytest.mark.parametrize("shape, p", [((3, 7, 8, 2), 3), ((2, 5, 4), 2), ((2, 4, 6, 3), 1)])
def test_stacking_order(shape, p, overlap):
    B = _btf(shape)
    P = patch_matrix(B, p, overlap=overlap)
    B4 = B if B.ndim == 4 else B[..., None]
    n_lv, h, w, C = B4.shape
    ny, nx = patch_grid(h, w, p, overlap=overlap)
    s = 1 if overlap else p
    assert P.shape == (p * p * n_lv, ny * nx * C)
    for iy, ix, c, dy, dx in itertools.product(range(ny), range(nx), range(C), range(p), range(p)):
        np.testing.assert_array_equal(P[(dy * p + dx) * n_lv:(dy * p + dx + 1) * n_lv, (iy * nx + ix) * C + c],
                                      B4[:, iy * s + dy, ix * s + dx, c])


def test_kron_identity_measures_every_texel_of_a_patch():
    n_lv, n_s, p = 6, 4, 3
    B = _btf((n_lv, 5, 7, 3))
    M = np.random.default_rng(1).integers(0, 2, (n_s, n_lv)).astype(float)
    measured = np.einsum("sl,lyxc->syxc", M, B)
    for overlap in (False, True):
        np.testing.assert_allclose(np.kron(np.eye(p * p), M) @ patch_matrix(B, p, overlap=overlap),
                                   patch_matrix(measured, p, overlap=overlap), rtol=1e-12)


def test_rank_of_patches():
    rng = np.random.default_rng(2)
    abrdf = rng.random(5)
    same = np.broadcast_to(abrdf[:, None, None], (5, 9, 9)).copy()
    P = patch_matrix(same, 3, overlap=True)
    assert np.linalg.matrix_rank(P) == 1                                   # identical ABRDFs: one ABTF
    np.testing.assert_array_equal(P, np.tile(abrdf, 9)[:, None] * np.ones(P.shape[1]))
    # two materials (ABRDFs a, b) in stripes 4 texels wide: a 3 x 3 column is (a, a, a) + sum_i d_i e_i (x) (b - a)
    # per patch column i with d in {0, 1}^3 (aaa, aab, abb, bbb, bba, baa): rank 1 + p
    b = rng.random(5)
    stripes = np.where((np.arange(12) // 4 % 2 == 0)[None, None, :], abrdf[:, None, None], b[:, None, None])
    stripes = np.broadcast_to(stripes, (5, 12, 12))
    assert np.linalg.matrix_rank(patch_matrix(stripes, 3, overlap=True)) == 4
    assert np.linalg.matrix_rank(patch_matrix(stripes, 1, overlap=True)) == 2


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("shape, p", [((4, 9, 11, 3), 3), ((2, 6, 5), 2), ((3, 3, 3), 3), ((2, 7, 4, 1), 4)])
def test_blending_all_patches_gives_back_the_btf_exactly(shape, p, dtype):
    B = _btf(shape, dtype)
    out = blend_patches(patch_matrix(B, p, overlap=True), B.shape, p)
    assert out.dtype == dtype
    np.testing.assert_array_equal(out, B)


def test_blending_weights_every_covering_patch_equally():
    n_lv, h, w, p = 2, 6, 7, 3
    ny, nx = patch_grid(h, w, p, overlap=True)
    patch_value = np.random.default_rng(3).random((ny, nx))                # each patch one constant value
    cols = np.broadcast_to(patch_value.ravel(), (p * p * n_lv, ny * nx))
    want = np.zeros((h, w))
    for y, x in itertools.product(range(h), range(w)):                       # brute force: mean of covering patches
        cover = [patch_value[iy, ix] for iy in range(ny) for ix in range(nx)
                 if iy <= y < iy + p and ix <= x < ix + p]
        want[y, x] = np.mean(cover)
    out = blend_patches(cols, (n_lv, h, w), p)
    np.testing.assert_allclose(out, np.broadcast_to(want, (n_lv, h, w)), rtol=1e-14)
    assert out[0, 0, 0] == patch_value[0, 0] and out[0, -1, -1] == patch_value[-1, -1]   # corners: one patch


@pytest.mark.parametrize("overlap", [False, True])
@pytest.mark.parametrize("band", [1, 2, 5, 100])
def test_band_by_band_equals_whole(overlap, band):
    p = 3
    B = _btf((4, 17, 10, 3), np.float32)
    whole = patch_matrix(B, p, overlap=overlap)
    ny, _ = patch_grid(17, 10, p, overlap=overlap)
    parts = [patch_matrix(B[:, patch_rows(a, min(a + band, ny), p, overlap=overlap)], p, overlap=overlap)
             for a in range(0, ny, band)]
    np.testing.assert_array_equal(np.concatenate(parts, axis=1), whole)


def test_patch_rows_by_hand():
    assert patch_rows(2, 4, 3, overlap=True) == slice(2, 6)                 # windows at rows 2, 3 read rows 2..5
    assert patch_rows(2, 4, 3, overlap=False) == slice(6, 12)               # tiles 2, 3 read rows 6..11


@pytest.mark.parametrize("call, match", [
    (lambda: patch_matrix(np.ones((2, 2, 5)), 3, overlap=True), "a 2 x 5 texture has no 3 x 3 patch"),
    (lambda: patch_matrix(np.ones((2, 5)), 3, overlap=True), "B must have 3 or 4 dimensions"),
    (lambda: patch_matrix(np.ones((2, 5, 5)), 0, overlap=False), "patch size p must be an integer >= 1"),
    (lambda: patch_matrix(np.ones((2, 5, 5)), 2.5, overlap=False), "patch size p"),
    (lambda: patch_matrix(np.pad(np.ones((1, 4, 4)), ((0, 0), (0, 0), (0, 1)), constant_values=np.nan), 3,
                          overlap=True), r"B\[0, 0, 4\] = nan is not finite \(4 NaN/Inf"),
    (lambda: blend_patches(patch_matrix(np.ones((2, 6, 6)), 3, overlap=False), (2, 6, 6), 3),
     r"columns must be \(18, 16\), the overlapping 3 x 3 patches"),
    (lambda: blend_patches(np.ones((18, 16)), (2, 6), 3), "texture_shape must be"),
    (lambda: patch_rows(3, 3, 3, overlap=True), "0 <= start < stop"),
])
def test_bad_input_is_refused(call, match):
    with pytest.raises(ValueError, match=match):
        call()
