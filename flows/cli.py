"""The ``btf`` command line.

Every subcommand is one entry of the command table :data:`COMMANDS`: its help,
its arguments, the paths it reads and writes, its own checks and how it runs.
Every subcommand that computes runs a Prefect flow on the Dask cluster of the
execution profile (``infra/local.yaml`` unless ``--cluster`` or
``$BTF_CLUSTER_CONFIG`` names another). Everything a command can check is
checked before Prefect and the cluster start (:func:`_preflight`), and every
error reaches the user as one message without a traceback (:func:`main`).
A computing command prints its first line before anything slow is imported (the
parser imports nothing of a command's until that command parses,
:class:`CommandParser`), then what it starts (:func:`_starting_line`); the global
options are accepted before and after the command (:mod:`flows.arguments`).
Exit codes: 0 success, 1 a failed run (a full disk, a lost worker: running the
same command again resumes it), 2 bad input or usage (the message names the
file, array and index and what to do), 3 Prefect or the cluster could not start.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import json
import os
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from flows import arguments
from flows.adaptive_cli import ACQUIRE_HELP, add_acquire_arguments, run_acquire
from flows.acquisition_cli import (PLAN_HELP, RENDER_HELP, SAMPLE_HELP, add_plan_arguments, add_render_arguments,
                                   add_sample_arguments, run_plan, run_render, run_sample)
from flows.bonn_cli import (EXPORT_HELP, IMPORT_HELP, add_export_arguments, add_import_arguments, import_btf_flow,
                            prepare_import, run_export)
from flows.import_cli import (IMPORT_IMAGES_DESCRIPTION, import_images_cli_flow, import_raw_cli_flow,
                              prepare_import_images, prepare_import_raw)
from flows.progress import say
from flows.server import CHILD_ENV, SERVER_HELP, add_server_arguments, run_server
from flows.superres_cli import (SUPERRES_HELP, add_superres_arguments, evaluate_superres_flow, prepare_superres,
                                run_superres_train, superres_apply_flow, superres_evaluation_config,
                                superres_on_cluster)

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
global options (--cluster, --no-progress, --quiet, --verbose, --log-level) may
also follow the command: `btf ingest CAPTURE --out BTF --quiet`. Progress goes
to stderr: bars in a terminal, elsewhere (a job log, CI, nohup) timestamped
lines at the start of each stage, about every 10 % and at its end.
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


class CommandParser(argparse.ArgumentParser):
    """A subcommand's parser that adds the command's arguments (and the global options again) only when
    it parses: ``btf --help`` and ``btf ingest`` build no other command's arguments and import nothing of
    theirs (``btf simulate``'s choices come from btfcore)."""

    def __init__(self, *args: Any, add_arguments: Callable[[argparse.ArgumentParser], None] | None = None,
                 **kwargs: Any):
        super().__init__(*args, **kwargs)
        self._add_arguments = add_arguments

    def parse_known_args(self, args=None, namespace=None):  # noqa: D102  (argparse's)
        if self._add_arguments is not None:
            add, self._add_arguments = self._add_arguments, None
            add(self)
            arguments.add_global_options(self, after_command=True)
        return super().parse_known_args(args, namespace)


def build_parser() -> argparse.ArgumentParser:
    """The ``btf`` parser: the global options and one subparser per entry of :data:`COMMANDS`.

    The global options are accepted before and after the subcommand (:class:`CommandParser`).
    """
    parser = argparse.ArgumentParser(prog="btf", description=DESCRIPTION, epilog=EPILOG,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    arguments.add_global_options(parser)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True, parser_class=CommandParser)
    for command in COMMANDS.values():
        raw = {"formatter_class": argparse.RawDescriptionHelpFormatter} if command.raw_description else {}
        sub.add_parser(command.name, help=command.help, description=command.description,
                       add_arguments=command.add_arguments, **raw)
    return parser


def _simulation_config(args: argparse.Namespace):
    from tasks.simulate import SimulationConfig

    kwargs = dict(device=args.device, n_materials=args.materials, seed=args.seed,
                  illumination=args.illumination, bayer_pattern=args.bayer,
                  texture_size=args.texture_size, n_turntable=args.turntable, psf_sigma_px=args.psf_sigma,
                  camera_scale=args.camera_scale)
    if args.classes:
        kwargs["classes"] = tuple(c.strip() for c in args.classes.split(",") if c.strip())
    if getattr(args, "non_ideal", None):
        kwargs["non_ideal"] = _non_ideal(args.non_ideal)
    if getattr(args, "plan", None):
        from tasks.plan import read_plan
        kwargs["plan"] = read_plan(args.plan)           # validated against the device by SimulationConfig
    return SimulationConfig(**kwargs)


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
    from btfcore.simulate.nonideal import IDEAL
    from tasks.evaluate_acquisition import EvaluationConfig
    return EvaluationConfig(device=args.eval_device, n_turntable=args.eval_turntable, texture_size=args.eval_texture,
                            materials_per_class=args.eval_materials_per_class, seed=args.eval_seed,
                            render_materials=args.eval_render, adaptive=not args.no_adaptive,
                            adaptive_select=args.adaptive_select, adaptive_rows=args.adaptive_rows,
                            adaptive_predictor=args.adaptive_predictor,
                            non_ideal=_non_ideal(args.non_ideal) if args.non_ideal else IDEAL)


def _non_ideal(text: str):
    """``--non-ideal``'s :class:`btfcore.simulate.nonideal.DomeNonIdeality` (bad input raises, naming the option)."""
    from btfcore.simulate.nonideal import parse_non_ideal
    try:
        return parse_non_ideal(text)
    except ValueError as exc:
        raise ValueError(f"--non-ideal {text}: {exc}") from None


def _evaluate(args: argparse.Namespace) -> int:
    from tasks.ingest import btf_error_against_truth
    from tasks.report import json_text
    from tasks.staging import write_file
    from tasks.stores import open_capture_store

    if not args.truth or not args.btf:
        raise ValueError("give --truth SIM and --btf BTF")
    if not open_capture_store(args.truth).has_truth:
        raise ValueError(f"{args.truth} has no ground truth (truth/ group); give a simulated capture store")
    metrics = {"evaluate": args.what, "truth": str(args.truth), "btf": str(args.btf),
               **btf_error_against_truth(args.btf, args.truth)}
    # one file, whole or not at all (kill points file-writing, file-replace); the default is locked only
    # for `evaluate ingest`, the one that writes it
    write_file(args.report or "report.json", lambda tmp: tmp.write_text(json_text(metrics)))
    print(json.dumps(metrics, indent=2))
    return 0


def _schedule(args: argparse.Namespace) -> int:
    from flows.schedule import serve_build_db

    serve_build_db(args.db, args.out, args.cron, cluster=args.cluster, classes=args.classes, name=args.name)
    return 0


def _deploy(args: argparse.Namespace) -> int:
    from flows.schedule import register

    result = register(args.file, pool=args.pool, names=args.name)
    print(json.dumps(result, indent=2))
    for command in result["worker_commands"]:
        say(f"btf deploy: a worker in this project's environment runs them: {command}")
    return 0


def _cluster(args: argparse.Namespace) -> int:
    from flows.runtime import cluster_spec

    print(cluster_spec(args.profile), end="")
    return 0


def _validate(args: argparse.Namespace) -> int:
    from tasks.integrity import CHECKSUM_NOTE, open_any_store, store_kind, unchecked_arrays, verify_store
    from tasks.model import SCHEMA_NAME as MODEL_SCHEMA
    from tasks.model_validate import validate_model_store
    from tasks.stores import validate_capture_store
    from tasks.stores.btf import SCHEMA_NAME as BTF_SCHEMA
    from tasks.stores.btf import validate_btf_store
    from tasks.stores.measurement import SCHEMA_NAME as MEASUREMENT_SCHEMA
    from tasks.stores.measurement import validate_measurement_store

    validators = {BTF_SCHEMA: validate_btf_store, MEASUREMENT_SCHEMA: validate_measurement_store,
                  MODEL_SCHEMA: validate_model_store}
    failed = 0
    for path in args.stores:
        try:
            group, opened = open_any_store(path)             # a build-db folder: its model.zarr
        except (FileNotFoundError, ValueError):
            group, opened = None, path                       # validate_capture_store says what is there
        validate = validators.get(store_kind(group) if group is not None else None, validate_capture_store)
        lines: list[str] = []
        for problem in validate(opened, require_complete=not args.allow_incomplete):
            if args.deep and (problem.index or "").startswith("chunk "):
                continue                                     # --deep names each of these chunks below
            where = f"[{problem.index}]" if problem.index else ""
            lines.append(f"{problem.array}{where}: expected {problem.expected}, found {problem.found}. "
                         f"{problem.hint}")
        if group is not None and args.deep:                  # damaged chunks, and NaN/Inf in float arrays
            lines += [f"array {p.array}, chunk {p.chunk}: {p.problem}; {p.hint}"
                      for p in verify_store(group, finite=True)]
        notes = [CHECKSUM_NOTE] if group is not None and unchecked_arrays(group) else []
        if lines:
            failed += 1
            print(f"{path}: {len(lines)} problem(s)")
        else:
            print(f"{path}: valid")
        for line in lines + [f"note: {n}" for n in notes]:
            print(f"  {line}")
    return EXIT_BAD_INPUT if failed else 0


# --------------------------------------------------------------------------- checks before the cluster starts


def _prepare_simulate(args: argparse.Namespace, prepared: dict) -> None:
    from tasks.simulate import check_outputs

    prepared["config"] = _simulation_config(args)
    check_outputs(prepared["config"], args.out, args.overwrite)


def _evaluate_on_cluster(args: argparse.Namespace) -> bool:
    return args.what in ("acquisition", "superres")


def _prepare_evaluate(args: argparse.Namespace, prepared: dict) -> None:
    # the evaluation's scale is checked before a cluster starts
    prepared["config"] = superres_evaluation_config(args) if args.what == "superres" else _evaluation_config(args)


def _evaluate_flow(args: argparse.Namespace, address: str, prepared: dict) -> dict:
    flow = evaluate_superres_flow if args.what == "superres" else _evaluate_acquisition_flow
    return flow(args, address, prepared)


def _prepare_reconstruct(args: argparse.Namespace, prepared: dict) -> None:
    from tasks.radiometric import load_calibration
    from tasks.reconstruct import ReconstructSettings, check_inputs

    prepared["config"] = ReconstructSettings(cls=args.cls, basis=args.basis, method=args.method, lam=args.lam,
                                             k=args.k)
    check_inputs(args.measurement, args.model, prepared["config"],
                 load_calibration(args.white, args.white_albedo, args.colour_matrix))


def _prepare_resample(args: argparse.Namespace, prepared: dict) -> None:
    from tasks.resample import check_inputs

    check_inputs(args.btf, args.out, args.sampling, overwrite=args.overwrite)


def _prepare_build_db(args: argparse.Namespace, prepared: dict) -> None:
    from tasks.model import check_model_target, discover, read_class_map

    materials = discover(args.db, read_class_map(args.classes))
    if not args.overwrite:
        check_model_target(Path(args.out) / "model.zarr", materials)


def _prepare_ingest(args: argparse.Namespace, prepared: dict) -> None:
    from tasks.ingest import check_ingest
    from tasks.radiometric import load_calibration

    prepared["calibration"] = load_calibration(args.white, args.white_albedo, args.colour_matrix)
    check_ingest(args.capture, args.out, overwrite=args.overwrite, calibration=prepared["calibration"],
                 keep_roi=args.keep_roi)


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
    report = build_db_flow(args.db, args.out, address, settings, classes=args.classes, progress=not args.no_progress,
                           overwrite=args.overwrite)
    out = Path(args.out).resolve()
    return {"command": "build-db", "out": str(out), "model": report["model"], "trends": report["trends"],
            "report_json": str(out / "report.json"), "report_html": str(out / "report.html")}


def _ingest_flow(args: argparse.Namespace, address: str, prepared: dict) -> dict:
    from flows.ingest import ingest_flow

    return ingest_flow(args.capture, args.out, address, overwrite=args.overwrite, progress=not args.no_progress,
                       white=args.white, white_albedo=args.white_albedo, colour_matrix=args.colour_matrix,
                       calibration=prepared.get("calibration"), keep_roi=args.keep_roi)


def _resample_flow(args: argparse.Namespace, address: str, prepared: dict) -> dict:
    from flows.resample import resample_flow

    return resample_flow(args.btf, args.out, args.sampling, address, overwrite=args.overwrite,
                         progress=not args.no_progress)


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
            add_arguments=arguments.simulate, prepare=_prepare_simulate, flow=_simulate_flow,
            inputs={"plan": "--plan"}),
    Command("demo", help="the main job on the embedded default data",
            description="The main job on the embedded virtual dome: simulate two materials per class on the tiny "
                        "dome (one per class also S-matrix multiplexed) and a white standard, calibrate the LEDs, "
                        "ingest every capture, build the model database (OUT/model), evaluate sparse, multiplexed "
                        "and combined acquisition on a larger simulated database against the thesis' claims "
                        "(OUT/acquisition) and write OUT/report.json and OUT/report.html. With --materials below 12 "
                        "(two per class) the model database and the evaluation are skipped. Re-running resumes or "
                        "reuses finished work.",
            add_arguments=arguments.demo, flow=_demo_flow),
    Command("import-raw", help="import camera raw files (DNG, any LibRaw format) into a capture store",
            description="Read a folder of camera raw files through LibRaw and write a capture store. The manifest "
                        "(CSV with header file,turntable,camera,illumination,exposure[,exposure_time][,role], or a "
                        "JSON list of such objects) maps each file to its place; exposure times missing from it are "
                        "read from the files. Everything is checked first and every problem is listed before any "
                        "work starts.",
            add_arguments=arguments.import_raw, prepare=prepare_import_raw, flow=import_raw_cli_flow,
            inputs={"folder": "FOLDER", "manifest": "--manifest", "calibration": "--calibration"}),
    Command("import-images", help="import 8- or 16-bit TIFF, PNG or JPEG brackets of a non-linear camera",
            description=IMPORT_IMAGES_DESCRIPTION,
            add_arguments=arguments.import_images, prepare=prepare_import_images, flow=import_images_cli_flow,
            inputs={"folder": "FOLDER", "manifest": "--manifest", "calibration": "--calibration",
                    "response": "--response"}),
    Command("ingest", help="capture store -> BTF store (HDR, demosaic, rectify, demultiplex)",
            description="Process every view of a capture store: merge the exposure brackets in the Bayer domain, "
                        "demosaic, rectify the sample to the texture and demultiplex the illumination patterns. "
                        "Writes the BTF store and, beside it, BTF-stem.report.json (with errors against the ground "
                        "truth for simulated captures). Resumes an unfinished run; never overwrites another finished "
                        "output. With --overwrite the new store is built beside it (BTF-stem.partial.zarr) and "
                        "replaces it, with its report, only once complete and checked.",
            add_arguments=arguments.ingest, prepare=_prepare_ingest, flow=_ingest_flow,
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
            add_arguments=arguments.resample, prepare=_prepare_resample, flow=_resample_flow,
            inputs={"btf": "BTF", "sampling": "--sampling"}),
    Command("build-db", help="model database: per-material bases, class and global merges, ABTF bases",
            description="Fit the linear models of a database of ingested BTFs (every finished `btf ingest` store in "
                        "DB): per-material truncated SVDs of log Y, U/Y and V/Y (paper 1), relative-error ALS bases "
                        "of linear RGB (paper 4), eigenspace merges per class and then globally, and per-class 3x3 "
                        "ABTF patch bases. Writes OUT/model.zarr, OUT/report.json (thesis Table 1 from a "
                        "leave-one-out evaluation) and OUT/report.html. A rerun reuses every basis whose inputs did "
                        "not change, so adding a material recomputes only it, its class and the global merge. A "
                        "complete OUT/model.zarr is never changed in place: the build works on a copy beside it "
                        "(model.partial.zarr, hard links to its files) that replaces it once complete, so a failed "
                        "or killed run leaves the old database whole (a rerun resumes the copy).",
            add_arguments=arguments.build_db, prepare=_prepare_build_db, flow=_build_db_flow,
            inputs={"db": "DB", "classes": "--classes"}),
    Command("schedule", help="serve a scheduled deployment (cron) of a database build from this shell",
            description="Serve a Prefect deployment that runs `btf build-db DB --out OUT` on a cron schedule, each "
                        "run on the Dask cluster of --cluster and incremental (only new or changed materials are "
                        "fitted). Needs a Prefect server that stays up: PREFECT_API_URL, else the running `btf "
                        "server` (`btf server start`); cron schedules do not fire on a temporary server. Runs until "
                        "stopped; `btf deploy` registers the same build with a work pool instead.",
            add_arguments=arguments.schedule, run=_schedule, inputs={"db": "DB", "classes": "--classes"}),
    Command("deploy", help="register the Prefect deployments of prefect.yaml with a process work pool",
            description="Register the deployments of prefect.yaml (build-db on a cron schedule, ingest, reconstruct, "
                        "evaluate acquisition; each with its parameters and execution profile) with the Prefect "
                        "API of PREFECT_API_URL, else the running `btf server`, on a process work pool (created if "
                        "missing), and print the `prefect worker start --pool NAME` command that runs them. A "
                        "deployment that exists is updated. Relative paths in its parameters are taken from the "
                        "repository root, where every run starts.",
            add_arguments=arguments.deploy, run=_deploy, inputs={"file": "--file"}, outputs={}),
    Command("export-exr", help="write BTF textures as OpenEXR files",
            description="Write selected (or all) textures of a BTF store (from `btf ingest`) as float32 RGB OpenEXR "
                        "files named lv<row>_t<turntable>_c<camera>_l<light>.exr, with the light and view directions "
                        "in each header. Textures with NaN or Inf texels are refused (the message names the rows and "
                        "counts) before any file is written, unless --keep-nonfinite.",
            add_arguments=arguments.export_exr, run=_export_exr, inputs={"btf": "BTF"}),
    Command("import-btf", help="import a Bonn BTF file (DFMF, FMF, BDI, PVF) into a BTF store",
            description=IMPORT_HELP, raw_description=True, add_arguments=add_import_arguments, prepare=prepare_import,
            flow=import_btf_flow, inputs={"file": "FILE"}),
    Command("export", help="write a BTF store as a Bonn BTF file (DFMF, FMF or BDI)",
            description=EXPORT_HELP, raw_description=True, add_arguments=add_export_arguments, run=run_export,
            inputs={"store": "STORE", "basis": "--basis"}),
    Command("evaluate", help="measure a result against the simulator's ground truth",
            description="Compare a result with the ground truth of a simulated capture and print the metrics as "
                        "JSON; they are also written to --report.",
            add_arguments=arguments.evaluate, run=_evaluate, prepare=_prepare_evaluate,
            flow=_evaluate_flow, cluster_when=_evaluate_on_cluster,
            inputs={"btf": "--btf", "db": "DB", "truth": "--truth"},
            outputs={"out": "--out", "report": "--report"}),
    Command("validate", help="check stores and list every problem",
            description="Open each store and print every problem found; exit 2 if any. A capture, BTF, measurement "
                        "or model store (a `btf build-db` folder means its model.zarr) is validated against its "
                        "schema (docs/capture-store.md, btf-store.md, measurement-store.md, model-database.md), a "
                        "capture store including a chunk file for every bracket marked written. --deep also reads "
                        "every chunk of every array and names each corrupt, truncated or missing one and each that "
                        "holds NaN or Inf values (array, chunk index and count). A store written before chunk "
                        "checksums were added is reported as such: --deep can then only find unreadable chunks, not "
                        "changed bytes.",
            add_arguments=arguments.validate, run=_validate, outputs={}),
    Command("reconstruct", help="measurement store + model basis -> full BTF store",
            description="Reconstruct a full BTF from a measurement store (`btf ingest` of a sparse or multiplexed "
                        "plan capture) or a demultiplexed BTF store, with a class basis of the model database (`btf "
                        "build-db`). The solve operator is built once from the basis and the measurement matrix G "
                        "and applied band of texels by band in one Dask graph. The output is built beside --out "
                        "(BTF-stem.partial.zarr) and renamed into place once complete; BTF-stem.report.json holds "
                        "the settings and, for a simulated capture, the errors against the ground truth. Log bases "
                        "need single-light measurements; multiplexed ones use --basis als --method direct "
                        "(docs/measurement-store.md).",
            add_arguments=arguments.reconstruct, prepare=_prepare_reconstruct, flow=_reconstruct_flow,
            inputs={"measurement": "MEASUREMENT", "model": "--model", "white": "--white",
                    "colour_matrix": "--colour-matrix"}),
    Command("sample", help="sparse sampling: which light/view pairs to measure (kappa-optimised)",
            description=SAMPLE_HELP, raw_description=True, add_arguments=add_sample_arguments, run=run_sample,
            inputs={"model": "--model"}),
    Command("plan", help="acquisition plan (JSON + CSV) and its predicted acquisition time",
            description=PLAN_HELP, raw_description=True, add_arguments=add_plan_arguments, run=run_plan,
            inputs={"samples": "--samples"}),
    Command("acquire", help="adaptive capture until a predicted error target (--adaptive)", description=ACQUIRE_HELP,
            raw_description=True, add_arguments=add_acquire_arguments, run=run_acquire,
            inputs={"truth": "--truth", "model": "--model"}),
    Command("render", help="render a BTF store on a sphere, cylinder or plane to a PNG",
            description=RENDER_HELP, raw_description=True, add_arguments=add_render_arguments, run=run_render,
            inputs={"btf": "BTF", "env": "--env"}),
    Command("superres", help="super-resolution: train the per-image CNN, or apply it to a BTF store at 2x",
            description=SUPERRES_HELP, raw_description=True, add_arguments=add_superres_arguments,
            run=run_superres_train, prepare=prepare_superres, flow=superres_apply_flow,
            cluster_when=superres_on_cluster, inputs={"btf": "BTF", "model": "--model"}),
    Command("cluster", help="print the cluster resource of an execution profile (kubernetes: for kubectl)",
            description="`btf cluster spec PROFILE` prints the DaskCluster resource that a kubernetes execution "
                        "profile creates (the dask-kubernetes operator's spec, with the worker environment), as YAML "
                        "that `kubectl apply -f -` takes (docs/clusters.md). The profile is checked first.",
            add_arguments=arguments.cluster, run=_cluster, inputs={"profile": "PROFILE"}, outputs={}),
    Command("server", help="start, stop or show a local Prefect server that later commands reuse",
            description=SERVER_HELP, add_arguments=add_server_arguments, run=run_server, outputs={}),
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


