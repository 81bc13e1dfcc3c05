"""Prefect flow of ``btf evaluate acquisition``: every acquisition strategy against the ground truth.

Stages (one Prefect task each; each builds one Dask graph over its chunks,
docs/architecture.md, "Execution"): the truth database, the per-material
bases, the leave-one-out reconstructions and scores with the renderings, and
the report. Numerics live in :mod:`tasks.evaluate_acquisition` and
:mod:`btfcore`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from prefect import flow, task
from prefect.cache_policies import NO_CACHE

from tasks.evaluate_acquisition import EvaluationConfig


@task(name="evaluate-acquisition", retries=1, cache_policy=NO_CACHE)
def evaluate_stage(db: str, out: str, scheduler_address: str, config: EvaluationConfig,
                   progress: bool) -> dict[str, Any]:
    from distributed import Client

    from flows.progress import progress_bars, say
    from tasks.evaluate_acquisition import evaluate_acquisition, reuse_message

    units = {"truth BTFs": "view", "bases": "material", "reconstruct": "material", "render": "material",
             "adaptive loop": "material"}
    with progress_bars(progress, units) as bar, Client(scheduler_address, set_as_default=False) as client:
        summary = evaluate_acquisition(db, out, client, config, progress=bar)
    if progress:
        say(reuse_message(summary["reused"]))
    return summary


@task(name="acquisition-report", cache_policy=NO_CACHE)
def acquisition_report_stage(out: str, summary: dict[str, Any]) -> dict[str, str]:
    from tasks.evaluate_acquisition import write_acquisition_report

    return write_acquisition_report(out, summary)


@flow(name="btf-evaluate-acquisition", log_prints=False)
def evaluate_acquisition_flow(db: str, out: str, scheduler_address: str,
                              config: EvaluationConfig = EvaluationConfig(), progress: bool = True
                              ) -> dict[str, Any]:
    """Leave-one-out evaluation of sparse, multiplexed and combined acquisition.

    ``db`` holds (or receives) the truth BTF stores of ``config``; ``out``
    receives ``model.zarr``, ``report.json``, ``report.html`` and the figures.
    A rerun on the same ``out`` reuses every finished result whose inputs did
    not change and says so (one line, and the summary's ``"reused"``).
    Returns the summary written to ``report.json``.
    """
    Path(out).mkdir(parents=True, exist_ok=True)
    summary = evaluate_stage(db, out, scheduler_address, config, progress)
    files = acquisition_report_stage(out, summary)
    return {**summary, **files}
