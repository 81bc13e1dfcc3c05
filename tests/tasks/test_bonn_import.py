"""Bonn BTF file -> btf-texture store on a real LocalCluster (tasks.bonn.import_btf): equal to an
in-memory decode of the file, the lazy Dask array too, resumption, staged overwrite, refusals,
attributes, NaN/Inf errors. Files are written with tasks.bonn's own writers into tmp_path."""

from __future__ import annotations

import hashlib
import json
import re

import numpy as np
import pytest
import zarr

from btfcore.bonn import decode_colour, decode_textures, restore_dynamic_range
from tasks.bonn.bdi import write_bdi
from tasks.bonn.dfmf import read_factorised, write_dfmf, write_fmf
from tasks.bonn.errors import BonnFormatError
from tasks.bonn.header import make_header
from tasks.bonn.pvf import PvfSlot, read_pvf, write_pvf
from tasks.bonn.import_btf import (
    NonFiniteValueError,
    bonn_dask_array,
    check_import,
    import_btf,
)
from tasks.staging import staging_path
from tasks.stores.btf import RESAMPLED_LV_ORDER, open_btf_store, validate_btf_store

# n_l * w * 12 bytes per texture row of a view: band_rows gives 170 rows, so h = 200 makes 2 bands
N_V, N_L, H, W = 3, 16, 200, 128


def _header(signature="!DFMF08FCR", n_v=N_V, n_l=N_L, h=H, w=W, cosine_flag=True):
    rng = np.random.default_rng(1)
    views = np.stack([rng.uniform(0, 1.2, n_v), rng.uniform(-np.pi, np.pi, n_v)], -1)
    lights = [np.stack([rng.uniform(0, 1.4, n_l), rng.uniform(-np.pi, np.pi, n_l)], -1) for _ in range(n_v)]
    rot = np.stack([np.eye(3), np.diag([1.0, -1.0, -1.0])]).astype(np.float32)
    return make_header(views, lights, w, h, signature=signature, cosine_flag=cosine_flag, xml="<m>x</m>",
                       measurement_setup="dome", image_sensor="cam", light_source="led", ppmm=12.5,
                       rgb_scale_factor=(1.0, 0.9, 1.1), rotations=rot)


def _factors(seed, n_lv, n_tx, ks, scale=1.0):
    rng = np.random.default_rng(seed)
    U = [rng.normal(0, 1, (n_lv, k)) / np.sqrt(k) for k in ks]
    SxV = [rng.normal(0, scale, (n_tx, k)) for k in ks]
    S = [np.linalg.norm(s, axis=0) for s in SxV]
    return S, U, SxV


def write_test_dfmf(path, seed=0, model=1, scalar_size=2, ks=(5, 3, 2), **hdr):
    """A DFMF of random factors in colour model ``model`` (1 YUV: channels of either sign decode)."""
    header = _header(**hdr)
    S, U, SxV = _factors(seed, header.n_lv, header.n_tx, ks, scale=0.3)
    U[0] = np.abs(U[0])                                       # Y mostly positive
    SxV[0] = np.abs(SxV[0]) + 0.5
    mean, matrix = np.zeros(3, np.float32), np.eye(3, dtype=np.float32)
    write_dfmf(path, header, model, mean, matrix, S, U, SxV, scalar_size)
    return path


def reference(path):
    """The whole file decoded in memory: (n_lv, h, w, 3) float32, rows l + n_l v, texel [y, x]."""
    f = read_factorised(path)
    hd = f.header
    U = [np.asarray(u, np.float32) for u in f.U]
    SxV = [np.asarray(s, np.float32) for s in f.SxV]
    out = decode_colour(decode_textures(U, SxV, slice(None)), f.colour_model, f.colour_mean, f.colour_matrix)
    if f.dynamic_range_reduced:
        out = restore_dynamic_range(out)
    return np.asarray(out, np.float32).reshape(hd.n_lv, hd.height, hd.width, 3)


def _btf(path):
    return zarr.open_group(str(path), mode="r", zarr_format=3)["btf"][...]


def _close(a, b):
    np.testing.assert_allclose(a, b, rtol=2e-5, atol=2e-5 * float(np.abs(b).max()))


@pytest.fixture(scope="module")
def dfmf(tmp_path_factory):
    return write_test_dfmf(tmp_path_factory.mktemp("bonn-import") / "mat.btf")


# --------------------------------------------------------------------------- values


