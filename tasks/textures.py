"""Texture photographs that the virtual dome's materials are drawn from.

``skimage.data`` ships ``brick``, ``grass`` and ``gravel`` (CC0) inside its wheel;
the colour photographs ``bricks.jpg`` and ``wood.jpg`` come from the shared data
folder when it is present (see ``docs/simulator.md`` for the fallback).
"""

from __future__ import annotations

import cv2
import numpy as np
import skimage.data

from tasks.shared_data import shared_file

#: Colour photographs in ``../shared/data/textures`` and their source names.
SHARED_TEXTURES = {"bricks_rgb": "textures/bricks.jpg", "wood_rgb": "textures/wood.jpg"}


def load_texture_sources() -> dict[str, np.ndarray]:
    """Load every available source photograph as a uint8 array.

    Returns
    -------
    sources : dict of str to ndarray
        ``brick``, ``grass``, ``gravel``: (512, 512) uint8 grey; ``bricks_rgb``,
        ``wood_rgb``: (512, 512, 3) uint8 RGB, only when the shared folder has them.
    """
    sources: dict[str, np.ndarray] = {
        "brick": np.ascontiguousarray(skimage.data.brick()),
        "grass": np.ascontiguousarray(skimage.data.grass()),
        "gravel": np.ascontiguousarray(skimage.data.gravel()),
    }
    for name, relative in SHARED_TEXTURES.items():
        path = shared_file(relative)
        if path is None:
            continue
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"{path}: OpenCV could not decode this texture photograph; restore the file")
        sources[name] = np.ascontiguousarray(bgr[:, :, ::-1])
    return sources
