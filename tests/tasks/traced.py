"""Calls measured where nothing else allocates (the Bonn readers' and writers' memory bounds).

tracemalloc counts the allocations of every thread of a process. A long pytest process keeps Dask
and Prefect threads from earlier tests, and their allocations would be charged to the call (CI
once saw 276 kB of them in a 108 kB bound). So the call runs in a fresh interpreter.
"""

from __future__ import annotations

import importlib
import inspect
import json
import subprocess
import sys
import tracemalloc
from pathlib import Path
from typing import Any, Callable

_RUN = ("import json, os, runpy, sys; sys.path.insert(0, os.path.dirname(sys.argv[1])); "
        "f = runpy.run_path(sys.argv[1])[sys.argv[2]]; print(json.dumps(f(*json.loads(sys.argv[3]))))")


def fresh_call(func: Callable[..., Any], *args: Any) -> Any:
    """``func(*args)`` in a fresh interpreter started in the repository root: ``func`` a top-level function
    of its file (the file is run, not imported, with its folder on ``sys.path``), ``args`` and the result plain JSON."""
    out = subprocess.run([sys.executable, "-c", _RUN, inspect.getfile(func), func.__name__, json.dumps(args)],
                         capture_output=True, text=True, check=True, cwd=Path(__file__).resolve().parents[2])
    return json.loads(out.stdout.strip().splitlines()[-1])


def _peak(name: str, *args: str) -> list:
    """Call ``name`` once untraced (lazy imports, caches), then traced: ``[peak bytes, exception name]``."""
    module, attr = name.rsplit(".", 1)
    f = getattr(importlib.import_module(module), attr)

    def call() -> str | None:
        try:
            f(*args)
        except Exception as exc:  # noqa: BLE001 - the caller checks which
            return type(exc).__name__
        return None

    call()
    tracemalloc.start()
    raised = call()
    return [tracemalloc.get_traced_memory()[1], raised]


def traced_peak(func: Callable[..., Any], *args: Any) -> tuple[int, str | None]:
    """``(peak bytes, name of the exception raised or None)`` of ``func(*args)`` (a module-level function;
    ``args`` passed as strings) in a fresh interpreter."""
    peak, raised = fresh_call(_peak, f"{func.__module__}.{func.__qualname__}", *map(str, args))
    return int(peak), raised
