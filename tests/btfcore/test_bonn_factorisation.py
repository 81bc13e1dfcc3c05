"""Decoding and computing the per-channel factorisations of DFMF/FMF files (btfcore.bonn.factorisation)."""

from __future__ import annotations

import numpy as np
import pytest

from btfcore.bonn import decode_colour, decode_textures, encode_colour, factorise
from threadpoolctl import threadpool_limits

from btfcore.bonn.factorisation import BLOCK_DIAGONAL_MAX_WASTE

F32 = float(np.finfo(np.float32).eps)


def _factors(rng: np.random.Generator, n_rows: int, n_tx: int, ks: tuple[int, ...], dtype=np.float32):
    U = [rng.standard_normal((n_rows, k)).astype(dtype) for k in ks]
    SxV = [(rng.standard_normal((n_tx, k)) * np.linspace(3, 0.1, k)).astype(dtype) for k in ks]
    return U, SxV


def _reference(U, SxV, rows, texels) -> tuple[np.ndarray, np.ndarray]:
    """float64 product of the factors as given (and the |U| |SxV|^T bound of float32 rounding)."""
    ref = np.stack([np.asarray(u, np.float64)[rows] @ np.asarray(s, np.float64)[texels].T for u, s in zip(U, SxV)], -1)
    mag = np.stack([np.abs(np.asarray(u, np.float64)[rows]) @ np.abs(np.asarray(s, np.float64)[texels]).T
                    for u, s in zip(U, SxV)], -1)
    return ref, mag


def _check(out, U, SxV, rows, texels, rtol_units: float = 4.0) -> None:
    ref, mag = _reference(U, SxV, rows, texels)
    assert out.dtype == np.float32 and out.shape == ref.shape
    if np.asarray(U[0]).dtype == np.float64:  # rounded to float32 before the GEMM
        rtol_units += 2.0
    k = max(np.shape(u)[1] for u in U) or 1
    assert (np.abs(out - ref) <= rtol_units * k * F32 * mag + 1e-30).all()


@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.float64])
@pytest.mark.parametrize(("rows", "texels"), [
    (slice(None), slice(None)),
    (slice(3, 40, 2), slice(5, None, 3)),
    (np.array([7, 0, 7, 44, -1]), np.array([90, 2, 2, 0, 119])),
    (slice(None, None, -1), np.arange(0, 120, 7)),
    (np.arange(10), slice(100, 20, -4)),
])
def test_decode_equals_float64_reference(dtype, rows, texels) -> None:
    U, SxV = _factors(np.random.default_rng(0), 45, 120, (5, 3, 7), dtype)
    out = decode_textures(U, SxV, rows, texels)
    _check(out, U, SxV, rows, texels)


def test_decode_writes_into_out_and_returns_it() -> None:
    U, SxV = _factors(np.random.default_rng(1), 30, 50, (4, 4, 2))
    out = np.full((6, 50, 3), np.nan, np.float32)
    got = decode_textures(U, SxV, np.arange(6) * 5, out=out)
    assert got is out
    _check(out, U, SxV, np.arange(6) * 5, slice(None))


def test_decode_into_a_strided_out_view() -> None:
    """``out`` need not be C-contiguous: a view of a larger array, or channel-planar storage."""
    U, SxV = _factors(np.random.default_rng(2), 20, 40, (3, 3, 3))
    big = np.zeros((20, 80, 3), np.float32)
    view = big[:, ::2]
    decode_textures(U, SxV, slice(None), out=view)
    _check(view, U, SxV, slice(None), slice(None))
    assert (big[:, 1::2] == 0).all(), "only the view was written"
    planar = np.empty((3, 20, 40), np.float32).transpose(1, 2, 0)
    decode_textures(U, SxV, slice(None), out=planar)
    _check(planar, U, SxV, slice(None), slice(None))


