"""The simulator's dome that is not ideal (tasks.simulate, ``non_ideal``): the ideal dome's stores are unchanged, a
non-ideal capture carries its effects in its raw frames, and it goes through simulate -> ingest with a sensible
error."""

from __future__ import annotations

import numpy as np
import pytest

from btfcore.simulate.nonideal import IDEAL, PRESETS, DomeNonIdeality, gain_factor


def test_the_ideal_dome_keeps_its_configs_and_hashes():
    from tasks.evaluate_acquisition import EvaluationConfig
    from tasks.simulate import SimulationConfig, config_hash, material_plan

    config = SimulationConfig()
    assert config.non_ideal is IDEAL and "non_ideal" not in config.to_json()
    # the hash of the default database's first store as it was before the option existed
    assert config_hash(config, material_plan(config)[0]) == "6bc13a910d01aa8d"
    assert "non_ideal" not in EvaluationConfig().to_json()
    real = SimulationConfig(non_ideal=PRESETS["realistic"])
    assert real.to_json()["non_ideal"]["single_gain_db"] == 10.0
    assert config_hash(real, material_plan(real)[0]) != config_hash(config, material_plan(config)[0])
    with pytest.raises(ValueError, match="non_ideal must be"):
        SimulationConfig(non_ideal={"led_drift": 0.1})


def _view(illumination: str = "both"):
    from btfcore.simulate.materials import make_material
    from btfcore.simulate.render import horizon_map, render_view
    from tasks.simulate import SimulationConfig, illumination_patterns
    from tasks.textures import load_texture_sources

    config = SimulationConfig(device="tiny", n_materials=1, seed=3, classes=("leather",), n_turntable=1,
                              texture_size=8, illumination=illumination)
    device = config.build_device()
    maps = make_material("leather", 11, (16, 16), load_texture_sources())
    truth_2x = render_view(maps, device.view_dir(0, 1), device.light_dirs(0), horizon_map(maps.height))
    weights = illumination_patterns(device.n_leds, illumination).astype(np.float32)
    return config, device, truth_2x, weights


def test_the_non_ideal_exposure_of_the_ideal_dome_is_the_ideal_one_bit_for_bit():
    import dataclasses

    from btfcore.simulate.sensor import choose_bracket, expose
    from tasks.simulate import MaterialSpec, _expose_nonideal, camera_dark_map, pattern_frames

    config, device, truth_2x, weights = _view()
    spec = MaterialSpec(0, "000-leather", "leather", 11)
    frames, mask = pattern_frames(device, weights, truth_2x, 0, 1)
    times = choose_bracket(frames, device.sensor, mask=mask)
    ideal = expose(frames[:, None], times, device.sensor, camera_dark_map(device, 1), np.random.default_rng(9))
    raw, t = _expose_nonideal(device, dataclasses.replace(config, non_ideal=IDEAL), spec, weights,
                              np.arange(len(weights)), len(weights), truth_2x, 0, 1, None, np.random.default_rng(9))
    assert np.array_equal(t, times) and np.array_equal(raw, ideal)


def test_a_non_ideal_view_has_its_effects_in_the_raw_frames():
    import dataclasses

    from tasks.simulate import DEVICE_SEED, MaterialSpec, _expose_nonideal
    from btfcore.simulate.nonideal import hot_pixel_mask

    config, device, truth_2x, weights = _view()
    spec = MaterialSpec(0, "000-leather", "leather", 11)
    dome = DomeNonIdeality(multiplex_single_exposure=True, single_gain_db=10.0, hot_pixel_fraction=0.002)
    real = dataclasses.replace(config, non_ideal=dome)
    n = len(weights)
    ideal_raw, ideal_t = _expose_nonideal(device, dataclasses.replace(config, non_ideal=IDEAL), spec, weights,
                                          np.arange(n), n, truth_2x, 0, 1, None, np.random.default_rng(9))
    raw, t = _expose_nonideal(device, real, spec, weights, np.arange(n), n, truth_2x, 0, 1, None,
                              np.random.default_rng(9))
    single = weights.sum(axis=1) == 1
    # singles at 10 dB: the recorded time (shutter x gain) of a bracket within 1 % of the 0 dB one
    np.testing.assert_allclose(t[single], ideal_t[single], rtol=0.01)
    # multiplexed: one bracket for all patterns of the view, one of the patterns' own
    assert np.all(t[~single] == t[~single][:1]) and any(np.array_equal(t[~single][0], b) for b in ideal_t[~single])
    # hot pixels read the white level in every frame
    hot = hot_pixel_mask(0.002, np.random.default_rng([DEVICE_SEED, 1, 5]), device.roi_shape)
    assert hot.sum() >= 10 and np.all(raw[:, :, hot] == device.sensor.white_level)
    assert not np.all(ideal_raw[:, :, hot] == device.sensor.white_level)
    # the brighter multiplexed patterns saturate in the shortest frame of the shared bracket, more than before
    white = device.sensor.white_level
    assert (raw[~single, 0][:, ~hot] >= white).sum() > (ideal_raw[~single, 0][:, ~hot] >= white).sum()


