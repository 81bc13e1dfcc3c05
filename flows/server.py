"""A local Prefect server that outlives one ``btf`` command: ``btf server start|stop|status``.

Without one, every computing command starts a temporary Prefect server (10-30 s on two cores) and
stops it at the end. ``btf server start`` starts one that stays up, bound to 127.0.0.1 on a free
port, and writes its URL and process id to a state file (:func:`state_file`, no token or secret in
it); ``flows.runtime.prefect_api`` then uses it instead of starting a temporary one, unless the
execution profile's ``prefect.api_url`` or ``PREFECT_API_URL`` names another API. A state file whose
process is gone or whose URL does not answer is ignored, with one line saying so
(docs/architecture.md, "Execution").

This module starts only processes and reads only its state file: it imports no Prefect or Dask
code, so that ``btf --help`` stays fast.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

#: Where every socket of a default run listens, the ``btf server`` included: this machine only.
LOOPBACK = "127.0.0.1"

SERVER_HELP = ("A Prefect server that stays up between commands, on 127.0.0.1 and a free port: `start` starts it "
               "(and prints its URL; every later computing command reports to it instead of starting a "
               "temporary server, unless the profile's prefect.api_url or PREFECT_API_URL names another), "
               "`status` says whether it runs and answers, `stop` stops it. Its URL and process id are kept in "
               "$XDG_STATE_HOME/btf-pipeline/server.json (default ~/.local/state/...), its log beside it. "
               "Its runs are kept in Prefect's database (PREFECT_HOME, ~/.prefect) and shown by its UI at the "
               "URL without /api.")


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


def _is_server_process(pid: Any) -> bool:
    """Whether ``pid`` is a live process that runs a Prefect server (not a reused process id)."""
    if not isinstance(pid, int) or pid <= 0 or not is_alive(pid):
        return False
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:  # no /proc (macOS): the live pid is all we can check
        return True
    return b"prefect" in cmdline and b"server" in cmdline


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
    """What the state file says and whether it holds: ``{"status": "running" | "stopped" | "stale", ...}``.

    ``running``: its process runs and its URL answers ``/health``; ``stale``: a state file whose process
    is gone or whose URL does not answer (``reason`` says which); ``stopped``: no state file.
    """
    path = path or state_file()
    state = _read_state(path)
    if state is None:
        return {"status": "stopped", "state_file": str(path)}
    info = {**state, "state_file": str(path)}
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


def start_server(timeout: float = 90, path: Path | None = None) -> dict[str, Any]:
    """Start a ``btf server`` (or find the one running) and return its status.

    The server is ``prefect server start`` in its own session (it outlives this process and a
    terminal's Ctrl-C), bound to 127.0.0.1 on a free port, logging to ``server.log`` beside the state
    file. The state file is written once the server answers ``/health``.

    Raises
    ------
    RuntimeUnavailable
        The server exited or did not answer within ``timeout`` seconds (the message holds the end of
        its log); its process is stopped.
    """
    path = path or state_file()
    status = server_status(path)
    if status["status"] == "running":
        return {**status, "started_now": False}
    path.parent.mkdir(parents=True, exist_ok=True)
    log = path.with_name("server.log")
    port = free_port()
    url = f"http://{LOOPBACK}:{port}/api"
    with open(log, "ab") as log_file:
        process = subprocess.Popen(
            [sys.executable, "-m", "prefect", "server", "start", "--host", LOOPBACK, "--port", str(port),
             "--analytics-off"],
            stdin=subprocess.DEVNULL, stdout=log_file, stderr=subprocess.STDOUT, env=_server_environ(),
            start_new_session=True, cwd=str(path.parent),
        )
    deadline = time.monotonic() + timeout
    while not is_healthy(url, timeout=2.0):
        if process.poll() is not None or time.monotonic() > deadline:
            why = (f"exited with code {process.returncode}" if process.poll() is not None
                   else f"did not answer /health within {timeout:.0f} s")
            _stop_pid(process.pid)
            raise RuntimeUnavailable(f"the btf server (prefect server start on {url}) {why}: {_log_tail(log)} "
                                     f"(log: {log})")
        time.sleep(0.3)
    state = {"url": url, "pid": process.pid, "port": port, "host": LOOPBACK, "log": str(log),
             "started": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}
    _write_state(path, state)
    return {**state, "state_file": str(path), "status": "running", "started_now": True}


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
    """Stop the ``btf server`` of the state file (by its process id) and remove the state file.

    A state file whose process is not a Prefect server (gone, or its id reused) is removed without
    signalling anything.
    """
    path = path or state_file()
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
        result = start_server(args.timeout)
    elif args.action == "stop":
        result = stop_server()
    else:
        result = server_status()
    print(json.dumps(result, indent=2))
    return 0