def test_dfmf_import_equals_in_memory_decode(dfmf, tmp_path, dask_client):
    ticks = []
    summary = import_btf(dfmf, tmp_path / "imp.zarr", dask_client, on_progress=lambda d, t: ticks.append((d, t)))
    store = open_btf_store(tmp_path / "imp.zarr")
    ref = reference(dfmf)
    assert store.btf.shape == (N_V * N_L, H, W, 3) and store.btf.chunks == (N_L, 170, W, 3)
    _close(store.btf[...], ref)
    assert store.written.shape == (N_V, 2) and store.written.all()
    assert summary["rows"] == N_V * N_L and summary["texture_shape"] == [H, W] and summary["format"] == "dfmf"
    assert summary["chunks"] == summary["chunks_written"] == N_V * 2 and summary["chunks_skipped"] == 0
    assert ticks[-1] == (N_V * 2, N_V * 2)
    assert validate_btf_store(tmp_path / "imp.zarr") == []
    again = import_btf(dfmf, tmp_path / "imp.zarr", dask_client)      # complete: left alone
    assert again["chunks_written"] == 0 and again["tasks"] == 0


def test_attributes_and_directions(dfmf, tmp_path, dask_client):
    import_btf(dfmf, tmp_path / "a.zarr", dask_client, material_class="leather", material_id="m1")
    store = open_btf_store(tmp_path / "a.zarr")
    attrs = store.attrs
    f = read_factorised(dfmf)
    hd = f.header
    np.testing.assert_allclose(store.light_dir, hd.light_dir())
    np.testing.assert_allclose(store.view_dir, hd.view_dir())
    assert np.array_equal(store.lv_index[N_L + 3], [1, 3])
    assert attrs["lv_order"] == RESAMPLED_LV_ORDER and attrs["views_lights"] == [N_V, N_L]
    assert attrs["material"] == {"material_id": "m1", "class": "leather"}
    assert re.fullmatch(r"[0-9a-f]{16}", attrs["import_hash"]) and store.content_key == attrs["import_hash"]
    src = attrs["imported_from"]
    assert src["sha256"] == hashlib.sha256(dfmf.read_bytes()).hexdigest()
    assert src["bytes"] == dfmf.stat().st_size and src["format"] == "dfmf" and src["signature"] == "!DFMF08FCR"
    bonn = attrs["bonn"]
    assert bonn["cosine_flag"] is True and "cosine flag set" in attrs["units"] and "DFMF" in attrs["units"]
    assert bonn["xml"] == "<m>x</m>" and bonn["channel_names"] == ["R", "G", "B"] and bonn["version"] == 4
    assert bonn["colour_model"] == 1 and bonn["components"] == [5, 3, 2] and bonn["scalar_size"] == 2
    assert bonn["n_rot"] == 2 and np.allclose(bonn["rotations"][1], np.diag([1.0, -1.0, -1.0]))
    assert bonn["ppmm"] == 12.5 and bonn["measurement_setup"] == "dome" and bonn["dynamic_range_reduced"] is False
    np.testing.assert_array_equal(store.group["bonn_view_angles"][...], hd.view_angles)
    np.testing.assert_array_equal(store.group["bonn_light_angles"][...], np.stack(hd.light_angles))
    json.dumps(attrs, allow_nan=False)


def test_fmf12_dynamic_range_and_height_map(tmp_path, dask_client):
    header = _header("!FMF12FCER", n_v=2, n_l=5, h=9, w=14, cosine_flag=False)
    S, U, SxV = _factors(4, 3 * header.n_lv, header.n_tx, (4,), scale=0.2)
    hm = np.random.default_rng(2).uniform(0, 1, (3, 5))
    write_fmf(tmp_path / "f.btf", header, S[0], U[0], SxV[0], 4, dynamic_range_reduced=True, height_map=hm)
    import_btf(tmp_path / "f.btf", tmp_path / "f.zarr", dask_client)
    store = open_btf_store(tmp_path / "f.zarr")
    ref = reference(tmp_path / "f.btf")
    assert (ref > 0).mean() > 0.9                       # exp(x) - eps, not x: mostly positive
    _close(store.btf[...], ref)
    np.testing.assert_allclose(store.group["height_map"][...], hm.astype(np.float16), rtol=0, atol=0)
    assert store.attrs["bonn"]["dynamic_range_reduced"] is True and "cosine flag not set" in store.attrs["units"]
    assert store.attrs["imported_from"]["format"] == "fmf12"


def test_bdi_import_equals_written_textures(tmp_path, dask_client):
    header = _header("!BDIF06R2!", n_v=2, n_l=3, h=11, w=6)
    tex = np.random.default_rng(5).uniform(0, 2, (header.n_lv, 11, 6, 3)).astype(np.float16)
    mask = np.ones((11, 6), bool)
    mask[4, 2] = False
    write_bdi(tmp_path / "b.bdi", header, tex, compression=1, lines_per_chunk=4, mask=mask)
    summary = import_btf(tmp_path / "b.bdi", tmp_path / "b.zarr", dask_client)
    store = open_btf_store(tmp_path / "b.zarr")
    want = tex.astype(np.float32)
    want[:, 4, 2] = 0
    np.testing.assert_array_equal(store.btf[...], want)
    assert store.btf.chunks == (3, 4, 6, 3) and summary["chunks"] == 2 * 3
    assert np.array_equal(store.group["bonn_mask"][...], mask)
    arr = bonn_dask_array(tmp_path / "b.bdi")                  # the file's unit: all rows x 4 scan lines
    assert arr.chunks == ((6,), (4, 4, 3), (6,), (3,))
    np.testing.assert_array_equal(arr.compute(scheduler="synchronous"), want)


