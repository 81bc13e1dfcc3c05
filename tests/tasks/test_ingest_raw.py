"""Importing camera raw files through LibRaw (rawpy) into a capture store."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from btfcore.dome import get_device
from tasks.ingest_raw import RawImportError, import_raw, plan_raw_import, probe_raw_file
from tasks.shared_data import shared_file
from tasks.stores import open_capture_store

@pytest.fixture()
def dng_capture(tmp_path, write_dng):
    """2 cameras x 2 LEDs x 3 exposures of 72x80 DNGs, exposure times only in the files."""
    rng = np.random.default_rng(5)
    frames, times, rows = {}, {}, []
    for c in range(2):
        for i in range(2):
            for e in range(3):
                t = 0.01 * 4**e * (1 + c + 0.5 * i)
                cfa = rng.integers(64, 4000, (72, 80), dtype=np.uint16)
                name = f"c{c}_l{i}_e{e}.dng"
                write_dng(tmp_path / name, cfa, "GBRG", t)
                frames[(0, c, i, e)], times[(0, c, i, e)] = cfa, t
                rows.append({"file": name, "turntable": 0, "camera": c, "illumination": i, "exposure": e})
    manifest = tmp_path / "manifest.csv"
    with manifest.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return tmp_path, manifest, frames, times


def test_dng_round_trip_with_exposure_from_metadata(dng_capture, tmp_path, dask_client):
    folder, manifest, frames, times = dng_capture
    info = probe_raw_file(folder / "c0_l0_e0.dng")
    assert (info.bayer_pattern, info.black_level_per_channel, info.white_level) == ("GBRG", (64,) * 4, 4095)
    plan = plan_raw_import(folder, manifest)
    assert plan.shape == (1, 2, 2, 3) and plan.frame_shape == (72, 80)
    store = import_raw(plan, get_device("tiny"), tmp_path / "capture.zarr", dask_client)
    assert store.complete and store.meta.bayer_pattern == "GBRG"
    for key, cfa in frames.items():
        got, got_times = store.read_bracket(*key[:3])
        np.testing.assert_array_equal(got[key[3]], cfa)
        assert got_times[key[3]] == pytest.approx(times[key], rel=1e-6)
    # the calibration follows the capture: 2 cameras, 2 LEDs, 1 turntable position, frame-sized ROI
    assert (store.n_cam, store.n_leds, store.n_turn, store.roi_shape) == (2, 2, 1, (72, 80))


def test_every_problem_is_listed_before_any_work(dng_capture, tmp_path, write_dng):
    folder, manifest, _, _ = dng_capture
    # truncate one file, remove another, duplicate a row, add a file of another size
    data = (folder / "c0_l1_e1.dng").read_bytes()
    (folder / "c0_l1_e1.dng").write_bytes(data[: len(data) // 3])
    (folder / "c1_l0_e2.dng").unlink()
    write_dng(folder / "odd.dng", np.full((24, 32), 100, np.uint16), "GBRG", 0.5)
    lines = manifest.read_text().splitlines()
    lines.append(lines[1])                       # duplicate of the first row
    lines.append("odd.dng,0,1,1,2")              # replaces nothing: a duplicate key, another size
    manifest.write_text("\n".join(lines) + "\n")
    with pytest.raises(RawImportError) as info:
        plan_raw_import(folder, manifest)
    text = str(info.value)
    assert "c0_l1_e1.dng): LibRaw cannot read it" in text
    assert "c1_l0_e2.dng): file not found" in text
    assert "the same file is also listed on line 2" in text
    assert "odd.dng): shape is (24, 32), the other files have (72, 80)" in text
    assert "duplicate entry for (turntable, camera, illumination, exposure) = (0, 1, 1, 2)" in text
    assert len(info.value.problems) >= 5
    assert not (tmp_path / "capture.zarr").exists()


def test_missing_bracket_members_and_bad_times(dng_capture):
    folder, manifest, _, _ = dng_capture
    lines = manifest.read_text().splitlines()
    header, body = lines[0] + ",exposure_time", lines[1:]
    # drop one exposure, give decreasing times to one bracket
    kept = [row + (",0.5" if row.startswith("c1_l1_e0") else ",") for row in body if not row.startswith("c0_l0_e2")]
    manifest.write_text("\n".join([header, *kept]) + "\n")
    with pytest.raises(RawImportError) as info:
        plan_raw_import(folder, manifest)
    text = str(info.value)
    assert "(turntable, camera, illumination, exposure) = (0, 0, 0, 2) is missing" in text


def test_decreasing_exposure_times_are_named(dng_capture):
    folder, manifest, _, _ = dng_capture
    lines = manifest.read_text().splitlines()
    rows = [lines[0] + ",exposure_time"] + [r + (",9.0" if r.startswith("c1_l1_e0") else ",") for r in lines[1:]]
    manifest.write_text("\n".join(rows) + "\n")
    with pytest.raises(RawImportError, match=r"bracket \(turntable, camera, illumination\) = \(0, 1, 1\) are not increasing"):
        plan_raw_import(folder, manifest)


@pytest.mark.shared_data
def test_real_kodak_raw_file(tmp_path, dask_client):
    kdc = shared_file("raw/RAW_KODAK_DC50.KDC")
    info = probe_raw_file(kdc)
    # MANIFEST.md: GRBG Bayer, 768x512, black 0 / white 16383 per LibRaw
    assert (info.shape, info.bayer_pattern, info.white_level) == ((512, 768), "GRBG", 16383)
    assert info.black_level_per_channel == (0, 0, 0, 0)
    manifest = tmp_path / "m.json"
    manifest.write_text('[{"file": "RAW_KODAK_DC50.KDC", "turntable": 0, "camera": 0, "illumination": 0, "exposure": 0}]')
    plan = plan_raw_import(kdc.parent, manifest)
    assert plan.exposure_time[0, 0, 0, 0] == pytest.approx(info.exposure_time)
    store = import_raw(plan, get_device("tiny"), tmp_path / "kodak.zarr", dask_client)
    frames, _ = store.read_bracket(0, 0, 0)
    import rawpy

    with rawpy.imread(str(kdc)) as raw:
        np.testing.assert_array_equal(frames[0], raw.raw_image_visible)
    assert open_capture_store(tmp_path / "kodak.zarr").meta.bayer_pattern == "GRBG"
