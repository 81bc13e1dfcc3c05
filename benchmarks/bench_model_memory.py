"""Benchmark: a material's model fit is out of core, bounded by a texel band, not by the material.

Writes a synthetic, positive BTF store in the ``btf-texture`` layout of
``btf ingest`` (``btf`` ``(n_lv, h, w, 3)`` float32, chunks of one view's 198
LEDs x a band of texture rows, :func:`tasks.ingest.band_rows`): by default
11 views (bonn-dome2's first turntable position) x 198 LEDs = 2,178
light/view pairs at 306 x 306 texels, 2.45 GB, a rank-16 positive BTF with
1 % multiplicative noise (full numerical rank). It then runs
:func:`tasks.model.fit_material` (the task ``btf build-db`` runs per
material: ``log_y``, ``u_y``, ``v_y``, ``abtf_log_y`` by truncated SVD with
the thesis' k = 200/100/100/200, then the streamed relative-error ``als``
basis, c = 64) on a LocalCluster whose two 1-thread workers are limited to
``--limit`` (1 GiB) each, so the matrix is more than twice one worker's
limit (and larger than both together), and samples every worker's resident
set size every 0.2 s. The ALS basis runs ``--als-iterations`` (2; the
default build runs 30): its memory does not depend on the number of
iterations, its time does (about a minute an iteration here). A failed task
is not retried (``distributed.scheduler.allowed-failures`` = 0). Reported:

* ``matrix_over_worker_limit`` = the store's ``btf`` bytes / one worker's limit;
* ``peak_worker_rss_mb`` and ``peak_over_limit``; ``idle_worker_rss_mb``
  (before the fit); ``peak_by_basis_mb``: the largest sample while each
  basis was being fitted (split at the times each basis was written);
* ``band_block_mb``: one texel band across all light/view pairs, the unit
  the bases stream (``n_views`` chunks of about 4 MiB), and the ``(rows, l)``
  float64 factors of each SVD basis;
* the bases written (each with its method and captured energy), whether a
  worker was restarted, the error if the fit failed, and ``"bars"`` (issue 4:
  every basis fitted, no restart, matrix >= 2x the limit; its value is the
  peak worker RSS / limit). The script exits 0 either way (``make bench``
  runs on); the JSON says.

The peak does not grow with the texels, but it does with the views: a band
spans every view (``--views 22`` doubles it).

Usage: ``python benchmarks/bench_model_memory.py [--views 11] [--texture 306] [--limit 1GiB] [--als-iterations 2]``
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
from _measure import WorkerRSS, bar, log

N_LEDS = 198


def parse_bytes(text: str) -> int:
    units = {"GiB": 1 << 30, "MiB": 1 << 20, "GB": 10**9, "MB": 10**6}
    for unit, factor in units.items():
        if text.endswith(unit):
            return int(float(text[: -len(unit)]) * factor)
    return int(text)


def write_store(path: Path, n_lv: int, h: int, w: int, rank: int = 16, seed: int = 0) -> tuple[int, int]:
    """A positive synthetic BTF store that `tasks.model.discover` accepts; (btf bytes, band rows)."""
    import zarr

    from tasks.integrity import create_array

    from tasks.ingest import band_rows

    rng = np.random.default_rng(seed)
    rows = band_rows(N_LEDS, h, w)
    group = zarr.open_group(str(path), mode="w", zarr_format=3)
    btf = create_array(group, "btf", shape=(n_lv, h, w, 3), chunks=(N_LEDS, rows, w, 3), dtype="float32",
                       fill_value=0.0, compressors=None,
                       dimension_names=["lv", "tex_row", "tex_col", "channel"])
    abrdfs = rng.uniform(0.02, 1.0, (n_lv, rank)).astype(np.float32)        # positive ABRDF basis
    for r0 in range(0, h, rows):
        r1 = min(r0 + rows, h)
        coeff = rng.uniform(0.0, 1.0 / rank, (rank, (r1 - r0) * w * 3)).astype(np.float32)
        band = abrdfs @ coeff
        band *= 1 + 0.01 * rng.standard_normal(band.shape, dtype=np.float32)
        btf[:, r0:r1] = band.reshape(n_lv, r1 - r0, w, 3)
    dirs = rng.standard_normal((2, n_lv, 3))
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    dirs[..., 2] = np.abs(dirs[..., 2])
    for name, data in (("light_dir", dirs[0]), ("view_dir", dirs[1])):
        create_array(group, name, shape=data.shape, dtype="float64", chunks=data.shape, compressors=None)[...] = data
    group.attrs.put({"schema": "btf-texture", "schema_version": "1.0", "complete": True, "texture_shape": [h, w],
                     "ingest_hash": f"synthetic-{n_lv}-{h}-{w}-{rank}-{seed}",
                     "material": {"material_id": "synthetic", "class": "synthetic"}})
    return n_lv * h * w * 3 * 4, rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, default=11, help="views x 198 LEDs = light/view pairs [default: 11]")
    parser.add_argument("--texture", type=int, default=None,
                        help="texture side [default: the smallest multiple of 6 making the store >= 2.25x the "
                             "limit: 306 for 11 views and 1 GiB]")
    parser.add_argument("--limit", default="1GiB", help="memory limit of each worker [default: 1GiB]")
    parser.add_argument("--als-iterations", type=int, default=2, help="ALS iterations [default: 2]")
    parser.add_argument("--scratch", type=Path, default=None, help="scratch folder [default: a temporary one]")
    args = parser.parse_args()
    import dask

    from flows.runtime import runtime
    from tasks.model import BASES, ModelSettings, discover, fit_material, open_model_store

    n_lv = args.views * N_LEDS
    limit = parse_bytes(args.limit)
    h = args.texture or 6 * int(np.ceil(np.sqrt(2.25 * limit / (n_lv * 12)) / 6))
    load_start = round(os.getloadavg()[0], 2)
    scratch = args.scratch or Path(tempfile.mkdtemp(prefix="bench-model-memory-"))
    try:
        log(f"writing a synthetic {n_lv} x {h} x {h} x 3 store")
        start = time.perf_counter()
        n_bytes, rows = write_store(scratch / "db" / "synthetic.zarr", n_lv, h, h)
        write_s = time.perf_counter() - start
        log(f"wrote {n_bytes / 1e9:.2f} GB in {write_s:.1f} s")
        settings = ModelSettings(als_iterations=args.als_iterations)
        materials = discover(scratch / "db", min_per_class=1)
        model_path = str(scratch / "model.zarr")
        open_model_store(model_path, materials)
        profile = scratch / "small-workers.yaml"
        profile.write_text(f"cluster: {{kind: local, n_workers: 2, threads_per_worker: 1, memory_limit: {limit}}}\n"
                           "prefect: {api_url: null, startup_timeout_s: 90}\n")
        with dask.config.set({"distributed.scheduler.allowed-failures": 0}), \
                runtime(profile) as (_p, _u, client):
            sampler = WorkerRSS(client)
            idle = sampler.idle()
            log("fit_material on a worker")
            with sampler:
                start, start_epoch = time.perf_counter(), time.time()
                future = client.submit(fit_material, model_path, materials[0], settings, pure=False)
                try:
                    future.result()
                    error = None
                except Exception as exc:                  # a worker killed past its limit, reported
                    error = f"{type(exc).__name__}: {exc}"[:400]
                seconds = time.perf_counter() - start
        samples, restarted = sampler.samples, sampler.restarted
        import zarr

        group = zarr.open_group(model_path, mode="r", zarr_format=3)
        bases, begin, peak_by_basis = {}, start_epoch, {}
        for basis in BASES:
            where = f"materials/{materials[0].material_id}/{basis}"
            written = Path(model_path) / where / "zarr.json"
            end = written.stat().st_mtime if where in group and "key" in group[where].attrs else float("inf")
            during = [rss for t, rss in sampler.timeline if begin <= t <= end]
            if during:
                peak_by_basis[basis] = round(max(during) / 1e6, 1)
            if end == float("inf"):
                break                                        # the basis being fitted when the task failed
            attrs = dict(group[where].attrs)
            bases[basis] = {"method": attrs["method"], "k": int(group[where]["U"].shape[1]),
                            "energy_captured": round(attrs["energy_captured"], 6), "s": round(end - begin, 1)}
            begin = end
    finally:
        if args.scratch is None:
            shutil.rmtree(scratch, ignore_errors=True)
        else:                                                # only what this run wrote there
            for name in ("db", "model.zarr"):
                shutil.rmtree(scratch / name, ignore_errors=True)
            (scratch / "small-workers.yaml").unlink(missing_ok=True)
    peak = max(samples)
    band_mb = n_lv * rows * h * 3 * 4 / 1e6
    factor_mb = {b: round(n_lv * (9 if b == "abtf_log_y" else 1) * (v["k"] + max(10, v["k"] // 4)) * 8 / 1e6, 1)
                 for b, v in bases.items() if b != "als"}
    result = {
        "benchmark": "model-memory", "date": time.strftime("%Y-%m-%d"),
        "machine": f"{platform.node()} {os.cpu_count()} cores", "command": "python " + " ".join(sys.argv),
        "data": f"synthetic positive BTF, {args.views} views x {N_LEDS} LEDs = {n_lv} pairs, {h} x {h} x 3, "
                "rank 16 + 1 % noise",
        "btf_gb": round(n_bytes / 1e9, 3), "worker_memory_limit": args.limit,
        "matrix_over_worker_limit": round(n_bytes / limit, 2),
        "band_rows": rows, "band_block_mb": round(band_mb, 1), "factor_mb_float64": factor_mb,
        "idle_worker_rss_mb": round(idle / 1e6, 1),
        "peak_worker_rss_mb": round(peak / 1e6, 1), "peak_over_limit": round(peak / limit, 3),
        "peak_by_basis_mb": peak_by_basis,
        "rss_samples": len(samples), "worker_restarted": restarted,
        "fit_s": round(seconds, 1), "bases": bases,
        "als_iterations": args.als_iterations, "error": error,
        "bars": [bar("peak worker RSS / worker memory limit", round(peak / limit, 3),
                     f"every basis fitted, no restart, matrix >= 2x the limit (here {n_bytes / limit:.2f}x)",
                     set(bases) == set(BASES) and not restarted and not error and n_bytes >= 2 * limit, 4)],
        "load_average_1min": {"start": load_start, "end": round(os.getloadavg()[0], 2)},
    }
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
