"""`btf sample`, `btf plan` and `btf render` end to end through flows.cli.main, and their bad-input exits."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import cv2
import numpy as np
import pytest
import zarr

from btfcore.model._lowrank import TruncatedSVD
from btfcore.capture.resample import lv_product
from btfcore.dome import get_device
from flows.cli import EXIT_BAD_INPUT, main
from tasks.model import SCHEMA_NAME, write_basis
from tasks.plan import read_plan


def _model(path, device_name: str = "tiny", k: int = 10):
    """A btf-model store with a device's rows in ingest order and random orthonormal 'leather' bases."""
    device = get_device(device_name)
    rows = []
    for angle in device.turntable_angle_deg:
        a = np.radians(angle)
        rot = np.array([[np.cos(a), np.sin(a), 0], [-np.sin(a), np.cos(a), 0], [0, 0, 1]])
        for cam in device.camera_position:
            for led in device.led_position:
                rows.append((rot @ (led / np.linalg.norm(led)), rot @ (cam / np.linalg.norm(cam))))
    L, V = (np.array(x) for x in zip(*rows))
    group = zarr.open_group(str(path / "model.zarr"), mode="w", zarr_format=3)
    group.create_array("light_dir", data=L)
    group.create_array("view_dir", data=V)
    group.attrs.put({"schema": SCHEMA_NAME, "schema_version": "1.0", "rows_id": "test", "n_lv": len(L)})
    rng = np.random.default_rng(0)
    for basis, n in (("log_y", len(L)), ("abtf_log_y", 9 * len(L)), ("als", len(L))):
        U = np.linalg.qr(rng.normal(size=(n, k)))[0]
        write_basis(group, f"classes/leather/{basis}", TruncatedSVD(U, np.linspace(5, 1, k), "merge"), "key")
    return path


def _btf_store(path):
    dirs = np.array([[0, 0, 1.0]] + [[math.sin(t) * math.cos(a), math.sin(t) * math.sin(a), math.cos(t)]
                                      for t in (0.5, 1.0, 1.5) for a in np.linspace(0, 2 * math.pi, 7)[:-1]])
    L, V = lv_product(dirs, dirs)
    albedo = np.random.default_rng(0).uniform(0.2, 0.8, (8, 8, 3))
    group = zarr.open_group(str(path), mode="w", zarr_format=3)
    group.create_array("btf", data=(L[:, 2, None, None, None] / math.pi * albedo[None]).astype(np.float32),
                       chunks=(len(dirs), 8, 8, 3))
    group.create_array("light_dir", data=L)
    group.create_array("view_dir", data=V)
    group.attrs.update({"schema": "btf-texture", "schema_version": "1.0", "complete": True})
    return path


def _run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, (json.loads(out) if code == 0 else None), err


def test_sample_then_plan_sparse(tmp_path, capsys):
    model = _model(tmp_path / "model")
    code, summary, err = _run(capsys, "sample", "--model", str(model), "--class", "leather", "--n", "10",
                              "--camera-parallel", "--device", "tiny", "--out", str(tmp_path / "s.json"))
    assert code == 0, err
    doc = json.loads((tmp_path / "s.json").read_text())
    assert summary["n_s"] == doc["n_s"] == 10 and len(doc["pairs"]) == 10 and doc["groups_from"] == "device"
    assert doc["kappa"] <= doc["kappa_history"]["start"] * (1 + 1e-9) and np.isfinite(doc["kappa"])
    assert "kappa" in err                                             # progress lines
    code, plan_summary, err = _run(capsys, "plan", "--device", "tiny", "--strategy", "sparse", "--samples",
                                   str(tmp_path / "s.json"), "--out", str(tmp_path / "plan"))
    assert code == 0, err
    plan = read_plan(tmp_path / "plan" / "plan.csv", get_device("tiny"))
    assert plan.n_shots == plan_summary["shots"] == 10
    assert {(s.turntable, s.leds[0]) for s in plan.shots} == {tuple(p) for p in doc["pairs"]}
    assert plan_summary["predicted_s"] > 0 and "shutter_s" in plan_summary["breakdown_s"]
    assert "predicted" in err
    code, _, err = _run(capsys, "plan", "--device", "tiny", "--strategy", "sparse-multiplexed", "--samples",
                        str(tmp_path / "s.json"), "--out", str(tmp_path / "plan2"))
    assert code == 0, err


@pytest.mark.parametrize("strategy", ["full", "multiplexed", "bootstrap"])
def test_plan_strategies_on_the_thesis_dome(tmp_path, capsys, strategy):
    code, summary, err = _run(capsys, "plan", "--device", "bonn-dome2", "--strategy", strategy, "--material",
                              "leather", "--out", str(tmp_path / "p"))
    assert code == 0, err
    doc = json.loads((tmp_path / "p" / "plan.json").read_text())
    assert doc["predicted_time"]["total_s"] == pytest.approx(summary["predicted_s"], abs=0.1)
    if strategy == "full":                                            # VMV Table 2, leather: 23.6 h (within 25 %)
        assert summary["shots"] == 12 * 198 and abs(summary["predicted_h"] / 23.6 - 1) < 0.25
    if strategy == "multiplexed":                                     # and 1.2 h multiplexed
        assert abs(summary["predicted_h"] / 1.2 - 1) < 0.25


