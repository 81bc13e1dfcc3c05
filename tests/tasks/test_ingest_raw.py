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


def _rewrite(manifest, header, rows):
    manifest.write_text("\n".join([header, *rows]) + "\n")


def test_shuffled_brackets_give_the_same_store(dng_capture, tmp_path, dask_client):
    """Exposure indices and row order scrambled: each bracket is sorted by its times and the store is
    bit-identical to the one of the ordered manifest."""
    folder, manifest, frames, times = dng_capture
    header, *body = manifest.read_text().splitlines()
    rng = np.random.default_rng(11)
    shuffled = []
    for row in body:
        name, t, c, i, e = row.split(",")
        shuffled.append([name, t, c, i, int(e)])
    for c in range(2):
        for i in range(2):
            members = [r for r in shuffled if r[2] == str(c) and r[3] == str(i)]
            for r, e in zip(members, rng.permutation(3)):
                r[4] = int(e)
    assert any(r[4] != int(b.split(",")[4]) for r, b in zip(shuffled, body))   # really scrambled
    rng.shuffle(shuffled)
    scrambled = tmp_path / "scrambled.csv"
    _rewrite(scrambled, header, [",".join(map(str, r)) for r in shuffled])
    ordered_plan, scrambled_plan = plan_raw_import(folder, manifest), plan_raw_import(folder, scrambled)
    assert scrambled_plan.files == ordered_plan.files
    np.testing.assert_array_equal(scrambled_plan.exposure_time, ordered_plan.exposure_time)
    assert (np.diff(scrambled_plan.exposure_time, axis=-1) > 0).all()
    device = get_device("tiny")
    a = import_raw(ordered_plan, device, tmp_path / "ordered.zarr", dask_client)
    b = import_raw(scrambled_plan, device, tmp_path / "scrambled.zarr", dask_client)
    assert a.meta.provenance["config_hash"] == b.meta.provenance["config_hash"]
    for c in range(2):
        for i in range(2):
            fa, ta = a.read_bracket(0, c, i)
            fb, tb = b.read_bracket(0, c, i)
            assert fa.tobytes() == fb.tobytes() and ta.tobytes() == tb.tobytes()
            for e in range(3):
                np.testing.assert_array_equal(fb[e], frames[(0, c, i, e)])


def test_shutter_times_as_photographers_write_them(dng_capture):
    folder, manifest, _, _ = dng_capture
    header, *body = manifest.read_text().splitlines()
    written = {"c0_l0_e0": "1/100", "c0_l0_e1": "1/25", "c0_l0_e2": '2"', "c0_l1_e0": "0.5s",
               "c0_l1_e1": "1/1", "c0_l1_e2": "8 s"}
    rows = [r + "," + (written.get(r.split(".")[0], "")) for r in body]
    _rewrite(manifest, header + ",exposure_time", rows)
    plan = plan_raw_import(folder, manifest)
    np.testing.assert_allclose(plan.exposure_time[0, 0, 0], [0.01, 0.04, 2.0])
    np.testing.assert_allclose(plan.exposure_time[0, 0, 1], [0.5, 1.0, 8.0])
    json_manifest = folder / "m.json"
    json_manifest.write_text('[{"file": "c0_l0_e0.dng", "turntable": 0, "camera": 0, "illumination": 0, '
                             '"exposure": 0, "exposure_time": "1/8000"}]')
    assert plan_raw_import(folder, json_manifest).exposure_time[0, 0, 0, 0] == pytest.approx(1 / 8000)


@pytest.mark.parametrize("value, reason", [("1/0", "division by zero"), ("-1/50", "a shutter time must be positive, got -0.02 s"),
                                           ("fast", "not a shutter time"), ("nan", "not a finite number")])
def test_bad_shutter_times_name_the_row_and_column(dng_capture, value, reason):
    folder, manifest, _, _ = dng_capture
    header, *body = manifest.read_text().splitlines()
    _rewrite(manifest, header + ",exposure_time", [r + ("," + value if i == 3 else ",") for i, r in enumerate(body)])
    with pytest.raises(RawImportError) as info:
        plan_raw_import(folder, manifest)
    assert f"{manifest}:5: column 'exposure_time' = '{value}': {reason}" in str(info.value)
    assert 'write seconds as 1/50, 1/8000, 0.5, 2" or 2s' in str(info.value)


def test_every_problem_at_once_even_those_behind_others(dng_capture):
    """Four independent problems in one manifest: all four are in the one message (the missing
    member used to hide the time check; a bad role or time used to hide the row's other faults)."""
    folder, manifest, _, _ = dng_capture
    header, *body = manifest.read_text().splitlines()
    rows = []
    for r in body:
        name = r.split(".")[0]
        if name == "c0_l0_e2":
            continue                                         # 1: a missing bracket member
        time = {"c1_l1_e0": "1/10", "c1_l1_e1": "0.1", "c1_l0_e1": "1/0"}.get(name, "")
        rows.append(f"{r},{time},frame")                     # 2: two frames of (0,1,1) at 0.1 s; 3: 1/0
    rows.append("c0_l0_e0.dng,-1,0,0,0,,flat")               # 4: bad role and a bad index on one row
    _rewrite(manifest, header + ",exposure_time,role", rows)
    with pytest.raises(RawImportError) as info:
        plan_raw_import(folder, manifest)
    text = str(info.value)
    assert "(turntable, camera, illumination, exposure) = (0, 0, 0, 2) is missing" in text
    assert "bracket (turntable, camera, illumination) = (0, 1, 1) has 2 frames at the same exposure time 0.1 s" in text
    assert "column 'exposure_time' = '1/0': division by zero" in text
    assert "column 'role' = 'flat' is neither 'frame' nor 'dark'" in text
    assert "column 'turntable' = '-1' is not a non-negative integer" in text
    assert len(info.value.problems) == 5, text


