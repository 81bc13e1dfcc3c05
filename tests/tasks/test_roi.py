"""Regions of interest kept at ingest (`btf ingest --keep-roi`), the 2x camera and the regions' 2x truth,
on a tiny simulated capture and a real LocalCluster."""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import asdict
from types import SimpleNamespace

import numpy as np
import pytest
import zarr
from scipy import ndimage

from btfcore.capture.rectify import apply_rectification, rectification_matrix
from btfcore.capture.view_chain import IngestSettings
from btfcore.simulate.camera import sample_mask
from btfcore.simulate.render import downsample2
from tasks.ingest import _check_keep_roi, ingest_capture, ingest_hash
from tasks.simulate import (
    SimulationConfig,
    config_hash,
    material_plan,
    pattern_frames,
    roi_truth,
    simulate_database,
)
from tasks.stores import open_capture_store
from tasks.stores.btf import open_btf_store, validate_btf_store

#: The capture of the fixture: one turntable position (4 views), 16 LEDs measured singly and through
#: S-matrix patterns (so the regions are demultiplexed), 8 x 8 texels.
CONFIG = SimulationConfig(device="tiny", n_materials=1, seed=8, classes=("leather",), n_turntable=1,
                          texture_size=8, illumination="both")


@pytest.fixture(scope="module")
def capture(tmp_path_factory, dask_client):
    return simulate_database(CONFIG, tmp_path_factory.mktemp("roi-capture"), dask_client).stores[0]


@pytest.fixture(scope="module")
def ingests(capture, tmp_path_factory, dask_client):
    """The capture ingested without and with the regions of interest."""
    out = tmp_path_factory.mktemp("roi-ingest")
    plain, kept = out / "plain.zarr", out / "kept.zarr"
    ingest_capture(capture, plain, dask_client)
    result = ingest_capture(capture, kept, dask_client, keep_roi=True)
    assert result["views_processed"] == 4
    return plain, kept


def test_the_regions_rectify_to_the_textures(capture, ingests):
    """Every view's stored region, rectified by the operator of its stored homography, is its stored texture."""
    cap = open_capture_store(capture)
    store = open_btf_store(ingests[1])
    attrs = store.attrs
    assert attrs["keep_roi"] is True and attrs["roi_shape"] == list(cap.roi_shape)
    assert attrs["sample_size_m"] == cap.meta.sample_size_m
    n_leds, (rows, cols), (h, w) = cap.n_leds, cap.roi_shape, store.texture_shape
    assert store.roi.shape == (cap.n_turn * cap.n_cam * n_leds, rows, cols, 3) and store.roi.dtype == np.float32
    assert store.roi.chunks[0] == n_leds                                    # one view's LEDs per chunk
    np.testing.assert_array_equal(store.homography, cap.homography)
    assert validate_btf_store(ingests[1]) == []
    roi, btf = store.roi[...], store.btf[...]
    assert np.isfinite(roi).all() and roi.max() > 0
    for t, c in np.ndindex(cap.n_turn, cap.n_cam):
        rows_of_view = slice((t * cap.n_cam + c) * n_leds, (t * cap.n_cam + c + 1) * n_leds)
        A = rectification_matrix(store.homography[t, c], attrs["roi_shape"], (h, w), attrs["sample_size_m"])
        stack = roi[rows_of_view].transpose(1, 2, 0, 3).reshape(rows, cols, 3 * n_leds)   # (rows, cols, 3 n)
        rectified = apply_rectification(A, stack, (h, w)).reshape(h, w, n_leds, 3).transpose(2, 0, 1, 3)
        expected = btf[rows_of_view]
        # float32 rounding of the demultiplexing GEMM, which cancels large terms: relative to the largest value
        np.testing.assert_allclose(rectified, expected, rtol=0, atol=2e-6 * np.abs(expected).max(),
                                   err_msg=f"view {(t, c)}")


def test_keeping_the_regions_leaves_the_textures_as_they_are(ingests):
    plain, kept = (open_btf_store(p) for p in ingests)
    assert plain.roi is None and plain.homography is None and "keep_roi" not in plain.attrs
    # the whole frame is merged and demosaicked instead of the window, the same pixels for the operator
    np.testing.assert_array_equal(kept.btf[...], plain.btf[...])
    np.testing.assert_array_equal(kept.group["valid_fraction"][...] > 0, plain.group["valid_fraction"][...] > 0)


