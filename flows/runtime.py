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
import ipaddress
import logging
import os
import sys
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import yaml
from distributed import WorkerPlugin

from flows.server import LOOPBACK, RuntimeUnavailable, running_server  # noqa: F401  (RuntimeUnavailable: re-exported)

DEFAULT_PROFILE = Path(__file__).resolve().parents[1] / "infra" / "local.yaml"

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
#: material, docs/benchmarks.md).
WORKER_ENVIRON = {
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
    "NUMPY_MADVISE_HUGEPAGE": "0",
    "MALLOC_MMAP_THRESHOLD_": "4194304",
    "MALLOC_TRIM_THRESHOLD_": str(8 << 20),
}


class ProfileError(ValueError):
    """An execution profile is missing, not YAML, or names a key, type or cluster kind that does not
    exist; the one-line message names the file and the key and says what is allowed (bad input: the
    CLI exits ``EXIT_BAD_INPUT`` before Prefect or a cluster starts)."""


@dataclass(frozen=True)
class Profile:
    """A parsed and validated execution profile (see ``infra/local.yaml``); build it with
    :func:`load_profile`, which refuses what a cluster kind does not know."""

    path: str
    cluster: dict[str, Any] = field(default_factory=dict)
    prefect: dict[str, Any] = field(default_factory=dict)


_INT = (int,)
_NUMBER = (int, float)
_STR = (str,)
_BOOL = (bool,)
_TYPE_NAMES = {int: "an integer", float: "a number", str: "a string", bool: "true or false", type(None): "null"}

#: The keys of a profile's ``cluster:`` section, per cluster kind, with the types their values may have.
#: A later cluster kind (SLURM, Kubernetes) adds its row here and its starter in ``_CLUSTER_STARTERS``;
#: ``infra/local.yaml`` explains each key of the ``local`` kind.
CLUSTER_KEYS: dict[str, dict[str, tuple[type, ...]]] = {
    "local": {
        "kind": _STR,
        "n_workers": _INT,
        "threads_per_worker": _INT,
        "memory_limit": (str, int),       # "4GiB", bytes, or "auto"
        "processes": _BOOL,
        "dashboard": _BOOL,
        "host": _STR,                     # interface of the scheduler, nannies and workers [127.0.0.1]
        "dashboard_address": _STR,        # host:port of the scheduler's HTTP server [<host>:8787 or :0]
    },
}

#: The keys of a profile's ``prefect:`` section (every cluster kind).
PREFECT_KEYS: dict[str, tuple[type, ...]] = {
    "api_url": (str, type(None)),
    "startup_timeout_s": _NUMBER,
}

#: ``LOOPBACK`` (from :mod:`flows.server`): where a default run listens: every socket (scheduler, its HTTP
#: server, nannies, workers, dashboard; the temporary Prefect server and the ``btf server`` bind 127.0.0.1
#: by themselves) stays on this machine (docs/decisions.md).


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


def _yaml_problem(exc: yaml.YAMLError) -> str:
    """One line for a YAML error: its problem and where (PyYAML's own text spans several lines)."""
    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    mark = getattr(exc, "problem_mark", None)
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    return " ".join(f"{where}{problem}".split())


def _check_section(path: Path, section: str, values: Any, allowed: dict[str, tuple[type, ...]],
                   what: str) -> dict[str, Any]:
    if values is None:
        return {}
    if not isinstance(values, dict):
        raise ProfileError(f"execution profile {path}: '{section}' must be a mapping of keys "
                           f"({', '.join(allowed)}), not {type(values).__name__}")
    for key, value in values.items():
        if key not in allowed:
            raise ProfileError(f"execution profile {path}: unknown key '{section}.{key}'{what}; "
                               f"allowed keys: {', '.join(allowed)}")
        types = allowed[key]
        if not isinstance(value, types) or (isinstance(value, bool) and bool not in types):
            expected = " or ".join(_TYPE_NAMES[t] for t in types if not (t is int and float in types))
            raise ProfileError(f"execution profile {path}: '{section}.{key}' must be {expected}, "
                               f"not {value!r} ({type(value).__name__})")
    return dict(values)