def _write_linearised_dng(path, cfa, table, white=None):
    """A CFA DNG with a LinearizationTable (tag 50712) and optionally a WhiteLevel."""
    import tifffile

    tags = [(33421, "H", 2, (2, 2), False), (33422, "B", 4, bytes((0, 1, 1, 2)), False),
            (33434, "2I", 1, (10_000, 1_000_000), False), (50706, "B", 4, (1, 4, 0, 0), False),
            (50708, "s", 0, "btf-pipeline test camera", False),
            (50712, "H", len(table), tuple(int(v) for v in table), False), (50714, "I", 1, (0,), False),
            (50721, "2i", 9, (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1), False),
            (50778, "H", 1, (21,), False)]
    if white is not None:
        tags.append((50717, "I", 1, (white,), False))
    tifffile.imwrite(path, cfa, photometric=32803, extratags=sorted(tags), subfiletype=0)


@pytest.mark.parametrize("white", [65535, None])
def test_white_level_from_the_linearisation_table(tmp_path, dask_client, white):
    """As in a real DNG: 12-bit values, a table ending at 65472, WhiteLevel 65535 (or absent, which
    DNG reads as 65535). LibRaw's raw is linearised, so it saturates at 65472."""
    table = np.round(np.arange(4096) * 65472 / 4095).astype(np.uint16)
    cfa = (np.arange(72 * 80, dtype=np.uint16).reshape(72, 80) * 7) % 4096
    cfa[0, :4] = 4095                                           # saturated pixels
    _write_linearised_dng(tmp_path / "lin.dng", cfa, table, white)
    info = probe_raw_file(tmp_path / "lin.dng")
    assert (info.white_level, info.white_level_source) == (65472, "linearisation table maximum")
    (tmp_path / "m.csv").write_text("file,turntable,camera,illumination,exposure\nlin.dng,0,0,0,0\n")
    store = import_raw(plan_raw_import(tmp_path, tmp_path / "m.csv"), get_device("tiny"), tmp_path / "s.zarr",
                       dask_client)
    meta = open_capture_store(tmp_path / "s.zarr").meta
    assert meta.white_level == 65472 and meta.provenance["white_level_source"] == "linearisation table maximum"
    frame = store.read_bracket(0, 0, 0)[0][0]
    assert frame.max() == 65472
    np.testing.assert_array_equal(frame, table[cfa])


def test_white_level_without_a_table_is_the_files(dng_capture):
    folder, manifest, _, _ = dng_capture
    plan = plan_raw_import(folder, manifest)
    assert (plan.white_level, plan.white_level_source) == (4095, "LibRaw white level (file metadata)")


@pytest.mark.parametrize("kind", ["png", "jpg", "tif"])
def test_an_image_given_to_the_raw_path_is_named(tmp_path, kind):
    import cv2

    image = np.random.default_rng(3).integers(0, 255, (32, 48, 3), dtype=np.uint8)
    if kind == "tif":
        import tifffile

        tifffile.imwrite(tmp_path / "img.tif", image)
    else:
        assert cv2.imwrite(str(tmp_path / f"img.{kind}"), image)
    (tmp_path / "m.csv").write_text(f"file,turntable,camera,illumination,exposure\nimg.{kind},0,0,0,0\n")
    with pytest.raises(RawImportError) as info:
        plan_raw_import(tmp_path, tmp_path / "m.csv")
    name = {"png": "PNG", "jpg": "JPEG", "tif": "TIFF"}[kind]
    text = str(info.value)
    assert f"(img.{kind}): a {name} image, not a camera raw file" in text
    assert "TIFF, PNG or JPEG images with `btf import-images`" in text
    assert "corrupt, truncated" not in text


@pytest.mark.shared_data
def test_real_png_and_jpeg_given_to_the_raw_path(tmp_path):
    """The real 16-bit Bayer PNG and a real JPEG of a bracket: named as images, not as corrupt raw."""
    png, jpg = shared_file("raw/bayer_small.png"), shared_file("hdr/frobisher/IMG_2600.jpg")
    for path, kind in ((png, "a PNG image"), (jpg, "a JPEG image")):
        manifest = tmp_path / f"{path.stem}.csv"
        manifest.write_text(f"file,turntable,camera,illumination,exposure\n{path.name},0,0,0,0\n")
        with pytest.raises(RawImportError, match=f"{path.name}\\): {kind}, not a camera raw file"):
            plan_raw_import(path.parent, manifest)


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
    # the white level is the file's (LibRaw's 16383; the Kodak decoding curve also ends there)
    assert (plan.white_level, plan.white_level_source) == (16383, "LibRaw white level (file metadata)")
    store = import_raw(plan, get_device("tiny"), tmp_path / "kodak.zarr", dask_client)
    assert store.meta.white_level == 16383 and store.meta.bit_depth == 14
    assert store.meta.provenance["white_level_source"] == "LibRaw white level (file metadata)"
    frames, _ = store.read_bracket(0, 0, 0)
    import rawpy

    with rawpy.imread(str(kdc)) as raw:
        np.testing.assert_array_equal(frames[0], raw.raw_image_visible)
    assert open_capture_store(tmp_path / "kodak.zarr").meta.bayer_pattern == "GRBG"
