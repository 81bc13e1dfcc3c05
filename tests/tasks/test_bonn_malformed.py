"""Malformed Bonn BTF files (docs/bonn-formats.md, "Malformed files").

Each case damages a valid file written by the project at a known byte and asserts a
BonnFormatError whose message names the file, ``byte <offset>`` of the bad field and the field.
Claims of huge counts must fail before anything of their size is allocated (tracemalloc peak
below the file's size). A seeded fuzz test flips, truncates and extends a small file 200 times:
every outcome is a successful read or a BonnFormatError.
"""

from __future__ import annotations

import io
import struct
import time
from dataclasses import dataclass

import numpy as np
import pytest
from traced import traced_peak

from btfcore.bonn.colour_models import COLOUR_MODELS
from tasks.bonn import BonnFormatError, make_header, write_common_header
from tasks.bonn.dfmf import read_factorised, write_dfmf, write_fmf
from tasks.bonn.header import meta_bytes
from tasks.bonn.pvf import PvfSlot, read_pvf, write_pvf

KS = (3, 2, 4)
N_V, N_L, W, H = 3, 4, 64, 64  # ~100 kB in half floats: tracemalloc peaks are measured against it


@dataclass
class Layout:
    """Byte offsets of the fields of the DFMF file built by :func:`_dfmf`."""

    data: bytes
    meta: int          # meta.size
    sampling: int      # sampling.n_v
    width: int
    n_rot: int
    body: int          # dfmf.max_components
    channels: list     # per channel: offset of its scalar size byte

    def view(self, v: int) -> int:  # offset of sampling.view_angles[v]
        return self.sampling + 4 + v * (12 + 8 * N_L)

    def k(self, c: int) -> int:
        return self.channels[c] + 1

    def rows(self, c: int) -> int:
        return self.channels[c] + 5


def _header(rng, **kw):
    views = np.stack([rng.uniform(0, 1.3, N_V), rng.uniform(-3, 3, N_V)], 1)
    lights = np.stack([rng.uniform(0, 1.3, N_L), rng.uniform(-3, 3, N_L)], 1)
    return make_header(views, lights, W, H, xml="<btf/>", **kw)


def _dfmf(seed: int = 0, n_rot: int = 1) -> Layout:
    rng = np.random.default_rng(seed)
    h = _header(rng, rotations=rng.standard_normal((n_rot, 3, 3)))
    S = [rng.random(k) for k in KS]
    U = [rng.standard_normal((h.n_lv, k)) for k in KS]
    SxV = [rng.standard_normal((h.n_tx, k)) for k in KS]
    buf = io.BytesIO()
    write_dfmf(buf, h, 0, np.zeros(3), np.eye(3), S, U, SxV, 2)
    hb = io.BytesIO()
    write_common_header(hb, h)
    body = len(hb.getvalue())
    sampling = 10 + len(meta_bytes(h))
    width = sampling + 4 + N_V * (12 + 8 * N_L)
    channels, at = [], body + 56
    for k in KS:
        channels.append(at)
        at += 13 + 2 * k * (1 + h.n_lv + h.n_tx)
    assert at == len(buf.getvalue())
    return Layout(buf.getvalue(), 10, sampling, width, width + 8, body, channels)


def _patch(data: bytes, offset: int, fmt: str, *values) -> bytes:
    out = bytearray(data)
    struct.pack_into(fmt, out, offset, *values)
    return bytes(out)


def _expect(tmp_path, data: bytes, offset: int, field: str, *, match: str | None = None,
            reader=read_factorised, name: str = "bad.btf", bounded: bool = False) -> BonnFormatError:
    path = tmp_path / name
    path.write_bytes(data)
    with pytest.raises(BonnFormatError) as info:
        reader(path)
    if bounded:                                               # in a fresh interpreter (tests/tasks/traced.py)
        peak, raised = traced_peak(reader, path)
        assert raised == "BonnFormatError" and peak < len(data), f"{peak} bytes allocated reading a {len(data)}-byte file"
    err = info.value
    text = str(err)
    assert str(path) in text and f"byte {offset}," in text and field in text, text
    assert (err.offset, err.field) == (offset, field)
    if match:
        assert match in text, text
    return err


