"""Renderings of BTF stores under point and environment light (stage 12, *evaluate*).

The I/O around :mod:`btfcore.render.btf_render`: reading a BTF store (Zarr) and an
HDR environment map (OpenEXR), writing the tone-mapped rendering as a PNG.
See ``docs/rendering.md``.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from btfcore.render.btf_render import (
    BTFLookup,
    Camera,
    DirectionalLight,
    PointLight,
    env_lights,
    render_btf,
    surface_geometry,
    to_srgb8,
)
from tasks.staging import write_file
from tasks.stores.btf import open_btf_store

__all__ = ["Rendering", "load_env_map", "read_btf_store", "render_store", "write_png"]


@dataclass(frozen=True)
class Rendering:
    """A rendering of a BTF store.

    Attributes
    ----------
    image : (rows, cols, 3) ndarray of float32
        Linear HDR radiance, the store's units times the lights' irradiance.
    mask : (rows, cols) ndarray of bool
        Pixels that see the object.
    srgb : (rows, cols, 3) ndarray of uint8
        Tone-mapped sRGB (:func:`btfcore.render.btf_render.to_srgb8`), RGB order.
    seconds : float
        Wall time of the rendering proper (geometry, look-ups, lights).
    png : Path or None
        Where the PNG was written.
    """

    image: np.ndarray
    mask: np.ndarray
    srgb: np.ndarray
    seconds: float
    png: Path | None


def load_env_map(path: str | os.PathLike) -> np.ndarray:
    """Read a latitude-longitude HDR environment map from an OpenEXR file.

    Parameters
    ----------
    path : str or PathLike
        An EXR file with an ``RGB`` channel group or ``R``, ``G``, ``B``
        channels (half or float).

    Returns
    -------
    env : (H, W, 3) ndarray of float32
        Linear radiance, finite and non-negative: negative values (ringing of
        lossy half-float compression; ``forest.exr`` has a few down to -3.3)
        are clipped to 0.

    Raises
    ------
    FileNotFoundError
        When the file does not exist.
    ValueError
        When it is not a readable EXR, lacks RGB channels or holds NaN/Inf
        (the message names the file and the pixel).
    """
    import OpenEXR

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p} does not exist; give a latitude-longitude HDR map in OpenEXR format")
    try:
        with OpenEXR.File(str(p)) as f:
            channels = {name: np.asarray(ch.pixels) for name, ch in f.channels().items()}
    except Exception as exc:  # OpenEXR raises plain Exception/RuntimeError on bad files
        raise ValueError(f"{p} is not a readable OpenEXR file ({exc}); give a latitude-longitude HDR map in "
                         "OpenEXR format, or forest, sky or studio") from None
    if "RGB" in channels and channels["RGB"].ndim == 3:
        env = channels["RGB"][..., :3]
    elif all(c in channels for c in "RGB"):
        env = np.stack([channels[c] for c in "RGB"], axis=-1)
    else:
        raise ValueError(f"{p} has channels {sorted(channels)}; an environment map needs R, G and B")
    env = env.astype(np.float32)
    finite = np.isfinite(env)
    if not finite.all():
        i = tuple(int(v) for v in np.unravel_index(int(np.argmin(finite)), env.shape))
        raise ValueError(f"{p}: pixel {list(i)} is {float(env[i])!r}; an environment map must be finite")
    return np.maximum(env, 0.0)


def read_btf_store(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Read a finished ``btf-texture`` store (ingested, resampled or reconstructed) into memory
    (:func:`tasks.stores.btf.open_btf_store` checks it first).

    Returns
    -------
    btf : (n_lv, h, w, 3) ndarray of float32
    light_dir, view_dir : (n_lv, 3) ndarray of float64
    attrs : dict
        The store's attributes.

    Raises
    ------
    FileNotFoundError
        When nothing is at ``path``.
    ValueError
        When it is not a finished BTF store, its arrays do not fit together or ``btf``
        holds NaN/Inf (the message names the store and the first index).

    Notes
    -----
    The whole BTF is read: ``n_lv * h * w * 12`` bytes (1.1 GB for a
    UBO2014-sampled 64 x 64 store).
    """
    store = open_btf_store(path, produced_by="`btf ingest` or `btf resample`")
    btf = np.asarray(store.btf[...], dtype=np.float32)
    finite = np.isfinite(btf)
    if not finite.all():
        idx = [int(v) for v in np.argwhere(~finite)[0]]
        raise ValueError(f"{path}: btf{idx} = {float(btf[tuple(idx)])!r} ({int(btf.size - finite.sum())} NaN/Inf "
                         "values); nothing was rendered: write the store again with the command that wrote it "
                         "(`btf export-exr --lv` names the rows)")
    return btf, store.light_dir, store.view_dir, store.attrs