def test_pvf_import_equals_its_row_decoder(tmp_path, dask_client):
    header = _header("!PVF06FCR", n_v=3, n_l=4, h=10, w=7)
    rng = np.random.default_rng(6)
    slots = [PvfSlot(2, np.ones(3), rng.uniform(0, 1, 3 * 4), rng.normal(0, 1, (3 * 4, 3)),
                     rng.normal(0, 0.3, (70, 3))) for _ in range(3)]
    write_pvf(tmp_path / "p.btf", header, slots)
    import_btf(tmp_path / "p.btf", tmp_path / "p.zarr", dask_client)
    store = open_btf_store(tmp_path / "p.zarr")
    ref = read_pvf(tmp_path / "p.btf").decode_rows(slice(None)).reshape(12, 10, 7, 3)
    _close(store.btf[...], ref)
    s = read_pvf(tmp_path / "p.btf").slots[1]            # row l + n_l v, texel x + w y: by hand
    l, x, y = 2, 5, 8
    by_hand = np.asarray(s.Ws[x + 7 * y], np.float32) @ np.asarray(s.Cs[3 * l:3 * l + 3], np.float32).T \
        + np.asarray(s.mean[3 * l:3 * l + 3], np.float32)
    _close(store.btf[4 + l, y, x], by_hand)
    assert store.attrs["bonn"]["orientation"] == "lights" and store.attrs["imported_from"]["format"] == "pvf"


def test_dask_array_equals_decode(dfmf):
    arr = bonn_dask_array(dfmf)
    assert arr.shape == (N_V * N_L, H, W, 3) and arr.dtype == np.float32
    assert arr.chunks[0] == (N_L,) * N_V and arr.chunks[1] == (170, 30)
    ref = reference(dfmf)
    _close(arr.compute(scheduler="synchronous"), ref)
    _close(arr[N_L + 2, 150:180, 3].compute(scheduler="synchronous"), ref[N_L + 2, 150:180, 3])


# --------------------------------------------------------------------------- resume, overwrite, refusals


def test_killed_import_resumes_only_unmarked_chunks(dfmf, tmp_path, dask_client):
    out = tmp_path / "r.zarr"
    import_btf(dfmf, out, dask_client)
    group = zarr.open_group(str(out), mode="r+", zarr_format=3)
    n_l = N_L
    group["written"][1, 0] = 0                     # a kill: these chunks were in flight ...
    group["written"][2, 1] = 0
    group["btf"][n_l:2 * n_l, :170] = 7.0          # ... and hold garbage
    group["btf"][2 * n_l:, 170:] = np.nan
    group["btf"][0:n_l, :170] = -3.0               # marked written: a resume must not touch it
    group.attrs["complete"] = False
    summary = import_btf(dfmf, out, dask_client)
    assert summary["chunks_written"] == 2 and summary["chunks_skipped"] == 4 and summary["views_resumed"] == 3
    ref = reference(dfmf)
    got = _btf(out)
    _close(got[n_l:], ref[n_l:])
    assert (got[:n_l, :170] == -3.0).all()        # only unmarked chunks were recomputed
    _close(got[:n_l, 170:], ref[:n_l, 170:])
    assert open_btf_store(out).complete


def test_overwrite_is_staged_and_failed_run_keeps_the_old_output(dfmf, tmp_path, dask_client):
    out = tmp_path / "o.zarr"
    import_btf(dfmf, out, dask_client)
    other = write_test_dfmf(tmp_path / "other.btf", seed=9)
    with pytest.raises(FileExistsError, match="another file.*--overwrite"):
        import_btf(other, out, dask_client)
    bad = _nan_dfmf(tmp_path / "bad.btf")
    with pytest.raises(NonFiniteValueError):
        import_btf(bad, out, dask_client, overwrite=True)
    assert open_btf_store(out).attrs["imported_from"]["path"] == str(dfmf.resolve())    # old output intact
    _close(_btf(out), reference(dfmf))
    assert staging_path(out).exists()                                                   # the failed staging
    summary = import_btf(other, out, dask_client, overwrite=True)
    assert summary["staged"] and not staging_path(out).exists()
    _close(_btf(out), reference(other))
    assert open_btf_store(out).attrs["imported_from"]["sha256"] == hashlib.sha256(other.read_bytes()).hexdigest()


