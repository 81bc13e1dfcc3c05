"""Helpers shared by the benchmark scripts (not a benchmark: `make bench` runs ``bench_*.py`` only).

The scripts run as ``python benchmarks/bench_x.py``, so this folder is on
``sys.path`` and they import it as ``_measure``.

Every benchmark's JSON result holds a list ``"bars"`` of :func:`bar` verdicts, one per bar it
measures; ``benchmarks/summary.py`` prints them as one table (docs/benchmarks.md, "Running them").
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np


def bar(measure: str, value: float | None, goal: str, met: bool | None, issue: int | None) -> dict:
    """One verdict of a benchmark, as every ``bench_*.py`` lists them under ``"bars"`` in its JSON.

    Parameters
    ----------
    measure : str
        What ``value`` is, with its unit or as a ratio (``"ALS GFLOP/s / GEMM GFLOP/s"``).
    value : float or None
        The figure measured in this run; None when the run could not measure it (a peer that did
        not install, a skipped part: say why in ``goal``).
    goal : str
        The bar ``value`` is held to (``">= 0.8"``), including any condition beside it.
    met : bool or None
        Whether this run meets the goal; None when there is no verdict: a figure recorded without a
        goal, or a bar this run could not measure (``value`` None).
    issue : int or None
        The issue that set the goal (the latest one where an issue raised it).

    Returns
    -------
    dict
        ``{"measure", "value", "goal", "met", "issue"}`` with plain JSON types.
    """
    return {"measure": measure, "value": None if value is None else float(value), "goal": goal,
            "met": None if met is None else bool(met), "issue": issue}


def log(msg: str) -> None:
    """A progress line on stderr (stdout carries the JSON result), with the time and the 1-minute load."""
    print(f"[{time.strftime('%H:%M:%S')} load {os.getloadavg()[0]:.2f}] {msg}", file=sys.stderr, flush=True)


def best_seconds(fn: Callable[[], object], repeats: int = 3) -> float:
    """The shortest of ``repeats`` timed calls of ``fn``, after one untimed warm-up call."""
    fn()
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


def _rss() -> int:
    import psutil

    return psutil.Process().memory_info().rss


class WorkerRSS:
    """Samples the resident set size of every worker of a Dask ``client`` every ``interval`` seconds
    while the ``with`` block runs; ``samples`` holds them all, ``timeline`` ``(time.time(), largest
    RSS)`` per sample round, ``restarted`` whether the set of workers changed (Dask restarts a worker
    past 95 % of its memory limit)."""

    def __init__(self, client, interval: float = 0.2) -> None:
        self.client, self.interval = client, interval
        self.samples: list[int] = []
        self.timeline: list[tuple[float, int]] = []
        self.restarted = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def idle(self) -> int:
        """The largest worker RSS right now (call before the work starts)."""
        return max(self.client.run(_rss).values())

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                values = list(self.client.run(_rss).values())
                self.samples.extend(values)
                self.timeline.append((time.time(), max(values)))
            except Exception:  # a worker restarting between samples
                pass
            time.sleep(self.interval)

    def __enter__(self) -> "WorkerRSS":
        self._workers = set(self.client.scheduler_info()["workers"])
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.restarted = set(self.client.scheduler_info()["workers"]) != self._workers


def gemm_rate(m: int, kk: int, n: int, repeats: int = 3) -> float:
    """GFLOP/s of a float32 ``(m, kk) @ (kk, n)`` numpy GEMM, best of ``repeats``."""
    rng = np.random.default_rng(0)
    A = rng.standard_normal((m, kk), dtype=np.float32)
    B = rng.standard_normal((kk, n), dtype=np.float32)
    C = np.empty((m, n), np.float32)
    return 2.0 * m * kk * n / best_seconds(lambda: np.matmul(A, B, out=C), repeats) / 1e9


def torch_gemm_rate(m: int = 2048, k: int | None = None, n: int | None = None, repeats: int = 3, *,
                    transpose_a: bool = False, device: str = "cpu") -> float:
    """GFLOP/s of a float32 torch ``(m, k) @ (k, n)`` GEMM (square ``m`` by default; ``transpose_a``: A
    stored as (k, m)) on ``device`` at torch's current thread count, best of ``repeats`` (on CUDA
    synchronised, at torch's default: no TF32)."""
    import torch

    k, n = k or m, n or m
    g = torch.Generator().manual_seed(0)
    A = torch.randn((k, m) if transpose_a else (m, k), generator=g).to(device)
    A = A.T if transpose_a else A
    B = torch.randn((k, n), generator=g).to(device)
    C = torch.empty((m, n), device=device)

    def product() -> None:
        torch.matmul(A, B, out=C)
        if device != "cpu":
            torch.cuda.synchronize()
    product()
    return 2.0 * m * k * n / best_seconds(product, repeats) / 1e9


def disk_write_rate(folder: Path, n_bytes: int = 1 << 30) -> float:
    """GB/s of writing and fsync-ing ``n_bytes`` of random bytes to one file in ``folder``, best of 2."""
    data = np.random.default_rng(1).integers(0, 255, n_bytes, dtype=np.uint8)
    path = Path(folder) / "disk-probe.bin"

    def write() -> None:
        with open(path, "wb") as f:
            data.tofile(f)
            f.flush()
            os.fsync(f.fileno())
        path.unlink()

    return n_bytes / best_seconds(write, 2) / 1e9


def disk_read_rate(folder: Path, n_bytes: int = 1 << 30, block: int = 16 << 20) -> float:
    """GB/s of reading ``n_bytes`` from one file in ``folder`` past the page cache, best of 2.

    The file is written and fsync-ed once; before each read its pages are dropped from the page
    cache (``posix_fadvise(DONTNEED)``, which needs no privileges for clean pages), so the reads come
    from the disk. Read in ``block``-byte pieces into one reused buffer.
    """
    path = Path(folder) / "disk-read-probe.bin"
    piece = np.random.default_rng(2).integers(0, 255, block, dtype=np.uint8)
    with open(path, "wb") as f:
        for _ in range(max(1, n_bytes // block)):
            piece.tofile(f)
        f.flush()
        os.fsync(f.fileno())
    size = path.stat().st_size
    buffer = bytearray(block)

    def read() -> None:
        with open(path, "rb", buffering=0) as f:
            os.posix_fadvise(f.fileno(), 0, 0, os.POSIX_FADV_DONTNEED)
            while f.readinto(buffer):
                pass

    try:
        seconds = min(_timed(read) for _ in range(2))
    finally:
        path.unlink()
    return size / seconds / 1e9


def _timed(fn: Callable[[], object]) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start
