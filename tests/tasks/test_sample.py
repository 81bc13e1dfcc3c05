"""Sparse sampling of a model-store basis (tasks.sample): groups, JSON round trip, errors naming the store."""

from __future__ import annotations

import json

import numpy as np
import pytest
import zarr

from btfcore.model._lowrank import TruncatedSVD
from btfcore.acquisition.sampling import selection_condition
from btfcore.dome import get_device
from tasks.model import SCHEMA_NAME, write_basis
from tasks.sample import (
    camera_parallel_groups,
    open_model,
    read_class_basis,
    read_samples,
    sample_model,
    write_samples,
)


def _device_rows(device):
    """Light/view directions of a device's rows in ingest order (turntable, camera, light), in the sample frame."""
    rows = []
    for t, angle in enumerate(device.turntable_angle_deg):
        a = np.radians(angle)
        rot = np.array([[np.cos(a), np.sin(a), 0], [-np.sin(a), np.cos(a), 0], [0, 0, 1]])
        for c in range(device.n_cam):
            v = device.camera_position[c] / np.linalg.norm(device.camera_position[c])
            for led in range(device.n_leds):
                ell = device.led_position[led] / np.linalg.norm(device.led_position[led])
                rows.append((rot @ ell, rot @ v))
    L, V = (np.array(x) for x in zip(*rows))
    return L, V


def make_model(path, device_name: str = "tiny", k: int = 12, classes=("leather",), seed: int = 0):
    """A tiny btf-model store: a device's rows and random orthonormal class bases (log_y, abtf_log_y, als)."""
    device = get_device(device_name)
    L, V = _device_rows(device)
    n_lv = L.shape[0]
    group = zarr.open_group(str(path / "model.zarr"), mode="w", zarr_format=3)
    for name, data in (("light_dir", L), ("view_dir", V)):
        group.create_array(name, data=data)
    group.attrs.put({"schema": SCHEMA_NAME, "schema_version": "1.0", "rows_id": "test", "n_lv": n_lv})
    rng = np.random.default_rng(seed)
    for cls in classes:
        for basis, rows in (("log_y", n_lv), ("abtf_log_y", 9 * n_lv), ("als", n_lv)):
            U = np.linalg.qr(rng.normal(size=(rows, k)))[0]
            write_basis(group, f"classes/{cls}/{basis}", TruncatedSVD(U, np.linspace(10, 1, k), "merge"), "key")
    return path, device


@pytest.fixture()
def model(tmp_path):
    return make_model(tmp_path)


def test_sample_greedy_writes_rows_with_their_kappa(model, tmp_path):
    path, _ = model
    doc = sample_model(path, "leather", "log_y", 30)
    U = zarr.open_group(str(path / "model.zarr"), mode="r")["classes/leather/log_y/U"][...]
    assert doc["n_s"] == 30 and len(doc["rows"]) == 30 and doc["method"] == "greedy"
    np.testing.assert_allclose(doc["kappa"], selection_condition(U, np.array(doc["rows"])), rtol=1e-10)
    assert doc["kappa_history"]["final"] <= doc["kappa_history"]["start"]
    out = write_samples(doc, tmp_path / "s" / "samples.json")
    assert read_samples(out) == json.loads(out.read_text()) == doc


def test_camera_parallel_groups_are_turntable_led_pairs(model):
    path, device = model
    group = zarr.open_group(str(path / "model.zarr"), mode="r")
    L, V = group["light_dir"][...], group["view_dir"][...]
    by_dev, how, pairs = camera_parallel_groups(L, V, device)
    assert how == "device" and pairs.shape == (device.n_turn * device.n_leds, 2)
    by_dir, how, _ = camera_parallel_groups(L, V)
    assert how == "row_order"
    # the same partition, read from the directions alone (the tiny dome's turntable steps map LEDs onto
    # each other, so grouping by light direction alone would merge pairs)
    assert len(np.unique(by_dir)) == len(np.unique(by_dev)) == device.n_turn * device.n_leds
    assert len(set(zip(by_dev.tolist(), by_dir.tolist()))) == device.n_turn * device.n_leds
    doc = sample_model(path, "leather", "log_y", 8, camera_parallel=True, device=device)
    rows = np.array(doc["rows"])
    assert rows.size == 8 * device.n_cam                               # all cameras of each chosen pair
    assert len(doc["pairs"]) == 8
    t, led = np.array(doc["pairs"]).T
    expected = np.sort(((t * device.n_cam)[:, None] + np.arange(device.n_cam)) * device.n_leds + led[:, None])
    np.testing.assert_array_equal(np.sort(expected.ravel()), rows)


def test_patch_basis_and_other_methods(model):
    path, _ = model
    abtf = sample_model(path, "leather", "abtf_log_y", 10)
    assert abtf["patch"] == 3 and abtf["n_s"] == 10
    swap = sample_model(path, "leather", "als", 30, method="random_swap", max_steps=200)
    assert swap["method"] == "random_swap" and swap["steps"] == 200
    para = sample_model(path, "leather", "log_y", None, method="parabolic_map")
    assert para["method"] == "parabolic_map" and para["n_rows"] > 0


def test_errors_name_the_store_and_the_fix(model, tmp_path):
    path, device = model
    with pytest.raises(ValueError, match="no such model directory"):
        open_model(tmp_path / "nothing")
    zarr.open_group(str(tmp_path / "other.zarr"), mode="w", zarr_format=3).attrs.put({"schema": "btf-texture"})
    with pytest.raises(ValueError, match="not a model store"):
        open_model(tmp_path / "other.zarr")
    group, store = open_model(path)
    with pytest.raises(ValueError, match=r"no class 'wood'.*leather.*--class"):
        read_class_basis(group, store, "wood", "log_y")
    with pytest.raises(ValueError, match="cannot be sampled"):
        read_class_basis(group, store, "leather", "u_y")
    with pytest.raises(ValueError, match=r"classes/leather/log_y.*fewer than its k=12"):
        sample_model(path, "leather", "log_y", 5)                     # fewer samples than basis vectors
    with pytest.raises(ValueError, match="needs the number of samples"):
        sample_model(path, "leather", "log_y", None)
    with pytest.raises(ValueError, match="another device|resampled"):
        sample_model(path, "leather", "log_y", 30, device=get_device("bonn-dome2"))
    U = group["classes/leather/log_y/U"]
    zarr.open_group(str(path / "model.zarr"), mode="r+")["classes/leather/log_y/U"][3, 2] = np.nan
    with pytest.raises(ValueError, match=r"log_y/U\[3, 2\].*not finite"):
        sample_model(path, "leather", "log_y", 30)
    assert U.shape[1] == 12
    bad = tmp_path / "bad.json"
    bad.write_text("{")
    with pytest.raises(ValueError, match="not JSON"):
        read_samples(bad)


def test_groups_of_a_resampled_sampling_are_lights_with_all_views():
    from btfcore.capture.resample import lv_product, ubo2014_directions

    d = ubo2014_directions()[:10]
    L, V = lv_product(d, d)                                            # view-major, light fastest
    groups, how, _ = camera_parallel_groups(L, V)
    assert how == "row_order"
    np.testing.assert_array_equal(groups, np.tile(np.arange(10), 10))
