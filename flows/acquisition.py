"""Prefect flows of the acquisition side: ``btf reconstruct`` (measurement + model -> BTF).

``btf simulate --plan`` runs :func:`flows.simulate.simulate_flow` with a plan in
its config, and ``btf ingest`` of a plan capture writes a measurement store
(:mod:`tasks.measurement`); this flow turns that into a full BTF. Flows only
wire stages; each stage is one Prefect task that builds one Dask graph.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from prefect import flow, task
from prefect.cache_policies import NO_CACHE

from flows.runtime import RETRY_ONCE
from tasks.reconstruct import ReconstructSettings


@task(name="reconstruct-bands", **RETRY_ONCE, cache_policy=NO_CACHE)
def reconstruct_stage(measurement: str, model: str, out: str, settings: ReconstructSettings, scheduler_address: str,
                      overwrite: bool, progress: bool, calibration=None) -> dict[str, Any]:
    """Build the solve operator and apply it over every texel band (one Dask graph); staged output."""
    from distributed import Client

    from flows.progress import progress_bar
    from tasks.reconstruct import reconstruct_store

    bar, update = progress_bar("reconstruct", progress, unit="band")
    with bar, Client(scheduler_address, set_as_default=False) as client:
        return reconstruct_store(measurement, model, out, settings, client, overwrite=overwrite,
                                 calibration=calibration, progress=update)


@task(name="reconstruct-evaluation", cache_policy=NO_CACHE)
def reconstruct_evaluation(measurement: str, out: str) -> dict[str, Any]:
    """Errors of the reconstruction against the simulated capture's ground truth (when there is one)."""
    import zarr

    from tasks.ingest import btf_error_against_truth
    from tasks.stores import open_capture_store

    capture = zarr.open_group(measurement, mode="r", zarr_format=3).attrs.get("source")
    try:
        store = open_capture_store(capture) if capture and Path(capture).exists() else None
    except ValueError:
        return {}
    if store is None or not store.has_truth:
        return {}
    return {"capture": capture, **btf_error_against_truth(out, store)}


@flow(name="btf-reconstruct", log_prints=False)
def reconstruct_flow(measurement: str, model: str, out: str, scheduler_address: str, settings: ReconstructSettings,
                     overwrite: bool = False, progress: bool = True, white: str | None = None,
                     white_albedo: float = 0.99, colour_matrix: str | None = None) -> dict[str, Any]:
    """Reconstruct a full BTF store from a measurement store and a class basis of a model store;
    with ``white`` / ``colour_matrix`` radiometrically corrected as ``btf ingest`` corrects.

    Writes ``out`` and ``<out stem>.report.json`` beside it (settings, operator
    condition, and for a simulated capture the relative errors against its
    ground truth).
    """
    from tasks.report import write_json

    start = time.perf_counter()
    from flows.ingest import calibration_stage

    calibration = calibration_stage(white, white_albedo, colour_matrix)
    stage = reconstruct_stage(measurement, model, out, settings, scheduler_address, overwrite, progress, calibration)
    report = {"report": "btf-reconstruct", "input": measurement, "model": model, "out": out,
              "settings": {"class": settings.cls, "basis": settings.basis, "method": settings.method,
                           "lam": settings.lam, "k": settings.k},
              "radiometric": None if calibration is None else calibration.info,
              "stages": {"reconstruct": stage}, "errors_against_truth": reconstruct_evaluation(measurement, out)}
    report["seconds"] = round(time.perf_counter() - start, 3)
    write_json(Path(out).with_name(Path(out).stem + ".report.json"), report)
    return report
