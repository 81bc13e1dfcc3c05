"""tasks.model on small stores written here: streamed evaluations equal their in-memory definitions."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import zarr

from btfcore.model.abtf import blend_patches, patch_matrix
from btfcore.model.colour import to_log_yuv
from tasks.buffers import prefaulted
from tasks.model import _bands, abtf_projection_errors, blocks, work_budget


def _store(path, btf: np.ndarray, band_rows: int) -> str:
    group = zarr.open_group(str(path), mode="w", zarr_format=3)
    group.create_array("btf", data=btf, chunks=(btf.shape[0], band_rows) + btf.shape[2:])
    return str(path)


@pytest.mark.parametrize("band_rows, budget", [(4, 1 << 30), (5, 1), (17, 3 * 9 * 12 * 14 * 8)])
def test_streamed_abtf_evaluation_equals_projecting_the_whole_texture(tmp_path, band_rows, budget):
    rng = np.random.default_rng(7)
    n_lv, h, w, p = 12, 17, 16, 3
    btf = rng.uniform(0.05, 1.0, (n_lv, h, w, 3)).astype(np.float32)
    log_y = to_log_yuv(btf)[..., 0].astype(np.float64)
    U = np.linalg.qr(rng.standard_normal((p * p * n_lv, 20)))[0]
    columns = patch_matrix(log_y, p, overlap=True)
    expected = {k: np.linalg.norm(blend_patches(U[:, :k] @ (U[:, :k].T @ columns), log_y.shape, p) - log_y)
                / np.linalg.norm(log_y) for k in (1, 2, 4, 8, 16, 20)}

    errors = abtf_projection_errors(_store(tmp_path / "m.zarr", btf, band_rows), U, p, budget)

    assert {k + 1 for k, e in enumerate(errors) if e is not None} == set(expected)
    for k, e in expected.items():
        assert errors[k - 1] == pytest.approx(e, rel=1e-10)


def test_work_budget_is_a_fraction_of_the_memory_outside_a_worker():
    assert work_budget(1 << 30) == (1 << 30) // 16
    assert work_budget(1000) == 1 << 20                     # never below 1 MiB


@pytest.mark.parametrize("multiple, max_bytes", [(1, None), (1, 1), (3, None), (3, 2 * 12 * 16 * 3 * 4), (1, 10**9)])
def test_bands_split_chunks_within_the_byte_bound_and_cover_every_usable_row(tmp_path, multiple, max_bytes):
    n_lv, h, w = 12, 23, 16
    btf = np.random.default_rng(0).uniform(0.1, 1, (n_lv, h, w, 3)).astype(np.float32)
    array = zarr.open_group(_store(tmp_path / "m.zarr", btf, 7), mode="r")["btf"]
    bands = _bands(array, multiple, max_bytes)
    usable = h - h % multiple
    assert [r for r0, r1 in bands for r in range(r0, r1)] == list(range(usable))
    for r0, r1 in bands:
        if multiple == 1:
            assert r0 // 7 == (r1 - 1) // 7                   # never straddles a store chunk
        assert (r1 - r0) % multiple == 0 or r1 == usable
        if max_bytes is not None and (r1 - r0) > multiple:
            assert 4 * n_lv * (r1 - r0) * w * 3 <= max_bytes


def test_blocks_of_a_matrix_within_the_bound_are_read_once_and_kept(tmp_path):
    btf = np.random.default_rng(2).uniform(0.1, 1, (12, 20, 16, 3)).astype(np.float32)
    path = _store(tmp_path / "m.zarr", btf, 8)
    for basis in ("log_y", "abtf_log_y"):
        kept, streamed = blocks(path, basis, max_bytes=10**7), blocks(path, basis, max_bytes=12 * 16 * 4 * 3)
        first = list(kept())
        np.testing.assert_array_equal(np.concatenate(first, axis=1), np.concatenate(list(streamed()), axis=1))
        shutil.move(path, tmp_path / "moved.zarr")           # the kept source no longer needs the store
        assert all(a is b for a, b in zip(first, kept()))
        gone = np.concatenate(list(streamed()), axis=1)     # a streamed source reads it on every pass:
        assert not np.array_equal(gone, np.concatenate(first, axis=1))   # zarr's fill values now
        shutil.move(tmp_path / "moved.zarr", path)


def test_blocks_under_a_byte_bound_hold_the_same_columns(tmp_path):
    btf = np.random.default_rng(1).uniform(0.1, 1, (12, 20, 16, 3)).astype(np.float32)
    path = _store(tmp_path / "m.zarr", btf, 8)
    for basis in ("log_y", "als", "abtf_log_y"):
        whole = np.concatenate(list(blocks(path, basis)()), axis=1)
        small = list(blocks(path, basis, max_bytes=12 * 16 * 3 * 4 * 3)())
        assert len(small) > 3
        np.testing.assert_array_equal(np.sort(np.concatenate(small, axis=1), axis=1), np.sort(whole, axis=1))


def test_transient_blocks_reuse_their_buffers_and_hold_the_same_values(tmp_path):
    """A fit's source (``transient=True``) reads every band into one of two buffers it keeps (one where
    only one band fits the bound), so a later pass allocates no band; consumed one block at a time it
    gives the blocks of a plain source."""
    btf = np.random.default_rng(5).uniform(0.1, 1, (12, 20, 16, 3)).astype(np.float32)
    path = _store(tmp_path / "m.zarr", btf, 8)
    one_band = 4 * 12 * 8 * 16 * 3
    for basis in ("als", "log_y"):
        plain = list(blocks(path, basis)())
        for max_bytes, n_buffers in ((None, 2), (one_band, 1)):
            source = blocks(path, basis, max_bytes=max_bytes, transient=True)
            seen, values = [], []
            for b in source():
                seen.append(b)
                values.append(b.copy())
            assert len(values) == len(plain) == 3
            for a, b in zip(values, plain):
                np.testing.assert_array_equal(a, b)
            if basis == "als":                                   # the blocks are views of the buffers
                buffers = seen[:n_buffers]
                assert not any(np.shares_memory(a, b) for i, a in enumerate(buffers) for b in buffers[i + 1:])
                for b in [*seen, *source()]:
                    assert sum(np.shares_memory(b, buffer) for buffer in buffers) == 1


def test_prefaulted_buffers_are_mapped_up_front_and_writable():
    """The band buffers of a fit: on Linux an anonymous mapping populated at once (no huge-page
    compaction at first touch), writable like ``numpy.empty``'s, freed with the array."""
    import mmap
    import weakref

    a = prefaulted(1000, np.float32)
    assert a.shape == (1000,) and a.dtype == np.float32 and a.flags.writeable
    a[:] = np.arange(1000)
    assert a[999] == 999
    if hasattr(mmap, "MAP_POPULATE"):
        backing = a.base.obj if isinstance(a.base, memoryview) else a.base
        assert isinstance(backing, mmap.mmap)
        gone = weakref.ref(backing)
        del a, backing
        assert gone() is None                                    # unmapped with the array
    assert prefaulted(0, np.float64).shape == (0,)


def test_reading_ahead_yields_the_same_blocks_in_the_same_order(tmp_path):
    """Without a bound (or where two bands fit it) the next band is read in a thread while the caller
    computes; with one band's bytes as the bound the same bands are read in turn."""
    btf = np.random.default_rng(4).uniform(0.1, 1, (12, 20, 16, 3)).astype(np.float32)
    path = _store(tmp_path / "m.zarr", btf, 8)
    one_band = 4 * 12 * 8 * 16 * 3
    for basis in ("log_y", "als", "abtf_log_y"):
        ahead, in_turn = list(blocks(path, basis)()), list(blocks(path, basis, max_bytes=one_band)())
        assert len(ahead) == len(in_turn) == 3
        for a, b in zip(ahead, in_turn):
            np.testing.assert_array_equal(a, b)
        source = blocks(path, basis)
        next(iter(source()))                                   # a pass left early leaves no thread behind
        assert len(list(source())) == 3
