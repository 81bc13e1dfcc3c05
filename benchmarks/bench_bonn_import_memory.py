"""Benchmark: `btf import-btf` memory is bounded by its tasks, not by the file.

Writes a synthetic single-precision DFMF (32 views x 32 lights = 1,024 rows, 256 x 256 texels,
K = 1,100 components per channel: about 865 MB, mostly SxV) with the project's own writer
(tasks.bonn.dfmf.write_dfmf, SxV generated block by block so the writer never holds it), then
imports it (tasks.bonn.import_btf.import_btf) on a LocalCluster of two single-threaded worker
processes limited to 200 MiB each, so the file is more than 4x one worker's limit (and 2x both
together). While the import runs, every worker's resident set size and the driver's are sampled
every 0.2 s. Reported:

* ``file_over_worker_limit`` = file bytes / one worker's memory limit;
* ``peak_worker_rss_mb`` and ``peak_over_limit`` = the largest sampled worker RSS / limit;
* ``idle_worker_rss_mb``: a worker's RSS before the import (Python, numpy, zarr, distributed);
* ``peak_driver_rss_mb``;
* ``restarted``: whether any worker was restarted (Dask restarts a worker past 95 % of its limit);
* ``no_limit``: the same import on workers without a memory limit (tasks of the default size),
  for the throughput;
* throughput: ``file_mb_per_s`` (file bytes / import seconds), ``output_mb_per_s`` (decoded
  float32 bytes / s) and ``decode_gflop_per_s`` (2 n_lv n_tx sum(K) / s), next to
  ``gemm_gflop_per_s_1thread`` (numpy float32 GEMM on one thread, as in a worker) x 2 workers.

Bar (issue 18): the peak worker RSS stays under the limit, no worker restarted, on a file at least 4x
one worker's limit (``"bars"``).

The file and the store are deleted at the end. Usage: ``python benchmarks/bench_bonn_import_memory.py``
(``--small`` or ``--quick`` for a quick run with a 1/8 file and the same limit: smaller than the limit,
so it exercises the code, not the bar).
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from _measure import WorkerRSS, bar, best_seconds, log

LIMIT_BYTES = 200 << 20


class _RandomRows:
    """A ``(n, k)`` float32 matrix of seeded random rows, generated when sliced (never held whole)."""

    ndim = 2

    def __init__(self, n: int, k: int, seed: int, scale: float) -> None:
        self.shape, self.seed, self.scale = (n, k), seed, scale

    def __getitem__(self, key: slice) -> np.ndarray:
        start, stop, _ = key.indices(self.shape[0])
        rng = np.random.default_rng((self.seed, start))
        return (rng.standard_normal((stop - start, self.shape[1]), dtype=np.float32) * self.scale)


def write_file(path: Path, n_v: int, n_l: int, side: int, k: int) -> None:
    from tasks.bonn.dfmf import write_dfmf
    from tasks.bonn.header import make_header

    rng = np.random.default_rng(0)
    views = np.stack([rng.uniform(0, 1.3, n_v), rng.uniform(-np.pi, np.pi, n_v)], -1)
    lights = np.stack([rng.uniform(0, 1.3, n_l), rng.uniform(-np.pi, np.pi, n_l)], -1)
    header = make_header(views, lights, side, side)
    U = [rng.standard_normal((n_v * n_l, k), dtype=np.float32) / np.sqrt(k) for _ in range(3)]
    SxV = [_RandomRows(side * side, k, seed=c, scale=0.1) for c in range(3)]
    S = [np.ones(k, np.float32) for _ in range(3)]
    write_dfmf(path, header, 0, np.zeros(3), np.eye(3), S, U, SxV, scalar_size=4)


def _gemm_rate_1thread(n: int = 1024) -> float:
    from threadpoolctl import threadpool_limits

    a = np.random.default_rng(0).standard_normal((n, n), dtype=np.float32)
    b = a.T.copy()
    c = np.empty_like(a)
    with threadpool_limits(1):
        return 2.0 * n**3 / best_seconds(lambda: np.matmul(a, b, out=c)) / 1e9


class _DriverRSS:
    def __init__(self, interval: float = 0.2) -> None:
        import psutil

        self.proc, self.interval, self.samples = psutil.Process(), interval, []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.samples.append(self.proc.memory_info().rss)
            time.sleep(self.interval)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


def main() -> int:
    from distributed import Client, LocalCluster

    from tasks.bonn.import_btf import import_btf

    small = "--small" in sys.argv or "--quick" in sys.argv
    n_v, n_l, side, k = (32, 32, 256, 1100) if not small else (32, 32, 128, 512)
    scratch = Path(tempfile.mkdtemp(prefix="bench-bonn-import-"))
    try:
        src = scratch / "synthetic_dfmf.btf"
        log(f"writing {src} ({n_v} x {n_l} rows, {side} x {side} texels, K = {k} float32)")
        start = time.perf_counter()
        write_file(src, n_v, n_l, side, k)
        write_seconds = time.perf_counter() - start
        file_bytes = src.stat().st_size
        log(f"wrote {file_bytes / 1e6:.0f} MB in {write_seconds:.1f} s; GEMM rate ...")
        gemm = _gemm_rate_1thread()
        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, memory_limit=LIMIT_BYTES,
                          dashboard_address=None) as cluster, Client(cluster) as client:
            client.run(lambda: __import__("tasks.bonn.import_btf"))    # the modules a task loads
            rss = WorkerRSS(client)
            idle = rss.idle()
            log(f"idle worker RSS {idle / 2**20:.0f} MiB; importing")
            with rss, _DriverRSS() as driver:
                start = time.perf_counter()
                summary = import_btf(src, scratch / "imported.zarr", client)
                seconds = time.perf_counter() - start
        store_bytes = sum(f.stat().st_size for f in (scratch / "imported.zarr").rglob("*") if f.is_file())
        shutil.rmtree(scratch / "imported.zarr")
        log("again without a memory limit (tasks of the default TASK_BYTES), for the throughput")
        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, memory_limit=0,
                          dashboard_address=None) as cluster, Client(cluster) as client:
            start = time.perf_counter()
            free = import_btf(src, scratch / "imported-free.zarr", client)
            free_seconds = time.perf_counter() - start
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    peak = max(rss.samples) if rss.samples else 0
    n_lv, n_tx = n_v * n_l, side * side
    decode_seconds = seconds - summary["hash_seconds"]
    result = {
        "benchmark": "bonn-import-memory", "date": time.strftime("%Y-%m-%d"),
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs", "small": small,
        "file": {"format": "DFMF float32", "rows": n_lv, "texels": n_tx, "components_per_channel": k,
                 "bytes": file_bytes, "write_seconds": round(write_seconds, 1)},
        "workers": 2, "threads_per_worker": 1, "worker_limit_mb": round(LIMIT_BYTES / 2**20),
        "file_over_worker_limit": round(file_bytes / LIMIT_BYTES, 2),
        "idle_worker_rss_mb": round(idle / 2**20, 1),
        "peak_worker_rss_mb": round(peak / 2**20, 1),
        "peak_over_limit": round(peak / LIMIT_BYTES, 3),
        "peak_driver_rss_mb": round(max(driver.samples) / 2**20, 1),
        "restarted": rss.restarted, "rss_samples": len(rss.samples),
        "import_seconds": round(seconds, 2), "hash_seconds": summary["hash_seconds"],
        "tasks": summary["tasks"], "chunks": summary["chunks"], "store_bytes": store_bytes,
        "file_mb_per_s": round(file_bytes / 1e6 / seconds, 1),
        "output_mb_per_s": round(n_lv * n_tx * 12 / 1e6 / seconds, 1),
        "decode_gflop_per_s": round(2.0 * n_lv * n_tx * 3 * k / 1e9 / decode_seconds, 2),
        "gemm_gflop_per_s_1thread": round(gemm, 2),
        "decode_over_2x_gemm": round(2.0 * n_lv * n_tx * 3 * k / 1e9 / decode_seconds / (2 * gemm), 3),
        "no_limit": {"import_seconds": round(free_seconds, 2), "tasks": free["tasks"],
                     "file_mb_per_s": round(file_bytes / 1e6 / free_seconds, 1),
                     "decode_gflop_per_s": round(2.0 * n_lv * n_tx * 3 * k / 1e9 / free_seconds, 2)},
        "load_average_1min_at_end": round(os.getloadavg()[0], 2),
        "bars": [bar("peak worker RSS / worker memory limit", round(peak / LIMIT_BYTES, 3),
                     f"< 1, no restart, file >= 4x the limit (here {file_bytes / LIMIT_BYTES:.2f}x)",
                     peak < LIMIT_BYTES and not rss.restarted and file_bytes >= 4 * LIMIT_BYTES, 18)],
    }
    print(json.dumps(result, indent=2))
    return 0 if peak < LIMIT_BYTES and not rss.restarted else 1


if __name__ == "__main__":
    sys.exit(main())
