"""Benchmark: the adaptive loop's per-step overhead against the device's time per shot, at the thesis' scale.

One step of :func:`btfcore.acquisition.adaptive.run_adaptive` besides the shot itself: choosing the next
group (the default, :meth:`AdaptiveState.committee_gains`: ``--committee`` other bases fitted to the measured
rows and compared with the class basis on the predictor's texel subset; and, timed beside it,
:meth:`AdaptiveState.gains`, every candidate's exact rank-``n_cam`` update) and updating the
reconstruction (:meth:`AdaptiveState.add`: the rank-``n_cam`` update of the solve, the error model and the
prediction on the predictor's texel subset), with the loop's default fused measured rows (their error counted
by :func:`~btfcore.acquisition.adaptive.fused_error`). The values matter to the prediction's cost in one
place: :func:`~btfcore.acquisition.adaptive.expected_log_error` reads its table for entries whose
uncertainty is above a tenth of their value, which on this random basis is every unmeasured entry (the
worst case). Solving for the coefficients of every texel
(:meth:`AdaptiveState.coefficients`, needed once at the stop) is timed beside it
(``all_coefficients_cpu_s``). It runs with one BLAS thread (set before numpy loads, unless the
environment sets it): with more, ``process_time`` counts the BLAS threads' spin-waiting. Scale:
the thesis' dome, 198 LEDs x 11 cameras x 12 turntable positions = 26,136 light/view pairs, 2,376
(turntable, LED) groups, 128 x 128 RGB texels, a k = 64 ALS basis (paper 4 §5). The basis is a random
orthonormal one and the measurements its rows times positive coefficients. Steps are timed in CPU seconds (``time.process_time``: the machine is shared) after
``--at`` groups measured, and compared with the time model's predicted seconds per shot of a sparse plan
of the thesis' n_s = 400 pairs (:func:`btfcore.acquisition.time_model.predict_time`, default exposure).

Bar (issue 20): per-step overhead < 5 % of the device's time per shot (CPU seconds, the largest ``--at``),
of the default (committee) selection; the posterior selection's share is reported beside it. With
``--predictor probes`` every :data:`~btfcore.acquisition.adaptive.PROBE_EVERY`-th group after the start design
is a probe and the update's prediction includes the probes' estimate, whose committee disagreement the next
choice reads from the model, as in :func:`~btfcore.acquisition.adaptive.run_adaptive` (each choice takes the
model of the update before it).

Usage: ``python benchmarks/bench_adaptive.py [--quick] [--k 64] [--texels 128] [--at 12,100,400]
[--committee 11] [--predictor probes]``;
``--quick`` uses 32 x 32 texels and ``--at 12,50``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")          # CPU seconds of the work, not of BLAS threads spin-waiting

import numpy as np  # noqa: E402
from _measure import bar, log  # noqa: E402


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--k", type=int, default=64)
    p.add_argument("--texels", type=int, default=128, help="texture side")
    p.add_argument("--at", default="12,100,400", help="groups measured before the timed steps")
    p.add_argument("--repeats", type=int, default=3, help="timed steps at each --at")
    p.add_argument("--committee", type=int, default=11,
                   help="other bases of the committee (the evaluation's: the other 11 materials)")
    p.add_argument("--predictor", default="posterior", choices=("posterior", "probes"),
                   help="the loop's predictor: probes adds the probe groups and their estimate to the step")
    args = p.parse_args(argv)
    if args.quick:
        args.texels, args.at, args.repeats = 32, "12,50", 2

    from btfcore.acquisition.adaptive import PROBE_EVERY, AdaptiveState, group_rows, start_groups
    from btfcore.acquisition.noise import SensorNoise
    from btfcore.acquisition.plan import sparse_plan
    from btfcore.acquisition.strategies import THESIS_N_S, Geometry
    from btfcore.acquisition.time_model import predict_time
    from btfcore.dome import get_device

    device = get_device("bonn-dome2")
    g = Geometry(device.n_turn, device.n_cam, device.n_leds, args.texels, args.texels)
    n_tx = args.texels ** 2
    rng = np.random.default_rng(0)
    log(f"basis {g.n_lv} x {args.k}, {n_tx} texels")
    U = np.linalg.qr(rng.normal(size=(g.n_lv, args.k)))[0]
    sigma = np.geomspace(100, 1, args.k)
    C = np.abs(rng.normal(size=(args.k, n_tx * 3))) * sigma[:, None] / 100
    noise = SensorNoise()

    def measure(group: int) -> tuple[np.ndarray, np.ndarray]:
        rows = group_rows(np.array([group]), g)[0]
        y = np.abs(U[rows] @ C).reshape(len(rows), n_tx, 3) + 1e-3
        return y, np.full(len(rows), 1e4)

    ats = [int(a) for a in args.at.split(",")]
    committee = [(np.linalg.qr(rng.normal(size=(g.n_lv, args.k)))[0], sigma) for _ in range(args.committee)]
    st = AdaptiveState(U, sigma, g, noise, n_tx=n_tx, committee=committee, measured_rows="fused")   # the loop's default
    first = start_groups(U, sigma, g, min(ats[0], 12))
    for grp in first:
        st.add(grp, *measure(grp))
    st.unbiased_groups = len(first)                    # as run_adaptive: the predictor's misfit from the start rows
    order = [x for x in rng.permutation(g.n_turn * g.n_leds).tolist() if x not in first]
    results = {}
    probes = args.predictor == "probes"

    def is_probe() -> bool:                            # run_adaptive's schedule
        return probes and (len(st.groups) - len(first)) % PROBE_EVERY == 0

    for at in ats:
        while len(st.groups) < at:
            grp = order.pop()
            if grp not in st.groups:                   # not one a timed step chose
                st.add(grp, *measure(grp), probe=is_probe())
        choose, posterior, update, coeffs = [], [], [], []
        model = st._model()
        for _ in range(args.repeats):
            t0 = time.process_time()
            nxt = int(np.argmax(st.committee_gains(model)))
            choose.append(time.process_time() - t0)      # the committee's choice alone (until 2026-12-06 this
            t0 = time.process_time()                     # also held the posterior gains timed next)
            st.gains(model)
            posterior.append(time.process_time() - t0)
            y, gain = measure(nxt)
            t0 = time.process_time()
            st.add(nxt, y, gain, probe=is_probe())
            model = st._model()
            st.predict(model)
            update.append(time.process_time() - t0)
            t0 = time.process_time()
            st.coefficients()
            coeffs.append(time.process_time() - t0)
        results[str(at)] = {"groups_measured": at, "choose_cpu_s": float(np.median(choose)),
                            "choose_posterior_cpu_s": float(np.median(posterior)),
                            "update_cpu_s": float(np.median(update)),
                            "all_coefficients_cpu_s": float(np.median(coeffs)),
                            "step_cpu_s": float(np.median(choose) + np.median(update))}
        log(f"at {at} groups: choose {results[str(at)]['choose_cpu_s']:.3f} s (committee of {args.committee}; "
            f"posterior {results[str(at)]['choose_posterior_cpu_s']:.3f} s), update "
            f"{results[str(at)]['update_cpu_s']:.3f} s CPU")
    n_s = THESIS_N_S[-1]
    pairs = np.stack(np.divmod(np.sort(rng.choice(g.n_turn * g.n_leds, n_s, replace=False)), g.n_leds), axis=1)
    per_shot = predict_time(sparse_plan(device, pairs)).total_s / n_s
    worst = max(r["step_cpu_s"] for r in results.values())
    share = worst / per_shot
    share_posterior = max(r["choose_posterior_cpu_s"] + r["update_cpu_s"] for r in results.values()) / per_shot
    out = {"benchmark": "adaptive", "platform": platform.platform(),
           "blas_threads": os.environ["OPENBLAS_NUM_THREADS"], "n_lv": g.n_lv, "k": args.k, "n_tx": n_tx,
           "committee": args.committee, "predictor": args.predictor,
           "probes": len(st.probes), "steps": results, "device_s_per_shot": per_shot,
           "overhead_share": share, "overhead_share_posterior": share_posterior,
           "bars": [bar("adaptive step CPU s / device s per shot (thesis scale" + (", probes)" if probes else ")"),
                        share, "< 0.05", share < 0.05, 20)]}
    print(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main(sys.argv[1:])
