"""Benchmark: 8-bit HDR calibration and merges against OpenCV's, same bracket, same run.

Bracket: generated here, seeded. A lognormal RGB radiance (sigma 1.5 plus
10 % colour) of ``--size`` x ``--size`` pixels, exposed at 1/8, 1 and 8 s
through a saturating film-like curve and an sRGB-like gamma, rounded to
uint8: ``(3, size, size, 3)``, about 0.8 % of the values at 0 or 255.
OpenCV gets the same arrays (channel order does not matter for timing).

Timed (best of ``--repeats`` after one warm-up call):

* ``calibrate_debevec``: ``response_debevec(..., channel_axis=-1)`` (4096
  stratified samples per channel) vs ``cv2.createCalibrateDebevec()`` (70
  grid samples);
* ``merge_debevec``: ``merge_response(..., method='debevec')`` vs
  ``cv2.createMergeDebevec()``, both through the same response;
* ``merge_robertson``: ``merge_response(..., method='robertson')`` vs
  ``cv2.createMergeRobertson()``, same response;
* ``calibrate_robertson``: ``response_robertson`` vs
  ``cv2.createCalibrateRobertson()`` (both up to 30 iterations; reported,
  not part of the target).

OpenCV is timed twice: with one thread (``cv2.setNumThreads(1)``, the
same as numpy's element-wise code) and with its default thread count.
**ratio** = OpenCV's seconds / ours: above 1, ours is faster.
Target (issue 19): ratio >= 1 against single-threaded OpenCV for the
Debevec calibration and both merges.

Usage: ``python benchmarks/bench_hdr_opencv.py [--quick] [--size 1024] [--repeats 7]``;
run with ``OMP_NUM_THREADS=1`` on an otherwise idle machine. ``--quick``: 256 x 256, 3 repeats.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import numpy as np
from _measure import bar, best_seconds, log

TIMES = np.array([0.125, 1.0, 8.0])


def bracket(size: int, seed: int) -> np.ndarray:
    """(3, size, size, 3) uint8 bracket of a seeded lognormal scene through a film-like, gamma-encoded curve."""
    rng = np.random.default_rng(seed)
    rad = np.exp(rng.normal(0.0, 1.5, (size, size, 1))) * np.exp(rng.normal(0.0, 0.1, (size, size, 3)))
    x = rad[None] * TIMES.reshape(-1, 1, 1, 1)
    z = 255.0 * (x / (1.0 + x)) ** (1 / 2.2) + rng.normal(0.0, 0.7, x.shape)
    return np.clip(np.rint(z), 0, 255).astype(np.uint8)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=1024, help="image side, pixels [default: 1024]")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="256 x 256 pixels, 3 repeats")
    args = parser.parse_args()
    if args.quick:
        args.size, args.repeats = 256, 3
    import cv2

    from btfcore.capture.hdr import merge_response, response_debevec, response_robertson

    load_start = round(os.getloadavg()[0], 2)
    imgs = bracket(args.size, args.seed)
    frames = [np.ascontiguousarray(im) for im in imgs]
    tf = TIMES.astype(np.float32)
    clipped = float(np.mean((imgs == 0) | (imgs == 255)))
    log(f"bracket {imgs.shape} uint8, {clipped:.3%} of the values at 0 or 255")
    resp = np.exp(response_debevec(imgs, TIMES, rng=0, channel_axis=-1))
    rob = response_robertson(imgs, TIMES, channel_axis=-1)
    cv_resp = np.ascontiguousarray(resp[:, None, :], dtype=np.float32)
    cv_rob = np.ascontiguousarray(rob[:, None, :], dtype=np.float32)
    cases = {
        "calibrate_debevec": (lambda: response_debevec(imgs, TIMES, rng=0, channel_axis=-1),
                              lambda: cv2.createCalibrateDebevec().process(frames, tf)),
        "merge_debevec": (lambda: merge_response(imgs, TIMES, resp, method="debevec"),
                          lambda: cv2.createMergeDebevec().process(frames, tf, cv_resp)),
        "merge_robertson": (lambda: merge_response(imgs, TIMES, rob, method="robertson"),
                            lambda: cv2.createMergeRobertson().process(frames, tf, cv_rob)),
        "calibrate_robertson": (lambda: response_robertson(imgs, TIMES, channel_axis=-1),
                                lambda: cv2.createCalibrateRobertson().process(frames, tf)),
    }
    default_threads = cv2.getNumThreads()
    runs = {}
    for name, (ours, theirs) in cases.items():
        reps = 1 if name == "calibrate_robertson" else args.repeats
        t_ours = best_seconds(ours, reps)
        cv2.setNumThreads(1)
        t_cv1 = best_seconds(theirs, reps)
        cv2.setNumThreads(default_threads)
        t_cvn = best_seconds(theirs, reps)
        runs[name] = {"ours_s": round(t_ours, 4), "opencv_1thread_s": round(t_cv1, 4),
                      f"opencv_{default_threads}threads_s": round(t_cvn, 4),
                      "ratio_1thread": round(t_cv1 / t_ours, 2),
                      "ratio_default_threads": round(t_cvn / t_ours, 2)}
        log(f"{name:20s} ours {t_ours:.4f} s, OpenCV 1 thread {t_cv1:.4f} s ({t_cv1 / t_ours:.2f}x), "
            f"{default_threads} threads {t_cvn:.4f} s ({t_cvn / t_ours:.2f}x)")
    targeted = ("calibrate_debevec", "merge_debevec", "merge_robertson")
    result = {
        "benchmark": "hdr_opencv", "date": time.strftime("%Y-%m-%d %H:%M"),
        "machine": f"{platform.node()} {os.cpu_count()} cores",
        "command": "python " + " ".join(sys.argv),
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
        "opencv": cv2.__version__, "numpy": np.__version__,
        "bracket": f"3 x {args.size} x {args.size} x 3 uint8, times {TIMES.tolist()} s",
        "runs": runs,
        "bars": [bar(f"OpenCV 1-thread s / ours, {name}", runs[name]["ratio_1thread"], ">= 1",
                     runs[name]["ratio_1thread"] >= 1, 19) for name in targeted],
        "load_average_1min": {"start": load_start, "end": round(os.getloadavg()[0], 2)},
    }
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
