"""Issue 13, silent corruption: a changed byte or a missing chunk file is an error that names the store,
the array and the chunk, from `btf validate --deep` and from the stage that reads it, never a result.
Issue 19, item 4: `btf validate` checks measurement and model stores against their schema, and `--deep`
finds NaN/Inf in every kind of store, naming the array, the chunk and the count.

Real stores written by the pipeline (the session's tiny capture and its ingested BTF store, a model store
written by tasks.model's writers, a measurement store ingested from a sparse multiplexed plan capture),
the real command line (`run_btf`).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr

from flows.cli import EXIT_BAD_INPUT
from tasks.integrity import has_checksums


def all_checksummed(path: Path) -> list[str]:
    group = zarr.open_group(str(path), mode="r")
    arrays = [(name, a) for name, a in group.members(max_depth=None) if isinstance(a, zarr.Array)]
    assert arrays
    return [name for name, a in arrays if not has_checksums(a)]


@pytest.fixture(scope="module")
def stores(tiny_btf, tmp_path_factory, dask_client) -> dict[str, Path]:
    """The session's capture, its BTF store, a model store (class ``leather``, k = 8) fitted on it and
    finished as `btf build-db` finishes one, and the measurement store of a sparse multiplexed plan
    capture (one turntable position, 8x8 texels) ingested by `btf ingest`'s code."""
    from dataclasses import asdict

    from btfcore.acquisition.plan import ExposureModel, sparse_multiplexed_plan
    from btfcore.dome import get_device
    from btfcore.model._lowrank import TruncatedSVD
    from tasks.measurement import ingest_measurement
    from tasks.model import ModelSettings, discover, open_model_store, write_basis
    from tasks.simulate import SimulationConfig, simulate_database

    capture = next(p for p in tiny_btf.parent.glob("*.zarr")
                   if zarr.open_group(str(p), mode="r").attrs.get("schema") == "btf-capture")
    model_dir = tmp_path_factory.mktemp("model")
    [material] = discover(tiny_btf.parent, min_per_class=1)
    group = open_model_store(model_dir / "model.zarr", [material])
    B = np.asarray(zarr.open_group(str(tiny_btf), mode="r")["btf"][...], dtype=np.float64)
    U, s, _ = np.linalg.svd(B.reshape(B.shape[0], -1), full_matrices=False)
    write_basis(group, "classes/leather/als", TruncatedSVD(U[:, :8], s[:8], "merge"), "full-svd")
    group.attrs.update({"settings": asdict(ModelSettings()), "complete": True})     # as build_database ends

    device = get_device("tiny")
    device = device.with_overrides(turntable_angle_deg=device.turntable_angle_deg[:1])
    plan = sparse_multiplexed_plan(device, [(0, 1), (0, 4), (0, 6)], ExposureModel(single_ms=(1.0, 10.0, 100.0)))
    root = tmp_path_factory.mktemp("plan-capture")
    config = SimulationConfig(device="tiny", n_materials=1, seed=3, classes=("leather",), n_turntable=1,
                              texture_size=8, plan=plan)
    planned = simulate_database(config, root, dask_client).stores[0]
    ingest_measurement(planned, root / "measurement.zarr", dask_client)
    return {"capture": capture, "btf": tiny_btf, "model": model_dir, "measurement": root / "measurement.zarr"}


@pytest.fixture()
def copies(stores, tmp_path) -> dict[str, Path]:
    return {kind: Path(shutil.copytree(path, tmp_path / path.name)) for kind, path in stores.items()}


def test_every_store_kind_is_written_with_chunk_checksums(stores, run_btf, tmp_path):
    for kind in ("capture", "btf"):
        assert all_checksummed(stores[kind]) == [], kind
    assert all_checksummed(stores["model"] / "model.zarr") == []
    code, _, err = run_btf("reconstruct", stores["btf"], "--model", stores["model"], "--class", "leather",
                           "--out", tmp_path / "rec.zarr")
    assert code == 0, err
    assert all_checksummed(tmp_path / "rec.zarr") == []
    for kind, path in stores.items():
        code, out, _ = run_btf("validate", "--deep", path)
        assert code == 0 and "problem" not in out and "note:" not in out, (kind, out)


