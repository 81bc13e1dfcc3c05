"""Real ``btf`` command lines in forked processes, for the kill matrix (tests/flows/test_kill_matrix.py).

A ``multiprocessing`` fork server imports the pipeline once (Prefect, Dask, Zarr, every flow); each
command is a fresh child forked from it that runs ``flows.cli.main`` with its own environment and
its standard output and error in files, as `btf server`'s command runner does
(docs/architecture.md, "Execution"). A child that SIGKILLs itself (``BTF_KILL_AT``) ends with exit
code -9, which the parent sees as it would a real ``btf`` process's.
"""

from __future__ import annotations

import atexit
import os
import sys

#: What the fork server imports once, so that a child starts in milliseconds.
PRELOAD = ["kill_runner", "prefect", "distributed", "zarr", "matplotlib.pyplot", "flows.cli", "flows.runtime",
           "flows.simulate", "flows.ingest", "flows.resample", "flows.model", "flows.acquisition",
           "flows.import_btf", "flows.superres", "tasks.simulate", "tasks.ingest", "tasks.ingest_raw",
           "tasks.resample", "tasks.model", "tasks.reconstruct", "tasks.report", "tasks.bonn.import_btf",
           "tasks.superres", "torch", "btfcore.superres.training", "flows.superres_cli", "flows.import_cli",
           "tasks.ingest_images", "tasks.export", "flows.evaluate_acquisition", "tasks.evaluate_acquisition",
           "tasks.evaluate_superres"]


def run_cli(argv: list[str], environ: dict[str, str], stdout: str, stderr: str) -> None:
    """In the forked child: ``btf ARGV`` with ``environ`` added, output to the files ``stdout`` and ``stderr``;
    exits with the command's exit code."""
    os.environ.update(environ)
    for target, path in ((1, stdout), (2, stderr)):
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(fd, target)
        os.close(fd)
    from flows.cli import main

    code = main(argv)
    atexit._run_exitfuncs()                        # what a process does at exit (Prefect's log drain)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
