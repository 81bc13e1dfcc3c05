"""Benchmark: ``btf reconstruct`` end to end (store in, store out) against the machine's limits.

:func:`tasks.reconstruct.reconstruct_store` on the project's default cluster
(2 workers x 1 thread) at the thesis' scale: 12 turntable positions x 11
cameras x 198 LEDs = 26,136 light/view pairs, 128 x 128 RGB texels. The input
is a sparse single-light measurement store of ``n_s`` (light, turntable)
pairs x 11 cameras (n_s = 400: 4,400 rows, 865 MB), the model a class ALS
basis of ``k`` vectors (the same shapes as ``bench_reconstruct.py``); the
output is the full 5.1 GB BTF store, written band by band and renamed into
place.

Reported, all measured in the same run:

* ``seconds``: operator build, bands (read, solve, write), total;
* ``gemm_gflop_per_s``: a float32 4096^3 numpy GEMM on the machine (all
  threads), best of 3, before and after;
* ``disk_write_gb_per_s``: writing and fsync-ing 1 GiB with numpy, best of 2,
  before and after;
* ``lower_bound_s``: the factored solve's flops at the GEMM rate plus the
  output's bytes at the disk write rate, i.e. what the machine cannot beat
  without overlapping the two; ``over_lower_bound``: that bound divided by
  the measured total time (1.0 = at the machine's limit).

Bar (issue 21, item 4): ``over_lower_bound`` at least 0.8 (``"bars"``).

Usage: ``python benchmarks/bench_reconstruct_store.py [--quick] [--n-s 400] [--k 1024] [--texture 128]
[--turntables 12] [--keep DIR]``; ``--quick`` (``--texture 32 --turntables 2 --n-s 200``) is a quick check.
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
from _measure import bar, disk_write_rate, gemm_rate, log

N_CAM, N_LEDS = 11, 198
OVER_BOUND = 0.8        # issue 21


def make_inputs(folder: Path, n_turn: int, size: int, n_s: int, k: int) -> tuple[str, str]:
    """A sparse single-light measurement store and a model store holding one class ALS basis."""
    import zarr

    from tasks.integrity import create_array
    from tasks.stores.measurement import write_measurement

    n_lv = n_turn * N_CAM * N_LEDS
    rng = np.random.default_rng(2)
    light = rng.normal(size=(n_lv, 3))
    view = rng.normal(size=(n_lv, 3))
    light[:, 2], view[:, 2] = np.abs(light[:, 2]) + 0.5, np.abs(view[:, 2]) + 0.5
    light /= np.linalg.norm(light, axis=1, keepdims=True)
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    pairs = np.sort(rng.choice(n_turn * N_LEDS, n_s, replace=False))              # (turntable, LED) pairs
    t, led = np.divmod(pairs, N_LEDS)
    rows = ((t[:, None] * N_CAM + np.arange(N_CAM)[None]) * N_LEDS + led[:, None]).ravel()
    G = np.zeros((len(rows), n_lv), np.float32)
    G[np.arange(len(rows)), rows] = 1.0
    measured = rng.uniform(0.01, 1.0, (len(rows), size, size, 3)).astype(np.float32)
    meas = folder / "measurement.zarr"
    write_measurement(meas, measured, G, light, view, (n_turn, N_CAM, N_LEDS))
    model = folder / "model.zarr"
    group = zarr.open_group(str(model), mode="w", zarr_format=3)
    for name, d in (("light_dir", light), ("view_dir", view)):
        create_array(group, name, shape=d.shape, dtype="float64", chunks=d.shape)[...] = d
    group.attrs.put({"schema": "btf-model", "schema_version": "1.0", "rows_id": "bench", "n_lv": n_lv})
    U = np.linalg.qr(rng.standard_normal((n_lv, k)))[0]
    sub = group.require_group("classes/leather/als")
    for name, d in (("U", U), ("sigma", np.linspace(100.0, 1.0, k))):
        create_array(sub, name, shape=d.shape, dtype="float64", chunks=d.shape)[...] = d
    sub.attrs.put({"method": "bench", "key": "bench-als"})
    return str(meas), str(model)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-s", type=int, default=400, help="(light, turntable) pairs measured [default: 400]")
    parser.add_argument("--k", type=int, default=1024, help="basis vectors [default: 1024]")
    parser.add_argument("--texture", type=int, default=128, help="texture side [default: 128]")
    parser.add_argument("--turntables", type=int, default=12, help="turntable positions [default: 12]")
    parser.add_argument("--keep", default=None, metavar="DIR", help="work in DIR and keep it [default: a temp dir]")
    parser.add_argument("--quick", action="store_true", help="--texture 32 --turntables 2 --n-s 200")
    args = parser.parse_args()
    if args.quick:
        args.texture, args.turntables, args.n_s = 32, 2, 200
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from flows.runtime import dask_client, load_profile
    from tasks.reconstruct import ReconstructSettings, reconstruct_store

    folder = Path(args.keep or tempfile.mkdtemp(prefix="bench-reconstruct-", dir=os.environ.get("TMPDIR", "/tmp")))
    folder.mkdir(parents=True, exist_ok=True)
    n_lv = args.turntables * N_CAM * N_LEDS
    n_meas = args.n_s * N_CAM
    n_cols = args.texture ** 2 * 3
    out_bytes = 4 * n_lv * n_cols
    try:
        log("machine limits before")
        gemm0, disk0 = gemm_rate(4096, 4096, 4096), disk_write_rate(folder)
        log(f"writing inputs: {n_meas} x {args.texture}^2 x 3 measurement, {n_lv} x {args.k} basis")
        meas, model = make_inputs(folder, args.turntables, args.texture, args.n_s, args.k)
        settings = ReconstructSettings(cls="leather", basis="als", method="tikhonov")
        with dask_client(load_profile()) as client:
            log("reconstructing")
            start = time.perf_counter()
            summary = reconstruct_store(meas, model, folder / "out.zarr", settings, client)
            total = time.perf_counter() - start
        log("machine limits after")
        gemm1, disk1 = gemm_rate(4096, 4096, 4096), disk_write_rate(folder)
    finally:
        if not args.keep:
            shutil.rmtree(folder, ignore_errors=True)
    gemm, disk = max(gemm0, gemm1), max(disk0, disk1)
    flops = 2.0 * args.k * (n_lv + n_meas) * n_cols                   # factored U (R y)
    bound = flops / (gemm * 1e9) + out_bytes / (disk * 1e9)
    result = {
        "benchmark": "btf reconstruct end to end (tasks.reconstruct.reconstruct_store)",
        "date": time.strftime("%Y-%m-%d %H:%M"), "machine": f"{platform.node()} ({os.cpu_count()} cores)",
        "shape": {"n_lv": n_lv, "n_meas": n_meas, "k": args.k, "texture": args.texture, "out_gb": out_bytes / 1e9},
        "seconds": {"total": round(total, 2), "reconstruct_store": summary["seconds"]},
        "bands": summary["bands_processed"],
        "gemm_gflop_per_s": {"before": round(gemm0, 1), "after": round(gemm1, 1)},
        "disk_write_gb_per_s": {"before": round(disk0, 3), "after": round(disk1, 3)},
        "solve_gflop": round(flops / 1e9, 1),
        "lower_bound_s": round(bound, 2),
        "over_lower_bound": round(bound / total, 3),
        "bars": [bar("GEMM + disk-write bound s / measured s", round(bound / total, 3), f">= {OVER_BOUND}",
                     bound / total >= OVER_BOUND, 21)],
        "load_average_1min": round(os.getloadavg()[0], 2),
    }
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
