"""``btf sample``, ``btf plan`` and ``btf render``: sparse sampling, capture plans, renderings.

Wiring only: the arguments and the run of each command (entries of the command
table :data:`flows.cli.COMMANDS`), calls into :mod:`tasks.sample`,
:mod:`tasks.plan` and :mod:`tasks.render`, JSON summaries on stdout and
progress on stderr. These commands work on small in-memory arrays (a basis,
a plan, one rendering), so they run in the calling process and start neither
a Dask cluster nor Prefect. Errors and exit codes are those of :mod:`flows.cli`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Any


PLAN_STRATEGIES: tuple[str, ...] = ("full", "sparse", "multiplexed", "sparse-multiplexed", "bootstrap", "patterns")

#: What to do when a multiplexed plan's predicted gain is below 1 (docs/acquisition-planning.md).
_MUX_ADVICE = ("capture single-light (--strategy full or sparse), give the multiplexed patterns longer exposures "
               "(--exposure-exponent below 1, up to the full well), or use fewer LEDs per pattern "
               "(--strategy bootstrap: smaller S-matrices)")

SAMPLE_HELP = """\
Choose which light/view pairs a sparse measurement takes, for a class basis of
a model store (`btf build-db`), by minimising the condition number kappa(M U)
(paper 1, Alg. 1; docs/sampling.md). Methods: greedy (default; not in the
thesis, batched then exactly predicted swaps, much faster than the random
swap), random_swap (Matusik et al., as the thesis), parabolic_map (the 7x7
heuristic of paper 1, Fig. 3b; --n not needed). With --camera-parallel whole
(turntable, LED) pairs are chosen and all cameras always used (paper 4, §5.2):
--n then counts pairs. The groups come from --device's row order (an
unresampled model of that dome), otherwise from the rows' light directions.
With --device the output also lists the (turntable, LED) pairs that
`btf plan --strategy sparse --samples` captures. Writes JSON: rows, kappa, its
history, method, settings, seconds.
"""

PLAN_HELP = """\
Write an acquisition plan for a dome (PLAN_DIR/plan.json, complete, and
PLAN_DIR/plan.csv, one row per shot: turntable angle, LEDs on, cameras, shutter
times, exposure steps) and print the predicted acquisition time with its
breakdown (btfcore.acquisition.time_model; docs/acquisition-planning.md). Strategies: full
(every LED alone at every turntable position), sparse (the (turntable, LED)
pairs of --samples, all cameras), multiplexed (S-matrix patterns), sparse-
multiplexed (at each turntable position the sampled LEDs multiplexed with
their own S-matrix), bootstrap (VMV §4.2: the quadrant opposite the cameras
single-light, the others with smaller S-matrices), patterns (issue 20: --patterns M
basis-aware on/off LED patterns per position for the ALS basis of --model's
--class, chosen to minimise the predicted reconstruction error under photon
and read noise and saturation; the summary compares them with the full
S-matrix and with S-matrix rows at equal shots and equal exposure time).
--material picks the
shutter times of VMV Table 2 (cloth, leather, wood). A plan with multiplexed
shots also reports its predicted multiplexing gain (SNR of the demultiplexed
result over single-light capture under the device's photon + read noise, at
the plan's shutter times) and warns when it is below 1: multiplexing loses.
"""

RENDER_HELP = """\
Render a BTF store (`btf ingest` or `btf resample`) on a sphere, cylinder or
plane and write a tone-mapped PNG (docs/rendering.md): angular interpolation
between the measured light/view directions, bilinear texels, under a point
light (--light, default upper right front) and/or an environment map (--env:
an EXR file, or forest, sky or studio from the shared data). Prints JSON with
the image size, seconds and the PNG path.
"""


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {v}")
    return v


def add_sample_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``btf sample``."""
    from btfcore.dome import DEVICE_NAMES

    p.add_argument("--model", required=True, metavar="MODEL_DIR", help="output folder of `btf build-db` (or its model.zarr)")
    p.add_argument("--class", dest="cls", required=True, metavar="CLS", help="material class of the basis (classes/CLS)")
    p.add_argument("--basis", default="log_y", choices=("log_y", "abtf_log_y", "als"),
                   help="log_y (ABRDF, paper 1), abtf_log_y (3x3 patches: kappa of (I_9 kron M) U), als (paper 4) "
                        "[default: log_y]")
    p.add_argument("--n", type=_positive_int, default=None, metavar="N",
                   help="rows to select (with --camera-parallel: (turntable, LED) pairs); the thesis used 6%% of the "
                        "rows (1369 of 22,801)")
    p.add_argument("--method", default="greedy", choices=("greedy", "random_swap", "parabolic_map"),
                   help="sampler [default: greedy]")
    p.add_argument("--camera-parallel", action="store_true",
                   help="choose (turntable, LED) pairs and use all cameras for each (paper 4, §5.2)")
    p.add_argument("--device", default=None, choices=DEVICE_NAMES,
                   help="dome whose (turntable, camera, LED) row order the model has; adds the (turntable, LED) "
                        "pairs for `btf plan`")
    p.add_argument("--seed", type=int, default=0, help="seed of the random start [default: 0]")
    p.add_argument("--max-steps", type=_positive_int, default=None, metavar="S",
                   help="most steps (random swap: trial swaps, default 10,000; greedy: per phase, default 2,000)")
    p.add_argument("--out", required=True, metavar="SAMPLES_JSON", help="where to write the samples")


def add_plan_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``btf plan``."""
    from btfcore.acquisition.time_model import VMV_TABLE2
    from btfcore.dome import DEVICE_NAMES

    p.add_argument("--device", default="bonn-dome2", choices=DEVICE_NAMES,
                   help="dome preset [default: bonn-dome2, the thesis' DOME II]")
    p.add_argument("--strategy", required=True, choices=PLAN_STRATEGIES, help="what to capture")
    p.add_argument("--samples", default=None, metavar="SAMPLES_JSON",
                   help="`btf sample --device DEVICE` output; needed by sparse and sparse-multiplexed")
    p.add_argument("--material", default=None, choices=tuple(VMV_TABLE2),
                   help="shutter times of VMV Table 2 for this material [default: the ExposureModel default]")
    p.add_argument("--exposure-exponent", type=float, default=None, metavar="G",
                   help="a pattern with m LEDs on gets the single-light bracket divided by m**G (1: as bright as "
                        "m LEDs, the same electrons; 0: the single-light shutter times) [default: 1]")
    p.add_argument("--signal-fraction", type=float, default=0.8, metavar="F",
                   help="texel signal for the predicted multiplexing gain: F x the full well under one LED at the "
                        "longest single-light shutter time, in (0, 1]; --strategy patterns: the brightest texel of a "
                        "typical single-LED image at the chosen shutter time [default: 0.8]")
    p.add_argument("--patterns", type=_positive_int, default=None, metavar="M",
                   help="--strategy patterns: patterns per turntable position (e.g. a quarter of the LEDs)")
    p.add_argument("--model", default=None, metavar="MODEL_DIR",
                   help="--strategy patterns: output folder of `btf build-db` (or its model.zarr) of this device")
    p.add_argument("--class", dest="cls", default=None, metavar="CLS",
                   help="--strategy patterns: material class whose ALS basis the patterns serve (classes/CLS/als)")
    p.add_argument("--seed", type=int, default=0, help="--strategy patterns: seed of the design [default: 0]")
    p.add_argument("--out", required=True, metavar="PLAN_DIR", help="output folder (plan.json, plan.csv)")


def add_render_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf render``."""
    p.add_argument("btf", metavar="BTF_STORE", help="finished BTF store (.zarr)")
    p.add_argument("--shape", default="sphere", choices=("sphere", "cylinder", "plane"), help="[default: sphere]")
    p.add_argument("--env", default=None, metavar="EXR",
                   help="environment map: a lat-long EXR file, or forest, sky or studio (../shared/data/env)")
    p.add_argument("--light", default=None, metavar="X,Y,Z",
                   help="point light position in world units (object of radius 1 at the origin, camera on +z); "
                        "default (2, 2, 4) when no --env is given")
    p.add_argument("--intensity", type=float, default=None, metavar="I",
                   help="radiant intensity of the point light [default: 24, irradiance 1 at the origin]")
    p.add_argument("--size", type=_positive_int, default=256, metavar="PX", help="image side [default: 256]")
    p.add_argument("--out", required=True, metavar="PNG", help="image to write")


def _print_summary(summary: dict[str, Any]) -> int:
    """Print a command's JSON summary on stdout; exit code 0 (errors: one message and exit code by
    :func:`flows.cli.main`)."""
    print(json.dumps(summary, indent=2))
    return 0


def run_sample(args: argparse.Namespace) -> int:
    """``btf sample``: write the samples, print their summary; the exit code."""
    return _print_summary(_sample(args))


def run_plan(args: argparse.Namespace) -> int:
    """``btf plan``: write the plan, print its predicted time; the exit code."""
    return _print_summary(_plan(args))


def run_render(args: argparse.Namespace) -> int:
    """``btf render``: write the PNG, print its summary; the exit code."""
    return _print_summary(_render(args))


# --------------------------------------------------------------------------- sample


def _sample(args: argparse.Namespace) -> dict[str, Any]:
    from btfcore.dome import get_device
    from flows.progress import say
    from tasks.sample import sample_model, write_samples

    show = not getattr(args, "no_progress", False)
    last = [0.0]

    def progress(phase: str, step: int, kappa: float) -> None:
        now = time.perf_counter()
        if show and (now - last[0] > 0.5 or step == 0):
            last[0] = now
            say(f"btf sample: {phase} step {step}: kappa {kappa:.5g}")

    device = get_device(args.device) if args.device else None
    doc = sample_model(args.model, args.cls, args.basis, args.n, method=args.method,
                       camera_parallel=args.camera_parallel, device=device, seed=args.seed,
                       max_steps=args.max_steps, progress=progress)
    out = write_samples(doc, args.out)
    return {"command": "sample", "out": str(out.resolve()), "method": doc["method"], "class": doc["class"],
            "basis": doc["basis"], "k": doc["k"], "n_s": doc["n_s"], "n_rows": doc["n_rows"],
            "kappa": doc["kappa"], "kappa_start": doc["kappa_history"]["start"], "steps": doc["steps"],
            "pairs": len(doc["pairs"]) if "pairs" in doc else None, "seconds": doc["seconds"]}


# --------------------------------------------------------------------------- plan


def _selection(args: argparse.Namespace, device) -> Any:
    import numpy as np

    from tasks.sample import read_samples

    if not args.samples:
        raise ValueError(f"--strategy {args.strategy} needs --samples SAMPLES_JSON (from `btf sample --device "
                         f"{device.name} ...`)")
    doc = read_samples(args.samples)
    if doc.get("device") not in (None, device.name):
        raise ValueError(f"{args.samples}: sampled for device {doc['device']!r}, not {device.name!r}; sample again "
                         f"with --device {device.name} or plan for --device {doc['device']}")
    if not doc.get("pairs"):
        raise ValueError(f"{args.samples}: holds no (turntable, LED) pairs (it was written without --device); "
                         f"run `btf sample ... --device {device.name}` on a model of that dome")
    return np.asarray(doc["pairs"], dtype=np.int64)


def _plan(args: argparse.Namespace) -> dict[str, Any]:
    from btfcore.acquisition import plan as P
    from btfcore.dome import get_device
    from btfcore.acquisition.time_model import TimeModelParams, predict_time, thesis_exposure
    from tasks.plan import write_plan

    device = get_device(args.device)
    exposure = thesis_exposure(args.material) if args.material else None
    if getattr(args, "exposure_exponent", None) is not None and not (
            math.isfinite(args.exposure_exponent) and args.exposure_exponent >= 0):
        raise ValueError(f"--exposure-exponent {args.exposure_exponent:g} must be finite and >= 0")
    if getattr(args, "exposure_exponent", None) is not None:
        exposure = dataclasses.replace(exposure or P.ExposureModel(), exponent=float(args.exposure_exponent))
    fraction = float(getattr(args, "signal_fraction", 0.8))
    if not 0 < fraction <= 1:
        raise ValueError(f"--signal-fraction {fraction:g} must lie in (0, 1]: the texel's signal under one LED as a "
                         "fraction of the full well")
    if args.samples and args.strategy not in ("sparse", "sparse-multiplexed"):
        raise ValueError(f"--samples applies to the sparse strategies, not {args.strategy!r}; drop it")
    pattern_args = {"--patterns": getattr(args, "patterns", None), "--model": getattr(args, "model", None),
                    "--class": getattr(args, "cls", None)}
    if args.strategy == "patterns" and None in pattern_args.values():
        missing = [k for k, v in pattern_args.items() if v is None]
        raise ValueError(f"--strategy patterns needs {', '.join(missing)}: e.g. --patterns {device.n_leds // 4} "
                         "--model MODEL_DIR --class leather (a `btf build-db` model of this device)")
    if args.strategy != "patterns" and any(v is not None for v in pattern_args.values()):
        given = [k for k, v in pattern_args.items() if v is not None]
        raise ValueError(f"{', '.join(given)} apply to --strategy patterns, not {args.strategy!r}; drop them")
    if args.strategy == "full":
        plan = P.full_single_light_plan(device, exposure)
    elif args.strategy == "sparse":
        plan = P.sparse_plan(device, _selection(args, device), exposure)
    elif args.strategy == "multiplexed":
        plan = P.multiplexed_plan(device, exposure)
    elif args.strategy == "sparse-multiplexed":
        plan = P.sparse_multiplexed_plan(device, _selection(args, device), exposure, select="leds")
    elif args.strategy == "patterns":
        from tasks.plan import plan_patterns

        plan = plan_patterns(args.model, args.cls, device, args.patterns, exposure=exposure, seed=args.seed,
                             signal_fraction=fraction)
    else:
        plan = P.bootstrapping_plan(device, exposure)
    out = Path(args.out)
    params = TimeModelParams()
    # designed patterns are not demultiplexed (one solve on the basis): no multiplexing gain
    mux = None if args.strategy == "patterns" else P.multiplexing_gain(
        plan, full_well_e=device.sensor.full_well_e, read_noise_e=device.sensor.read_noise_e,
        signal_fraction=fraction)
    if mux is not None and mux["loses"]:
        mux["advice"] = _MUX_ADVICE
    write_plan(plan, out / "plan.json", out / "plan.csv", device=device, time_params=params, multiplexing=mux)
    t = predict_time(plan, params)
    breakdown = {name: round(float(v), 1) for name, v in t.to_dict().items()
                 if name.endswith("_s") and name != "total_s"}
    if not getattr(args, "quiet", False):
        print(f"btf plan: {args.strategy} on {device.name}: {t.n_shots} shots, {t.n_exposures} exposures, "
              f"predicted {t.total_h:.2f} h ({t.total_s / 60:.1f} min)", file=sys.stderr)
        for name, v in breakdown.items():
            print(f"  {name:22s} {v:12.1f} s", file=sys.stderr)
        if mux is not None:
            print(f"  predicted multiplexing gain {mux['gain']:.3f} (SNR over single-light capture, photon + "
                  f"read noise, texel at {mux['signal_fraction']:g} of the full well)", file=sys.stderr)
    if mux is not None and mux["loses"]:
        print(f"btf plan: WARNING: multiplexing loses against single-light capture: predicted gain "
              f"{mux['gain']:.3f} < 1 on {device.name} at this exposure; {_MUX_ADVICE}", file=sys.stderr)
    extra = {} if mux is None else {"multiplexing_gain": round(mux["gain"], 4),
                                    "multiplexing_loses": mux["loses"], "multiplexing": mux}
    if args.strategy == "patterns":
        extra = {"patterns": args.patterns, "class": args.cls,
                 "predicted_relative_error": plan.parameters["predicted_relative_error"],
                 "comparison": plan.parameters["comparison"]}
        if not getattr(args, "quiet", False):
            for name, c in plan.parameters["comparison"].items():
                print(f"  {name:34s} m = {c['m']:4d}: predicted relative error {c['predicted_relative_error']:.4g}"
                      f", time {c['predicted_time_s']:,.0f} s", file=sys.stderr)
    return {"command": "plan", "device": device.name, "strategy": plan.strategy,
            "material": args.material, "out": str(out.resolve()),
            "plan_json": str((out / "plan.json").resolve()), "plan_csv": str((out / "plan.csv").resolve()),
            "shots": t.n_shots, "exposures": t.n_exposures, "images": plan.n_images,
            "predicted_s": round(t.total_s, 1), "predicted_h": round(t.total_h, 3), "breakdown_s": breakdown,
            "time_model": params.to_dict(), **extra}


# --------------------------------------------------------------------------- render


def _env_path(text: str) -> Path:
    from tasks.shared_data import shared_file

    path = Path(text)
    if path.exists():
        return path
    if "/" not in text and "." not in text:
        found = shared_file(f"env/{text}.exr")
        if found is not None:
            return found
    raise ValueError(f"--env {text}: no such file (and not forest, sky or studio of ../shared/data/env); "
                     "give a lat-long EXR file")


def _render(args: argparse.Namespace) -> dict[str, Any]:
    from btfcore.render.btf_render import PointLight
    from tasks.render import render_store

    light = None
    if args.light is not None or args.intensity is not None:
        position = (2.0, 2.0, 4.0)
        if args.light is not None:
            try:
                position = tuple(float(v) for v in args.light.split(","))
            except ValueError:
                position = ()
            if len(position) != 3 or not all(abs(v) < float("inf") for v in position):
                raise ValueError(f"--light {args.light!r}: give the point light position as three numbers X,Y,Z")
        intensity = 24.0 if args.intensity is None else float(args.intensity)
        if not intensity > 0:
            raise ValueError(f"--intensity {args.intensity}: must be > 0")
        light = PointLight(position=position, intensity=(intensity,) * 3)
    env = _env_path(args.env) if args.env else None
    if not Path(args.btf).exists():
        raise ValueError(f"{args.btf}: no such BTF store; give the output of `btf ingest` or `btf resample`")
    r = render_store(args.btf, args.shape, light=light, env=env, out_png=args.out, image_size=args.size)
    return {"command": "render", "btf": str(Path(args.btf).resolve()), "shape": args.shape,
            "env": str(env) if env else None, "light": list(light.position) if light else None,
            "size": list(r.srgb.shape[:2]), "object_pixels": int(r.mask.sum()), "seconds": round(r.seconds, 3),
            "png": str(Path(r.png).resolve()) if r.png else None}