def write_png(path: str | os.PathLike, srgb: np.ndarray) -> Path:
    """Write an RGB ``uint8`` image as PNG (OpenCV, BGR on disk); the folder is created."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    rgb = np.asarray(srgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"srgb must be an (rows, cols, 3) uint8 image, got {rgb.dtype} {rgb.shape}")

    def write(tmp: Path) -> None:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
            raise OSError(f"OpenCV could not write {p}; check the folder and the .png suffix")
    write_file(p, write)                                   # never a half-written image at ``path``
    return p


def _one_blas_thread():
    """Limit BLAS/LAPACK to one thread while rendering.

    The triangulations' barycentric transforms make many tiny LAPACK calls; on
    a machine whose cores are busy, a multi-threaded OpenBLAS turns each into a
    thread wake-up and a 6 s rendering into a minute (measured on 2 cores).
    """
    from threadpoolctl import threadpool_limits

    return threadpool_limits(1, "blas")


def render_store(
    btf_store_path: str | os.PathLike,
    shape: Literal["sphere", "cylinder", "plane"] = "sphere",
    light: PointLight | DirectionalLight | None = None,
    env: str | os.PathLike | np.ndarray | None = None,
    out_png: str | os.PathLike | None = None,
    *,
    image_size: int | tuple[int, int] = 256,
    camera: Camera | None = None,
    tiles: float = 2.0,
    spatial: Literal["bilinear", "nearest"] = "bilinear",
    env_lights_shape: tuple[int, int] = (8, 16),
    env_rotation_deg: float = 0.0,
    env_scale: float = 1.0,
    white: float | None = None,
) -> Rendering:
    """Render a BTF store on a sphere, a cylinder or a plane and optionally write a PNG.

    Parameters
    ----------
    btf_store_path : str or PathLike
        A finished ``btf-texture`` store (``btf ingest`` or ``btf resample``).
    shape : {'sphere', 'cylinder', 'plane'}
    light : PointLight or DirectionalLight, optional
        A light; when neither ``light`` nor ``env`` is given, the default
        :class:`~btfcore.render.btf_render.PointLight` (upper right front,
        irradiance 1 at the origin).
    env : path, (H, W, 3) ndarray or None
        Latitude-longitude HDR map (an EXR file or its array), reduced to
        ``env_lights_shape`` directional lights; summed with ``light``.
    out_png : str or PathLike, optional
        Where to write the tone-mapped rendering.
    image_size : int or (rows, cols)
        Image size of the default orthographic camera.
    camera : Camera, optional
        Overrides ``image_size``.
    tiles : float
        Texture tiles across the object's width (:func:`~btfcore.render.btf_render.surface_geometry`).
    spatial : {'bilinear', 'nearest'}
        Texel look-up.
    env_lights_shape : (n_theta, n_phi)
        Blocks of the environment map, one directional light each.
    env_rotation_deg : float
        Turn the environment about the vertical axis.
    env_scale : float
        Multiplies the environment's radiance.
    white : float, optional
        Radiance mapped to white in the PNG (99.5th percentile when omitted).

    Returns
    -------
    rendering : Rendering
    """
    btf, light_dir, view_dir, _ = read_btf_store(btf_store_path)
    env_map = None
    if env is not None:
        env_map = load_env_map(env) if isinstance(env, (str, os.PathLike)) else np.asarray(env, np.float32)
    if camera is None:
        size = (int(image_size), int(image_size)) if np.ndim(image_size) == 0 else tuple(image_size)
        camera = Camera(size)
    lights: list = [] if light is None else [light]
    start = time.perf_counter()
    with _one_blas_thread():
        if env_map is not None:
            lights.append(env_lights(env_map * float(env_scale), *env_lights_shape, rotation_deg=env_rotation_deg))
        if not lights:
            lights.append(PointLight())
        lookup = BTFLookup(btf, light_dir, view_dir, spatial=spatial)
        geometry = surface_geometry(shape, camera, tiles=tiles, texture_shape=btf.shape[1:3])
        image = render_btf(lookup, geometry, lights)
    seconds = time.perf_counter() - start
    srgb = to_srgb8(image, geometry.mask, white=white)
    png = write_png(out_png, srgb) if out_png is not None else None
    return Rendering(image, geometry.mask, srgb, seconds, png)
