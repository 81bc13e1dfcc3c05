"""The environment of a ``btf`` subprocess in a test (imported by the test modules of this folder)."""

from __future__ import annotations

import os
from pathlib import Path

#: Variables a ``btf`` subprocess must not inherit from the test process: the session's Prefect API and
#: profile, and the defaults ``flows.runtime`` writes into ``os.environ`` when a test runs a command in
#: process (``PREFECT_LOGGING_TO_API_ENABLED=false`` would read as the user's choice and keep a btf
#: server's run logs from its API).
NOT_INHERITED = ("PREFECT_API_URL", "BTF_CLUSTER_CONFIG", "PREFECT_LOGGING_TO_API_ENABLED")


def btf_environ(state_home: Path, **extra: str) -> dict[str, str]:
    """This process' environment without :data:`NOT_INHERITED`, with ``XDG_STATE_HOME`` and ``extra``."""
    environ = {key: value for key, value in os.environ.items() if key not in NOT_INHERITED}
    return {**environ, "XDG_STATE_HOME": str(state_home), **extra}


def live_processes(*, parent: int | None = None, group: int | None = None) -> list[int]:
    """Process ids of live (not zombie) processes whose parent is ``parent`` or whose process group is
    ``group`` (read from ``/proc``)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rpartition(")")[2].split()
        except OSError:
            continue
        if fields[0] in ("Z", "X"):
            continue
        if (parent is not None and int(fields[1]) == parent) or (group is not None and int(fields[2]) == group):
            found.append(int(stat.parent.name))
    return found
