"""Bonn BTF file layouts: common header, DFMF, FMF, PVF (docs/bonn-formats.md, "File layout").

Real files in tmp_path, seeded synthetic factors. Every format is written, read back lazily
(np.memmap), its values compared with the factors, and rewritten byte for byte.
"""

from __future__ import annotations

import dataclasses
import filecmp
import io
import struct

import numpy as np
import pytest
from traced import traced_peak

from tasks.bonn import (SIGNATURES, BonnFormatError, CommonHeader, make_header, open_reader,
                        read_common_header, read_signature, write_common_header)
from tasks.bonn.dfmf import Factorised, read_factorised, rewrite, write_dfmf, write_fmf
from tasks.bonn.header import meta_bytes
from tasks.bonn.pvf import PvfSlot, read_pvf, rewrite_pvf, write_pvf

HALF_TOL = 4e-3  # relative, products of half floats


def _header(rng, n_v=3, n_l=4, width=5, height=2, **kw) -> CommonHeader:
    views = np.stack([rng.uniform(0, 1.4, n_v), rng.uniform(-np.pi, np.pi, n_v)], 1)
    lights = np.stack([rng.uniform(0, 1.4, n_l), rng.uniform(-np.pi, np.pi, n_l)], 1)
    return make_header(views, lights, width, height, **kw)


def _dfmf_factors(rng, header, ks=(3, 2, 4)):
    S = [np.sort(rng.random(k))[::-1] for k in ks]
    U = [rng.standard_normal((header.n_lv, k)) for k in ks]
    SxV = [rng.standard_normal((header.n_tx, k)) for k in ks]
    return S, U, SxV


def _same_bytes(a, b) -> bool:
    return filecmp.cmp(a, b, shallow=False)


# ------------------------------------------------------------------------------ common header


def test_header_round_trip_is_exact_and_the_meta_size_counts_from_its_own_field(tmp_path):
    rng = np.random.default_rng(0)
    h = _header(rng, xml="<measurement date='2014'>é ü</measurement>", measurement_setup="dome 1",
                image_sensor="Canon", light_source="LED", ppmm=11.5, cosine_flag=True,
                rgb_scale_factor=(1.5, 1.0, 0.75), rotations=rng.standard_normal((2, 3, 3)))
    path = tmp_path / "h.bin"
    with open(path, "wb") as f:
        write_common_header(f, h)
    data = path.read_bytes()
    assert data[:10] == b"!DFMF08FCR"
    meta = meta_bytes(h)
    (size,) = struct.unpack_from("<I", data, 10)
    assert size == len(meta) and data[10:10 + size] == meta  # size field included in the count
    assert struct.unpack_from("<I", data, 14)[0] == 4  # version
    with open_reader(path) as r:
        sig = read_signature(r)
        back = read_common_header(r, sig)
        assert r.offset == len(data)
    assert back == h and back.xml == h.xml and back.cosine_flag is True
    assert back.rotations.shape == (2, 3, 3) and back.rotations.dtype == np.float32
    np.testing.assert_array_equal(back.rotations, h.rotations)
    out = io.BytesIO()
    write_common_header(out, back)
    assert out.getvalue() == data


def test_rotation_blocks_are_nine_floats_each(tmp_path):
    rng = np.random.default_rng(1)
    rot = rng.standard_normal((3, 3, 3)).astype(np.float32)
    h = _header(rng, rotations=rot)
    buf = io.BytesIO()
    write_common_header(buf, h)
    data = buf.getvalue()
    assert struct.unpack_from("<I", data, len(data) - 4 - 36 * 3)[0] == 3
    np.testing.assert_array_equal(np.frombuffer(data[-36 * 3:], "<f4").reshape(3, 3, 3), rot)


@pytest.mark.parametrize("version", [1, 2, 3, 4])
def test_every_meta_version_round_trips(tmp_path, version):
    rng = np.random.default_rng(version)
    kw = dict(version=version, cosine_flag=version > 1, xml="<x/>" if version > 2 else "")
    h = _header(rng, **kw)
    path = tmp_path / "h.bin"
    with open(path, "wb") as f:
        write_common_header(f, h)
    expected_meta = 4 + 4 + 240 + 16 + (4 if version > 1 else 0) + (8 if version > 2 else 0) \
        + (4 + 3 * 5 if version > 3 else 0)
    assert struct.unpack_from("<I", path.read_bytes(), 10)[0] == expected_meta
    with open_reader(path) as r:
        back = read_common_header(r, read_signature(r))
    assert back == h and back.channel_names == ("R", "G", "B")