def test_refuses_foreign_out_before_any_work(dfmf, tmp_path):
    foreign = tmp_path / "foreign.zarr"
    zarr.open_group(str(foreign), mode="w", zarr_format=3).attrs["schema"] = "btf-model"
    with pytest.raises(FileExistsError, match="not an imported BTF store.*btf-model"):
        check_import(dfmf, foreign)
    plain = tmp_path / "plain"
    plain.mkdir()
    (plain / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="not a Zarr store"):
        check_import(dfmf, plain)
    assert (plain / "notes.txt").read_text() == "mine"
    with pytest.raises(FileExistsError, match="a run never writes into what it reads"):
        check_import(dfmf, dfmf)
    plan = check_import(dfmf, tmp_path / "new.zarr")
    assert (plan.n_v, plan.n_l, plan.height, plan.width, plan.band, plan.format) == (N_V, N_L, H, W, 170, "dfmf")
    assert not plan.staged and not (tmp_path / "new.zarr").exists()


def test_bad_file_fails_in_the_preflight(dfmf, tmp_path):
    cut = tmp_path / "cut.btf"
    cut.write_bytes(dfmf.read_bytes()[:-1000])
    with pytest.raises(BonnFormatError, match=r"cut\.btf: byte \d+"):
        check_import(cut, tmp_path / "x.zarr")
    with pytest.raises(FileNotFoundError):
        check_import(tmp_path / "missing.btf", tmp_path / "x.zarr")
    assert not (tmp_path / "x.zarr").exists()


# --------------------------------------------------------------------------- NaN / Inf


def _nan_dfmf(path, texel=(7, 190)):
    """A single-precision DFMF whose SxV holds an infinity at texel (x, y) of channel 1."""
    header = _header()
    S, U, SxV = _factors(3, header.n_lv, header.n_tx, (2, 2, 2))
    x, y = texel
    SxV[1][x + W * y, 0] = np.inf
    write_dfmf(path, header, 0, np.zeros(3), np.eye(3), S, U, SxV, 4)
    return path


def test_nonfinite_value_names_file_row_and_texel(tmp_path, dask_client):
    bad = _nan_dfmf(tmp_path / "nan.btf")
    with pytest.raises(NonFiniteValueError) as info:
        import_btf(bad, tmp_path / "n.zarr", dask_client)
    msg = str(info.value)
    assert str(bad.resolve()) in msg and "(x 7, y 190)" in msg and re.search(r"view \d, light \d+", msg), msg
    assert not open_btf_store(tmp_path / "n.zarr", require_complete=False).complete


def test_imported_stores_are_materials_of_a_database(tmp_path, dask_client):
    from tasks.model import discover

    db = tmp_path / "db"
    keys = {}
    for i in range(2):
        f = write_test_dfmf(tmp_path / f"m{i}.btf", seed=20 + i, n_v=2, n_l=3, h=5, w=4)
        keys[f"m{i}"] = import_btf(f, db / f"m{i}.zarr", dask_client, material_class="felt")["import_hash"]
    found = discover(db)
    assert {m.material_id: m.ingest_hash for m in found} == keys and {m.cls for m in found} == {"felt"}
    assert all(m.n_lv == 6 and m.texture_shape == (5, 4) for m in found)


_KILLED_RUN = """
import os, sys
from distributed import Client, LocalCluster
from tasks.bonn.import_btf import import_btf

def die(done, total):
    if done >= 3:
        os.kill(os.getpid(), 9)                 # SIGKILL: nothing is cleaned up

if __name__ == "__main__":
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster, \\
            Client(cluster) as client:
        import_btf(sys.argv[1], sys.argv[2], client, on_progress=die)
"""


@pytest.mark.slow
def test_sigkilled_import_resumes(tmp_path, dask_client):
    """A real SIGKILL of the importing process after 3 of 8 chunks; the rerun computes only the rest."""
    import subprocess
    import sys

    src = write_test_dfmf(tmp_path / "k.btf", seed=11, n_v=4)
    script = tmp_path / "run.py"
    script.write_text(_KILLED_RUN)
    out = tmp_path / "k.zarr"
    proc = subprocess.run([sys.executable, str(script), str(src), str(out)], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == -9, proc.stderr[-2000:]
    written = zarr.open_group(str(out), mode="r", zarr_format=3)["written"][...]
    assert 3 <= written.sum() < 8 and not open_btf_store(out, require_complete=False).complete
    summary = import_btf(src, out, dask_client)
    assert summary["chunks_skipped"] == written.sum() and summary["chunks_written"] == 8 - written.sum()
    _close(_btf(out), reference(src))
