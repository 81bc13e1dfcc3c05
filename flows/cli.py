"""The ``btf`` command line.

Every subcommand that computes runs a Prefect flow on the Dask cluster of the
execution profile (``infra/local.yaml`` unless ``--cluster`` or
``$BTF_CLUSTER_CONFIG`` names another). Everything a command can check is
checked before Prefect and the cluster start (:func:`_preflight`), and every
error reaches the user as one message without a traceback (:func:`main`).
Exit codes: 0 success, 1 a failed run (a full disk, a lost worker: running the
same command again resumes it), 2 bad input or usage (the message names the
file, array and index and what to do), 3 Prefect or the cluster could not start.
"""

from __future__ import annotations

import argparse
import errno
import json
import sys
import time
from pathlib import Path
from typing import Sequence

EXIT_FAILED = 1
EXIT_BAD_INPUT = 2
EXIT_RUNTIME = 3
#: Errors that mean bad input or a refused output: the message names the file, array or index and what to do.
BAD_INPUT = (ValueError, KeyError, FileExistsError, FileNotFoundError, NotADirectoryError, IsADirectoryError,
             PermissionError)

DESCRIPTION = """\
btf-pipeline: raw camera-dome captures to bidirectional texture functions.

The embedded default data is a physically based virtual camera dome: `btf demo`
simulates a small database of materials on the `tiny` dome and writes
report.json and report.html. Runs use a Dask cluster and a Prefect API chosen
by an execution profile (default: infra/local.yaml, a 2-worker LocalCluster
with a temporary Prefect server).
"""


EPILOG = """\
exit codes: 0 success; 1 a failed run (running the same command again resumes
it); 2 bad input or usage (the message names the file, array and index and
what to do; nothing was started or written); 3 Prefect or the Dask cluster
could not start. BTF_DEBUG=1 shows the traceback of an error.
Docs: docs/capture-store.md, docs/devices.md, docs/decisions.md.
"""