def test_render_png(tmp_path, capsys):
    store = _btf_store(tmp_path / "b.zarr")
    code, summary, err = _run(capsys, "render", str(store), "--shape", "sphere", "--light", "2,2,4", "--size", "32",
                              "--out", str(tmp_path / "img.png"))
    assert code == 0, err
    img = cv2.imread(str(tmp_path / "img.png"), cv2.IMREAD_UNCHANGED)
    assert img.shape == (32, 32, 3) and img.max() > 0 and summary["object_pixels"] > 0


def test_bad_input_exits_1_and_names_it(tmp_path, capsys):
    model = _model(tmp_path / "model")
    cases = [
        (["sample", "--model", str(tmp_path / "none"), "--class", "leather", "--n", "5", "--out", "x.json"],
         "no such model directory"),
        (["sample", "--model", str(model), "--class", "wood", "--n", "20", "--out", "x.json"], "no class 'wood'"),
        (["sample", "--model", str(model), "--class", "leather", "--n", "3", "--out", "x.json"],
         "classes/leather/log_y"),                                    # fewer samples than basis vectors
        (["sample", "--model", str(model), "--class", "leather", "--n", "20", "--device", "bonn-dome2",
          "--out", "x.json"], "bonn-dome2"),
        (["plan", "--device", "tiny", "--strategy", "sparse", "--out", str(tmp_path / "p")], "needs --samples"),
        (["plan", "--device", "tiny", "--strategy", "full", "--samples", "s.json", "--out", str(tmp_path / "p")],
         "applies to the sparse"),
        (["plan", "--device", "tiny", "--strategy", "sparse", "--samples", str(tmp_path / "missing.json"),
          "--out", str(tmp_path / "p")], "no such samples file"),
        (["render", str(tmp_path / "none.zarr"), "--out", str(tmp_path / "i.png")], "no such BTF store"),
        (["render", str(tmp_path / "none.zarr"), "--light", "1,2", "--out", str(tmp_path / "i.png")], "X,Y,Z"),
        (["render", str(tmp_path / "none.zarr"), "--env", "nowhere", "--out", str(tmp_path / "i.png")],
         "--env nowhere"),
    ]
    for argv, message in cases:
        code = main(argv)
        err = capsys.readouterr().err
        assert code == EXIT_BAD_INPUT, (argv, err)
        assert message in err, (argv, err)
    # a samples file of another device
    main(["sample", "--model", str(model), "--class", "leather", "--n", "10", "--device", "tiny",
          "--out", str(tmp_path / "s.json")])
    capsys.readouterr()
    assert main(["plan", "--device", "bonn-dome2", "--strategy", "sparse", "--samples", str(tmp_path / "s.json"),
                 "--out", str(tmp_path / "p")]) == EXIT_BAD_INPUT
    assert "sampled for device 'tiny'" in capsys.readouterr().err


def test_help_explains_the_commands():
    for command, words in (("sample", "kappa"), ("plan", "breakdown"), ("render", "PNG")):
        out = subprocess.run([sys.executable, "-m", "flows.cli", command, "--help"], capture_output=True, text=True,
                             check=True).stdout
        assert words in out


def test_plan_flags_multiplexing_that_loses(tmp_path, capsys):
    # the default exposure model shortens a pattern of m LEDs m times: the demultiplexed noise grows
    code, summary, err = _run(capsys, "plan", "--device", "tiny", "--strategy", "multiplexed", "--out",
                              str(tmp_path / "lose"))
    assert code == 0, err
    doc = json.loads((tmp_path / "lose" / "plan.json").read_text())
    assert summary["multiplexing_loses"] is True and doc["multiplexing_loses"] is True
    assert doc["multiplexing_gain"] < 1 and doc["multiplexing_gain"] == pytest.approx(summary["multiplexing_gain"], abs=1e-4)
    assert "WARNING: multiplexing loses" in err and "single-light" in err and "fewer LEDs per pattern" in err
    assert "single-light" in doc["multiplexing"]["advice"]
    # the single-light shutter times for the patterns and a dark texel (read noise dominant): multiplexing wins
    code, summary, err = _run(capsys, "plan", "--device", "tiny", "--strategy", "multiplexed", "--exposure-exponent",
                              "0", "--signal-fraction", "0.0005", "--out", str(tmp_path / "win"))
    assert code == 0, err
    doc = json.loads((tmp_path / "win" / "plan.json").read_text())
    assert doc["multiplexing_loses"] is False and summary["multiplexing_gain"] > 1.2
    assert "WARNING" not in err and "predicted multiplexing gain" in err and "advice" not in doc["multiplexing"]
    # single-light plans carry no gain; a bad fraction is refused with the option named
    code, summary, err = _run(capsys, "plan", "--device", "tiny", "--strategy", "full", "--out", str(tmp_path / "f"))
    assert code == 0 and "multiplexing_gain" not in summary and "multiplexing" not in err
    code, _, err = _run(capsys, "plan", "--device", "tiny", "--strategy", "multiplexed", "--signal-fraction", "0",
                        "--out", str(tmp_path / "bad"))
    assert code == EXIT_BAD_INPUT and "--signal-fraction 0 must lie in (0, 1]" in err
    code, _, err = _run(capsys, "plan", "--device", "tiny", "--strategy", "multiplexed", "--exposure-exponent", "-1",
                        "--out", str(tmp_path / "bad"))
    assert code == EXIT_BAD_INPUT and "--exposure-exponent -1 must be finite and >= 0" in err
