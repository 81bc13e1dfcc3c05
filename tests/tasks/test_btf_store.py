"""Tests of the BTF store module (tasks/stores/btf.py) on real Zarr v3 stores on disk."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import zarr

from tasks.integrity import has_checksums
from tasks.stores.btf import (
    LV_ORDER,
    SCHEMA_NAME,
    SCHEMA_VERSION,
    BtfStore,
    BtfStoreError,
    band_rows,
    create_btf_store,
    open_btf_store,
    validate_btf_store,
)

N_TURN, N_CAM, N_LEDS, H, W = 1, 2, 3, 4, 5
N_LV = N_TURN * N_CAM * N_LEDS


def directions(n: int, seed: int = 0) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2]) + 0.1
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def make_store(path, *, complete: bool = True) -> BtfStore:
    """A small ingested-like store: every view written, marked complete."""
    lv_index = np.indices((N_TURN, N_CAM, N_LEDS)).reshape(3, -1).T.astype(np.int32)
    store = create_btf_store(path, {"units": "test", "lv_order": LV_ORDER, "ingest_hash": "abc",
                                    "turntable_cameras_leds": [N_TURN, N_CAM, N_LEDS]},
                             light_dir=directions(N_LV), view_dir=directions(N_LV, seed=1), lv_index=lv_index,
                             texture_shape=(H, W), rows_per_chunk=N_LEDS, band=band_rows(N_LEDS, H, W),
                             written_shape=(N_TURN, N_CAM), valid_fraction_shape=(N_TURN, N_CAM, N_LEDS))
    store.btf[...] = np.ones((N_LV, H, W, 3), np.float32)
    store.group["written"][...] = 1
    if complete:
        store.mark_complete()
    return store


def test_create_open_validate_round_trip(tmp_path):
    path = tmp_path / "b.zarr"
    made = make_store(path)
    assert made.mode == "r+" and made.complete
    store = open_btf_store(path)
    assert isinstance(store, BtfStore) and store.mode == "r" and store.path == str(path)
    assert store.btf.shape == (N_LV, H, W, 3) and store.btf.dtype == np.float32
    assert store.n_lv == N_LV and store.texture_shape == (H, W) and store.kind == "ingested"
    np.testing.assert_array_equal(store.light_dir, made.light_dir)
    assert store.lv_index.shape == (N_LV, 3) and store.written.all()
    assert store.attrs["schema"] == SCHEMA_NAME and store.attrs["schema_version"] == SCHEMA_VERSION
    assert store.attrs["texture_shape"] == [H, W] and store.units == "test" and store.content_key == "abc"
    assert store.group["btf"].chunks == (N_LEDS, band_rows(N_LEDS, H, W), W, 3)
    assert all(has_checksums(a) for _, a in store.group.arrays())
    assert validate_btf_store(path) == []
    assert "BtfStore(" in repr(store)


def test_an_unfinished_store_is_refused_unless_asked(tmp_path):
    path = tmp_path / "u.zarr"
    make_store(path, complete=False)
    with pytest.raises(BtfStoreError, match=r"u\.zarr is an unfinished BTF store \(attribute complete is false\)"):
        open_btf_store(path)
    assert not open_btf_store(path, require_complete=False).complete
    problems = validate_btf_store(path)
    assert [(p.array, p.index) for p in problems] == [("attrs", "complete")]
    assert validate_btf_store(path, require_complete=False) == []


def test_mark_complete_refuses_missing_markers(tmp_path):
    store = make_store(tmp_path / "m.zarr", complete=False)
    store.group["written"][0, 1] = 0
    with pytest.raises(RuntimeError, match=r"m\.zarr: some views were not written; re-run to resume"):
        store.mark_complete("views")
    assert not store.complete


def test_each_refusal_names_the_store_and_what_is_wrong(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"ghost\.zarr does not exist; give a BTF store written by"):
        open_btf_store(tmp_path / "ghost.zarr")
    (tmp_path / "file.zarr").write_text("not a store")
    with pytest.raises(BtfStoreError, match=r"file\.zarr is not a Zarr v3 group"):
        open_btf_store(tmp_path / "file.zarr")
    zarr.open_group(str(tmp_path / "cap.zarr"), mode="w", zarr_format=3).attrs.put({"schema": "btf-capture"})
    with pytest.raises(BtfStoreError, match=r"cap\.zarr is not a BTF store \(schema 'btf-capture', expected "
                                            r"'btf-texture'\); give the output of `btf ingest`"):
        open_btf_store(tmp_path / "cap.zarr", produced_by="`btf ingest`")

    v2 = make_store(tmp_path / "v2.zarr")
    v2.group.attrs["schema_version"] = "2.0"
    with pytest.raises(BtfStoreError, match=r"v2\.zarr: BTF store of schema version '2\.0'; this code reads "
                                            r"btf-texture 1\.0"):
        open_btf_store(tmp_path / "v2.zarr")

    resampled = make_store(tmp_path / "r.zarr")
    resampled.group.attrs["resampled_from"] = {"path": "x"}
    with pytest.raises(BtfStoreError, match=r"r\.zarr: not the output of `btf ingest` .*resampled\); evaluate"):
        open_btf_store(tmp_path / "r.zarr", ingested_only="evaluate the ingested store")
    assert open_btf_store(tmp_path / "r.zarr").kind == "resampled"

    no_view = make_store(tmp_path / "nv.zarr")
    del no_view.group["view_dir"]
    with pytest.raises(BtfStoreError, match=r"nv\.zarr: arrays \['view_dir'\] are missing"):
        open_btf_store(tmp_path / "nv.zarr")


def test_arrays_that_do_not_fit_are_named(tmp_path):
    store = make_store(tmp_path / "s.zarr")
    group = store.group
    del group["light_dir"]
    group.create_array("light_dir", data=directions(N_LV - 1))
    with pytest.raises(BtfStoreError, match=r"s\.zarr: btf \(6, 4, 5, 3\), light_dir \(5, 3\) and view_dir \(6, 3\) "
                                            "do not fit"):
        open_btf_store(tmp_path / "s.zarr")
    problems = {(p.array, p.index) for p in validate_btf_store(tmp_path / "s.zarr")}
    assert ("light_dir", None) in problems


def test_validation_lists_every_problem_naming_array_and_attribute(tmp_path):
    path = tmp_path / "bad.zarr"
    store = make_store(path)
    group = store.group
    attrs = dict(group.attrs)
    del attrs["units"]
    attrs["texture_shape"] = [H, W + 1]
    attrs["lv_order"] = ["light", "view"]
    group.attrs.put(attrs)
    group["view_dir"][0] = [0.0, 0.0, 2.0]                    # not a unit vector
    group["written"][0, 0] = 0                                # although complete
    del group["lv_index"]
    found = {(p.array, p.index) for p in validate_btf_store(path)}
    assert {("attrs", "units"), ("attrs", "lv_order"), ("btf", "axes 1, 2 (tex_row, tex_col)"),
            ("view_dir", "lv 0"), ("written", None), ("lv_index", None)} <= found, found
    for problem in validate_btf_store(path):
        assert problem.hint and problem.expected and problem.found


def test_validation_of_what_is_not_a_btf_store(tmp_path):
    [nothing] = validate_btf_store(tmp_path / "none.zarr")
    assert nothing.array == "<store>" and "nothing at" in nothing.found
    zarr.open_group(str(tmp_path / "m.zarr"), mode="w", zarr_format=3).attrs.put({"schema": "btf-model"})
    [other] = validate_btf_store(tmp_path / "m.zarr")
    assert (other.array, other.index, other.found) == ("attrs", "schema", "'btf-model'")


def test_create_needs_the_writers_attributes(tmp_path):
    with pytest.raises(ValueError, match=r"x\.zarr: BTF store attributes \['units'\] are missing"):
        create_btf_store(tmp_path / "x.zarr", {"lv_order": LV_ORDER, "ingest_hash": "k"},
                         light_dir=directions(2), view_dir=directions(2), lv_index=np.zeros((2, 3), np.int32),
                         texture_shape=(2, 2), rows_per_chunk=1, band=2, written_shape=(2,))
    assert not (tmp_path / "x.zarr").exists()


def test_create_refuses_rows_that_do_not_fit(tmp_path):
    with pytest.raises(ValueError, match=r"y\.zarr: light_dir \(2, 3\), view_dir \(3, 3\) and lv_index \(2, 3\)"):
        create_btf_store(tmp_path / "y.zarr", {"units": "u", "lv_order": LV_ORDER, "ingest_hash": "k"},
                         light_dir=directions(2), view_dir=directions(3), lv_index=np.zeros((2, 3), np.int32),
                         texture_shape=(2, 2), rows_per_chunk=1, band=2, written_shape=(2,))
    assert not (tmp_path / "y.zarr").exists()


def test_the_error_pickles():
    error = pickle.loads(pickle.dumps(BtfStoreError("p.zarr", "p.zarr: message")))
    assert isinstance(error, ValueError) and error.path == "p.zarr" and str(error) == "p.zarr: message"
