"""Execution environment of a ``btf`` run: one Prefect API and one Dask cluster.

The cluster and the Prefect API are chosen by a profile file (``infra/local.yaml``
by default), never by code edits. With no Prefect server configured, a running
``btf server`` (:mod:`flows.server`) is used, else one temporary server is
started for the run, at the same time as the cluster, and its URL is handed to
the Dask workers, so that no worker starts a server of its own
(docs/architecture.md, "Execution").
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Iterator

from distributed import WorkerPlugin

# the profile names other modules import from here (flows.cli, flows.cluster_service, tests, benchmarks)
from flows.profiles import (CLUSTER_KEYS, DEFAULT_PROFILE, PREFECT_KEYS, Profile, ProfileError,  # noqa: F401
                            dashboard_address, exposure_warnings, load_profile)
from flows.server import LOOPBACK, RuntimeUnavailable, running_server  # noqa: F401  (RuntimeUnavailable: re-exported)


#: Environment every Dask worker process starts with: one thread per library
#: (parallelism comes from Dask), no huge-page hint, and a fixed glibc mmap
#: threshold (docs/architecture.md, "Execution"). By default the threshold
#: grows (up to 32 MiB) each time a large array is freed, after which
#: band-sized arrays come from the heap and fragment it: fitting one material's
#: five bases then held 880 MB after its ALS basis and peaked at 980 MB; with
#: the threshold fixed at 4 MiB, 323 MB and 599 MB (docs/benchmarks.md, out of
#: core). The heap keeps up to 8 MiB free at its top (trim threshold): trimming
#: at 64 KiB gave every small array fresh pages, which cost the acquisition
#: evaluation a third of its time in page faults (sys time 2.0 s vs 0.5 s per
#: material, docs/benchmarks.md). Tasks made of many arrays above 4 MiB raise the
#: threshold while they run (:func:`tasks.buffers.heap_arrays`).
WORKER_ENVIRON = {
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
    "NUMPY_MADVISE_HUGEPAGE": "0",
    "MALLOC_MMAP_THRESHOLD_": "4194304",
    "MALLOC_TRIM_THRESHOLD_": str(8 << 20),
}


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


#: Prefect loggers that report a failed task or flow run ("Task run ... Finished in state Failed",
#: "Flow run ... Encountered exception", each with the traceback). The error reaches the caller anyway
#: and the CLI names it in one line, so by default their ERROR records are dropped (``quiet_logs``).
RUN_LOGGERS = ("prefect.flow_runs", "prefect.task_runs")

#: Set by ``quiet_logs`` when it chose ``PREFECT_LOGGING_LEVEL`` itself (the user did not).
_QUIET = {"prefect": False, "to_api": False}


#: Prefect log levels at which a failed run's tracebacks are shown (the user asked for detail).
VERBOSE_LEVELS = ("DEBUG", "INFO")


class _QuietRunFailures(logging.Filter):
    """Drops the ERROR records of ``RUN_LOGGERS`` unless ``PREFECT_LOGGING_LEVEL`` asks for detail
    (``INFO`` or ``DEBUG``): at the default ``WARNING`` (``quiet_logs``'s choice, or the same level
    inherited from a parent ``btf`` process or set by hand) the error reaches ``btf`` in one line."""

    def filter(self, record: logging.LogRecord) -> bool:
        verbose = os.environ.get("PREFECT_LOGGING_LEVEL", "WARNING").upper() in VERBOSE_LEVELS
        return record.levelno < logging.ERROR or verbose


_RUN_FAILURE_FILTER = _QuietRunFailures()


class _QuietTaskFailures(logging.Filter):
    """Drops a Dask worker's "Compute Failed" record (a screen of traceback per failed task, printed by
    every worker before the client re-raises the task's exception, which ``btf`` names in one line)
    while Dask's log level is the default warning; ``DASK_LOGGING__DISTRIBUTED=info`` shows it."""

    def filter(self, record: logging.LogRecord) -> bool:
        quiet = os.environ.get("DASK_LOGGING__DISTRIBUTED", "warning").lower() == "warning"
        return not (quiet and isinstance(record.msg, str) and record.msg.startswith("Compute Failed"))


