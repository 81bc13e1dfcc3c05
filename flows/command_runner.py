"""A process that has imported the pipeline once and forks one child per ``btf`` command (``btf server``).

A fresh ``btf`` process spends most of a tiny run's start-up importing: Prefect (about 1.6 s on two
idle cores), zarr, NumPy, SciPy and OpenCV, and the flows (docs/benchmarks.md, start-up). ``btf
server start`` also starts this runner (its own process, beside the Prefect server and the Dask
cluster of :mod:`flows.cluster_service`): it imports all of that, checks that no thread has
started (a fork copies only the forking thread), and listens on a Unix socket in the state folder
(``runner.sock``, readable and writable by its owner only).

A computing command (:func:`flows.server.forward`) sends it its arguments, working folder, environment, umask and
its standard input, output and error (the file descriptors themselves, ``SCM_RIGHTS``); the runner
forks, the child takes them over and runs :func:`flows.cli.main` as the command would, and the
exit status goes back to the command, which exits with it. The command forwards SIGINT, SIGTERM and
SIGHUP to the child (Ctrl-C interrupts the run as usual), and a child whose command went away is
interrupted. A command is forwarded only where the runner's imports are the ones it would make
itself: the same interpreter and code (:func:`flows.server.runner_fingerprint`), the same ``PREFECT_*`` and
``DASK_*`` environment (both configure logging and settings when imported) and no
``--verbose``/``--log-level``/``--quiet``; otherwise, or where the runner does not answer, the
command runs in its own process as without a server. ``BTF_NO_RUNNER=1`` turns forwarding off.

Usage: ``python -m flows.command_runner --state FILE``
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import importlib
import json
import os
import select
import signal
import socket
import sys
import threading
from pathlib import Path
from typing import Any

from flows.server import _HEADER, CHILD_ENV, _write_state, runner_fingerprint

#: What the runner imports before it forks: every flow and the tasks their drivers run.
PRELOAD = ("flows.cli", "flows.runtime", "flows.ingest", "flows.simulate", "flows.model", "flows.acquisition",
           "flows.resample", "flows.evaluate_acquisition", "tasks.ingest", "tasks.simulate", "tasks.model",
           "tasks.reconstruct", "tasks.resample", "tasks.report", "distributed", "prefect.flows",
           "prefect.flow_engine", "prefect.task_engine")

# ---- the runner ---------------------------------------------------------------------------------------------

def serve(state: Path) -> None:
    """Import :data:`PRELOAD`, listen on ``runner.sock`` beside ``state``, write ``state``, fork a child per
    request until SIGTERM or SIGINT, then remove both."""
    fingerprint = runner_fingerprint()           # the environment before the runtime's defaults are set
    from flows.runtime import _quiet_before_prefect, quiet_logs

    _quiet_before_prefect()
    quiet_logs()
    for name in PRELOAD:
        importlib.import_module(name)
    if threading.active_count() != 1:
        raise SystemExit(f"not serving: importing the pipeline started threads {threading.enumerate()}, "
                         "which a fork would not copy")
    path = state.with_name("runner.sock")
    with contextlib.suppress(FileNotFoundError):
        path.unlink()
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    old_umask = os.umask(0o177)
    try:
        listener.bind(str(path))
    finally:
        os.umask(old_umask)
    listener.listen(16)
    stop = []
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.append(True))
    _write_state(state, {"pid": os.getpid(), "socket": str(path), "fingerprint": fingerprint})
    print(f"command runner ready on {path}", flush=True)
    try:
        while not stop:
            with contextlib.suppress(InterruptedError):
                if select.select([listener], [], [], 1.0)[0]:
                    connection, _ = listener.accept()
                    _fork(connection, listener)
            with contextlib.suppress(ChildProcessError):
                while os.waitpid(-1, os.WNOHANG)[0]:
                    pass
    finally:
        for leftover in (state, path):
            with contextlib.suppress(FileNotFoundError):
                leftover.unlink()


def _receive(connection: socket.socket) -> tuple[dict[str, Any], list[int]]:
    """One request: a length-prefixed JSON document, with the command's three standard streams attached."""
    data, fds, _flags, _addr = socket.recv_fds(connection, 1 << 16, 3)
    while len(data) < _HEADER.size or len(data) < _HEADER.size + _HEADER.unpack_from(data)[0]:
        more = connection.recv(1 << 16)
        if not more:
            raise ConnectionError("request cut short")
        data += more
    (size,) = _HEADER.unpack_from(data)
    return json.loads(data[_HEADER.size:_HEADER.size + size]), fds


def _fork(connection: socket.socket, listener: socket.socket) -> None:
    """Fork a child that runs the request of ``connection``; the runner keeps nothing of it."""
    try:
        request, fds = _receive(connection)
    except (OSError, ValueError):
        connection.close()
        return
    if len(fds) != 3:
        for fd in fds:
            os.close(fd)
        connection.close()
        return
    pid = os.fork()
    if pid:
        for fd in fds:
            os.close(fd)
        connection.close()
        return
    try:                                          # the child: never returns into the runner's loop
        listener.close()
        code = _run_child(request, fds, connection)
    except BaseException:  # noqa: BLE001  (whatever happens, the child must not continue as the runner)
        code = 1
    os._exit(code)


def _run_child(request: dict[str, Any], fds: list[int], connection: socket.socket) -> int:
    """Take over the command's streams, folder and environment, run ``btf``, report the exit status."""
    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    for target, fd in enumerate(fds):
        os.dup2(fd, target)
        os.close(fd)
    sys.stdout.reconfigure(line_buffering=os.isatty(1))
    os.chdir(request["cwd"])
    os.umask(request["umask"])
    os.environ.clear()
    os.environ.update(request["environ"])
    os.environ[CHILD_ENV] = str(os.getpid())
    connection.sendall(f"{os.getpid()}\n".encode())

    def interrupt_when_gone() -> None:             # the command exited (killed): stop its run
        with contextlib.suppress(OSError):
            if not connection.recv(1):
                os.kill(os.getpid(), signal.SIGINT)

    threading.Thread(target=interrupt_when_gone, daemon=True, name="btf-runner-watch").start()
    from flows.cli import main

    try:
        code = main(request["argv"])
    except SystemExit as exc:                       # argparse's errors and --help
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    with contextlib.suppress(Exception):
        atexit._run_exitfuncs()                     # what a process does at exit (Prefect's log drain)
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    with contextlib.suppress(OSError):
        connection.sendall(f"exit {code}\n".encode())
    return code


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m flows.command_runner", description=__doc__.split("\n\n")[0])
    parser.add_argument("--state", required=True, type=Path, help="state file to write once it listens")
    serve(parser.parse_args(argv).state)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
