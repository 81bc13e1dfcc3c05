"""`btf acquire --adaptive` end to end through the real command line, on the tiny dome's truth database."""

from __future__ import annotations

import json

from tasks.plan import read_plan


def test_acquire_adaptive_tiny(acquisition_evaluation, model_report, run_btf, tmp_path):
    db = acquisition_evaluation[0].parent / "acquisition-database"
    truth = sorted(db.glob("*-carpet.zarr"))[0]
    out = tmp_path / "acq"
    code, stdout, err = run_btf("acquire", "--adaptive", "--target-error", "0.05", "--budget", "8",
                                "--truth", truth, "--model", model_report, "--class", "carpet", "--out", out)
    assert code == 0, err
    summary = json.loads(stdout)
    doc = json.loads((out / "report.json").read_text())
    steps = doc["record"]["steps"]
    assert summary["shots"] == len(steps) == doc["record"]["n_shots"] <= 8
    assert summary["stopped"] in ("target", "budget")
    if summary["stopped"] == "budget":
        assert len(steps) == 8
    else:
        assert steps[-1]["predicted"] <= 0.05
    for s in steps:                                          # every step recorded: rows, predicted and true error
        assert len(s["rows"]) == 4 and s["predicted"] > 0 and s["true"] > 0
    groups = [s["group"] for s in steps]
    assert len(set(groups)) == len(groups)
    plans = sorted((out / "plans").glob("step_*.json"))
    assert len(plans) == len(steps)                           # one plan file per step, one shot each
    first = json.loads(plans[0].read_text())
    assert len(first["shots"]) == 1 and first["shots"][0]["leds"] == [steps[0]["led"]]
    assert len(first["shots"][0]["cameras"]) == 4 and first["predicted_time"]["total_s"] > 0
    from btfcore.dome import get_device
    plan = read_plan(out / "plan.json", get_device("tiny"))
    assert [(s.turntable, s.leds[0]) for s in plan.shots] == [(s["turntable"], s["led"]) for s in steps]
    assert {f["n_thesis"] for f in doc["record"]["fixed"]} == {100, 200, 400, None}
    html = (out / "report.html").read_text()
    assert "error_vs_shots.png" in html and (out / "error_vs_shots.png").exists()
    assert 0 < doc["record"]["basis_floor"] < 1        # (the fixed samplings' fused rows may get under it)
    assert "class basis&#x27; floor" in html                 # beside the target in the report's head
    # the time-aware choice: a run of other inputs (refused into the same --out), fewer turntable moves
    base = ("acquire", "--adaptive", "--target-error", "0.05", "--budget", "8", "--truth", truth, "--model",
            model_report, "--class", "carpet", "--no-compare", "--time-aware", "--out")
    code, _, err = run_btf(*base, out)
    assert code == 2 and "--overwrite" in err, err
    code, stdout, err = run_btf(*base, tmp_path / "timed")
    assert code == 0, err
    timed = json.loads((tmp_path / "timed" / "report.json").read_text())["record"]
    assert timed["settings"]["move_s"] == 5.0 and timed["settings"]["shot_s"] > 0

    moves = [sum(a["turntable"] != b["turntable"] for a, b in zip(r["steps"], r["steps"][1:]))
             for r in (timed, doc["record"])]
    assert moves[0] <= moves[1], moves
    # the default: the committee of the model's other per-material bases, the measured rows fused
    import zarr
    own = truth.stem
    n_other = sum(1 for m in zarr.open_group(model_report / "model.zarr", mode="r")["materials"].group_keys()
                  if m != own)
    assert doc["record"]["settings"]["select"] == "committee" and doc["record"]["settings"]["committee"] == n_other
    assert doc["record"]["settings"]["measured_rows"] == "fused"


def test_acquire_needs_adaptive_and_a_valid_target(acquisition_evaluation, model_report, run_btf, tmp_path):
    db = acquisition_evaluation[0].parent / "acquisition-database"
    truth = sorted(db.glob("*-carpet.zarr"))[0]
    base = ["--truth", truth, "--model", model_report, "--class", "carpet", "--out", tmp_path / "x"]
    code, _, err = run_btf("acquire", "--target-error", "0.1", *base)
    assert code == 2 and "--adaptive" in err
    code, _, err = run_btf("acquire", "--adaptive", "--target-error", "3", *base)
    assert code == 2 and "target-error" in err
    code, _, err = run_btf("acquire", "--adaptive", "--target-error", "0.1", *base[:4], "--class", "cloth",
                           *base[6:])
    assert code == 2 and "cloth" in err
    code, _, err = run_btf("acquire", "--adaptive", "--target-error", "0.1", "--predictor", "probes", "--select",
                           "posterior", *base)
    assert code == 2 and "--predictor probes needs --select committee" in err, err