_TASK_FAILURE_FILTER = _QuietTaskFailures()


def quiet_task_failures() -> None:
    """Install :class:`_QuietTaskFailures` on ``distributed.worker`` in this process (idempotent)."""
    logger = logging.getLogger("distributed.worker")
    if _TASK_FAILURE_FILTER not in logger.filters:
        logger.addFilter(_TASK_FAILURE_FILTER)


def quiet_logs() -> None:
    """Keep Prefect, Dask and HTTP chatter out of the terminal unless asked for.

    Unless ``PREFECT_LOGGING_LEVEL`` is set by the user, Prefect logs warnings only and the tracebacks
    Prefect prints for a failed task or flow run (``RUN_LOGGERS``) are dropped: the error is raised to
    the caller, and ``btf`` names it in one line. ``PREFECT_LOGGING_LEVEL=INFO`` (or ``DEBUG``) shows
    them, as ``DASK_LOGGING__DISTRIBUTED=info`` shows Dask's.
    """
    _quiet_before_prefect()
    import prefect  # noqa: F401  (prefect configures logging on import; override after it)

    _quiet_log_levels()


def _quiet_before_prefect() -> None:
    """What :func:`quiet_logs` sets before Prefect is imported: the environment (which the Dask workers
    and a temporary server inherit) and Dask's log level (which a starting cluster reads)."""
    if "PREFECT_LOGGING_LEVEL" not in os.environ:
        os.environ["PREFECT_LOGGING_LEVEL"] = "WARNING"
        _QUIET["prefect"] = True
    if "PREFECT_LOGGING_TO_API_ENABLED" not in os.environ:  # on for a lasting API: temporary_settings_of_run
        os.environ["PREFECT_LOGGING_TO_API_ENABLED"] = "false"
        _QUIET["to_api"] = True
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    # the client's first-run telemetry notice: printed by `import prefect` in a terminal (this process or
    # a temporary server's, which inherits the terminal) unless DO_NOT_TRACK is set
    os.environ.setdefault("DO_NOT_TRACK", "1")
    os.environ.setdefault("PREFECT_UI_ENABLED", "false")
    # distributed sets its logger levels from dask config when first imported
    dask_level = os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")
    os.environ.setdefault("DASK_DISTRIBUTED__WORKER__DAEMON", "False")
    if dask_level.lower() == "warning":
        logging.getLogger("distributed").setLevel(logging.WARNING)


