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

from flows.progress import progress_bar
from tasks.report import simulation_report, write_json
from tasks.simulate import SimulationConfig, simulate_database


# Retrying the stage resumes it: finished views are skipped, pending ones re-run.
@task(name="simulate-captures", retries=1, cache_policy=NO_CACHE)
def simulate_stage(config: SimulationConfig, out_dir: str, scheduler_address: str, overwrite: bool,
                   progress: bool) -> dict[str, Any]:
    from distributed import Client

    bar, update = progress_bar(f"simulate {config.device}", progress)
    with bar, Client(scheduler_address, set_as_default=False) as client:
        result = simulate_database(config, out_dir, client, overwrite=overwrite, progress=update)
    return {"stores": result.stores, "views_rendered": result.views_done,
            "views_skipped": result.views_skipped, "seconds": round(result.seconds, 3)}


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
    position, 2,178 light/view pairs (``btf evaluate acquisition`` defaults to two, 4,356), so that the
    demo stays within three minutes (docs/decisions.md). With fewer than two materials per class the
    model database and the evaluation are skipped.
    """
    from flows.ingest import calibration_stage, ingest_database_stage
    from flows.model import build_stage, model_report_stage
    from tasks.model import ModelSettings

    start = time.perf_counter()
    out = Path(out_dir)
    config = SimulationConfig(device="tiny", n_materials=n_materials, seed=seed)
    stage = simulate_stage(config, str(out / "database"), scheduler_address, False, progress)
    white_config = SimulationConfig(device="tiny", n_materials=1, seed=seed, classes=("white-standard",))
    white = simulate_stage(white_config, str(out / "white-standard"), scheduler_address, False, progress)
    ingest_database_stage(white["stores"], str(out / "btf-white"), scheduler_address, progress)
    calibration = calibration_stage(str(out / "btf-white" / Path(white["stores"][0]).name), 0.99, None)
    ingest = ingest_database_stage(stage["stores"], str(out / "btf"), scheduler_address, progress, calibration)
    n_classes = len(config.classes)
    mux_config = SimulationConfig(device="tiny", n_materials=min(n_materials, n_classes), seed=seed,
                                  illumination="multiplexed")
    mux = simulate_stage(mux_config, str(out / "database-multiplexed"), scheduler_address, False, progress)
    ingest_mux = ingest_database_stage(mux["stores"], str(out / "btf-multiplexed"), scheduler_address, progress,
                                       calibration)
    run = {"command": "demo", "config": config.to_json(), "out_dir": str(out.resolve()),
           "stages": {"simulate": {k: v for k, v in stage.items() if k != "stores"},
                      "ingest": {"seconds": round(sum(r["seconds"] for r in ingest.values()), 3)},
                      "simulate multiplexed": {k: v for k, v in mux.items() if k != "stores"},
                      "ingest multiplexed": {"seconds": round(sum(r["seconds"] for r in ingest_mux.values()), 3)}},
           "radiometric": calibration.info, "ingest": ingest, "ingest_multiplexed": ingest_mux,
           "ingest_btf": {Path(store).stem: str(out / "btf" / Path(store).name) for store in stage["stores"]}}
    if n_materials >= 2 * n_classes:         # leave-one-out needs two materials per class
        start_model = time.perf_counter()
        model = model_report_stage(str(out / "model"), build_stage(str(out / "btf"), str(out / "model"),
                                   scheduler_address, ModelSettings(), None, progress), ModelSettings())
        run["stages"]["build-db"] = {"seconds": round(time.perf_counter() - start_model, 3)}
        run["model"] = {"report_html": str(out / "model" / "report.html"), "ks": model["ks"],
                        "table_1": model["table_1"], "trends": model["trends"], "k": model["k"]}
    if evaluate_acquisition and n_materials >= 2 * n_classes:    # the demo's full run; --materials 2 skips it
        from flows.evaluate_acquisition import evaluate_acquisition_flow
        from tasks.evaluate_acquisition import EvaluationConfig

        start_eval = time.perf_counter()
        acquisition = evaluate_acquisition_flow(str(out / "acquisition-database"), str(out / "acquisition"),
                                                scheduler_address, EvaluationConfig(seed=seed, n_turntable=1),
                                                progress)
        run["stages"]["evaluate acquisition"] = {"seconds": round(time.perf_counter() - start_eval, 3)}
        run["acquisition"] = {"report_html": str(out / "acquisition" / "report.html"),
                              "scale": acquisition["scale"], "claims": acquisition["claims"]}
    report = report_stage(config, out_dir, stage["stores"], run)
    report["seconds"] = round(time.perf_counter() - start, 3)
    write_json(Path(out_dir) / "report.json", report)
    return report
