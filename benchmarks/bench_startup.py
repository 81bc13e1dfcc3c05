"""Benchmark: start-up overhead of a tiny ``btf ingest``, cold (temporary Prefect server) and warm
(a ``btf server`` already running), measured in the same run.

Data: a simulated ``tiny`` capture, one material, one turntable position (4 views x 16 LEDs, 8x8
texels), made once at the start. Each measured run is a fresh ``python -m flows.cli --no-progress
ingest CAPTURE --out NEW.zarr`` subprocess on the default profile (``infra/local.yaml``: 2 worker
processes):

* ``wall_s``: the subprocess' wall time, interpreter start to exit;
* ``stage_s``: the ingest stage's own time (``stages.ingest.seconds`` of its JSON);
* ``overhead_s`` = wall - stage: imports, Prefect API, Dask cluster, flow bookkeeping, close.

Cold runs use an empty state folder (``XDG_STATE_HOME``), so each starts a temporary Prefect server
(in parallel with the cluster) and a Dask cluster; warm runs use the folder of a ``btf server``
started once by this script (its start time is reported as ``server_start_s``) and stopped at the
end: its Prefect server, its Dask cluster and its command runner (``used_server_cluster`` and
``used_runner`` count the runs whose stderr says they ran on the cluster and in a fork of the runner). Cold and warm runs
alternate, ``--repeats`` of each, against the machine's drifting load. With ``--before DIR`` (an
export of an earlier revision, e.g. ``git archive HEAD | tar -x -C DIR``), the same ingest run from
that tree is interleaved too (``before``: the serial start of that revision).

Also counted in every run's stderr: Prefect's telemetry notice and the nanny's "Worker process still
alive ... killing" (both should be 0). The bar (issue 15): median warm overhead under 3 s (``"bars"``).

Usage: ``python benchmarks/bench_startup.py [--quick] [--repeats 3] [--before DIR]``; ``--quick``: one repeat.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _measure import bar, log

REPO = Path(__file__).resolve().parents[1]
NOISE = {"telemetry_notice": "anonymous usage data", "nanny_kill": "still alive after"}


def _environ(state_home: Path) -> dict[str, str]:
    environ = {k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "BTF_CLUSTER_CONFIG")}
    return {**environ, "XDG_STATE_HOME": str(state_home), "PYTHONUNBUFFERED": "1"}


def _btf(tree: Path, state_home: Path, *args: str) -> tuple[subprocess.CompletedProcess, float]:
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "flows.cli", *args], cwd=tree, env=_environ(state_home),
                          capture_output=True, text=True, timeout=900)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"btf {' '.join(args)} failed ({done.returncode}): {done.stderr[-2000:]}")
    return done, wall


def _ingest(tree: Path, state_home: Path, capture: Path, out: Path) -> dict:
    load = os.getloadavg()[0]
    done, wall = _btf(tree, state_home, "--no-progress", "ingest", str(capture), "--out", str(out))
    stage = json.loads(done.stdout)["stages"]["ingest"]["seconds"]
    return {"wall_s": round(wall, 2), "stage_s": round(stage, 3), "overhead_s": round(wall - stage, 2),
            "load_1min": round(load, 2), "used_server_cluster": int("(the btf server's) ready" in done.stderr),
            "used_runner": int("forked by the btf server's command runner" in done.stderr),
            **{name: done.stderr.count(text) for name, text in NOISE.items()}}


def _summary(runs: list[dict]) -> dict:
    return {"runs": runs, "median_overhead_s": round(statistics.median(r["overhead_s"] for r in runs), 2),
            "min_overhead_s": min(r["overhead_s"] for r in runs),
            **{name: sum(r[name] for r in runs) for name in (*NOISE, "used_server_cluster", "used_runner")}}


def _machine() -> dict:
    model = ""
    if shutil.which("lscpu"):
        lines = subprocess.run(["lscpu"], capture_output=True, text=True).stdout.splitlines()
        model = next((line.split(":", 1)[1].strip() for line in lines if line.startswith("Model name")), "")
    return {"nproc": os.cpu_count(), "cpu": model, "python": platform.python_version()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="one repeat")
    parser.add_argument("--before", type=Path, default=None, metavar="DIR",
                        help="an export of an earlier revision to measure the same way (its own start-up)")
    args = parser.parse_args()
    if args.quick:
        args.repeats = 1
    work = Path(tempfile.mkdtemp(prefix="bench-startup-"))
    cold_home, warm_home = work / "cold-state", work / "warm-state"
    try:
        log("simulating the tiny capture")
        _btf(REPO, cold_home, "--no-progress", "simulate", "--device", "tiny", "--materials", "1",
             "--turntable", "1", "--texture-size", "8", "--out", str(work / "db"))
        capture = next((work / "db").glob("*.zarr"))
        log("starting the btf server")
        started, server_start = _btf(REPO, warm_home, "server", "start")
        server = json.loads(started.stdout)
        runs: dict[str, list[dict]] = {"cold": [], "warm": [], **({"before": []} if args.before else {})}
        for i in range(args.repeats):
            for kind in runs:
                tree, home = (args.before, cold_home) if kind == "before" else (REPO, warm_home if kind == "warm"
                                                                                 else cold_home)
                runs[kind].append(_ingest(tree, home, capture, work / f"{kind}-{i}.zarr"))
                log(f"{kind} {i + 1}/{args.repeats}: {runs[kind][-1]}")
        result = {
            "benchmark": "startup", "date": time.strftime("%Y-%m-%d %H:%M"), "machine": _machine(),
            "data": "tiny capture: 1 material, 4 views x 16 LEDs, 8x8 texels; default profile (2 worker processes)",
            "server_start_s": round(server_start, 2), "server_url": server["url"],
            **{kind: _summary(r) for kind, r in runs.items()},
        }
        result["warm_over_cold"] = round(result["warm"]["median_overhead_s"] / result["cold"]["median_overhead_s"], 3)
        warm = result["warm"]["median_overhead_s"]
        result["bars"] = [bar("median warm start-up overhead of a tiny btf ingest, s", warm, "< 3 s", warm < 3, 15)]
        print(json.dumps(result, indent=2))
    finally:
        subprocess.run([sys.executable, "-m", "flows.cli", "server", "stop"], cwd=REPO, env=_environ(warm_home),
                       capture_output=True, timeout=120)
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