def _quiet_log_levels() -> None:
    """The logger levels and filters of :func:`quiet_logs` (after Prefect is imported)."""
    for name in ("httpx", "uvicorn", "asyncio"):
        logging.getLogger(name).setLevel(logging.WARNING)
    if _QUIET["prefect"] and os.environ["PREFECT_LOGGING_LEVEL"] == "WARNING":
        logging.getLogger("prefect").setLevel(logging.WARNING)
    for name in RUN_LOGGERS:
        if _RUN_FAILURE_FILTER not in logging.getLogger(name).filters:
            logging.getLogger(name).addFilter(_RUN_FAILURE_FILTER)
    quiet_task_failures()               # a threaded cluster's workers log in this process


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
def _starting_prefect_api(profile: Profile) -> Iterator[tuple[str, Callable[[], str], bool]]:
    """``(url, ready, lasting)`` of the run's Prefect API, its URL known before it answers; ``lasting``
    is False for a temporary server, which stops with the run.

    The API is, in this order: ``PREFECT_API_URL`` or the profile's ``prefect.api_url``; else a
    running ``btf server`` (:func:`flows.server.running_server`; a stale state file is ignored with
    one line); else a temporary server started here, in a thread, so that the caller can start the
    Dask cluster meanwhile (docs/architecture.md, "Execution"). ``ready()`` waits until the API
    answers and returns its URL, or raises :class:`RuntimeUnavailable`; the temporary server is
    stopped on exit.
    """
    timeout = float(profile.prefect.get("startup_timeout_s", 90))
    url = os.environ.get("PREFECT_API_URL") or profile.prefect.get("api_url")
    if url:
        def configured() -> str:
            _check_health(url, timeout)
            return url

        yield url, configured, True
        return
    url = running_server()
    if url:
        yield url, lambda: url, True
        return

    from flows.server import free_port

    port = free_port()
    servers: list[Any] = []

    def start() -> str:
        # the server's environment is this process' at the moment it spawns: possibly with the
        # workers' WORKER_ENVIRON and its own URL as PREFECT_API_URL (dask_client), both harmless to it
        from prefect.server.api.server import SubprocessASGIServer

        servers.append(SubprocessASGIServer(port=port))
        try:
            servers[0].start(timeout=max(1, int(timeout)))
        except Exception as exc:  # prefect raises RuntimeError/httpx errors of several kinds
            raise RuntimeUnavailable(
                f"could not start a temporary Prefect server within {timeout:.0f} s: {exc}. "
                "Raise prefect.startup_timeout_s in the profile or set PREFECT_API_URL to a running server."
            ) from None
        return servers[0].api_url

    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="btf-prefect-server")
    started = pool.submit(start)
    try:
        yield f"http://{LOOPBACK}:{port}/api", started.result, False
    finally:
        with contextlib.suppress(Exception):  # its error, if any, was raised by ready() already
            started.result()
        pool.shutdown()
        for server in servers:
            server.stop()


@contextlib.contextmanager
def prefect_api(profile: Profile) -> Iterator[str]:
    """Yield the URL of a Prefect API that answers, starting a temporary one if needed (see
    :func:`_starting_prefect_api` for which API is chosen).

    Raises
    ------
    RuntimeUnavailable
        When the configured server does not answer or the temporary one does not
        start within ``prefect.startup_timeout_s``; never hangs.
    """
    with _starting_prefect_api(profile) as (_url, ready, lasting):
        url = ready()
        with temporary_settings_of_run(url, lasting):
            yield url


def worker_environ(prefect_url: str | None) -> dict[str, str]:
    """The environment every Dask worker process of a run starts with: ``WORKER_ENVIRON``, the run's
    Prefect API and, where this process has them, the log levels and ``BTF_SHARED_DATA``."""
    environ = dict(WORKER_ENVIRON)
    if prefect_url:
        environ["PREFECT_API_URL"] = prefect_url
    for key in ("PREFECT_LOGGING_LEVEL", "PREFECT_LOGGING_TO_API_ENABLED", "BTF_SHARED_DATA"):
        if key in os.environ:
            environ[key] = os.environ[key]
    return environ


def start_cluster(profile: Profile, environ: dict[str, str]) -> Any:
    """Start the profile's Dask cluster, its workers with ``environ`` (:func:`worker_environ`).

    The starter is the kind's (``_CLUSTER_STARTERS``; ``local`` here, the others in :mod:`flows.clusters`).
    Every socket of a local cluster binds ``cluster.host`` (default 127.0.0.1), the scheduler's HTTP server
    ``cluster.dashboard_address`` (default the same host); a profile that binds beyond this machine
    without TLS gets one warning line per socket kind on stderr (:func:`exposure_warnings`). Close it
    with :func:`_close_quietly`, which does so without Dask's shutdown warnings.
    """
    import dask

    start = _CLUSTER_STARTERS[profile.kind]  # load_profile refused other kinds; `address` starts none
    for line in exposure_warnings(profile):
        print(line, file=sys.stderr)
    # distributed's nanny applies pre-spawn-environ to this process's os.environ too:
    # restore it afterwards, or a later run in this process would inherit a dead server's URL
    saved = {key: os.environ.get(key) for key in environ}
    try:
        with dask.config.set({"distributed.nanny.pre-spawn-environ": environ,
                              "distributed.worker.daemon": False}):
            try:
                return start(profile.cluster, environ)
            except Exception as exc:
                raise RuntimeUnavailable(f"could not start the Dask cluster of {profile.path}: {exc}") from exc
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


