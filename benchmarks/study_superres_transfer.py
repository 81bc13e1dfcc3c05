"""Issue 17 study (not a speed benchmark): does the ESPCN transfer across scales?

The SR paper's protocol trains on twice down-sampled images (1/4 -> 1/2) and applies the
network one scale up (1/2 -> 1). On the simulated BTFs the ESPCN lost to bicubic there
(docs/super-resolution.md). This study separates the two things that could cause it, on
single-channel images with no capture noise at all:

* ``same``: trained 1/4 -> 1/2 and applied 1/4 -> 1/2 to held-out images (no change of scale);
* ``paper``: the same network applied 1/2 -> 1 (the paper's protocol).

Images: the three texture photographs scikit-image ships (gravel, grass, brick; 512 x 512,
trained on their top 256-pixel quarters with the 8 rotations and flips, scored on the bottom
quarters) and the simulator's leather and cloth maps (albedo luminance times a shading of the
height map's slope), drawn at 192 and 384 pixels (train seeds 0..n-1, test seeds 100..103).
PSNR per image with the reference's maximum as the peak, averaged. One torch thread; about 5
minutes on 2 cores.

``--residual``: the network learns the residual to bicubic up-sampling instead (its output is added
to the bicubic image; not the paper's architecture), to see whether a global bicubic skip keeps the
network's lead across the change of scale.

    .venv/bin/python benchmarks/study_superres_transfer.py [--residual]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import skimage.data as sd
import torch

from btfcore.simulate.materials import make_material
from btfcore.superres.espcn import EspcnConfig, load_espcn, upscale
from btfcore.superres.scaling import area_downsample, bicubic_upsample
from btfcore.superres.training import TrainingSettings, patch_pairs, train_espcn

SOURCES = ("gravel", "grass", "brick")


def psnr(x: np.ndarray, ref: np.ndarray) -> float:
    return float(10 * np.log10(ref.max() ** 2 / np.mean((x - ref) ** 2)))


def aug8(images: list[np.ndarray]) -> np.ndarray:
    """The 8 rotations and flips of each square image."""
    out = []
    for im in images:
        for k in range(4):
            r = np.rot90(im, k)
            out += [r, r[:, ::-1]]
    return np.ascontiguousarray(np.stack(out))


def study(train: np.ndarray, tests: dict[str, np.ndarray], epochs: int = 40, residual: bool = False) -> dict:
    """Train 1/4 -> 1/2 on ``train`` (1x images), score both protocols on each test set.

    ``residual``: train on ``half - bicubic(quarter)`` and add the bicubic image back (a global skip;
    'scale' normalisation is linear, so the residual is normalised with the LR image's scale)."""
    config = EspcnConfig()
    half = area_downsample(train, 2)
    quarter = area_downsample(half, 2)
    target = half[:, :2 * quarter.shape[1], :2 * quarter.shape[2]] - bicubic_upsample(quarter, 2) if residual else half
    low, high = patch_pairs(quarter, target, normalisation=config.normalisation)
    t0 = time.perf_counter()
    result = train_espcn(low, high, config, TrainingSettings(max_epochs=epochs, seed=0))
    model = load_espcn(result.state, config)

    def network(x: np.ndarray) -> np.ndarray:
        return bicubic_upsample(x, 2) + upscale(model, x) if residual else upscale(model, x)

    out = {"pairs": int(len(low)), "train_s": round(time.perf_counter() - t0, 1)}
    for name, full in tests.items():
        half = area_downsample(full, 2)
        quarter = area_downsample(half, 2)
        scores = {
            "same_espcn": np.mean([psnr(a, b) for a, b in zip(network(quarter), half)]),
            "same_bicubic": np.mean([psnr(a, b) for a, b in zip(bicubic_upsample(quarter, 2), half)]),
            "paper_espcn": np.mean([psnr(a, b) for a, b in zip(network(half), full)]),
            "paper_bicubic": np.mean([psnr(a, b) for a, b in zip(bicubic_upsample(half, 2), full)]),
        }
        out[name] = {k: round(float(v), 2) for k, v in scores.items()}
    return out


def shaded(cls: str, seeds: range, size: int) -> np.ndarray:
    """Albedo luminance times a grazing-light shading of the height map, per material seed."""
    sources = {n: getattr(sd, n)() for n in SOURCES}
    images = []
    for seed in seeds:
        m = make_material(cls, seed, (size, size), sources)
        _, gx = np.gradient(m.height.astype(np.float64))
        images.append((m.albedo.mean(axis=2) * np.clip(0.7 - 0.6 * gx, 0.05, None)).astype(np.float32))
    return np.stack(images)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--residual", action="store_true", help="learn the residual to bicubic (a global skip)")
    residual = parser.parse_args().residual
    torch.set_num_threads(1)
    photos = {n: getattr(sd, n)().astype(np.float32) / 255.0 + 0.02 for n in SOURCES}
    results = {"photographs": study(aug8([q for im in photos.values() for q in (im[:256, :256], im[:256, 256:])]),
                                    {n: np.stack([im[256:, :256], im[256:, 256:]]) for n, im in photos.items()},
                                    residual=residual)}
    for cls in ("leather", "cloth"):
        for size, n in ((192, 48), (384, 16)):
            results[f"{cls} {size}"] = study(shaded(cls, range(n), size), {"test": shaded(cls, range(100, 104), size)},
                                                residual=residual)
    print(json.dumps(results, indent=1))
    print(f"{'images':<22}{'same: ESPCN':>12}{'bicubic':>9}{'paper: ESPCN':>14}{'bicubic':>9}")
    for group, res in results.items():
        for name, s in res.items():
            if isinstance(s, dict):
                label = group if name == "test" else f"{group}: {name}"
                print(f"{label:<22}{s['same_espcn']:>12.2f}{s['same_bicubic']:>9.2f}"
                      f"{s['paper_espcn']:>14.2f}{s['paper_bicubic']:>9.2f}")


if __name__ == "__main__":
    main()