def test_decode_crosses_texel_tiles_in_both_paths(monkeypatch) -> None:
    rng = np.random.default_rng(3)
    # small rank: one block-structured GEMM per texel tile (16,384 texels at most)
    U, SxV = _factors(rng, 9, 40_001, (5, 6, 4))
    texels = np.sort(rng.choice(40_001, 33_000, replace=False))
    _check(decode_textures(U, SxV, slice(None), texels), U, SxV, slice(None), texels)
    # tiles of 64 texels (the smallest) and, into a strided out, row blocks of 5 rows
    import btfcore.bonn.factorisation as fact
    monkeypatch.setattr(fact, "_TILE_BYTES", 4096)
    U, SxV = _factors(rng, 23, 1_000, (5, 6, 4))
    _check(decode_textures(U, SxV, slice(None), slice(3, None)), U, SxV, slice(None), slice(3, None))
    planar = np.empty((3, 23, 997), np.float32).transpose(1, 2, 0)
    decode_textures(U, SxV, slice(None), slice(3, None), out=planar)
    _check(planar, U, SxV, slice(None), slice(3, None))
    monkeypatch.undo()
    # rank above the block-diagonal limit: per-channel GEMMs interleaved by cv2.merge, in tiles that the
    # selection crosses (tiles of 16 rows x texels here), on one thread and on two row shares
    monkeypatch.setattr(fact, "_MERGE_TILE", 16)
    k = BLOCK_DIAGONAL_MAX_WASTE // 4 + 1
    U, SxV = _factors(rng, 300, 1_000, (k, k, 3), np.float16)
    texels = np.arange(999, -1, -3)
    for threads in (1, 2):
        with threadpool_limits(threads, "blas"):
            _check(decode_textures(U, SxV, slice(None), texels), U, SxV, slice(None), texels)
            # a channel-planar out cannot take cv2.merge: the strided copy writes it
            planar = np.empty((3, 300, texels.size), np.float32).transpose(1, 2, 0)
            decode_textures(U, SxV, slice(None), texels, out=planar)
            _check(planar, U, SxV, slice(None), texels)
            wide = np.zeros((300, texels.size + 7, 3), np.float32)   # interleaved rows of a wider array:
            decode_textures(U, SxV, slice(None), texels, out=wide[:, 7:])   # cv2.merge writes in place
            _check(wide[:, 7:], U, SxV, slice(None), texels)
            assert (wide[:, :7] == 0).all(), "only the view was written"


def test_decode_from_a_float16_memmap_on_disk_leaves_the_file_alone(tmp_path) -> None:
    rng = np.random.default_rng(4)
    n_rows, n_tx, ks = 36, 64, (6, 2, 2)
    U, SxV = _factors(rng, n_rows, n_tx, ks, np.float16)
    path = tmp_path / "factors.bin"
    with open(path, "wb") as f:
        for u, s in zip(U, SxV):
            f.write(u.tobytes())
            f.write(s.tobytes())
    before = path.read_bytes()
    mU, mS, offset = [], [], 0
    for k in ks:
        mU.append(np.memmap(path, np.float16, "r", offset, (n_rows, k)))
        offset += n_rows * k * 2
        mS.append(np.memmap(path, np.float16, "r", offset, (n_tx, k)))
        offset += n_tx * k * 2
    out = decode_textures(mU, mS, np.array([35, 0, 17]), slice(10, 60))
    _check(out, U, SxV, np.array([35, 0, 17]), slice(10, 60))
    assert path.read_bytes() == before


def test_decode_edge_cases() -> None:
    U, SxV = _factors(np.random.default_rng(5), 8, 10, (3, 0, 2))
    out = decode_textures(U, SxV, slice(None))
    _check(out, U, SxV, slice(None), slice(None))
    assert (out[..., 1] == 0).all(), "a channel with no components decodes to zero"
    assert decode_textures(U, SxV, np.array([], dtype=int)).shape == (0, 10, 3)
    assert decode_textures(U, SxV, slice(None), slice(4, 4)).shape == (8, 0, 3)
    # a single channel of any rank is one plain GEMM per tile
    bu, bs = _factors(np.random.default_rng(6), 8, 40, (500,))
    _check(decode_textures(bu, bs, slice(None), slice(3, 9)), bu, bs, slice(None), slice(3, 9))
    one = decode_textures(U[:1], SxV[:1], slice(2, 3))
    assert one.shape == (1, 10, 1)
    np.testing.assert_allclose(one[0, :, 0], U[0][2] @ SxV[0].T, rtol=1e-5)


def test_decode_refuses_bad_input() -> None:
    U, SxV = _factors(np.random.default_rng(6), 8, 10, (3, 3, 3))
    with pytest.raises(ValueError, match="same count"):
        decode_textures(U, SxV[:2], slice(None))
    with pytest.raises(ValueError, match="components"):
        decode_textures(U, [SxV[0], SxV[1][:, :2], SxV[2]], slice(None))
    with pytest.raises(ValueError, match="differ"):
        decode_textures(U, [SxV[0], SxV[1][:9], SxV[2]], slice(None))
    with pytest.raises(ValueError, match="1-D integer"):
        decode_textures(U, SxV, np.array([0.0, 1.0]))
    with pytest.raises(ValueError, match="scalar"):
        decode_textures(U, SxV, 3)
    with pytest.raises(IndexError, match="out of bounds"):
        decode_textures(U, SxV, slice(None), np.array([0, 10]))
    with pytest.raises(ValueError, match="float32 array of shape"):
        decode_textures(U, SxV, slice(None), out=np.empty((8, 10, 3)))
    with pytest.raises(ValueError, match="float32 array of shape"):
        decode_textures(U, SxV, slice(None), out=np.empty((8, 10, 2), np.float32))


