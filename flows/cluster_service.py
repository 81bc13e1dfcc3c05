"""The Dask cluster a ``btf server`` keeps up between commands (its own process, started by
:func:`flows.server.start_server`).

Starting a local cluster costs a tiny run about two seconds of its start-up (two worker processes
that import the numerical stack) and closing it a few tenths more. The server's cluster is started
once, with the execution profile, worker environment (:func:`flows.runtime.worker_environ`, its
Prefect API the server's), interpreter and code it records in its state file
(:func:`flows.runtime.cluster_settings`); a later run whose settings are the same connects a client
to it instead of starting its own (:func:`flows.runtime.dask_client`), and one whose settings differ
starts its own, saying why (docs/architecture.md, "Execution").

Runs until SIGTERM or SIGINT, then closes its workers and removes its state file.

Usage: ``python -m flows.cluster_service --state FILE --prefect-url URL [--profile YAML]``
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import sys
import threading
from pathlib import Path

from flows.runtime import (DEFAULT_PROFILE, _close_quietly, _quiet_before_prefect, cluster_settings, load_profile,
                           start_cluster, worker_environ)
from flows.server import _write_state


def serve(state: Path, prefect_url: str, profile_path: str | None = None) -> None:
    """Start the profile's cluster, write ``state`` (address, process id, settings), wait for SIGTERM
    or SIGINT, then close the cluster and remove ``state``."""
    import os

    from distributed import Client

    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    profile = load_profile(profile_path)
    if profile.kind != "local":  # other kinds start their cluster per run (docs/clusters.md)
        print(f"{profile.path}: a btf server keeps a local cluster only; it starts {DEFAULT_PROFILE}'s", flush=True)
        profile = load_profile(DEFAULT_PROFILE)
    _quiet_before_prefect()  # the same worker environment a command's runtime() computes
    environ = worker_environ(prefect_url)
    cluster = start_cluster(profile, environ)
    client = None
    try:
        client = Client(cluster)
        _write_state(state, {"address": cluster.scheduler_address, "pid": os.getpid(), "profile": profile.path,
                             "log": str(state.with_name("cluster.log")),
                             "settings": cluster_settings(profile, environ)})
        print(f"Dask cluster {cluster.scheduler_address} ready (profile {profile.path})", flush=True)
        while not stop.wait(1.0):
            pass
    finally:
        with contextlib.suppress(FileNotFoundError):
            state.unlink()
        _close_quietly(client, cluster)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m flows.cluster_service", description=__doc__.split("\n\n")[0])
    parser.add_argument("--state", required=True, type=Path, help="state file to write once the cluster runs")
    parser.add_argument("--prefect-url", required=True, help="the Prefect API the workers report to")
    parser.add_argument("--profile", default=None, help="execution profile [default: $BTF_CLUSTER_CONFIG "
                        "or infra/local.yaml]")
    args = parser.parse_args(argv)
    serve(args.state, args.prefect_url, args.profile)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
