"""The ``btf`` command line.

Every subcommand is one entry of the command table :data:`COMMANDS`: its help,
its arguments, the paths it reads and writes, its own checks and how it runs.
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
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from flows.acquisition_cli import (PLAN_HELP, RENDER_HELP, SAMPLE_HELP, add_plan_arguments, add_render_arguments,
                                   add_sample_arguments, run_plan, run_render, run_sample)

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


@dataclass(frozen=True)
class Command:
    """One ``btf`` subcommand: its parser, the paths it reads and writes, and how it runs.

    Attributes
    ----------
    name, help, description : str
        The subcommand, its line in ``btf --help`` and the text of ``btf NAME --help``.
    add_arguments : callable
        ``add_arguments(parser)`` adds the subcommand's arguments to its parser.
    run : callable, optional
        ``run(args) -> exit code``: the command in this process, without cluster or Prefect.
    flow : callable, optional
        ``flow(args, scheduler_address, prepared) -> summary``: the command's Prefect flow on the
        execution profile's Dask cluster; :func:`main` prints the summary as JSON.
    prepare : callable, optional
        ``prepare(args, prepared)``: the command's own checks before the cluster starts (bad input
        raises); what the flow reuses (its config, a read plan) goes into ``prepared``.
    cluster_when : callable, optional
        ``cluster_when(args)``: whether these arguments run ``flow`` rather than ``run`` (default:
        whenever there is a ``flow``).
    inputs, outputs : dict
        ``{argparse destination: the name the user typed it under}`` of the paths the command reads
        and writes, for the one output guard (:func:`tasks.staging.refuse_inputs_as_outputs`); an
        input that does not exist (``--sampling ubo2014``) is no path and is ignored.
    raw_description : bool
        Print ``description`` with its line breaks.
    """

    name: str
    help: str
    description: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int] | None = None
    flow: Callable[[argparse.Namespace, str, dict], dict] | None = None
    prepare: Callable[[argparse.Namespace, dict], None] | None = None
    cluster_when: Callable[[argparse.Namespace], bool] | None = None
    inputs: dict[str, str] = field(default_factory=dict)
    outputs: dict[str, str] = field(default_factory=lambda: {"out": "--out"})
    raw_description: bool = False

    def on_cluster(self, args: argparse.Namespace) -> bool:
        """Whether ``args`` run the command's flow on the cluster (else its ``run`` in this process)."""
        return self.flow is not None and (self.cluster_when is None or self.cluster_when(args))


def _add_simulation_options(p: argparse.ArgumentParser) -> None:
    from btfcore.dome import BAYER_PATTERNS, DEVICE_NAMES
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
    p.add_argument("--bayer", default=None, choices=BAYER_PATTERNS,
                   help="override the device's Bayer layout")
    p.add_argument("--texture-size", type=int, default=None, metavar="PX",
                   help="override the rectified texture side (ground truth is also written at 2x)")
    p.add_argument("--turntable", type=int, default=None, metavar="N",
                   help="simulate only the first N turntable positions (a pruned run)")
    p.add_argument("--psf-sigma", type=float, default=0.0, metavar="PX",
                   help="Gaussian point spread function of the cameras, sigma in raw pixels [default: 0, off]")


def _simulate_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``btf simulate``: the simulation's and the output's."""
    _add_simulation_options(p)
    p.add_argument("--out", required=True, metavar="PATH", help="output folder of the database")
    p.add_argument("--overwrite", action="store_true", help="replace finished stores of another config")
    p.add_argument("--plan", default=None, metavar="PLAN.json",
                   help="execute an acquisition plan (`btf plan` JSON or CSV): per turntable position its shots "
                        "(LEDs on, cameras, shutter brackets) instead of --illumination and automatic brackets; "
                        "`btf ingest` then writes a BTF store (full sets) or a measurement store "
                        "(docs/measurement-store.md)")


def _demo_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf demo``."""
    p.add_argument("--out", default="demo-output", metavar="DIR", help="output folder [default: demo-output]")
    p.add_argument("--seed", type=int, default=0, help="root seed [default: 0]")
    p.add_argument("--materials", type=int, default=12, metavar="N",
                   help="materials to simulate; the model database is built when there are at least two per "
                        "class [default: 12]")