def test_raw_string_bytes_after_the_nul_survive_a_rewrite(tmp_path):
    rng = np.random.default_rng(2)
    h = _header(rng, measurement_setup="setup")
    buf = io.BytesIO()
    write_common_header(buf, h)
    data = bytearray(buf.getvalue())
    # garbage after the terminating NUL of the first string (C writers leave stack bytes there)
    at = 10 + 8 + len("setup") + 1
    data[at:at + 4] = b"\x7fjk\x01"
    path = tmp_path / "h.bin"
    path.write_bytes(bytes(data))
    with open_reader(path) as r:
        back = read_common_header(r, read_signature(r))
    assert back.measurement_setup == "setup"
    out = io.BytesIO()
    write_common_header(out, back)
    assert out.getvalue() == bytes(data)
    changed = dataclasses.replace(back, measurement_setup="other")  # a new value writes clean
    out = io.BytesIO()
    write_common_header(out, changed)
    assert out.getvalue()[18:18 + 80] == b"other".ljust(80, b"\0")


def test_directions_follow_row_order_light_fastest():
    rng = np.random.default_rng(3)
    h = _header(rng, n_v=2, n_l=3)
    assert (h.n_v, h.n_l, h.n_lv, h.n_tx, h.n_channels) == (2, 3, 6, 10, 3)
    L, V = h.light_dir(), h.view_dir()
    assert L.shape == V.shape == (6, 3)
    np.testing.assert_allclose(np.linalg.norm(L, axis=1), 1.0)
    t, p = h.light_angles[1][2].astype(np.float64)
    np.testing.assert_allclose(L[2 + 3 * 1], [np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])
    t, p = h.view_angles[1].astype(np.float64)
    np.testing.assert_allclose(V[0 + 3 * 1], [np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])
    np.testing.assert_array_equal(V[3], V[5])


def test_signatures_prefer_the_longest_match(tmp_path):
    for sig in SIGNATURES:
        p = tmp_path / "s.bin"
        p.write_bytes(sig.encode() + b"\x00" * 8)
        with open_reader(p) as r:
            assert read_signature(r) == sig and r.offset == len(sig)


def test_error_text_and_pickling():
    import pickle

    e = BonnFormatError("/a/b.btf", 42, "channel[1].rows", "12, expected 9", "re-export it")
    assert str(e) == "/a/b.btf: byte 42, channel[1].rows: 12, expected 9; re-export it"
    assert isinstance(e, ValueError)
    back = pickle.loads(pickle.dumps(e))
    assert str(back) == str(e) and (back.path, back.offset, back.field) == ("/a/b.btf", 42,
                                                                            "channel[1].rows")


# ------------------------------------------------------------------------------------- DFMF


@pytest.mark.parametrize("scalar_size", [2, 4, 8])
def test_dfmf_round_trip(tmp_path, scalar_size):
    rng = np.random.default_rng(10 + scalar_size)
    h = _header(rng, rotations=rng.standard_normal((1, 3, 3)), cosine_flag=True)
    S, U, SxV = _dfmf_factors(rng, h)
    mean, matrix = rng.random(3), rng.random((3, 3))
    a, b = tmp_path / "a.btf", tmp_path / "b.btf"
    write_dfmf(a, h, 1, mean, matrix, S, U, SxV, scalar_size)
    # layout: signature, header, uint32 K, int32 model, mean, matrix, per channel blocks
    hb = io.BytesIO()
    write_common_header(hb, h)
    body = 4 + 4 + 12 + 36 + sum(1 + 12 + scalar_size * k * (1 + h.n_lv + h.n_tx)
                                 for k in (3, 2, 4))
    assert a.stat().st_size == len(hb.getvalue()) + body
    assert struct.unpack_from("<Ii", a.read_bytes(), len(hb.getvalue())) == (4, 1)

    f = read_factorised(a)
    assert isinstance(f, Factorised) and f.format == "dfmf" and f.scalar_size == scalar_size
    assert f.header == h and f.colour_model == 1 and f.components == [3, 2, 4]
    np.testing.assert_allclose(f.colour_mean, mean.astype(np.float32))
    np.testing.assert_allclose(f.colour_matrix, matrix.astype(np.float32))
    tol = HALF_TOL if scalar_size == 2 else 1e-6
    for c in range(3):
        assert isinstance(f.U[c], np.memmap) and isinstance(f.SxV[c], np.memmap)
        assert f.U[c].shape == (h.n_lv, U[c].shape[1]) and f.SxV[c].shape == (h.n_tx, U[c].shape[1])
        want = U[c] @ SxV[c].T
        got = f.U[c].astype(np.float64) @ f.SxV[c].astype(np.float64).T
        assert np.abs(got - want).max() <= tol * np.abs(want).max() * 4
    rewrite(f, b)
    assert _same_bytes(a, b)
    # a file object target writes the same bytes
    buf = io.BytesIO()
    rewrite(read_factorised(b), buf)
    assert buf.getvalue() == a.read_bytes()


