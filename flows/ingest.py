"""Prefect flows of the ingest side: ``btf import-raw`` (raw files -> capture store)."""

from __future__ import annotations

from typing import Any

from prefect import flow, task
from prefect.cache_policies import NO_CACHE

from btfcore.simulate.devices import Device
from tasks.ingest_raw import import_raw, plan_raw_import


@task(name="import-raw-files", retries=1, cache_policy=NO_CACHE)
def import_raw_stage(folder: str, manifest: str, device: Device, out: str, scheduler_address: str,
                     overwrite: bool) -> dict[str, Any]:
    from distributed import Client

    plan = plan_raw_import(folder, manifest)  # every problem listed before any work
    with Client(scheduler_address, set_as_default=False) as client:
        store = import_raw(plan, device, out, client, overwrite=overwrite,
                           provenance={"manifest": str(manifest), "folder": str(folder)})
    return {"store": str(out), "shape": list(plan.shape), "frame_shape": list(plan.frame_shape),
            "bayer_pattern": plan.bayer_pattern, "complete": store.complete}


@flow(name="btf-import-raw", log_prints=False)
def import_raw_flow(folder: str, manifest: str, device: Device, out: str, scheduler_address: str,
                    overwrite: bool = False) -> dict[str, Any]:
    """Validate a folder of camera raw files and its manifest, then write a capture store."""
    return import_raw_stage(folder, manifest, device, out, scheduler_address, overwrite)