def _import_raw_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf import-raw``."""
    p.add_argument("folder", metavar="FOLDER", help="folder holding the raw files")
    p.add_argument("--manifest", required=True, metavar="FILE", help="CSV or JSON manifest")
    p.add_argument("--device", default=None, help="dome calibration preset (tiny, bonn-dome2, ubo-dome1)")
    p.add_argument("--calibration", default=None, metavar="JSON",
                   help="dome calibration file (Device.to_json layout); overrides --device")
    p.add_argument("--out", required=True, metavar="STORE", help="capture store to write (.zarr)")
    p.add_argument("--overwrite", action="store_true", help="replace a finished store at --out")


def _ingest_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf ingest``."""
    p.add_argument("capture", metavar="CAPTURE", help="capture store (.zarr)")
    p.add_argument("--out", required=True, metavar="BTF", help="BTF store to write (.zarr)")
    _add_calibration_args(p)
    p.add_argument("--overwrite", action="store_true",
                   help="recompute and replace the output at --out (kept until the new one is complete and checked)")


def _resample_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf resample``."""
    p.add_argument("btf", metavar="BTF", help="finished BTF store from `btf ingest` (.zarr)")
    p.add_argument("--out", required=True, metavar="BTF2", help="resampled BTF store to write (.zarr)")
    p.add_argument("--sampling", default="ubo2014", metavar="ubo2014|FILE.json",
                   help='target directions: ubo2014 (151 lights x 151 views) or a JSON file {"light_dirs": '
                        '[[x, y, z], ...], "view_dirs": [[x, y, z], ...]} in the sample frame (z = surface '
                        'normal, z > 0; normalised here) [default: ubo2014]')
    p.add_argument("--overwrite", action="store_true", help="replace an output of another source or sampling")


def _build_db_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf build-db``."""
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


def _schedule_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf schedule``."""
    p.add_argument("what", choices=("build-db",), help="the job to schedule")
    p.add_argument("db", metavar="DB", help="folder of ingested BTF stores")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder of the model database")
    p.add_argument("--cron", required=True, metavar="EXPR", help='cron expression, e.g. "0 3 * * *" (03:00 daily)')
    p.add_argument("--name", default="build-db", help="deployment name [default: build-db]")
    p.add_argument("--classes", default=None, metavar="JSON", help="material classes for stores without one")


def _export_exr_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf export-exr``."""
    p.add_argument("btf", metavar="BTF", help="BTF store (.zarr)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--lv", default="all", metavar="ROWS",
                   help="rows to export: 'all' or a comma list of indices and ranges, e.g. 0,5,10-20 [default: all]")
    p.add_argument("--keep-nonfinite", action="store_true",
                   help="write textures with NaN or Inf texels as they are instead of refusing them")


def _evaluate_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf evaluate``."""
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


def _validate_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf validate``."""
    p.add_argument("stores", nargs="+", metavar="STORE")
    p.add_argument("--allow-incomplete", action="store_true", help="accept stores whose run has not finished")
    p.add_argument("--deep", action="store_true",
                   help="read every chunk and verify its checksum (reads the whole store, one chunk at a time)")


