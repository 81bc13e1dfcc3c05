"""Plans on disk (tasks.plan): JSON and CSV round trips, validation against a device."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from btfcore.acquisition.plan import ExposureModel, bootstrapping_plan, multiplexed_plan, sparse_multiplexed_plan, sparse_plan
from btfcore.dome import get_device
from btfcore.acquisition.time_model import TimeModelParams, predict_time, thesis_exposure
from tasks.plan import CSV_COLUMNS, read_plan, read_plan_json, write_plan


@pytest.fixture(scope="module")
def tiny():
    return get_device("tiny")


def _plans(tiny):
    e = ExposureModel(single_ms=(0.3, 7.25, 1000.0 / 3), min_shutter_ms=0.05)
    return [
        multiplexed_plan(tiny, e),
        sparse_plan(tiny, np.array([[0, 3], [2, 15]]), e, cameras=[1, 3]),
        sparse_multiplexed_plan(tiny, np.array([[0, 1], [0, 4], [0, 9], [2, 2]]), e, select="leds"),
    ]


@pytest.mark.parametrize("which", [0, 1, 2])
def test_json_and_csv_round_trip(tmp_path, tiny, which):
    plan = _plans(tiny)[which]
    doc = write_plan(plan, tmp_path / "p" / "plan.json", tmp_path / "p" / "plan.csv", device=tiny)
    for path in ("p/plan.json", "p/plan.csv"):
        again = read_plan(tmp_path / path, device=tiny)
        assert again.to_dict() == plan.to_dict(), path
        assert again.shots == plan.shots
    on_disk = json.loads((tmp_path / "p" / "plan.json").read_text())
    assert on_disk == doc
    assert on_disk["device"] == "tiny" and on_disk["strategy"] == plan.strategy
    assert on_disk["parameters"]["exposure"]["single_ms"][2] == 1000.0 / 3
    assert on_disk["predicted_time"]["total_s"] == pytest.approx(predict_time(plan).total_s)
    assert on_disk["predicted_time"]["model"] == TimeModelParams().to_dict()
    assert not list((tmp_path / "p").glob(".*.tmp.*"))


def test_csv_rows(tmp_path, tiny):
    plan = sparse_plan(tiny, np.array([[1, 3]]), ExposureModel(single_ms=(1.5, 20.0)), cameras=[0, 2])
    write_plan(plan, tmp_path / "plan.json", tmp_path / "plan.csv")
    lines = (tmp_path / "plan.csv").read_text().splitlines()
    rows = list(csv.DictReader(ln for ln in lines if not ln.startswith("#")))
    assert tuple(rows[0]) == CSV_COLUMNS and len(rows) == 1
    assert rows[0] == {"shot": "0", "turntable": "1", "turntable_angle_deg": "120.0", "leds": "3",
                       "cameras": "0;2", "shutter_ms": "1.5;20.0", "exposure_steps": "2", "group": "single"}
    mux = multiplexed_plan(tiny)
    write_plan(mux, tmp_path / "m.json", tmp_path / "m.csv")
    first = list(csv.DictReader(ln for ln in (tmp_path / "m.csv").read_text().splitlines()
                                if not ln.startswith("#")))[0]
    assert first["leds"] == ";".join(str(i) for i in mux.shots[0].leds)


def test_thesis_plan_predicted_time(tmp_path):
    dome2 = get_device("bonn-dome2")
    doc = write_plan(bootstrapping_plan(dome2, thesis_exposure("leather"), specular_half_width_deg=50.0),
                     tmp_path / "boot.json", tmp_path / "boot.csv", device=dome2)
    assert 5.0 < doc["predicted_time"]["total_h"] < 12.0
    assert read_plan(tmp_path / "boot.csv").n_shots == doc["predicted_time"]["n_shots"]


def test_read_validates_against_device(tmp_path, tiny):
    dome2 = get_device("bonn-dome2")
    plan = sparse_plan(dome2, np.array([[0, 5], [1, 150]]))
    write_plan(plan, tmp_path / "big.json", tmp_path / "big.csv")
    for name in ("big.json", "big.csv"):
        with pytest.raises(ValueError, match=rf"{name}: plan for device 'tiny': shot 0 uses camera\(s\) "):
            read_plan(tmp_path / name, device=tiny)
    with pytest.raises(ValueError, match=r"shot 1 switches on LED\(s\) \[150\]"):
        write_plan(sparse_plan(dome2, np.array([[0, 5], [1, 150]]), cameras=[0]), tmp_path / "x.json",
                   device=tiny)


def test_bad_files(tmp_path, tiny):
    plan = multiplexed_plan(tiny)
    write_plan(plan, tmp_path / "plan.json", tmp_path / "plan.csv")
    text = (tmp_path / "plan.csv").read_text()
    bad = tmp_path / "bad.csv"
    bad.write_text(text.replace("\n2,0,0.0,", "\n2,0,0.0,99;", 1))
    with pytest.raises(ValueError, match=r"bad.csv: plan for 'tiny': shot 2 switches on LED\(s\) \[99\]"):
        read_plan(bad)
    bad.write_text("\n".join(ln for ln in text.splitlines() if not ln.startswith("# schema:")))
    with pytest.raises(ValueError, match="schema"):
        read_plan(bad)
    doc = json.loads((tmp_path / "plan.json").read_text())
    doc["shots"][4]["shutter_ms"] = [5.0, 1.0]
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"bad.json: plan shot 4: .*strictly increasing"):
        read_plan(tmp_path / "bad.json")
    with pytest.raises(ValueError, match="no such plan file"):
        read_plan(tmp_path / "missing.json")
    (tmp_path / "plan.txt").write_text("x")
    with pytest.raises(ValueError, match=r"\.json or \.csv"):
        read_plan(tmp_path / "plan.txt")
    assert read_plan_json(tmp_path / "plan.json")[1]["predicted_time"]["n_shots"] == plan.n_shots