#: Seconds between the tries of :func:`_connect` to set up the workers of a running scheduler.
CONNECT_RETRY_S = 1.0


def _connect(profile: Profile, environ: dict[str, str]) -> Any:
    """A client of the running scheduler of an ``address`` profile, once it has a worker; one warning line
    on stderr when its workers lack part of ``environ`` (their owner starts them with it: docs/clusters.md)."""
    from distributed import Client

    from flows.clusters import environ_differences, security_of

    for line in exposure_warnings(profile):
        print(line, file=sys.stderr)
    address, timeout = profile.cluster["address"], float(profile.cluster.get("timeout_s", 60))
    try:
        client = Client(address, security=security_of(profile.cluster), timeout=f"{timeout}s")
    except Exception as exc:
        raise RuntimeUnavailable(f"could not connect to the Dask scheduler {address} of {profile.path}: {exc}") from exc
    deadline = time.monotonic() + timeout
    while True:
        try:
            client.wait_for_workers(1, timeout=max(deadline - time.monotonic(), 0.1))
            client.register_plugin(WorkerSetup(environ), name="btf-worker-setup")
            lacking = sorted({item for items in client.run(environ_differences, environ).values() for item in items})
            break
        except Exception as exc:
            # a worker that left while this client set the workers up (its connection closed: an OSError) is no
            # reason to fail while others may be there: try again until the profile's timeout
            if isinstance(exc, OSError) and time.monotonic() < deadline - CONNECT_RETRY_S:
                time.sleep(CONNECT_RETRY_S)
                continue
            client.close()
            raise RuntimeUnavailable(f"the Dask scheduler {address} of {profile.path} has no usable worker within "
                                     f"{timeout:.0f} s: {exc}") from exc
    if lacking:
        print(f"btf: warning: the workers of {address} did not start with {' '.join(lacking)}; btf set the thread "
              "counts and Prefect settings in them, but not the memory settings: start them with that environment "
              "(docs/clusters.md, 'address')", file=sys.stderr)
    return client


@contextlib.contextmanager
def dask_client(profile: Profile, prefect_url: str | None = None) -> Iterator[Any]:
    """Yield a ``distributed.Client`` of the profile's Dask cluster, with :func:`WorkerSetup` registered.

    An ``address`` profile's client connects to its running scheduler (:func:`_connect`). A ``local``
    profile's is the cluster a running ``btf server`` keeps (:func:`flows.server.server_cluster`) where it
    was started with this run's profile, worker environment and code; else, and for every other kind,
    one started here (:func:`start_cluster`) and closed on exit, the client first (:func:`_close_quietly`).
    """
    from distributed import Client

    from flows.server import server_cluster

    environ = worker_environ(prefect_url)
    client = None
    if profile.kind == "address":
        client = _connect(profile, environ)  # registers WorkerSetup before it checks the workers' environment
    elif profile.kind == "local" and (address := server_cluster(lambda: cluster_settings(profile, environ))):
        client = Client(address, timeout="10s")
        client.register_plugin(WorkerSetup(environ), name="btf-worker-setup")
    if client is not None:  # a cluster this run did not start: close only the client
        try:
            yield client
        finally:
            with contextlib.suppress(Exception):
                client.close(timeout=10)
        return
    cluster = start_cluster(profile, environ)
    client = None
    try:
        client = Client(cluster)  # with the cluster's security (TLS), where it has one
        client.register_plugin(WorkerSetup(environ), name="btf-worker-setup")
        yield client
    finally:
        _close_quietly(client, cluster)