def _absolute_paths(args: argparse.Namespace, command: Command) -> None:
    """Make the input paths that exist and every output path of ``args`` absolute: the cluster's workers
    open them, and a ``btf server``'s workers (or a batch system's) do not run in the folder the command
    was typed in. An input that does not exist (or a keyword such as ``--sampling ubo2014``) keeps what
    the user typed, for the command's own message."""
    def absolute(value: Any, output: bool) -> Any:
        if not isinstance(value, str) or not value or "://" in value or not (output or os.path.exists(value)):
            return value
        return os.path.abspath(value)

    for table, output in ((command.inputs, False), (command.outputs, True)):
        for dest in table:
            value = getattr(args, dest, None)
            setattr(args, dest, [absolute(v, output) for v in value] if isinstance(value, list)
                    else absolute(value, output))


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
    _absolute_paths(args, command)
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
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.quiet and (args.verbose or args.log_level):
        parser.error("--quiet shows errors only: give it without --verbose and --log-level")
    args.no_progress = args.no_progress or args.quiet
    if COMMANDS[args.command].on_cluster(args):  # a btf server's runner has the imports done: run there
        from flows.server import forward

        code = forward(list(sys.argv[1:] if argv is None else argv),
                       detail_flags=bool(args.verbose or args.log_level or args.quiet))
        if code is not None:
            return code
    with _library_log_level(args):
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


