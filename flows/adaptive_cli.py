"""``btf acquire --adaptive``: adaptive capture that stops at a quality target (docs/adaptive-capture.md).

Wiring only: the arguments and the run of the command (an entry of :data:`flows.cli.COMMANDS`); the loop
is :func:`tasks.adaptive_acquire.acquire_adaptive` over :mod:`btfcore.acquisition.adaptive`. It works on one
material's arrays in memory (a basis, the measured rows), so it runs in the calling process and starts
neither a Dask cluster nor Prefect. Errors and exit codes are those of :mod:`flows.cli`.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

ACQUIRE_HELP = """\
Adaptive capture (--adaptive): a closed loop of plan -> capture -> reconstruct ->
choose the next camera-parallel (turntable, LED) group, until the predicted
relative L2 error of log Y has been at or under --target-error at 3 consecutive
steps after the start design (early predictions run low), or --budget shots are
spent.
The error is predicted without the truth, from the posterior of the class ALS
basis' coefficients (paper 4 eq. 10, Tikhonov lambda Sigma^-1) under the
sensor's noise and a model residual estimated from the material's own rows
(the start design's, the largest of their estimates at the last 3 steps).
It is a guide, not a guarantee: on simulated held-out materials it was within
25 % of the true error at the budget on 58-100 % of them, depending on the draw
of materials, up to 2.9x over it, and a loop stopped at a target ended at up
to 2.3x the target (docs/adaptive-capture.md, "A second draw of materials").
With --predictor probes every third shot after the start design is a group
drawn at random from one brightness quartile of the groups in turn, not
chosen, and the error of the groups not measured is estimated from theirs (a
target is tested from the fifth such shot on): within 25 % at the budget on
71 of 72 simulated held-out materials (three draws of materials, two scales;
the posterior: 51), at 16-36 % more shots to the fixed sampling's error in
leather and stone at the default scale (docs/adaptive-capture.md, "Probes by
brightness stratum").
The next group is, by default (--select committee), the one whose rows hold the
most error as a committee of the model database's other per-material ALS bases,
fitted to the same measurements, sees it (where they disagree with the class
basis, it lacks a structure), or (--select posterior) the one whose shot most
reduces the posterior error; the measured rows of the reconstruction are fused
with their measurements (--rows fused) or the basis' fit (--rows model).
The simulator executes every shot on --truth (a noise-free BTF store, e.g.
of `btf evaluate acquisition`'s truth database) and scores each step against
it; every step's shot is also written as a plan (OUT/plans/step_NNN.json) that
a dome could execute, and OUT/plan.json holds all shots in acquisition order
with the predicted time. OUT/report.json records every step (rows, predicted
and true error); OUT/report.html plots error against shots beside the thesis'
fixed random-swap samplings (n_s = 100/200/400 scaled) and the 7x7 parabolic map.
A real dome closes the loop through the same plan files with --measured DIR
instead of --truth: each run reads step k's shot from DIR/step_kkk.zarr (`btf
ingest` of the capture of OUT/plans/step_kkk.json; --white / --colour-matrix
correct its rows as `btf reconstruct` does); where the next one is missing it
writes that step's plan, prints what to capture and ingest, and stops; run the
same command again once it is there (no true error, no fixed samplings).
Resumable: OUT/journal.json records every finished step under a key of the
inputs; the same command after a kill replays the recorded steps (measures their
groups again, chooses none) and continues, with the outputs of an uninterrupted
run; a finished run's rerun prints its summary. A run of other inputs at --out
is refused unless --overwrite.
"""


def add_acquire_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``btf acquire``."""
    from btfcore.dome import DEVICE_NAMES

    p.add_argument("--adaptive", action="store_true", help="adaptive capture (the only mode so far)")
    p.add_argument("--target-error", type=float, required=True, metavar="E",
                   help="stop when the predicted relative L2 error of log Y has been at most E (a fraction: 0.2 = "
                        "20 %%) at 3 consecutive steps")
    p.add_argument("--budget", type=int, default=None, metavar="SHOTS",
                   help="most shots ((turntable, LED) groups) [default: all groups]")
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--truth", metavar="TRUTH_BTF",
                        help="noise-free BTF store the simulator measures (rows (turntable, camera, LED))")
    source.add_argument("--measured", metavar="DIR",
                        help="a dome's shots instead: DIR/step_NNN.zarr, `btf ingest` of the capture of "
                             "OUT/plans/step_NNN.json (needs --device)")

    from flows.arguments import add_adaptive_choices, add_calibration

    add_calibration(p, " (with --measured)")
    add_adaptive_choices(p, "--")
    p.add_argument("--model", required=True, metavar="MODEL_DIR", help="output folder of `btf build-db`")
    p.add_argument("--class", dest="cls", required=True, metavar="CLS", help="material class of the ALS basis")
    p.add_argument("--device", default=None, choices=DEVICE_NAMES,
                   help="dome of the plans [default: the one the truth store records]")
    p.add_argument("--weighting", default="relative", choices=("relative", "none"),
                   help="row weights of the solve: relative to each row's brightness, or none (paper 4 eq. 10 as "
                        "is) [default: relative]")
    p.add_argument("--time-aware", action="store_true",
                   help="choose the group with the largest expected error reduction per second of the time model "
                        "(a turntable move, 5 s, must buy its time) instead of per shot: fewer moves, a shorter "
                        "acquisition for its error, possibly more shots")
    p.add_argument("--no-compare", action="store_true", help="skip the fixed samplings of the report")
    p.add_argument("--seed", type=int, default=0, help="seed of the simulated noise [default: 0]")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (report, plans, step journal)")
    p.add_argument("--overwrite", action="store_true",
                   help="discard the steps and outputs of a run of other inputs at --out and start over")


def run_acquire(args: argparse.Namespace) -> int:
    """``btf acquire``: run (or resume) the loop, write the report and plans, print the summary; the exit code.

    The summary's ``reused`` is ``{"steps": [replayed, total]}`` (steps of a killed run taken from its
    journal, not chosen again) and ``finished_before`` says that the run had finished already.
    """
    from btfcore.acquisition.adaptive import PREDICTION_KEYS
    from flows.progress import say
    from tasks.adaptive_acquire import acquire_adaptive

    if not args.adaptive:
        raise ValueError("btf acquire needs --adaptive (the only acquisition mode so far; fixed samplings are "
                         "`btf sample` + `btf plan`)")
    if args.budget is not None and args.budget < 1:
        raise ValueError(f"--budget must be >= 1 shot, got {args.budget}")
    if args.predictor == "probes" and args.select != "committee":
        raise ValueError("--predictor probes needs --select committee: its estimate regresses the probes' errors on "
                         "the committee's disagreement")
    if args.measured is not None and args.device is None:
        raise ValueError("--measured needs --device: the dome whose plans the loop writes")
    calibration = None
    if args.white is not None or args.colour_matrix is not None:
        if args.measured is None:
            raise ValueError("--white and --colour-matrix apply to --measured (the simulator's --truth is in the "
                             "truth's unit already)")
        from tasks.radiometric import load_calibration

        calibration = load_calibration(args.white, args.white_albedo, args.colour_matrix)
    doc = acquire_adaptive(args.truth, args.model, args.cls, args.out, target=args.target_error,
                           budget=args.budget, device_name=args.device, seed=args.seed, compare=not args.no_compare,
                           predictor=args.predictor, weighting=args.weighting, overwrite=args.overwrite,
                           say=lambda line: say(line, not args.quiet), time_aware=args.time_aware,
                           measured=args.measured, calibration=calibration, select=args.select,
                           measured_rows=args.rows)
    if "waiting" in doc:
        wait = doc["waiting"]
        say(f"btf acquire: step {wait['step']} (turntable {wait['turntable']}, LED {wait['led']}): capture "
            f"{wait['plan']} and ingest it with `btf ingest CAPTURE --out {wait['measurement']}`, then run this "
            "command again", not args.quiet)
        print(json.dumps({"command": "acquire", "out": args.out, **doc}, indent=2))
        return 0
    rec = doc["record"]
    last = rec["steps"][-1]
    summary: dict[str, Any] = {
        "command": "acquire", "out": args.out, "stopped": rec["stopped"], "shots": rec["n_shots"],
        "target_error": args.target_error, "predictor": args.predictor,
        "predicted_error": last[PREDICTION_KEYS[args.predictor]], "predicted_error_posterior": last["predicted"],
        "predicted_error_cv": last["predicted_cv"],
        "true_error": last["true"], "predicted_time_s": doc["predicted_time_s"],
        "fixed": {f["name"]: {"shots": f["n_shots"], "error": f["error"]} for f in rec.get("fixed", [])},
        "report_html": doc["report_html"], "report_json": doc["report_json"],
        "reused": doc["reused"], "finished_before": doc["finished_before"],
        **({"exposure": doc["exposure"]} if "exposure" in doc else {})}    # --measured: where each gain came from
    print(json.dumps(summary, indent=2))
    return 0