def cluster_settings(profile: Profile, environ: dict[str, str]) -> dict[str, Any]:
    """What makes two Dask clusters interchangeable for a run: the profile's ``cluster:`` section, the
    workers' environment, this interpreter and the pipeline's code (each ``.py`` file's size and
    modification time: workers import it once, when they start). A ``btf server``'s cluster is used
    only by a run whose settings equal the ones it was started with."""
    from flows.server import code_version

    return {"cluster": dict(profile.cluster), "environ": dict(sorted(environ.items())),
            "python": sys.executable, "code": code_version()}


def _local_cluster(spec: dict[str, Any], environ: dict[str, str]) -> Any:
    """``distributed.LocalCluster`` of a ``kind: local`` profile section (keys: ``CLUSTER_KEYS['local']``); its
    nannies give the workers ``environ`` (``distributed.nanny.pre-spawn-environ``, set by :func:`start_cluster`)."""
    from distributed import LocalCluster

    dashboard = bool(spec.get("dashboard", False))
    return LocalCluster(
        n_workers=spec.get("n_workers", 2),
        threads_per_worker=spec.get("threads_per_worker", 1),
        memory_limit=spec.get("memory_limit", "4GiB"),
        processes=spec.get("processes", True),
        # scheduler, nannies and workers: None is LocalCluster's 127.0.0.1 over TCP (in-process: no socket)
        host=spec.get("host"),
        # the scheduler always serves HTTP (/metrics, worker addresses, logs): on the cluster's host, on
        # 8787 with the dashboard, else on a random port
        dashboard_address=dashboard_address(spec),
        scheduler_kwargs={"dashboard": dashboard},
        silence_logs=logging.getLogger("distributed").getEffectiveLevel(),   # WARNING; INFO with btf --verbose
    )


def _starter(name: str) -> Callable[[dict[str, Any], dict[str, str]], Any]:
    """A starter of :mod:`flows.clusters`, imported when it starts (dask_jobqueue, dask_kubernetes)."""
    def start(spec: dict[str, Any], environ: dict[str, str]) -> Any:
        from flows import clusters

        return getattr(clusters, name)(spec, environ)

    return start


#: How each cluster kind of ``CLUSTER_KEYS`` starts: ``(profile section, worker environment)`` -> a
#: ``distributed`` cluster. ``address`` starts none (:func:`_connect`).
_CLUSTER_STARTERS = {"local": _local_cluster, "slurm": _starter("jobqueue_cluster"),
                     "pbs": _starter("jobqueue_cluster"), "kubernetes": _starter("kubernetes_cluster")}

#: distributed's loggers that report the expected end of a closing cluster: at WARNING a worker process
#: killed or a task cancelled (``Worker process still alive after 4.0 seconds, killing``, ``Async
#: instruction ... cancelled``), at ERROR with a traceback a worker's heartbeat that met the scheduler's
#: closed connection (``Failed to communicate with scheduler during heartbeat``, a race of every close).
_CLOSE_LOGGERS = ("distributed",)

#: Their level while the cluster closes: the run's outcome is decided and reported by ``btf`` itself.
_CLOSE_LOG_LEVEL = logging.CRITICAL


def _raise_log_level(names: tuple[str, ...] = _CLOSE_LOGGERS) -> None:
    """Raise ``names`` to ``_CLOSE_LOG_LEVEL`` where they are at the quiet default (WARNING); a user's
    INFO (``btf --verbose``, ``DASK_LOGGING__DISTRIBUTED=info``) stays."""
    for name in names:
        logger = logging.getLogger(name)
        if logger.getEffectiveLevel() == logging.WARNING:
            logger.setLevel(_CLOSE_LOG_LEVEL)


#: Seconds an idle worker process gets to exit at the end of a run before its nanny kills it.
#: distributed's own grace is 4 s, which a loaded machine exceeds after a successful run
#: ("distributed.nanny - WARNING - Worker process still alive after 4.0 seconds, killing").
IDLE_WORKER_CLOSE_S = 30.0