@contextlib.contextmanager
def _library_log_level(args: argparse.Namespace) -> Iterator[None]:
    """Prefect's and Dask's log level for ``--log-level``, ``--verbose`` (INFO) or ``--quiet`` (ERROR).

    Set as ``PREFECT_LOGGING_LEVEL`` and ``DASK_LOGGING__DISTRIBUTED``, which Prefect and Dask read when
    imported (after this) and :func:`flows.runtime.quiet_logs` and the workers follow; without one of
    the options they stay as the user set them (default WARNING). Restored afterwards (a run in a test).
    """
    level = args.log_level or ("INFO" if args.verbose else "ERROR" if args.quiet else None)
    names = ("PREFECT_LOGGING_LEVEL", "DASK_LOGGING__DISTRIBUTED")
    saved = {name: os.environ.get(name) for name in names}
    if level:
        os.environ.update({"PREFECT_LOGGING_LEVEL": level, "DASK_LOGGING__DISTRIBUTED": level.lower()})
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def _label(args: argparse.Namespace) -> str:
    """``btf ingest``, ``btf evaluate acquisition``: the command as its info lines name it."""
    return " ".join(["btf", args.command] + ([args.what] if isinstance(getattr(args, "what", None), str) else []))


def _starting_line(label: str, profile: Any) -> str:
    """What a computing command starts once its inputs are checked: the Prefect API and the Dask cluster
    of ``profile`` (a :class:`flows.runtime.Profile`), or the ``btf server``'s where one is recorded."""
    from flows.clusters import planned
    from flows.server import recorded_server_url

    url = os.environ.get("PREFECT_API_URL") or profile.prefect.get("api_url")
    server = None if url else recorded_server_url()
    kind, size = profile.kind, planned(profile)
    if server and kind == "local":
        return (f"{label}: connecting to the btf server's Prefect API at {server} and its local "
                f"Dask cluster (or starting one: {size}; profile {profile.path}) ...")
    api = (f"connecting to the Prefect API at {url or server} and" if url or server
           else "starting a local Prefect API and")
    if kind == "address":
        return f"{label}: {api} connecting to the Dask scheduler {size} (profile {profile.path}) ..."
    api = f"{api} starting" if url or server else api
    return f"{label}: {api} a {kind} Dask cluster ({size}; profile {profile.path}) ..."


