"""Renderings of BTF stores: EXR environment maps in, PNG out (tasks.render)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import OpenEXR
import pytest
import zarr

from btfcore.render.btf_render import Camera, DirectionalLight, PointLight
from btfcore.capture.resample import lv_product
from tasks.render import load_env_map, read_btf_store, render_store
from tasks.shared_data import shared_file


def _ring(n: int, theta_deg: float) -> np.ndarray:
    a = 2 * math.pi * np.arange(n) / n
    t = math.radians(theta_deg)
    return np.stack([math.sin(t) * np.cos(a), math.sin(t) * np.sin(a), np.full(n, math.cos(t))], axis=1)


def _store(path, complete: bool = True) -> np.ndarray:
    """A resampled-style BTF store: a textured Lambertian material (albedo texture * cos / pi)."""
    dirs = np.concatenate([[[0.0, 0.0, 1.0]], _ring(6, 30.0), _ring(8, 60.0), _ring(8, 90.0)])
    L, V = lv_product(dirs, dirs)
    albedo = np.random.default_rng(0).uniform(0.2, 0.8, (8, 8, 3))
    B = (L[:, 2, None, None, None] / math.pi * albedo[None]).astype(np.float32)
    group = zarr.open_group(str(path), mode="w", zarr_format=3)
    group.create_array("btf", data=B, chunks=(len(dirs), 8, 8, 3))
    group.create_array("light_dir", data=L)
    group.create_array("view_dir", data=V)
    group.attrs.update({"schema": "btf-texture", "schema_version": "1.0", "complete": complete})
    return albedo


def test_render_store_writes_a_readable_png(tmp_path):
    albedo = _store(tmp_path / "b.zarr")
    out = render_store(tmp_path / "b.zarr", "sphere", light=PointLight(), out_png=tmp_path / "png" / "s.png",
                       image_size=64)
    assert out.image.shape == (64, 64, 3) and out.image.dtype == np.float32 and out.mask.shape == (64, 64)
    assert np.isfinite(out.image).all() and out.image[out.mask].max() > 0 and (out.image[~out.mask] == 0).all()
    back = cv2.imread(str(out.png), cv2.IMREAD_UNCHANGED)
    assert back is not None and back.shape == (64, 64, 3) and back.dtype == np.uint8
    np.testing.assert_array_equal(back[..., ::-1], out.srgb)                   # BGR on disk
    # head-on plane under a frontal directional light: albedo * cos(0) / pi, texture orientation kept
    plane = render_store(tmp_path / "b.zarr", "plane", light=DirectionalLight((0, 0, 1), (1, 1, 1)),
                         tiles=1.0, spatial="nearest", camera=Camera((8, 8), extent=1.0))
    np.testing.assert_allclose(plane.image, albedo / math.pi, rtol=1e-5)


def test_render_store_with_an_environment_array(tmp_path):
    albedo = _store(tmp_path / "b.zarr")
    out = render_store(tmp_path / "b.zarr", "cylinder", env=np.ones((32, 64, 3), np.float32), image_size=32,
                       env_lights_shape=(16, 32))
    # white environment of radiance 1 on a Lambertian BTF: the outgoing radiance is the albedo
    vals = out.image[out.mask]
    assert albedo.min() * 0.97 <= vals.min() and vals.max() <= albedo.max() * 1.03


def test_load_env_map_round_trip_and_clipping(tmp_path):
    env = np.random.default_rng(0).lognormal(0, 2, (16, 32, 3)).astype(np.float32)
    env[3, 4, 1] = -0.5
    path = tmp_path / "e.exr"
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                      {"RGB": env}) as f:
        f.write(str(path))
    got = load_env_map(path)
    expected = np.maximum(env, 0)
    np.testing.assert_array_equal(got, expected)
    with pytest.raises(FileNotFoundError):
        load_env_map(tmp_path / "missing.exr")
    (tmp_path / "bad.exr").write_bytes(b"not an exr")
    with pytest.raises(ValueError, match="not a readable OpenEXR"):
        load_env_map(tmp_path / "bad.exr")


@pytest.mark.shared_data
def test_forest_environment_map(tmp_path):
    path = shared_file("env/forest.exr")
    env = load_env_map(path)
    # MANIFEST.md: lat-long, 512x256 half float
    assert env.shape == (256, 512, 3) and env.dtype == np.float32
    assert np.isfinite(env).all() and env.min() >= 0 and env.max() > 10.0    # HDR: far above display white
    assert (env.mean(axis=(0, 1)) > 0).all()
    _store(tmp_path / "b.zarr")
    out = render_store(tmp_path / "b.zarr", "sphere", env=path, out_png=tmp_path / "forest.png", image_size=48)
    assert np.isfinite(out.image).all() and out.image[out.mask].min() >= 0 and out.image[out.mask].max() > 0
    assert cv2.imread(str(out.png)).shape == (48, 48, 3)


def test_bad_stores_are_refused(tmp_path):
    _store(tmp_path / "b.zarr", complete=False)
    with pytest.raises(ValueError, match="unfinished BTF store"):
        read_btf_store(tmp_path / "b.zarr")
    zarr.open_group(str(tmp_path / "o.zarr"), mode="w", zarr_format=3)
    with pytest.raises(ValueError, match="not a BTF store"):
        render_store(tmp_path / "o.zarr")
    with pytest.raises(FileNotFoundError):
        render_store(tmp_path / "nothing.zarr")