async def _close_workers(cluster: Any, timeout: float) -> None:
    """Close every worker (its nanny and process) of ``cluster``, each given ``timeout`` seconds to exit."""
    import asyncio

    await asyncio.gather(*(worker.close(timeout=timeout, reason="btf-run-finished")
                           for worker in list(cluster.workers.values())), return_exceptions=True)


def _close_quietly(client: Any, cluster: Any) -> None:
    """Close ``client``, then the workers, then ``cluster``, without the warnings Dask prints on the way.

    After a run that finished, no task runs: each worker is asked to close and given
    ``IDLE_WORKER_CLOSE_S`` to exit, so that none is killed however loaded the machine is. After a
    failed run a worker may still be busy with a task of it: that one gets distributed's grace (4 s)
    to finish and is then killed, as before. What distributed logs on the way (``_CLOSE_LOGGERS``:
    the nanny's "still alive ... killing", the workers' "task cancelled" and a heartbeat's traceback
    against the closed scheduler) describes that expected end and is not printed. Closing
    the client first lets the scheduler release its tasks before the workers are asked to stop.
    """
    distributed_logger = logging.getLogger("distributed")
    level = distributed_logger.level
    try:
        idle = False
        if client is not None:
            with contextlib.suppress(Exception):
                idle = not any(client.processing().values())
            if getattr(cluster, "processes", False):  # in-process workers share this process's loggers
                with contextlib.suppress(Exception):  # a wedged worker must not hold up the close
                    client.sync(client._run, _raise_log_level, on_error="ignore", callback_timeout=5)
            with contextlib.suppress(Exception):
                client.close(timeout=10)
        _raise_log_level()
        from distributed import LocalCluster

        if idle and isinstance(cluster, LocalCluster):  # a job-queue cluster's "workers" are its jobs
            with contextlib.suppress(Exception):
                cluster.sync(_close_workers, cluster, IDLE_WORKER_CLOSE_S,
                             callback_timeout=IDLE_WORKER_CLOSE_S + 10)
        cluster.close(timeout=30)
    finally:
        distributed_logger.setLevel(level)


class WorkerSetup(WorkerPlugin):
    """Dask worker plugin: pins BLAS (threadpoolctl), OpenCV and torch to one thread (parallelism comes from
    Dask) and imports the pipeline's numerical stack when a worker starts, so that the first task of a run
    does not pay for it (about a second per worker on two cores; docs/architecture.md, "Execution").

    ``environ`` (:func:`worker_environ`): the keys a worker reads when it uses them
    (``flows.clusters.LATE_ENVIRON_KEYS``: the Prefect API, log levels, ``BTF_SHARED_DATA``) are set in its
    ``os.environ``, for the workers of an ``address`` profile, which someone else started; the thread
    counts are set here for them too, but the malloc settings only take effect at process start.
    """

    modules = ("tasks.ingest", "tasks.simulate", "tasks.resample")

    def __init__(self, environ: dict[str, str] | None = None):
        self.environ = dict(environ or {})
        self.client_pid = os.getpid()  # in-process (threaded) workers share the client's environment

    def setup(self, worker: Any) -> None:
        import importlib

        import cv2
        from threadpoolctl import threadpool_limits

        from flows.clusters import LATE_ENVIRON_KEYS

        if os.getpid() != self.client_pid:  # never in the client's own process: a run's URL would outlive it
            os.environ.update({key: value for key, value in self.environ.items() if key in LATE_ENVIRON_KEYS})
        cv2.setNumThreads(1)
        threadpool_limits(1)
        quiet_task_failures()
        for name in self.modules:
            importlib.import_module(name)
        if "torch" in sys.modules:
            sys.modules["torch"].set_num_threads(1)