def test_keep_roi_enters_the_hash_only_when_true_and_is_never_resumed_across(capture, ingests, dask_client):
    cap = open_capture_store(capture)
    settings = IngestSettings()
    before = {"capture": cap.group.attrs["provenance"]["config_hash"], "settings": asdict(settings),
              "schema": "btf-texture/1.0", "calibration": None}                # the hash before --keep-roi existed
    old = hashlib.sha256(json.dumps(before, sort_keys=True).encode()).hexdigest()[:16]
    assert ingest_hash(cap, settings) == ingest_hash(cap, settings, None, False) == old
    assert ingest_hash(cap, settings, None, True) != old
    plain, kept = ingests
    assert open_btf_store(plain).attrs["ingest_hash"] == old
    with pytest.raises(FileExistsError, match="written without --keep-roi"):
        ingest_capture(capture, plain, dask_client, keep_roi=True)
    with pytest.raises(FileExistsError, match="written with --keep-roi"):
        ingest_capture(capture, kept, dask_client)
    # the simulator's config hash is untouched by camera_scale at 1 (existing stores keep theirs)
    spec = material_plan(CONFIG)[0]
    assert "camera_scale" not in CONFIG.to_json()
    assert config_hash(SimulationConfig(**{**CONFIG.__dict__, "camera_scale": 1}), spec) == config_hash(CONFIG, spec)
    assert config_hash(SimulationConfig(**{**CONFIG.__dict__, "camera_scale": 2}), spec) != config_hash(CONFIG, spec)
    assert config_hash(SimulationConfig(device="tiny", n_materials=1, seed=8, classes=("leather",), n_turntable=1,
                                        texture_size=8), spec) == "8f5d30dbc52efdcf"


def test_a_killed_ingest_with_regions_resumes(capture, ingests, tmp_path, dask_client):
    out = tmp_path / "kept.zarr"
    shutil.copytree(ingests[1], out)
    group = zarr.open_group(str(out), mode="r+")
    group["written"][0, 2] = 0                                  # a view whose marker never came
    group["roi"][32:48] = 0.0
    group.attrs["complete"] = False
    again = ingest_capture(capture, out, dask_client, keep_roi=True)
    assert again["views_processed"] == 1 and again["views_skipped"] == 3
    np.testing.assert_array_equal(open_btf_store(out).roi[...], open_btf_store(ingests[1]).roi[...])


def test_validation_names_missing_or_misshapen_regions(ingests, tmp_path):
    out = tmp_path / "bad.zarr"
    shutil.copytree(ingests[1], out)
    group = zarr.open_group(str(out), mode="r+")
    del group["homography"]
    group.attrs["roi_shape"] = [10, 10]
    problems = {(p.array, p.expected.split(" ")[0]) for p in validate_btf_store(out)}
    assert ("homography", "array") in problems and ("roi", "float32") in problems, problems


def test_plan_captures_without_single_led_frames_refuse_keep_roi():
    sparse = SimpleNamespace(path="plan.zarr", is_plan_capture=True, planned=np.zeros((1, 1, 2), bool),
                             meta=SimpleNamespace(plan={"strategy": "sparse"}))
    with pytest.raises(ValueError, match="plan.zarr: --keep-roi .* measurement store"):
        _check_keep_roi(sparse)
    mixed = SimpleNamespace(path="plan.zarr", is_plan_capture=True, planned=np.ones((1, 1, 2), bool),
                            illumination=np.eye(2, dtype=np.uint8), exposure_time=np.array([[[[1e-3, 0.0]]]]))
    with pytest.raises(ValueError, match="differ in length"):
        _check_keep_roi(mixed)


