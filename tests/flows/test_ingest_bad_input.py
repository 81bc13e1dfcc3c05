"""Issue 3's bad-input list where the user meets it: `btf import-raw` and `btf ingest`.

Each bad input must exit 1 with a message that names the file, the array and
the index and says what to do, and a finished output at ``--out`` must survive
the failed run bit for bit, even with ``--overwrite`` (which builds the new
store beside it and replaces it only once complete and checked). An S-matrix order that does not
exist reaches the user only as illumination patterns that cannot be
demultiplexed (no command takes an order). The numerical layer's own checks are
in tests/btfcore (test_hdr, test_rectify, test_hadamard, test_demultiplex,
test_radiometric, test_devices); the store's in tests/tasks/test_store.py and
the raw import's in tests/tasks/test_ingest_raw.py.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr

from btfcore.dome import get_device
from tasks.simulate import SimulationConfig, simulate_database


def _report(btf: Path) -> Path:
    return btf.with_name(btf.stem + ".report.json")


def _digest(*paths: Path) -> str:
    """Hash of the names and bytes of every file under ``paths`` (folders or files)."""
    h = hashlib.sha256()
    for root in paths:
        for f in [root] if root.is_file() else sorted(p for p in root.rglob("*") if p.is_file()):
            h.update(str(f.relative_to(root.parent)).encode())
            h.update(f.read_bytes())
    return h.hexdigest()


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


# --------------------------------------------------------------------------- btf ingest


@pytest.fixture(scope="module")
def capture(tmp_path_factory, dask_client) -> Path:
    """A tiny capture: one turntable position, 4 views x 16 single-LED brackets of 3 exposures."""
    config = SimulationConfig(device="tiny", n_materials=1, seed=3, classes=("leather",), n_turntable=1)
    return Path(simulate_database(config, tmp_path_factory.mktemp("bad-input"), dask_client).stores[0])


@pytest.fixture(scope="module")
def finished(capture, dask_client) -> Path:
    """A finished `btf ingest` of the capture: BTF store and report."""
    from flows.ingest import ingest_flow

    out = capture.parent / "finished.zarr"
    ingest_flow(str(capture), str(out), dask_client.scheduler.address, progress=False)
    return out


@pytest.fixture()
def finished_copy(finished, tmp_path) -> tuple[Path, str]:
    """A copy of the finished output (store and report) and its digest."""
    out = _copy(finished, tmp_path / "finished.zarr")
    shutil.copy(_report(finished), _report(out))
    return out, _digest(out, _report(out))


def _corrupted(capture: Path, tmp_path: Path, corrupt) -> Path:
    bad = _copy(capture, tmp_path / "capture.zarr")
    corrupt(zarr.open_group(str(bad), mode="r+", zarr_format=3), bad)
    return bad


def _set(array, index, value):
    def corrupt(group, _path):
        group[array][index] = value
    return corrupt


def _reversed_times(group, _path):
    group["exposure_time"][0, 3, 9] = group["exposure_time"][0, 3, 9][::-1].copy()


def _homography_off_frame(group, _path):
    H = group["homography"][...]
    H[0, 2] = np.array([[1, 0, 30], [0, 1, 0], [0, 0, 1.0]]) @ H[0, 2]         # 30 px to the right
    group["homography"][...] = H


def _nan_sensor_gain(group, _path):
    group.attrs["sensor"] = {**group.attrs["sensor"], "gain_e_per_dn": float("nan")}


def _white(group, _path):
    group["raw"][0, 1, 3] = group.attrs["white_level"]


def _black(group, _path):
    group["raw"][0, 1, 3] = group.attrs["black_level"]


def _duplicate_pattern(group, _path):
    group["illumination"][5] = group["illumination"][4]            # LEDs 4 and 5 always lit together


def _truncated_chunk(_group, path):
    chunk = path / "raw" / "c" / "0" / "0" / "15" / "0" / "0" / "0"
    chunk.write_bytes(chunk.read_bytes()[:100])


#: Bad captures that opening the store refuses, each at its own index: (corruption, what the message names)
REFUSED_AT_OPEN = {
    "missing exposure time": (_set("exposure_time", (0, 2, 5, 1), 0.0),
                              ["exposure_time[(t, c, i)=(0, 2, 5)]", "all exposure times > 0 s", "re-write it"]),
    "missing bracket": (_set("written", (0, 1, 7), 0),
                        ["written[(t, c, i)=(0, 1, 7)]", "1 of 64 bracket(s) not written", "to resume"]),
    "non-monotonic exposure times": (_reversed_times,
                                     ["exposure_time[(t, c, i)=(0, 3, 9)]", "strictly increasing", "re-write it"]),
    "homography outside the frame": (_homography_off_frame,
                                     ["homography[(t, c)=(0, 2)]", "inside the 72x72 raw frame", "Fix: check"]),
    "NaN in the homography": (_set("homography", (0, 1, 0, 0), np.nan),
                              ["homography[(t, c, i, j)=(0, 1, 0, 0)]", "NaN/Inf", "device calibration"]),
    "Inf in exposure times": (_set("exposure_time", (0, 3, 2, 0), np.inf),
                              ["exposure_time[(t, c, i)=(0, 3, 2)]", "finite exposure times", "re-write it"]),
    "Inf in LED positions": (_set("led_position", (3, 0), np.inf),
                             ["led_position[(led, xyz)=(3, 0)]", "NaN/Inf", "device calibration"]),
    "NaN sensor gain": (_nan_sensor_gain, ["attrs[sensor.gain_e_per_dn]", "finite float or null", "calibrated value"]),
}


def test_ingest_names_every_problem_of_a_bad_capture_and_keeps_the_finished_output(capture, finished_copy,
                                                                                   tmp_path, run_btf):
    """All corruptions in one store: one run must name each (the store is checked before any work)."""
    def corrupt_all(group, path):
        for corrupt, _ in REFUSED_AT_OPEN.values():
            corrupt(group, path)

    bad = _corrupted(capture, tmp_path, corrupt_all)
    out, before = finished_copy
    code, _, err = run_btf("ingest", bad, "--out", out, "--overwrite")
    assert code == 2, err
    assert f"capture store '{bad}' (btf-capture 1.0) has {len(REFUSED_AT_OPEN)} problems" in err, err
    for case, (_, needles) in REFUSED_AT_OPEN.items():
        for needle in (f"{bad}: {needles[0]}", *needles[1:]):
            assert needle in err, f"{case}: {needle!r} not in {err!r}"
    assert _digest(out, _report(out)) == before


def test_a_good_ingest_reports_its_valid_fraction(finished):
    validity = json.loads(_report(finished).read_text())["valid_fraction"]
    assert validity["problem"] is None and validity["brackets_without_usable_pixel"] == 0
    assert 0.9 < validity["min"] <= validity["mean"] <= 1.0, validity


@pytest.mark.parametrize("corrupt, found", [(_white, "100% saturated"), (_black, "0% saturated")],
                         ids=["all saturated", "all black"])
def test_a_bracket_without_a_usable_pixel_is_an_error(corrupt, found, capture, tmp_path, run_btf):
    bad = _corrupted(capture, tmp_path, corrupt)
    out = tmp_path / "btf.zarr"
    code, _, err = run_btf("ingest", bad, "--out", out)
    assert code == 2, err
    assert f"{bad}: raw[(t, c, i)=(0, 1, 3) [shortest exposure {found}]]: 1 of 64 bracket(s)" in err, err
    assert "Capture those brackets again with shorter exposures where saturated" in err
    validity = json.loads(_report(out).read_text())["valid_fraction"]
    assert validity["brackets_without_usable_pixel"] == 1 and validity["min"] == 0.0
    assert validity["listed"][0]["t_c_i"] == [0, 1, 3]


@pytest.mark.parametrize("corrupt, named", [
    pytest.param(_white, "raw[(t, c, i)=(0, 1, 3)", id="all-saturated bracket"),
    pytest.param(_duplicate_pattern, "illumination (16 patterns x 16 LEDs)", id="inseparable patterns"),
    pytest.param(_truncated_chunk, "array raw, chunk (0, 0, ", id="truncated raw chunk"),
])
def test_a_failed_overwrite_names_the_input_and_keeps_the_finished_output(corrupt, named, capture, finished_copy,
                                                                          tmp_path, run_btf):
    bad = _corrupted(capture, tmp_path, corrupt)
    out, before = finished_copy
    code, _, err = run_btf("ingest", bad, "--out", out, "--overwrite")
    assert code == 2, err
    assert f"{bad}: {named}" in err, err
    assert _digest(out, _report(out)) == before


@pytest.mark.parametrize("rerun", [["--overwrite"], []], ids=["rerun with --overwrite", "rerun without"])
def test_a_failed_staged_overwrite_keeps_the_output_and_the_rerun_resumes_and_replaces_it(
        rerun, capture, finished, finished_copy, tmp_path, run_btf):
    """--overwrite with another ingest (here a colour matrix) builds ``finished.partial.zarr``: a run that dies
    part-way leaves the finished store and report bit for bit; the rerun resumes the staged store and only
    then puts it, and its report, in place."""
    out, before = finished_copy
    matrix = tmp_path / "half.json"
    matrix.write_text(json.dumps({"matrix": (0.5 * np.eye(3)).tolist()}))
    bad = _corrupted(capture, tmp_path, _truncated_chunk)
    code, _, err = run_btf("ingest", bad, "--out", out, "--overwrite", "--colour-matrix", matrix)
    assert code == 2 and f"{bad}: array raw, chunk (0, 0, " in err and ": truncated (" in err, err
    assert _digest(out, _report(out)) == before
    staging = tmp_path / "finished.partial.zarr"
    staged = zarr.open_group(str(staging), mode="r")
    assert not staged.attrs["complete"] and staged["written"][0, 0] == 0
    done = int(staged["written"][...].sum())

    chunk = Path("raw", "c", "0", "0", "15", "0", "0", "0")
    shutil.copy(capture / chunk, bad / chunk)                       # the capture is written again
    code, printed, err = run_btf("ingest", bad, "--out", out, "--colour-matrix", matrix, *rerun)
    assert code == 0, err
    stage = json.loads(printed)["stages"]["ingest"]
    assert stage["staged"] and (stage["views_skipped"], stage["views_processed"]) == (done, 4 - done), stage
    assert sorted(p.name for p in tmp_path.iterdir() if "finished" in p.name) == \
        ["finished.report.json", "finished.zarr"]                    # staging and the replaced store are gone
    new, old = zarr.open_group(str(out), mode="r"), zarr.open_group(str(finished), mode="r")
    assert new.attrs["complete"] and new.attrs["radiometric"]["colour_matrix"] == str(matrix)
    np.testing.assert_allclose(new["btf"][...], 0.5 * old["btf"][...], rtol=1e-6)
    assert json.loads(_report(out).read_text())["radiometric"]["colour_matrix"] == str(matrix)


@pytest.mark.parametrize("error, runs", [(ValueError, 1), (FileExistsError, 1), (RuntimeError, 2)])
def test_a_stage_retries_only_unexpected_errors(error, runs, runtime_session, monkeypatch):
    """The ingest-side stages' one retry (``RETRY_ONCE``) is for a lost worker, not for bad input."""
    from prefect import flow, task

    from flows.runtime import RETRY_ONCE

    monkeypatch.setenv("PREFECT_API_URL", runtime_session[1])
    calls = []

    @task(name="failing-stage", **RETRY_ONCE)
    def stage():
        calls.append(1)
        raise error("failed")

    @flow(name="retry-check")
    def run():
        stage()

    with pytest.raises(error, match="failed"):
        run()
    assert len(calls) == runs