def test_a_non_ideal_capture_goes_through_simulate_and_ingest(tmp_path, dask_client, tiny_btf, tiny_btf_nonideal):
    """The realistic dome's capture (conftest ``tiny_btf_nonideal``) ingests with an error above the ideal dome's
    and within a sensible bound; a multiplexed capture under it too."""
    from tasks.ingest import btf_error_against_truth, ingest_capture
    from tasks.simulate import SimulationConfig, simulate_database

    ideal = btf_error_against_truth(tiny_btf, next(tiny_btf.parent.glob("000-*.zarr")))
    real = btf_error_against_truth(tiny_btf_nonideal, next(tiny_btf_nonideal.parent.glob("000-*.zarr")))
    assert all(np.isfinite(v) for v in real.values())
    assert ideal["relative_l2_log_y"] < real["relative_l2_log_y"] < 0.3, (ideal, real)
    errors = {}
    for name in ("ideal", "realistic"):
        config = SimulationConfig(device="tiny", n_materials=1, seed=8, classes=("leather",), n_turntable=1,
                                  texture_size=8, illumination="multiplexed", non_ideal=PRESETS[name])
        capture = simulate_database(config, tmp_path / name, dask_client).stores[0]
        ingest_capture(capture, tmp_path / name / "btf.zarr", dask_client)
        errors[name] = btf_error_against_truth(tmp_path / name / "btf.zarr", capture)
    print("ingest errors, single-light ideal / realistic:", ideal, real, "multiplexed:", errors)
    assert errors["ideal"]["relative_l2_log_y"] < errors["realistic"]["relative_l2_log_y"] < 0.5, errors


def test_build_db_reconstruct_and_render_run_on_the_non_ideal_btf(tiny_btf_nonideal, tmp_path, dask_client):
    """The stages after ingest on the realistic dome's BTF: a model database (per-material fit and class merge),
    a reconstruction projecting the BTF on its class basis, a rendering."""
    import zarr

    from tasks.model import ModelSettings, discover, fit_material, merge_bases, open_model_store
    from tasks.reconstruct import ReconstructSettings, reconstruct_store
    from tasks.render import render_store

    [material] = discover(tiny_btf_nonideal.parent, min_per_class=1)
    model = tmp_path / "model.zarr"
    group = open_model_store(model, [material])
    settings = ModelSettings(k_material={"als": 8}, als_iterations=3)
    assert fit_material(str(model), material, settings, bases=("als",))["bases"]["als"] != "reused"
    merge_bases(group, [material], settings, bases=("als",))
    reconstruct_store(tiny_btf_nonideal, tmp_path, tmp_path / "rec.zarr",
                      ReconstructSettings(cls=material.cls, basis="als", method="pinv"), dask_client)
    B = np.asarray(zarr.open_group(str(tiny_btf_nonideal), mode="r")["btf"][...], dtype=np.float64)
    R = np.asarray(zarr.open_group(str(tmp_path / "rec.zarr"), mode="r")["btf"][...], dtype=np.float64)
    assert np.all(np.isfinite(R)) and np.linalg.norm(R - B) / np.linalg.norm(B) < 0.5
    rendering = render_store(tmp_path / "rec.zarr", out_png=tmp_path / "sphere.png", image_size=32)
    assert (tmp_path / "sphere.png").stat().st_size > 0 and np.all(np.isfinite(rendering.image))