def test_a_flipped_raw_byte_is_named_by_validate_and_by_ingest(copies, run_btf, tmp_path, chunk_files):
    capture = copies["capture"]
    chunk_files.flip_byte(chunk_files.path(capture, "raw", (0, 1, 3, 0, 0, 0)), offset=1000)
    named = "array raw, chunk (0, 1, 3, 0, 0, 0): checksum mismatch (the chunk file was changed after it was written)"
    code, out, _ = run_btf("validate", "--deep", capture)
    assert code == EXIT_BAD_INPUT and f"{capture}: 1 problem(s)" in out and named in out, out
    code, _, err = run_btf("ingest", capture, "--out", tmp_path / "out.zarr")
    assert code == EXIT_BAD_INPUT, err
    assert f"{capture}: {named}" in err and err.count("chunk (0, 1, 3, 0, 0, 0)") == 1, err


def test_a_missing_raw_chunk_is_named_not_taken_for_an_unusable_bracket(copies, run_btf, tmp_path, chunk_files):
    capture = copies["capture"]
    chunk_files.path(capture, "raw", (0, 1, 3, 0, 0, 0)).unlink()
    for args in (["validate", capture], ["ingest", capture, "--out", tmp_path / "out.zarr"]):
        code, out, err = run_btf(*args)
        assert code == EXIT_BAD_INPUT, (args, out, err)
        said = out + err
        assert str(capture) in said and "raw[chunk (0, 1, 3, 0, 0, 0)]" in said and "chunk file missing" in said \
            and "damaged after writing" in said, (args, out, err)
        assert "usable pixel" not in out + err
    assert not (tmp_path / "out.zarr").exists()


def test_a_flipped_btf_byte_is_named_by_validate_and_by_reconstruct(copies, run_btf, tmp_path, chunk_files):
    btf = copies["btf"]
    chunk_files.flip_byte(chunk_files.path(btf, "btf", (2, 0, 0, 0)))
    named = "array btf, chunk (2, 0, 0, 0): checksum mismatch"
    code, out, _ = run_btf("validate", "--deep", btf)
    assert code == EXIT_BAD_INPUT and named in out and "btf ingest --overwrite" in out, out
    code, _, err = run_btf("reconstruct", btf, "--model", copies["model"], "--class", "leather",
                           "--out", tmp_path / "rec.zarr")
    assert code == EXIT_BAD_INPUT, err
    assert f"{btf}: {named}" in err, err


def test_a_flipped_model_byte_is_named_by_validate_and_by_reconstruct(copies, run_btf, tmp_path, chunk_files):
    model = copies["model"]
    chunk_files.flip_byte(chunk_files.path(model / "model.zarr", "classes/leather/als/U", (0, 0)))
    named = "array classes/leather/als/U, chunk (0, 0): checksum mismatch"
    code, out, _ = run_btf("validate", "--deep", model)            # a build-db folder means its model.zarr
    assert code == EXIT_BAD_INPUT and named in out and "btf build-db" in out, out
    code, _, err = run_btf("reconstruct", copies["btf"], "--model", model, "--class", "leather",
                           "--out", tmp_path / "rec.zarr")
    assert code == EXIT_BAD_INPUT, err
    assert f"{model / 'model.zarr'}: {named}" in err, err


def _rewrite(store: Path, array: str, data: np.ndarray) -> None:
    """Replace ``store[array]`` by ``data`` (an array of the pipeline's own kind, with checksums)."""
    from tasks.integrity import create_array

    group = zarr.open_group(str(store), mode="r+", zarr_format=3)
    create_array(group, array, shape=data.shape, dtype=data.dtype, chunks=data.shape, overwrite=True)[...] = data


def test_measurement_and_model_stores_are_checked_against_their_schema(stores, run_btf, tmp_path):
    from tasks.stores.measurement import write_measurement

    measurement = zarr.open_group(str(stores["measurement"]), mode="r")
    assert measurement.attrs["schema"] == "btf-measurement" and "meas_index" in measurement
    assert not measurement.attrs["single_light"]                    # a multiplexed G is checked row by row
    btf = zarr.open_group(str(stores["btf"]), mode="r")
    B, n_lv = np.asarray(btf["btf"][...]), btf["btf"].shape[0]
    G = np.eye(n_lv, dtype=np.float32)[::2]                         # a measurement made elsewhere: every second row
    write_measurement(tmp_path / "elsewhere.zarr", (G @ B.reshape(n_lv, -1)).reshape(len(G), *B.shape[1:]), G,
                      btf["light_dir"][...], btf["view_dir"][...], tuple(btf.attrs["turntable_cameras_leds"]))
    for path in (stores["measurement"], tmp_path / "elsewhere.zarr", stores["model"]):
        code, out, _ = run_btf("validate", path)
        assert code == 0 and out == f"{path}: valid\n", out


