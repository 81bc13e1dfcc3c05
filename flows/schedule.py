"""Scheduled and deployed runs: ``btf deploy`` registers the deployments of ``prefect.yaml`` with a process
work pool, ``btf schedule build-db`` serves a cron deployment of ``btf build-db`` from the current shell.

Both need a Prefect server that stays up (a schedule does not fire on the temporary server of a single
run): ``PREFECT_API_URL``, else a running ``btf server`` (:func:`flows.server.running_server`). The
deployments' flows are those of :mod:`flows.deploy`, named by their entrypoints in ``prefect.yaml``
(``flows/deploy.py:build_db``) and loaded from the repository, whose root is each run's working
directory (docs/architecture.md, "Execution"). A worker started with ``prefect worker start --pool
NAME`` in the project's environment runs them: each run starts the Dask cluster of its execution
profile (the parameter ``cluster``), runs the command and stops it.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml

from flows.server import RuntimeUnavailable, is_healthy, running_server

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DEPLOYMENTS = REPO / "prefect.yaml"
#: The entry flow of ``btf schedule build-db`` (and of the ``build-db`` deployment of ``prefect.yaml``).
BUILD_DB_ENTRYPOINT = "flows/deploy.py:build_db"
DEFAULT_POOL = "btf"

#: Keys of a deployment in ``prefect.yaml`` that ``btf deploy`` reads (Prefect's own ``prefect deploy``
#: reads the same file); any other key is refused, naming the file and deployment.
DEPLOYMENT_KEYS = ("name", "entrypoint", "description", "tags", "parameters", "schedules", "work_pool",
                   "concurrency_limit", "version")
SCHEDULE_KEYS = ("cron", "interval", "timezone", "active")
WORK_POOL_KEYS = ("name", "work_queue_name", "job_variables")


def deployment_api() -> str:
    """The Prefect API deployments are registered with: ``PREFECT_API_URL``, else a running ``btf server``.

    Raises
    ------
    RuntimeUnavailable
        Neither is set or running, or the API does not answer (the CLI exits 3).
    """
    url = os.environ.get("PREFECT_API_URL") or running_server()
    if not url:
        raise RuntimeUnavailable("no Prefect server: start one with `btf server start` or set PREFECT_API_URL to "
                                 "a running server; a schedule does not fire on the temporary server of a single run")
    if not is_healthy(url, timeout=5.0):
        raise RuntimeUnavailable(f"the Prefect API at {url} does not answer; start it (`btf server start`) or fix "
                                 "PREFECT_API_URL")
    return url


def read_deployments(path: str | os.PathLike, names: list[str] | None = None) -> list[dict[str, Any]]:
    """The deployments of a ``prefect.yaml`` (only ``names``, if given), each checked for the keys
    ``btf deploy`` knows (``DEPLOYMENT_KEYS``, ``SCHEDULE_KEYS``, ``WORK_POOL_KEYS``).

    Raises
    ------
    ValueError
        The file is not YAML, has no ``deployments`` list, a deployment has an unknown key or no
        ``name`` and ``entrypoint``, or a name in ``names`` is not in it; the message names the file,
        the deployment and the key.
    FileNotFoundError
        ``path`` does not exist.
    """
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ValueError(f"{path}: not a valid YAML file: {' '.join(str(exc).split())}") from None
    entries = (data or {}).get("deployments") if isinstance(data, dict) else None
    if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
        raise ValueError(f"{path}: no 'deployments' list (each a mapping with name, entrypoint, parameters, ...)")
    for entry in entries:
        where = f"{path}: deployment {entry.get('name', '?')!r}"
        if not entry.get("name") or not entry.get("entrypoint"):
            raise ValueError(f"{where}: give its 'name' and 'entrypoint' (e.g. {BUILD_DB_ENTRYPOINT})")
        _refuse_unknown(entry, DEPLOYMENT_KEYS, where)
        _refuse_unknown(entry.get("work_pool") or {}, WORK_POOL_KEYS, f"{where}, work_pool")
        for schedule in entry.get("schedules") or []:
            _refuse_unknown(schedule, SCHEDULE_KEYS, f"{where}, schedule")
            if ("cron" in schedule) == ("interval" in schedule):
                raise ValueError(f"{where}: each schedule needs one of 'cron' (e.g. \"0 3 * * *\") or 'interval' "
                                 f"(seconds), not {schedule}")
    known = [e["name"] for e in entries]
    missing = [n for n in names or [] if n not in known]
    if missing:
        raise ValueError(f"{path}: no deployment named {', '.join(missing)}; it has {', '.join(known)}")
    return [e for e in entries if not names or e["name"] in names]


def _refuse_unknown(values: Any, allowed: tuple[str, ...], where: str) -> None:
    if not isinstance(values, dict):
        raise ValueError(f"{where}: must be a mapping of {', '.join(allowed)}, not {values!r}")
    unknown = [key for key in values if key not in allowed]
    if unknown:
        raise ValueError(f"{where}: unknown key {unknown[0]!r}; allowed keys: {', '.join(allowed)}")


def _schedules(entry: dict[str, Any]) -> list[Any]:
    from prefect.schedules import Cron, Interval

    return [Cron(s["cron"], timezone=s.get("timezone"), active=s.get("active", True)) if "cron" in s
            else Interval(float(s["interval"]), timezone=s.get("timezone"), active=s.get("active", True))
            for s in entry.get("schedules") or []]


def _ensure_process_pool(name: str) -> bool:
    """Create the ``process`` work pool ``name`` unless it exists; True if it was created.

    Raises
    ------
    ValueError
        A pool of that name exists with another type (its workers would not run a process).
    """
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.actions import WorkPoolCreate
    from prefect.exceptions import ObjectNotFound
    from prefect.workers.process import ProcessWorker

    with get_client(sync_client=True) as client:
        try:
            pool = client.read_work_pool(name)
        except ObjectNotFound:
            client.create_work_pool(WorkPoolCreate(name=name, type="process",
                                                   base_job_template=ProcessWorker.get_default_base_job_template()))
            return True
    if pool.type != "process":
        raise ValueError(f"work pool {name!r} exists with type {pool.type!r}; give another --pool (btf deploy "
                         "creates a 'process' pool)")
    return False


def register(path: str | os.PathLike | None = None, pool: str | None = None,
             names: list[str] | None = None) -> dict[str, Any]:
    """Register the deployments of ``path`` (a ``prefect.yaml``, default the repository's; ``names``: only
    these) with the Prefect API of :func:`deployment_api` on the process work pool ``pool`` (default: each
    deployment's ``work_pool.name``, else ``btf``), creating the pool if missing. A deployment that exists
    is updated.

    Returns ``{"api", "pools", "created_pools", "deployments", "worker_commands"}``: the
    ``prefect worker start --pool NAME`` command per pool is what runs the deployments.
    """
    from prefect import Flow
    from prefect.settings import PREFECT_API_URL, temporary_settings

    path = Path(path or DEFAULT_DEPLOYMENTS)
    entries = read_deployments(path, names)  # bad input first, before the API is asked
    url = deployment_api()
    registered, pools, created = [], [], []
    with temporary_settings({PREFECT_API_URL: url}):
        for entry in entries:
            work_pool = entry.get("work_pool") or {}
            pool_name = pool or work_pool.get("name") or DEFAULT_POOL
            if pool_name not in pools:
                pools.append(pool_name)
                if _ensure_process_pool(pool_name):
                    created.append(pool_name)
            entry_flow = Flow.from_source(source=str(REPO), entrypoint=entry["entrypoint"])
            parameters = dict(entry.get("parameters") or {})
            unknown = sorted(set(parameters) - set(entry_flow.parameters.properties))
            if unknown:
                raise ValueError(f"{path}: deployment {entry['name']!r}: unknown parameter {unknown[0]!r} of "
                                 f"{entry['entrypoint']}; it takes {', '.join(entry_flow.parameters.properties)}")
            deployment = entry_flow.to_deployment(
                name=entry["name"], parameters=parameters, description=entry.get("description"),
                tags=entry.get("tags"), schedules=_schedules(entry), version=entry.get("version"),
                concurrency_limit=entry.get("concurrency_limit"),
                work_queue_name=work_pool.get("work_queue_name"), job_variables=work_pool.get("job_variables"))
            deployment.apply(work_pool_name=pool_name)
            registered.append(f"{entry_flow.name}/{entry['name']}")
    return {"api": url, "pools": pools, "created_pools": created, "deployments": registered,
            "worker_commands": [f"PREFECT_API_URL={url} prefect worker start --pool {p}" for p in pools]}


def build_db_deployment(db: str, out: str, cron: str, *, cluster: str | None = None, classes: str | None = None,
                        name: str = "build-db") -> Any:
    """The deployment ``btf schedule build-db`` serves: the ``build-db`` entry flow of :mod:`flows.deploy`
    on ``cron`` with these parameters (a ``prefect.deployments.runner.RunnerDeployment``)."""
    from prefect.flows import load_flow_from_entrypoint

    build_db = load_flow_from_entrypoint(str(REPO / BUILD_DB_ENTRYPOINT))
    return build_db.to_deployment(
        name=name, cron=cron, parameters={"db": str(db), "out": str(out), "cluster": cluster, "classes": classes},
        description=f"btf build-db {db} --out {out}, on the cron schedule {cron!r}")


def serve_build_db(db: str, out: str, cron: str, *, cluster: str | None = None, classes: str | None = None,
                   name: str = "build-db") -> None:
    """Serve :func:`build_db_deployment` from this process against :func:`deployment_api` until stopped,
    its paths made absolute (the served runs may start elsewhere); print what is served (JSON) first."""
    import json

    url = deployment_api()
    os.environ["PREFECT_API_URL"] = url  # the served runs (subprocesses of this one) report to it too
    from prefect import serve

    absolute = {key: os.path.abspath(value) if value else None
                for key, value in dict(db=db, out=out, cluster=cluster, classes=classes).items()}
    deployment = build_db_deployment(cron=cron, name=name, **absolute)
    print(json.dumps({"serving": f"{deployment.flow_name}/{name}", "api": url, "cron": cron,
                      "parameters": deployment.parameters}, indent=2), flush=True)
    serve(deployment)
