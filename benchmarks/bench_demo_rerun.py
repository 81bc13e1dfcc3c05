"""Benchmark: a rerun of `btf demo` on its own finished output against a fresh run (bar: under 0.2).

Both are measured in the same run (these machines are noisy), each as the
wall time of the whole command (Prefect server and Dask cluster started by
it, as a user runs it):

* ``fresh_s``: ``btf demo`` into a new output folder;
* ``rerun_s``: the same command again on that folder, which reuses every
  finished result whose inputs did not change (content keys,
  docs/architecture.md "Storage contract");
* ``rerun_over_fresh`` = ``rerun_s / fresh_s`` (bar: under 0.2), with what
  each stage of the rerun reused (its ``"reused"``: ``[reused, total]``).

The demo's smallest scale that still builds the model database and runs the
acquisition evaluation is ``--materials 12`` (two per class), the default.

Usage: ``python benchmarks/bench_demo_rerun.py [--materials N] [--json PATH]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _measure import bar, log

ROOT = Path(__file__).resolve().parents[1]
BAR = 0.2


def timed_demo(out: Path, n_materials: int) -> tuple[float, dict]:
    """Wall time of one ``btf demo`` into ``out`` and its report."""
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "flows.cli", "--no-progress", "demo", "--out", str(out),
                    "--materials", str(n_materials)], cwd=ROOT, check=True, capture_output=True)
    return time.perf_counter() - start, json.loads((out / "report.json").read_text())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--materials", type=int, default=12, help="materials of the demo [default: 12]")
    parser.add_argument("--json", type=Path, default=None, help="also write the result here")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "demo"
        log(f"fresh btf demo --materials {args.materials}")
        fresh_s, fresh = timed_demo(out, args.materials)
        log(f"fresh: {fresh_s:.1f} s; rerun on its output")
        rerun_s, rerun = timed_demo(out, args.materials)
        log(f"rerun: {rerun_s:.1f} s")
    result = {
        "benchmark": "demo-rerun",
        "date": time.strftime("%Y-%m-%d"),
        "machine": f"{platform.node()} {os.cpu_count()} cores {platform.processor() or platform.machine()}",
        "command": f"python benchmarks/bench_demo_rerun.py --materials {args.materials}",
        "load_1min": round(os.getloadavg()[0], 2),
        "fresh_s": round(fresh_s, 2),
        "rerun_s": round(rerun_s, 2),
        "rerun_over_fresh": round(rerun_s / fresh_s, 3),
        "bars": [bar("rerun s / fresh s of btf demo", round(rerun_s / fresh_s, 3), f"< {BAR}",
                     rerun_s / fresh_s < BAR, 15)],
        "fresh_stages_s": {name: f.get("seconds") for name, f in fresh["stages"].items()},
        "rerun_stages_s": {name: f.get("seconds") for name, f in rerun["stages"].items()},
        "rerun_reused": {name: f.get("reused") for name, f in rerun["stages"].items()},
    }
    print(json.dumps(result, indent=2))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