def _check_values(path: Path, cluster: dict[str, Any], prefect: dict[str, Any]) -> None:
    for key in ("n_workers", "threads_per_worker"):
        if key in cluster and cluster[key] < 1:
            raise ProfileError(f"execution profile {path}: 'cluster.{key}' must be at least 1, not {cluster[key]}")
    if "memory_limit" in cluster and cluster["memory_limit"] != "auto":
        from dask.utils import parse_bytes

        try:
            if parse_bytes(cluster["memory_limit"]) <= 0:
                raise ValueError("not positive")
        except (ValueError, TypeError):
            raise ProfileError(f"execution profile {path}: 'cluster.memory_limit' must be a size like 4GiB "
                               f"(per worker), a number of bytes or auto, not {cluster['memory_limit']!r}") from None
    if "startup_timeout_s" in prefect and not prefect["startup_timeout_s"] > 0:
        raise ProfileError(f"execution profile {path}: 'prefect.startup_timeout_s' must be a number of "
                           f"seconds above 0, not {prefect['startup_timeout_s']!r}")


def load_profile(path: str | os.PathLike | None = None) -> Profile:
    """Read and validate an execution profile; ``None`` means ``$BTF_CLUSTER_CONFIG`` or the default.

    This is the one place a profile is checked: every key must exist for its section and cluster kind
    (``CLUSTER_KEYS``, ``PREFECT_KEYS``) and have a value of its type, so that a typo is named before
    Prefect or a cluster starts instead of reaching ``LocalCluster``.

    Raises
    ------
    ProfileError
        The file is missing or unreadable, not YAML (``!!python/...`` tags included), or names an
        unknown section, key or cluster kind, or a value of the wrong type; the message is one line
        that names the file and the key.
    """
    path = Path(path or os.environ.get("BTF_CLUSTER_CONFIG") or DEFAULT_PROFILE)
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ProfileError(
            f"execution profile {path} does not exist; pass --cluster with a file "
            f"shaped like {DEFAULT_PROFILE}"
        ) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ProfileError(f"execution profile {path} cannot be read: {exc}; pass --cluster with a readable "
                           "YAML file") from None
    except yaml.YAMLError as exc:
        raise ProfileError(f"execution profile {path} is not valid YAML ({_yaml_problem(exc)}); a profile holds "
                           f"plain keys and values only, shaped like {DEFAULT_PROFILE}") from None
    data = {} if data is None else data
    if not isinstance(data, dict):
        raise ProfileError(f"execution profile {path}: expected a mapping with 'cluster' and 'prefect' "
                           f"sections, not {type(data).__name__}")
    unknown = [key for key in data if key not in ("cluster", "prefect")]
    if unknown:
        raise ProfileError(f"execution profile {path}: unknown section '{unknown[0]}'; "
                           "allowed sections: cluster, prefect")
    raw_cluster = data.get("cluster") or {}
    kind = raw_cluster.get("kind", "local") if isinstance(raw_cluster, dict) else "local"
    if not isinstance(kind, str) or kind not in CLUSTER_KEYS:
        raise ProfileError(
            f"execution profile {path}: cluster kind {kind!r} is not supported yet "
            f"(supported: {', '.join(map(repr, CLUSTER_KEYS))}); "
            "SLURM and Kubernetes profiles arrive with the cluster issue"
        )
    cluster = _check_section(path, "cluster", data.get("cluster"), CLUSTER_KEYS[kind],
                             f" for cluster kind {kind!r}")
    prefect = _check_section(path, "prefect", data.get("prefect"), PREFECT_KEYS, "")
    _check_values(path, cluster, prefect)
    return Profile(str(path), cluster, prefect)


def _host_of(address: str) -> str:
    """The host of ``tcp://HOST``, ``HOST:PORT``, ``[V6]:PORT`` or ``:PORT`` ('' means every interface)."""
    address = address.split("://", 1)[-1]
    if address.startswith("["):
        return address[1:].split("]", 1)[0]
    if address.count(":") == 1:
        return address.split(":", 1)[0]
    return address


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # '' (every interface), 0.0.0.0 parses; a host name or interface IP may be public
        return False


