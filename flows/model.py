"""Prefect flow of ``btf build-db``: the model database of a folder of ingested BTFs (docs/architecture.md,
"Stages", stage 8)."""

from __future__ import annotations

from typing import Any

from prefect import flow, task
from prefect.cache_policies import NO_CACHE

from flows.runtime import RETRY_ONCE
from tasks.model import ModelSettings


# Retrying the stage resumes it: bases whose key is stored are reused; bad input is not retried.
@task(name="model-database", **RETRY_ONCE, cache_policy=NO_CACHE)
def build_stage(db: str, out: str, scheduler_address: str, settings: ModelSettings,
                class_map: dict[str, str] | None, progress: bool, overwrite: bool = False) -> dict[str, Any]:
    from distributed import Client

    from flows.progress import progress_bars
    from tasks.model import build_database

    units = {"material bases": "material", "leave-one-out": "material"}
    with progress_bars(progress, units) as bar, Client(scheduler_address, set_as_default=False) as client:
        return build_database(db, out, client, settings=settings, class_map=class_map, progress=bar,
                              overwrite=overwrite)


@task(name="model-report", cache_policy=NO_CACHE)
def model_report_stage(out: str, summary: dict[str, Any], settings: ModelSettings,
                       links: list[tuple[str, str]] | None = None) -> dict[str, Any]:
    """The build's ``report.json`` and ``report.html``, linking ``links`` (default: the demo's reports that exist)."""
    from tasks.model_report import model_report

    return model_report(out, summary, settings, links)


@flow(name="btf-build-db", log_prints=False)
def build_db_flow(db: str, out: str, scheduler_address: str, settings: ModelSettings = ModelSettings(),
                  classes: str | None = None, progress: bool = True, overwrite: bool = False) -> dict[str, Any]:
    """Ingested BTF stores in ``db`` -> ``out/model.zarr`` with ``out/report.json`` and ``report.html``.

    Materials are grouped by the class in their store (``classes``: a JSON
    file mapping store names to classes, for real captures). Per-material
    bases run in parallel, then the class merges, the global merge, the
    per-class ABTF bases and the leave-one-out evaluation. A rerun reuses
    every basis whose inputs did not change.
    """
    from tasks.model import read_class_map

    summary = build_stage(db, out, scheduler_address, settings, read_class_map(classes), progress, overwrite)
    return model_report_stage(out, summary, settings)
