"""`btf plan --strategy patterns` (issue 20) end to end through flows.cli.main, and its bad-input exits."""

from __future__ import annotations

import json

import numpy as np
import zarr

from btfcore.acquisition.hadamard import multiplexing_patterns
from btfcore.dome import get_device
from btfcore.model._lowrank import TruncatedSVD
from flows.cli import EXIT_BAD_INPUT, main
from tasks.model import SCHEMA_NAME, write_basis
from tasks.plan import read_plan


def _model(path, device_name: str = "tiny", k: int = 6):
    """A btf-model store with the device's row count and a positive-mean orthonormal 'leather' ALS basis."""
    device = get_device(device_name)
    n = device.n_turn * device.n_cam * device.n_leds
    rng = np.random.default_rng(0)
    group = zarr.open_group(str(path / "model.zarr"), mode="w", zarr_format=3)
    group.create_array("light_dir", data=np.tile([0.0, 0.0, 1.0], (n, 1)))
    group.create_array("view_dir", data=np.tile([0.0, 0.0, 1.0], (n, 1)))
    group.attrs.put({"schema": SCHEMA_NAME, "schema_version": "1.0", "rows_id": "test", "n_lv": n})
    U = np.linalg.qr(np.column_stack([np.ones(n) + 0.3 * rng.random(n), rng.normal(size=(n, k - 1))]))[0]
    write_basis(group, "classes/leather/als", TruncatedSVD(U, np.geomspace(50, 1, k), "merge"), "key")
    return path


def _run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, (json.loads(out) if code == 0 else None), err


def test_plan_patterns_writes_a_plan_with_its_predicted_error_and_time(tmp_path, capsys):
    model = _model(tmp_path / "model")
    device = get_device("tiny")
    m = device.n_leds // 4
    code, summary, err = _run(capsys, "plan", "--device", "tiny", "--strategy", "patterns", "--patterns", str(m),
                              "--model", str(model), "--class", "leather", "--out", str(tmp_path / "plan"))
    assert code == 0, err
    plan = read_plan(tmp_path / "plan" / "plan.csv", device)
    assert plan.strategy == "patterns" and plan.n_shots == summary["shots"] == m * device.n_turn
    assert {s.group for s in plan.shots} == {f"P{m}"}
    # the same patterns at every turntable position, each with at least one LED on
    per_turn = [sorted(s.leds for s in plan.shots if s.turntable == t) for t in range(device.n_turn)]
    assert all(p == per_turn[0] for p in per_turn) and all(len(leds) >= 1 for leds in per_turn[0])
    doc = json.loads((tmp_path / "plan" / "plan.json").read_text())
    comp = doc["parameters"]["comparison"]
    assert summary["comparison"] == comp and 0 < summary["predicted_relative_error"] < 1
    assert comp["patterns"]["predicted_relative_error"] == summary["predicted_relative_error"]
    # the design beats the S-matrix rows at the same shot count, on its own objective
    assert comp["patterns"]["predicted_relative_error"] < comp["s-matrix-rows-equal-shots"]["predicted_relative_error"]
    assert comp["full-s-matrix"]["m"] == multiplexing_patterns(device.n_leds).shape[0] and comp["patterns"]["m"] == m
    assert summary["predicted_s"] == round(comp["patterns"]["predicted_time_s"], 1)
    assert comp["patterns"]["predicted_time_s"] < comp["full-s-matrix"]["predicted_time_s"]
    assert "multiplexing_gain" not in doc and "predicted relative error" in err


def test_plan_patterns_bad_inputs_exit_with_the_fix(tmp_path, capsys):
    model = _model(tmp_path / "model")
    out = str(tmp_path / "plan")
    code, _, err = _run(capsys, "plan", "--device", "tiny", "--strategy", "patterns", "--patterns", "4", "--out", out)
    assert code == EXIT_BAD_INPUT and "needs --model, --class" in err
    code, _, err = _run(capsys, "plan", "--device", "tiny", "--strategy", "full", "--patterns", "4", "--out", out)
    assert code == EXIT_BAD_INPUT and "apply to --strategy patterns" in err
    code, _, err = _run(capsys, "plan", "--device", "tiny", "--strategy", "patterns", "--patterns", "4",
                        "--model", str(model), "--class", "stone", "--out", out)
    assert code == EXIT_BAD_INPUT and "no class 'stone'" in err
    code, _, err = _run(capsys, "plan", "--device", "bonn-dome2", "--strategy", "patterns", "--patterns", "4",
                        "--model", str(model), "--class", "leather", "--out", out)
    assert code == EXIT_BAD_INPUT and "plan for the device the model was built from" in err