def test_acquire_with_probe_groups(acquisition_evaluation, model_report, run_btf, tmp_path):
    """``--predictor probes``: every third shot after the start design a drawn group, the summary's prediction the
    probes' (from the fifth on), the report's steps marking the probes."""
    db = acquisition_evaluation[0].parent / "acquisition-database"
    truth = sorted(db.glob("*-carpet.zarr"))[0]
    out = tmp_path / "probes"
    code, stdout, err = run_btf("acquire", "--adaptive", "--target-error", "0.001", "--budget", "40", "--truth",
                                truth, "--model", model_report, "--class", "carpet", "--predictor", "probes",
                                "--no-compare", "--out", out)
    assert code == 0, err
    summary, rec = json.loads(stdout), json.loads((out / "report.json").read_text())["record"]
    n0, steps = rec["settings"]["n_start"], rec["steps"]
    assert rec["settings"]["predictor"] == summary["predictor"] == "probes" and len(steps) == 40
    assert [s["step"] for s in steps if s["probe"]] == list(range(n0, 40, 3))
    assert summary["predicted_error"] == steps[-1]["predicted_probes"] != steps[-1]["predicted"]
    assert summary["predicted_error_posterior"] == steps[-1]["predicted"]
    assert "probes&#x27; prediction [%]" in (out / "report.html").read_text() or \
        "probes' prediction [%]" in (out / "report.html").read_text()


def test_acquire_refuses_the_outputs_of_another_run_unless_overwrite(acquisition_evaluation, model_report, run_btf,
                                                                    tmp_path):
    """Outputs without a step journal, or an unreadable journal, at --out are not overwritten silently
    (tests/flows/test_kill_acquire.py: a journal of other inputs, and the resume)."""
    db = acquisition_evaluation[0].parent / "acquisition-database"
    truth = sorted(db.glob("*-carpet.zarr"))[0]
    out = tmp_path / "acq"
    out.mkdir()
    (out / "report.json").write_text("{}")
    args = ("acquire", "--adaptive", "--target-error", "0.3", "--budget", "4", "--truth", truth, "--model",
            model_report, "--class", "carpet", "--out", out)
    code, _, err = run_btf(*args)
    assert code == 2 and "without a step journal (report.json)" in err and "--overwrite" in err, err
    (out / "journal.json").write_text("not json")
    code, _, err = run_btf(*args)
    assert code == 2 and "unreadable step journal" in err, err
    code, stdout, err = run_btf(*args, "--overwrite")
    assert code == 0, err
    journal = json.loads((out / "journal.json").read_text())
    assert journal["finished"] and len(journal["steps"]) == json.loads(stdout)["shots"]