def test_the_regions_truth_at_twice_the_pixels(capture):
    """The 2x truth of a region, each 2 x 2 block averaged, is its 1x truth; the 1x truth times the LED
    gains is the radiance the simulator exposed (pattern_frames of single-LED patterns)."""
    cap = open_capture_store(capture)
    device = CONFIG.build_device()
    n_leds = device.n_leds
    for t, c in ((0, 0), (0, 2), (0, 3)):
        view = slice((t * device.n_cam + c) * n_leds, (t * device.n_cam + c + 1) * n_leds)
        truth_2x = cap.truth["btf_2x"][view]
        once, twice = roi_truth(device, truth_2x, t, c), roi_truth(device, truth_2x, t, c, factor=2)
        assert once.shape == (n_leds, *device.roi_shape, 3) and once.dtype == np.float32
        assert twice.shape == (n_leds, 2 * device.roi_shape[0], 2 * device.roi_shape[1], 3)
        # render_frame averages 3 x 3 sub-pixels per pixel: 6 x 6 per 1x pixel at 2x. Measured on these
        # views: relative L2 0.07-4.6 % over the whole region, most of it where a pixel straddles the
        # sample's edge (the covered fraction in 1/9 against 1/36 steps); elsewhere 0.07-0.24 %, at most
        # 3.3 % of the largest value
        diff = downsample2(twice) - once
        on_sample = sample_mask(device, t, c)
        off_edge = ndimage.binary_erosion(on_sample) | ~ndimage.binary_dilation(on_sample)
        assert np.linalg.norm(diff) < 0.06 * np.linalg.norm(once)
        assert np.linalg.norm(diff[:, off_edge]) < 5e-3 * np.linalg.norm(once[:, off_edge])
        assert np.abs(diff[:, off_edge]).max() < 0.05 * np.abs(once).max()
        frames, _ = pattern_frames(device, np.eye(n_leds, dtype=np.float32), truth_2x, t, c)
        np.testing.assert_allclose(once * device.led_rgb_gain[:, None, None, :].astype(np.float32), frames,
                                   rtol=1e-5, atol=1e-7 * np.abs(frames).max())
    with pytest.raises(ValueError, match="one view's LEDs"):
        roi_truth(device, truth_2x[:3], 0, 0)


def test_camera_scale_makes_a_larger_region():
    big = SimulationConfig(**{**CONFIG.__dict__, "camera_scale": 2})
    small_dev, big_dev = CONFIG.build_device(), big.build_device()
    assert big_dev.roi_shape == (2 * small_dev.roi_shape[0], 2 * small_dev.roi_shape[1])
    assert big.to_json()["camera_scale"] == 2
    with pytest.raises(ValueError, match="camera_scale"):
        SimulationConfig(camera_scale=0)


def test_calibrated_regions_rectify_to_the_calibrated_textures(capture):
    """With LED gains and a colour matrix the regions are corrected exactly like the textures."""
    from btfcore.capture.view_chain import process_view, view_window
    from tasks.ingest import view_chain_arguments
    from tasks.radiometric import Calibration

    cap = open_capture_store(capture)
    rng = np.random.default_rng(3)
    calibration = Calibration(led_gain=rng.uniform(0.5, 2.0, (cap.n_leds, 3)),
                              colour_matrix=np.eye(3) + rng.uniform(-0.1, 0.1, (3, 3)), info={})
    h, w = cap.meta.texture_shape
    for t, c in ((0, 1), (0, 3)):
        window = view_window(cap.homography[t, c], cap.roi_shape, (h, w), cap.meta.sample_size_m, whole_frame=True)
        assert (window[0], window[1]) == (slice(0, cap.roi_shape[0]), slice(0, cap.roi_shape[1]))
        roi = np.empty((cap.n_leds, *cap.roi_shape, 3), dtype=np.float32)
        textures, _ = process_view(cap.raw[t, c], cap.exposure_time[t, c], cap.illumination, roi_out=roi,
                                   **view_chain_arguments(cap, t, c, window, IngestSettings(), calibration))
        stack = roi.transpose(1, 2, 0, 3).reshape(*cap.roi_shape, -1)
        rectified = apply_rectification(window[2], stack, (h, w)).reshape(h, w, cap.n_leds, 3).transpose(2, 0, 1, 3)
        np.testing.assert_allclose(rectified, textures, rtol=0, atol=2e-6 * np.abs(textures).max())
    with pytest.raises(ValueError, match="roi_out must be"):
        process_view(cap.raw[0, 0], cap.exposure_time[0, 0], cap.illumination, roi_out=roi[:3],
                     **view_chain_arguments(cap, 0, 0, window, IngestSettings()))


def test_a_nan_in_a_views_float_frames_is_named_before_merging(capture):
    """The view chain merges its brackets without scanning each (`linear_merger(check_finite=False)`): it scans
    the view's frames once and names the first NaN by its (illumination, exposure, row, column)."""
    from btfcore.capture.view_chain import process_view, view_window
    from tasks.ingest import view_chain_arguments

    cap = open_capture_store(capture)
    window = view_window(cap.homography[0, 1], cap.roi_shape, tuple(cap.meta.texture_shape), cap.meta.sample_size_m)
    frames = cap.read_raw(0, 1, window).astype(np.float32)
    frames[2, 1, 3, 4] = np.nan
    with pytest.raises(ValueError, match=r"frames\[2, 1, 3, 4\] is nan"):
        process_view(frames, cap.exposure_time[0, 1], cap.illumination,
                     **view_chain_arguments(cap, 0, 1, window, IngestSettings()))