def test_a_broken_measurement_schema_is_named_by_validate(stores, copies, run_btf):
    store = copies["measurement"]
    shutil.rmtree(store / "meas_index")                              # a removed array
    code, out, _ = run_btf("validate", store)
    assert code == EXIT_BAD_INPUT and f"{store}: 1 problem(s)" in out, out
    assert "meas_index: expected array 'meas_index', int of shape (n_meas, 3), found nothing. the store is " \
        "incomplete; write the store again (`btf ingest CAPTURE --out STORE --overwrite`" in out, out
    _rewrite(store, "meas_index", np.asarray(zarr.open_group(str(stores["measurement"]), mode="r")["meas_index"][...]))
    group = zarr.open_group(str(store), mode="r+", zarr_format=3)
    G = np.asarray(group["G"][...])
    group["G"][1] = np.roll(G[1], 1)                                 # not the pattern of its bracket at its view
    group.attrs["n_meas"] = G.shape[0] + 1                           # contradicts measured, G and the rest
    code, out, _ = run_btf("validate", store)
    assert code == EXIT_BAD_INPUT, out
    for named in (f"measured[axis 0 (n_meas)]: expected length {G.shape[0] + 1} (shape ({G.shape[0] + 1}, 8, 8, 3))"
                  f", found length {G.shape[0]}", f"G[axis 0 (n_meas)]: expected length {G.shape[0] + 1}",
                  f"meas_index[axis 0 (n_meas)]: expected length {G.shape[0] + 1}"):
        assert named in out, (named, out)
    group.attrs["n_meas"] = G.shape[0]
    code, out, _ = run_btf("validate", store)
    assert code == EXIT_BAD_INPUT and f"{store}: 1 problem(s)" in out and "G[row (1)]: expected the pattern " \
        "illumination[i] of each row's bracket meas_index = (t, c, i) at the LEDs of its view (t, c)" in out, out


def test_a_broken_model_schema_is_named_by_validate(copies, run_btf):
    model = copies["model"]
    store = model / "model.zarr"
    group = zarr.open_group(str(store), mode="r+", zarr_format=3)
    sigma, rows_id = np.asarray(group["classes/leather/als/sigma"][...]), group.attrs["rows_id"]
    _rewrite(store, "classes/leather/als/sigma", sigma[:7])          # a sigma of the wrong length
    group.attrs["rows_id"] = "0123456789abcdef"                      # not the hash of the directions
    code, out, _ = run_btf("validate", model)
    assert code == EXIT_BAD_INPUT and f"{model}: 2 problem(s)" in out, out
    assert "classes/leather/als/sigma[axis 0]: expected float64 of shape (8,): one value per column of U" in out \
        and "found float64 of shape (7,)" in out and "btf build-db" in out, out
    assert "attrs[rows_id]: expected '" in out and "the hash of light_dir and view_dir" in out, out
    _rewrite(store, "classes/leather/als/sigma", sigma[::-1].copy())  # increasing
    group.attrs["rows_id"] = rows_id
    code, out, _ = run_btf("validate", store)
    assert code == EXIT_BAD_INPUT and f"{store}: 1 problem(s)" in out and "classes/leather/als/sigma[(1), (2), " \
        "(3), (4), (5), (6), (7)]: expected non-increasing values" in out, out


#: A float array of each kind of store (its last chunk gets two NaN and an Inf).
NAN_IN = {"capture": "truth/btf", "btf": "btf", "measurement": "measured", "model": "classes/leather/als/U"}


@pytest.mark.parametrize("kind", list(NAN_IN))
def test_deep_finds_nan_in_every_kind_of_store(kind, copies, run_btf):
    path = copies[kind]
    store = path / "model.zarr" if kind == "model" else path
    array = zarr.open_group(str(store), mode="r+", zarr_format=3)[NAN_IN[kind]]
    chunk = tuple(n - 1 for n in array.cdata_shape)                  # the last chunk
    region = tuple(slice(c * s, min((c + 1) * s, n)) for c, s, n in zip(chunk, array.chunks, array.shape))
    data = np.asarray(array[region])
    data.reshape(-1)[[1, 3]] = np.nan
    data.reshape(-1)[5] = np.inf
    array[region] = data                                             # rewritten with a valid checksum
    first = ", ".join(str(r.start + i) for r, i in zip(region, np.unravel_index(1, data.shape)))
    code, out, _ = run_btf("validate", "--deep", path)
    named = (f"array {NAN_IN[kind]}, chunk {chunk}: 2 NaN and 1 Inf value(s), first at {NAN_IN[kind]}"
             f"[{first}]")
    assert code == EXIT_BAD_INPUT and named in out, out
    code, out, _ = run_btf("validate", path)                         # without --deep the bulk arrays are not read
    assert code == 0 and named not in out, out