# ------------------------------------------------------------------------ signature, truncation


def test_empty_file(tmp_path):
    _expect(tmp_path, b"", 0, "signature", match="unknown signature")


def test_wrong_signature(tmp_path):
    lay = _dfmf()
    _expect(tmp_path, b"!DFMX08FCR" + lay.data[10:], 0, "signature", match="!DFMF08FCR")


def test_pvf_given_to_the_factorised_reader(tmp_path):
    lay = _dfmf()
    _expect(tmp_path, b"!PVF06FCR" + lay.data[10:], 0, "signature", match="read_pvf")


def test_truncated_inside_the_meta_block(tmp_path):
    lay = _dfmf()
    _expect(tmp_path, lay.data[:100], lay.meta, "meta.size", match="truncated")


def test_truncated_inside_the_light_angles(tmp_path):
    lay = _dfmf()
    cut = lay.view(0) + 12 + 8 * N_L - 4  # the n_v check passes, view 0's lights do not fit
    _expect(tmp_path, lay.data[:cut], lay.view(0) + 8, "sampling.n_l[0]", match="truncated")


def test_truncated_inside_u_of_channel_1(tmp_path):
    lay = _dfmf()
    _expect(tmp_path, lay.data[:lay.channels[1] + 40], lay.k(1), "channel[1].components")


def test_truncated_by_one_byte(tmp_path):
    lay = _dfmf()
    _expect(tmp_path, lay.data[:-1], lay.k(2), "channel[2].components", match="truncated")


def test_trailing_garbage(tmp_path):
    lay = _dfmf()
    _expect(tmp_path, lay.data + b"\0" * 7, len(lay.data), "end_of_data", match="7 bytes")


# ------------------------------------------------------------------------------ counts and sizes


def test_meta_size_too_large(tmp_path):
    lay = _dfmf()
    size = struct.unpack_from("<I", lay.data, 10)[0]
    _expect(tmp_path, _patch(lay.data, 10, "<I", size + 4), 10, "meta.size",
            match="does not add up")


def test_meta_size_too_small(tmp_path):
    lay = _dfmf()
    size = struct.unpack_from("<I", lay.data, 10)[0]
    # the last channel name's 1 byte no longer fits in the block
    at = 10 + size - 5
    _expect(tmp_path, _patch(lay.data, 10, "<I", size - 1), at, "meta.channel_names[2].length",
            match="does not add up")


def test_unknown_meta_version(tmp_path):
    lay = _dfmf()
    _expect(tmp_path, _patch(lay.data, 14, "<I", 7), 14, "meta.version", match="[1, 2, 3, 4]")


def test_light_count_differs_between_views(tmp_path):
    lay = _dfmf()
    _expect(tmp_path, _patch(lay.data, lay.view(1) + 8, "<I", N_L - 1), lay.view(1) + 8,
            "sampling.n_l[1]", match="same light count")


def test_nan_angle(tmp_path):
    lay = _dfmf()
    _expect(tmp_path, _patch(lay.data, lay.view(1) + 4, "<f", float("nan")), lay.view(1),
            "sampling.view_angles[1]", match="not finite")


def test_rows_not_n_l_times_n_v(tmp_path):
    lay = _dfmf()
    _expect(tmp_path, _patch(lay.data, lay.rows(0), "<I", N_L * N_V + 1), lay.rows(0),
            "channel[0].rows", match="n_l * n_v")


def test_cols_not_width_times_height(tmp_path):
    lay = _dfmf()
    _expect(tmp_path, _patch(lay.data, lay.rows(1) + 4, "<I", W * H - W), lay.rows(1) + 4,
            "channel[1].cols", match="width * height")


def test_unknown_scalar_size(tmp_path):
    lay = _dfmf()
    _expect(tmp_path, _patch(lay.data, lay.channels[0], "<B", 3), lay.channels[0],
            "channel[0].scalar_size", match="2 half")


def test_mixed_scalar_sizes(tmp_path):
    lay = _dfmf()
    _expect(tmp_path, _patch(lay.data, lay.channels[2], "<B", 4), lay.channels[2],
            "channel[2].scalar_size", match="differs")


