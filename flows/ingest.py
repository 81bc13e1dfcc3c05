"""Prefect flows of the ingest side: ``btf import-raw`` (raw files -> capture store), ``btf import-images``
(LDR image brackets -> capture store) and ``btf ingest``."""

from __future__ import annotations

from typing import Any

from prefect import flow, task
from prefect.cache_policies import NO_CACHE

from btfcore.dome import Device
from flows.runtime import RETRY_ONCE
from tasks.ingest_raw import RawImportPlan, import_raw, plan_raw_import


@task(name="import-raw-files", **RETRY_ONCE, cache_policy=NO_CACHE)
def import_raw_stage(folder: str, manifest: str, device: Device, out: str, scheduler_address: str,
                     overwrite: bool, plan: RawImportPlan | None = None, strict_brackets: bool = False
                     ) -> dict[str, Any]:
    from distributed import Client

    if plan is None:
        plan = plan_raw_import(folder, manifest)  # every problem listed before any work
    with Client(scheduler_address, set_as_default=False) as client:
        store = import_raw(plan, device, out, client, overwrite=overwrite, strict_brackets=strict_brackets,
                           provenance={"manifest": str(manifest), "folder": str(folder)})
    return {"store": str(out), "shape": list(plan.shape), "frame_shape": list(plan.frame_shape),
            "bayer_pattern": plan.bayer_pattern, "bracket_warnings": store.attrs.get("bracket_warnings", []),
            "complete": store.complete}


@flow(name="btf-import-raw", log_prints=False)
def import_raw_flow(folder: str, manifest: str, device: Device, out: str, scheduler_address: str,
                    overwrite: bool = False, plan: RawImportPlan | None = None,
                    strict_brackets: bool = False) -> dict[str, Any]:
    """Validate a folder of camera raw files and its manifest (unless ``plan`` is their validated
    :func:`tasks.ingest_raw.plan_raw_import`, as ``btf import-raw`` passes it), then write a capture store."""
    return import_raw_stage(folder, manifest, device, out, scheduler_address, overwrite, plan, strict_brackets)


@task(name="import-image-files", **RETRY_ONCE, cache_policy=NO_CACHE)
def import_images_stage(folder: str, manifest: str, device: Device, out: str, scheduler_address: str,
                        overwrite: bool, plan: RawImportPlan, method: str, response: str | None,
                        strict_brackets: bool) -> dict[str, Any]:
    from distributed import Client

    from tasks.ingest_images import import_images

    with Client(scheduler_address, set_as_default=False) as client:
        store = import_images(plan, device, out, client, method=method, response_file=response,
                              overwrite=overwrite, strict_brackets=strict_brackets,
                              provenance={"manifest": str(manifest), "folder": str(folder)})
    return {"store": str(out), "shape": list(plan.shape), "frame_shape": list(plan.frame_shape),
            "bit_depth": int(plan.white_level).bit_length(), "response": store.response[1],
            "bracket_warnings": store.attrs.get("bracket_warnings", []), "complete": store.complete}


@flow(name="btf-import-images", log_prints=False)
def import_images_flow(folder: str, manifest: str, device: Device, out: str, scheduler_address: str,
                       plan: RawImportPlan, overwrite: bool = False, method: str = "debevec",
                       response: str | None = None, strict_brackets: bool = False) -> dict[str, Any]:
    """Write a capture store from a validated image import (:func:`tasks.ingest_images.plan_image_import`):
    each camera's response calibrated with ``method`` (or read from ``response``), then the brackets."""
    return import_images_stage(folder, manifest, device, out, scheduler_address, overwrite, plan, method,
                               response, strict_brackets)


@task(name="radiometric-calibration", cache_policy=NO_CACHE)
def calibration_stage(white: str | None, white_albedo: float, colour_matrix: str | None):
    from tasks.radiometric import load_calibration

    return load_calibration(white, white_albedo, colour_matrix)


@task(name="ingest-views", **RETRY_ONCE, cache_policy=NO_CACHE)
def ingest_stage(capture: str, out: str, scheduler_address: str, overwrite: bool, progress: bool,
                 calibration=None, keep_roi: bool = False) -> dict[str, Any]:
    """Ingest the views (with ``keep_roi`` also their regions of interest); a replacement of another
    ingest's output stays staged (not committed)."""
    from distributed import Client

    from flows.progress import progress_bar
    from tasks.ingest import ingest_capture

    bar, update = progress_bar("ingest", progress, unit="view")
    with bar, Client(scheduler_address, set_as_default=False) as client:
        return ingest_capture(capture, out, client, overwrite=overwrite, calibration=calibration, progress=update,
                              commit=False, keep_roi=keep_roi)


