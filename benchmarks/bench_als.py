"""Benchmark: the batched relative-error ALS solve against the machine's GEMM rate.

:func:`btfcore.model.als.als_basis` (paper 4, eqs. 5-8) on a positive synthetic
matrix ``D`` (``--n-lv`` x ``--n-tx``, float32, rank ``--c`` plus 1 %
noise, all entries positive) with ``W = relative_error_weights(D)``, as
``tasks.model`` fits a material, on the default backend (torch; CPU here,
torch's default threads). Reported:

* ``s_per_iteration`` = (T(K iterations) - T(1 iteration)) / (K - 1), K = ``--iterations`` (3), so that the
  set-up, the first solve for ``V`` and the last one (which does not
  accumulate the rows' systems) cancel; medians of ``--repeats`` runs
  (``tol=0``: every iteration runs);
* ``gemm_gflop_per_iteration``: the matrix products of one iteration as
  btfcore/model/als.py does them, with ``n_pack = c (c + 1) / 2``:
  ``Gp = (W^2)^T P`` (2 n_lv n_tx n_pack), ``(W^2 D)^T U`` (2 n_lv n_tx c),
  the residual ``U V_chunk`` (2 n_lv n_tx c), ``Gr += W^2 (V_i V_j)^T``
  (2 n_lv n_tx n_pack) and ``Rr += (W^2 D) V^T`` (2 n_lv n_tx c), i.e.
  ``2 n_lv n_tx (2 n_pack + 3 c)``; the batched Cholesky solves
  (``(n_tx + n_lv) c^3 / 3`` and the substitutions) are not counted;
* ``als_gflop_per_s`` = those flops / ``s_per_iteration``;
* ``gemm_gflop_per_s``: plain float32 torch GEMMs of the two packed
  normal-matrix products' shapes (one chunk of texels, as als_basis
  chunks them), a torch 4096^3 and a numpy 4096^3 (numpy has its own BLAS,
  which may be faster), best of 3 each, measured before and after;
  ``over_gemm_peak`` divides by the largest of all, ``over_torch_gemm_peak``
  by the largest torch one;
* ``cholesky_s_per_iteration``: the library's solve of ``n_tx + n_lv`` packed random SPD
  ``c x c`` normal systems (scatter, batched Cholesky, triangular solves), timed on its own,
  and its share of an iteration.

Bar (issue 21, raising issue 4's 0.40): the batched ALS solve runs at no less than 0.8 of the
GEMM rate (``over_gemm_peak``).

Usage: ``python benchmarks/bench_als.py [--quick] [--n-lv 4096] [--n-tx 16384] [--c 64] [--repeats 3] [--chunk-mb MB]``;
``--quick``: 1,024 x 4,096, c = 32, one repeat (a smoke run, not a figure).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import numpy as np
from _measure import bar, best_seconds, log, torch_gemm_rate

ALS_OVER_GEMM = 0.8      # issue 21


def numpy_gemm_rate(n: int, repeats: int = 3) -> float:
    """GFLOP/s of a float32 numpy ``(n, n) @ (n, n)`` GEMM (numpy's own BLAS), best of ``repeats``."""
    A = np.random.default_rng(0).standard_normal((n, n), dtype=np.float32)
    C = np.empty_like(A)
    return 2.0 * n**3 / best_seconds(lambda: np.matmul(A, A, out=C), repeats) / 1e9


def gemm_rates(n_lv: int, step: int, n_pack: int, device: str = "cpu") -> dict[str, float]:
    """GFLOP/s of the GEMMs the ALS is held to, on the device it ran on (numpy's only on the CPU)."""
    rates = {} if device != "cpu" else {"numpy 4096x4096 @ 4096x4096": numpy_gemm_rate(4096)}
    rates.update({
        f"torch {device} 4096x4096 @ 4096x4096": torch_gemm_rate(4096, 4096, 4096, device=device),
        f"(W^2)^T P: ({step},{n_lv})^T-stored @ ({n_lv},{n_pack})": torch_gemm_rate(step, n_lv, n_pack,
                                                                                transpose_a=True, device=device),
        f"W^2 (V_i V_j)^T: ({n_lv},{step}) @ ({step},{n_pack})": torch_gemm_rate(n_lv, step, n_pack, device=device),
    })
    return {name: round(r, 1) for name, r in rates.items()}


def cholesky_seconds(n_systems: int, c: int, step: int, device: str = "cpu") -> float:
    """Seconds the library's normal-equation solve (``als._solve_packed``: scatter the packed triangles,
    factorise, two triangular solves, in its CPU batches and threads) takes for ``n_systems`` SPD
    ``c x c`` systems handed over in chunks of ``step``, as one iteration's V- and U-steps do."""
    import torch

    from btfcore.model import als

    ops = als._ops("torch", device, np.dtype(np.float32))
    iu, ju = (ops.asarray(i) for i in np.triu_indices(c))
    g = torch.Generator().manual_seed(0)
    A = torch.randn((step, 2 * c, c), generator=g)
    G = A.transpose(1, 2) @ A + torch.eye(c)
    Gp, R = G[:, iu, ju].to(device), torch.randn((step, c), generator=g).to(device)
    sync = torch.cuda.synchronize if device != "cpu" else (lambda: None)
    sync()
    start = time.perf_counter()
    done = 0
    while done < n_systems:
        m = min(step, n_systems - done)
        als._solve_packed(ops, Gp[:m], R[:m], iu, ju, c, m)
        done += m
    sync()
    return time.perf_counter() - start


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-lv", type=int, default=4096)
    parser.add_argument("--n-tx", type=int, default=16384)
    parser.add_argument("--c", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=3, help="runs of T(1) and T(K), interleaved [default: 3]")
    parser.add_argument("--iterations", type=int, default=3,
                        help="K of the long run, >= 2 [default: 3; on a GPU, where the set-up dominates, 21]")
    parser.add_argument("--backend", default="auto", choices=("auto", "torch", "numpy"))
    parser.add_argument("--data-rank", type=int, default=None,
                        help="rank of the synthetic D [default: c; above c the fit keeps improving for more "
                             "iterations, which a long --iterations run needs]")
    parser.add_argument("--chunk-mb", type=int, default=None,
                        help="working-memory budget of one chunk's solve, MiB [default: als_basis' CHUNK_BYTES]")
    parser.add_argument("--quick", action="store_true", help="1024 x 4096, c = 32, one repeat")
    args = parser.parse_args()
    if args.quick:
        args.n_lv, args.n_tx, args.c, args.repeats = 1024, 4096, 32, 1
    import torch

    from btfcore.model import als
    from btfcore.model.als import CHUNK_BYTES, als_basis, relative_error_weights

    n_lv, n_tx, c = args.n_lv, args.n_tx, args.c
    load_start = round(os.getloadavg()[0], 2)
    rng = np.random.default_rng(0)
    rank = args.data_rank or c
    A = rng.uniform(0.1, 1.0, (n_lv, rank)).astype(np.float32)
    B = rng.uniform(0.1, 1.0, (rank, n_tx)).astype(np.float32)
    D = A @ B
    D *= (1 + 0.01 * rng.standard_normal(D.shape, dtype=np.float32))
    np.maximum(D, 0.0, out=D)
    W = relative_error_weights(D)
    del A, B
    n_pack = c * (c + 1) // 2
    chunk_bytes = CHUNK_BYTES if args.chunk_mb is None else args.chunk_mb * 2**20
    step = als._chunk_size(als._per_texel_floats(n_lv, c), 4, n_tx, chunk_bytes)   # als_basis' chunk
    device = "cuda" if args.backend != "numpy" and torch.cuda.is_available() else "cpu"   # where als_basis runs
    gemm_before = gemm_rates(n_lv, step, n_pack, device)
    log(f"GEMM GFLOP/s: {gemm_before}")

    def run(n_iter: int) -> tuple[float, object]:
        start = time.perf_counter()
        res = als_basis(D, c, W, n_iter=n_iter, tol=0.0, seed=0, backend=args.backend, chunk_bytes=chunk_bytes)
        return time.perf_counter() - start, res

    run(1)                                                         # warm-up: first touch, thread pools
    t1, t3, res3 = [], [], None
    for rep in range(args.repeats):
        t, res1 = run(1)
        t1.append(t)
        t, res3 = run(args.iterations)
        t3.append(t)
        log(f"run {rep + 1}: T(1) = {t1[-1]:.2f} s, T({args.iterations}) = {t3[-1]:.2f} s (iterations "
            f"{res1.iterations}, {res3.iterations})")
    # the iterations run (an objective that stops falling by rounding ends the fit early even at tol = 0)
    per_it = (float(np.median(t3)) - float(np.median(t1))) / max(1, res3.iterations - res1.iterations)
    gemm_flops = 2.0 * n_lv * n_tx * (2 * n_pack + 3 * c)
    chol = cholesky_seconds(n_tx + n_lv, c, step, device)
    gemm_after = gemm_rates(n_lv, step, n_pack, device)
    log(f"GEMM GFLOP/s after: {gemm_after}")
    peak = max(max(gemm_before.values()), max(gemm_after.values()))
    torch_peak = max(v for d in (gemm_before, gemm_after) for name, v in d.items() if not name.startswith("numpy"))
    rate = gemm_flops / per_it / 1e9
    result = {
        "benchmark": "als", "date": time.strftime("%Y-%m-%d"),
        "machine": f"{platform.node()} {os.cpu_count()} cores", "command": "python " + " ".join(sys.argv),
        "data": f"positive rank-{rank} + 1 % noise, {n_lv} x {n_tx} float32, W = relative_error_weights(D)",
        "backend": f"{res3.backend} on {res3.device}, {torch.get_num_threads()} torch threads",
        "c": c, "chunk_texels": step, "iterations_run": [1, res3.iterations],
        "t1_s": [round(t, 2) for t in t1], "tK_s": [round(t, 2) for t in t3],
        "s_per_iteration": round(per_it, 4),
        "gemm_gflop_per_iteration": round(gemm_flops / 1e9, 1),
        "als_gflop_per_s": round(rate, 1),
        "gemm_gflop_per_s": {"before": gemm_before, "after": gemm_after, "peak": peak},
        "over_gemm_peak": round(rate / peak, 3), "over_torch_gemm_peak": round(rate / torch_peak, 3),
        "cholesky_s_per_iteration": round(chol, 4), "cholesky_share": round(chol / per_it, 3),
        "objective_non_increasing": bool(np.all(np.diff(res3.objective) <= 1e-6 * res3.objective[:-1])),
        "bars": [bar("ALS GFLOP/s / GEMM GFLOP/s", round(rate / peak, 3), f">= {ALS_OVER_GEMM}",
                     rate / peak >= ALS_OVER_GEMM, 21)],
        "load_average_1min": {"start": load_start, "end": round(os.getloadavg()[0], 2)},
    }
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