def _add_simulation_options(p: argparse.ArgumentParser) -> None:
    from btfcore.dome import DEVICE_NAMES
    from btfcore.simulate.materials import MATERIAL_CLASSES

    p.add_argument("--device", default="tiny", choices=DEVICE_NAMES,
                   help="dome preset: tiny (tests, seconds), bonn-dome2 (11 cameras x 198 LEDs x 12 "
                        "turntable positions = 26,136 pairs), ubo-dome1 (151 x 151) [default: tiny]")
    p.add_argument("--materials", type=int, default=6, metavar="N",
                   help=f"number of materials; classes cycle through {', '.join(MATERIAL_CLASSES)} [default: 6]")
    p.add_argument("--seed", type=int, default=0, help="root seed of materials and noise [default: 0]")
    p.add_argument("--illumination", default="single", choices=("single", "multiplexed", "both"),
                   help="single-LED patterns, S-matrix multiplexed patterns, or both [default: single]")
    p.add_argument("--classes", default=None, metavar="A,B,...",
                   help="comma-separated material classes to cycle through; 'white-standard' simulates the "
                        "flat white target of a radiometric calibration [default: the six material classes]")
    p.add_argument("--bayer", default=None, choices=("RGGB", "BGGR", "GRBG", "GBRG"),
                   help="override the device's Bayer layout")
    p.add_argument("--texture-size", type=int, default=None, metavar="PX",
                   help="override the rectified texture side (ground truth is also written at 2x)")
    p.add_argument("--turntable", type=int, default=None, metavar="N",
                   help="simulate only the first N turntable positions (a pruned run)")
    p.add_argument("--psf-sigma", type=float, default=0.0, metavar="PX",
                   help="Gaussian point spread function of the cameras, sigma in raw pixels [default: 0, off]")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="btf", description=DESCRIPTION, epilog=EPILOG,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cluster", default=None, metavar="PROFILE",
                        help="execution profile YAML (cluster kind, workers, memory, Prefect API) "
                             "[default: $BTF_CLUSTER_CONFIG or infra/local.yaml]")
    parser.add_argument("--no-progress", action="store_true", help="hide progress bars")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser("simulate", help="simulate capture stores on a virtual dome",
                       description="Simulate materials on a virtual camera dome. Writes one capture store "
                                   "per material (OUT/<id>.zarr, ground truth in its truth/ group), "
                                   "OUT/database.json, OUT/report.json and OUT/report.html. An unfinished "
                                   "run resumes where it stopped; finished stores are never overwritten "
                                   "unless --overwrite is given.")
    _add_simulation_options(p)
    p.add_argument("--out", required=True, metavar="PATH", help="output folder of the database")
    p.add_argument("--overwrite", action="store_true", help="replace finished stores of another config")
    p.add_argument("--plan", default=None, metavar="PLAN.json",
                   help="execute an acquisition plan (`btf plan` JSON or CSV): per turntable position its shots "
                        "(LEDs on, cameras, shutter brackets) instead of --illumination and automatic brackets; "
                        "`btf ingest` then writes a BTF store (full sets) or a measurement store "
                        "(docs/measurement-store.md)")

    p = sub.add_parser("demo", help="the main job on the embedded default data",
                       description="The main job on the embedded virtual dome: simulate two materials per class "
                                   "on the tiny dome (one per class also S-matrix multiplexed) and a white standard, "
                                   "calibrate the LEDs, ingest every capture, build the model database "
                                   "(OUT/model), evaluate sparse, multiplexed and combined acquisition on a larger "
                                   "simulated database against the thesis' claims (OUT/acquisition) and write "
                                   "OUT/report.json and OUT/report.html. With --materials below 12 (two per class) "
                                   "the model database and the evaluation are skipped. Re-running resumes or "
                                   "reuses finished work.")
    p.add_argument("--out", default="demo-output", metavar="DIR", help="output folder [default: demo-output]")
    p.add_argument("--seed", type=int, default=0, help="root seed [default: 0]")
    p.add_argument("--materials", type=int, default=12, metavar="N",
                   help="materials to simulate; the model database is built when there are at least two per "
                        "class [default: 12]")

    p = sub.add_parser("import-raw", help="import camera raw files (DNG, any LibRaw format) into a capture store",
                       description="Read a folder of camera raw files through LibRaw and write a capture store. "
                                   "The manifest (CSV with header file,turntable,camera,illumination,exposure"
                                   "[,exposure_time][,role], or a JSON list of such objects) maps each file to its "
                                   "place; exposure times missing from it are read from the files. Everything is "
                                   "checked first and every problem is listed before any work starts.")
    p.add_argument("folder", metavar="FOLDER", help="folder holding the raw files")
    p.add_argument("--manifest", required=True, metavar="FILE", help="CSV or JSON manifest")
    p.add_argument("--device", default=None, help="dome calibration preset (tiny, bonn-dome2, ubo-dome1)")
    p.add_argument("--calibration", default=None, metavar="JSON",
                   help="dome calibration file (Device.to_json layout); overrides --device")
    p.add_argument("--out", required=True, metavar="STORE", help="capture store to write (.zarr)")
    p.add_argument("--overwrite", action="store_true", help="replace a finished store at --out")

    p = sub.add_parser("ingest", help="capture store -> BTF store (HDR, demosaic, rectify, demultiplex)",
                       description="Process every view of a capture store: merge the exposure brackets in "
                                   "the Bayer domain, demosaic, rectify the sample to the texture and "
                                   "demultiplex the illumination patterns. Writes the BTF store and, beside it, "
                                   "BTF-stem.report.json (with errors against the ground truth for simulated "
                                   "captures). "
                                   "Resumes an unfinished run; never overwrites another finished output. With "
                                   "--overwrite the new store is built beside it (BTF-stem.partial.zarr) and "
                                   "replaces it, with its report, only once complete and checked.")
    p.add_argument("capture", metavar="CAPTURE", help="capture store (.zarr)")
    p.add_argument("--out", required=True, metavar="BTF", help="BTF store to write (.zarr)")
    _add_calibration_args(p)
    p.add_argument("--overwrite", action="store_true",
                   help="recompute and replace the output at --out (kept until the new one is complete and checked)")

    p = sub.add_parser("resample", help="BTF store -> BTF store on a common light x view sampling",
                       description="Resample a finished BTF store (from `btf ingest`) to a common light x view "
                                   "sampling: every light with every view of the UBO2014 151 x 151 set, or of "
                                   "your own JSON file. Values are barycentric interpolations on Delaunay "
                                   "triangulations of the measured directions (3 views x 3 lights); a target "
                                   "outside the measured hull takes the values of the nearest hull point and is "
                                   "flagged in the output's outside_hull array. Writes a new BTF store at --out "
                                   "(rows ordered view-major, light fastest, one chunk per target view; "
                                   "docs/btf-store.md, 'Resampled stores') and, beside it, "
                                   "BTF2-stem.report.json (rows, outside-hull count, seconds). The input is never "
                                   "modified. An unfinished run resumes with the target views not yet written; a "
                                   "store of another source or sampling at --out is never overwritten unless "
                                   "--overwrite, which builds the new store beside it (BTF2-stem.partial.zarr) and "
                                   "replaces the old one only once it is complete.")
    p.add_argument("btf", metavar="BTF", help="finished BTF store from `btf ingest` (.zarr)")
    p.add_argument("--out", required=True, metavar="BTF2", help="resampled BTF store to write (.zarr)")
    p.add_argument("--sampling", default="ubo2014", metavar="ubo2014|FILE.json",
                   help='target directions: ubo2014 (151 lights x 151 views) or a JSON file {"light_dirs": '
                        '[[x, y, z], ...], "view_dirs": [[x, y, z], ...]} in the sample frame (z = surface '
                        'normal, z > 0; normalised here) [default: ubo2014]')
    p.add_argument("--overwrite", action="store_true", help="replace an output of another source or sampling")

    p = sub.add_parser("build-db", help="model database: per-material bases, class and global merges, ABTF bases",
                       description="Fit the linear models of a database of ingested BTFs (every finished `btf "
                                   "ingest` store in DB): per-material truncated SVDs of log Y, U/Y and V/Y "
                                   "(paper 1), relative-error ALS bases of linear RGB (paper 4), eigenspace merges "
                                   "per class and then globally, and per-class 3x3 ABTF patch bases. Writes "
                                   "OUT/model.zarr, OUT/report.json (thesis Table 1 from a leave-one-out "
                                   "evaluation) and OUT/report.html. A rerun reuses every basis whose inputs did "
                                   "not change, so adding a material recomputes only it, its class and the global "
                                   "merge.")
    p.add_argument("db", metavar="DB", help="folder of ingested BTF stores (.zarr), one per material")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--classes", default=None, metavar="JSON",
                   help='material classes for stores that do not carry one: {"<store name>": "<class>", ...}')
    p.add_argument("--k-log-y", type=int, default=None, metavar="K",
                   help="per-material log Y basis vectors [default: the thesis' 200, capped by the data]")
    p.add_argument("--k-chroma", type=int, default=None, metavar="K",
                   help="per-material U/Y and V/Y basis vectors [default: 100, capped by the data]")
    p.add_argument("--k-merged", type=int, default=None, metavar="K",
                   help="basis vectors kept by each merge [default: 2048, capped by the data]")

    p = sub.add_parser("schedule", help="serve a scheduled deployment (cron) of a database build",
                       description="Serve a Prefect deployment that runs `btf build-db DB --out OUT` on a cron "
                                   "schedule, each run on the Dask cluster of --cluster and incremental (only new "
                                   "or changed materials are fitted). Needs a running Prefect server: set "
                                   "PREFECT_API_URL (e.g. `prefect server start` elsewhere); cron schedules do "
                                   "not fire on a temporary server. Runs until stopped.")
    p.add_argument("what", choices=("build-db",), help="the job to schedule")
    p.add_argument("db", metavar="DB", help="folder of ingested BTF stores")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder of the model database")
    p.add_argument("--cron", required=True, metavar="EXPR", help='cron expression, e.g. "0 3 * * *" (03:00 daily)')
    p.add_argument("--name", default="build-db", help="deployment name [default: build-db]")
    p.add_argument("--classes", default=None, metavar="JSON", help="material classes for stores without one")

    p = sub.add_parser("export-exr", help="write BTF textures as OpenEXR files",
                       description="Write selected (or all) textures of a BTF store (from `btf ingest`) as "
                                   "float32 RGB OpenEXR files named lv<row>_t<turntable>_c<camera>_l<light>.exr, "
                                   "with the light and view directions in each header. Textures with NaN or Inf "
                                   "texels are refused (the message names the rows and counts) before any file is "
                                   "written, unless --keep-nonfinite.")
    p.add_argument("btf", metavar="BTF", help="BTF store (.zarr)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--lv", default="all", metavar="ROWS",
                   help="rows to export: 'all' or a comma list of indices and ranges, e.g. 0,5,10-20 [default: all]")
    p.add_argument("--keep-nonfinite", action="store_true",
                   help="write textures with NaN or Inf texels as they are instead of refusing them")

    p = sub.add_parser("evaluate", help="measure a result against the simulator's ground truth",
                       description="Compare a result with the ground truth of a simulated capture and print the "
                                   "metrics as JSON; they are also written to --report.")
    p.add_argument("what", choices=("ingest", "acquisition"),
                   help="ingest: a BTF store from `btf ingest` against its capture's truth; acquisition: leave-one-out "
                        "evaluation of sparse, multiplexed and sparse+multiplexed acquisition on a simulated truth "
                        "database (--db, --out; docs/evaluation.md)")
    p.add_argument("--truth", default=None, metavar="SIM", help="ingest: simulated capture store (with truth/)")
    p.add_argument("--btf", default=None, metavar="BTF", help="ingest: BTF store from `btf ingest`")
    p.add_argument("--db", default=None, metavar="TRUTH_DB_DIR",
                   help="acquisition: folder of truth BTF stores; missing ones are rendered into it")
    p.add_argument("--out", default=None, metavar="DIR", help="acquisition: output folder (report.json, report.html)")
    p.add_argument("--eval-device", default="bonn-dome2", metavar="NAME",
                   help="acquisition: dome preset [default: bonn-dome2]")
    p.add_argument("--eval-turntable", type=int, default=2, metavar="N",
                   help="acquisition: first N turntable positions [default: 2, 4,356 light/view pairs]")
    p.add_argument("--eval-texture", type=int, default=32, metavar="PX", help="acquisition: texture side [default: 32]")
    p.add_argument("--eval-materials-per-class", type=int, default=2, metavar="N",
                   help="acquisition: materials per class (>= 2 for leave-one-out) [default: 2]")
    p.add_argument("--eval-seed", type=int, default=0, metavar="S", help="acquisition: root seed [default: 0]")
    p.add_argument("--eval-render", type=int, default=1, metavar="N",
                   help="acquisition: materials (one per class, structured classes first) whose reconstructions "
                        "are rendered and scored by rendering PSNR; each adds one reconstruction store per "
                        "strategy and its renderings [default: 1]")
    p.add_argument("--report", default="report.json", metavar="PATH", help="where to write the metrics [default: report.json]")

    p = sub.add_parser("validate", help="check stores and list every problem",
                       description="Open each store and print every problem found; exit 2 if any. A capture "
                                   "store is validated against the btf-capture schema (docs/capture-store.md), "
                                   "including a chunk file for every bracket marked written; a BTF, measurement "
                                   "or model store (a `btf build-db` folder means its model.zarr) is opened. "
                                   "--deep also reads every chunk of every array and names each corrupt, "
                                   "truncated or missing one (array and chunk index). A store written before "
                                   "chunk checksums were added is reported as such: --deep can then only find "
                                   "unreadable chunks, not changed bytes.")
    p.add_argument("stores", nargs="+", metavar="STORE")
    p.add_argument("--allow-incomplete", action="store_true", help="accept stores whose run has not finished")
    p.add_argument("--deep", action="store_true",
                   help="read every chunk and verify its checksum (reads the whole store, one chunk at a time)")
    p = sub.add_parser("reconstruct", help="measurement store + model basis -> full BTF store",
                       description="Reconstruct a full BTF from a measurement store (`btf ingest` of a sparse or "
                                   "multiplexed plan capture) or a demultiplexed BTF store, with a class basis of "
                                   "the model database (`btf build-db`). The solve operator is built once from the "
                                   "basis and the measurement matrix G and applied band of texels by band in one "
                                   "Dask graph. The output is built beside --out (BTF-stem.partial.zarr) and renamed "
                                   "into place once complete; BTF-stem.report.json holds the settings and, for a "
                                   "simulated capture, the errors against the ground truth. Log bases need "
                                   "single-light measurements; multiplexed ones use --basis als --method direct "
                                   "(docs/measurement-store.md).")
    p.add_argument("measurement", metavar="MEASUREMENT", help="measurement store or BTF store (.zarr)")
    p.add_argument("--model", required=True, metavar="MODEL_DIR", help="`btf build-db` output folder")
    p.add_argument("--class", dest="cls", required=True, metavar="CLS", help="material class whose basis is used")
    p.add_argument("--basis", default="als", choices=("als", "log_y", "abtf_log_y"),
                   help="als (linear RGB; any measurement), log_y or abtf_log_y (single-light only) [default: als]")
    p.add_argument("--method", default="pinv", choices=("pinv", "tikhonov", "direct", "projection", "thresholded"),
                   help="pinv/tikhonov: sparse single-light; direct: multiplexed (paper 4 eq. 10); projection/"
                        "thresholded: denoise a full demultiplexable measurement [default: pinv]")
    p.add_argument("--lam", type=float, default=None, metavar="L",
                   help="lambda of lambda*Sigma^-1 [default: tikhonov 0.01 for als, 40 for log bases (the thesis); direct 0]")
    p.add_argument("--k", type=int, default=None, metavar="K", help="use only the first K basis vectors")
    p.add_argument("--out", required=True, metavar="BTF", help="BTF store to write (.zarr)")
    p.add_argument("--overwrite", action="store_true", help="replace another store at --out once the new one is complete")
    _add_calibration_args(p, " (for a model of corrected BTFs; the measurement store itself is uncorrected: "
                             "single-light rows are corrected before the solve, multiplexed rows get one operator "
                             "per colour channel)")
    from flows.acquisition_cli import add_acquisition_commands
    add_acquisition_commands(sub)  # btf sample, btf plan, btf render
    return parser


