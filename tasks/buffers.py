"""Large buffers a task fills and reuses: mapped at once, page-aligned, kept per worker thread.

On the 2-core VM the first touch of fresh memory is a visible part of a task's time: ``numpy.empty``
asks the kernel for huge pages (``madvise``), whose first touch, with the kernel's ``defrag`` setting at
``madvise``, can wait for memory compaction (1.07 s against 0.16-0.22 s for 522 MB; docs/benchmarks.md,
2026-12-05). :func:`prefaulted` maps all pages at once; :func:`reused_buffer` keeps one such buffer per
name and worker thread, so that a worker's views, bands or blocks share it. Both are page-aligned, which
:func:`tasks.integrity.write_chunks_directly` needs to write chunks past the page cache.
"""

from __future__ import annotations

import mmap
import threading
from typing import Any

import numpy as np

__all__ = ["prefaulted", "reused_buffer"]


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