def _reconstruct_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments of ``btf reconstruct``."""
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


def build_parser() -> argparse.ArgumentParser:
    """The ``btf`` parser: the global options and one subparser per entry of :data:`COMMANDS`."""
    parser = argparse.ArgumentParser(prog="btf", description=DESCRIPTION, epilog=EPILOG,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cluster", default=None, metavar="PROFILE",
                        help="execution profile YAML (cluster kind, workers, memory, Prefect API) "
                             "[default: $BTF_CLUSTER_CONFIG or infra/local.yaml]")
    parser.add_argument("--no-progress", action="store_true", help="hide progress bars")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for command in COMMANDS.values():
        raw = {"formatter_class": argparse.RawDescriptionHelpFormatter} if command.raw_description else {}
        command.add_arguments(sub.add_parser(command.name, help=command.help, description=command.description,
                                             **raw))
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
    from tasks.export import export_exr, parse_selection
    from tasks.stores.btf import open_btf_store

    try:
        store = open_btf_store(args.btf, require_complete=False, produced_by="`btf ingest`")
        files = export_exr(args.btf, args.out, parse_selection(args.lv, store.btf.shape[0]),
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
    from tasks.stores.btf import SCHEMA_NAME as BTF_SCHEMA
    from tasks.stores.btf import validate_btf_store

    opened_only = ("btf-measurement", "btf-model")   # no schema check beyond opening (yet)
    failed = 0
    for path in args.stores:
        try:
            group, _ = open_any_store(path)
        except (FileNotFoundError, ValueError):
            group = None                                     # validate_capture_store says what is there
        kind = store_kind(group) if group is not None else None
        lines: list[str] = []
        if kind in opened_only:
            status = f"valid ({kind} store opened; schema checks are for capture and BTF stores"
            status += ")" if args.deep else ", --deep reads every chunk)"
        else:
            status = "valid"
            validate = validate_btf_store if kind == BTF_SCHEMA else validate_capture_store
            for problem in validate(path, require_complete=not args.allow_incomplete):
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


# --------------------------------------------------------------------------- checks before the cluster starts


def _prepare_simulate(args: argparse.Namespace, prepared: dict) -> None:
    from tasks.simulate import check_outputs

    prepared["config"] = _simulation_config(args)
    check_outputs(prepared["config"], args.out, args.overwrite)


def _is_acquisition(args: argparse.Namespace) -> bool:
    return args.what == "acquisition"


def _prepare_evaluate(args: argparse.Namespace, prepared: dict) -> None:
    prepared["config"] = _evaluation_config(args)  # acquisition: its scale is checked before a cluster starts


def _prepare_reconstruct(args: argparse.Namespace, prepared: dict) -> None:
    from tasks.radiometric import load_calibration
    from tasks.reconstruct import ReconstructSettings, check_inputs

    prepared["config"] = ReconstructSettings(cls=args.cls, basis=args.basis, method=args.method, lam=args.lam,
                                             k=args.k)
    check_inputs(args.measurement, args.model, prepared["config"],
                 load_calibration(args.white, args.white_albedo, args.colour_matrix))


def _prepare_import_raw(args: argparse.Namespace, prepared: dict) -> None:
    from tasks.ingest_raw import plan_raw_import, raw_import_metadata
    from tasks.staging import refuse_inputs_as_outputs
    from tasks.stores import check_capture_target

    prepared["device"] = _calibration(args)
    prepared["plan"] = plan_raw_import(args.folder, args.manifest)   # every problem listed at once
    refuse_inputs_as_outputs({"--out": args.out}, {f"raw file {p.name}": p for p in prepared["plan"].files.values()})
    meta = raw_import_metadata(prepared["plan"], prepared["device"])
    if not args.overwrite:
        check_capture_target(args.out, meta)


def _prepare_resample(args: argparse.Namespace, prepared: dict) -> None:
    from tasks.resample import check_inputs

    check_inputs(args.btf, args.out, args.sampling, overwrite=args.overwrite)


def _prepare_build_db(args: argparse.Namespace, prepared: dict) -> None:
    from tasks.model import check_model_target, discover, read_class_map

    check_model_target(Path(args.out) / "model.zarr", discover(args.db, read_class_map(args.classes)))


def _prepare_ingest(args: argparse.Namespace, prepared: dict) -> None:
    from tasks.ingest import check_ingest
    from tasks.radiometric import load_calibration

    prepared["calibration"] = load_calibration(args.white, args.white_albedo, args.colour_matrix)
    check_ingest(args.capture, args.out, overwrite=args.overwrite, calibration=prepared["calibration"])


# --------------------------------------------------------------------------- the flows: a JSON summary each


def _evaluate_acquisition_flow(args: argparse.Namespace, address: str, prepared: dict) -> dict:
    from flows.evaluate_acquisition import evaluate_acquisition_flow

    summary = evaluate_acquisition_flow(args.db, args.out, address, prepared["config"], progress=not args.no_progress)
    return {"command": "evaluate acquisition", "scale": summary["scale"],
            "claims": {k: c["verdict"] for k, c in summary["claims"].items()},
            "report_json": summary["report_json"], "report_html": summary["report_html"]}


def _reconstruct_flow(args: argparse.Namespace, address: str, prepared: dict) -> dict:
    from flows.acquisition import reconstruct_flow

    report = reconstruct_flow(args.measurement, args.model, args.out, address, prepared["config"],
                              overwrite=args.overwrite, progress=not args.no_progress, white=args.white,
                              white_albedo=args.white_albedo, colour_matrix=args.colour_matrix)
    return {"command": "reconstruct", "out": str(Path(args.out).resolve()), **report["stages"]["reconstruct"],
            "errors_against_truth": report["errors_against_truth"]}


def _build_db_flow(args: argparse.Namespace, address: str, prepared: dict) -> dict:
    from flows.model import build_db_flow
    from tasks.model import ModelSettings, with_k

    settings = with_k(ModelSettings(k_class=args.k_merged, k_global=args.k_merged), log_y=args.k_log_y,
                      u_y=args.k_chroma, v_y=args.k_chroma)
    report = build_db_flow(args.db, args.out, address, settings, classes=args.classes, progress=not args.no_progress)
    out = Path(args.out).resolve()
    return {"command": "build-db", "out": str(out), "model": report["model"], "trends": report["trends"],
            "report_json": str(out / "report.json"), "report_html": str(out / "report.html")}


def _ingest_flow(args: argparse.Namespace, address: str, prepared: dict) -> dict:
    from flows.ingest import ingest_flow

    return ingest_flow(args.capture, args.out, address, overwrite=args.overwrite, progress=not args.no_progress,
                       white=args.white, white_albedo=args.white_albedo, colour_matrix=args.colour_matrix,
                       calibration=prepared.get("calibration"))


def _resample_flow(args: argparse.Namespace, address: str, prepared: dict) -> dict:
    from flows.resample import resample_flow

    return resample_flow(args.btf, args.out, args.sampling, address, overwrite=args.overwrite,
                         progress=not args.no_progress)


def _import_raw_flow(args: argparse.Namespace, address: str, prepared: dict) -> dict:
    from flows.ingest import import_raw_flow

    return import_raw_flow(args.folder, args.manifest, prepared["device"], args.out, address,
                           overwrite=args.overwrite, plan=prepared["plan"])


def _simulate_flow(args: argparse.Namespace, address: str, prepared: dict) -> dict:
    from flows.simulate import simulate_flow

    report = simulate_flow(prepared["config"], args.out, address, overwrite=args.overwrite,
                           progress=not args.no_progress)
    return _database_summary(args, report)


def _demo_flow(args: argparse.Namespace, address: str, prepared: dict) -> dict:
    from flows.simulate import demo_flow

    report = demo_flow(args.out, address, seed=args.seed, n_materials=args.materials, progress=not args.no_progress)
    return _database_summary(args, report)


def _database_summary(args: argparse.Namespace, report: dict[str, Any]) -> dict:
    """The JSON summary of ``btf simulate`` and ``btf demo``: the output folder and its reports."""
    out = Path(args.out).resolve()
    return {"command": args.command, "out": str(out), "report_json": str(out / "report.json"),
            "report_html": str(out / "report.html"), "materials": len(report.get("materials", []))}


#: Every ``btf`` subcommand, in the order ``btf --help`` lists them.
COMMANDS: dict[str, Command] = {command.name: command for command in (
    Command("simulate", help="simulate capture stores on a virtual dome",
            description="Simulate materials on a virtual camera dome. Writes one capture store per material "
                        "(OUT/<id>.zarr, ground truth in its truth/ group), OUT/database.json, OUT/report.json and "
                        "OUT/report.html. An unfinished run resumes where it stopped; finished stores are never "
                        "overwritten unless --overwrite is given.",
            add_arguments=_simulate_arguments, prepare=_prepare_simulate, flow=_simulate_flow,
            inputs={"plan": "--plan", "classes": "--classes"}),
    Command("demo", help="the main job on the embedded default data",
            description="The main job on the embedded virtual dome: simulate two materials per class on the tiny "
                        "dome (one per class also S-matrix multiplexed) and a white standard, calibrate the LEDs, "
                        "ingest every capture, build the model database (OUT/model), evaluate sparse, multiplexed "
                        "and combined acquisition on a larger simulated database against the thesis' claims "
                        "(OUT/acquisition) and write OUT/report.json and OUT/report.html. With --materials below 12 "
                        "(two per class) the model database and the evaluation are skipped. Re-running resumes or "
                        "reuses finished work.",
            add_arguments=_demo_arguments, flow=_demo_flow),
    Command("import-raw", help="import camera raw files (DNG, any LibRaw format) into a capture store",
            description="Read a folder of camera raw files through LibRaw and write a capture store. The manifest "
                        "(CSV with header file,turntable,camera,illumination,exposure[,exposure_time][,role], or a "
                        "JSON list of such objects) maps each file to its place; exposure times missing from it are "
                        "read from the files. Everything is checked first and every problem is listed before any "
                        "work starts.",
            add_arguments=_import_raw_arguments, prepare=_prepare_import_raw, flow=_import_raw_flow,
            inputs={"folder": "FOLDER", "manifest": "--manifest", "calibration": "--calibration"}),
    Command("ingest", help="capture store -> BTF store (HDR, demosaic, rectify, demultiplex)",
            description="Process every view of a capture store: merge the exposure brackets in the Bayer domain, "
                        "demosaic, rectify the sample to the texture and demultiplex the illumination patterns. "
                        "Writes the BTF store and, beside it, BTF-stem.report.json (with errors against the ground "
                        "truth for simulated captures). Resumes an unfinished run; never overwrites another finished "
                        "output. With --overwrite the new store is built beside it (BTF-stem.partial.zarr) and "
                        "replaces it, with its report, only once complete and checked.",
            add_arguments=_ingest_arguments, prepare=_prepare_ingest, flow=_ingest_flow,
            inputs={"capture": "CAPTURE", "white": "--white", "colour_matrix": "--colour-matrix"}),
    Command("resample", help="BTF store -> BTF store on a common light x view sampling",
            description="Resample a finished BTF store (from `btf ingest`) to a common light x view sampling: every "
                        "light with every view of the UBO2014 151 x 151 set, or of your own JSON file. Values are "
                        "barycentric interpolations on Delaunay triangulations of the measured directions (3 views x "
                        "3 lights); a target outside the measured hull takes the values of the nearest hull point "
                        "and is flagged in the output's outside_hull array. Writes a new BTF store at --out (rows "
                        "ordered view-major, light fastest, one chunk per target view; docs/btf-store.md, 'Resampled "
                        "stores') and, beside it, BTF2-stem.report.json (rows, outside-hull count, seconds). The "
                        "input is never modified. An unfinished run resumes with the target views not yet written; a "
                        "store of another source or sampling at --out is never overwritten unless --overwrite, which "
                        "builds the new store beside it (BTF2-stem.partial.zarr) and replaces the old one only once "
                        "it is complete.",
            add_arguments=_resample_arguments, prepare=_prepare_resample, flow=_resample_flow,
            inputs={"btf": "BTF", "sampling": "--sampling"}),
    Command("build-db", help="model database: per-material bases, class and global merges, ABTF bases",
            description="Fit the linear models of a database of ingested BTFs (every finished `btf ingest` store in "
                        "DB): per-material truncated SVDs of log Y, U/Y and V/Y (paper 1), relative-error ALS bases "
                        "of linear RGB (paper 4), eigenspace merges per class and then globally, and per-class 3x3 "
                        "ABTF patch bases. Writes OUT/model.zarr, OUT/report.json (thesis Table 1 from a "
                        "leave-one-out evaluation) and OUT/report.html. A rerun reuses every basis whose inputs did "
                        "not change, so adding a material recomputes only it, its class and the global merge.",
            add_arguments=_build_db_arguments, prepare=_prepare_build_db, flow=_build_db_flow,
            inputs={"db": "DB", "classes": "--classes"}),
    Command("schedule", help="serve a scheduled deployment (cron) of a database build",
            description="Serve a Prefect deployment that runs `btf build-db DB --out OUT` on a cron schedule, each "
                        "run on the Dask cluster of --cluster and incremental (only new or changed materials are "
                        "fitted). Needs a running Prefect server: set PREFECT_API_URL (e.g. `prefect server start` "
                        "elsewhere); cron schedules do not fire on a temporary server. Runs until stopped.",
            add_arguments=_schedule_arguments, run=_schedule, inputs={"db": "DB", "classes": "--classes"}),
    Command("export-exr", help="write BTF textures as OpenEXR files",
            description="Write selected (or all) textures of a BTF store (from `btf ingest`) as float32 RGB OpenEXR "
                        "files named lv<row>_t<turntable>_c<camera>_l<light>.exr, with the light and view directions "
                        "in each header. Textures with NaN or Inf texels are refused (the message names the rows and "
                        "counts) before any file is written, unless --keep-nonfinite.",
            add_arguments=_export_exr_arguments, run=_export_exr, inputs={"btf": "BTF"}),
    Command("evaluate", help="measure a result against the simulator's ground truth",
            description="Compare a result with the ground truth of a simulated capture and print the metrics as "
                        "JSON; they are also written to --report.",
            add_arguments=_evaluate_arguments, run=_evaluate, prepare=_prepare_evaluate,
            flow=_evaluate_acquisition_flow, cluster_when=_is_acquisition,
            inputs={"btf": "--btf", "db": "DB", "truth": "--truth"},
            outputs={"out": "--out", "report": "--report"}),
    Command("validate", help="check stores and list every problem",
            description="Open each store and print every problem found; exit 2 if any. A capture store is validated "
                        "against the btf-capture schema (docs/capture-store.md), including a chunk file for every "
                        "bracket marked written; a BTF, measurement or model store (a `btf build-db` folder means "
                        "its model.zarr) is opened. --deep also reads every chunk of every array and names each "
                        "corrupt, truncated or missing one (array and chunk index). A store written before chunk "
                        "checksums were added is reported as such: --deep can then only find unreadable chunks, not "
                        "changed bytes.",
            add_arguments=_validate_arguments, run=_validate, outputs={}),
    Command("reconstruct", help="measurement store + model basis -> full BTF store",
            description="Reconstruct a full BTF from a measurement store (`btf ingest` of a sparse or multiplexed "
                        "plan capture) or a demultiplexed BTF store, with a class basis of the model database (`btf "
                        "build-db`). The solve operator is built once from the basis and the measurement matrix G "
                        "and applied band of texels by band in one Dask graph. The output is built beside --out "
                        "(BTF-stem.partial.zarr) and renamed into place once complete; BTF-stem.report.json holds "
                        "the settings and, for a simulated capture, the errors against the ground truth. Log bases "
                        "need single-light measurements; multiplexed ones use --basis als --method direct "
                        "(docs/measurement-store.md).",
            add_arguments=_reconstruct_arguments, prepare=_prepare_reconstruct, flow=_reconstruct_flow,
            inputs={"measurement": "MEASUREMENT", "model": "--model", "white": "--white",
                    "colour_matrix": "--colour-matrix"}),
    Command("sample", help="sparse sampling: which light/view pairs to measure (kappa-optimised)",
            description=SAMPLE_HELP, raw_description=True, add_arguments=add_sample_arguments, run=run_sample,
            inputs={"model": "--model"}),
    Command("plan", help="acquisition plan (JSON + CSV) and its predicted acquisition time",
            description=PLAN_HELP, raw_description=True, add_arguments=add_plan_arguments, run=run_plan,
            inputs={"samples": "--samples"}),
    Command("render", help="render a BTF store on a sphere, cylinder or plane to a PNG",
            description=RENDER_HELP, raw_description=True, add_arguments=add_render_arguments, run=run_render,
            inputs={"btf": "BTF", "env": "--env"}),
)}

#: Inputs that are folders of inputs: an output may be created inside them (``raws/capture.zarr``).
FOLDER_ARGS = ("FOLDER", "DB")

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
    command = COMMANDS[args.command]

    def named(table):
        found = {}
        for dest, name in table.items():
            value = getattr(args, dest, None)
            if isinstance(value, str) and value:
                found[name] = value
        return found
    return named(command.outputs), named(command.inputs)


def _preflight(args: argparse.Namespace, command: Command) -> dict:
    """Everything a command can refuse before Prefect and a cluster start; what it prepared on the way.

    The one output guard of every command (no output is or holds an input; outputs in writable
    folders) runs first, then, for a command that runs on the cluster, the execution profile is
    loaded and checked, then the command's own input and output checks (:attr:`Command.prepare`).
    Raises the bad-input errors :func:`main` maps to exit 2.
    """
    from tasks.staging import check_output_location, refuse_inputs_as_outputs

    outputs, inputs = _io_args(args)
    refuse_inputs_as_outputs(outputs, inputs, folders=FOLDER_ARGS)
    for name, path in outputs.items():
        check_output_location(path, name)
    prepared: dict = {"config": None, "device": None}
    if not command.on_cluster(args):
        return prepared
    from flows.runtime import load_profile

    prepared["profile"] = load_profile(args.cluster)
    if command.prepare is not None:
        command.prepare(args, prepared)
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
    command = COMMANDS[args.command]
    prepared = _preflight(args, command)
    if not command.on_cluster(args):
        return command.run(args)  # in this process: sample, plan, render, validate, export-exr, ...

    from flows.runtime import runtime

    start = time.perf_counter()
    with runtime(prepared["profile"]) as (_profile, _url, client):
        summary = command.flow(args, client.scheduler.address, prepared)
    print(json.dumps({**summary, "seconds": round(time.perf_counter() - start, 2)}, indent=2))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
