"""Every acquisition strategy end to end on `tiny`: `btf simulate --plan`, `btf ingest`, `btf reconstruct`
(real Prefect, real LocalCluster, real Zarr)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import zarr

from btfcore.acquisition.plan import (
    ExposureModel,
    bootstrapping_plan,
    full_single_light_plan,
    multiplexed_plan,
    sparse_multiplexed_plan,
    sparse_plan,
)
from btfcore.dome import get_device
from tasks.plan import write_plan

EXPOSURE = ExposureModel(single_ms=(1.0, 10.0, 100.0, 1000.0))   # spans the tiny sensor's radiance range
COMMON = ["--device", "tiny", "--materials", "1", "--seed", "3", "--classes", "leather", "--texture-size", "8"]


def _plans():
    device = get_device("tiny")
    rng = np.random.default_rng(0)
    pairs = np.argwhere(rng.random((device.n_turn, device.n_leds)) < 0.4)
    return {
        "full-single": full_single_light_plan(device, EXPOSURE),
        "sparse": sparse_plan(device, pairs, EXPOSURE),
        "multiplexed": multiplexed_plan(device, EXPOSURE),
        "sparse-multiplexed": sparse_multiplexed_plan(device, np.argwhere(rng.random((device.n_turn, 19)) < 0.5),
                                                      EXPOSURE),
        "bootstrapping": bootstrapping_plan(device, EXPOSURE),
    }


_EXECUTED: dict = {}


@pytest.fixture()
def executed(run_btf, tmp_path_factory):
    """Each strategy's plan simulated and ingested through the command line (once per session: `run_btf`
    is function-scoped, so the result is cached here)."""
    if "runs" not in _EXECUTED:
        _EXECUTED["runs"] = _execute(run_btf, tmp_path_factory.mktemp("plans"))
    return _EXECUTED["runs"]


def _execute(run_btf, root):
    out = {}
    for name, plan in _plans().items():
        path = root / f"{name}.json"
        write_plan(plan, path, device=get_device("tiny"))
        code, _, err = run_btf("simulate", "--plan", path, *COMMON, "--out", root / name)
        assert code == 0, err
        capture = root / name / "000-leather.zarr"
        code, stdout, err = run_btf("ingest", capture, "--out", root / f"{name}.btf.zarr")
        assert code == 0, err
        out[name] = (plan, capture, root / f"{name}.btf.zarr", json.loads(stdout))
    return root, out


def test_every_strategy_runs_end_to_end(executed):
    _, runs = executed
    for name, (plan, capture, out, report) in runs.items():
        group = zarr.open_group(str(out), mode="r")
        if name in ("full-single", "multiplexed", "bootstrapping"):    # full sets: demultiplexed as before
            assert group.attrs["schema"] == "btf-texture", name
            assert report["errors_against_truth"]["relative_l2_log_y"] < 0.1, (name, report)
        else:
            assert group.attrs["schema"] == "btf-measurement", name
            assert report["errors_against_truth"]["measurement_relative_l2_linear"] < 0.15, (name, report)
        assert report["valid_fraction"]["problem"] is None, name
        cap = zarr.open_group(str(capture), mode="r")
        assert cap.attrs["provenance"]["simulation"]["plan"]["strategy"] == plan.strategy
        assert cap["plan"].attrs["plan"]["shots"][0] == plan.shots[0].to_dict()
        shot_t = plan.shots[0]                                 # its shutter bracket is the plan's
        i = int(np.flatnonzero((cap["plan/shot"][shot_t.turntable, shot_t.cameras[0]] == 0))[0])
        np.testing.assert_allclose(cap["exposure_time"][shot_t.turntable, shot_t.cameras[0], i][:shot_t.n_exposures],
                                   np.asarray(shot_t.shutter_ms) / 1000)


@pytest.mark.parametrize("name", ["sparse", "sparse-multiplexed"])
def test_measurement_matrix_matches_the_plan(executed, name):
    _, runs = executed
    plan, _, out, _ = runs[name]
    group = zarr.open_group(str(out), mode="r")
    G, shots, index = group["G"][...], group["shot"][...], group["meas_index"][...]
    n_cam, n_leds = plan.n_cam, plan.n_leds
    assert G.shape == (sum(len(s.cameras) for s in plan.shots), plan.n_turn * n_cam * n_leds)
    assert group["measured"].shape == (G.shape[0], 8, 8, 3)
    assert (np.diff(index[:, 0] * 10**6 + index[:, 1] * 10**3 + index[:, 2]) > 0).all()    # row-major (t, c, i)
    for r in range(len(G)):
        s = plan.shots[shots[r]]
        t, c, _ = index[r]
        assert t == s.turntable and c in s.cameras
        want = np.zeros(G.shape[1], np.float32)
        want[(t * n_cam + c) * n_leds + np.asarray(s.leds)] = 1                # the shot's LEDs at its view
        np.testing.assert_array_equal(G[r], want)
    light = group["light_dir"][...]
    full = zarr.open_group(str(runs["full-single"][2]), mode="r")
    np.testing.assert_allclose(light, full["light_dir"][...])                 # the full ingest's row order


def _model_from(btf_path, model_dir, k: int) -> None:
    """A model store whose class basis is the truncated SVD of a full ingest (same device, same units)."""
    src = zarr.open_group(str(btf_path), mode="r")
    B = np.asarray(src["btf"][...], dtype=np.float64)
    U, s, _ = np.linalg.svd(B.reshape(B.shape[0], -1), full_matrices=False)
    group = zarr.open_group(str(model_dir / "model.zarr"), mode="w", zarr_format=3)
    for name in ("light_dir", "view_dir"):
        data = src[name][...]
        group.create_array(name, shape=data.shape, dtype="float64", chunks=data.shape)[...] = data
    group.attrs.put({"schema": "btf-model", "schema_version": "1.0", "rows_id": "test", "n_lv": int(B.shape[0])})
    sub = group.require_group("classes/leather/als")
    sub.create_array("U", shape=(B.shape[0], k), dtype="float64", chunks=(B.shape[0], k))[...] = U[:, :k]
    sub.create_array("sigma", shape=(k,), dtype="float64", chunks=(k,))[...] = s[:k]
    sub.attrs.put({"method": "test", "key": "full-svd"})


def test_reconstruct_sparse_and_multiplexed_captures(executed, run_btf):
    root, runs = executed
    full = runs["full-single"][2]
    _model_from(full, root / "model", k=12)
    B_full = zarr.open_group(str(full), mode="r")["btf"][...]
    errors = {}
    for name, args in (("sparse", ["--method", "pinv"]),
                       ("sparse-multiplexed", ["--method", "direct", "--lam", "0.01"])):
        out = root / f"{name}.rec.zarr"
        code, stdout, err = run_btf("reconstruct", runs[name][2], "--model", root / "model", "--class", "leather",
                                    *args, "--out", out)
        assert code == 0, err
        rec = zarr.open_group(str(out), mode="r")
        assert rec.attrs["schema"] == "btf-texture" and rec.attrs["complete"]
        assert rec["btf"].shape == B_full.shape
        errors[name] = float(np.linalg.norm(rec["btf"][...] - B_full) / np.linalg.norm(B_full))
        summary = json.loads(stdout)
        assert summary["errors_against_truth"]["relative_l2_log_y"] < 0.3, summary
        assert (root / f"{name}.rec.report.json").exists()
    assert max(errors.values()) < 0.15, errors
    # fewer samples than basis vectors with pinv: refused before anything is written, tikhonov suggested
    _model_from(full, root / "big-model", k=150)
    code, _, err = run_btf("reconstruct", runs["sparse"][2], "--model", root / "big-model", "--class", "leather",
                           "--out", root / "bad.zarr")
    assert code == 2 and "tikhonov" in err and "measured rows for k=150" in err, err
    assert not (root / "bad.zarr").exists() and not (root / "bad.partial.zarr").exists()


def test_plan_with_an_led_the_device_lacks_is_refused(run_btf, tmp_path):
    plan = _plans()["sparse"].to_dict()
    plan["n_leds"] = 200
    plan["shots"][1]["leds"] = [150]
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(plan))
    code, _, err = run_btf("simulate", "--plan", path, *COMMON, "--out", tmp_path / "db")
    assert code == 2
    assert "shot 1" in err and "150" in err, err
    assert not (tmp_path / "db").exists()
