"""Benchmark: decoding a DFMF file to textures against the float32 GEMM rate and btf-extractor.

Data: a synthetic DFMF file written by :func:`tasks.bonn.dfmf.write_dfmf`, half floats, colour model
0, n_l = n_v = 81 (UBO2003/ATRIUM: 6,561 rows), 256 x 256 texels, K = 64 components per channel
(``--lights``, ``--texture``, ``--k``); seeded Gaussian factors. About 27 MB on disk.

Contenders, timed in this run on the same file (page cache warm: it was just written):

* ours: :func:`tasks.bonn.dfmf.read_factorised` (lazy memmaps; its time is the ``load``), then
  :func:`btfcore.bonn.decode_textures` over every row and texel in bands of ``--band-rows`` texture
  rows (all light/view rows each; the store's chunks are texture-row bands too) into one reused
  ``out`` buffer per band width, best of ``--repeats``. Work ``2 * n_rows * n_tx * K * 3`` flops; GFLOP/s =
  work / seconds, and its ratio to the GEMM rate;
* GEMM rate: the same useful flops as plain numpy float32 GEMMs of the shapes ours computes,
  ``(n_rows, K) @ (K, band texels)`` per band and channel, one such pass right before each of our
  passes (the load of these shared machines changes by the minute: each pair sees the same
  conditions); the ratio is best over best. A square ``2048^3`` GEMM is reported beside it for the
  machine's peak;
* btf-extractor (PyPI, btf.hh's half-float AVX decode behind Cython, OpenMP over texture rows) in
  its own venv (``BTF_READERS_PYTHON`` or ``.venv-readers``, built by ``make test``):
  ``tests/tasks/bonn_readers.py btf-extractor FILE OUT --time-only`` decodes every (light, view)
  image and keeps none; its constructor (reads the whole file, flips the rows) is timed as its
  ``load``, its decoding calls (summed) separately, both inside the subprocess; best of
  ``--peer-repeats`` subprocesses. Skipped with the reason when its venv is absent.

Both sums of the squares of all decoded values are compared (a flip and a channel swap do not
change them), so the contenders are shown to decode the same numbers.

Bars (issue 18): ours at least 0.5 of the same-shape GEMM rate, and faster than btf-extractor where it
installs (``"bars"``; not measured when its venv is absent).

Usage: ``python benchmarks/bench_bonn_decode.py [--quick] [--lights 81] [--texture 256] [--k 64]
[--band-rows 16] [--repeats 3] [--peer-repeats 1] [--skip-btf-extractor]`` (30 s on the idle 2-core VM,
minutes when other work shares it: btf-extractor's OpenMP suffers most; progress and a result table on
stderr, the JSON result on stdout). ``--quick``: 27 x 27 rows, 128 x 128 texels, one repeat.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from _measure import bar, gemm_rate, log

OURS_OVER_GEMM = 0.5     # issue 18

ROOT = Path(__file__).resolve().parents[1]
READERS_SCRIPT = ROOT / "tests" / "tasks" / "bonn_readers.py"


def write_file(path: Path, n_l: int, side: int, k: int, seed: int) -> None:
    """A half-float DFMF of ``n_l`` lights x ``n_l`` views, ``side`` x ``side`` texels, K = ``k``."""
    from tasks.bonn.dfmf import write_dfmf
    from tasks.bonn.header import make_header

    rng = np.random.default_rng(seed)
    i = np.arange(n_l)
    angles = np.stack([np.deg2rad(75.0) * np.sqrt((i + 0.5) / n_l), np.deg2rad(137.5) * i % (2 * np.pi)], 1)
    header = make_header(angles, angles, side, side, signature="!DFMF08FCR", xml="<synthetic/>")
    n_rows, n_tx = n_l * n_l, side * side
    U = [rng.standard_normal((n_rows, k), dtype=np.float32) * 0.1 for _ in range(3)]
    SxV = [rng.standard_normal((n_tx, k), dtype=np.float32) * 0.1 for _ in range(3)]
    S = [np.linalg.norm(s, axis=0) for s in SxV]
    write_dfmf(path, header, 0, np.zeros(3, np.float32), np.eye(3, dtype=np.float32), S, U, SxV, scalar_size=2)


def gemm_pass(n_rows: int, k: int, band_tx: int, n_bands: int) -> Callable[[], None]:
    """The plain float32 GEMMs of one decoding pass: ``(n_rows, k) @ (k, band_tx)`` per band and channel."""
    rng = np.random.default_rng(0)
    A = rng.standard_normal((n_rows, k), dtype=np.float32)
    B = rng.standard_normal((k, band_tx), dtype=np.float32)
    C = np.empty((n_rows, band_tx), np.float32)

    def run() -> None:
        for _ in range(3 * n_bands):
            np.matmul(A, B, out=C)
    return run


def run_ours(path: Path, band_tx: int, repeats: int, flops: float) -> dict:
    """Load (lazy) and decode every texel band into reused buffers, each pass right after a pass of
    the same GEMMs in plain numpy (the machine's load changes: the pairs see the same conditions)."""
    from btfcore.bonn import decode_textures
    from tasks.bonn.dfmf import read_factorised

    start = time.perf_counter()
    fact = read_factorised(path)
    load_s = time.perf_counter() - start
    n_rows, n_tx, k = fact.header.n_lv, fact.header.n_tx, int(fact.U[0].shape[1])
    bands = [(t0, min(t0 + band_tx, n_tx)) for t0 in range(0, n_tx, band_tx)]
    # one reused contiguous buffer per band width (only the last band can be narrower)
    buffers = {w: np.empty((n_rows, w, 3), np.float32) for w in {t1 - t0 for t0, t1 in bands}}

    def decode_all(checksum: bool = False) -> float:
        acc = 0.0
        for t0, t1 in bands:
            block = decode_textures(fact.U, fact.SxV, slice(None), slice(t0, t1), out=buffers[t1 - t0])
            if checksum:
                acc += float(np.square(block, dtype=np.float64).sum())
        return acc

    gemm = gemm_pass(n_rows, k, band_tx, len(bands))
    gemm()
    checksum = decode_all(checksum=True)          # warm-up, and the sum of squares of every value
    ours_s, gemm_s = [], []
    for _ in range(repeats):
        for fn, times in ((gemm, gemm_s), (decode_all, ours_s)):
            start = time.perf_counter()
            fn()
            times.append(time.perf_counter() - start)
    return {"load_s": round(load_s, 4), "decode_s": round(min(ours_s), 3),
            "decode_s_all": [round(t, 3) for t in ours_s], "gemm_pass_s_all": [round(t, 3) for t in gemm_s],
            "gflop_per_s": round(flops / min(ours_s) / 1e9, 1),
            "gemm_gflop_per_s": round(flops / min(gemm_s) / 1e9, 1),
            "over_gemm": round(min(gemm_s) / min(ours_s), 3), "checksum": checksum}


def readers_python() -> Path:
    return Path(os.environ.get("BTF_READERS_PYTHON") or ROOT / ".venv-readers" / "bin" / "python")


def run_btf_extractor(path: Path, scratch: Path, repeats: int) -> dict:
    """btf-extractor in its venv, ``repeats`` subprocesses: its load and decode seconds as measured
    inside each (best of them)."""
    python = readers_python()
    if not python.exists():
        return {"skipped": f"no readers venv at {python.parent.parent} (`make readers` builds it)"}
    out = scratch / "btf-extractor.npz"
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        proc = subprocess.run([str(python), str(READERS_SCRIPT), "btf-extractor", str(path), str(out),
                               "--time-only"], capture_output=True, text=True)
        wall = time.perf_counter() - start
        if proc.returncode:
            return {"skipped": f"btf-extractor failed (status {proc.returncode}): {proc.stderr.strip()[-500:]}"}
        with np.load(out) as saved:
            runs.append({"load_s": float(saved["load_s"]), "decode_s": float(saved["decode_s"]),
                         "wall_s": wall, "checksum": float(saved["checksum"])})
    return {"load_s": round(min(r["load_s"] for r in runs), 4),
            "decode_s": round(min(r["decode_s"] for r in runs), 3),
            "decode_s_all": [round(r["decode_s"], 3) for r in runs],
            "subprocess_wall_s_all": [round(r["wall_s"], 2) for r in runs], "checksum": runs[0]["checksum"]}


def table(result: dict) -> str:
    """The human-readable summary printed to stderr."""
    ours, peer, gemm = result["ours"], result["btf_extractor"], result["gemm_gflop_per_s"]
    rows = [("data", result["data"]),
            ("GEMM float32, the decode's shapes (GFLOP/s)", f"{gemm['decode_pass']} ({gemm['decode_pass_shapes']})"),
            ("GEMM float32, 2048^3 (GFLOP/s)", f"{gemm['square_2048']}"),
            ("ours: load (lazy memmaps)", f"{ours['load_s']} s"),
            ("ours: decode all textures", f"{ours['decode_s']} s = {ours['gflop_per_s']} GFLOP/s"),
            ("ours / GEMM rate (bar: >= 0.5)", f"{ours['over_gemm']}")]
    if "skipped" in peer:
        rows.append(("btf-extractor", peer["skipped"]))
    else:
        rows += [("btf-extractor: load (reads whole file, flips)", f"{peer['load_s']} s"),
                 ("btf-extractor: decode all images", f"{peer['decode_s']} s = {peer['gflop_per_s']} GFLOP/s"),
                 ("btf-extractor decode / ours (speed-up)", f"{result['speedup_over_btf_extractor']}"),
                 ("checksums: relative difference", f"{result['checksum_relative_difference']:.2e}")]
    width = max(len(name) for name, _ in rows)
    return "\n".join(f"{name:<{width}}  {value}" for name, value in rows)


def _parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--lights", type=int, default=81, help="n_l = n_v [default: 81]")
    parser.add_argument("--texture", type=int, default=256, help="texture side [default: 256]")
    parser.add_argument("--k", type=int, default=64, help="components per channel [default: 64]")
    parser.add_argument("--band-rows", type=int, default=16, help="texture rows per band [default: 16]")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--peer-repeats", type=int, default=1, help="btf-extractor runs [default: 1]")
    parser.add_argument("--skip-btf-extractor", action="store_true")
    parser.add_argument("--quick", action="store_true", help="27 x 27 rows, 128 x 128 texels, one repeat")
    args = parser.parse_args()
    if args.quick:
        args.lights, args.texture, args.repeats = 27, 128, 1
    return args


def main() -> int:
    args = _parse_args()
    n_rows, n_tx, k = args.lights ** 2, args.texture ** 2, args.k
    band_tx = min(args.band_rows * args.texture, n_tx)
    flops = 2.0 * n_rows * n_tx * k * 3
    scratch = Path(tempfile.mkdtemp(prefix="bench-bonn-decode-"))
    load = {"start": round(os.getloadavg()[0], 2)}
    result: dict = {
        "benchmark": "bonn-decode", "date": time.strftime("%Y-%m-%d %H:%M"),
        "machine": f"{platform.node()} {os.cpu_count()} cores", "command": "python " + " ".join(sys.argv),
        "data": f"DFMF half, {args.lights} x {args.lights} = {n_rows} rows, {args.texture} x {args.texture} "
                f"texels, K = {k} x 3 channels; bands of {band_tx} texels",
        "gflop": round(flops / 1e9, 1),
    }
    try:
        path = scratch / "synthetic.btf"
        log(f"writing {path}")
        write_file(path, args.lights, args.texture, k, args.seed)
        result["file_mb"] = round(path.stat().st_size / 1e6, 1)
        log("decoding (ours), each pass after the same GEMMs in plain numpy")
        ours = result["ours"] = run_ours(path, band_tx, args.repeats, flops)
        log(f"ours: {ours}")
        peer = result["btf_extractor"] = ({"skipped": "--skip-btf-extractor"} if args.skip_btf_extractor
                                          else run_btf_extractor(path, scratch, args.peer_repeats))
        if "decode_s" in peer:
            peer["gflop_per_s"] = round(flops / peer["decode_s"] / 1e9, 1)
            result["speedup_over_btf_extractor"] = round(peer["decode_s"] / ours["decode_s"], 2)
            result["checksum_relative_difference"] = abs(peer["checksum"] - ours["checksum"]) / max(
                abs(ours["checksum"]), 1e-30)
        log(f"btf-extractor: {peer}")
        square = round(gemm_rate(2048, 2048, 2048), 1)
        result["gemm_gflop_per_s"] = {"decode_pass_shapes": f"3 x {-(-n_tx // band_tx)} x ({n_rows},{k}) @ "
                                                            f"({k},{band_tx})",
                                      "decode_pass": ours["gemm_gflop_per_s"], "square_2048": square}
        speedup = result.get("speedup_over_btf_extractor")
        result["bars"] = [
            bar("decode GFLOP/s / same-shape GEMM GFLOP/s", ours["over_gemm"], f">= {OURS_OVER_GEMM}",
                ours["over_gemm"] >= OURS_OVER_GEMM, 18),
            bar("btf-extractor decode s / ours", speedup,
                "> 1" if speedup is not None else f"> 1; not measured: {peer.get('skipped', 'no result')[:80]}",
                None if speedup is None else speedup > 1, 18)]
    finally:
        load["end"] = round(os.getloadavg()[0], 2)
        result["load_average_1min"] = load
        shutil.rmtree(scratch, ignore_errors=True)
    print(table(result), file=sys.stderr)
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
