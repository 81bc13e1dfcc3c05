"""Benchmark: ingest memory is bounded by the chunk (one view), not by the capture.

Simulates a bonn-dome2 capture of the first two turntable positions (22 views,
about 2.8 GB of raw frames) and ingests it on a LocalCluster whose two
workers are limited to 1 GiB each, so the capture is more than twice one
worker's limit (and larger than both together). While the ingest runs, each
worker's resident set size is sampled every 0.2 s. Reported:

* ``capture_over_worker_limit`` = raw bytes / one worker's memory limit;
* ``peak_worker_rss_mb`` and ``peak_over_limit`` = the largest sampled RSS / limit;
* ``view_chunk_mb`` = raw bytes of one view (the unit of work);
* whether any worker was restarted (Dask restarts a worker past 95 % of its limit).

Bar (issue 3): peak worker RSS under the limit, no restart, on a capture at least twice one worker's
limit (``"bars"``).

Usage: ``python benchmarks/bench_ingest_memory.py``
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

from _measure import WorkerRSS, bar

LIMIT = "1GiB"
LIMIT_BYTES = 1 << 30


def main() -> int:
    from flows.runtime import runtime
    from tasks.ingest import ingest_capture
    from tasks.simulate import SimulationConfig, simulate_database
    from tasks.stores import open_capture_store

    scratch = Path(tempfile.mkdtemp(prefix="bench-memory-"))
    try:
        config = SimulationConfig(device="bonn-dome2", n_materials=1, seed=0, classes=("leather",), n_turntable=2)
        with runtime() as (_p, _u, client):
            capture = simulate_database(config, scratch / "db", client).stores[0]
        store = open_capture_store(capture)
        raw_bytes = store.raw.nbytes
        view_bytes = raw_bytes // (store.n_turn * store.n_cam)
        profile = scratch / "small-workers.yaml"
        profile.write_text(f"cluster: {{kind: local, n_workers: 2, threads_per_worker: 1, memory_limit: {LIMIT}}}\n"
                           "prefect: {api_url: null, startup_timeout_s: 90}\n")
        with runtime(profile) as (_p, _u, client), WorkerRSS(client) as rss:
            start = time.perf_counter()
            ingest_capture(capture, scratch / "btf.zarr", client)
            seconds = time.perf_counter() - start
        samples, restarted = rss.samples, rss.restarted
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    peak = max(samples)
    result = {
        "benchmark": "ingest-memory", "date": time.strftime("%Y-%m-%d"),
        "machine": f"{platform.node()} {os.cpu_count()} cores", "command": "python benchmarks/bench_ingest_memory.py",
        "data": "bonn-dome2, 2 turntable positions (22 views), 1 leather, single-LED",
        "raw_gb": round(raw_bytes / 1e9, 3), "worker_memory_limit": LIMIT,
        "capture_over_worker_limit": round(raw_bytes / LIMIT_BYTES, 2),
        "view_chunk_mb": round(view_bytes / 1e6, 1),
        "peak_worker_rss_mb": round(peak / 1e6, 1), "peak_over_limit": round(peak / LIMIT_BYTES, 3),
        "rss_samples": len(samples), "worker_restarted": restarted,
        "ingest_s": round(seconds, 2), "raw_mb_per_s": round(raw_bytes / 1e6 / seconds, 1),
        "bars": [bar("peak worker RSS / worker memory limit", round(peak / LIMIT_BYTES, 3),
                     f"< 1, no restart, capture >= 2x the limit (here {raw_bytes / LIMIT_BYTES:.2f}x)",
                     peak < LIMIT_BYTES and not restarted and raw_bytes >= 2 * LIMIT_BYTES, 3)],
    }
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
