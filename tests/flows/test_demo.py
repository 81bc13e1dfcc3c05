"""`btf demo` (the README's first command) end to end, and `btf ingest --white` on the CLI."""

from __future__ import annotations

import json
import re

import pytest
import zarr
from test_kill_matrix import btf  # noqa: F401 - the forked `btf` runner, for the demo killed mid-run


def test_demo_simulates_calibrates_ingests_and_reports(run_btf, btf, tmp_path):
    out = tmp_path / "demo"
    # a real `btf demo` process SIGKILLed after its third simulated view (tests/flows/test_kill_matrix.py's
    # runner): the run below resumes it, keeping the views that were finished
    btf.killed("chunk-done:3", "demo", "--out", out, "--materials", "2")
    code, stdout, stderr = run_btf("demo", "--out", out, "--materials", "2", progress=True)
    assert code == 0, stderr[-3000:]
    assert json.loads(stdout)["materials"] == 2
    # stderr is not a terminal here (a job log): every stage says when it starts and ends, timestamped
    stamped = re.findall(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d (.+)$", stderr, re.M)
    assert stamped[0] == "btf demo: checking the inputs ...", stderr[:2000]
    for stage in ("simulate tiny: 2 materials", "simulate tiny: white standard", "ingest: 2 materials, calibrated",
                  "ingest floors: noise-free and full-RGB sensors"):
        assert f"{stage}: started" in stamped and any(s.startswith(f"{stage}: ") and s.endswith(", done")
                                                       for s in stamped), stderr[-3000:]
    report = json.loads((out / "report.json").read_text())
    # the white standard calibrated every LED, and both illuminations were ingested with it
    assert report["radiometric"]["views"] == 12 and report["radiometric"]["max_relative_spread_over_views"] < 0.05
    for key in ("ingest", "ingest_multiplexed"):
        assert len(report[key]) == 2
        for errors in report[key].values():
            # a calibration that failed (wrong unit, wrong LED) would be off by far more than 0.05
            assert abs(errors["calibrated_relative_l2_linear"] - errors["relative_l2_linear"]) < 0.05, errors
            assert 0 < errors["relative_l2_linear"] < 0.5, errors
    # every ingest error beside its floors: a noise-free capture, and a noise-free full-RGB sensor
    assert set(report["ingest_floors"]) == set(report["ingest"])
    for name, floors in report["ingest_floors"].items():
        for metric in ("relative_l2_linear", "relative_l2_log_y"):
            assert 0 < floors["full_rgb"][metric] <= floors["noise_free"][metric] <= report["ingest"][name][metric] + 1e-3
    shares = report["ingest_floor_shares"]["relative_l2_linear"]
    assert shares["noise"] + shares["mosaic"] + shares["sampling"] == pytest.approx(shares["error"])
    assert report["stages"]["ingest floors"]["reused"] == {"materials": [0, 2]}
    for material in report["materials"]:
        assert 1 <= material["usable_exposures_per_pixel_mean"] <= material["n_exposures"], material
    html = (out / "report.html").read_text()
    assert "calibrated log Y" in html and "multiplexed" in html
    assert "noise-free floor, linear [1]" in html and "full-RGB floor, log Y [1]" in html
    assert "Ingested BTF beside the ground truth" in html and (out / "report_files" / "000-leather_ingest_lv0.png").exists()
    # super-resolution on the demo's leather and cloth: every method scored, the crops in the demo's report
    superres = report["superres"]
    assert set(superres["means"]["exact"]) >= {"bicubic", "dong", "espcn"}
    assert all(0 < v["mre"] < 100 for v in superres["means"]["paper"].values())
    assert "Super-resolution (btf evaluate superres" in html and (out / "superres" / "report.html").is_file()
    assert all((out / f["file"]).is_file() for f in superres["figures"]) and len(superres["figures"]) == 10
    btf = zarr.open_group(str(out / "btf-multiplexed" / "000-leather.zarr"), mode="r")
    assert btf.attrs["complete"] and "white-standard calibrated" in btf.attrs["units"]
    # a second run reuses every finished store
    stderr_first = stderr
    code, _, stderr = run_btf("demo", "--out", out, "--materials", "2")
    assert code == 0, stderr[-3000:]
    again = json.loads((out / "report.json").read_text())
    assert again["stages"]["simulate"]["views_rendered"] == 0
    assert again["stages"]["ingest floors"]["reused"] == {"materials": [2, 2]}
    assert again["stages"]["super-resolution"]["reused"] == {"materials": [2, 2]}   # scores and networks
    assert again["ingest_floors"] == report["ingest_floors"]
    assert all(r["views_processed"] == 0 for r in again["ingest"].values())
    # and says so, per stage, in its report (and, with progress, in one line per stage)
    for stage in ("simulate", "ingest", "simulate multiplexed", "ingest multiplexed"):
        reused, total = again["stages"][stage]["reused"]["views"]
        assert reused == total > 0, (stage, again["stages"][stage])
        # the killed run finished at least 3 simulated views (those its workers had in hand may follow)
        first = report["stages"][stage]["reused"]["views"][0]
        assert 3 <= first < total if stage == "simulate" else first == 0, (stage, report["stages"][stage])
    assert re.search(r"simulate: reused [1-9]\d* of ", stderr_first) and "ingest: reused 0 of " in stderr_first


def test_ingest_white_standard_errors_name_the_store(run_btf, tiny_database, tmp_path):
    capture = sorted(tiny_database[1].glob("*.zarr"))[0]
    code, _, stderr = run_btf("ingest", capture, "--out", tmp_path / "b.zarr", "--white", tmp_path / "none.zarr")
    assert code == 2
    assert "none.zarr" in stderr and "ingest the white-standard capture first" in stderr
    assert not (tmp_path / "b.zarr").exists()
    matrix = tmp_path / "m.json"
    matrix.write_text('{"matrix": [[1, 0, 0], [0, NaN, 0], [0, 0, 1]]}')
    code, _, stderr = run_btf("ingest", capture, "--out", tmp_path / "b.zarr", "--colour-matrix", matrix)
    assert code == 2 and "m.json" in stderr and "matrix[1, 1]" in stderr, stderr
