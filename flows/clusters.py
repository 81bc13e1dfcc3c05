"""The Dask cluster of each execution-profile kind, and how the worker environment reaches its workers.

:func:`flows.runtime.start_cluster` dispatches on the profile's kind to a starter here (``local`` stays
in :mod:`flows.runtime`): ``slurm`` and ``pbs`` start a ``dask_jobqueue`` cluster whose job script exports
the worker environment before the workers start, scaled adaptively between ``minimum_jobs`` and
``maximum_jobs``; ``kubernetes`` starts the dask-kubernetes operator's ``KubeCluster`` from the spec
:func:`kubernetes_spec` builds (the worker environment is the containers' env); ``address`` starts nothing
and connects to a running scheduler, whose workers someone else started: :func:`environ_differences`
finds what of the worker environment they lack, which :func:`flows.runtime.dask_client` reports
(docs/clusters.md).
"""

from __future__ import annotations

import copy
import os
import shlex
import sys
from typing import Any

from flows.profiles import Profile
from flows.server import LOOPBACK


def security_of(spec: dict[str, Any]) -> Any:
    """``distributed.Security`` of a ``cluster.security`` section (one CA, one certificate and key for the
    client, scheduler and workers; encryption required), or None without one."""
    if "security" not in spec:
        return None
    from distributed.security import Security

    sec = spec["security"]
    pair = {"cert": sec["cert_file"], "key": sec["key_file"]}
    return Security(tls_ca_file=sec["ca_file"], require_encryption=True,
                    **{f"tls_{role}_{part}": path for role in ("client", "scheduler", "worker")
                       for part, path in pair.items()})


def job_script_exports(environ: dict[str, str]) -> list[str]:
    """Shell lines of a job script that export ``environ`` before the workers start (``slurm``, ``pbs``)."""
    return [f"export {key}={shlex.quote(value)}" for key, value in sorted(environ.items())]


def jobqueue_options(spec: dict[str, Any], environ: dict[str, str]) -> tuple[Any, dict[str, Any]]:
    """``(cluster class, its keyword arguments)`` of a ``slurm`` or ``pbs`` profile section: see
    :func:`jobqueue_cluster`."""
    from dask_jobqueue import PBSCluster, SLURMCluster

    from flows.server import state_file

    kind = spec["kind"]
    dashboard = bool(spec.get("dashboard", False))
    security = security_of(spec)
    options: dict[str, Any] = {
        "cores": spec["cores"], "memory": spec["memory"], "processes": spec.get("processes", 1),
        "walltime": spec.get("walltime", "01:00:00"), "queue": spec.get("queue"), "account": spec.get("account"),
        "job_extra_directives": spec.get("job_extra_directives", []),
        "job_script_prologue": [*spec.get("job_script_prologue", []), *job_script_exports(environ)],
        "interface": spec.get("interface"),
        "log_directory": spec.get("log_directory") or str(state_file().with_name(f"{kind}-logs")),
        "local_directory": spec.get("local_directory"), "python": spec.get("python", sys.executable),
        "job_name": "btf-worker", "security": security, "protocol": "tls://" if security else None,
        "scheduler_options": {"dashboard": dashboard,
                              "dashboard_address": spec.get("dashboard_address",
                                                            f"{LOOPBACK}:{8787 if dashboard else 0}")},
        "silence_logs": "error",
    }
    cls = SLURMCluster if kind == "slurm" else PBSCluster
    return cls, {key: value for key, value in options.items() if value is not None}


def jobqueue_cluster(spec: dict[str, Any], environ: dict[str, str]) -> Any:
    """``dask_jobqueue.SLURMCluster`` (``kind: slurm``) or ``PBSCluster`` (``kind: pbs``) of a profile
    section (keys: ``flows.profiles.CLUSTER_KEYS['slurm']``), adaptive between ``minimum_jobs`` [1] and
    ``maximum_jobs`` [1] jobs.

    Each job runs ``processes`` worker processes of ``cores / processes`` threads; its script exports
    ``environ`` (:func:`job_script_exports`) after the profile's own ``job_script_prologue`` lines. The
    scheduler runs in this process on ``interface``; its HTTP server on ``dashboard_address`` [127.0.0.1,
    port 8787 with the dashboard, else a random one]. A job's output goes to ``log_directory``
    [$XDG_STATE_HOME/btf-pipeline/<kind>-logs], never to the current folder.
    """
    cls, options = jobqueue_options(spec, environ)
    os.makedirs(options["log_directory"], exist_ok=True)
    cluster = cls(**options)
    cluster.adapt(minimum_jobs=spec.get("minimum_jobs", 1), maximum_jobs=spec.get("maximum_jobs", 1))
    return cluster


