"""Fault injection for tests: a process SIGKILLs itself at a named point of a stage.

A testing hook, off unless an environment variable names a point (docs/architecture.md,
"Kill points"). The points sit at the few central places every writing stage passes:

================================  ==========================================================
point                             where
================================  ==========================================================
``store-creating``                a new store's skeleton is built at ``.X.zarr.creating``, not yet
                                  renamed into place (:func:`tasks.staging.finish_store`); ``btf acquire``:
                                  a new run, nothing written to its output yet
``store-created``                 the new store (or staging store) is in place, no chunk written yet;
                                  ``btf acquire``: its empty step journal is in place
``chunk-done``                    the driver has awaited one more finished task, whose resume marker
                                  is on disk (:func:`tasks.compute.wait_all`); ``btf acquire``: one
                                  more step is recorded in its journal (:func:`tasks.adaptive_acquire.open_journal`)
``chunk-written``                 a worker task has written a chunk's data but not yet its resume
                                  marker (one line before each marker write), or computed a result
                                  whose record is its marker (an evaluation's scores record)
``commit-start``                  a staged replacement is complete, before the first rename of
                                  :func:`tasks.staging.commit_staged`
``commit-between-renames``        the old output is renamed aside, the new one not yet in place
``file-writing``                  a single-file output (Bonn file, PNG, EXR, model, samples, a plan's
                                  JSON and CSV, `evaluate ingest`'s report) is computed, its temporary
                                  file beside its path not yet written (:func:`tasks.staging.write_file`;
                                  ``btf acquire``: each step's plan files, then the final ``plan.json``)
``file-replace``                  such a file is written beside its path, before the rename that puts
                                  it in place
================================  ==========================================================

``BTF_KILL_AT=POINT`` or ``BTF_KILL_AT=POINT:N``: the process that reaches ``POINT`` for the
``N``-th time (default 1; each process counts its own) writes one line to its standard error and
SIGKILLs itself, as ``kill -9`` would: no ``finally``, no ``atexit``, no flush.

``BTF_KILL_WORKER_ONCE=SENTINEL`` or ``SENTINEL:N``: a Dask worker process running a task kills
itself at its ``N``-th ``chunk-written`` point (default 1), but only if it can create the file
``SENTINEL`` exclusively (``O_EXCL``), so that exactly one worker dies once: its nanny starts a
new worker, the scheduler retries the task elsewhere (one failure of
``distributed.scheduler.allowed-failures``, 3 by default) and the run completes. The sentinel
holds ``pid point occurrence`` of the killed worker.
"""

from __future__ import annotations

import os
import signal
from collections import Counter

#: The variable naming the point (and occurrence) at which a process kills itself.
KILL_AT = "BTF_KILL_AT"
#: The variable naming the sentinel file of the once-only worker kill.
KILL_WORKER_ONCE = "BTF_KILL_WORKER_ONCE"
#: The worker-side point, between a chunk's data and its resume marker.
CHUNK_WRITTEN = "chunk-written"

#: Occurrences of each point in this process, counted only while a variable is set.
_seen: Counter[str] = Counter()


def kill_point(name: str) -> None:
    """SIGKILL this process here if ``BTF_KILL_AT`` (or, on a worker, ``BTF_KILL_WORKER_ONCE``) says so.

    Returns at once (two dictionary look-ups) when neither variable is set.

    Parameters
    ----------
    name : str
        The point, one of the table of this module.
    """
    at = os.environ.get(KILL_AT)
    if at is not None:
        point, n = _point_and_count(at)
        if point == name:
            _seen[name] += 1
            if _seen[name] == n:
                _die(f"btf: {KILL_AT}={at}: process {os.getpid()} killed at {name} (occurrence {n})\n")
    if name == CHUNK_WRITTEN and KILL_WORKER_ONCE in os.environ:
        _kill_worker_once(os.environ[KILL_WORKER_ONCE])


def _point_and_count(spec: str) -> tuple[str, int]:
    """``("chunk-done", 3)`` from ``"chunk-done:3"``; a spec without ``:N`` means the first occurrence."""
    head, _, tail = spec.rpartition(":")
    return (head, int(tail)) if head and tail.isdigit() else (spec, 1)


def _kill_worker_once(spec: str) -> None:
    """Kill this Dask worker at its N-th chunk if the sentinel of ``spec`` can still be created."""
    try:
        from distributed import get_worker

        get_worker()
    except (ImportError, ValueError):
        return                                          # not inside a Dask worker's task: never the driver
    sentinel, n = _point_and_count(spec)
    key = f"{KILL_WORKER_ONCE}={sentinel}"
    _seen[key] += 1
    if _seen[key] < n:
        return
    try:
        fd = os.open(sentinel, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    except FileExistsError:
        return                                          # a worker was killed already
    os.write(fd, f"{os.getpid()} {CHUNK_WRITTEN} {_seen[key]}\n".encode())
    os.close(fd)
    _die(f"btf: {KILL_WORKER_ONCE}={spec}: worker process {os.getpid()} killed at {CHUNK_WRITTEN} "
         f"(occurrence {_seen[key]})\n")


def _die(line: str) -> None:
    os.write(2, line.encode())
    os.kill(os.getpid(), signal.SIGKILL)