def _add_calibration_args(p: argparse.ArgumentParser, note: str = "") -> None:
    """``--white``, ``--white-albedo`` and ``--colour-matrix`` of ``btf ingest`` and ``btf reconstruct``."""
    p.add_argument("--white", default=None, metavar="WHITE_BTF",
                   help="radiometric correction: the uncorrected `btf ingest` output of a white-standard capture "
                        "on the same dome (simulate one with --classes white-standard); each LED's RGB gain is "
                        "measured on it and divided out, so the BTF is in the ground truth's unit" + note)
    p.add_argument("--white-albedo", type=float, default=0.99, metavar="A",
                   help="albedo of the white standard [default: 0.99]")
    p.add_argument("--colour-matrix", default=None, metavar="JSON",
                   help='camera colour matrix applied after the LED gains: {"matrix": [[...], [...], [...]]}, '
                        "3x3 or 3x4 (affine)")


def _simulation_config(args: argparse.Namespace):
    from tasks.simulate import SimulationConfig

    kwargs = dict(device=args.device, n_materials=args.materials, seed=args.seed,
                  illumination=args.illumination, bayer_pattern=args.bayer,
                  texture_size=args.texture_size, n_turntable=args.turntable, psf_sigma_px=args.psf_sigma)
    if args.classes:
        kwargs["classes"] = tuple(c.strip() for c in args.classes.split(",") if c.strip())
    if getattr(args, "plan", None):
        from tasks.plan import read_plan
        kwargs["plan"] = read_plan(args.plan)           # validated against the device by SimulationConfig
    return SimulationConfig(**kwargs)


