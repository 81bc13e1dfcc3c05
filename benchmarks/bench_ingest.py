"""Benchmark: raw MB/s through `btf ingest` against an OpenCV per-image loop.

Data: a simulated bonn-dome2 capture, first turntable position, one material
(11 views x 198 single-LED brackets of 4 raw frames of 280x288, about 1.4 GB
of raw input).

* ``ingest_mb_per_s``: raw bytes / wall time of `ingest_capture` on the default
  LocalCluster (2 workers x 1 thread): HDR merge, Malvar demosaicing,
  anti-aliased rectification, demultiplexing, Zarr in and out;
* peer ``opencv_loop_mb_per_s``: the same steps as a plain per-image loop in one
  process, the way a lab script would write them with OpenCV: per frame
  black subtraction and a hat-weighted merge in float32, `cv2.cvtColor`
  edge-aware demosaic on the merge quantised to 16 bit, `cv2.warpPerspective`
  to the texture (INTER_LINEAR), each view's textures saved as one float32
  ``.npy`` file (the ingest writes the same bytes to Zarr); timed on the
  first ``--peer-views`` views;
* peer ``opencv_window_loop_mb_per_s``: the same loop on only the window of
  each frame that the texture reads (what btf ingest processes,
  :func:`btfcore.capture.rectify.support_window`), so that the ratio against it
  shows what is left once both crop;
* ``ratio`` = ingest / full-frame peer, ``ratio_window`` = ingest / window
  peer, measured in the same run;
* ``disk_read_mb_per_s``: reading a 1 GiB file past the page cache in the
  scratch folder (:func:`_measure.disk_read_rate`), before and after;
  ``over_disk_read`` = ingest / the larger of the two.

Bars (issue 21, raising issue 3's 2x and 300 MB/s): ``ratio`` at least 4 and
``over_disk_read`` at least 0.5 (``"bars"``).

The contenders run in ``--repeats`` interleaved rounds on the same cluster
and the medians are compared; the first round's ingest also includes the
workers' first imports of the numerical stack (``ratio_first_run``).

Usage: ``python benchmarks/bench_ingest.py [--peer-views N] [--capture STORE]``
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

import cv2
import numpy as np
from _measure import bar, disk_read_rate, log

OVER_LOOP, OVER_DISK_READ = 4.0, 0.5       # issue 21

OPENCV_EA = {"RGGB": cv2.COLOR_BayerBG2RGB_EA, "BGGR": cv2.COLOR_BayerRG2RGB_EA,
             "GRBG": cv2.COLOR_BayerGB2RGB_EA, "GBRG": cv2.COLOR_BayerGR2RGB_EA}


def opencv_loop(capture_path: str, n_views: int, out_dir: Path, window: bool = False) -> tuple[float, int]:
    """Seconds and raw bytes of the per-image OpenCV loop over the first views (``window``:
    only the part of each frame the texture reads, as btf ingest does). Each view's textures
    are saved to ``out_dir`` as one float32 .npy file: the same bytes the ingest writes."""
    from btfcore.capture.rectify import rectification_matrix, support_window, texture_homography
    from tasks.stores import open_capture_store

    store = open_capture_store(capture_path)
    meta = store.meta
    h, w = meta.texture_shape
    black, white = float(meta.black_level), float(meta.white_level)
    n_bytes, start = 0, time.perf_counter()
    views = [(t, c) for t in range(store.n_turn) for c in range(store.n_cam)][:n_views]
    textures = np.empty((store.n_illum, h, w, 3), np.float32)
    for t, c in views:
        G = texture_homography(store.homography[t, c], (h, w), meta.sample_size_m)
        rows, cols = slice(None), slice(None)
        if window:
            A = rectification_matrix(store.homography[t, c], store.roi_shape, (h, w), meta.sample_size_m)
            rows, cols, _ = support_window(A, store.roi_shape, margin=2, align=2)
            G = np.array([[1, 0, -cols.start], [0, 1, -rows.start], [0, 0, 1]]) @ G   # window pixel coordinates
        for i in range(store.n_illum):
            frames, times = store.read_bracket(t, c, i)
            n_bytes += frames.nbytes
            frames = np.ascontiguousarray(frames[:, rows, cols])
            acc = np.zeros(frames.shape[1:], np.float32)
            wsum = np.zeros(frames.shape[1:], np.float32)
            for frame, exposure in zip(frames, times):
                x = cv2.subtract(frame.astype(np.float32), black)
                weight = 1.0 - np.abs(2.0 * x / (white - black) - 1.0)          # hat weight
                weight[frame >= 0.98 * white] = 0.0
                acc += weight * x / float(exposure)
                wsum += weight
            hdr = acc / np.maximum(wsum, 1e-6)
            scale = 65535.0 / max(float(hdr.max()), 1e-12)
            rgb = cv2.cvtColor(np.clip(hdr * scale, 0, 65535).astype(np.uint16), OPENCV_EA[meta.bayer_pattern])
            textures[i] = cv2.warpPerspective(rgb.astype(np.float32) / scale, G, (w, h),
                                              flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        np.save(out_dir / f"view_t{t}_c{c}.npy", textures)
    return time.perf_counter() - start, n_bytes


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--peer-views", type=int, default=3, help="views timed for the OpenCV loop [default: 3]")
    parser.add_argument("--repeats", type=int, default=3,
                        help="interleaved rounds of (ingest, loop, window loop); medians are reported [default: 3]")
    parser.add_argument("--capture", default=None, help="reuse this bonn-dome2 capture store instead of simulating one")
    args = parser.parse_args()
    from flows.runtime import runtime
    from tasks.ingest import ingest_capture
    from tasks.simulate import SimulationConfig, simulate_database
    from tasks.stores import open_capture_store

    scratch = Path(tempfile.mkdtemp(prefix="bench-ingest-"))
    ingest_s, loop, window = [], [], []
    try:
        config = SimulationConfig(device="bonn-dome2", n_materials=1, seed=0, classes=("leather",), n_turntable=1)
        disk_read = [disk_read_rate(scratch) * 1e3]
        log(f"disk read {disk_read[0]:.0f} MB/s")
        with runtime() as (_profile, _url, client):
            capture = args.capture or simulate_database(config, scratch / "db", client).stores[0]
            raw_bytes = open_capture_store(capture).raw.nbytes
            # rounds interleave the contenders, so that the machine's drifts hit both alike
            for run in range(args.repeats):
                start = time.perf_counter()
                ingest_capture(capture, scratch / f"btf-{run}.zarr", client)
                ingest_s.append(time.perf_counter() - start)
                shutil.rmtree(scratch / f"btf-{run}.zarr")
                loop.append(opencv_loop(capture, args.peer_views, scratch))   # the workers idle meanwhile
                window.append(opencv_loop(capture, args.peer_views, scratch, window=True))
                log(f"round {run + 1}: ingest {ingest_s[-1]:.1f} s")
        disk_read.append(disk_read_rate(scratch) * 1e3)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)

    def rate(seconds: float, n_bytes: int) -> float:
        return n_bytes / 1e6 / seconds

    ingest_rates = [rate(s, raw_bytes) for s in ingest_s]
    ingest_rate = float(np.median(ingest_rates))
    peer_rate = float(np.median([rate(*r) for r in loop]))
    window_rate = float(np.median([rate(*r) for r in window]))
    result = {
        "benchmark": "ingest", "date": time.strftime("%Y-%m-%d"),
        "machine": f"{platform.node()} {os.cpu_count()} cores", "command": "python benchmarks/bench_ingest.py",
        "load_average_1min_at_end": round(os.getloadavg()[0], 2),
        "data": "bonn-dome2, 1 turntable position, 1 leather, single-LED",
        "raw_gb": round(raw_bytes / 1e9, 3), "ingest_s": [round(s, 2) for s in ingest_s],
        "ingest_mb_per_s": [round(r, 1) for r in ingest_rates],
        "opencv_loop_mb_per_s": [round(rate(*r), 1) for r in loop],
        "opencv_window_loop_mb_per_s": [round(rate(*r), 1) for r in window],
        "median_ingest_mb_per_s": round(ingest_rate, 1), "median_loop_mb_per_s": round(peer_rate, 1),
        "ratio": round(ingest_rate / peer_rate, 2), "ratio_window": round(ingest_rate / window_rate, 2),
        "ratio_first_run": round(ingest_rates[0] / peer_rate, 2),
        "disk_read_mb_per_s": [round(r, 1) for r in disk_read],
        "over_disk_read": round(ingest_rate / max(disk_read), 3),
        "bars": [bar("ingest MB/s / OpenCV loop MB/s (medians)", round(ingest_rate / peer_rate, 2),
                     f">= {OVER_LOOP:g}", ingest_rate / peer_rate >= OVER_LOOP, 21),
                 bar("ingest MB/s / disk read MB/s", round(ingest_rate / max(disk_read), 3),
                     f">= {OVER_DISK_READ:g}", ingest_rate / max(disk_read) >= OVER_DISK_READ, 21)],
    }
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
