"""End to end: `btf evaluate acquisition`'s flow on a tiny truth database (real Prefect, real LocalCluster)."""

from __future__ import annotations

import json
import re

import pytest


def test_flow_writes_every_strategy_and_claim(acquisition_evaluation):
    from btfcore.acquisition.strategies import FLOOR_COMPUTED, floor_kinds
    from tasks.evaluate_acquisition import strategy_names

    out, summary = acquisition_evaluation          # the tiny evaluation (tests/flows/conftest.py), run once
    report = json.loads((out / "report.json").read_text())
    assert report["scale"]["light_view_pairs"] == 3 * 4 * 16
    assert set(report["claims"]) == {"a", "b", "c", "d", "e", "f"}
    f = report["claims"]["f"]                       # issue 20: m = n/4 basis-aware patterns vs the full S-matrix
    err, ratio = f["numbers"]["rel_l2_log_y_percent"], f["numbers"]["time_ratio_to_full_s_matrix"]
    assert f["verdict"] == ("met" if err["patterns"] <= err["multiplexed"] and ratio <= 0.5 else "not met")
    assert report["times"]["evaluated_device_s"]["patterns"] > 0
    for claim in report["claims"].values():
        assert claim["numbers"]
    # the verdicts follow from the measured numbers written beside them
    means = report["claims"]["c"]["numbers"]["all"]
    in_order = means["thresholded"] < means["projection"] < means["demultiplexed"]
    assert report["claims"]["c"]["verdict"] == ("met" if in_order else "not met")
    b_met = all(nums["optimized"] < nums["pmap7"] for nums in report["claims"]["b"]["numbers"].values())
    assert report["claims"]["b"]["verdict"] == ("met" if b_met else "not met")
    for mid, record in report["materials"].items():
        assert list(record["scores"]) == strategy_names()
        for scores in record["scores"].values():
            assert set(scores) == {"rel_l2_log_y", "mrmse", "mpsnr", "mre"}
            assert 0 < scores["rel_l2_log_y"] < float("inf")
        # projecting the truth on the ABRDF basis is the lower bound of reconstructing from its samples
        err = {name: s["rel_l2_log_y"] for name, s in record["scores"].items()}
        assert err["abrdf-projection"] < min(err["abrdf-pmap7"], err["abrdf-optimized"]), mid
        # every strategy that reads a noisy measurement has its noise-free floor beside its scores
        assert list(record["floors"]) == [n for n, k in floor_kinds().items() if k == FLOOR_COMPUTED], mid
        for name, floor in record["floors"].items():
            assert set(floor) == set(record["scores"][name]) and 0 < floor["rel_l2_log_y"] < float("inf"), name
    # per strategy the mean floor (diverged floors left out), or what the floor is where it is known
    floors = report["floors"]
    assert list(floors) == strategy_names()
    assert floors["demultiplexed"]["kind"] == "exact" and floors["abrdf-projection"]["kind"] == "noise-free input"
    for name, floor in floors.items():
        if floor["kind"] == FLOOR_COMPUTED:
            left_out, total = floor["diverged_left_out"]
            assert total == len(report["materials"]) and 0 < floor["rel_l2_log_y"] < float("inf"), name
    # on average the noise-free floors lie below the noisy errors
    computed = [n for n, f in floors.items() if f["kind"] == FLOOR_COMPUTED]
    noisy = {n: sum(r["scores"][n]["rel_l2_log_y"] for r in report["materials"].values()) for n in computed}
    floor_sum = {n: sum(r["floors"][n]["rel_l2_log_y"] for r in report["materials"].values()) for n in computed}
    assert sum(floor_sum.values()) < sum(noisy.values())
    assert report["times"]["evaluated_device_s"]["sparse-multiplexed"] > 0
    html = (out / "report.html").read_text()
    assert "Claims of the thesis" in html and "Paper 1, Table 2" in html
    assert "noise-free floor, rel. L2 log Y [%]" in html and "what the sensor noise and the dome" in html
    (mid, figs), = report["figures"].items()
    assert set(figs["renderings"]["psnr_db"]["point"]) == set(strategy_names())
    for name in figs["renderings"]["images"]["point"].values():
        assert (out / "figures" / mid / name).is_file()
    assert summary["report_html"].endswith("report.html")
    # issue 20: the adaptive loop ran on every held-out material, its bars and figure in both reports
    adaptive = report["adaptive"]
    assert list(adaptive["materials"]) == list(report["materials"]) and adaptive["bars"]
    assert all(rec["n_shots"] >= 1 and rec["steps"] for rec in adaptive["materials"].values())
    assert (out / adaptive["figure"]).is_file() and "Adaptive capture (leave-one-out" in html
    # the loop reports its own progress per held-out material (a job log's lines), after the scores' stage
    # has ended, so that neither stage's time is the other's
    lines = (out.parent / "stderr.log").read_text().splitlines()
    n_materials = len(report["materials"])
    reconstructed = next(i for i, line in enumerate(lines) if re.search(r" reconstruct: .*, done$", line))
    rendered = next(i for i, line in enumerate(lines) if re.search(r" render: 1/1 material \(100 %\), .*, done$", line))
    started = next(i for i, line in enumerate(lines) if line.endswith(" adaptive loop: started"))
    assert reconstructed < rendered < started, lines             # so is the rendering of the one material
    assert any(re.search(rf" adaptive loop: {n_materials}/{n_materials} materials \(100 %\), \d+\.\d s, done$",
                         line) for line in lines[started:]), lines
    # the default: a committee of every other material's ALS basis, the measured rows fused
    assert all(rec["settings"]["select"] == "committee" and rec["settings"]["committee"] == n_materials - 1
               and rec["settings"]["measured_rows"] == "fused" for rec in adaptive["materials"].values())


def test_cli_evaluate_acquisition_needs_db_and_out(capsys):
    from flows.cli import main

    assert main(["evaluate", "acquisition", "--db", "x"]) == 2
    assert "give --db TRUTH_DB_DIR and --out DIR" in capsys.readouterr().err


def test_cli_evaluate_ingest_still_needs_truth_and_btf(capsys):
    from flows.cli import main

    assert main(["evaluate", "ingest"]) == 2
    assert "--truth" in capsys.readouterr().err


@pytest.mark.parametrize("argv,msg", [(["--eval-materials-per-class", "0"], "materials_per_class must be >= 1"),
                                      (["--eval-render", "7"], "render_materials must lie in [0, 6]")])
def test_cli_bad_scale(argv, msg, tmp_path, capsys):
    from flows.cli import main

    assert main(["evaluate", "acquisition", "--db", str(tmp_path / "db"), "--out", str(tmp_path / "o"), *argv]) == 2
    assert msg in capsys.readouterr().err
