"""BDI (``!BDIF06R2!``) reader and writer: layout against a file built by hand, round trips, laziness,
bounded memory, malformed files and a small fuzz test (docs/bonn-formats.md, "BDI")."""

from __future__ import annotations

import bz2
import dataclasses
import io
import pickle
import struct
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from traced import fresh_call, traced_peak

from tasks.bonn.bdi import (BDI_SIGNATURE, BZIP2, BZIP2_LEVEL, RAW, SPARSE, Bdi, read_bdi,
                            rewrite_bdi, write_bdi)
from tasks.bonn.errors import BonnFormatError
from tasks.bonn.header import make_header, write_common_header

COMPRESSIONS = (RAW, BZIP2, SPARSE)


def _header(rng, n_v=2, n_l=3, w=5, h=7, channels=("R", "G", "B"), rotations=None):
    views = rng.uniform(0, 1.2, (n_v, 2))
    lights = [rng.uniform(0, 1.2, (n_l, 2)) for _ in range(n_v)]
    return make_header(views, lights, w, h, signature=BDI_SIGNATURE, channel_names=channels,
                       xml="<m/>", measurement_setup="dome", rotations=rotations)


def _textures(rng, header) -> np.ndarray:
    shape = (header.n_lv, header.height, header.width, header.n_channels)
    return rng.uniform(0, 4, shape).astype(np.float32)


def _half(x: np.ndarray) -> np.ndarray:
    return x.astype(np.float16).astype(np.float32)


def _expect(fn, path, offset: int, field: str, words: str = "") -> BonnFormatError:
    with pytest.raises(BonnFormatError) as info:
        fn()
    err, text = info.value, str(info.value)
    assert str(path) in text and f"byte {offset}," in text and field in text, text
    assert err.offset == offset and err.field == field, (err.offset, err.field, text)
    assert words in text, text
    return err


# ---------------------------------------------------------------------------------- layout


def _hand_built(path: Path, compression: int, mask: np.ndarray, lines: int, header, value) -> None:
    """A BDI assembled field by field from the documented layout, not by write_bdi."""
    h, w = mask.shape
    n_l, n_v, n_c = header.n_l, header.n_v, header.n_channels
    stored = [(x, y) for y in range(h) for x in range(w) if compression != SPARSE or mask[y, x]]
    per_chunk = w * lines
    buf = io.BytesIO()
    write_common_header(buf, header)
    buf.write(struct.pack("<IB", lines, compression))
    buf.write(bytes(int(mask[y, x]) for y in range(h) for x in range(w)))   # byte x + w * y
    rot = header.rotations
    buf.write(struct.pack("<I", len(rot)) + np.asarray(rot, "<f4").tobytes())
    for start in range(0, len(stored), per_chunk):
        vals = []
        for x, y in stored[start:start + per_chunk]:
            for v in range(n_v):
                for l in range(n_l):
                    for c in range(n_c):
                        vals.append(value(c, l, v, x, y) if mask[y, x] else 0.0)
        data = np.asarray(vals, "<f2").tobytes()
        if compression == BZIP2:
            data = bz2.compress(data, 9)
        buf.write(struct.pack("<I", len(data)) + data)
    path.write_bytes(buf.getvalue())


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_a_hand_built_file_reads_texel_x_y_light_view_channel_where_documented(tmp_path, compression):
    rng = np.random.default_rng(1)
    rot = rng.normal(size=(2, 3, 3)).astype(np.float32)
    header = _header(rng, n_v=2, n_l=2, w=3, h=5, rotations=rot)   # non-square, 5 % 2 != 0
    mask = np.ones((5, 3), bool)
    mask[0, 2] = mask[3, 0] = mask[4, 1] = False                    # asymmetric: catches x/y swaps

    def value(c, l, v, x, y):   # exact in half floats (integers < 2048), distinct per index
        return c + 4 * l + 16 * v + 64 * x + 256 * y

    path = tmp_path / "hand.bdi"
    _hand_built(path, compression, mask, 2, header, value)
    bdi = read_bdi(path)
    assert (bdi.width, bdi.height, bdi.lines_per_chunk, bdi.compression) == (3, 5, 2, compression)
    np.testing.assert_array_equal(bdi.mask, mask)
    np.testing.assert_array_equal(bdi.header.rotations, rot)
    assert bdi.n_stored == (12 if compression == SPARSE else 15)
    assert bdi.n_chunks == (2 if compression == SPARSE else 3)
    tex = bdi.read_texture_rows(0, 5)
    assert tex.shape == (4, 5, 3, 3) and tex.dtype == np.float32
    for v in range(2):
        for l in range(2):
            for y in range(5):
                for x in range(3):
                    for c in range(3):
                        want = value(c, l, v, x, y) if mask[y, x] else 0.0
                        assert tex[l + 2 * v, y, x, c] == want, (l, v, x, y, c)
    # and the writer produces exactly these bytes from the textures
    out = tmp_path / "written.bdi"
    write_bdi(out, header, tex, compression=compression, lines_per_chunk=2, mask=mask)
    assert out.read_bytes() == path.read_bytes()


