"""Capture store -> BTF store on a real LocalCluster: chunked equals in-memory, resumes, errors."""

from __future__ import annotations

import numpy as np
import pytest
import zarr

from btfcore.capture.view_chain import IngestSettings, process_view
from tasks.ingest import btf_error_against_truth, ingest_capture
from tasks.simulate import SimulationConfig, simulate_database
from tasks.stores import open_capture_store


@pytest.fixture(scope="module")
def capture(tmp_path_factory, dask_client):
    out = tmp_path_factory.mktemp("ingest-capture")
    # leather draws only on scikit-image's photographs, so the capture is the same with or
    # without ../shared/data (stone and wood use the shared colour photographs when present)
    config = SimulationConfig(device="tiny", n_materials=1, seed=8, classes=("leather",), n_turntable=1,
                              illumination="both")
    return simulate_database(config, out, dask_client).stores[0]


def _in_memory(capture_path, t, c, illum=slice(None)):
    store = open_capture_store(capture_path)
    meta = store.meta
    return process_view(store.raw[t, c][illum], store.exposure_time[t, c][illum], store.illumination[illum],
                        bayer_pattern=meta.bayer_pattern, black_level=meta.black_level,
                        white_level=meta.white_level, homography=store.homography[t, c],
                        texture_shape=tuple(meta.texture_shape), sample_size_m=meta.sample_size_m,
                        dark_frames=store.dark_frames[c], dark_exposure_time=meta.dark_exposure_time,
                        gain_e_per_dn=meta.sensor["gain_e_per_dn"], read_noise_e=meta.sensor["read_noise_e"])[0]


def test_chunked_ingest_equals_in_memory_and_resumes(capture, tmp_path, dask_client):
    out = tmp_path / "btf.zarr"
    result = ingest_capture(capture, out, dask_client)
    assert result["views_processed"] == 4
    group = zarr.open_group(str(out), mode="r")
    assert group.attrs["complete"] and group["btf"].shape == (4 * 16, 32, 32, 3)
    btf = group["btf"][...]
    for c in range(4):
        # equal up to float32 rounding: the demultiplexing GEMM sums in an order that depends on
        # the BLAS thread count, which is 1 on the workers and the machine's cores here
        # (demultiplexing cancels large terms, so the tolerance is relative to the largest value)
        expected = _in_memory(capture, 0, c)
        np.testing.assert_allclose(btf[c * 16:(c + 1) * 16], expected, rtol=0, atol=1e-6 * np.abs(expected).max())
    # forget two views as a killed run would, resume: only those are recomputed, bit-identically
    rw = zarr.open_group(str(out), mode="r+")
    rw["written"][0, 1:3] = 0
    rw.attrs["complete"] = False
    again = ingest_capture(capture, out, dask_client)
    assert again["views_processed"] == 2
    np.testing.assert_array_equal(zarr.open_group(str(out), mode="r")["btf"][...], btf)
    # other settings do not overwrite a finished output
    with pytest.raises(FileExistsError, match="another capture or settings"):
        ingest_capture(capture, out, dask_client, settings=IngestSettings(demosaic="bilinear"))


def test_overwrite_is_staged_and_a_commit_killed_between_its_renames_is_finished(capture, tmp_path, dask_client):
    """overwrite builds ``btf.partial.zarr`` beside ``btf.zarr`` and renames it over the old output only
    when complete; a commit killed after moving the old output aside is finished by the next ingest."""
    from tasks.radiometric import Calibration

    out = tmp_path / "btf.zarr"
    ingest_capture(capture, out, dask_client)
    old = zarr.open_group(str(out), mode="r")["btf"][...]
    half = Calibration(colour_matrix=0.5 * np.eye(3), info={"colour_matrix": "half.json"})
    staged = ingest_capture(capture, out, dask_client, overwrite=True, calibration=half, commit=False)
    assert staged["staged"] and staged["views_processed"] == 4
    np.testing.assert_array_equal(zarr.open_group(str(out), mode="r")["btf"][...], old)
    assert zarr.open_group(str(tmp_path / "btf.partial.zarr"), mode="r").attrs["complete"]

    out.rename(tmp_path / "btf.replaced.zarr")          # killed between commit_staged's two renames
    again = ingest_capture(capture, out, dask_client, calibration=half)
    assert not again["staged"] and again["views_processed"] == 0
    assert [p.name for p in tmp_path.iterdir()] == ["btf.zarr"]
    np.testing.assert_allclose(zarr.open_group(str(out), mode="r")["btf"][...], 0.5 * old, rtol=1e-6)

    back = ingest_capture(capture, out, dask_client, overwrite=True)     # staged and committed in one call
    assert back["staged"] and back["views_processed"] == 4
    assert [p.name for p in tmp_path.iterdir()] == ["btf.zarr"]
    np.testing.assert_array_equal(zarr.open_group(str(out), mode="r")["btf"][...], old)