def exposure_warnings(profile: Profile) -> list[str]:
    """One-line warnings for the sockets of ``profile``'s cluster that listen beyond this machine without TLS.

    A default profile binds everything to 127.0.0.1 and gets none. A profile that sets ``cluster.host``
    or ``cluster.dashboard_address`` off the loopback asked for it explicitly; it still gets a warning
    unless the Dask configuration sets up TLS (``distributed.comm.require-encryption`` or a
    ``tls://`` host for the scheduler and workers, ``distributed.scheduler.dashboard.tls.cert`` for the
    HTTP server), because the scheduler runs any code sent to it and its HTTP server serves metrics,
    worker addresses and logs, both without authentication.
    """
    import dask

    spec = profile.cluster
    warnings = []
    host = spec.get("host", LOOPBACK)
    comm_tls = host.startswith("tls://") or bool(dask.config.get("distributed.comm.require-encryption", False))
    if not _is_loopback(_host_of(host)) and not comm_tls:
        warnings.append(
            f"btf: warning: {profile.path}: the Dask scheduler and workers listen on "
            f"{_host_of(host) or 'every interface'} (cluster.host) without TLS, so anyone who reaches this "
            f"machine can run code on them; use host {LOOPBACK} or set distributed.comm.require-encryption "
            "and distributed.comm.tls.* in the Dask config"
        )
    http = _dashboard_address(spec)
    http_tls = bool(dask.config.get("distributed.scheduler.dashboard.tls.cert", None))
    if not _is_loopback(_host_of(http)) and not http_tls:
        warnings.append(
            f"btf: warning: {profile.path}: the Dask scheduler's HTTP server (dashboard, /metrics, worker "
            f"addresses and logs) listens on {http} without TLS or authentication; use "
            f"dashboard_address {LOOPBACK}:8787 or set distributed.scheduler.dashboard.tls.cert in the Dask config"
        )
    return warnings