def test_a_padded_last_chunk_as_btflib_writes_from_memory_is_read_and_kept(tmp_path):
    rng = np.random.default_rng(2)
    header = _header(rng, w=4, h=6)
    tex = _textures(rng, header)
    for compression in COMPRESSIONS:
        short, padded = tmp_path / f"s{compression}.bdi", tmp_path / f"p{compression}.bdi"
        write_bdi(short, header, tex, compression=compression)
        write_bdi(padded, header, tex, compression=compression, pad_last_chunk=True)
        a, b = read_bdi(short), read_bdi(padded)
        assert not a.last_chunk_padded() and b.last_chunk_padded()
        if compression != BZIP2:
            assert b.chunk_nbytes[-1] == 2 * a.chunk_nbytes[-1]   # 2 of 4 lines -> 4 of 4
        np.testing.assert_array_equal(a.read_texture_rows(0, 6), b.read_texture_rows(0, 6))
        rewrite_bdi(b, tmp_path / "again.bdi")
        assert (tmp_path / "again.bdi").read_bytes() == padded.read_bytes()


# ---------------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("compression", COMPRESSIONS)
@pytest.mark.parametrize("lines", [1, 4, 5])
def test_write_read_write_is_byte_identical_and_values_are_half_rounded(tmp_path, compression, lines):
    rng = np.random.default_rng(10 + lines)
    header = _header(rng, n_v=3, n_l=2, w=6, h=9, channels=("450", "550", "650", "750"))
    tex = _textures(rng, header)
    mask = rng.uniform(size=(9, 6)) > 0.25
    first = tmp_path / "a.bdi"
    write_bdi(first, header, tex, compression=compression, lines_per_chunk=lines, mask=mask)
    bdi = read_bdi(first)
    assert dataclasses.replace(bdi.header, rotations=None) == header and bdi.header.xml == "<m/>"
    assert bdi.header.rotations.shape == (0, 3, 3)
    assert bdi.header.channel_names == ("450", "550", "650", "750")
    want = np.where(mask[None, :, :, None], _half(tex), 0)
    got = bdi.read_texture_rows(0, 9)
    np.testing.assert_array_equal(got, want)
    present = np.broadcast_to(mask[None, :, :, None], got.shape)
    assert np.abs(got - tex)[present].max() <= 2**-10       # half rounding of values in [0, 4)
    second = tmp_path / "b.bdi"
    write_bdi(second, bdi.header, bdi.read_texture_rows, compression=compression,
              lines_per_chunk=lines, mask=bdi.mask)
    assert second.read_bytes() == first.read_bytes()
    rewrite_bdi(bdi, tmp_path / "c.bdi")
    assert (tmp_path / "c.bdi").read_bytes() == first.read_bytes()


