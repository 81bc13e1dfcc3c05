"""Benchmark: applying a reconstruction operator over texel chunks against the machine's GEMM rate.

:func:`btfcore.acquisition.reconstruct.apply` at the thesis' scale (paper 4, §5: 198
LEDs x 11 cameras x 12 turntable positions = 26,136 light/view pairs,
128 x 128 RGB texels, float32; ``n_s = 400`` light/turntable pairs times 11
cameras = 4,400 measured rows; ``k = 1024`` basis vectors). The full
reconstruction ``B_hat`` is 26,136 x 49,152 float32 = 5.1 GB: it is never
held; each chunk of ``--chunk`` texel-channel columns is written into one
reused output buffer (nothing is written to disk). The measurement
``(n_meas, n_tx)`` is generated once, in chunks, before timing (its values do
not affect the speed).

Reported:

* ``fused``: the operator ``F = U R`` (``n_lv x n_meas``) applied chunk by
  chunk, one GEMM each; flops ``2 n_lv n_meas n_tx``; ``fused_gflop_per_s``
  and its ratio to the plain GEMM rate;
* ``factored``: ``U (R y)``, two GEMMs, ``2 k (n_lv + n_meas) n_tx`` flops;
  its wall time (what :func:`solve_operator`'s ``fused=None`` picks by flop
  count, ``auto_choice``);
* ``gemm_gflop_per_s``: a plain float32 numpy GEMM of the same shapes
  (``(n_lv, n_meas) @ (n_meas, chunk)`` into a preallocated output) and a
  4096^3 one, best of 3, measured before and after; ``over_gemm`` divides by
  the largest;
* ``build_s``: building the operator (float64 SVD of ``M U`` and ``U R``;
  about 15 s on an idle 2-core VM, much more when the cores are shared).

Bar (issue 5): the fused apply runs at >= 0.5 of the plain float32 GEMM rate (``"bars"``).

Usage: ``python benchmarks/bench_reconstruct.py [--quick] [--n-lv 26136] [--n-meas 4400] [--k 1024]
[--n-tx 49152] [--chunk 2048] [--repeats 3]``; ``--quick`` uses 4,096 columns and one repeat.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time

import numpy as np
from _measure import bar, best_seconds, gemm_rate, log


def gemm_rates(n_lv: int, n_meas: int, chunk: int, repeats: int) -> dict[str, float]:
    rates = {
        f"({n_lv},{n_meas}) @ ({n_meas},{chunk})": gemm_rate(n_lv, n_meas, chunk, repeats),
        "4096x4096 @ 4096x4096": gemm_rate(4096, 4096, 4096, repeats),
    }
    return {name: round(r, 1) for name, r in rates.items()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-lv", type=int, default=26136)
    parser.add_argument("--n-meas", type=int, default=4400)
    parser.add_argument("--k", type=int, default=1024)
    parser.add_argument("--n-tx", type=int, default=128 * 128 * 3)
    parser.add_argument("--chunk", type=int, default=2048, help="texel-channel columns per chunk [2048]")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="4096 columns, one repeat")
    args = parser.parse_args()
    if args.quick:
        args.n_tx, args.repeats = 4096, 1

    from btfcore.acquisition.reconstruct import apply, solve_operator

    n_lv, n_meas, k, n_tx, chunk = args.n_lv, args.n_meas, args.k, args.n_tx, args.chunk
    load_start = round(os.getloadavg()[0], 2)
    rng = np.random.default_rng(0)
    U = rng.standard_normal((n_lv, k), dtype=np.float32)
    rows = np.sort(rng.choice(n_lv, n_meas, replace=False))
    start = time.perf_counter()
    fused = solve_operator(U, rows=rows, fused=True)                   # float32 apply
    build_s = time.perf_counter() - start
    factored = dataclasses.replace(fused, fused=None)                  # same R and U, two GEMMs
    auto_fused = n_lv * n_meas <= k * (n_lv + n_meas)                  # solve_operator's fused=None rule
    del U
    log(f"operator built in {build_s:.1f} s (condition {fused.condition:.3g})")
    bounds = [(a, min(a + chunk, n_tx)) for a in range(0, n_tx, chunk)]
    measured = [rng.standard_normal((n_meas, b - a), dtype=np.float32) for a, b in bounds]
    out = np.empty((n_lv, chunk), np.float32)

    def run(op) -> None:
        for y in measured:
            apply(op, y, out=out[:, :y.shape[1]] if y.shape[1] == chunk else None)

    gemm_before = gemm_rates(n_lv, n_meas, chunk, 3)
    log(f"GEMM GFLOP/s: {gemm_before}")
    t_fused = best_seconds(lambda: run(fused), args.repeats)
    log(f"fused: {t_fused:.2f} s")
    t_factored = best_seconds(lambda: run(factored), args.repeats)
    log(f"factored: {t_factored:.2f} s")
    gemm_after = gemm_rates(n_lv, n_meas, chunk, 3)
    log(f"GEMM GFLOP/s after: {gemm_after}")
    peak = max(max(gemm_before.values()), max(gemm_after.values()))
    flops_fused = 2.0 * n_lv * n_meas * n_tx
    flops_factored = 2.0 * k * (n_lv + n_meas) * n_tx
    rate = flops_fused / t_fused / 1e9
    result = {
        "benchmark": "reconstruct", "date": time.strftime("%Y-%m-%d"),
        "machine": f"{platform.node()} {os.cpu_count()} cores", "command": "python " + " ".join(sys.argv),
        "data": f"n_lv={n_lv}, n_meas={n_meas} (sparse pinv), k={k}, n_tx={n_tx} float32 in chunks of {chunk}",
        "b_hat_gb": round(n_lv * n_tx * 4 / 1e9, 2), "build_s": round(build_s, 2),
        "fused_s": round(t_fused, 2), "fused_gflop": round(flops_fused / 1e9, 1),
        "fused_gflop_per_s": round(rate, 1),
        "factored_s": round(t_factored, 2), "factored_gflop": round(flops_factored / 1e9, 1),
        "factored_gflop_per_s": round(flops_factored / t_factored / 1e9, 1),
        "auto_choice": "fused" if auto_fused else "factored",
        "texels_per_s_fused": round(n_tx / 3 / t_fused), "texels_per_s_factored": round(n_tx / 3 / t_factored),
        "gemm_gflop_per_s": {"before": gemm_before, "after": gemm_after, "peak": peak},
        "over_gemm": round(rate / peak, 3),
        "factored_over_gemm": round(flops_factored / t_factored / 1e9 / peak, 3),
        "bars": [bar("fused apply GFLOP/s / GEMM GFLOP/s", round(rate / peak, 3), ">= 0.5", rate / peak >= 0.5, 5)],
        "load_average_1min": {"start": load_start, "end": round(os.getloadavg()[0], 2)},
    }
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