def test_single_and_multiplexed_reach_the_truth(capture):
    store = open_capture_store(capture)
    truth = store.truth["btf"][...]
    device = SimulationConfig(device="tiny", n_turntable=1).build_device()
    sensor = device.sensor
    frontal = slice(0, 16)  # camera 0 looks straight down
    expected = truth[frontal] * device.led_rgb_gain[:, None, None, :] * np.array(sensor.sensitivity_rgb) \
        / sensor.gain_e_per_dn
    errors = {}
    for name, illum in (("single", slice(0, 16)), ("multiplexed", slice(16, None))):
        got = _in_memory(capture, 0, 0, illum)
        errors[name] = np.linalg.norm(got - expected) / np.linalg.norm(expected)
    # demosaicing and rectifying a 48-px view of a 32-texel texture costs a few per cent
    assert errors["single"] < 0.15 and errors["multiplexed"] < 0.15, errors
    assert abs(errors["multiplexed"] - errors["single"]) < 0.03, errors


def test_error_against_truth_is_reported(capture, tmp_path, dask_client):
    out = tmp_path / "btf.zarr"
    ingest_capture(capture, out, dask_client)
    errors = btf_error_against_truth(out, capture)
    assert 0 < errors["relative_l2_log_y"] < 0.3 and 0 < errors["relative_l2_linear"] < 0.5, errors


def test_white_standard_capture_calibrates_the_leds_and_the_ingest(capture, tmp_path, dask_client):
    """The simulator captures a white standard; its ingest yields each LED's gain, and `btf ingest
    --white` brings a material to the truth's unit (issue 3, item 4)."""
    from btfcore.capture.radiometric import led_calibration
    from tasks.radiometric import load_calibration

    config = SimulationConfig(device="tiny", n_materials=1, seed=2, classes=("white-standard",), n_turntable=1)
    white_capture = simulate_database(config, tmp_path / "white", dask_client).stores[0]
    out = tmp_path / "white-btf.zarr"
    ingest_capture(white_capture, out, dask_client)
    group = zarr.open_group(str(out), mode="r")
    n_leds = 16
    white = np.moveaxis(group["btf"][...].reshape(4, n_leds, 32, 32, 3), 1, 0)     # (leds, views, h, w, 3)
    light = group["light_dir"][...][:n_leds]
    mask = np.zeros((4, 32, 32), bool)
    mask[:3, 4:-4, 4:-4] = True          # leave out the grazing 75-degree camera and the borders
    gain = led_calibration(white, light, mask=mask)
    device = config.build_device()
    # what the chain should measure: LED gain x camera sensitivity / ADC gain (DN/s per unit radiance)
    expected = device.led_rgb_gain * np.array(device.sensor.sensitivity_rgb) / device.sensor.gain_e_per_dn
    np.testing.assert_allclose(gain, expected, rtol=0.02)

    # the out-of-core estimate (median over views of per-view medians, no mask) agrees
    calibration = load_calibration(out)
    np.testing.assert_allclose(calibration.led_gain, expected, rtol=0.03)
    assert calibration.info["white_standard"] == str(out) and calibration.info["views"] == 4
    plain, calibrated = tmp_path / "plain.zarr", tmp_path / "calibrated.zarr"
    ingest_capture(capture, plain, dask_client)
    ingest_capture(capture, calibrated, dask_client, calibration=calibration)
    cal = zarr.open_group(str(calibrated), mode="r")
    assert "white-standard calibrated" in cal.attrs["units"]
    np.testing.assert_array_equal(cal["led_gain"][...], calibration.led_gain)
    b_plain = zarr.open_group(str(plain), mode="r")["btf"][...].reshape(4, 16, -1, 3)
    np.testing.assert_allclose(cal["btf"][...].reshape(4, 16, -1, 3), b_plain / calibration.led_gain[None, :, None],
                               rtol=1e-5, atol=1e-6 * np.abs(b_plain).max())
    # no fitted scale: the calibrated BTF is within a few per cent of the chain's own error
    errors = btf_error_against_truth(calibrated, capture)
    assert errors["calibrated_relative_l2_linear"] < errors["relative_l2_linear"] + 0.03, errors
    assert errors["calibrated_relative_l2_log_y"] < errors["relative_l2_log_y"] + 0.03, errors
    assert "calibrated_relative_l2_linear" not in btf_error_against_truth(plain, capture)
    # calibrating from a corrected store, or with another dome's LED count, is refused
    with pytest.raises(ValueError, match="already radiometrically corrected"):
        load_calibration(calibrated)
    wrong = type(calibration)(led_gain=calibration.led_gain[:5], info=calibration.info)
    with pytest.raises(ValueError, match="5 LEDs"):
        ingest_capture(capture, tmp_path / "wrong.zarr", dask_client, calibration=wrong)


def test_evaluation_refuses_a_store_that_is_not_an_ingest(capture, tmp_path):
    resampled = zarr.open_group(str(tmp_path / "r.zarr"), mode="w", zarr_format=3)
    resampled.attrs.put({"schema": "btf-texture", "resampled_from": {"path": "x"}})
    with pytest.raises(ValueError, match="r.zarr: not the output of `btf ingest`.*resampled"):
        btf_error_against_truth(tmp_path / "r.zarr", capture)