def test_sparse_stores_only_present_abrdfs_and_absent_texels_read_as_zero(tmp_path):
    rng = np.random.default_rng(3)
    header = _header(rng, w=8, h=8)
    tex = _textures(rng, header)
    mask = np.zeros((8, 8), bool)
    mask[2:5, 1:7] = True
    paths = {c: tmp_path / f"{c}.bdi" for c in COMPRESSIONS}
    for c, p in paths.items():
        write_bdi(p, header, tex, compression=c, mask=mask)
    raw, sparse = read_bdi(paths[RAW]), read_bdi(paths[SPARSE])
    abrdf = header.n_lv * 3 * 2
    assert sparse.n_stored == 18 and sparse.chunk_nbytes.sum() == 18 * abrdf
    assert raw.chunk_nbytes.sum() == 64 * abrdf
    for c in COMPRESSIONS:
        tex_c = read_bdi(paths[c]).read_texture_rows(0, 8)
        assert np.all(tex_c[:, ~mask] == 0)
        np.testing.assert_array_equal(tex_c[:, mask], _half(tex)[:, mask])


def test_values_under_the_mask_are_kept_only_when_asked(tmp_path):
    rng = np.random.default_rng(4)
    header = _header(rng, w=4, h=4)
    tex = _textures(rng, header)
    mask = np.eye(4, dtype=bool)
    kept, zeroed = tmp_path / "kept.bdi", tmp_path / "zeroed.bdi"
    write_bdi(kept, header, tex, mask=mask, zero_absent=False)
    write_bdi(zeroed, header, tex, mask=mask)
    bdi = read_bdi(kept)
    np.testing.assert_array_equal(bdi.read_texture_rows(0, 4, apply_mask=False), _half(tex))
    assert np.all(bdi.read_texture_rows(0, 4)[:, ~mask] == 0)
    assert np.all(read_bdi(zeroed).read_texture_rows(0, 4, apply_mask=False)[:, ~mask] == 0)
    rewrite_bdi(bdi, tmp_path / "again.bdi")
    assert (tmp_path / "again.bdi").read_bytes() == kept.read_bytes()


def test_mask_bytes_other_than_one_mean_present_and_survive_a_rewrite(tmp_path):
    rng = np.random.default_rng(5)
    header = _header(rng, w=3, h=2)
    mask = np.array([[255, 0, 1], [7, 1, 0]], np.uint8)
    path = tmp_path / "m.bdi"
    write_bdi(path, header, _textures(rng, header), compression=SPARSE, mask=mask)
    bdi = read_bdi(path)
    np.testing.assert_array_equal(bdi.mask_values, mask)
    assert bdi.n_stored == 4
    rewrite_bdi(bdi, tmp_path / "again.bdi")
    assert (tmp_path / "again.bdi").read_bytes() == path.read_bytes()


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_read_abrdfs_agrees_with_the_textures(tmp_path, compression):
    rng = np.random.default_rng(6)
    header = _header(rng, w=7, h=10)
    mask = rng.uniform(size=(10, 7)) > 0.3
    path = tmp_path / "t.bdi"
    write_bdi(path, header, _textures(rng, header), compression=compression, mask=mask)
    bdi = read_bdi(path)
    tex = bdi.read_texture_rows(0, 10)
    x, y = rng.integers(0, 7, 40), rng.integers(0, 10, 40)
    np.testing.assert_array_equal(bdi.read_abrdfs(x, y), tex[:, y, x])
    with pytest.raises(IndexError, match="outside"):
        bdi.read_abrdfs([7], [0])


