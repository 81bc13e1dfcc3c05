"""Prefect flow of ``btf resample``: a BTF store onto a common light x view sampling (docs/architecture.md, "Stages", stage 7)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from prefect import flow, task
from prefect.cache_policies import NO_CACHE

from flows.runtime import RETRY_ONCE
from tasks.report import write_json

#: Share of the resampled rows outside the measured hull above which the report warns.
OUTSIDE_HULL_WARN = 0.10


# Retrying the stage resumes it: finished target views are skipped, pending ones re-run; bad input is
# not retried (it would only fail again).
@task(name="resample-views", **RETRY_ONCE, cache_policy=NO_CACHE)
def resample_stage(btf: str, out: str, sampling: str, scheduler_address: str, overwrite: bool,
                   progress: bool) -> dict[str, Any]:
    from distributed import Client

    from flows.progress import progress_bar
    from tasks.resample import resample_store

    bar, update = progress_bar("resample", progress, unit="view")
    with bar, Client(scheduler_address, set_as_default=False) as client:
        return resample_store(btf, out, client, sampling=sampling, overwrite=overwrite, progress=update)


@flow(name="btf-resample", log_prints=False)
def resample_flow(btf: str, out: str, sampling: str, scheduler_address: str, overwrite: bool = False,
                  progress: bool = True) -> dict[str, Any]:
    """BTF store -> resampled BTF store on ``sampling`` ("ubo2014" or a JSON file).

    Writes ``<out stem>.report.json`` beside the output: rows, how many were
    extrapolated outside the measured hull, and seconds. With ``overwrite`` the
    new store is built in ``<out stem>.partial.zarr`` and put in place of ``out``
    once complete (inside the stage); the report is written only after that
    swap, so a failed or killed run leaves the old store and report as they were.
    """
    stage = resample_stage(btf, out, sampling, scheduler_address, overwrite, progress)
    report = {"report": "btf-resample", "btf": btf, "out": out, "sampling": stage["sampling"],
              "rows": stage["rows"], "outside_hull_rows": stage["outside_hull_rows"],
              "seconds": stage["seconds"], "warnings": outside_hull_warnings(stage), "stages": {"resample": stage}}
    if progress:
        from flows.progress import say

        for warning in report["warnings"]:
            say(f"btf resample: warning: {warning}")
    write_json(Path(out).with_name(Path(out).stem + ".report.json"), report)
    return report


def outside_hull_warnings(stage: dict[str, Any]) -> list[str]:
    """A warning when more than :data:`OUTSIDE_HULL_WARN` of the rows are not interpolated but extrapolated."""
    outside, rows = stage["outside_hull_rows"], max(stage["rows"], 1)
    if outside / rows <= OUTSIDE_HULL_WARN:
        return []
    return [f"{outside / rows:.0%} of the resampled rows ({outside} of {rows}) lie outside the hull of the measured "
            "light/view directions: they take the values of the nearest hull point, not measured data (flagged in "
            "the store's outside_hull array); use a target sampling within the dome's directions, or mask those rows"]
