"""Helpers shared by the benchmark scripts (not a benchmark: `make bench` runs ``bench_*.py`` only).

The scripts run as ``python benchmarks/bench_x.py``, so this folder is on
``sys.path`` and they import it as ``_measure``.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Callable

import numpy as np


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


def torch_gemm_rate(n: int = 2048, repeats: int = 3) -> float:
    """GFLOP/s of a float32 torch ``(n, n) @ (n, n)`` GEMM at torch's current thread count, best of ``repeats``."""
    import torch

    g = torch.Generator().manual_seed(0)
    A, B = torch.randn((n, n), generator=g), torch.randn((n, n), generator=g)
    C = torch.empty((n, n))
    return 2.0 * n**3 / best_seconds(lambda: torch.matmul(A, B, out=C), repeats) / 1e9