def test_bzip2_chunks_are_the_raw_chunks_compressed_at_level_9(tmp_path):
    rng = np.random.default_rng(7)
    header = _header(rng, w=5, h=9)
    tex = _textures(rng, header)
    write_bdi(tmp_path / "raw.bdi", header, tex, compression=RAW)
    write_bdi(tmp_path / "bz.bdi", header, tex, compression=BZIP2)
    write_bdi(tmp_path / "bz2.bdi", header, tex, compression=BZIP2)
    assert (tmp_path / "bz.bdi").read_bytes() == (tmp_path / "bz2.bdi").read_bytes()
    raw, bz = read_bdi(tmp_path / "raw.bdi"), read_bdi(tmp_path / "bz.bdi")
    assert BZIP2_LEVEL == 9 and raw.n_chunks == bz.n_chunks == 3
    rb, zb = (tmp_path / "raw.bdi").read_bytes(), (tmp_path / "bz.bdi").read_bytes()
    for k in range(3):
        r0, z0 = int(raw.chunk_offsets[k]) + 4, int(bz.chunk_offsets[k]) + 4
        chunk = rb[r0:r0 + int(raw.chunk_nbytes[k])]
        assert zb[z0:z0 + int(bz.chunk_nbytes[k])] == bz2.compress(chunk, 9)


def test_a_header_of_another_format_is_written_as_bdi_and_a_bdi_pickles(tmp_path):
    rng = np.random.default_rng(12)
    rot = rng.normal(size=(1, 3, 3))
    header = make_header(rng.uniform(size=(2, 2)), rng.uniform(size=(3, 2)), 4, 5,
                         signature="!DFMF08FCR", rotations=rot)
    path = tmp_path / "from_dfmf.bdi"
    write_bdi(path, header, _textures(rng, header), compression=BZIP2)
    assert path.read_bytes().startswith(BDI_SIGNATURE.encode())
    bdi = read_bdi(path)
    assert bdi.header.signature == BDI_SIGNATURE
    np.testing.assert_array_equal(bdi.header.rotations, rot.astype(np.float32))
    first = bdi.read_texture_rows(0, 5)                       # fills the chunk cache
    copy = pickle.loads(pickle.dumps(bdi))                    # as Dask ships it to a worker
    assert copy._cache is None
    np.testing.assert_array_equal(copy.read_texture_rows(0, 5), first)


# ---------------------------------------------------------------------------------- laziness, memory