def _spectrum_matrix(rng: np.random.Generator, n_rows: int, n_tx: int) -> tuple[np.ndarray, np.ndarray]:
    q1 = np.linalg.qr(rng.standard_normal((n_rows, n_rows)))[0]
    q2 = np.linalg.qr(rng.standard_normal((n_tx, n_rows)))[0]
    sigma = 2.0 ** -np.arange(n_rows, dtype=float) * 10
    return (q1 * sigma) @ q2.T, sigma


@pytest.mark.parametrize("k", [1, 3, 7])
def test_factorise_is_the_best_rank_k_approximation(k: int) -> None:
    B, sigma = _spectrum_matrix(np.random.default_rng(k), 12, 40)
    S, U, SxV = factorise(B, k)
    assert S.shape == (k,) and U.shape == (12, k) and SxV.shape == (40, k)
    assert S.dtype == U.dtype == SxV.dtype == np.float64
    np.testing.assert_allclose(S, sigma[:k], rtol=1e-12)
    np.testing.assert_allclose(U.T @ U, np.eye(k), atol=1e-13)
    # SxV = V * S with orthonormal V
    np.testing.assert_allclose((SxV / S).T @ (SxV / S), np.eye(k), atol=1e-12)
    err = np.sum((B - U @ SxV.T) ** 2)
    np.testing.assert_allclose(err, np.sum(sigma[k:] ** 2), rtol=1e-9, atol=1e-28)


def test_factorise_sign_convention_is_deterministic() -> None:
    B = np.random.default_rng(8).standard_normal((15, 25))
    S, U, SxV = factorise(B, 6)
    cols = np.arange(6)
    assert (U[np.argmax(np.abs(U), axis=0), cols] > 0).all()
    S2, U2, SxV2 = factorise(-B, 6)
    np.testing.assert_allclose(S2, S, rtol=1e-13)
    np.testing.assert_allclose(U2, U, atol=1e-12)
    np.testing.assert_allclose(SxV2, -SxV, atol=1e-12)
    again = factorise(B, 6)
    for a, b in zip(again, (S, U, SxV)):
        np.testing.assert_array_equal(a, b)


def test_factorise_clips_k_and_refuses_bad_input() -> None:
    B = np.random.default_rng(9).standard_normal((10, 7)).astype(np.float32)
    S, U, SxV = factorise(B, 100)
    assert S.shape == (7,) and U.shape == (10, 7) and SxV.shape == (7, 7)
    np.testing.assert_allclose(U @ SxV.T, B, atol=1e-5)
    for bad_k in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="k must be"):
            factorise(B, bad_k)
    B[3, 4] = np.nan
    with pytest.raises(ValueError, match=r"B\[3, 4\]"):
        factorise(B, 2)
    with pytest.raises(ValueError, match="2-D"):
        factorise(np.ones(5), 1)


def test_encode_factorise_store_half_decode_round_trip() -> None:
    """The whole DFMF path: RGB -> model 11 -> per-channel SVD -> float16 factors -> decode -> RGB."""
    rng = np.random.default_rng(11)
    n_lv, n_tx = 24, 300
    # a low-rank positive HDR BTF: per-texel albedo times per-direction lobes
    albedo = np.exp(rng.uniform(-3, 1, (n_tx, 3)))
    lobes = np.exp(rng.uniform(-2, 2, (n_lv, 1)))
    rgb = lobes[:, :, None] * albedo[None] * (1 + 0.1 * rng.standard_normal((n_lv, 1, 1)))
    channels, mean, matrix = encode_colour(rgb, 11)
    U, SxV = [], []
    for c in range(3):
        _, u, sxv = factorise(channels[..., c], n_lv)  # full rank: exact up to float16 storage
        U.append(u.astype(np.float16))
        SxV.append(sxv.astype(np.float16))
    stored = decode_textures(U, SxV, slice(None))
    back = decode_colour(stored, 11, mean, matrix)
    rel = np.abs(back - rgb) / rgb.max(axis=-1, keepdims=True)
    assert np.median(rel) < 3e-3 and rel.max() < 5e-2, "float16 factors: about half-float precision"