def kubernetes_spec(spec: dict[str, Any], environ: dict[str, str]) -> dict[str, Any]:
    """The ``DaskCluster`` resource of a ``kind: kubernetes`` profile section, as ``kubectl apply -f -``
    takes it (the dask-kubernetes operator's ``make_cluster_spec``): ``n_workers`` [2] worker pods of
    ``threads_per_worker`` [1] threads, each container with ``environ`` and ``resources``."""
    from dask_kubernetes.operator import make_cluster_spec

    threads = spec.get("threads_per_worker", 1)
    resource = make_cluster_spec(
        name=spec.get("name", "btf"), image=spec["image"], n_workers=spec.get("n_workers", 2),
        resources=spec.get("resources"), env=environ, worker_command=f"dask worker --nthreads {threads}")
    resource = copy.deepcopy(resource)          # make_cluster_spec shares one resources dict between pods
    if "namespace" in spec:
        resource["metadata"]["namespace"] = spec["namespace"]
    return resource


def kubernetes_cluster(spec: dict[str, Any], environ: dict[str, str]) -> Any:
    """The operator's ``KubeCluster`` of :func:`kubernetes_spec` (needs a cluster with the operator; none here)."""
    from dask_kubernetes.operator import KubeCluster

    return KubeCluster(custom_cluster_spec=kubernetes_spec(spec, environ), namespace=spec.get("namespace"),
                       shutdown_on_close=True, quiet=True)


def cluster_spec_yaml(profile: Profile, environ: dict[str, str]) -> str:
    """``btf cluster spec PROFILE``: the resource a ``kubernetes`` profile creates, as YAML."""
    import yaml

    if profile.kind != "kubernetes":
        raise ValueError(f"{profile.path}: 'btf cluster spec' prints the DaskCluster resource of a kubernetes "
                         f"profile; this one's cluster kind is {profile.kind!r} (example: infra/kubernetes.yaml)")
    return yaml.safe_dump(kubernetes_spec(profile.cluster, environ), sort_keys=False)


#: Worker-environment keys a running worker reads when it uses them, so that setting ``os.environ`` in a
#: worker started by someone else still takes effect (``address`` kind); the others are read at start-up.
LATE_ENVIRON_KEYS = ("PREFECT_API_URL", "PREFECT_LOGGING_LEVEL", "PREFECT_LOGGING_TO_API_ENABLED",
                     "BTF_SHARED_DATA")


def environ_differences(environ: dict[str, str]) -> list[str]:
    """In a worker: the keys of ``environ`` its process did not start with (``KEY=value`` it lacks)."""
    return [f"{key}={value}" for key, value in sorted(environ.items()) if os.environ.get(key) != value]


def describe(profile: Profile, client: Any) -> str:
    """``slurm, 2 workers, adaptive 1-2 jobs, dashboard http://...``: the cluster kind, its worker count now
    and its dashboard link where it serves one (the ready line of every computing command)."""
    kind = profile.kind
    workers = len(client.nthreads())
    parts = [kind, f"{workers} worker{'s' * (workers != 1)}"]
    if kind in ("slurm", "pbs"):
        parts.append(f"adaptive {profile.cluster.get('minimum_jobs', 1)}-{profile.cluster.get('maximum_jobs', 1)} "
                     "jobs")
    if profile.cluster.get("dashboard") or (kind == "address" and _serves_dashboard(client)):
        parts.append(f"dashboard {client.dashboard_link}")
    return ", ".join(parts)


def _serves_dashboard(client: Any) -> bool:
    try:
        return "dashboard" in client.scheduler_info(n_workers=0).get("services", {})
    except Exception:  # an old scheduler or a closed connection: no link
        return False


def planned(profile: Profile) -> str:
    """What the profile's cluster will hold, before it starts: ``2 workers x 1 thread``, ``1-2 slurm jobs of
    1 worker x 1 core, 2GiB``, ``4 worker pods x 1 thread``, or the scheduler address (kind ``address``)."""
    spec, kind = profile.cluster, profile.kind
    if kind == "address":
        return spec["address"]
    if kind in ("slurm", "pbs"):
        processes = spec.get("processes", 1)
        return (f"{spec.get('minimum_jobs', 1)}-{spec.get('maximum_jobs', 1)} {kind} jobs of {processes} "
                f"worker{'s' * (processes != 1)} x {spec['cores'] // processes} core"
                f"{'s' * (spec['cores'] // processes != 1)}, {spec['memory']}")
    workers, threads = spec.get("n_workers", 2), spec.get("threads_per_worker", 1)
    unit = "worker pod" if kind == "kubernetes" else "worker"
    return (f"{workers} {unit}{'s' * (workers != 1)} x {threads} thread{'s' * (threads != 1)}"
            + (", in this process" if spec.get("processes") is False else ""))
