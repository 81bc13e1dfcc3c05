"""Texture photographs the virtual dome draws its materials from."""

from __future__ import annotations

import numpy as np
import pytest

from tasks.shared_data import shared_data_dir
from tasks.textures import load_texture_sources


def test_grey_sources_come_from_scikit_image(monkeypatch, tmp_path):
    monkeypatch.setenv("BTF_SHARED_DATA", str(tmp_path))  # a folder without MANIFEST.md
    assert shared_data_dir() is None
    sources = load_texture_sources()
    assert sorted(sources) == ["brick", "grass", "gravel"]
    for image in sources.values():
        assert image.dtype == np.uint8 and image.shape == (512, 512) and image.std() > 10


@pytest.mark.shared_data
def test_colour_photographs_come_from_the_shared_folder():
    sources = load_texture_sources()
    for name in ("bricks_rgb", "wood_rgb"):
        image = sources[name]
        assert image.dtype == np.uint8 and image.shape == (512, 512, 3)
        # RGB order (OpenCV reads BGR): the wood photograph is redder than it is blue
    assert sources["wood_rgb"][..., 0].mean() > sources["wood_rgb"][..., 2].mean()


def test_a_corrupt_photograph_is_named(monkeypatch, tmp_path):
    (tmp_path / "MANIFEST.md").write_text("test\n")
    (tmp_path / "textures").mkdir()
    (tmp_path / "textures" / "wood.jpg").write_bytes(b"not a jpeg")
    monkeypatch.setenv("BTF_SHARED_DATA", str(tmp_path))
    with pytest.raises(ValueError, match=r"wood\.jpg: OpenCV could not decode"):
        load_texture_sources()
