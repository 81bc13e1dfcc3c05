"""A local Prefect server and Dask cluster that outlive one ``btf`` command: ``btf server start|stop|status``.

Without one, every computing command starts a temporary Prefect server (10-30 s on two cores) and a
Dask cluster, and stops both at the end. ``btf server start`` starts one that stays up, bound to 127.0.0.1 on a free
port, and writes its URL and process id to a state file (:func:`state_file`, no token or secret in
it); ``flows.runtime.prefect_api`` then uses it instead of starting a temporary one, unless the
execution profile's ``prefect.api_url`` or ``PREFECT_API_URL`` names another API. A state file whose
process is gone or whose URL does not answer is ignored, with one line saying so
(docs/architecture.md, "Execution"). Beside it, :mod:`flows.cluster_service` keeps the profile's
Dask cluster, which :func:`server_cluster` offers to runs started with the same settings, and
:mod:`flows.command_runner` keeps a process with the pipeline imported, to which :func:`forward`
hands a command.

This module starts only processes and reads only its state files: it imports no Prefect or Dask
code, so that ``btf --help`` stays fast.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import hashlib
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

#: Where every socket of a default run listens, the ``btf server`` included: this machine only.
LOOPBACK = "127.0.0.1"

SERVER_HELP = ("A Prefect server, a Dask cluster and a process with the pipeline imported, kept up between "
               "commands on 127.0.0.1. `start` starts the three (the cluster of the execution profile: --cluster "
               "or the default) and prints their addresses. Every later computing command then reports to that "
               "server instead of starting a temporary one (unless the profile's prefect.api_url or "
               "PREFECT_API_URL names another); runs on that cluster where its profile, log level and the "
               "pipeline's code are the ones the cluster was started with (else it starts its own and says why); "
               "and, from a shell with the same PREFECT_*/DASK_* settings, runs in a fork of the imported "
               "process, which saves the imports' seconds (not with --verbose, --log-level, --quiet or "
               "BTF_NO_RUNNER=1). `status` says whether they run, `stop` stops them and the commands running in "
               "them. Their addresses and process ids are in $XDG_STATE_HOME/btf-pipeline/ (server.json, "
               "cluster.json, runner.json; default ~/.local/state/...), their logs beside them. The runs are kept "
               "in Prefect's database (PREFECT_HOME, ~/.prefect) and shown by its UI at the URL without /api.")


class RuntimeUnavailable(RuntimeError):
    """Prefect or the Dask cluster could not be started; the message says why (exit 3)."""


def state_file() -> Path:
    """The state file of the ``btf server``: ``$XDG_STATE_HOME/btf-pipeline/server.json``, by default
    under ``~/.local/state``."""
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "btf-pipeline" / "server.json"


def _read_state(path: Path) -> dict[str, Any] | None:
    """The state file's content, or None where there is none; an unreadable one is an empty dict."""
    try:
        state = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError):
        return {}
    return state if isinstance(state, dict) else {}


