"""Large buffers a task fills and reuses: mapped at once, page-aligned, kept per worker thread.

On the 2-core VM the first touch of fresh memory is a visible part of a task's time: ``numpy.empty``
asks the kernel for huge pages (``madvise``), whose first touch, with the kernel's ``defrag`` setting at
``madvise``, can wait for memory compaction (1.07 s against 0.16-0.22 s for 522 MB; docs/benchmarks.md,
2026-12-05). :func:`prefaulted` maps all pages at once; :func:`reused_buffer` keeps one such buffer per
name and worker thread, so that a worker's views, bands or blocks share it. Both are page-aligned, which
:func:`tasks.integrity.write_chunks_directly` needs to write chunks past the page cache.

:func:`heap_arrays` is for the tasks that make many short-lived arrays of a few megabytes instead
(the acquisition evaluation's bands): within it glibc serves them from its heap, reusing the pages, where
the workers' fixed mmap threshold (``flows.runtime.WORKER_ENVIRON``) would map and fault fresh ones for
each.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import mmap
import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

__all__ = ["HEAP_ARRAYS_BYTES", "heap_arrays", "prefaulted", "reused_buffer"]


def prefaulted(n: int, dtype: Any) -> np.ndarray:
    """An uninitialised, page-aligned ``(n,)`` array whose pages are all mapped at once (Linux
    ``MAP_POPULATE``). Workers already turn numpy's huge-page hint off (``NUMPY_MADVISE_HUGEPAGE=0``,
    docs/architecture.md, "Pitfalls"); this covers any other process too, with the same GEMM rate.
    Elsewhere (no ``MAP_POPULATE``, or empty), ``numpy.empty``. The memory is given back when the array
    is freed."""
    populate = getattr(mmap, "MAP_POPULATE", 0)
    nbytes = n * np.dtype(dtype).itemsize
    if not populate or nbytes == 0:
        return np.empty(n, dtype)
    return np.frombuffer(mmap.mmap(-1, nbytes, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | populate), dtype, n)


_workspace = threading.local()


def reused_buffer(name: str, shape: tuple[int, ...], dtype: Any) -> np.ndarray:
    """A per-thread :func:`prefaulted` array of ``shape`` that outlives the task (grown when a larger one
    is asked for): first touch of fresh memory costs about a fifth of an ingested view's work here
    (docs/benchmarks.md), so a worker's tasks share their large buffers."""
    buffers = _workspace.__dict__.setdefault("buffers", {})
    size, dtype = int(np.prod(shape)), np.dtype(dtype)
    flat = buffers.get(name)
    if flat is None or flat.size < size or flat.dtype != dtype:
        flat = buffers[name] = prefaulted(size, dtype)
    return flat[:size].reshape(shape)


#: Within :func:`heap_arrays`, allocations up to this size come from glibc's heap.
HEAP_ARRAYS_BYTES = 256 << 20
_M_MMAP_THRESHOLD = -3                   # glibc's mallopt parameter (malloc.h)
_GLIBC_DEFAULT_MMAP_THRESHOLD = 128 << 10
_heap = {"depth": 0, "lock": threading.Lock(), "libc": None}


def _libc() -> Any:
    """glibc with ``mallopt`` and ``malloc_trim``, or False elsewhere (musl, macOS)."""
    if _heap["libc"] is None:
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            _heap["libc"] = libc if hasattr(libc, "mallopt") and hasattr(libc, "malloc_trim") else False
        except OSError:
            _heap["libc"] = False
    return _heap["libc"]


@contextmanager
def heap_arrays(threshold: int = HEAP_ARRAYS_BYTES) -> Iterator[None]:
    """Serve allocations up to ``threshold`` bytes from glibc's heap while inside, then give its free
    pages back.

    The workers fix glibc's mmap threshold at 4 MiB so that model fits do not fragment the heap
    (``flows.runtime.WORKER_ENVIRON``); above it every array is a fresh mapping whose pages fault in on
    first touch and are unmapped when it is freed. A task that makes hundreds of temporaries of 5-50 MB
    (one acquisition-evaluation band: 35 reconstructions and their scores) pays that for each; from the
    heap the pages are reused (one band task 4.35 s -> 3.69 s, system time 1.29 s -> 0.72 s;
    docs/benchmarks.md, 2026-12-05). On leaving, the threshold returns to the process' setting
    (``MALLOC_MMAP_THRESHOLD_``, else glibc's 128 KiB) and ``malloc_trim(0)`` returns the heap's free
    pages, so the worker holds no more between tasks than before. Nested or concurrent uses (threads of
    one worker) keep the raised threshold until the last leaves. A no-op without glibc."""
    libc = _libc()
    if not libc:
        yield
        return
    with _heap["lock"]:
        if _heap["depth"] == 0:
            libc.mallopt(_M_MMAP_THRESHOLD, int(threshold))
        _heap["depth"] += 1
    try:
        yield
    finally:
        with _heap["lock"]:
            _heap["depth"] -= 1
            if _heap["depth"] == 0:
                libc.mallopt(_M_MMAP_THRESHOLD, _process_mmap_threshold())
                libc.malloc_trim(0)


def _process_mmap_threshold() -> int:
    """The process' own mmap threshold: ``MALLOC_MMAP_THRESHOLD_`` (the workers', ``flows.runtime.WORKER_ENVIRON``),
    else glibc's initial 128 KiB (glibc reads the variable only as a number, as here)."""
    value = os.environ.get("MALLOC_MMAP_THRESHOLD_", "")
    return int(value) if value.isdigit() else _GLIBC_DEFAULT_MMAP_THRESHOLD
