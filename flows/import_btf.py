"""Prefect flow of ``btf import-btf``: a Bonn BTF file streamed into a btf-texture store on the Dask cluster
(docs/bonn-formats.md, "Importing (btf import-btf)")."""

from __future__ import annotations

from typing import Any

from prefect import flow, task
from prefect.cache_policies import NO_CACHE

from flows.runtime import RETRY_ONCE


# Retrying the stage starts the import again; bad input is not retried (it would only fail again).
@task(name="import-btf", **RETRY_ONCE, cache_policy=NO_CACHE)
def import_stage(source: str, out: str, scheduler_address: str, overwrite: bool, material_class: str | None,
                 material_id: str | None, progress: bool) -> dict[str, Any]:
    from distributed import Client

    from flows.progress import progress_bar
    from tasks.bonn.import_btf import import_btf

    bar, update = progress_bar("import-btf", progress, unit="chunk")
    with bar, Client(scheduler_address, set_as_default=False) as client:
        return import_btf(source, out, client, overwrite=overwrite, material_class=material_class,
                          material_id=material_id, on_progress=update)


@flow(name="btf-import-btf", log_prints=False)
def import_btf_flow(source: str, out: str, scheduler_address: str, overwrite: bool = False,
                    material_class: str | None = None, material_id: str | None = None,
                    progress: bool = True) -> dict[str, Any]:
    """Bonn BTF file ``source`` -> btf-texture store ``out`` (:func:`tasks.bonn.import_btf.import_btf`).

    Returns
    -------
    dict
        The import's summary (store, format, rows, texture size, seconds ...).
    """
    return import_stage(source, out, scheduler_address, overwrite, material_class, material_id, progress)
