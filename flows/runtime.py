"""Execution environment of a ``btf`` run: one Prefect API and one Dask cluster.

The cluster and the Prefect API are chosen by a profile file (``infra/local.yaml``
by default, DESIGN §5), never by code edits. With no Prefect server configured,
one temporary server is started for the run and its URL is handed to the Dask
workers, so that no worker starts a server of its own.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import yaml
from distributed import WorkerPlugin

DEFAULT_PROFILE = Path(__file__).resolve().parents[1] / "infra" / "local.yaml"

#: Environment every Dask worker process starts with: one thread per library
#: (parallelism comes from Dask), no huge-page hint (DESIGN §5), and a fixed
#: glibc mmap threshold. By default the threshold grows (up to 32 MiB) each time
#: a large array is freed, after which band-sized arrays come from the heap and
#: fragment it: fitting one material's five bases then held 880 MB after its
#: ALS basis and peaked at 980 MB; with the threshold fixed at 4 MiB, 323 MB
#: and 599 MB (docs/benchmarks.md, out of core). The heap keeps up to 8 MiB
#: free at its top (trim threshold): trimming at 64 KiB gave every small array
#: fresh pages, which cost the acquisition evaluation a third of its time in
#: page faults (sys time 2.0 s vs 0.5 s per material, docs/benchmarks.md).
WORKER_ENVIRON = {
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
    "NUMPY_MADVISE_HUGEPAGE": "0",
    "MALLOC_MMAP_THRESHOLD_": "4194304",
    "MALLOC_TRIM_THRESHOLD_": str(8 << 20),
}


class RuntimeUnavailable(RuntimeError):
    """Prefect or the Dask cluster could not be started; the message says why."""


@dataclass(frozen=True)
class Profile:
    """A parsed execution profile (see ``infra/local.yaml``)."""

    path: str
    cluster: dict[str, Any] = field(default_factory=dict)
    prefect: dict[str, Any] = field(default_factory=dict)


#: Errors that mean bad input or a refused output (the message says what to fix): running the stage
#: again cannot help, so a stage's retry is kept for the unexpected (a lost worker, a full disk).
BAD_INPUT_ERRORS = (ValueError, FileExistsError, FileNotFoundError)


def retry_unless_bad_input(task: Any, task_run: Any, state: Any) -> bool:
    """Prefect ``retry_condition_fn``: retry a failed stage unless it failed on bad input."""
    try:
        state.result()
    except BAD_INPUT_ERRORS:
        return False
    except Exception:  # anything else (a lost worker, a full disk) is worth the stage's retry
        return True
    return True


#: ``@task(**RETRY_ONCE)``: a stage's one retry resumes it (finished views are skipped); bad input is
#: not computed twice.
RETRY_ONCE: dict[str, Any] = {"retries": 1, "retry_condition_fn": retry_unless_bad_input}


def load_profile(path: str | os.PathLike | None = None) -> Profile:
    """Read an execution profile; ``None`` means ``$BTF_CLUSTER_CONFIG`` or the default."""
    path = Path(path or os.environ.get("BTF_CLUSTER_CONFIG") or DEFAULT_PROFILE)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except FileNotFoundError:
        raise RuntimeUnavailable(
            f"execution profile {path} does not exist; pass --cluster with a file "
            f"shaped like {DEFAULT_PROFILE}"
        ) from None
    except yaml.YAMLError as exc:
        raise RuntimeUnavailable(f"execution profile {path} is not valid YAML: {exc}") from None
    if not isinstance(data, dict) or not isinstance(data.get("cluster", {}), dict):
        raise RuntimeUnavailable(f"execution profile {path}: expected a mapping with a 'cluster' section")
    return Profile(str(path), dict(data.get("cluster") or {}), dict(data.get("prefect") or {}))


def quiet_logs() -> None:
    """Keep Prefect, Dask and HTTP chatter out of the terminal unless asked for."""
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
    os.environ.setdefault("PREFECT_LOGGING_TO_API_ENABLED", "false")
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("PREFECT_UI_ENABLED", "false")
    # distributed sets its logger levels from dask config when first imported
    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")
    os.environ.setdefault("DASK_DISTRIBUTED__WORKER__DAEMON", "False")
    import prefect  # noqa: F401  (prefect configures logging on import; override after it)

    for name in ("distributed", "prefect", "httpx", "uvicorn", "asyncio"):
        logging.getLogger(name).setLevel(logging.WARNING)


def _check_health(api_url: str, timeout: float) -> None:
    import httpx

    deadline = time.monotonic() + timeout
    last: Exception | None = None
    while time.monotonic() < deadline:
        try:
            response = httpx.get(f"{api_url.rstrip('/')}/health", timeout=2.0)
            if response.status_code == 200:
                return
            last = RuntimeError(f"HTTP {response.status_code}")
        except httpx.HTTPError as exc:
            last = exc
        time.sleep(0.2)
    raise RuntimeUnavailable(
        f"the Prefect API at {api_url} did not answer /health within {timeout:.0f} s ({last}); "
        "start it (`prefect server start`), fix PREFECT_API_URL, or unset it to use a temporary server"
    )


@contextlib.contextmanager
def prefect_api(profile: Profile) -> Iterator[str]:
    """Yield the URL of a Prefect API that answers, starting a temporary one if needed.

    Raises
    ------
    RuntimeUnavailable
        When the configured server does not answer or the temporary one does not
        start within ``prefect.startup_timeout_s``; never hangs.
    """
    from prefect.settings import PREFECT_API_URL, temporary_settings

    timeout = float(profile.prefect.get("startup_timeout_s", 90))
    url = os.environ.get("PREFECT_API_URL") or profile.prefect.get("api_url")
    if url:
        _check_health(url, timeout)
        with temporary_settings({PREFECT_API_URL: url}):
            yield url
        return

    from prefect.server.api.server import SubprocessASGIServer

    server = SubprocessASGIServer()
    try:
        server.start(timeout=max(1, int(timeout)))
    except Exception as exc:  # prefect raises RuntimeError/httpx errors of several kinds
        server.stop()
        raise RuntimeUnavailable(
            f"could not start a temporary Prefect server within {timeout:.0f} s: {exc}. "
            "Raise prefect.startup_timeout_s in the profile or set PREFECT_API_URL to a running server."
        ) from None
    try:
        with temporary_settings({PREFECT_API_URL: server.api_url}):
            yield server.api_url
    finally:
        server.stop()


@contextlib.contextmanager
def dask_client(profile: Profile, prefect_url: str | None = None) -> Iterator[Any]:
    """Start the profile's Dask cluster and yield a connected ``distributed.Client``."""
    import dask
    from distributed import Client, LocalCluster

    spec = dict(profile.cluster)
    kind = spec.pop("kind", "local")
    if kind != "local":
        raise RuntimeUnavailable(
            f"{profile.path}: cluster kind {kind!r} is not supported yet (supported: 'local'); "
            "SLURM and Kubernetes profiles arrive with the cluster issue"
        )
    environ = dict(WORKER_ENVIRON)
    if prefect_url:
        environ["PREFECT_API_URL"] = prefect_url
    for key in ("PREFECT_LOGGING_LEVEL", "PREFECT_LOGGING_TO_API_ENABLED", "BTF_SHARED_DATA"):
        if key in os.environ:
            environ[key] = os.environ[key]
    # distributed's nanny applies pre-spawn-environ to this process's os.environ too:
    # restore it afterwards, or a later run in this process would inherit a dead server's URL
    saved = {key: os.environ.get(key) for key in environ}
    dashboard = bool(spec.pop("dashboard", False))
    try:
        with dask.config.set({"distributed.nanny.pre-spawn-environ": environ,
                              "distributed.worker.daemon": False}):
            try:
                cluster = LocalCluster(
                    n_workers=int(spec.pop("n_workers", 2)),
                    threads_per_worker=int(spec.pop("threads_per_worker", 1)),
                    memory_limit=spec.pop("memory_limit", "4GiB"),
                    processes=bool(spec.pop("processes", True)),
                    # the scheduler always serves HTTP (metrics); a random port avoids clashes
                    dashboard_address=":8787" if dashboard else ":0",
                    scheduler_kwargs={"dashboard": dashboard},
                    silence_logs=logging.WARNING,
                    **spec,
                )
            except Exception as exc:
                raise RuntimeUnavailable(f"could not start the Dask cluster of {profile.path}: {exc}") from exc
            try:
                with Client(cluster) as client:
                    client.register_plugin(WorkerSetup(), name="btf-worker-setup")
                    yield client
            finally:
                cluster.close()
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


class WorkerSetup(WorkerPlugin):
    """Dask worker plugin: pins OpenCV to one thread (parallelism comes from Dask, DESIGN §5) and
    imports the pipeline's numerical stack when a worker starts, so that the first task of a run
    does not pay for it (about a second per worker on two cores)."""

    modules = ("tasks.ingest", "tasks.simulate", "tasks.resample")

    def setup(self, worker: Any) -> None:
        import importlib

        import cv2

        cv2.setNumThreads(1)
        for name in self.modules:
            importlib.import_module(name)


@contextlib.contextmanager
def runtime(profile_path: str | os.PathLike | None = None) -> Iterator[tuple[Profile, str, Any]]:
    """Prefect API and Dask client for one run: ``(profile, prefect_url, client)``."""
    quiet_logs()
    profile = load_profile(profile_path)
    with prefect_api(profile) as url, dask_client(profile, url) as client:
        yield profile, url, client