@contextlib.contextmanager
def runtime(profile: Profile | str | os.PathLike | None = None) -> Iterator[tuple[Profile, str, Any]]:
    """Prefect API and Dask client for one run: ``(profile, prefect_url, client)``.

    ``profile`` is a :class:`Profile` from :func:`load_profile` (the CLI loads it before anything
    starts, so that a bad profile is bad input), or a path to load, or ``None`` for
    ``$BTF_CLUSTER_CONFIG`` or ``infra/local.yaml``.
    """
    if not isinstance(profile, Profile):
        profile = load_profile(profile)
    _quiet_before_prefect()
    # Prefect is imported (quiet_logs, seconds), a temporary Prefect server started (its own thread)
    # and the Dask cluster started at the same time; each failure is raised with its own message, and
    # what did start is stopped
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="btf-import-prefect") as pool:
        quieted = pool.submit(quiet_logs)
        with _starting_prefect_api(profile) as (url, ready, lasting), dask_client(profile, url) as client:
            quieted.result()
            url = ready()
            with temporary_settings_of_run(url, lasting), _recorded_in_reports(profile):
                yield profile, url, client


@contextlib.contextmanager
def _recorded_in_reports(profile: Profile) -> Iterator[None]:
    """Every ``report.json`` written during the run records ``profile`` (``tasks.report.RUN_PROFILE``)."""
    from tasks import report

    saved = dict(report.RUN_PROFILE)
    report.RUN_PROFILE.clear()
    report.RUN_PROFILE.update(profile.record())
    try:
        yield
    finally:
        report.RUN_PROFILE.clear()
        report.RUN_PROFILE.update(saved)


def cluster_spec(path: str | os.PathLike) -> str:
    """``btf cluster spec PROFILE``: the DaskCluster resource of a ``kubernetes`` profile as YAML, its
    containers' env the worker environment with the profile's Prefect API (:func:`worker_environ`).

    Raises
    ------
    ProfileError, ValueError
        The profile is bad or not of kind ``kubernetes`` (bad input).
    """
    from flows.clusters import cluster_spec_yaml

    profile = load_profile(path)
    return cluster_spec_yaml(profile, worker_environ(profile.prefect.get("api_url")))


#: Prefect's flow-run heartbeat thread sleeps in whole seconds and is joined when a flow run ends, so
#: every flow run (a demo has several) ended up to a second late (0.9 s of a 1-second ``btf ingest``,
#: measured with cProfile, docs/benchmarks.md). The heartbeats only feed server automations that
#: mark silent runs as crashed, which a default setup does not have; a user who configured one sets
#: ``PREFECT_FLOWS_HEARTBEAT_FREQUENCY`` and keeps them (docs/decisions.md).
HEARTBEAT_ENV = "PREFECT_FLOWS_HEARTBEAT_FREQUENCY"


def temporary_settings_of_run(api_url: str, lasting: bool) -> contextlib.AbstractContextManager:
    """Prefect settings of one run: its API; no flow-run heartbeats unless ``HEARTBEAT_ENV`` is set; and,
    for a ``lasting`` API (a ``btf server`` or one the user named), logs sent to it (the UI's page of
    each run shows them: Prefect's warnings and the stages' progress lines, :func:`flows.progress.say`)
    unless the user set ``PREFECT_LOGGING_TO_API_ENABLED``. A temporary server is stopped at the end of
    the run, so nobody reads its logs."""
    from prefect.settings import (PREFECT_API_URL, PREFECT_FLOWS_HEARTBEAT_FREQUENCY, PREFECT_LOGGING_TO_API_ENABLED,
                                  temporary_settings)

    updates: dict[Any, Any] = {PREFECT_API_URL: api_url}
    if lasting and _QUIET["to_api"]:
        updates[PREFECT_LOGGING_TO_API_ENABLED] = True
    if HEARTBEAT_ENV not in os.environ and "PREFECT_RUNNER_HEARTBEAT_FREQUENCY" not in os.environ:
        updates[PREFECT_FLOWS_HEARTBEAT_FREQUENCY] = None
    return temporary_settings(updates)