def test_a_plan_executes_on_the_non_ideal_dome(tmp_path, dask_client):
    """``btf simulate --plan`` under the realistic dome: the plan's shutter brackets are recorded as planned,
    and the capture ingests to a measurement store."""
    from btfcore.acquisition.plan import ExposureModel, sparse_plan
    from btfcore.dome import get_device
    from tasks.ingest import ingest_capture
    from tasks.simulate import SimulationConfig, simulate_database
    from tasks.stores import open_capture_store

    plan = sparse_plan(get_device("tiny"), np.array([[0, 3], [2, 15]]),
                       ExposureModel(single_ms=(0.3, 7.25, 1000.0 / 3), min_shutter_ms=0.05), cameras=[1, 3])
    config = SimulationConfig(device="tiny", n_materials=1, seed=8, classes=("leather",), texture_size=8, plan=plan,
                              non_ideal=PRESETS["realistic"])
    path = simulate_database(config, tmp_path / "db", dask_client).stores[0]
    capture = open_capture_store(path)
    times = np.asarray(capture.exposure_time[...])
    taken = times[times > 0]
    assert taken.size and np.allclose(np.sort(np.unique(taken)), np.sort(np.unique(
        [t / 1000.0 for s in plan.shots for t in s.shutter_ms])))
    summary = ingest_capture(path, tmp_path / "meas.zarr", dask_client)
    assert summary is not None and (tmp_path / "meas.zarr").exists()


def test_superres_and_bonn_export_run_on_the_non_ideal_capture(tiny_btf_nonideal, tmp_path, dask_client):
    """The stages that read regions and write files, on the realistic dome's capture: ingest keeping the regions,
    a few epochs of ESPCN training and its application at 2x (finite, 2x texture, near bicubic's result), and a
    Bonn DFMF export that imports back within half-float precision."""
    import zarr

    from btfcore.superres.espcn import EspcnConfig
    from btfcore.superres.training import TrainingSettings
    from tasks.bonn.export_btf import export_store
    from tasks.bonn.import_btf import import_btf
    from tasks.ingest import ingest_capture
    from tasks.superres import superres_apply, train_model

    capture = next(tiny_btf_nonideal.parent.glob("000-*.zarr"))
    btf = tmp_path / "roi.zarr"
    ingest_capture(capture, btf, dask_client, keep_roi=True)
    model = tmp_path / "model.pt"
    trained = train_model([btf], model, protocol="exact", fraction=0.2, config=EspcnConfig(features=(8, 4, 4)),
                          settings=TrainingSettings(max_epochs=2, batch_size=16, seed=1))
    assert trained["patches"] > 0 and np.isfinite(trained["best_validation_loss"])
    up = {}
    for method, weights in (("espcn", model), ("bicubic", None)):
        summary = superres_apply(btf, weights, tmp_path / f"{method}.zarr", dask_client, method=method)
        assert summary["texture_shape"] == [16, 16], summary
        up[method] = np.asarray(zarr.open_group(str(tmp_path / f"{method}.zarr"), mode="r")["btf"][...], np.float64)
        assert np.all(np.isfinite(up[method])), method
    # two epochs of a tiny net: not better than bicubic, but a sensible image (within 50 % of bicubic's)
    assert np.linalg.norm(up["espcn"] - up["bicubic"]) / np.linalg.norm(up["bicubic"]) < 0.5
    export_store(tiny_btf_nonideal, tmp_path / "a.btf", format="dfmf", precision="single")
    import_btf(tmp_path / "a.btf", tmp_path / "imported.zarr", dask_client)
    B = zarr.open_group(str(tiny_btf_nonideal), mode="r")["btf"][...]
    back = zarr.open_group(str(tmp_path / "imported.zarr"), mode="r")["btf"][...]
    np.testing.assert_allclose(back, B, rtol=1e-5, atol=1e-6 * float(np.abs(B).max()))
