"""Super-resolution on stores: model files, training data from regions, and `superres_apply` (chunked over
views on a real LocalCluster) against the same steps in memory."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest
import torch

from btfcore.superres.espcn import Espcn, EspcnConfig
from btfcore.superres.regions import rectify_regions, scale_homography, upsample_regions
from btfcore.superres.training import TrainingSettings
from tasks.ingest import ingest_capture
from tasks.simulate import SimulationConfig, simulate_database
from tasks.stores.btf import BtfStore, open_btf_store
from tasks.superres import (
    load_model,
    save_model,
    superres_apply,
    train_model,
    training_images,
    view_rows,
    with_regions,
)

CONFIG = SimulationConfig(device="tiny", n_materials=2, seed=3, classes=("leather", "cloth"), n_turntable=1,
                          texture_size=16)
SMALL = EspcnConfig(features=(8, 4, 4))
QUICK = TrainingSettings(max_epochs=2, batch_size=16, seed=1)


@pytest.fixture(scope="module")
def stores(tmp_path_factory, dask_client):
    """Two tiny captures (one turntable position, 16 x 16 texels) ingested with their regions."""
    db = tmp_path_factory.mktemp("sr-db")
    out = tmp_path_factory.mktemp("sr-btf")
    paths = []
    for capture in simulate_database(CONFIG, db, dask_client).stores:
        paths.append(out / capture.split("/")[-1])
        ingest_capture(capture, paths[-1], dask_client, keep_roi=True)
    return [str(p) for p in paths]


@pytest.fixture(scope="module")
def model_file(stores, tmp_path_factory):
    path = tmp_path_factory.mktemp("sr-model") / "model.pt"
    summary = train_model(stores[:1], path, protocol="exact", fraction=0.1, config=SMALL, settings=QUICK)
    assert summary["reused"] is False and summary["patches"] > 0
    return path


def test_training_images_are_down_sampled_regions(stores):
    store = with_regions(stores[0])
    low, high, drawn = training_images([store], protocol="exact", fraction=0.05, seed=0)
    rows = drawn[0]["rows"]
    assert len(rows) == round(0.05 * store.n_lv) and len(low) == 3 * len(rows)
    roi = store.group["roi"].oindex[rows, :, :, :]
    np.testing.assert_array_equal(high[0], roi[0, ..., 0])                       # channel images, in order
    np.testing.assert_allclose(low[0], roi[0, ..., 0].reshape(36, 2, 36, 2).mean(axis=(1, 3)), rtol=1e-6)
    low2, high2, drawn2 = training_images([store], protocol="paper", fraction=0.05, seed=0)
    assert drawn2 == drawn and high2.shape[1:] == low.shape[1:] and low2.shape[1:] == (18, 18)


def test_model_file_round_trip_and_reuse(stores, model_file):
    loaded = load_model(model_file)
    assert loaded.config == SMALL and loaded.provenance["protocol"] == "exact"
    x = np.random.default_rng(0).random((2, 20, 20), dtype=np.float32)
    fresh = Espcn(SMALL)
    fresh.load_state_dict(loaded.model.state_dict())
    fresh.eval()
    from btfcore.superres.espcn import upscale
    np.testing.assert_array_equal(upscale(loaded.model, x), upscale(fresh, x))
    again = train_model(stores[:1], model_file, protocol="exact", fraction=0.1, config=SMALL, settings=QUICK)
    assert again["reused"] is True


def test_bad_model_files_are_refused(model_file, tmp_path):
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a model at all")
    with pytest.raises(ValueError, match="junk.pt: not a readable model file.*btf superres train"):
        load_model(junk)
    payload = torch.load(model_file, weights_only=True)
    payload["state_dict"]["conv1.weight"][0, 0, 0, 0] += 1.0                      # tampered weights
    torch.save(payload, tmp_path / "tampered.pt")
    with pytest.raises(ValueError, match="tampered.pt: the weights do not match the file's SHA-256"):
        load_model(tmp_path / "tampered.pt")
    other = save_model(tmp_path / "other.pt", Espcn(EspcnConfig(features=(8, 4, 2))).state_dict(), SMALL, {})
    with pytest.raises(ValueError, match="other.pt: the weights are not those of the network"):
        load_model(other)
    wide = save_model(tmp_path / "scale3.pt", Espcn(EspcnConfig(features=(8, 4, 4), scale=3)).state_dict(),
                      EspcnConfig(features=(8, 4, 4), scale=3), {})
    with pytest.raises(ValueError, match="scale3.pt: a network of scale 3"):
        load_model(wide)
    with zipfile.ZipFile(tmp_path / "zip.pt", "w") as z:
        z.writestr("x", "y")
    with pytest.raises(ValueError, match="zip.pt: not a readable model file"):
        load_model(tmp_path / "zip.pt")


@pytest.mark.parametrize("method", ["bicubic", "espcn"])
def test_apply_on_the_cluster_equals_in_memory_and_resumes(stores, model_file, tmp_path, dask_client, method):
    model = str(model_file) if method == "espcn" else None
    out = tmp_path / "sr.zarr"
    summary = superres_apply(stores[1], model, out, dask_client, method=method)
    assert summary["views_processed"] == 4 and summary["texture_shape"] == [32, 32]
    source, result = with_regions(stores[1]), open_btf_store(out)
    net = None if model is None else load_model(model).model
    for t, c in np.ndindex(1, 4):
        rows = view_rows(source, t, c)
        up = upsample_regions(source.group["roi"][rows], method=method, model=net)
        expected = rectify_regions(up, scale_homography(source.group["homography"][t, c], 2), (32, 32),
                                   source.attrs["sample_size_m"])
        np.testing.assert_allclose(result.btf[rows], expected, rtol=1e-5, atol=1e-7 * float(np.abs(expected).max()))
    before = result.btf[...]
    result = BtfStore(out, "r+")
    result.group["written"][0, 2] = 0                                              # as if killed in view (0, 2)
    result.group["btf"][view_rows(source, 0, 2)] = 0.0
    result.group.attrs["complete"] = False
    again = superres_apply(stores[1], model, out, dask_client, method=method)
    assert again["views_processed"] == 1 and again["views_skipped"] == 3
    np.testing.assert_array_equal(open_btf_store(out).btf[...], before)


def test_stores_without_regions_and_non_finite_regions_are_refused(stores, tmp_path, dask_client):
    plain = tmp_path / "plain.zarr"
    capture = open_btf_store(stores[0]).attrs["source"]
    ingest_capture(capture, plain, dask_client)
    with pytest.raises(ValueError, match="plain.zarr: the store holds no regions.*--keep-roi"):
        superres_apply(plain, None, tmp_path / "x.zarr", dask_client, method="bicubic")
    with pytest.raises(ValueError, match="give at least one BTF store"):
        training_images([], protocol="exact")


def test_non_finite_regions_are_named(stores, tmp_path):
    import shutil

    copy = tmp_path / "nan.zarr"
    shutil.copytree(stores[0], copy)
    BtfStore(copy, "r+").group["roi"][5, 1, 2, 0] = np.nan
    with pytest.raises(ValueError, match=r"nan.zarr: 1 NaN or Inf values in roi, first at index"):
        training_images([with_regions(copy)], fraction=1.0)
