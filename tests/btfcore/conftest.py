"""Fixtures of the btfcore tests: seeded synthetic stand-ins for texture photographs."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage


def _grey(rng: np.random.Generator, sigma: float, n: int = 256) -> np.ndarray:
    x = ndimage.gaussian_filter(rng.standard_normal((n, n)), sigma, mode="wrap")
    x = (x - x.min()) / (x.max() - x.min())
    return np.round(x * 255).astype(np.uint8)


@pytest.fixture(scope="session")
def sources() -> dict[str, np.ndarray]:
    """Seeded synthetic stand-ins for the texture photographs, keyed like SOURCE_NAMES."""
    rng = np.random.default_rng(1234)
    out = {"brick": _grey(rng, 4.0), "grass": _grey(rng, 1.2), "gravel": _grey(rng, 2.5)}
    out["bricks_rgb"] = np.stack([_grey(rng, 3.0) for _ in range(3)], axis=-1)
    out["wood_rgb"] = np.stack([_grey(rng, 2.0) for _ in range(3)], axis=-1)
    return out