def _calibration(args: argparse.Namespace):
    from btfcore.dome import Device, get_device

    if args.calibration:
        try:
            return Device.from_json(json.loads(Path(args.calibration).read_text()))
        except (OSError, ValueError, KeyError, TypeError) as exc:  # ValueError: bad JSON, NaN/Inf, bad geometry
            raise ValueError(f"{args.calibration}: not a valid dome calibration ({exc}); fix the file or "
                             "write it again with Device.to_json") from None
    if not args.device:
        raise ValueError("give the dome calibration: --device NAME or --calibration FILE.json")
    return get_device(args.device)


def _export_exr(args: argparse.Namespace) -> int:
    import zarr

    from tasks.export import export_exr, parse_selection

    try:
        group = zarr.open_group(args.btf, mode="r", zarr_format=3)
        if group.attrs.get("schema") != "btf-texture":
            raise ValueError(f"not a BTF store (schema {group.attrs.get('schema')!r}); give the output of `btf ingest`")
        files = export_exr(args.btf, args.out, parse_selection(args.lv, group["btf"].shape[0]),
                           keep_nonfinite=args.keep_nonfinite)
    except (ValueError, KeyError, FileNotFoundError) as exc:
        text = (f"no array {exc} in the store; give the output of `btf ingest`" if isinstance(exc, KeyError)
                else str(exc))
        where = "" if text.startswith(str(args.btf)) else f"{args.btf}: "      # every message names the store once
        print(f"btf export-exr: {where}{text}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(json.dumps({"out": str(Path(args.out).resolve()), "files": len(files)}, indent=2))
    return 0


def _evaluation_config(args: argparse.Namespace):
    """``btf evaluate acquisition``'s :class:`tasks.evaluate_acquisition.EvaluationConfig` (bad input raises)."""
    if not args.db or not args.out:
        raise ValueError("give --db TRUTH_DB_DIR and --out DIR")
    from tasks.evaluate_acquisition import EvaluationConfig
    return EvaluationConfig(device=args.eval_device, n_turntable=args.eval_turntable, texture_size=args.eval_texture,
                            materials_per_class=args.eval_materials_per_class, seed=args.eval_seed,
                            render_materials=args.eval_render)


def _evaluate(args: argparse.Namespace) -> int:
    from tasks.ingest import btf_error_against_truth
    from tasks.report import write_json
    from tasks.stores import open_capture_store

    if not args.truth or not args.btf:
        raise ValueError("give --truth SIM and --btf BTF")
    if not open_capture_store(args.truth).has_truth:
        raise ValueError(f"{args.truth} has no ground truth (truth/ group); give a simulated capture store")
    metrics = {"evaluate": args.what, "truth": str(args.truth), "btf": str(args.btf),
               **btf_error_against_truth(args.btf, args.truth)}
    write_json(args.report, metrics)
    print(json.dumps(metrics, indent=2))
    return 0


def _schedule(args: argparse.Namespace) -> int:
    import os

    if not os.environ.get("PREFECT_API_URL"):
        print("btf schedule: no Prefect server: set PREFECT_API_URL to a running server (start one with "
              "`prefect server start`); a cron schedule does not fire on the temporary server of a single run",
              file=sys.stderr)
        return EXIT_RUNTIME
    from prefect import serve

    from flows.schedule import build_db_deployment

    deployment = build_db_deployment(args.db, args.out, args.cron, cluster=args.cluster, classes=args.classes,
                                     name=args.name)
    print(json.dumps({"serving": f"btf-build-db-scheduled/{args.name}", "cron": args.cron,
                      "parameters": deployment.parameters}, indent=2), flush=True)
    serve(deployment)
    return 0


def _validate(args: argparse.Namespace) -> int:
    from tasks.integrity import CHECKSUM_NOTE, open_any_store, store_kind, unchecked_arrays, verify_store
    from tasks.stores import validate_capture_store

    opened_only = ("btf-texture", "btf-measurement", "btf-model")   # no schema check beyond opening (yet)
    failed = 0
    for path in args.stores:
        try:
            group, _ = open_any_store(path)
        except (FileNotFoundError, ValueError):
            group = None                                     # validate_capture_store says what is there
        kind = store_kind(group) if group is not None else None
        lines: list[str] = []
        if kind in opened_only:
            status = f"valid ({kind} store opened; schema checks are for capture stores"
            status += ")" if args.deep else ", --deep reads every chunk)"
        else:
            status = "valid"
            for problem in validate_capture_store(path, require_complete=not args.allow_incomplete):
                if args.deep and (problem.index or "").startswith("chunk "):
                    continue                                 # --deep names each of these chunks below
                where = f"[{problem.index}]" if problem.index else ""
                lines.append(f"{problem.array}{where}: expected {problem.expected}, found {problem.found}. "
                             f"{problem.hint}")
        if group is not None and args.deep:
            lines += [f"array {p.array}, chunk {p.chunk}: {p.problem}; {p.hint}" for p in verify_store(group)]
        notes = [CHECKSUM_NOTE] if group is not None and unchecked_arrays(group) else []
        if lines:
            failed += 1
            print(f"{path}: {len(lines)} problem(s)")
        else:
            print(f"{path}: {status}")
        for line in lines + [f"note: {n}" for n in notes]:
            print(f"  {line}")
    return EXIT_BAD_INPUT if failed else 0


#: What each command reads and writes, by argparse destination, with the name the user typed it under:
#: :func:`tasks.staging.refuse_inputs_as_outputs` (an input that does not exist, e.g. ``--sampling
#: ubo2014``, is no path and is ignored).
INPUT_ARGS = {"capture": "CAPTURE", "btf": "BTF", "measurement": "MEASUREMENT", "folder": "FOLDER", "db": "DB",
              "model": "--model", "white": "--white", "colour_matrix": "--colour-matrix", "manifest": "--manifest",
              "calibration": "--calibration", "plan": "--plan", "samples": "--samples", "classes": "--classes",
              "truth": "--truth", "sampling": "--sampling", "env": "--env"}
OUTPUT_ARGS = {"out": "--out", "report": "--report"}
#: Inputs that are folders of inputs: an output may be created inside them (``raws/capture.zarr``).
FOLDER_ARGS = ("FOLDER", "DB")
#: Commands that run on the execution profile's Dask cluster and Prefect API.
CLUSTER_COMMANDS = ("simulate", "demo", "import-raw", "ingest", "resample", "build-db", "reconstruct")

#: OS errors that mean the machine failed the run (exit 1), not that the user gave a bad path (exit 2).
_RUN_FAILURES = {errno.ENOSPC: "the disk is full: free space or choose another --out",
                 errno.EDQUOT: "the disk quota is spent: free space or choose another --out",
                 errno.EIO: "an input/output error of the disk"}
_PATH_HINTS = {errno.ENOTDIR: "a part of the path is a file, not a folder",
               errno.EISDIR: "it is a folder where a file is expected",
               errno.ENOENT: "no such file or folder",
               errno.EACCES: "permission denied: choose a path you may write, or fix its permissions",
               errno.EPERM: "operation not permitted: choose another path",
               errno.EROFS: "read-only file system: choose a path on a writable one"}


def _io_args(args: argparse.Namespace) -> tuple[dict[str, str], dict[str, str]]:
    """``(outputs, inputs)`` of a parsed command line as ``{name the user typed: path}``."""
    def named(table):
        found = {}
        for dest, name in table.items():
            value = getattr(args, dest, None)
            if isinstance(value, str) and value:
                found[name] = value
        return found
    inputs = named(INPUT_ARGS)
    if args.command == "evaluate":
        inputs = {("--btf" if k == "BTF" else k): v for k, v in inputs.items()}
    return named(OUTPUT_ARGS), inputs


def _preflight(args: argparse.Namespace) -> dict:
    """Everything a command can refuse before Prefect and a cluster start; what it prepared on the way.

    The one output guard of every command (no output is or holds an input; outputs in writable
    folders) runs first, then the execution profile is loaded and checked, then each command's own
    input and output checks. Raises the bad-input errors :func:`main` maps to exit 2.
    """
    from tasks.staging import check_output_location, refuse_inputs_as_outputs

    outputs, inputs = _io_args(args)
    refuse_inputs_as_outputs(outputs, inputs, folders=FOLDER_ARGS)
    for name, path in outputs.items():
        check_output_location(path, name)
    prepared: dict = {"config": None, "device": None}
    if args.command not in CLUSTER_COMMANDS and not (args.command == "evaluate" and args.what == "acquisition"):
        return prepared
    from flows.runtime import load_profile

    prepared["profile"] = load_profile(args.cluster)
    if args.command == "simulate":
        from tasks.simulate import check_outputs
        prepared["config"] = _simulation_config(args)
        check_outputs(prepared["config"], args.out, args.overwrite)
    elif args.command == "evaluate":  # acquisition: its scale is checked before a cluster starts
        prepared["config"] = _evaluation_config(args)
    elif args.command == "reconstruct":
        from tasks.radiometric import load_calibration
        from tasks.reconstruct import ReconstructSettings, check_inputs
        prepared["config"] = ReconstructSettings(cls=args.cls, basis=args.basis, method=args.method, lam=args.lam,
                                                 k=args.k)
        check_inputs(args.measurement, args.model, prepared["config"],
                     load_calibration(args.white, args.white_albedo, args.colour_matrix))
    elif args.command == "import-raw":
        from tasks.ingest_raw import plan_raw_import, raw_import_metadata
        from tasks.stores import check_capture_target
        prepared["device"] = _calibration(args)
        prepared["plan"] = plan_raw_import(args.folder, args.manifest)   # every problem listed at once
        refuse_inputs_as_outputs(outputs, {f"raw file {p.name}": p for p in prepared["plan"].files.values()})
        meta = raw_import_metadata(prepared["plan"], prepared["device"])
        if not args.overwrite:
            check_capture_target(args.out, meta)
    elif args.command == "resample":
        from tasks.resample import check_inputs
        check_inputs(args.btf, args.out, args.sampling, overwrite=args.overwrite)
    elif args.command == "build-db":
        from tasks.model import check_model_target, discover, read_class_map
        check_model_target(Path(args.out) / "model.zarr", discover(args.db, read_class_map(args.classes)))
    elif args.command == "ingest":
        from tasks.ingest import check_ingest
        from tasks.radiometric import load_calibration
        prepared["calibration"] = load_calibration(args.white, args.white_albedo, args.colour_matrix)
        check_ingest(args.capture, args.out, overwrite=args.overwrite, calibration=prepared["calibration"])
    return prepared


def _error_message(exc: BaseException, args: argparse.Namespace) -> tuple[str, int]:
    """One line (or the lines of a list of problems) for ``exc`` and the exit code it means."""
    if isinstance(exc, KeyError) and exc.args:
        return str(exc.args[0]), EXIT_BAD_INPUT
    if isinstance(exc, OSError) and exc.errno is not None and exc.strerror:
        # an error without a file name (a full disk while a worker wrote a chunk) is the output's
        where = exc.filename if exc.filename is not None else next(iter(_io_args(args)[0].values()), "?")
        if exc.errno in _RUN_FAILURES:
            return f"{where}: {exc.strerror} ({_RUN_FAILURES[exc.errno]})", EXIT_FAILED
        hint = _PATH_HINTS.get(exc.errno)
        return f"{where}: {exc.strerror}" + (f" ({hint})" if hint and hint != exc.strerror.lower() else ""), \
            EXIT_BAD_INPUT
    if isinstance(exc, BAD_INPUT):
        return str(exc), EXIT_BAD_INPUT
    if isinstance(exc, RuntimeError):  # a run that stopped (e.g. views not written): re-running resumes it
        return str(exc), EXIT_FAILED
    return (f"failed: {type(exc).__name__}: {exc} (set BTF_DEBUG=1 for the traceback; re-running resumes "
            "finished work)"), EXIT_FAILED


def main(argv: Sequence[str] | None = None) -> int:
    """The ``btf`` command: exit 0 success, 1 a failed run, 2 bad input or usage, 3 no runtime."""
    import os

    args = build_parser().parse_args(argv)
    try:
        return _main(args)
    except KeyboardInterrupt:
        print(f"btf {args.command}: interrupted; run the same command again to resume", file=sys.stderr)
        return 130
    except Exception as exc:  # every error reaches the user as one message, never as a traceback
        from flows.runtime import RuntimeUnavailable
        if os.environ.get("BTF_DEBUG"):
            raise
        if isinstance(exc, RuntimeUnavailable):
            message, code = str(exc), EXIT_RUNTIME
        else:
            message, code = _error_message(exc, args)
        print(f"btf {args.command}: {message}", file=sys.stderr)
        return code


def _main(args: argparse.Namespace) -> int:
    prepared = _preflight(args)
    from flows.acquisition_cli import run_acquisition_command
    code = run_acquisition_command(args)  # sample, plan, render: in-process, no cluster
    if code is not None:
        return code
    if args.command == "validate":
        return _validate(args)
    if args.command == "export-exr":
        return _export_exr(args)
    if args.command == "evaluate" and args.what != "acquisition":
        return _evaluate(args)
    if args.command == "schedule":
        return _schedule(args)

    from flows.runtime import runtime

    start = time.perf_counter()
    with runtime(prepared["profile"]) as (_profile, _url, client):
        summary = _run_flow(args, client.scheduler.address, prepared)
    print(json.dumps({**summary, "seconds": round(time.perf_counter() - start, 2)}, indent=2))
    return 0


def _run_flow(args: argparse.Namespace, address: str, prepared: dict) -> dict:
    """Run the flow of a computing subcommand on the cluster at ``address`` with what :func:`_preflight`
    prepared; a JSON summary."""
    from flows.ingest import import_raw_flow, ingest_flow
    from flows.simulate import demo_flow, simulate_flow

    config = prepared["config"]

    progress = not args.no_progress
    if args.command == "evaluate":
        from flows.evaluate_acquisition import evaluate_acquisition_flow
        summary = evaluate_acquisition_flow(args.db, args.out, address, config, progress=progress)
        return {"command": "evaluate acquisition", "scale": summary["scale"],
                "claims": {k: c["verdict"] for k, c in summary["claims"].items()},
                "report_json": summary["report_json"], "report_html": summary["report_html"]}
    if args.command == "reconstruct":
        from flows.acquisition import reconstruct_flow
        report = reconstruct_flow(args.measurement, args.model, args.out, address, config, overwrite=args.overwrite,
                                  progress=progress, white=args.white, white_albedo=args.white_albedo,
                                  colour_matrix=args.colour_matrix)
        return {"command": "reconstruct", "out": str(Path(args.out).resolve()), **report["stages"]["reconstruct"],
                "errors_against_truth": report["errors_against_truth"]}
    if args.command == "build-db":
        from flows.model import build_db_flow
        from tasks.model import ModelSettings, with_k

        settings = with_k(ModelSettings(k_class=args.k_merged, k_global=args.k_merged), log_y=args.k_log_y,
                          u_y=args.k_chroma, v_y=args.k_chroma)
        report = build_db_flow(args.db, args.out, address, settings, classes=args.classes, progress=progress)
        out = Path(args.out).resolve()
        return {"command": "build-db", "out": str(out), "model": report["model"], "trends": report["trends"],
                "report_json": str(out / "report.json"), "report_html": str(out / "report.html")}
    if args.command == "ingest":
        return ingest_flow(args.capture, args.out, address, overwrite=args.overwrite, progress=progress,
                           white=args.white, white_albedo=args.white_albedo, colour_matrix=args.colour_matrix,
                           calibration=prepared.get("calibration"))
    if args.command == "resample":
        from flows.resample import resample_flow
        return resample_flow(args.btf, args.out, args.sampling, address, overwrite=args.overwrite, progress=progress)
    if args.command == "import-raw":
        return import_raw_flow(args.folder, args.manifest, prepared["device"], args.out, address,
                               overwrite=args.overwrite, plan=prepared["plan"])
    if args.command == "simulate":
        report = simulate_flow(config, args.out, address, overwrite=args.overwrite, progress=progress)
    else:
        report = demo_flow(args.out, address, seed=args.seed, n_materials=args.materials, progress=progress)
    out = Path(args.out).resolve()
    return {"command": args.command, "out": str(out), "report_json": str(out / "report.json"),
            "report_html": str(out / "report.html"), "materials": len(report.get("materials", []))}


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