@task(name="commit-staged-output", cache_policy=NO_CACHE)
def commit_stage(out: str) -> str:
    from tasks.ingest import commit_staged

    return str(commit_staged(out))


@task(name="ingest-evaluation", cache_policy=NO_CACHE)
def ingest_evaluation(capture: str, out: str) -> dict[str, Any]:
    from tasks.ingest import btf_error_against_truth
    from tasks.stores import open_capture_store

    store = open_capture_store(capture)                  # opened once, for the check and the errors
    if not store.has_truth:
        return {}
    return btf_error_against_truth(out, store)


@task(name="ingest-validity", cache_policy=NO_CACHE)
def ingest_validity_stage(capture: str, out: str) -> dict[str, Any]:
    from tasks.report import ingest_validity

    return ingest_validity(out, capture)


@flow(name="btf-ingest", log_prints=False)
def ingest_flow(capture: str, out: str, scheduler_address: str, overwrite: bool = False,
                progress: bool = True, white: str | None = None, white_albedo: float = 0.99,
                colour_matrix: str | None = None, calibration: Any = None,
                keep_roi: bool = False) -> dict[str, Any]:
    """Capture store -> BTF store (HDR, demosaic, rectify, demultiplex per view; with ``white``
    and/or ``colour_matrix`` also the radiometric correction of :mod:`tasks.radiometric`, or with
    ``calibration`` the one already loaded from them, as ``btf ingest`` does before its cluster starts).
    With ``keep_roi`` (``btf ingest --keep-roi``) the store also keeps each view's HDR radiance regions
    of interest before rectification (docs/btf-store.md, "Regions of interest").

    Writes ``<out stem>.report.json`` beside the BTF store (never the folder's
    ``report.json``, which may belong to the simulation that made the capture).
    Against a simulated capture the report also holds the relative errors
    against its ground truth. Brackets without a single usable pixel (every
    exposure saturated or near-black) are listed in the report's
    ``valid_fraction`` and make the run fail with a ValueError naming them.

    With ``overwrite``, another ingest's output at ``out`` (and its report) is
    replaced only when the new store is complete and has no such bracket;
    until then the new store is ``<out stem>.partial.zarr``, and a failed
    check writes its report beside it (``<out stem>.partial.report.json``).
    """
    from pathlib import Path

    from tasks.ingest import staging_path
    from tasks.report import write_json

    if calibration is None:
        calibration = calibration_stage(white, white_albedo, colour_matrix)
    stage = ingest_stage(capture, out, scheduler_address, overwrite, progress, calibration, keep_roi)
    store = str(staging_path(out)) if stage["staged"] else out
    validity = ingest_validity_stage(capture, store)
    report = {"report": "btf-ingest", "capture": capture, "out": out, "stages": {"ingest": stage},
              "radiometric": None if calibration is None else calibration.info,
              "valid_fraction": validity, "errors_against_truth": ingest_evaluation(capture, store)}
    if validity["problem"]:
        # bad input: `btf ingest` exits 2 (bad input), the report (beside the store that holds this run) lists the brackets
        write_json(Path(store).with_name(Path(store).stem + ".report.json"), report)
        kept = f"; {out} was left as it was, the new store is {store}" if stage["staged"] else ""
        raise ValueError(validity["problem"] + kept)
    if stage["staged"]:
        commit_stage(out)
    write_json(Path(out).with_name(Path(out).stem + ".report.json"), report)
    return report


@task(name="ingest-database", **RETRY_ONCE, cache_policy=NO_CACHE)
def ingest_database_stage(stores: list[str], out_dir: str, scheduler_address: str,
                          progress: bool, calibration=None, name: str = "ingest") -> dict[str, dict[str, Any]]:
    """Ingest every capture of a simulated database; errors against each one's truth (``name``: the
    progress display's, e.g. ``"ingest: white standard"``)."""
    from pathlib import Path

    from distributed import Client

    from flows.progress import in_parts, progress_bar
    from tasks.ingest import btf_error_against_truth, ingest_capture
    from tasks.stores import open_capture_store

    results = {}
    captures = [open_capture_store(store) for store in stores]     # opened once, for the ingest and the errors
    bar, update = progress_bar(name, progress, unit="view")
    parts = in_parts(update, [capture.n_views for capture in captures])     # one count over every store's views
    with bar, Client(scheduler_address, set_as_default=False) as client:
        for store, capture, part in zip(stores, captures, parts):
            out = str(Path(out_dir) / Path(store).name)
            results[Path(store).stem] = {**ingest_capture(capture, out, client, calibration=calibration,
                                                          progress=part),
                                         **btf_error_against_truth(out, capture)}
    return results