def _dashboard_address(spec: dict[str, Any]) -> str:
    """``host:port`` of the scheduler's HTTP server: the profile's, else the cluster host on 8787 (dashboard) or
    a random port (it always serves /metrics); never the empty host, which distributed binds to 0.0.0.0."""
    if "dashboard_address" in spec:
        return spec["dashboard_address"]
    host = _host_of(spec.get("host", LOOPBACK)) or LOOPBACK
    host = f"[{host}]" if ":" in host else host
    return f"{host}:{8787 if spec.get('dashboard', False) else 0}"


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

    Every socket of the cluster binds ``cluster.host`` (default 127.0.0.1), the scheduler's HTTP server
    ``cluster.dashboard_address`` (default the same host); a profile that binds beyond this machine
    without TLS gets one warning line per socket kind on stderr (:func:`exposure_warnings`). Close it
    with :func:`_close_quietly`, which does so without Dask's shutdown warnings.
    """
    import dask

    start = _CLUSTER_STARTERS[profile.cluster.get("kind", "local")]  # load_profile refused other kinds
    for line in exposure_warnings(profile):
        print(line, file=sys.stderr)
    # distributed's nanny applies pre-spawn-environ to this process's os.environ too:
    # restore it afterwards, or a later run in this process would inherit a dead server's URL
    saved = {key: os.environ.get(key) for key in environ}
    try:
        with dask.config.set({"distributed.nanny.pre-spawn-environ": environ,
                              "distributed.worker.daemon": False}):
            try:
                return start(profile.cluster)
            except Exception as exc:
                raise RuntimeUnavailable(f"could not start the Dask cluster of {profile.path}: {exc}") from exc
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


@contextlib.contextmanager
def dask_client(profile: Profile, prefect_url: str | None = None) -> Iterator[Any]:
    """Yield a ``distributed.Client`` of the profile's Dask cluster, with :func:`WorkerSetup` registered.

    The cluster is the one a running ``btf server`` keeps (:func:`flows.server.server_cluster`) where
    it was started with this run's profile, worker environment and code; else one started here
    (:func:`start_cluster`) and closed on exit, the client first (:func:`_close_quietly`).
    """
    from distributed import Client

    from flows.server import server_cluster

    environ = worker_environ(prefect_url)
    address = server_cluster(cluster_settings(profile, environ))
    if address:
        client = Client(address, timeout="10s")
        try:
            client.register_plugin(WorkerSetup(), name="btf-worker-setup")
            yield client
        finally:
            with contextlib.suppress(Exception):
                client.close(timeout=10)
        return
    cluster = start_cluster(profile, environ)
    client = None
    try:
        client = Client(cluster)
        client.register_plugin(WorkerSetup(), name="btf-worker-setup")
        yield client
    finally:
        _close_quietly(client, cluster)


def cluster_settings(profile: Profile, environ: dict[str, str]) -> dict[str, Any]:
    """What makes two Dask clusters interchangeable for a run: the profile's ``cluster:`` section, the
    workers' environment, this interpreter and the pipeline's code (each ``.py`` file's size and
    modification time: workers import it once, when they start). A ``btf server``'s cluster is used
    only by a run whose settings equal the ones it was started with."""
    import hashlib

    root = Path(__file__).resolve().parents[1]
    code = hashlib.sha256()
    for package in ("btfcore", "tasks", "flows"):
        for path in sorted((root / package).rglob("*.py")):
            stat = path.stat()
            code.update(f"{path.relative_to(root)}:{stat.st_size}:{stat.st_mtime_ns};".encode())
    return {"cluster": dict(profile.cluster), "environ": dict(sorted(environ.items())),
            "python": sys.executable, "code": code.hexdigest()[:16]}


def _local_cluster(spec: dict[str, Any]) -> Any:
    """``distributed.LocalCluster`` of a ``kind: local`` profile section (keys: ``CLUSTER_KEYS['local']``)."""
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
        dashboard_address=_dashboard_address(spec),
        scheduler_kwargs={"dashboard": dashboard},
        silence_logs=logging.getLogger("distributed").getEffectiveLevel(),   # WARNING; INFO with btf --verbose
    )


#: How each cluster kind of ``CLUSTER_KEYS`` starts: its profile section -> a ``distributed`` cluster.
_CLUSTER_STARTERS = {"local": _local_cluster}

#: distributed's loggers that report, at WARNING, a worker process killed or a task cancelled while
#: closing (``Worker process still alive after 4.0 seconds, killing``, ``Async instruction ... cancelled``).
_CLOSE_LOGGERS = ("distributed",)


def _raise_log_level(names: tuple[str, ...] = _CLOSE_LOGGERS) -> None:
    """Raise ``names`` to ERROR where they are at the quiet default (WARNING); a user's INFO stays."""
    for name in names:
        logger = logging.getLogger(name)
        if logger.getEffectiveLevel() == logging.WARNING:
            logger.setLevel(logging.ERROR)


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
    to finish and is then killed, as before, and the nanny's "still alive ... killing" and the
    workers' "task cancelled" warnings, which describe that expected end, are not printed. Closing
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
        if distributed_logger.getEffectiveLevel() == logging.WARNING:
            distributed_logger.setLevel(logging.ERROR)
        if idle:
            with contextlib.suppress(Exception):
                cluster.sync(_close_workers, cluster, IDLE_WORKER_CLOSE_S,
                             callback_timeout=IDLE_WORKER_CLOSE_S + 10)
        cluster.close(timeout=30)
    finally:
        distributed_logger.setLevel(level)


class WorkerSetup(WorkerPlugin):
    """Dask worker plugin: pins OpenCV to one thread (parallelism comes from Dask) and imports the
    pipeline's numerical stack when a worker starts, so that the first task of a run does not pay
    for it (about a second per worker on two cores; docs/architecture.md, "Execution")."""

    modules = ("tasks.ingest", "tasks.simulate", "tasks.resample")

    def setup(self, worker: Any) -> None:
        import importlib

        import cv2

        cv2.setNumThreads(1)
        quiet_task_failures()
        for name in self.modules:
            importlib.import_module(name)


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
            with temporary_settings_of_run(url, lasting):
                yield profile, url, client


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