def test_unknown_colour_model_lists_the_supported_ones(tmp_path):
    lay = _dfmf()
    assert 99 not in COLOUR_MODELS
    err = _expect(tmp_path, _patch(lay.data, lay.body + 4, "<i", 99), lay.body + 4,
                  "dfmf.colour_model", match="unknown colour model 99")
    for model, name in COLOUR_MODELS.items():
        assert f"{model}: {name!r}" in str(err)


@pytest.mark.parametrize("what", ["n_v", "meta.size", "xml", "n_rot", "K"])
def test_huge_claims_fail_before_allocating(tmp_path, what):
    lay = _dfmf()
    big = 0xFFFFFFFF
    xml_len_at = 10 + 4 + 4 + 240 + 16 + 4
    at, field, data = {
        "n_v": (lay.sampling, "sampling.n_v", _patch(lay.data, lay.sampling, "<I", big)),
        "meta.size": (10, "meta.size", _patch(lay.data, 10, "<I", big - 3)),
        "xml": (xml_len_at, "meta.xml_length", _patch(lay.data, xml_len_at, "<I", big)),
        "n_rot": (lay.n_rot, "rotations.n_rot", _patch(lay.data, lay.n_rot, "<I", big)),
        "K": (lay.k(0), "channel[0].components", _patch(lay.data, lay.k(0), "<I", big)),
    }[what]
    _expect(tmp_path, data, at, field, bounded=True)


# -------------------------------------------------------------------------------------- FMF


def _fmf(seed: int = 1, **kw) -> tuple[bytes, int]:
    """A FMF12 file with a 6 x 4 height map and the offset of its extended header."""
    rng = np.random.default_rng(seed)
    h = _header(rng, rotations=np.eye(3)[None])
    k = 3
    buf = io.BytesIO()
    write_fmf(buf, h, np.ones(k), rng.standard_normal((3 * h.n_lv, k)),
              rng.standard_normal((h.n_tx, k)), 2, height_map=rng.random((6, 4)), **kw)
    hb = io.BytesIO()
    write_common_header(hb, h)
    return buf.getvalue(), len(hb.getvalue())


def test_fmf_rows_must_count_every_channel(tmp_path):
    data, ext = _fmf()
    rows_at = ext + 1 + 4 + 8 + 2 * 24 + 4 + 1 + 4
    assert struct.unpack_from("<I", data, rows_at)[0] == 3 * N_L * N_V
    _expect(tmp_path, _patch(data, rows_at, "<I", N_L * N_V), rows_at, "fmf.rows",
            match="n_channels * n_l * n_v")


def test_fmf_header_version_3_is_refused(tmp_path):
    data, ext = _fmf()
    _expect(tmp_path, _patch(data, ext, "<B", 3), ext, "fmf.header_version", match="up to 2")


def test_fmf_huge_height_map(tmp_path):
    data, ext = _fmf()
    _expect(tmp_path, _patch(data, ext + 5, "<II", 0xFFFFFFFF, 0xFFFFFFFF), ext + 5,
            "fmf.height_map_size", bounded=True)


# -------------------------------------------------------------------------------------- PVF


def _pvf(tmp_path, orientation="lights") -> tuple[bytes, int]:
    rng = np.random.default_rng(3)
    h = _header(rng)
    slots = []
    for _ in range(N_V):
        dim, n_w = (3 * N_L, W * H) if orientation == "lights" else (3 * W * H, N_L)
        slots.append(PvfSlot(2, rng.random(2), rng.random(dim), rng.random((dim, 2)),
                             rng.random((n_w, 2))))
    buf = io.BytesIO()
    write_pvf(buf, h, slots)
    hb = io.BytesIO()
    write_common_header(hb, h)
    # "!PVF06FCR" is one byte shorter than the "!DFMF08FCR" the header was measured with
    return buf.getvalue(), len(hb.getvalue()) - 1


def test_pvf_slot_count_must_equal_the_views(tmp_path):
    data, body = _pvf(tmp_path)
    _expect(tmp_path, _patch(data, body + 4, "<I", N_V + 1), body + 4, "pvf.n_slots",
            reader=read_pvf, name="bad.pvf", match="4 view slots for 3 views")


