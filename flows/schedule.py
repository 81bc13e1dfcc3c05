"""Scheduled database builds: a Prefect deployment of ``btf build-db`` with a cron schedule.

A maintainer runs ``btf schedule build-db DB --out MODEL --cron "0 3 * * *"``
on a machine that stays up, against a running Prefect server
(``PREFECT_API_URL``; cron schedules do not fire on a temporary server,
docs/architecture.md, "Pitfalls"). Each scheduled run starts the Dask cluster of its execution
profile, builds the database incrementally (only new or changed materials
are fitted) and writes the reports.
"""

from __future__ import annotations

import os
from typing import Any

from prefect import flow

from flows.model import build_db_flow
from tasks.model import ModelSettings


@flow(name="btf-build-db-scheduled", log_prints=False)
def scheduled_build_db(db: str, out: str, cluster: str | None = None, classes: str | None = None) -> dict[str, Any]:
    """One scheduled build: start the profile's cluster, run ``btf build-db`` on it, stop it."""
    from flows.runtime import dask_client, load_profile

    with dask_client(load_profile(cluster), os.environ.get("PREFECT_API_URL")) as client:
        report = build_db_flow(db, out, client.scheduler.address, ModelSettings(), classes=classes, progress=False)
    return {"model": report["model"], "trends": report["trends"]}


def build_db_deployment(db: str, out: str, cron: str, *, cluster: str | None = None, classes: str | None = None,
                        name: str = "build-db") -> Any:
    """The deployment ``btf schedule build-db`` serves: ``scheduled_build_db`` on ``cron`` with these
    parameters (a ``prefect.deployments.runner.RunnerDeployment``)."""
    return scheduled_build_db.to_deployment(
        name=name, cron=cron, parameters={"db": str(db), "out": str(out), "cluster": cluster, "classes": classes},
        description=f"btf build-db {db} --out {out}, on the cron schedule {cron!r}")
