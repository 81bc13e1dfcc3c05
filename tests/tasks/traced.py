"""Peak memory of one call, measured where nothing else allocates (the Bonn readers' memory bounds).

tracemalloc counts the allocations of every thread of a process. A long pytest process keeps Dask
and Prefect threads from earlier tests, and their allocations would be charged to the call (CI
once saw 276 kB of them in a 108 kB bound). So the call runs in a fresh interpreter, once untraced
(lazy imports, caches) and once traced.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any, Callable

_CODE = """
import importlib, json, sys, tracemalloc
mod, name = sys.argv[1].rsplit(".", 1)
f = getattr(importlib.import_module(mod), name)
def call():
    try:
        f(*sys.argv[2:])
    except Exception as exc:
        return type(exc).__name__
err = call()
tracemalloc.start()
err = call()
print(json.dumps([tracemalloc.get_traced_memory()[1], err]))
"""


def traced_peak(func: Callable[..., Any], *args: Any) -> tuple[int, str | None]:
    """``(peak bytes, name of the exception raised or None)`` of ``func(*args)`` (a module-level function;
    ``args`` passed as strings) in a fresh interpreter."""
    out = subprocess.run([sys.executable, "-c", _CODE, f"{func.__module__}.{func.__qualname__}", *map(str, args)],
                         capture_output=True, text=True, check=True, cwd=Path(__file__).resolve().parents[2])
    peak, err = json.loads(out.stdout.strip().splitlines()[-1])
    return int(peak), err