def test_pvf_slot_dimension_fits_no_orientation(tmp_path):
    data, body = _pvf(tmp_path)
    slot0 = body + 8
    # weights 5, dimension n_c n_l: neither texels nor lights for weights
    _expect(tmp_path, _patch(data, slot0 + 5, "<I", 5), slot0 + 9, "slot[0].dimension",
            reader=read_pvf, name="bad.pvf")


def test_pvf_truncated(tmp_path):
    data, body = _pvf(tmp_path)
    k, dim, n_w = 2, 3 * N_L, W * H
    slot_bytes = 1 + 12 + 2 * (k + dim + dim * k + n_w * k)
    _expect(tmp_path, data[:-3], len(data) - slot_bytes + 1, "slot[2].components",
            reader=read_pvf, name="bad.pvf", match="truncated")


# -------------------------------------------------------------------------------------- fuzz


def _small_files() -> list[tuple[bytes, object]]:
    rng = np.random.default_rng(7)
    views = rng.uniform(0, 1, (2, 2))
    h = make_header(views, rng.uniform(0, 1, (2, 2)), 3, 2, xml="<x/>", rotations=np.eye(3)[None])
    out = []
    buf = io.BytesIO()
    write_dfmf(buf, h, 0, np.zeros(3), np.eye(3), [np.ones(2)] * 3,
               [rng.random((4, 2)) for _ in range(3)], [rng.random((6, 2)) for _ in range(3)], 2)
    out.append((buf.getvalue(), read_factorised))
    buf = io.BytesIO()
    write_fmf(buf, h, np.ones(2), rng.random((12, 2)), rng.random((6, 2)), 4,
              dynamic_range_reduced=True, height_map=rng.random((2, 3)))
    out.append((buf.getvalue(), read_factorised))
    buf = io.BytesIO()
    write_pvf(buf, h, [PvfSlot(2, np.ones(2), rng.random(6), rng.random((6, 2)), rng.random((6, 2)))
                       for _ in range(2)])
    out.append((buf.getvalue(), read_pvf))
    return out


def _touch(result) -> None:
    """Use what a successful read returned: decode everything (the arrays must be sound)."""
    if hasattr(result, "decode_rows"):
        result.decode_rows(slice(None))
        return
    for u, sxv in zip(result.U, result.SxV):
        np.asarray(u, np.float64) @ np.asarray(sxv, np.float64).T


def test_fuzz_every_outcome_is_a_read_or_a_bonn_format_error(tmp_path):
    rng = np.random.default_rng(2024)
    files = _small_files()
    outcomes = {"read": 0, "error": 0}
    start = time.perf_counter()
    for i in range(200):
        data, reader = files[i % len(files)]
        buf = bytearray(data)
        op = rng.integers(4)
        if op == 0:    # flip 1-4 random bytes
            for at in rng.integers(len(buf), size=rng.integers(1, 5)):
                buf[at] = int(rng.integers(256))
        elif op == 1:  # truncate
            buf = buf[:rng.integers(len(buf))]
        elif op == 2:  # a random uint32 at a random place (counts become huge or small)
            at = int(rng.integers(len(buf) - 4))
            buf[at:at + 4] = struct.pack("<I", int(rng.choice([0, 1, 0xFFFFFFFF,
                                                                 rng.integers(1 << 32)])))
        else:          # trailing or inserted bytes
            at = int(rng.integers(len(buf) + 1))
            buf[at:at] = bytes(rng.integers(256, size=rng.integers(1, 9), dtype=np.uint8))
        path = tmp_path / f"fuzz{i}.bin"
        path.write_bytes(bytes(buf))
        try:
            result = reader(path)
        except BonnFormatError as e:
            assert str(path) in str(e) and "byte " in str(e)
            outcomes["error"] += 1
        else:
            with np.errstate(all="ignore"):
                _touch(result)
            outcomes["read"] += 1
        finally:
            path.unlink()
    assert outcomes["error"] > 100 and outcomes["read"] > 5, outcomes
    assert time.perf_counter() - start < 10