def test_a_dome_closes_the_loop_through_the_plan_files(acquisition_evaluation, model_report, run_btf, tmp_path):
    """`--measured`: each run writes the next step's plan and stops; the virtual dome executes the plan
    (`btf simulate --plan`), `btf ingest` writes its measurement store where the loop reads it, and the next run
    replays the finished steps from their stores and goes on, until the budget."""
    out, measured = tmp_path / "acq", tmp_path / "measured"
    loop = ("acquire", "--adaptive", "--target-error", "0.01", "--budget", "2", "--measured", measured, "--model",
            model_report, "--class", "carpet", "--device", "tiny", "--select", "posterior", "--rows", "model",
            "--out", out)
    for step in range(2):
        code, stdout, err = run_btf(*loop)
        assert code == 0, err
        wait = json.loads(stdout)["waiting"]
        assert wait["step"] == step and f"capture {out / 'plans' / f'step_{step:03d}.json'}" in err
        capture = tmp_path / f"capture-{step}"
        code, _, err = run_btf("simulate", "--plan", wait["plan"], "--device", "tiny", "--materials", "1",
                               "--classes", "carpet", "--seed", "5", "--texture-size", "8", "--out", capture)
        assert code == 0, err
        code, _, err = run_btf("ingest", capture / "000-carpet.zarr", "--out", wait["measurement"])
        assert code == 0, err
    code, stdout, err = run_btf(*loop)
    assert code == 0, err
    summary = json.loads(stdout)
    # step 0 replayed from its store, step 1 measured now
    assert summary["shots"] == 2 and summary["true_error"] is None and summary["reused"]["steps"] == [1, 2]
    record = json.loads((out / "report.json").read_text())["record"]
    assert (record["settings"]["select"], record["settings"]["committee"], record["settings"]["measured_rows"]) == (
        "posterior", 0, "model")                   # the earlier loop: no committee, every row from the basis
    steps = record["steps"]
    for k, s in enumerate(steps):                  # each step measured what its plan file asked for
        shot = json.loads((out / "plans" / f"step_{k:03d}.json").read_text())["shots"][0]
        assert (shot["turntable"], shot["leds"]) == (s["turntable"], [s["led"]])
        assert 0 < s["predicted"] < 10 and s["true"] is None
    # --white's correction (tasks.reconstruct.RowCorrection, as `btf reconstruct` applies it): each row divided by
    # its LED's gain, then the colour matrix
    import numpy as np

    from btfcore.acquisition.noise import SensorNoise
    from tasks.adaptive import measured_executor
    from tasks.reconstruct import RowCorrection

    rows = np.asarray([(steps[0]["turntable"] * 4 + c) * 16 + steps[0]["led"] for c in range(4)])
    led_gain = np.linspace(0.5, 2.0, 16 * 3).reshape(16, 3)
    matrix = np.array([[1.0, 0.1, 0.0], [0.0, 0.9, 0.0], [0.0, 0.2, 1.1]])
    noise = SensorNoise(1e4, 5.0)
    plain, gain = measured_executor(measured, noise)(steps[0]["group"], rows)
    corrected, corrected_gain = measured_executor(measured, noise, RowCorrection.of(led_gain, matrix, None, 192))(
        steps[0]["group"], rows)
    want = (plain / led_gain[steps[0]["led"]]) @ matrix.T
    np.testing.assert_allclose(corrected, want, rtol=1e-5)
    # each row's noise gain is that of its bracket's longest frame that did not saturate at its brightest value
    import zarr

    from tasks.stores import open_capture_store

    assert summary["exposure"] == {"capture": 2, "assumed": 0}
    capture = open_capture_store(tmp_path / "capture-0" / "000-carpet.zarr")
    e_per_dn, sat = capture.meta.sensor["gain_e_per_dn"], capture.meta.white_level - capture.meta.black_level
    bright = plain.reshape(len(rows), -1).max(axis=1)
    meas_index = np.asarray(zarr.open_group(str(measured / "step_000.zarr"), mode="r")["meas_index"][...])
    for k, (g, b) in enumerate(zip(gain, bright)):                      # row k: camera k
        t, c, i = meas_index[meas_index[:, 1] == k][0]
        times = np.asarray(capture.exposure_time)[t, c, i]
        frame = g / e_per_dn
        assert np.isclose(times, frame).any() and b * frame <= sat, (k, frame, times)
        assert not any(b * t <= sat for t in times if t > frame * 1.0001), (k, frame, times)
    np.testing.assert_allclose(corrected_gain * corrected.reshape(len(rows), -1).max(axis=1), gain * bright, rtol=1e-5)
    code, _, err = run_btf(*loop[:8], "--white", measured / "step_000.zarr", *loop[8:])   # not a white standard
    assert code == 2 and str(measured / "step_000.zarr") in err and "Traceback" not in err, err
    code, _, err = run_btf("acquire", "--adaptive", "--target-error", "0.1", "--truth", measured, "--model",
                           model_report, "--class", "carpet", "--white", measured / "step_000.zarr", "--out",
                           tmp_path / "x")
    assert code == 2 and "--white and --colour-matrix apply to --measured" in err, err
    # a measurement of the wrong rows is named
    wrong = tmp_path / "wrong"
    wrong.mkdir()
    (wrong / "step_000.zarr").symlink_to(measured / "step_001.zarr", target_is_directory=True)
    code, _, err = run_btf(*loop[:7], wrong, *loop[8:-1], tmp_path / "acq-wrong")
    assert code == 2 and "step_000.zarr: measures rows" in err and "plans/step_000.json" in err, err


def test_the_help_states_the_loops_stop_rule():
    """The CLI's help (which imports no numerics) names the loop's patience as btfcore has it."""
    import argparse

    from btfcore.acquisition.adaptive import STOP_PATIENCE
    from flows.adaptive_cli import ACQUIRE_HELP, add_acquire_arguments

    assert f"at {STOP_PATIENCE} consecutive" in " ".join(ACQUIRE_HELP.split())
    parser = argparse.ArgumentParser()
    add_acquire_arguments(parser)
    assert f"at {STOP_PATIENCE} consecutive steps" in " ".join(parser.format_help().split())