def _main(args: argparse.Namespace) -> int:
    command = COMMANDS[args.command]
    info = command.on_cluster(args) and not args.quiet
    if info:                           # within a second of the start, before anything slow is imported
        forked = (" (in a process forked by the btf server's command runner, imports done)"
                  if os.environ.get(CHILD_ENV) else "")
        say(f"{_label(args)}: checking the inputs{forked} ...")
    from tasks.locks import output_locks

    outputs = [p for p in _io_args(args)[0].values() if "://" not in p]  # not fsspec URLs
    with output_locks(outputs, _label(args)):  # one writer per output (tasks.locks)
        prepared = _preflight(args, command)
        if not command.on_cluster(args):
            return command.run(args)  # in this process: sample, plan, render, validate, export-exr, ...

        summary = run_on_cluster(args, command, prepared, info)
    print(json.dumps(summary, indent=2))
    return 0


def run_on_cluster(args: argparse.Namespace, command: Command, prepared: dict, info: bool = True) -> dict[str, Any]:
    """Start the run's Prefect API and Dask cluster (:func:`flows.runtime.runtime`), run ``command``'s flow
    on them and return its summary with the seconds it took; ``info`` prints the starting and ready
    lines. The one place a command line runs on a cluster: ``btf`` and the deployments of
    :mod:`flows.deploy` both call it."""
    from flows.clusters import describe
    from flows.runtime import runtime

    if info:
        say(_starting_line(_label(args), prepared["profile"]))
    start = time.perf_counter()
    with runtime(prepared["profile"]) as (profile, url, client):
        if info:
            whose = " (the btf server's)" if client.cluster is None and profile.kind == "local" else ""
            say(f"{_label(args)}: Prefect API {url} and Dask cluster {client.scheduler.address}{whose} ready after "
                f"{time.perf_counter() - start:.1f} s ({describe(profile, client)})")
        summary = command.flow(args, client.scheduler.address, prepared)
    return {**summary, "seconds": round(time.perf_counter() - start, 2)}


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
