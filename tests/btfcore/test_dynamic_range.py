"""Every material class spans at least 1e3 in radiance on the tiny dome (issue 2 bar)."""

from __future__ import annotations

import numpy as np
import pytest

from btfcore.dome import get_device
from btfcore.simulate.materials import MATERIAL_CLASSES, make_material
from btfcore.simulate.render import downsample2, horizon_map, render_view

LUMA = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)


@pytest.fixture(scope="module")
def photos():
    from tasks.textures import load_texture_sources

    return load_texture_sources()


@pytest.mark.parametrize("class_name", MATERIAL_CLASSES)
def test_every_class_is_high_dynamic_range_on_tiny(class_name, photos):
    device = get_device("tiny")
    h, w = device.texture_shape
    for seed in range(3):
        maps = make_material(class_name, seed, (2 * h, 2 * w), photos)
        horizon = horizon_map(maps.height)
        lum = np.concatenate([
            (downsample2(render_view(maps, device.view_dir(t, c), device.light_dirs(t), horizon)) @ LUMA).ravel()
            for t in range(device.n_turn) for c in range(device.n_cam)
        ])
        assert np.isfinite(lum).all() and lum.min() > 0, "shadows keep a little indirect light"
        assert lum.max() / lum.min() >= 1e3, (class_name, seed, lum.max() / lum.min())
