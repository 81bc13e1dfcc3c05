"""Benchmark: virtual-dome generation throughput against the disk's write rate.

Simulates one material on a pruned ``bonn-dome2`` (first turntable position:
11 views x 198 LEDs = 2,178 light/view pairs at 128x128, truth also at
256x256) on the default LocalCluster, and reports

* ``written_gb_per_s`` = bytes of the store / wall time of the simulate stage;
* ``over_disk_write`` = that rate / the rate of writing the same number of
  bytes with numpy + fsync to the same filesystem, measured in the same run;
* ``pairs_per_s`` = rendered light/view pairs (each a 128x128 and a 256x256
  texture plus a raw bracket) per second.

No bar: ``over_disk_write`` is recorded without a goal (``"bars"``, met None).

Usage: ``python benchmarks/bench_simulate.py [--out DIR]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _measure import bar



def _du(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def disk_write_rate(directory: Path, n_bytes: int, block: int = 256 << 20) -> float:
    """Bytes per second of writing ``n_bytes`` in ``block``-sized files with fsync."""
    data = np.random.default_rng(0).integers(0, 255, block, dtype=np.uint8)
    start = time.perf_counter()
    written, i = 0, 0
    while written < n_bytes:
        with open(directory / f"block{i}", "wb") as fh:
            fh.write(data.tobytes())
            fh.flush()
            os.fsync(fh.fileno())
        written += block
        i += 1
    rate = written / (time.perf_counter() - start)
    for f in directory.glob("block*"):
        f.unlink()
    return rate


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=None, help="scratch folder [default: a temporary one]")
    args = parser.parse_args()
    from flows.runtime import runtime
    from tasks.simulate import SimulationConfig, simulate_database

    config = SimulationConfig(device="bonn-dome2", n_materials=1, seed=0, classes=("leather",), n_turntable=1)
    scratch = Path(args.out or tempfile.mkdtemp(prefix="bench-simulate-"))
    scratch.mkdir(parents=True, exist_ok=True)
    try:
        with runtime() as (_profile, _url, client):
            result = simulate_database(config, scratch / "db", client)
        n_bytes = _du(scratch / "db")
        disk = disk_write_rate(scratch, n_bytes)
    finally:
        if args.out is None:
            shutil.rmtree(scratch, ignore_errors=True)
    rate = n_bytes / result.seconds
    out = {
        "benchmark": "simulate",
        "date": time.strftime("%Y-%m-%d"),
        "machine": f"{platform.node()} {os.cpu_count()} cores",
        "command": "python benchmarks/bench_simulate.py",
        "device": "bonn-dome2, 1 turntable position, 1 material",
        "lv_pairs": config.build_device().n_lv,
        "simulate_s": round(result.seconds, 2),
        "store_gb": round(n_bytes / 1e9, 3),
        "written_gb_per_s": round(rate / 1e9, 3),
        "disk_write_gb_per_s": round(disk / 1e9, 3),
        "over_disk_write": round(rate / disk, 3),
        "pairs_per_s": round(config.build_device().n_lv / result.seconds, 1),
        "bars": [bar("generation GB/s / disk write GB/s", round(rate / disk, 3), "none (recorded)", None, 2)],
    }
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
