"""Benchmark: super-resolution inference and training against the machine's float32 GEMM rate (issue 17).

Measured in one run, each figure beside the GEMM rate at the same torch thread count:

* **inference**: :func:`btfcore.superres.espcn.upscale` of ``--images`` regions of
  ``--size`` x ``--size`` pixels (one channel each) with the paper's network (SR
  paper §4); FLOPs = :func:`btfcore.superres.espcn.conv_flops` (2 x the
  multiply-adds of the four convolutions per low-resolution pixel); at 1 thread
  (a Dask worker's) and at torch's default threads; ``over_gemm`` = conv GFLOP/s /
  GEMM GFLOP/s (the bar: >= 0.5);
* **training**: :func:`btfcore.superres.training.train_espcn` on ``--patches`` random
  17 x 17 / 34 x 34 pairs for two epochs: patch pairs per second;
* **thesis-scale projection**: a BTF of 26,136 regions of 200 x 200 pixels x 3
  channels (SR paper §5.1) through the network at the measured 2-thread rate, and
  the rectification of the up-sampled 400 x 400 regions at twice the texture
  (256 x 256) from a timed batch (:func:`btfcore.superres.regions.rectify_regions`),
  against the paper's 32 minutes (2 of them the network, 30 the resampling, GTX 980).

With a CUDA device the inference is also timed there (``cuda``), and the GEMM on it.

Bar (issue 17): inference ``over_gemm`` >= 0.5 at every CPU thread count (``"bars"``).

Usage: ``python benchmarks/bench_superres.py [--quick] [--images 16] [--size 144] [--patches 2048]``;
``--quick``: 4 regions of 64 x 64, 256 patches.
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

THESIS_REGIONS = 26_136
THESIS_REGION_PX = 200
THESIS_TEXTURE = 128
PAPER_MINUTES = {"network": 2.0, "resampling": 30.0, "total": 32.0}


def inference_rate(images: np.ndarray, device: str = "cpu") -> tuple[float, float]:
    """(seconds, conv GFLOP/s) of ``upscale`` on ``images`` (best of 3)."""
    from btfcore.superres.espcn import Espcn, EspcnConfig, conv_flops, upscale

    config = EspcnConfig()
    model = Espcn(config).eval().to(device)
    seconds = best_seconds(lambda: upscale(model, images, device=device), 3)
    flops = conv_flops(config, int(np.prod(images.shape[1:]))) * len(images)
    return seconds, flops / seconds / 1e9


def network_rate(images: np.ndarray, device: str) -> float:
    """Conv GFLOP/s of the network alone (eval mode, no normalisation, no host transfer) on ``images``
    already on ``device``, best of 3: what ``upscale`` would reach if its host-side work were free."""
    import torch

    from btfcore.superres.espcn import Espcn, EspcnConfig, conv_flops

    config = EspcnConfig()
    model = Espcn(config).eval().to(device)
    x = torch.from_numpy(images).to(device)[:, None]

    def forward() -> None:
        with torch.no_grad():
            model(x)
        torch.cuda.synchronize()
    forward()
    return conv_flops(config, int(np.prod(images.shape[1:]))) * len(images) / best_seconds(forward, 3) / 1e9


def training_rate(n: int) -> float:
    from btfcore.superres.espcn import EspcnConfig
    from btfcore.superres.training import TrainingSettings, train_espcn

    rng = np.random.default_rng(0)
    high = rng.random((n, 34, 34), dtype=np.float32)
    low = high.reshape(n, 17, 2, 17, 2).mean(axis=(2, 4))
    result = train_espcn(low, high, EspcnConfig(normalisation="scale"), TrainingSettings(max_epochs=2, patience=5))
    return float(result.samples_per_second)


def rectification_seconds_per_region() -> float:
    """Seconds to rectify one 400 x 400 up-sampled region at a 256 x 256 texture (a batch of 16, best of 3)."""
    from btfcore.dome import get_device
    from btfcore.superres.regions import rectify_regions, scale_homography

    dev = get_device("bonn-dome2")
    H = scale_homography(dev.homography(0, 5), 2)
    rows, cols = (2 * v for v in dev.roi_shape)
    regions = np.random.default_rng(0).random((16, rows, cols, 3), dtype=np.float32)
    s = best_seconds(lambda: rectify_regions(regions, H, (2 * THESIS_TEXTURE, 2 * THESIS_TEXTURE),
                                             dev.sample_size_m), 3)
    return s / 16


def main() -> None:
    import torch

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--images", type=int, default=16)
    p.add_argument("--size", type=int, default=144)
    p.add_argument("--patches", type=int, default=2048)
    p.add_argument("--quick", action="store_true", help="4 regions of 64 x 64, 256 patches")
    a = p.parse_args()
    if a.quick:
        a.images, a.size, a.patches = 4, 64, 256
    images = np.random.default_rng(1).random((a.images, a.size, a.size), dtype=np.float32) + 0.1
    default_threads = torch.get_num_threads()
    result = {"benchmark": "superres", "machine": platform.node(), "cpus": os.cpu_count(),
              "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "images": a.images, "size": a.size,
              "inference": {}}
    for threads in sorted({1, default_threads}):
        torch.set_num_threads(threads)
        gemm_before = torch_gemm_rate()
        seconds, rate = inference_rate(images)
        gemm_after = torch_gemm_rate()
        gemm = max(gemm_before, gemm_after)
        result["inference"][f"cpu_{threads}_threads"] = {
            "seconds": round(seconds, 4), "conv_gflop_per_s": round(rate, 1), "gemm_gflop_per_s": round(gemm, 1),
            "over_gemm": round(rate / gemm, 3)}
        result.setdefault("bars", []).append(bar(f"ESPCN inference GFLOP/s / torch GEMM GFLOP/s, {threads} thread(s)",
                                                 round(rate / gemm, 3), ">= 0.5", rate / gemm >= 0.5, 17))
        log(f"inference, {threads} thread(s): {rate:.1f} GFLOP/s = {rate / gemm:.2f} of GEMM {gemm:.1f}")
    torch.set_num_threads(default_threads)
    if torch.cuda.is_available():
        big = np.concatenate([images] * max(1, 256 // len(images)))       # enough pixels to fill a GPU
        seconds, rate = inference_rate(big, "cuda")
        network = network_rate(big, "cuda")
        g = torch_gemm_rate(4096, device="cuda")
        result["inference"]["cuda"] = {
            "images": len(big), "seconds": round(seconds, 4), "conv_gflop_per_s": round(rate, 1),
            "network_only_conv_gflop_per_s": round(network, 1), "gemm_gflop_per_s": round(g, 1),
            "over_gemm": round(rate / g, 3), "network_only_over_gemm": round(network / g, 3),
            "cudnn_tf32": bool(torch.backends.cudnn.allow_tf32), "matmul_tf32": bool(torch.backends.cuda.matmul.allow_tf32),
            "device": torch.cuda.get_device_name(0)}
        log(f"cuda: upscale {rate:.0f} GFLOP/s, the network alone {network:.0f} GFLOP/s, GEMM {g:.0f}")
    result["training_patch_pairs_per_s"] = round(training_rate(a.patches), 1)
    log(f"training: {result['training_patch_pairs_per_s']} patch pairs/s")
    from btfcore.superres.espcn import EspcnConfig, conv_flops

    cpu = result["inference"][f"cpu_{default_threads}_threads"]["conv_gflop_per_s"]
    network_s = conv_flops(EspcnConfig(), THESIS_REGION_PX**2) * 3 * THESIS_REGIONS / (cpu * 1e9)
    rect_s = rectification_seconds_per_region() * THESIS_REGIONS
    result["thesis_projection_minutes"] = {"network": round(network_s / 60, 1), "rectification": round(rect_s / 60, 1),
                                           "total": round((network_s + rect_s) / 60, 1), "paper": PAPER_MINUTES}
    log(f"thesis scale: network {network_s / 60:.1f} min + rectification {rect_s / 60:.1f} min (paper: 2 + 30)")
    json.dump(result, sys.stdout, indent=2)
    print()


if __name__ == "__main__":
    main()