def is_alive(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie (exited, waiting to be reaped)."""
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, PermissionError):  # gone, or another user's
        return False
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:  # no /proc (macOS): the signal is all we can check
        return True
    return stat.rpartition(")")[2].split()[0] not in ("Z", "X")


def _runs(pid: Any, *words: bytes) -> bool:
    """Whether ``pid`` is a live process whose command line holds ``words`` (not a reused process id)."""
    if not isinstance(pid, int) or pid <= 0 or not is_alive(pid):
        return False
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:  # no /proc (macOS): the live pid is all we can check
        return True
    return all(word in cmdline for word in words)


def _is_server_process(pid: Any) -> bool:
    """Whether ``pid`` is a live process that runs a Prefect server."""
    return _runs(pid, b"prefect", b"server")


#: The module a ``btf server``'s Dask cluster runs in (its own process, beside the Prefect server).
CLUSTER_SERVICE = "flows.cluster_service"

#: What each key of :func:`flows.runtime.cluster_settings` means, for the line that says why a run
#: does not use the ``btf server``'s cluster.
_SETTING_NAMES = {"cluster": "cluster section of the profile", "environ": "worker environment (log level, "
                  "Prefect API, BTF_SHARED_DATA)", "python": "Python interpreter", "code": "pipeline code"}


def code_version() -> str:
    """A hash of the size and modification time of every ``.py`` file of btfcore, tasks and flows: a
    process that imported the pipeline earlier (the ``btf server``'s workers and command runner) holds
    the code of that moment, and serves a command only while this hash is unchanged."""
    import hashlib

    root = Path(__file__).resolve().parents[1]
    code = hashlib.sha256()
    for package in ("btfcore", "tasks", "flows"):
        for path in sorted((root / package).rglob("*.py")):
            stat = path.stat()
            code.update(f"{path.relative_to(root)}:{stat.st_size}:{stat.st_mtime_ns};".encode())
    return code.hexdigest()[:16]


def cluster_state_file(path: Path | None = None) -> Path:
    """The state file of the ``btf server``'s Dask cluster: ``cluster.json`` beside :func:`state_file`."""
    return (path or state_file()).with_name("cluster.json")


#: The module of the ``btf server``'s command runner (a third process, :mod:`flows.command_runner`).
COMMAND_RUNNER = "flows.command_runner"


def runner_state_file(path: Path | None = None) -> Path:
    """The state file of the ``btf server``'s command runner: ``runner.json`` beside :func:`state_file`."""
    return (path or state_file()).with_name("runner.json")


def _service_status(state_path: Path, module: str, keys: tuple[str, ...]) -> dict[str, Any] | None:
    """``keys`` of the state file of a ``btf server`` process running ``module``, its state file, log and
    ``status``: running, or stale (its process is gone; ``reason``); None without a state file."""
    state = _read_state(state_path)
    if state is None:
        return None
    info = {**{key: state.get(key) for key in keys}, "state_file": str(state_path),
            "log": str(state_path.with_suffix(".log"))}
    if not _runs(state.get("pid"), module.encode()):
        return {**info, "status": "stale", "reason": f"process {state.get('pid')} is not running"}
    return {**info, "status": "running"}


def _cluster_status(path: Path | None = None) -> dict[str, Any] | None:
    """The server's Dask cluster (address, process, profile, settings) and its status."""
    return _service_status(cluster_state_file(path), CLUSTER_SERVICE, ("address", "pid", "profile", "settings"))


def _runner_status(path: Path | None = None) -> dict[str, Any] | None:
    """The server's command runner (process, socket) and its status."""
    return _service_status(runner_state_file(path), COMMAND_RUNNER, ("pid", "socket"))


def server_cluster(settings: Callable[[], dict[str, Any]], path: Path | None = None) -> str | None:
    """The scheduler address of the ``btf server``'s Dask cluster where it runs and was started with
    ``settings()`` (:func:`flows.runtime.cluster_settings` of this run, computed only where a cluster
    runs: it hashes the code), else None.

    A run whose settings differ (another profile, log level or Prefect API, edited code) starts its own
    cluster, with one line on stderr that says which setting differs and how to restart the server's.
    """
    status = _cluster_status(path)
    if status is None:
        return None
    if status["status"] != "running":
        print(f"btf: ignoring the btf server's Dask cluster ({status['state_file']}): {status['reason']} "
              "(`btf server stop` and `btf server start` restart it)", file=sys.stderr)
        return None
    if not str(status["address"]).startswith(("tcp://", "tls://")):
        print(f"btf: not using the btf server's Dask cluster {status['address']}: its workers are threads of "
              "the server's process, which another process cannot reach (a profile with processes: true can be "
              "shared)", file=sys.stderr)
        return None
    wanted = settings()
    differ = [_SETTING_NAMES.get(key, key) for key in wanted if (status["settings"] or {}).get(key) != wanted[key]]
    if differ:
        print(f"btf: not using the btf server's Dask cluster {status['address']}: this run's "
              f"{' and '.join(differ)} {'differ' if len(differ) > 1 else 'differs'} from the ones it was started with, so this run starts its own "
              "(`btf server stop` and `btf server start` restart it with the current ones)", file=sys.stderr)
        return None
    return status["address"]


def recorded_server_url(path: Path | None = None) -> str | None:
    """The URL in the state file of a ``btf server`` whose process runs, unchecked otherwise (no HTTP
    request, no import: for a first line printed before anything starts); None without one."""
    state = _read_state(path or state_file())
    if not state or not _is_server_process(state.get("pid")) or not isinstance(state.get("url"), str):
        return None
    return state["url"]


def is_healthy(api_url: str, timeout: float = 2.0) -> bool:
    """Whether the Prefect API at ``api_url`` answers ``/health`` with 200 within ``timeout`` seconds."""
    import httpx

    try:
        return httpx.get(f"{api_url.rstrip('/')}/health", timeout=timeout).status_code == 200
    except httpx.HTTPError:
        return False


def server_status(path: Path | None = None) -> dict[str, Any]:
    """What the state files say and whether it holds: ``{"status": "running" | "stopped" | "stale", ...}``.

    ``running``: its process runs and its URL answers ``/health``; ``stale``: a state file whose process
    is gone or whose URL does not answer (``reason`` says which); ``stopped``: no state file. ``cluster``
    is the state of the server's Dask cluster (address, process, status), where there is one.
    """
    path = path or state_file()
    state = _read_state(path)
    cluster = _cluster_status(path)
    if cluster is not None:
        cluster.pop("settings", None)
    runner = _runner_status(path)
    extra = {**({"cluster": cluster} if cluster is not None else {}),
             **({"runner": runner} if runner is not None else {})}
    if state is None:
        return {"status": "stopped", "state_file": str(path), **extra}
    info = {**state, "state_file": str(path), **extra}
    if not _is_server_process(state.get("pid")):
        return {**info, "status": "stale", "reason": f"process {state.get('pid')} is not running"}
    if not isinstance(state.get("url"), str) or not is_healthy(state["url"]):
        return {**info, "status": "stale", "reason": f"{state.get('url')} does not answer /health"}
    return {**info, "status": "running"}


def running_server(path: Path | None = None) -> str | None:
    """The API URL of a running, healthy ``btf server``, else None.

    A stale state file (process gone, URL not answering) is ignored, with one line on stderr that
    says so and how to clear it.
    """
    status = server_status(path)
    if status["status"] == "stale":
        print(f"btf: ignoring the btf server state file {status['state_file']}: {status['reason']} "
              "(`btf server start` replaces it, `btf server stop` removes it)", file=sys.stderr)
    return status["url"] if status["status"] == "running" else None


def free_port(host: str = LOOPBACK) -> int:
    """A TCP port on ``host`` that is free now (the OS picks it)."""
    with contextlib.closing(socket.socket(socket.AF_INET, socket.SOCK_STREAM)) as sock:
        sock.bind((host, 0))
        return sock.getsockname()[1]


def _server_environ() -> dict[str, str]:
    """The server's environment: this one, with analytics off and the UI on unless the user chose otherwise."""
    environ = dict(os.environ)
    environ.pop("PREFECT_API_URL", None)  # the server is the API; it reports to no other
    environ.setdefault("DO_NOT_TRACK", "1")
    environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    environ.setdefault("PREFECT_UI_ENABLED", "true")  # the runs' pages: the one UI a user would open
    return environ


def _write_state(path: Path, state: dict[str, Any]) -> None:
    """Write the state file atomically (a reader never sees half of it), readable by its owner only."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(".json.partial")
    fd = os.open(partial, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as file:
        json.dump(state, file, indent=2)
    os.replace(partial, path)


def _log_tail(log: Path, n_lines: int = 5) -> str:
    with contextlib.suppress(OSError):
        lines = [line for line in log.read_text(errors="replace").splitlines() if line.strip()]
        return " | ".join(lines[-n_lines:])
    return ""


def _spawn(argv: list[str], log: Path, cwd: Path, environ: dict[str, str] | None = None) -> subprocess.Popen:
    """Start ``argv`` in its own session (it outlives this process and a terminal's Ctrl-C), logging to
    ``log``, with ``environ`` (default :func:`_server_environ`)."""
    with open(log, "ab") as log_file:
        return subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=log_file, stderr=subprocess.STDOUT,
                                env=_server_environ() if environ is None else environ, start_new_session=True,
                                cwd=str(cwd))


def _wait_for(ready: Any, process: subprocess.Popen, deadline: float, what: str, log: Path) -> None:
    """Wait until ``ready()``; raise :class:`RuntimeUnavailable` (and stop ``process``) if it exits first
    or ``deadline`` passes."""
    while not ready():
        if process.poll() is not None or time.monotonic() > deadline:
            why = (f"exited with code {process.returncode}" if process.poll() is not None
                   else "did not start in time")
            _stop_pid(process.pid)
            raise RuntimeUnavailable(f"the btf server's {what} {why}: {_log_tail(log)} (log: {log})")
        time.sleep(0.3)


def start_server(timeout: float = 90, path: Path | None = None, profile: str | None = None) -> dict[str, Any]:
    """Start a ``btf server`` (or find the one running) and return its status.

    The server is three processes, each in its own session and logging beside the state file, started
    at the same time: ``prefect server start`` bound to 127.0.0.1 on a free port (``server.log``); the
    Dask cluster of the execution profile ``profile`` (default: ``$BTF_CLUSTER_CONFIG`` or
    ``infra/local.yaml``), started by :mod:`flows.cluster_service`, its workers reporting to that
    server (``cluster.log``); and the command runner of :mod:`flows.command_runner`, with this
    process' environment, so that commands from the same shell match it (``runner.log``). Each state
    file is written once its process answers. A server that runs without its cluster or runner (one
    exited) gets a new one.

    Raises
    ------
    RuntimeUnavailable
        A process exited or did not answer within ``timeout`` seconds (the message holds the end of
        its log); what was started is stopped.
    """
    path = path or state_file()
    status = server_status(path)
    cluster_running = (status.get("cluster") or {}).get("status") == "running"
    runner_running = (status.get("runner") or {}).get("status") == "running"
    if status["status"] == "running" and cluster_running and runner_running:
        return {**status, "started_now": False}
    path.parent.mkdir(parents=True, exist_ok=True)
    deadline = time.monotonic() + timeout
    url, server = status.get("url"), None
    if status["status"] != "running":
        port = free_port()
        url = f"http://{LOOPBACK}:{port}/api"
        server = _spawn([sys.executable, "-m", "prefect", "server", "start", "--host", LOOPBACK,
                         "--port", str(port), "--analytics-off"], path.with_name("server.log"), path.parent)
    root = Path(__file__).resolve().parents[1]
    cluster_path, cluster_log, cluster = cluster_state_file(path), path.with_name("cluster.log"), None
    if not cluster_running:
        with contextlib.suppress(FileNotFoundError):
            cluster_path.unlink()  # a stale one
        cluster = _spawn([sys.executable, "-m", CLUSTER_SERVICE, "--state", str(cluster_path), "--prefect-url",
                          url, *(["--profile", profile] if profile else [])], cluster_log, root)
    runner_path, runner_log, runner = runner_state_file(path), path.with_name("runner.log"), None
    if not runner_running:
        with contextlib.suppress(FileNotFoundError):
            runner_path.unlink()
        runner = _spawn([sys.executable, "-m", COMMAND_RUNNER, "--state", str(runner_path)], runner_log, root,
                        environ=dict(os.environ))
    try:
        if server is not None:
            _wait_for(lambda: is_healthy(url, timeout=2.0), server, deadline,
                      f"Prefect server (prefect server start on {url})", path.with_name("server.log"))
            _write_state(path, {"url": url, "pid": server.pid, "port": int(url.rsplit(":", 1)[1].split("/")[0]),
                                "host": LOOPBACK, "log": str(path.with_name("server.log")),
                                "started": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")})
        if cluster is not None:
            _wait_for(lambda: (_cluster_status(path) or {}).get("status") == "running", cluster, deadline,
                      f"Dask cluster ({CLUSTER_SERVICE})", cluster_log)
        if runner is not None:
            _wait_for(lambda: (_runner_status(path) or {}).get("status") == "running", runner, deadline,
                      f"command runner ({COMMAND_RUNNER})", runner_log)
    except RuntimeUnavailable:
        for process in (server, cluster, runner):
            if process is not None:
                _stop_pid(process.pid)
        if server is not None:
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
        raise
    return {**server_status(path), "started_now": True}


def _stop_pid(pid: int, grace: float = 10.0) -> None:
    """SIGTERM the server's process group (it leads its own session), then SIGKILL after ``grace`` s."""
    for sig, wait in ((signal.SIGTERM, grace), (signal.SIGKILL, 5.0)):
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(pid, sig)
        deadline = time.monotonic() + wait
        while time.monotonic() < deadline:
            with contextlib.suppress(ChildProcessError):
                os.waitpid(pid, os.WNOHANG)  # reap it where this process started it
            if not is_alive(pid):
                return
            time.sleep(0.1)


def stop_server(path: Path | None = None) -> dict[str, Any]:
    """Stop the ``btf server`` of the state files (its Prefect server and Dask cluster, by process id)
    and remove the state files.

    A state file whose process is not the one it names (gone, or its id reused) is removed without
    signalling anything.
    """
    path = path or state_file()
    runner = _read_state(runner_state_file(path))
    if runner is not None:
        if _runs(runner.get("pid"), COMMAND_RUNNER.encode()):
            _stop_pid(runner["pid"])  # and the commands it runs: they are in its process group
        with contextlib.suppress(FileNotFoundError):
            runner_state_file(path).unlink()
    cluster = _read_state(cluster_state_file(path))
    if cluster is not None:
        if _runs(cluster.get("pid"), CLUSTER_SERVICE.encode()):
            _stop_pid(cluster["pid"], grace=40.0)  # it closes its workers first (flows.cluster_service)
        with contextlib.suppress(FileNotFoundError):
            cluster_state_file(path).unlink()
    state = _read_state(path)
    if state is None:
        return {"status": "stopped", "state_file": str(path), "stopped_now": False}
    pid = state.get("pid")
    stopped_now = _is_server_process(pid)
    if stopped_now:
        _stop_pid(pid)
    with contextlib.suppress(FileNotFoundError):
        path.unlink()
    return {"status": "stopped", "state_file": str(path), "pid": pid, "url": state.get("url"),
            "stopped_now": stopped_now}


def add_server_arguments(p: argparse.ArgumentParser) -> None:
    """Arguments of ``btf server``: the action and the start-up timeout."""
    p.add_argument("action", choices=("start", "stop", "status"), help="start, stop or show the btf server")
    p.add_argument("--timeout", type=float, default=90.0, metavar="S",
                   help="start: seconds to wait for the server to answer [default: 90]")


def run_server(args: argparse.Namespace) -> int:
    """``btf server start|stop|status``: print the server's status as JSON; exit 0 (3 if it cannot start)."""
    if args.action == "start":
        result = start_server(args.timeout, profile=args.cluster)
    elif args.action == "stop":
        result = stop_server()
    else:
        result = server_status()
    print(json.dumps(result, indent=2))
    return 0


#: Set in a forked child: its ``btf`` does not forward again, and its ready line says where it runs.
CHILD_ENV = "BTF_RUNNER_CHILD"

_HEADER = struct.Struct("!I")


def _environ_key(environ: dict[str, str]) -> str:
    """Hash of the ``PREFECT_*`` and ``DASK_*`` variables of ``environ`` (values may be secrets: only the hash is kept)."""
    items = sorted((k, v) for k, v in environ.items() if k.startswith(("PREFECT_", "DASK_")))
    return hashlib.sha256(json.dumps(items).encode()).hexdigest()[:16]


def runner_fingerprint(environ: dict[str, str] | None = None) -> dict[str, str]:
    """What a command and the runner must share for a forwarded run to import what it would itself."""
    return {"python": sys.executable, "code": code_version(),
            "environ": _environ_key(dict(os.environ if environ is None else environ))}


def forward(argv: list[str], detail_flags: bool, path: Path | None = None) -> int | None:
    """Run ``btf argv`` in a child of the ``btf server``'s runner and return its exit status, or None
    where it cannot be forwarded (no runner, another fingerprint, ``detail_flags`` (``--verbose``,
    ``--log-level`` or ``--quiet``: they configure logging before Prefect is imported), or
    ``BTF_NO_RUNNER``), in which case the caller runs the command itself."""
    if (detail_flags or os.environ.get(CHILD_ENV) or os.environ.get("BTF_NO_RUNNER")
            or threading.current_thread() is not threading.main_thread()):  # signals are forwarded from there
        return None
    try:
        state = json.loads(runner_state_file(path).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(state, dict) or state.get("fingerprint") != runner_fingerprint():
        return None
    connection = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        connection.connect(str(state.get("socket")))
        request = json.dumps({"argv": list(argv), "cwd": os.getcwd(), "environ": dict(os.environ),
                              "umask": _umask()}).encode()
        socket.send_fds(connection, [_HEADER.pack(len(request)) + request], [0, 1, 2])
        reader = connection.makefile("rb")
        child = int(reader.readline() or b"0")
    except (OSError, ValueError):
        connection.close()
        return None                                  # nothing ran: run it here
    if not child:
        connection.close()
        return None
    previous = {sig: signal.signal(sig, lambda sig, _frame: _signal(child, sig))
                for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:
        for line in reader:
            if line.startswith(b"exit "):
                return int(line.split()[1])
        print(f"btf: the run (process {child} of the btf server's command runner) ended without an exit "
              "status; see the server's log (`btf server status`)", file=sys.stderr)
        return 1
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        connection.close()


def _signal(pid: int, sig: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, sig)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