# --------------------------------------------------------------------------- btf import-raw

_SHAPE = (72, 80)
_TIMES = (0.01, 0.08)


@pytest.fixture(scope="module")
def raw_folder(tmp_path_factory, write_dng, dask_client) -> tuple[Path, Path]:
    """Four DNGs (2 LEDs x 2 exposures) with a manifest, and their finished capture store."""
    from tasks.ingest_raw import import_raw, plan_raw_import

    folder = tmp_path_factory.mktemp("raw")
    rng = np.random.default_rng(2)
    lines = ["file,turntable,camera,illumination,exposure"]
    for i in range(2):
        for e, t in enumerate(_TIMES):
            write_dng(folder / f"l{i}_e{e}.dng", rng.integers(64, 4000, _SHAPE, dtype=np.uint16), "RGGB", t)
            lines.append(f"l{i}_e{e}.dng,0,0,{i},{e}")
    (folder / "manifest.csv").write_text("\n".join(lines) + "\n")
    store = folder.parent / "imported.zarr"
    import_raw(plan_raw_import(folder, folder / "manifest.csv"), get_device("tiny"), store, dask_client)
    return folder, store


def _truncate(folder, _write_dng):
    data = (folder / "l1_e0.dng").read_bytes()
    (folder / "l1_e0.dng").write_bytes(data[: len(data) // 3])
    return ["--device", "tiny"]


def _no_exposure_time(folder, write_dng):
    write_dng(folder / "l1_e1.dng", np.full(_SHAPE, 500, np.uint16), "RGGB", 0.0)   # ExposureTime 0/1
    return ["--device", "tiny"]


def _drop_member(folder, _write_dng):
    manifest = folder / "manifest.csv"
    manifest.write_text("".join(line for line in manifest.read_text().splitlines(True)
                                if not line.startswith("l1_e1")))
    return ["--device", "tiny"]


def _equal_times(folder, _write_dng):
    # brackets may come in any order (sorted by time), but two frames of one bracket at one time cannot be
    manifest = folder / "manifest.csv"
    lines = manifest.read_text().splitlines()
    rows = [lines[0] + ",exposure_time"] + [row + (",0.08" if row.startswith("l0_e0") else ",") for row in lines[1:]]
    manifest.write_text("\n".join(rows) + "\n")
    return ["--device", "tiny"]


def _calibration(edit):
    def make(folder, _write_dng):
        device = get_device("tiny").to_json()
        edit(device)
        (folder / "cal.json").write_text(json.dumps(device))             # NaN and Infinity as Python writes them
        return ["--calibration", folder / "cal.json"]
    return make


def _nan_gain(device):
    device["led_rgb_gain"][1][2] = float("nan")


def _inf_intrinsics(device):
    device["camera_K"][0][0][2] = float("inf")


def _off_frame(device):
    device["camera_K"][0][0][2] += 60.0                                  # principal point 60 px to the right


#: Bad raw imports: (how the folder is spoiled, what the message must name)
REFUSED_IMPORTS = {
    "corrupt file": (_truncate, ["manifest.csv:4 (l1_e0.dng): LibRaw cannot read it", "re-copy it"]),
    "missing exposure time": (_no_exposure_time, ["manifest.csv:5 (l1_e1.dng): no exposure_time in the manifest "
                                                  "and none in the file's metadata", "add the exposure_time column"]),
    "missing bracket member": (_drop_member, ["(turntable, camera, illumination, exposure) = (0, 0, 1, 1) is "
                                              "missing", "add its file"]),
    "equal exposure times": (_equal_times, ["bracket (turntable, camera, illumination) = (0, 0, 0) has 2 frames at "
                                            "the same exposure time 0.08 s", "needs its own time"]),
    "NaN in the LED calibration": (_calibration(_nan_gain), ["cal.json: not a valid dome calibration",
                                                             "led_rgb_gain contains NaN or Inf at [1, 2]"]),
    "Inf in the camera calibration": (_calibration(_inf_intrinsics), ["cal.json: not a valid dome calibration",
                                                                      "camera_K contains NaN or Inf at [0, 0, 2]"]),
    "homography outside the frame": (_calibration(_off_frame), ["homography[(t, c)=(0, 0)]",
                                                                "inside the 72x80 raw frame", "Fix: check"]),
}


@pytest.mark.parametrize("case", list(REFUSED_IMPORTS))
def test_import_raw_names_bad_files_and_keeps_the_finished_store(case, raw_folder, tmp_path, write_dng, run_btf):
    spoil, needles = REFUSED_IMPORTS[case]
    folder = _copy(raw_folder[0], tmp_path / "raw")
    extra = spoil(folder, write_dng)
    store = _copy(raw_folder[1], tmp_path / "imported.zarr")
    before = _digest(store)
    code, _, err = run_btf("import-raw", folder, "--manifest", folder / "manifest.csv", *extra,
                           "--out", store, "--overwrite")
    assert code == 2, err
    for needle in needles:
        assert needle in err, f"{needle!r} not in {err!r}"
    assert _digest(store) == before


def test_all_saturated_raw_files_are_named_by_ingest(raw_folder, tmp_path, write_dng, run_btf):
    folder = _copy(raw_folder[0], tmp_path / "raw")
    for e, t in enumerate(_TIMES):
        write_dng(folder / f"l1_e{e}.dng", np.full(_SHAPE, 4095, np.uint16), "RGGB", t)   # LED 1 clipped throughout
    store = tmp_path / "clipped.zarr"
    code, _, err = run_btf("import-raw", folder, "--manifest", folder / "manifest.csv", "--device", "tiny",
                           "--out", store)
    assert code == 0, err                                   # the store holds what the camera recorded
    code, _, err = run_btf("ingest", store, "--out", tmp_path / "btf.zarr")
    assert code == 2
    assert f"{store}: raw[(t, c, i)=(0, 0, 1) [shortest exposure 100% saturated]]: 1 of 2 bracket(s)" in err, err
