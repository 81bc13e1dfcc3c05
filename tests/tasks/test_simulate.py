"""Chunked virtual-dome generation on a real LocalCluster, writing real Zarr."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tasks.simulate import SimulationConfig, material_plan, simulate_database
from tasks.stores import open_capture_store


def _arrays(path):
    store = open_capture_store(path)
    return {
        "raw": store.raw[...],
        "exposure_time": store.exposure_time,
        "dark": store.dark_frames[...],
        "btf": store.truth["btf"][...],
        "btf_2x": store.truth["btf_2x"][...],
    }


def test_simulation_is_deterministic_and_valid(tmp_path, dask_client):
    config = SimulationConfig(device="tiny", n_materials=1, seed=11, classes=("leather",), n_turntable=1)
    a = simulate_database(config, tmp_path / "a", dask_client)
    b = simulate_database(config, tmp_path / "b", dask_client)
    assert a.views_done == b.views_done == config.build_device().n_cam
    first, second = _arrays(a.stores[0]), _arrays(b.stores[0])
    for name in first:
        np.testing.assert_array_equal(first[name], second[name], err_msg=name)
    # the stores pass validation as complete stores
    store = open_capture_store(a.stores[0])
    assert store.complete
    # a different seed gives a different material and different noise
    other = simulate_database(SimulationConfig(**{**config.__dict__, "seed": 12}), tmp_path / "c", dask_client)
    assert not np.array_equal(_arrays(other.stores[0])["raw"], first["raw"])


def test_resume_recomputes_only_pending_views(tmp_path, dask_client):
    config = SimulationConfig(device="tiny", n_materials=1, seed=5, classes=("cloth",), n_turntable=1)
    full = simulate_database(config, tmp_path, dask_client)
    before = _arrays(full.stores[0])
    # Simulate a run killed after some views: forget two views and the completion flag.
    store = open_capture_store(full.stores[0], mode="r+")
    store.group["written"][0:1, 1:3, :] = 0
    store.group.attrs["complete"] = False
    again = simulate_database(config, tmp_path, dask_client)
    assert again.views_done == 2
    after = _arrays(again.stores[0])
    for name in before:
        np.testing.assert_array_equal(before[name], after[name], err_msg=name)
    # a finished store is reused, not recomputed
    third = simulate_database(config, tmp_path, dask_client)
    assert third.views_done == 0


def test_finished_store_of_another_config_is_not_overwritten(tmp_path, dask_client):
    config = SimulationConfig(device="tiny", n_materials=1, seed=1, classes=("wood",), n_turntable=1)
    result = simulate_database(config, tmp_path, dask_client)
    raw = open_capture_store(result.stores[0]).raw[...]
    other = SimulationConfig(device="tiny", n_materials=1, seed=2, classes=("wood",), n_turntable=1)
    # same material id, different seed -> different config hash
    assert material_plan(other)[0].material_id == material_plan(config)[0].material_id
    with pytest.raises(FileExistsError, match="000-wood"):
        simulate_database(other, tmp_path, dask_client)
    np.testing.assert_array_equal(open_capture_store(result.stores[0]).raw[...], raw)


def _radiance_estimate(frames, times, black, white):
    """Per-pixel radiance rate from the longest unsaturated exposure of a bracket."""
    level = frames.astype(np.float64) - black
    ok = (frames < white - 1) & (level > 20)
    best = np.where(ok, np.arange(len(times))[:, None, None], -1).max(axis=0)
    rate = np.take_along_axis(level / times[:, None, None], np.maximum(best, 0)[None], 0)[0]
    return np.where(best >= 0, rate, np.nan)


def test_multiplexed_frame_is_the_sum_of_singles(tmp_path, dask_client):
    config = SimulationConfig(device="tiny", n_materials=1, seed=3, classes=("stone",), n_turntable=1,
                              illumination="both")
    store = open_capture_store(simulate_database(config, tmp_path, dask_client).stores[0])
    patterns = store.illumination
    n_leds = store.n_leds
    assert patterns.shape[0] > n_leds and (patterns[:n_leds] == np.eye(n_leds)).all()
    meta = store.meta
    t, c = 0, 1
    singles = np.stack([_radiance_estimate(*store.read_bracket(t, c, i), meta.black_level, meta.white_level)
                        for i in range(n_leds)])
    for i in range(n_leds, patterns.shape[0]):
        multiplexed = _radiance_estimate(*store.read_bracket(t, c, i), meta.black_level, meta.white_level)
        summed = singles[patterns[i].astype(bool)].sum(axis=0)
        valid = np.isfinite(multiplexed) & np.isfinite(summed) & (summed > 0)
        assert valid.mean() > 0.5
        rel = np.abs(multiplexed[valid] - summed[valid]) / summed[valid]
        # photon + read noise of a few hundred electrons per pixel: a few per cent
        assert np.median(rel) < 0.05, (i, np.median(rel))


def test_a_database_that_cannot_fit_is_refused_before_any_work(tmp_path, dask_client):
    # ~425 TB: more than any test machine's disk
    config = SimulationConfig(device="bonn-dome2", n_materials=10_000)
    with pytest.raises(ValueError, match=r"needs about .* GB but only .* GB are free"):
        simulate_database(config, tmp_path / "huge", dask_client)
    assert not (tmp_path / "huge").exists()


def test_noise_free_frames_reproduce_the_capture_without_its_noise(tmp_path, dask_client):
    # the floors re-expose the stored truth through the simulator's own frames: the same brackets,
    # and a noise-free frame is the mean the noisy capture scatters around
    from btfcore.simulate.sensor import SensorModel, expected_dn, expose
    from tasks.simulate import camera_dark_map, pattern_frames

    config = SimulationConfig(device="tiny", n_materials=1, seed=4, classes=("cloth",), n_turntable=1)
    store = open_capture_store(simulate_database(config, tmp_path, dask_client).stores[0])
    device, t, c, n_leds = config.build_device(), 0, 2, store.n_leds
    truth_2x = store.truth["btf_2x"][(t * store.n_cam + c) * n_leds:(t * store.n_cam + c + 1) * n_leds]
    frames, _ = pattern_frames(device, store.illumination.astype(np.float32), truth_2x, t, c)
    times = store.exposure_time[t, c]
    clean = expose(frames[:, None], times, device.sensor, camera_dark_map(device, c), None,
                   model=SensorModel(noise=False))
    dark_map = camera_dark_map(device, c)
    np.testing.assert_array_equal(clean, expected_dn(frames[:, None], times, device.sensor, dark_map))
    raw = store.raw[t, c].astype(np.float64)
    unsaturated = (raw < store.meta.white_level) & (clean < store.meta.white_level)
    assert abs(np.mean((raw - clean)[unsaturated])) < 0.5          # unbiased: the noise averages out
    full = expose(frames[:, None], times, device.sensor, None, None, model=SensorModel(noise=False, mosaic=False))
    assert full.shape == (*raw.shape, 3)                            # R, G and B at every pixel


def test_floors_are_below_the_ingest_error_and_reused(tmp_path, dask_client):
    # property on seeded data: removing the noise cannot make the chain worse, nor can removing the mosaic
    from tasks.floors import FLOOR_SENSORS, ingest_floors
    from tasks.ingest import btf_error_against_truth, ingest_capture

    config = SimulationConfig(device="tiny", n_materials=2, seed=6, classes=("cloth", "stone"), n_turntable=1)
    stores = simulate_database(config, tmp_path / "db", dask_client).stores
    result = ingest_floors(config, stores, dask_client, tmp_path / "floors.json")
    assert result["reused"] == {"materials": [0, 2]} and result["seconds"] > 0
    for path in stores:
        out = tmp_path / "btf" / Path(path).name
        ingest_capture(path, out, dask_client)
        error = btf_error_against_truth(out, path)
        floors = result["floors"][Path(path).stem]
        assert set(floors) == set(FLOOR_SENSORS)
        for metric in ("relative_l2_linear", "relative_l2_log_y"):
            assert 0 < floors["full_rgb"][metric] <= floors["noise_free"][metric] <= error[metric] + 1e-3, \
                (path, metric, floors, error)
    again = ingest_floors(config, stores, dask_client, tmp_path / "floors.json")
    assert again["reused"] == {"materials": [2, 2]} and again["floors"] == result["floors"]