def test_reading_rows_decodes_only_their_chunks(tmp_path):
    rng = np.random.default_rng(8)
    header = _header(rng, w=4, h=12)
    tex = _textures(rng, header)
    path = tmp_path / "lazy.bdi"
    write_bdi(path, header, tex, compression=BZIP2)          # chunks of rows 0-3, 4-7, 8-11
    bdi = read_bdi(path)
    data = bytearray(path.read_bytes())
    start = int(bdi.chunk_offsets[1]) + 4
    n = int(bdi.chunk_nbytes[1])
    data[start + n // 2:start + n // 2 + 8] = bytes(8)        # chunk 1 no longer decompresses
    path.write_bytes(bytes(data))
    bdi = read_bdi(path)                                      # opening decompresses nothing
    assert list(bdi.chunks_for_rows(2, 9)) == [0, 1, 2]
    np.testing.assert_array_equal(bdi.read_texture_rows(0, 4), _half(tex)[:, 0:4])
    np.testing.assert_array_equal(bdi.read_texture_rows(8, 12), _half(tex)[:, 8:12])
    _expect(lambda: bdi.read_texture_rows(3, 5), path, start, "chunk 1 data", "decompress")


def _source(n_lv: int, w: int, n_c: int):
    def source(y0, y1):
        return np.random.default_rng(y0).uniform(0, 1, (n_lv, y1 - y0, w, n_c)).astype(np.float32)
    return source


def _traced_peaks(path: str, compression: int, n_lv: int, h: int, w: int, n_c: int) -> dict:
    """Write, open and read one band of a BDI under tracemalloc; run in a fresh interpreter."""
    rng = np.random.default_rng(9)
    header = make_header(rng.uniform(0, 1, (6, 2)), rng.uniform(0, 1, (8, 2)), w, h,
                         signature=BDI_SIGNATURE)
    calls = []
    band = _source(n_lv, w, n_c)

    def source(y0, y1):
        calls.append((y0, y1))
        return band(y0, y1)

    mask = np.ones((h, w), bool)
    mask[::3] = False
    tracemalloc.start()
    bz2.compress(bytes(1000), BZIP2_LEVEL)                   # bzip2's own fixed state (~7.6 MB)
    _, bz2_state = tracemalloc.get_traced_memory()
    tracemalloc.reset_peak()
    write_bdi(path, header, source, compression=compression, mask=mask)
    _, peak_write = tracemalloc.get_traced_memory()
    tracemalloc.reset_peak()
    bdi = read_bdi(path)
    _, peak_open = tracemalloc.get_traced_memory()
    tracemalloc.reset_peak()
    bdi.read_texture_rows(100, 104)
    _, peak_rows = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return dict(bz2_state=bz2_state, write=peak_write, open=peak_open, rows=peak_rows, calls=calls)


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_write_and_read_hold_one_band_in_memory(tmp_path, compression):
    # measured in a fresh interpreter: tracemalloc would charge other tests' threads to the reader
    n_lv, h, w, n_c = 48, 256, 32, 3
    full_bytes = n_lv * h * w * n_c * 4                       # 4.7 MB of float32
    band_bytes = n_lv * 4 * w * n_c * 4                       # 74 kB per chunk of 4 lines
    path = tmp_path / "big.bdi"
    peaks = fresh_call(_traced_peaks, str(path), compression, n_lv, h, w, n_c)   # tests/tasks/traced.py
    assert 12 * band_bytes < full_bytes / 5
    assert peaks["write"] < 12 * band_bytes + (peaks["bz2_state"] if compression == BZIP2 else 0), peaks
    assert peaks["open"] < h * w + 100_000, peaks             # the mask and little more
    assert peaks["rows"] < 12 * band_bytes, peaks
    calls = peaks["calls"]
    assert all(y1 - y0 <= 4 for y0, y1 in calls)
    assert [y for y0, y1 in calls for y in range(y0, y1)] == list(range(h))   # each band once
    mask = np.ones((h, w), bool)
    mask[::3] = False
    want = np.where(mask[None, 100:104, :, None], _half(_source(n_lv, w, n_c)(100, 104)), 0)
    np.testing.assert_array_equal(read_bdi(path).read_texture_rows(100, 104), want)


def test_writer_refuses_shapes_masks_and_values_it_cannot_store(tmp_path):
    rng = np.random.default_rng(11)
    header = _header(rng, w=3, h=4)
    tex = _textures(rng, header)
    path = tmp_path / "x.bdi"
    with pytest.raises(ValueError, match="shape"):
        write_bdi(path, header, tex[:, :3])
    with pytest.raises(ValueError, match="mask"):
        write_bdi(path, header, tex, mask=np.ones((3, 4), bool))
    with pytest.raises(ValueError, match="compression"):
        write_bdi(path, header, tex, compression=3)
    with pytest.raises(ValueError, match="lines_per_chunk"):
        write_bdi(path, header, tex, lines_per_chunk=0)
    big = tex.copy()
    big[1, 2, 0, 1] = 70000.0
    with pytest.raises(ValueError, match="half-float range"):
        write_bdi(path, header, big)
    with pytest.raises(ValueError, match=r"textures\(0, 4\) returned shape"):
        write_bdi(path, header, lambda y0, y1: tex[:, y0:y1, :2])
    assert not path.exists() and not list(tmp_path.iterdir())   # nothing half-written left


# ---------------------------------------------------------------------------------- malformed files


def _good(tmp_path, compression=RAW, name="good.bdi", w=5, h=9, mask=None) -> tuple[Path, Bdi]:
    rng = np.random.default_rng(20)
    header = _header(rng, w=w, h=h)
    path = tmp_path / name
    write_bdi(path, header, _textures(rng, header), compression=compression, mask=mask)
    return path, read_bdi(path)


def _patch(path: Path, offset: int, data: bytes) -> None:
    raw = bytearray(path.read_bytes())
    raw[offset:offset + len(data)] = data
    path.write_bytes(bytes(raw))


def test_truncated_chunk_table(tmp_path):
    path, bdi = _good(tmp_path)
    chunks = bdi.field_offsets["chunks"]
    path.write_bytes(path.read_bytes()[:chunks + 6])          # three chunks need 12 bytes of counts
    _expect(lambda: read_bdi(path), path, chunks, "chunk table", "3 chunks")


def test_truncated_inside_the_chunks_of_a_raw_file(tmp_path):
    path, bdi = _good(tmp_path)
    path.write_bytes(path.read_bytes()[:int(bdi.chunk_offsets[2]) + 10])
    _expect(lambda: read_bdi(path), path, bdi.field_offsets["chunks"], "chunk table", "truncated")


def test_chunk_byte_count_beyond_the_file(tmp_path):
    path, bdi = _good(tmp_path, BZIP2)
    at = int(bdi.chunk_offsets[1])
    _patch(path, at, struct.pack("<I", 0xFFFFFFF0))
    _expect(lambda: read_bdi(path), path, at, "chunk 1 byte count", "only")


def test_raw_chunk_byte_count_that_does_not_match_its_abrdfs(tmp_path):
    path, bdi = _good(tmp_path)
    data = path.read_bytes()
    at = int(bdi.chunk_offsets[0])
    n = int(bdi.chunk_nbytes[0])
    path.write_bytes(data[:at] + struct.pack("<I", n - 2) + data[at + 4:at + 4 + n - 2]
                     + data[at + 4 + n:])
    _expect(lambda: read_bdi(path), path, at, "chunk 0 byte count", f"{n} bytes")


def test_bzip2_chunk_that_fails_to_decompress(tmp_path):
    path, bdi = _good(tmp_path, BZIP2)
    start = int(bdi.chunk_offsets[0]) + 4
    _patch(path, start, b"XYZ!")                              # not even a bzip2 stream header
    bdi = read_bdi(path)
    _expect(lambda: bdi.read_texture_rows(0, 1), path, start, "chunk 0 data", "decompress")


def test_bzip2_chunk_of_the_wrong_decompressed_size(tmp_path):
    path, bdi = _good(tmp_path, BZIP2)
    data = path.read_bytes()
    at, n = int(bdi.chunk_offsets[2]), int(bdi.chunk_nbytes[2])
    want = bdi.chunk_abrdfs(2) * bdi.abrdf_nbytes
    short = bz2.compress(bytes(want - 6), 9)
    path.write_bytes(data[:at] + struct.pack("<I", len(short)) + short + data[at + 4 + n:])
    bdi = read_bdi(path)
    _expect(lambda: bdi.read_texture_rows(8, 9), path, at + 4, "chunk 2 data",
            f"decompresses to {want - 6} bytes")
    long = bz2.compress(bytes(10 * want), 9)                  # never inflated past the limit
    path.write_bytes(data[:at] + struct.pack("<I", len(long)) + long + data[at + 4 + n:])
    bdi = read_bdi(path)
    _expect(lambda: bdi.read_texture_rows(8, 9), path, at + 4, "chunk 2 data", "more than")


def test_bzip2_chunk_with_a_cut_stream(tmp_path):
    path, bdi = _good(tmp_path, BZIP2)
    data = path.read_bytes()
    at, n = int(bdi.chunk_offsets[2]), int(bdi.chunk_nbytes[2])
    path.write_bytes(data[:at] + struct.pack("<I", n - 20) + data[at + 4:at + 4 + n - 20])
    bdi = read_bdi(path)
    _expect(lambda: bdi.read_texture_rows(8, 9), path, at + 4, "chunk 2 data")


def test_unknown_compression_code(tmp_path):
    path, bdi = _good(tmp_path)
    at = bdi.field_offsets["compression"]
    _patch(path, at, bytes([7]))
    _expect(lambda: read_bdi(path), path, at, "compression", "unknown code 7")


def test_zero_scan_lines_per_chunk(tmp_path):
    path, bdi = _good(tmp_path)
    at = bdi.field_offsets["scan lines per chunk"]
    _patch(path, at, struct.pack("<I", 0))
    _expect(lambda: read_bdi(path), path, at, "scan lines per chunk", "is 0")


def test_mask_larger_than_the_file_is_refused_before_allocating(tmp_path):
    path, bdi = _good(tmp_path)
    width_at = bdi.field_offsets["scan lines per chunk"] - 8
    _patch(path, width_at, struct.pack("<II", 1 << 20, 1 << 20))   # a 1 TiB mask
    _expect(lambda: read_bdi(path), path, bdi.field_offsets["mask"], "mask", "needs")
    peak, raised = traced_peak(read_bdi, path)      # in a fresh interpreter: this one's threads allocate too
    assert raised == "BonnFormatError" and peak < path.stat().st_size + 100_000, (peak, raised)


def test_mask_that_does_not_match_the_chunks(tmp_path):
    mask = np.ones((9, 5), bool)
    path, bdi = _good(tmp_path, SPARSE, mask=mask)           # 45 ABRDFs: chunks of 20, 20, 5
    _patch(path, bdi.field_offsets["mask"] + 7, bytes([0]))  # now 44: the last chunk should hold 4
    _expect(lambda: read_bdi(path), path, int(bdi.chunk_offsets[2]), "chunk 2 byte count",
            "4 ABRDFs")


def test_rotation_count_beyond_the_file(tmp_path):
    path, bdi = _good(tmp_path)
    at = bdi.field_offsets["rotations"]
    _patch(path, at, struct.pack("<I", 1 << 30))
    _expect(lambda: read_bdi(path), path, at, "rotations.n_rot", "needs")


def test_bytes_after_the_last_chunk(tmp_path):
    path, bdi = _good(tmp_path)
    size = path.stat().st_size
    path.write_bytes(path.read_bytes() + b"\0\0\0")
    _expect(lambda: read_bdi(path), path, size, "end of file", "3 bytes")


def test_a_file_of_another_format(tmp_path):
    rng = np.random.default_rng(21)
    path = tmp_path / "dfmf.btf"
    buf = io.BytesIO()
    write_common_header(buf, make_header(rng.uniform(size=(2, 2)), rng.uniform(size=(2, 2)), 2, 2))
    path.write_bytes(buf.getvalue())
    _expect(lambda: read_bdi(path), path, 0, "signature", "not a BDI")
    (tmp_path / "junk.bdi").write_bytes(b"!BDIF05!" + bytes(40))
    _expect(lambda: read_bdi(tmp_path / "junk.bdi"), tmp_path / "junk.bdi", 0, "signature")


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_fuzz_damaged_files_decode_or_raise_a_format_error(tmp_path, compression):
    """Truncations and byte flips: every damaged file either opens and decodes to the right shape or
    raises BonnFormatError; nothing else escapes (no IndexError, no MemoryError, no numpy error)."""
    mask = np.random.default_rng(22).uniform(size=(9, 5)) > 0.2
    path, bdi = _good(tmp_path, compression, mask=mask)
    good = path.read_bytes()
    rng = np.random.default_rng(23 + compression)
    damaged = tmp_path / "damaged.bdi"
    outcomes = {"ok": 0, "error": 0}
    for _ in range(150):
        data = bytearray(good)
        if rng.uniform() < 0.3:
            data = data[:int(rng.integers(0, len(good)))]
        else:
            for _ in range(int(rng.integers(1, 4))):
                # mostly the header and the chunk table, where the structure is
                i = int(rng.integers(0, bdi.field_offsets["chunks"] + 40) if rng.uniform() < 0.8
                        else rng.integers(0, len(good)))
                data[i] = int(rng.integers(0, 256))
        damaged.write_bytes(bytes(data))
        try:
            got = read_bdi(damaged)
            tex = got.read_texture_rows(0, got.height)
            assert tex.shape == (got.n_lv, got.height, got.width, got.n_channels)
            outcomes["ok"] += 1
        except BonnFormatError as err:
            assert str(damaged) in str(err) and "byte " in str(err)
            outcomes["error"] += 1
    assert outcomes["ok"] > 0 and outcomes["error"] > 0, outcomes