def test_dfmf_multispectral_and_without_rotations(tmp_path):
    rng = np.random.default_rng(20)
    h = _header(rng, channel_names=("450", "550", "650", "750", "850"))
    S, U, SxV = _dfmf_factors(rng, h, ks=(1, 2, 3, 2, 1))
    a, b = tmp_path / "a.btf", tmp_path / "b.btf"
    write_dfmf(a, h, 0, np.zeros(3), np.eye(3), S, U, SxV, 4)
    f = read_factorised(a)
    assert f.header.channel_names == ("450", "550", "650", "750", "850") and f.n_channels == 5
    assert f.header.rotations.shape == (0, 3, 3)  # DFMF always has the block; here it is empty
    rewrite(f, b)
    assert _same_bytes(a, b)


def test_writers_refuse_values_beyond_half_range_and_wrong_shapes(tmp_path):
    rng = np.random.default_rng(21)
    h = _header(rng)
    S, U, SxV = _dfmf_factors(rng, h)
    U[1][2, 0] = 1e6
    with pytest.raises(ValueError, match=r"U\[1\] row 2.*scalar_size"):
        write_dfmf(tmp_path / "x.btf", h, 0, np.zeros(3), np.eye(3), S, U, SxV, 2)
    write_dfmf(tmp_path / "x.btf", h, 0, np.zeros(3), np.eye(3), S, U, SxV, 4)  # single holds it
    with pytest.raises(ValueError, match=r"SxV\[0\] has shape"):
        write_dfmf(tmp_path / "x.btf", h, 0, np.zeros(3), np.eye(3), S, U, [SxV[0][:-1]] + SxV[1:])
    with pytest.raises(ValueError, match="scalar_size 3"):
        write_dfmf(tmp_path / "x.btf", h, 0, np.zeros(3), np.eye(3), S, U, SxV, 3)


def test_reading_a_large_file_reads_none_of_its_matrices(tmp_path):
    rng = np.random.default_rng(22)
    h = _header(rng, n_v=4, n_l=4, width=128, height=128)
    k = 8
    S = [np.ones(k)] * 3
    U = [rng.standard_normal((h.n_lv, k)).astype(np.float32)] * 3
    SxV = [rng.standard_normal((h.n_tx, k)).astype(np.float32)] * 3
    path = tmp_path / "big.btf"
    write_dfmf(path, h, 0, np.zeros(3), np.eye(3), S, U, SxV, 4)
    size = path.stat().st_size
    assert size > 1_000_000
    peak, raised = traced_peak(read_factorised, path)        # in a fresh interpreter (tests/tasks/traced.py)
    assert raised is None and peak < size / 20, f"reading allocated {peak} bytes of a {size}-byte file"
    f = read_factorised(path)
    np.testing.assert_array_equal(f.SxV[2][-1], SxV[2][-1])  # the last texel, from the file


# -------------------------------------------------------------------------------------- FMF


@pytest.mark.parametrize("scalar_size", [2, 4])
@pytest.mark.parametrize("kind", ["fmf12-height-map", "fmf12-plain", "fmf06R", "fmf06"])
def test_fmf_round_trip(tmp_path, kind, scalar_size):
    rng = np.random.default_rng(30 + scalar_size)
    rot = None if kind == "fmf06" else rng.standard_normal((2, 3, 3))
    h = _header(rng, rotations=rot, signature="!FMF06FC" if rot is None else "!FMF06FCR")
    if rot is None:
        h = dataclasses.replace(h, rotations=None)
    n_c, k = 3, 5
    S = np.sort(rng.random(k))[::-1]
    U_full = rng.standard_normal((n_c * h.n_lv, k))
    SxV = rng.standard_normal((h.n_tx, k))
    extended = kind.startswith("fmf12")
    hm = rng.random((6, 4)) if kind == "fmf12-height-map" else None
    a, b = tmp_path / "a.btf", tmp_path / "b.btf"
    write_fmf(a, h, S, U_full, SxV, scalar_size, dynamic_range_reduced=extended, height_map=hm,
              extended=extended)
    sig = {"fmf12-height-map": "!FMF12FCER", "fmf12-plain": "!FMF12FCER", "fmf06R": "!FMF06FCR",
           "fmf06": "!FMF06FC"}[kind]
    assert a.read_bytes()[:len(sig) + 1].startswith(sig.encode())
    f = read_factorised(a)
    assert f.format == "fmf" and f.header.signature == sig and f.scalar_size == scalar_size
    assert f.dynamic_range_reduced is extended and f.colour_model == 0
    np.testing.assert_array_equal(f.colour_matrix, np.eye(3))
    if hm is None:
        assert f.height_map is None
    else:
        assert f.height_map.shape == (6, 4) and f.height_map.dtype == np.float16
        np.testing.assert_array_equal(f.height_map, hm.astype(np.float16))
    assert (f.header.rotations is None) == (rot is None)
    tol = HALF_TOL if scalar_size == 2 else 1e-6
    for c in range(n_c):
        assert f.SxV[c] is f.SxV[0] and isinstance(f.SxV[c], np.memmap)
        assert f.U[c].shape == (h.n_lv, k)
        want = U_full[c::n_c] @ SxV.T  # U rows c + n_c * (l + n_l v): channel fastest
        got = f.U[c].astype(np.float64) @ f.SxV[c].astype(np.float64).T
        assert np.abs(got - want).max() <= tol * np.abs(want).max() * 4
    rewrite(f, b)
    assert _same_bytes(a, b)


