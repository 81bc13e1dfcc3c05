"""Benchmark: what the chunk checksums (CRC32C, tasks/integrity.py) cost the ingest and the model database.

Every array the pipeline writes carries Zarr v3's ``crc32c`` codec (issue 13). This measures, in one
run with the contenders interleaved, the same work with and without the checksum:

* ``ingest``: ``tasks.ingest.ingest_capture`` on the default LocalCluster (2 workers x 1 thread) of a
  simulated bonn-dome2 capture, first turntable position, one leather (11 views x 198 single-LED
  brackets of 4 raw frames of 280x288, 1.4 GB raw): once from the capture as written (checksummed) into
  a checksummed BTF store, once from a copy of its arrays without checksums (the truth group left out,
  which the ingest does not read) into a BTF store without them (``tasks.integrity.checksummed``
  patched in this process, where the output store is created); wall seconds and the CPU seconds of
  the workers. Bar: the checksums cost under 5 % of the ingest's throughput;
* ``model``: a synthetic btf-texture store (``bench_model_svd.write_store``: 11 views x 198 LEDs =
  2,178 rows x 128 x 128 x 3 texels, float32, 428 MB), written with and without checksums; per
  variant the write, one streaming pass of ``tasks.model.blocks`` (what the basis fits read) and a
  randomized truncated SVD of rank ``--k`` over that stream (``btfcore.model.truncated_svd``, BLAS on one
  thread), each as CPU seconds of this process and wall seconds; costs from the fastest runs;
* ``io``: the ingest's own store traffic alone, on one worker (its environment: malloc settings,
  one thread), nothing else computed: every view's raw read as ``ingest_view`` reads it
  (``tasks.integrity.read_chunk_windows`` into a reused buffer: the chunk files read without Zarr, with
  or without their CRC32C) from each capture, and every view's textures written to a BTF-layout array
  as ``ingest_view`` writes them (``tasks.stores.write_chunk_aligned``: the chunk files written past the
  page cache); fastest of
  ``--repeats`` interleaved runs (other work on the machine only adds time), and the difference set
  against the ingest's worker CPU seconds;
* the codec's own rates on one raw chunk (645 KB): ``google_crc32c.value`` and the ``np.append`` copy
  that ``zarr.codecs.Crc32cCodec`` makes to put the 4 checksum bytes after the chunk.

Bar (issue 13): ``ingest.throughput_cost`` (medians) under 0.05 (``"bars"``; not measured with
``--skip-ingest``).

Usage: ``python benchmarks/bench_checksum.py [--repeats N] [--capture STORE] [--skip-ingest] [--skip-model]``
(about 2.5 minutes on 2 cores with the defaults, a third of it simulating the capture, which
``--capture`` reuses; progress lines go to stderr, the JSON result to stdout).
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
from _measure import bar, best_seconds, log


def set_checksums(enabled: bool) -> None:
    """Create arrays with (the pipeline's) or without (the old) checksums in this process."""
    import tasks.integrity as integrity

    original = integrity.__dict__.setdefault("_bench_checksummed", integrity.checksummed)
    integrity.checksummed = original if enabled else (lambda compressors=None: list(compressors or []))


def copy_without_checksums(src: Path, dst: Path) -> None:
    """The arrays of a capture store (not its truth group) re-encoded without checksums, chunk by chunk."""
    import zarr

    source = zarr.open_group(str(src), mode="r", zarr_format=3)
    target = zarr.open_group(str(dst), mode="w", zarr_format=3)
    for name, node in sorted(source.members(max_depth=None)):
        if name == "truth" or name.startswith("truth/"):
            continue
        if isinstance(node, zarr.Group):
            target.require_group(name).attrs.put(dict(node.attrs))
            continue
        dims = getattr(node.metadata, "dimension_names", None)
        out = target.create_array(name, shape=node.shape, dtype=node.dtype, chunks=node.chunks,
                                  fill_value=node.fill_value, compressors=None, dimension_names=dims)
        for idx in np.ndindex(*node.cdata_shape):
            region = tuple(slice(i * c, min((i + 1) * c, n)) for i, c, n in zip(idx, node.chunks, node.shape))
            out[region] = node[region]
    attrs = dict(source.attrs)
    target.attrs.put(attrs)


def codec_rates() -> dict[str, float]:
    """GB/s of the checksum and of the codec's np.append copy on one raw chunk (4 x 280 x 288 uint16)."""
    import google_crc32c

    chunk = np.random.default_rng(0).integers(0, 4096, (4, 280, 288), dtype=np.uint16).view(np.uint8).reshape(-1)
    tail = np.zeros(4, np.uint8)
    crc = best_seconds(lambda: google_crc32c.value(chunk), 20)
    append = best_seconds(lambda: np.append(chunk, tail), 20)
    return {"chunk_bytes": int(chunk.nbytes), "crc32c_gb_per_s": round(chunk.nbytes / crc / 1e9, 2),
            "np_append_gb_per_s": round(chunk.nbytes / append / 1e9, 2)}


def bench_io(inputs: dict[bool, Path], repeats: int, scratch: Path) -> dict:
    """Fastest seconds of the ingest's raw reads and texture writes with and without checksums."""
    import zarr

    from tasks.ingest import band_rows
    from tasks.integrity import read_chunk_windows
    from tasks.stores import write_chunk_aligned

    raw = {k: zarr.open_group(str(p), mode="r")["raw"] for k, p in inputs.items()}
    n_turn, n_cam, n_illum, n_exp, rows, cols = raw[True].shape
    views = [(t, c) for t in range(n_turn) for c in range(n_cam)]
    buf = np.empty((n_illum, n_exp, rows, cols), np.uint16)
    whole = (slice(None),) * 3
    h = w = 128
    textures = np.random.default_rng(0).random((n_illum, h, w, 3), dtype=np.float32)
    read: dict[bool, list[float]] = {True: [], False: []}
    write: dict[bool, list[float]] = {True: [], False: []}
    for rep in range(max(repeats, 5)):
        for enabled in ((True, False) if rep % 2 == 0 else (False, True)):
            start = time.perf_counter()
            for t, c in views:
                read_chunk_windows(raw[enabled], (t, c), whole, buf)
            read[enabled].append(time.perf_counter() - start)
            set_checksums(enabled)
            from tasks.integrity import create_array
            group = zarr.open_group(str(scratch / "io.zarr"), mode="w", zarr_format=3)
            btf = create_array(group, "btf", shape=(len(views) * n_illum, h, w, 3), dtype="float32",
                               chunks=(n_illum, band_rows(n_illum, h, w), w, 3), fill_value=0.0, compressors=None)
            start = time.perf_counter()
            for k in range(len(views)):
                write_chunk_aligned(btf, slice(k * n_illum, (k + 1) * n_illum), textures)
            write[enabled].append(time.perf_counter() - start)
    set_checksums(True)
    best = {name: {k: min(v) for k, v in d.items()} for name, d in (("read", read), ("write", write))}
    return {"read_gb": round(raw[True].nbytes / 1e9, 3), "write_gb": round(len(views) * textures.nbytes / 1e9, 3),
            "read_s": {str(k): round(v, 3) for k, v in best["read"].items()},
            "write_s": {str(k): round(v, 3) for k, v in best["write"].items()},
            "checksum_s": round(best["read"][True] - best["read"][False] + best["write"][True] - best["write"][False],
                                3)}


def bench_ingest(args, scratch: Path) -> dict:
    from flows.runtime import runtime
    from tasks.ingest import ingest_capture
    from tasks.simulate import SimulationConfig, simulate_database
    from tasks.stores import open_capture_store

    config = SimulationConfig(device="bonn-dome2", n_materials=1, seed=0, classes=("leather",), n_turntable=1)
    runs: dict[bool, list[float]] = {True: [], False: []}
    cpu: dict[bool, list[float]] = {True: [], False: []}
    with runtime() as (_profile, _url, client):
        set_checksums(True)
        log("simulating the capture" if not args.capture else f"reusing {args.capture}")
        capture = Path(args.capture or simulate_database(config, scratch / "db", client).stores[0])
        plain = scratch / "plain-capture.zarr"
        log("copying it without checksums")
        copy_without_checksums(capture, plain)
        raw_bytes = open_capture_store(capture).raw.nbytes
        inputs = {True: capture, False: plain}
        for rep in range(args.repeats):
            for enabled in ((True, False) if rep % 2 == 0 else (False, True)):   # interleaved, order alternating
                set_checksums(enabled)
                out = scratch / f"btf-{rep}-{enabled}.zarr"
                cpu0 = sum(client.run(time.process_time).values())
                start = time.perf_counter()
                ingest_capture(inputs[enabled], out, client)
                runs[enabled].append(time.perf_counter() - start)
                cpu[enabled].append(sum(client.run(time.process_time).values()) - cpu0)
                shutil.rmtree(out)
                log(f"ingest {'with' if enabled else 'without'} checksums: {runs[enabled][-1]:.2f} s, "
                    f"workers' CPU {cpu[enabled][-1]:.2f} s")
        set_checksums(True)
        io = client.submit(bench_io, inputs, args.repeats, scratch, pure=False).result()   # a worker's malloc
    med = {k: float(np.median(v)) for k, v in runs.items()}
    med_cpu = {k: float(np.median(v)) for k, v in cpu.items()}
    return {
        "data": "bonn-dome2, 1 turntable position, 1 leather, single-LED",
        "raw_gb": round(raw_bytes / 1e9, 3),
        "with_checksums_s": [round(s, 2) for s in runs[True]],
        "without_checksums_s": [round(s, 2) for s in runs[False]],
        "median_with_mb_per_s": round(raw_bytes / 1e6 / med[True], 1),
        "median_without_mb_per_s": round(raw_bytes / 1e6 / med[False], 1),
        "throughput_cost": round(1.0 - med[False] / med[True], 4),
        "throughput_cost_of_fastest": round(1.0 - min(runs[False]) / min(runs[True]), 4),
        "with_checksums_worker_cpu_s": [round(s, 2) for s in cpu[True]],
        "without_checksums_worker_cpu_s": [round(s, 2) for s in cpu[False]],
        "cpu_cost": round(1.0 - med_cpu[False] / med_cpu[True], 4),
        "io": {**io, "checksum_s_over_ingest_worker_cpu": round(io["checksum_s"] / min(cpu[True]), 4),
               "checksum_s_over_ingest_core_s": round(io["checksum_s"] / (2 * min(runs[True])), 4)},
    }


def bench_model(args, scratch: Path) -> dict:
    from bench_model_svd import N_LEDS, factors, write_store
    from threadpoolctl import threadpool_limits

    from btfcore.model.truncated_svd import truncated_svd
    from tasks.model import blocks

    n_lv, h = args.views * N_LEDS, args.texture
    n_tx = h * h * 3
    U, make_V = factors(n_lv, n_tx, 256, 0)
    V = make_V()
    s = np.arange(1, 257, dtype=np.float64) ** -0.75
    stores = {True: scratch / "with.zarr", False: scratch / "without.zarr"}
    figures: dict[str, dict[bool, list[float]]] = {
        name: {True: [], False: []} for name in ("write_cpu_s", "pass_s", "pass_cpu_s", "svd_s", "svd_cpu_s")}
    for rep in range(args.repeats):
        for enabled in ((True, False) if rep % 2 == 0 else (False, True)):
            set_checksums(enabled)
            shutil.rmtree(stores[enabled], ignore_errors=True)
            start = time.process_time()
            write_store(stores[enabled], U, V, s, h, h, N_LEDS, {"rep": rep})
            figures["write_cpu_s"][enabled].append(time.process_time() - start)
            start, wall = time.process_time(), time.perf_counter()
            n_bytes = sum(b.nbytes for b in blocks(str(stores[enabled]), "als")())
            figures["pass_cpu_s"][enabled].append(time.process_time() - start)
            figures["pass_s"][enabled].append(time.perf_counter() - wall)
            start, wall = time.process_time(), time.perf_counter()
            with threadpool_limits(1, "blas"):                     # one core: less exposed to other work
                truncated_svd(blocks(str(stores[enabled]), "als"), n_lv, args.k, "randomized", seed=0)
            figures["svd_cpu_s"][enabled].append(time.process_time() - start)
            figures["svd_s"][enabled].append(time.perf_counter() - wall)
            log(f"model {'with' if enabled else 'without'}: " +
                ", ".join(f"{k} {v[enabled][-1]:.2f}" for k, v in figures.items()))
    set_checksums(True)
    out: dict = {"data": f"synthetic btf-texture store, {n_lv} x {n_tx} float32 ({n_bytes / 1e9:.3f} GB)",
                 "k": args.k}
    for name, runs in figures.items():
        best = {k: min(v) for k, v in runs.items()}
        out[name] = {"with": [round(x, 2) for x in runs[True]], "without": [round(x, 2) for x in runs[False]],
                     "cost_of_fastest": round(1.0 - best[False] / best[True], 4)}
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=3, help="interleaved rounds of each variant [default: 3]")
    parser.add_argument("--capture", default=None, help="reuse this bonn-dome2 capture store instead of simulating")
    parser.add_argument("--views", type=int, default=11, help="model store: views x 198 LEDs rows [default: 11]")
    parser.add_argument("--texture", type=int, default=128, help="model store: texture side [default: 128]")
    parser.add_argument("--k", type=int, default=32, help="model: rank of the truncated SVD [default: 32]")
    parser.add_argument("--skip-ingest", action="store_true")
    parser.add_argument("--skip-model", action="store_true")
    args = parser.parse_args()
    scratch = Path(tempfile.mkdtemp(prefix="bench-checksum-"))
    load = {"start": round(os.getloadavg()[0], 2)}
    result: dict = {"benchmark": "checksum", "date": time.strftime("%Y-%m-%d"),
                    "machine": f"{platform.node()} {os.cpu_count()} cores",
                    "command": "python " + " ".join(sys.argv), "codec": codec_rates()}
    try:
        if not args.skip_ingest:
            result["ingest"] = bench_ingest(args, scratch)
        if not args.skip_model:
            result["model"] = bench_model(args, scratch)
        cost = result["ingest"]["throughput_cost"] if "ingest" in result else None
        result["bars"] = [bar("ingest throughput cost of the checksums (medians)", cost,
                              "< 0.05" if cost is not None else "< 0.05; not measured: --skip-ingest",
                              None if cost is None else cost < 0.05, 13)]
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
        load["end"] = round(os.getloadavg()[0], 2)
        result["load_average_1min"] = load
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
