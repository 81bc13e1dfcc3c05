"""Prefect flows of the virtual dome: ``btf simulate`` and ``btf demo``.

Flows only wire stages together. Each stage is one Prefect task that builds
one Dask computation over all chunks on the cluster whose scheduler address it
is given: one Prefect task per chunk would flood the Prefect database
(docs/architecture.md, "Execution").
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from prefect import flow, task
from prefect.cache_policies import NO_CACHE

from flows.progress import progress_bar, say
from tasks.report import reused_text, simulation_report, write_json
from tasks.simulate import SimulationConfig, simulate_database


# Retrying the stage resumes it: finished views are skipped, pending ones re-run.
@task(name="simulate-captures", retries=1, cache_policy=NO_CACHE)
def simulate_stage(config: SimulationConfig, out_dir: str, scheduler_address: str, overwrite: bool,
                   progress: bool, name: str | None = None) -> dict[str, Any]:
    """Simulate the captures of ``config`` (``name``: the progress display's, by default
    ``"simulate DEVICE: N materials"``)."""
    from distributed import Client

    name = name or f"simulate {config.device}: {config.n_materials} material{'s' * (config.n_materials != 1)}"
    bar, update = progress_bar(name, progress, unit="view")
    with bar, Client(scheduler_address, set_as_default=False) as client:
        result = simulate_database(config, out_dir, client, overwrite=overwrite, progress=update)
    return {"stores": result.stores, "views_rendered": result.views_done,
            "views_skipped": result.views_skipped, "seconds": round(result.seconds, 3)}


@task(name="ingest-floors", cache_policy=NO_CACHE)
def floors_stage(config: SimulationConfig, stores: list[str], record: str, scheduler_address: str,
                 progress: bool) -> dict[str, Any]:
    """The ingest errors' floors of the demo's single-LED captures (:func:`tasks.floors.ingest_floors`)."""
    from distributed import Client

    from tasks.floors import ingest_floors

    bar, update = progress_bar("ingest floors: noise-free and full-RGB sensors", progress, unit="material")
    with bar, Client(scheduler_address, set_as_default=False) as client:
        return ingest_floors(config, stores, client, record, progress=update)


@task(name="simulation-report", cache_policy=NO_CACHE)
def report_stage(config: SimulationConfig, report_dir: str, stores: list[str], run: dict[str, Any]) -> dict[str, Any]:
    return simulation_report(report_dir, config.build_device(), stores, run)


@flow(name="btf-simulate", log_prints=False)
def simulate_flow(config: SimulationConfig, out_dir: str, scheduler_address: str, overwrite: bool = False,
                  progress: bool = True, command: str = "simulate", report_dir: str | None = None) -> dict[str, Any]:
    """Simulate a database of capture stores into ``out_dir`` and write its report.

    The report (``report.json``, ``report.html``) goes to ``report_dir``, by
    default ``out_dir``.
    """
    report_dir = report_dir or out_dir
    start = time.perf_counter()
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    stage = simulate_stage(config, out_dir, scheduler_address, overwrite, progress)
    run = {"command": command, "config": config.to_json(), "out_dir": str(Path(out_dir).resolve()),
           "stages": {"simulate": {k: v for k, v in stage.items() if k != "stores"}}}
    report_start = time.perf_counter()
    report = report_stage(config, report_dir, stage["stores"], run)
    report["stages"]["report"] = {"seconds": round(time.perf_counter() - report_start, 3)}
    report["seconds"] = round(time.perf_counter() - start, 3)
    write_json(Path(report_dir) / "report.json", report)
    return report


@task(name="demo-model-database", cache_policy=NO_CACHE)
def model_database_stage(btf_dir: str, model_dir: str, scheduler_address: str, progress: bool,
                         evaluate_acquisition: bool = True) -> tuple[dict[str, Any], dict[str, list[int]]]:
    """The demo's model database (``btf build-db`` and its report) unless a finished one of the same key
    is there (:func:`tasks.evaluate_acquisition.reuse.model_database_key`): what the demo's report shows of
    it, and what was reused."""
    from flows.model import build_stage, model_report_stage
    from tasks.evaluate_acquisition.reuse import model_database_key, read_record, write_record
    from tasks.model import ModelSettings
    from tasks.model_report import RELATED_REPORTS

    settings, record_path = ModelSettings(), Path(model_dir) / "demo.json"
    key = model_database_key(btf_dir, model_dir, settings)
    record = read_record(record_path, key) if key else None
    if record is not None:
        return record["model"], {"bases": [record["bases"]] * 2, "leave_one_out_table": [1, 1]}
    build = build_stage.fn(btf_dir, model_dir, scheduler_address, settings, None, progress)
    links = list(RELATED_REPORTS[:2 if evaluate_acquisition else 1])        # the reports the demo writes next
    model = model_report_stage.fn(model_dir, build, settings, links)
    fitted = [how for fit in build["fits"] for how in fit["bases"].values()]
    record = write_record(record_path, model_database_key(btf_dir, model_dir, settings), {
        "model": {k: model[k] for k in ("ks", "table_1", "trends", "k")}, "bases": len(fitted)})
    return record["model"], {"bases": [fitted.count("reused"), len(fitted)], "leave_one_out_table": [0, 1]}


@flow(name="btf-demo", log_prints=False)
def demo_flow(out_dir: str, scheduler_address: str, seed: int = 0, n_materials: int = 12,
              progress: bool = True, evaluate_acquisition: bool = True) -> dict[str, Any]:
    """The main job on the embedded default: simulate a small database (single-LED, and
    S-matrix multiplexed for one material per class) and a white standard, calibrate the LEDs
    on the white standard, ingest every capture back to a calibrated BTF, build the model
    database from the single-LED BTFs (``out/model``), and report against the ground truth.

    It ends with the acquisition evaluation (``btf evaluate acquisition``: sparse, multiplexed and
    combined acquisition reconstructed leave-one-out against the truth of a second, larger simulated
    database, ``out/acquisition``), whose thesis claims the report shows: bonn-dome2 at one turntable
    position, 2,178 light/view pairs (``btf evaluate acquisition`` defaults to two, 4,356), and without
    the adaptive-capture loop (``--no-adaptive``), so that the demo stays near three minutes (docs/decisions.md). With fewer than two materials per class the
    model database and the evaluation are skipped.
    """
    from flows.ingest import calibration_stage, ingest_database_stage

    start = time.perf_counter()
    out = Path(out_dir)
    config = SimulationConfig(device="tiny", n_materials=n_materials, seed=seed)
    stage = simulate_stage(config, str(out / "database"), scheduler_address, False, progress)
    stages = {"simulate": _said("simulate", _simulated(stage), progress)}
    white_config = SimulationConfig(device="tiny", n_materials=1, seed=seed, classes=("white-standard",))
    white = simulate_stage(white_config, str(out / "white-standard"), scheduler_address, False, progress,
                           name="simulate tiny: white standard")
    stages["simulate white standard"] = _said("simulate white standard", _simulated(white), progress)
    ingest_white = ingest_database_stage(white["stores"], str(out / "btf-white"), scheduler_address, progress,
                                         name="ingest: white standard")
    stages["ingest white standard"] = _said("ingest white standard", _ingested(ingest_white), progress)
    calibration = calibration_stage(str(out / "btf-white" / Path(white["stores"][0]).name), 0.99, None)
    ingest = ingest_database_stage(stage["stores"], str(out / "btf"), scheduler_address, progress, calibration,
                                   name=f"ingest: {n_materials} materials, calibrated")
    stages["ingest"] = _said("ingest", _ingested(ingest), progress)
    floors = floors_stage(config, stage["stores"], str(out / "floors.json"), scheduler_address, progress)
    stages["ingest floors"] = _said("ingest floors", {k: v for k, v in floors.items() if k != "floors"}, progress)
    n_classes = len(config.classes)
    mux_config = SimulationConfig(device="tiny", n_materials=min(n_materials, n_classes), seed=seed,
                                  illumination="multiplexed")
    mux = simulate_stage(mux_config, str(out / "database-multiplexed"), scheduler_address, False, progress,
                         name=f"simulate tiny: S-matrix, {mux_config.n_materials} materials")
    stages["simulate multiplexed"] = _said("simulate multiplexed", _simulated(mux), progress)
    ingest_mux = ingest_database_stage(mux["stores"], str(out / "btf-multiplexed"), scheduler_address, progress,
                                       calibration, name=f"ingest: S-matrix, {mux_config.n_materials} materials")
    stages["ingest multiplexed"] = _said("ingest multiplexed", _ingested(ingest_mux), progress)
    run = {"command": "demo", "config": config.to_json(), "out_dir": str(out.resolve()), "stages": stages,
           "radiometric": calibration.info, "ingest": ingest, "ingest_multiplexed": ingest_mux,
           "ingest_floors": floors["floors"],
           "ingest_btf": {Path(store).stem: str(out / "btf" / Path(store).name) for store in stage["stores"]}}
    if n_materials >= 2 * n_classes:         # leave-one-out needs two materials per class
        start_model = time.perf_counter()
        model, reused = model_database_stage(str(out / "btf"), str(out / "model"), scheduler_address, progress,
                                             evaluate_acquisition)
        stages["build-db"] = _said("build-db", {"seconds": round(time.perf_counter() - start_model, 3),
                                                "reused": reused}, progress)
        run["model"] = {"report_html": str(out / "model" / "report.html"), **model}
    classes = {Path(p).stem.split("-", 1)[-1] for p in stage["stores"]}
    if {"leather", "cloth"} <= classes:      # super-resolution on the demo's first leather and cloth
        run["superres"] = _demo_superres(out, stage["stores"], scheduler_address, seed, progress)
        run["stages"]["super-resolution"] = {"seconds": run["superres"].pop("seconds"),
                                             "reused": run["superres"].pop("reused")}
    if evaluate_acquisition and n_materials >= 2 * n_classes:    # the demo's full run; --materials 2 skips it
        from flows.evaluate_acquisition import evaluate_acquisition_flow
        from tasks.evaluate_acquisition import EvaluationConfig

        start_eval = time.perf_counter()
        acquisition = evaluate_acquisition_flow(str(out / "acquisition-database"), str(out / "acquisition"),
                                                scheduler_address,
                                                EvaluationConfig(seed=seed, n_turntable=1, adaptive=False),
                                                progress)
        run["stages"]["evaluate acquisition"] = {"seconds": round(time.perf_counter() - start_eval, 3),
                                                 "reused": acquisition["reused"]}
        run["acquisition"] = {"report_html": str(out / "acquisition" / "report.html"),
                              "scale": acquisition["scale"], "claims": acquisition["claims"]}
    report = report_stage(config, out_dir, stage["stores"], run)
    report["seconds"] = round(time.perf_counter() - start, 3)
    write_json(Path(out_dir) / "report.json", report)
    return report


def _demo_superres(out: Path, stores: list[str], scheduler_address: str, seed: int, progress: bool) -> dict[str, Any]:
    """``btf evaluate superres`` at the demo's scale on its own first leather and cloth, each training its own
    networks (a quarter of its rows, a few epochs; docs/super-resolution.md)."""
    from flows.superres import evaluate_superres_flow
    from tasks.evaluate_superres import DEMO_SUPERRES

    start = time.perf_counter()
    first = {}
    for p in stores:                                     # the first leather and the first cloth
        first.setdefault(Path(p).stem.split("-", 1)[-1], p)
    captures = [first[c] for c in ("leather", "cloth") if c in first]
    summary = evaluate_superres_flow(str(out / "superres"), scheduler_address,
                                     DEMO_SUPERRES.with_seed(seed), progress, captures=captures)
    reused = sum(bool(rec.get("reused")) for rec in summary["materials"])
    return {"report_html": str(out / "superres" / "report.html"), "means": summary["means"],
            "verdicts": summary["verdicts"], "normalisation": summary["normalisation"],
            "figures": [dict(f, file=f"superres/{f['file']}") for rec in summary["materials"] for f in rec["figures"]],
            "seconds": round(time.perf_counter() - start, 3),
            "reused": {"materials": [reused, len(summary["materials"])]}}


def _said(name: str, figures: dict[str, Any], progress: bool) -> dict[str, Any]:
    """A stage's figures for the demo's report, after one line saying what it reused (with ``progress``)."""
    if progress:
        say(f"{name}: reused {reused_text(figures['reused'])}")
    return figures


def _simulated(stage: dict[str, Any]) -> dict[str, Any]:
    """A simulate stage's figures for the demo's report, with the views it reused from an earlier run."""
    done = stage["views_rendered"] + stage["views_skipped"]
    return {**{k: v for k, v in stage.items() if k != "stores"}, "reused": {"views": [stage["views_skipped"], done]}}


def _ingested(results: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """An ingest stage's figures (over all its stores) for the demo's report, with the views it reused."""
    skipped = sum(r.get("views_skipped", 0) for r in results.values())
    total = skipped + sum(r.get("views_processed", 0) for r in results.values())
    return {"seconds": round(sum(r["seconds"] for r in results.values()), 3), "reused": {"views": [skipped, total]}}