def test_fmf_writer_interleaves_per_channel_u(tmp_path):
    rng = np.random.default_rng(40)
    h = _header(rng, signature="!FMF12FCER")
    U = [rng.standard_normal((h.n_lv, 3)) for _ in range(3)]
    SxV = rng.standard_normal((h.n_tx, 3))
    a, b = tmp_path / "a.btf", tmp_path / "b.btf"
    write_fmf(a, h, np.ones(3), U, SxV, 4)
    write_fmf(b, h, np.ones(3), np.stack(U, axis=1).reshape(-1, 3), SxV, 4)
    assert _same_bytes(a, b)
    f = read_factorised(a)
    for c in range(3):
        np.testing.assert_allclose(f.U[c], U[c].astype(np.float32))


# -------------------------------------------------------------------------------------- PVF


def _pvf_slots(rng, h, orientation, k=2, scalar_size=2):
    slots = []
    for _ in range(h.n_v):
        dim, n_w = (3 * h.n_l, h.n_tx) if orientation == "lights" else (3 * h.n_tx, h.n_l)
        slots.append(PvfSlot(scalar_size, rng.random(k), rng.random(dim), rng.standard_normal((dim, k)),
                             rng.standard_normal((n_w, k))))
    return slots


@pytest.mark.parametrize("legacy", [False, True])
@pytest.mark.parametrize("orientation", ["lights", "texels"])
@pytest.mark.parametrize("scalar_size", [2, 4])
def test_pvf_read_decode_and_rewrite(tmp_path, legacy, orientation, scalar_size):
    rng = np.random.default_rng(50 + scalar_size)
    h = _header(rng, rotations=None if legacy else np.eye(3)[None])
    slots = _pvf_slots(rng, h, orientation, scalar_size=scalar_size)
    a, b = tmp_path / "a.pvf", tmp_path / "b.pvf"
    write_pvf(a, h, slots, legacy=legacy)
    if legacy:
        assert struct.unpack_from("<i", a.read_bytes(), len("!PVF06FC"))[0] == 301074
    p = read_pvf(a)
    assert p.legacy is legacy and p.orientation == orientation and len(p.slots) == h.n_v
    assert isinstance(p.slots[0].Cs, np.memmap) and isinstance(p.slots[0].Ws, np.memmap)
    np.testing.assert_array_equal(p.header.view_angles, h.view_angles)
    if not legacy:
        assert p.header == dataclasses.replace(h, signature="!PVF06FCR")
    # reference decode straight from the written factors, value(l, v, t, c)
    ref = np.empty((h.n_lv, h.n_tx, 3))
    dt = np.float16 if scalar_size == 2 else np.float32
    for v, s in enumerate(slots):
        Cs, Ws, M = (x.astype(dt).astype(np.float64) for x in (s.Cs, s.Ws, s.mean))
        for l in range(h.n_l):
            for c in range(3):
                if orientation == "lights":
                    ref[l + h.n_l * v, :, c] = Ws @ Cs[c + 3 * l] + M[c + 3 * l]
                else:
                    t = np.arange(h.n_tx)
                    ref[l + h.n_l * v, :, c] = Cs[c + 3 * t] @ Ws[l] + M[c + 3 * t]
    got = p.decode_rows(slice(None))
    assert got.shape == (h.n_lv, h.n_tx, 3) and got.dtype == np.float32
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-5)
    rows, texels = np.array([7, 0, 11]), np.array([9, 2])
    np.testing.assert_allclose(p.decode_rows(rows, texels), ref[rows][:, texels], rtol=1e-5, atol=1e-5)
    rewrite_pvf(p, b)
    assert _same_bytes(a, b)
