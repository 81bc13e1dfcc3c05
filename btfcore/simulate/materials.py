"""Procedural material samples for the virtual dome.

Each material is a set of co-registered maps over the square sample: a
height field, a diffuse RGB albedo, a GGX roughness, a specular weight and a
Fresnel reflectance at normal incidence.  The maps are drawn per seed from
real texture photographs (passed in as arrays; this module reads no files) by
random crops, quarter-turn rotations, flips and contrast curves, combined
with simple procedural structure (weaves, brush strokes, scratches).

Conventions (shared with :mod:`btfcore.simulate.render`):

* a map of ``H`` rows x ``W`` columns covers the square sample; pixel
  ``(i, j)`` is centred at ``x = (j + 0.5) / W - 0.5``,
  ``y = 0.5 - (i + 0.5) / H`` in units of the sample side;
* heights are in units of the *column pitch* ``side / W`` (the pixel pitch of
  a square map), are ``>= 0`` with minimum 0; the renderer places the
  reference plane at the mean height;
* physical sizes (thread period, relief amplitude) are drawn in units of the
  sample side and converted to pixels, so a material rendered at 2x the
  resolution has the same geometry.

See ``docs/simulator-physics.md`` for the physical model.
"""

from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np
from scipy import ndimage
from skimage.transform import resize

from btfcore.model.colour import luminance

__all__ = [
    "MATERIAL_CLASSES",
    "SOURCE_NAMES",
    "MaterialMaps",
    "make_material",
    "white_standard",
    "flat_material",
]

MATERIAL_CLASSES: tuple[str, ...] = ("leather", "cloth", "wood", "metal", "stone", "carpet")

SOURCE_NAMES: tuple[str, ...] = ("brick", "grass", "gravel", "bricks_rgb", "wood_rgb")
"""Names of the texture photographs :func:`make_material` draws from.

``brick``, ``grass``, ``gravel``: greyscale ``(512, 512)`` uint8 photographs
(``skimage.data``); ``bricks_rgb``, ``wood_rgb``: ``(512, 512, 3)`` uint8
colour photographs.  The two colour ones are optional.
"""

_GREY_SOURCES = ("brick", "grass", "gravel")
_NOISE_GRID = 512  # resolution of procedural noise before resizing to the map
_RGB_SOURCES = ("bricks_rgb", "wood_rgb")

#: Fresnel reflectance at normal incidence of common dielectrics (n ~ 1.5).
DIELECTRIC_F0 = 0.04

#: Normal-incidence reflectance (linear sRGB) of metals, after the
#: measured-data tables commonly used in physically based rendering.
METAL_F0: dict[str, tuple[float, float, float]] = {
    "silver": (0.97, 0.96, 0.91),
    "aluminium": (0.91, 0.92, 0.92),
    "gold": (1.00, 0.78, 0.34),
    "copper": (0.95, 0.64, 0.54),
    "brass": (0.91, 0.78, 0.42),
    "iron": (0.56, 0.57, 0.58),
    "titanium": (0.54, 0.50, 0.45),
    "chromium": (0.55, 0.56, 0.55),
}

_LEATHER_COLOURS = {
    "brown": (0.30, 0.17, 0.09),
    "tan": (0.55, 0.37, 0.21),
    "black": (0.06, 0.055, 0.05),
    "burgundy": (0.30, 0.07, 0.07),
    "beige": (0.62, 0.52, 0.40),
    "olive": (0.28, 0.26, 0.14),
}

_WOOD_TONES = {  # (dark, light) linear RGB
    "oak": ((0.25, 0.15, 0.07), (0.62, 0.45, 0.26)),
    "walnut": ((0.09, 0.05, 0.03), (0.32, 0.20, 0.11)),
    "pine": ((0.45, 0.30, 0.15), (0.80, 0.64, 0.42)),
    "cherry": ((0.22, 0.08, 0.04), (0.55, 0.27, 0.14)),
}

_STONE_TONES = {  # (dark, light) linear RGB
    "granite": ((0.07, 0.07, 0.07), (0.55, 0.54, 0.52)),
    "sandstone": ((0.16, 0.11, 0.07), (0.70, 0.58, 0.42)),
    "brick": ((0.15, 0.05, 0.03), (0.55, 0.25, 0.15)),
    "slate": ((0.04, 0.045, 0.05), (0.25, 0.27, 0.30)),
    "limestone": ((0.22, 0.21, 0.18), (0.80, 0.78, 0.70)),
}


@dataclass(frozen=True, eq=False)
class MaterialMaps:
    """Spatially varying surface description of one material sample.

    Parameters
    ----------
    class_name : str
        Material class (one of :data:`MATERIAL_CLASSES`, or ``"white_standard"``
        / ``"flat"`` for the calibration and test targets).
    height : (H, W) ndarray of float32
        Height field in units of the column pitch ``side / W``, ``>= 0``.
    albedo : (H, W, 3) ndarray of float32
        Diffuse (Lambertian) RGB albedo in ``[0, 1]``.
    roughness : (H, W) ndarray of float32
        GGX (Trowbridge-Reitz) ``alpha`` in ``(0, 1]``.
    specular : (H, W) ndarray of float32
        Weight ``>= 0`` of the specular lobe.
    f0 : (3,) ndarray of float32
        Fresnel reflectance at normal incidence, in ``[0, 1]``.
    params : dict
        Plain-JSON record (Python ``str``/``int``/``float``/``bool``/lists
        and dicts thereof) of every random draw that made the maps.
    """

    class_name: str
    height: np.ndarray
    albedo: np.ndarray
    roughness: np.ndarray
    specular: np.ndarray
    f0: np.ndarray
    params: dict

    def __post_init__(self) -> None:
        h = self.height
        if h.ndim != 2 or min(h.shape) < 2:
            raise ValueError(f"height must be (H, W) with H, W >= 2, got shape {h.shape}")
        shape = h.shape
        checks = (
            ("height", h, shape),
            ("albedo", self.albedo, shape + (3,)),
            ("roughness", self.roughness, shape),
            ("specular", self.specular, shape),
            ("f0", self.f0, (3,)),
        )
        for name, arr, want in checks:
            if arr.shape != want:
                raise ValueError(f"{name} must have shape {want}, got {arr.shape}")
            if arr.dtype != np.float32:
                raise ValueError(f"{name} must be float32, got {arr.dtype}")
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name} contains NaN or Inf")
        if h.min() < 0:
            raise ValueError("height must be >= 0")
        if self.albedo.min() < 0 or self.albedo.max() > 1:
            raise ValueError("albedo must lie in [0, 1]")
        if self.roughness.min() <= 0 or self.roughness.max() > 1:
            raise ValueError("roughness (GGX alpha) must lie in (0, 1]")
        if self.specular.min() < 0:
            raise ValueError("specular weight must be >= 0")
        if self.f0.min() < 0 or self.f0.max() > 1:
            raise ValueError("f0 must lie in [0, 1]")

    @property
    def shape(self) -> tuple[int, int]:
        """Map grid ``(H, W)``."""
        return self.height.shape  # type: ignore[return-value]


# ---------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------


def _check_shape(shape) -> tuple[int, int]:
    try:
        H, W = (int(s) for s in shape)
    except Exception as exc:  # pragma: no cover - message path
        raise ValueError(f"shape must be (H, W), got {shape!r}") from exc
    if H < 2 or W < 2:
        raise ValueError(f"shape must be at least (2, 2), got {(H, W)}")
    return H, W


def _to_unit(img: np.ndarray) -> np.ndarray:
    """Image to float64 in [0, 1] (integer dtypes by their range)."""
    arr = np.asarray(img)
    if np.issubdtype(arr.dtype, np.integer):
        out = arr.astype(np.float64) / float(np.iinfo(arr.dtype).max)
    else:
        out = np.clip(arr.astype(np.float64), 0.0, 1.0)
    if not np.all(np.isfinite(out)):
        raise ValueError("texture source contains NaN or Inf")
    return out


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """Decode sRGB-encoded values in [0, 1] to linear reflectance (IEC 61966-2-1)."""
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)  # eq. sRGB EOTF


def _get_source(sources: Mapping[str, np.ndarray], name: str) -> np.ndarray:
    if name not in sources:
        raise KeyError(
            f"texture source {name!r} missing; pass sources with keys {_GREY_SOURCES} "
            f"(greyscale arrays, e.g. skimage.data.{name}()) and optionally {_RGB_SOURCES}"
        )
    arr = np.asarray(sources[name])
    want_rgb = name in _RGB_SOURCES
    if want_rgb and (arr.ndim != 3 or arr.shape[2] != 3):
        raise ValueError(f"source {name!r} must be (h, w, 3), got shape {arr.shape}")
    if not want_rgb and arr.ndim != 2:
        raise ValueError(f"source {name!r} must be a greyscale (h, w) array, got shape {arr.shape}")
    if min(arr.shape[:2]) < 16:
        raise ValueError(f"source {name!r} is too small ({arr.shape[:2]}); need at least 16x16")
    return arr


def _crop(
    rng: np.random.Generator,
    img: np.ndarray,
    shape: tuple[int, int],
    frac: tuple[float, float],
    aspect: float = 1.0,
) -> tuple[np.ndarray, dict]:
    """Random crop, quarter turn and flip of a source, area-resized to ``shape``.

    ``frac`` bounds the crop height as a fraction of the source's shorter side;
    ``aspect`` is the crop's width / height before rotation (values < 1
    stretch features across the columns once resized to a square).
    """
    src = _to_unit(img)
    h, w = src.shape[:2]
    f = float(rng.uniform(*frac))
    ch = int(np.clip(round(f * min(h, w)), 8, h))
    cw = int(np.clip(round(ch * aspect), 4, w))
    r0 = int(rng.integers(0, h - ch + 1))
    c0 = int(rng.integers(0, w - cw + 1))
    k = int(rng.integers(0, 4))
    flip = bool(rng.integers(0, 2))
    patch = src[r0 : r0 + ch, c0 : c0 + cw]
    patch = np.rot90(patch, k, axes=(0, 1))
    if flip:
        patch = patch[:, ::-1]
    out_shape = tuple(shape) + patch.shape[2:]
    # anti-aliased (area-like) resampling: Gaussian prefilter then linear
    out = resize(patch, out_shape, order=1, mode="reflect", anti_aliasing=True, preserve_range=True)
    info = {"row": r0, "col": c0, "height": ch, "width": cw, "rot90": k, "flip": flip}
    return out, info


def _contrast(rng: np.random.Generator, x: np.ndarray, gamma: tuple[float, float]) -> tuple[np.ndarray, float]:
    """Robust normalisation to [0, 1] then a random gamma curve."""
    lo, hi = np.percentile(x, [1.0, 99.0])
    y = np.clip((x - lo) / max(hi - lo, 1e-6), 0.0, 1.0)
    g = float(np.exp(rng.uniform(np.log(gamma[0]), np.log(gamma[1]))))
    return y**g, g


def _jitter(rng: np.random.Generator, rgb, scale: float) -> list[float]:
    c = np.asarray(rgb, dtype=np.float64) * np.exp(rng.normal(0.0, scale, 3))
    return [float(v) for v in np.clip(c, 0.0, 1.0)]


def _hsv(rng: np.random.Generator, s: tuple[float, float], v: tuple[float, float]) -> list[float]:
    hue = float(rng.uniform(0.0, 1.0))
    sat = float(rng.uniform(*s))
    val = float(rng.uniform(*v))
    return [float(c) for c in colorsys.hsv_to_rgb(hue, sat, val)]


def _normalise(x: np.ndarray) -> np.ndarray:
    x = x - x.min()
    m = x.max()
    return x / m if m > 0 else x


def _finish(
    class_name: str,
    height: np.ndarray,
    albedo: np.ndarray,
    roughness: np.ndarray,
    specular: np.ndarray,
    f0,
    params: dict,
) -> MaterialMaps:
    height = np.asarray(height, dtype=np.float64)
    height = height - height.min()
    return MaterialMaps(
        class_name=class_name,
        height=height.astype(np.float32),
        albedo=np.clip(albedo, 0.0, 1.0).astype(np.float32),
        roughness=np.clip(roughness, 0.02, 1.0).astype(np.float32),
        specular=np.maximum(specular, 0.0).astype(np.float32),
        f0=np.clip(np.asarray(f0, dtype=np.float64), 0.0, 1.0).astype(np.float32),
        params=params,
    )


def _pixel_xy(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Sample-frame coordinates (units of the side) of the pixel centres."""
    H, W = shape
    x = (np.arange(W) + 0.5) / W - 0.5
    y = 0.5 - (np.arange(H) + 0.5) / H
    return np.broadcast_to(x[None, :], shape), np.broadcast_to(y[:, None], shape)


# ---------------------------------------------------------------------------
# material classes
# ---------------------------------------------------------------------------


def _leather(rng, shape, sources, params):
    H, W = shape
    src = str(rng.choice(["gravel", "grass"]))
    grain, crop = _crop(rng, _get_source(sources, src), shape, (0.2, 0.5))
    sigma = float(rng.uniform(0.002, 0.004))  # rounding of the pebbles, side units
    grain = ndimage.gaussian_filter(grain, sigma * W, mode="reflect")
    grain, gamma = _contrast(rng, grain, (0.6, 1.0))  # gamma < 1: rounded tops, narrow creases
    amp = float(rng.uniform(0.004, 0.012))  # relief, side units
    height = grain * amp * W

    tone, _crop2 = _crop(rng, _get_source(sources, "grass"), shape, (0.5, 1.0))
    tone, _ = _contrast(rng, tone, (1.0, 1.0))
    name = str(rng.choice(sorted(_LEATHER_COLOURS)))
    base = _jitter(rng, _LEATHER_COLOURS[name], 0.15)
    mod = (0.65 + 0.5 * grain) * (0.9 + 0.2 * (tone - 0.5))  # creases darker
    albedo = np.asarray(base)[None, None, :] * mod[..., None]

    rough0 = float(rng.uniform(0.1, 0.25))  # finished (top-coated) leather has a sheen
    roughness = rough0 * (0.85 + 0.3 * (1.0 - grain))  # creases rougher
    spec0 = float(rng.uniform(0.5, 1.0))
    specular = spec0 * (0.6 + 0.8 * grain)  # worn tops glossier
    params.update(
        source=src, crop=crop, tone_source="grass", tone_crop=_crop2, smoothing_side=sigma,
        gamma=gamma, amplitude_side=amp, colour_name=name, colour=base,
        roughness_base=rough0, specular_base=spec0,
    )
    return height, albedo, roughness, specular, [DIELECTRIC_F0] * 3


def _block_mean(x: np.ndarray, f: int) -> np.ndarray:
    """Exact f x f box mean (area average of a supersampled field)."""
    if f == 1:
        return x
    H, W = x.shape[0] // f, x.shape[1] // f
    return x.reshape(H, f, W, f).mean(axis=(1, 3))


def _cloth(rng, shape, sources, params):
    H, W = shape
    n = int(rng.integers(10, 24))  # threads across the side (coarse weaves: canvas, tweed)
    pu, pv = (float(v) for v in rng.uniform(0.0, 1.0, 2))
    width = float(rng.uniform(0.65, 0.95))  # thread width / period
    lift = float(rng.uniform(0.3, 0.8))  # undulation / thread thickness
    thick_side = float(rng.uniform(0.45, 0.8)) / n  # thread thickness, side units
    # evaluate the weave with >= 8 samples per thread and area-average it, so
    # that maps at different resolutions describe the same (unaliased) cloth
    ss = int(np.clip(math.ceil(8.0 * n / min(H, W)), 1, 8))
    x, y = _pixel_xy((H * ss, W * ss))
    u = x * n + pu
    v = y * n + pv
    a = np.floor(u)
    b = np.floor(v)
    fu = u - a
    fv = v - b
    # circular thread cross-sections, plain weave over/under undulation
    p_warp = np.sqrt(np.clip(1.0 - ((fu - 0.5) / (0.5 * width)) ** 2, 0.0, 1.0))
    p_weft = np.sqrt(np.clip(1.0 - ((fv - 0.5) / (0.5 * width)) ** 2, 0.0, 1.0))
    e_warp = 0.5 + 0.5 * np.cos(np.pi * (v - 0.5 + a))
    e_weft = 0.5 - 0.5 * np.cos(np.pi * (u - 0.5 + b))
    h_warp = np.where(p_warp > 0, p_warp + lift * e_warp, 0.0)
    h_weft = np.where(p_weft > 0, p_weft + lift * e_weft, 0.0)
    weave = _block_mean(np.maximum(h_warp, h_weft), ss)
    warp_top = _block_mean((h_warp >= h_weft).astype(np.float64), ss)
    gap = _block_mean(((p_warp <= 0) & (p_weft <= 0)).astype(np.float64), ss)

    fibre, crop = _crop(rng, _get_source(sources, "grass"), shape, (0.3, 0.8))
    fibre, gamma = _contrast(rng, fibre, (0.8, 1.25))
    fuzz = float(rng.uniform(0.05, 0.2))
    height = (weave + fuzz * (fibre - 0.5) * (1.0 - gap)) * thick_side * W

    c_warp = _hsv(rng, (0.2, 0.9), (0.15, 0.8))
    same = bool(rng.integers(0, 2))
    c_weft = list(c_warp) if same else _hsv(rng, (0.2, 0.9), (0.15, 0.8))
    col = warp_top[..., None] * np.asarray(c_warp) + (1.0 - warp_top[..., None]) * np.asarray(c_weft)
    shade = (0.75 + 0.25 * np.minimum(weave / (1.0 + lift), 1.0)) * (0.8 + 0.4 * (fibre - 0.5))
    shade = shade * (1.0 - 0.6 * gap)  # gaps between threads are dark
    albedo = col * shade[..., None]

    rough0 = float(rng.uniform(0.3, 0.6))  # synthetic and silk fibres have a sheen
    roughness = rough0 * (0.9 + 0.2 * fibre)
    spec0 = float(rng.uniform(0.2, 0.6))
    specular = spec0 * (1.0 - gap)
    params.update(
        weave="plain", threads_across=n, phase=[pu, pv], thread_width=width, lift=lift,
        thickness_side=thick_side, source="grass", crop=crop, gamma=gamma, fuzz=fuzz,
        warp_colour=c_warp, weft_colour=c_weft, same_colour=same,
        roughness_base=rough0, specular_base=spec0,
    )
    return height, albedo, roughness, specular, [DIELECTRIC_F0] * 3


def _wood(rng, shape, sources, params):
    H, W = shape
    if "wood_rgb" in sources:
        photo, crop = _crop(rng, _get_source(sources, "wood_rgb"), shape, (0.4, 1.0))
        bright = float(rng.uniform(0.7, 1.1))
        tint = _jitter(rng, (1.0, 1.0, 1.0), 0.08)
        albedo = _srgb_to_linear(photo) * bright * np.asarray(tint)
        lum = luminance(albedo)
        params.update(source="wood_rgb", rgb_fallback=False, crop=crop, brightness=bright, tint=tint)
    else:
        # grey fallback: grass stretched 5x along one axis gives grain-like streaks
        grain, crop = _crop(rng, _get_source(sources, "grass"), shape, (0.4, 0.9), aspect=0.2)
        grain, gamma = _contrast(rng, grain, (0.7, 1.4))
        name = str(rng.choice(sorted(_WOOD_TONES)))
        dark = _jitter(rng, _WOOD_TONES[name][0], 0.1)
        light = _jitter(rng, _WOOD_TONES[name][1], 0.1)
        albedo = np.asarray(dark) + (np.asarray(light) - np.asarray(dark)) * grain[..., None]
        lum = grain
        params.update(
            source="grass", rgb_fallback=True, crop=crop, gamma=gamma, tone_name=name,
            tone_dark=dark, tone_light=light,
        )
    pores = _normalise(ndimage.gaussian_filter(lum, 0.002 * W, mode="reflect"))
    amp = float(rng.uniform(0.0005, 0.0015))  # nearly flat, side units
    height = pores * amp * W  # open pores (dark grain) lie low
    rough0 = float(rng.uniform(0.03, 0.07))  # clear varnish coat: a sharp highlight
    roughness = rough0 * (0.9 + 0.2 * (1.0 - pores))
    spec0 = float(rng.uniform(0.7, 1.0))  # varnish
    specular = np.full(shape, spec0)
    params.update(amplitude_side=amp, roughness_base=rough0, specular_base=spec0)
    return height, albedo, roughness, specular, [DIELECTRIC_F0] * 3


def _metal(rng, shape, sources, params):
    H, W = shape
    name = str(rng.choice(sorted(METAL_F0)))
    f0 = _jitter(rng, METAL_F0[name], 0.03)
    # brushed: white noise smeared along one axis
    # (drawn on a fixed 512 x 512 grid from a child generator, then
    # area-resized, so that every resolution shows the same strokes)
    axis = int(rng.integers(0, 2))
    noise_seed = int(rng.integers(0, 2**63 - 1))
    noise = np.random.default_rng(noise_seed).standard_normal((_NOISE_GRID, _NOISE_GRID))
    sig = [0.5, 0.5]
    sig[axis] = float(rng.uniform(0.03, 0.08)) * _NOISE_GRID
    brushed = ndimage.gaussian_filter(noise, sig, mode="wrap")
    brushed = _normalise(resize(brushed, shape, order=1, mode="reflect", anti_aliasing=True))
    amp_brush = float(rng.uniform(0.0002, 0.0008))
    # scratches: straight grooves with a Gaussian profile
    x, y = _pixel_xy(shape)
    n_scr = int(rng.integers(5, 30))
    scratches = np.zeros(shape)
    scr_params = []
    for _ in range(n_scr):  # loop over scratches, each vectorised over the grid
        cx, cy = (float(v) for v in rng.uniform(-0.5, 0.5, 2))
        ang = float(rng.uniform(0.0, np.pi))
        half = float(rng.uniform(0.05, 0.4))
        wid = float(rng.uniform(0.001, 0.003))
        dep = float(rng.uniform(0.0003, 0.0015))
        dx, dy = np.cos(ang), np.sin(ang)
        s = np.clip((x - cx) * dx + (y - cy) * dy, -half, half)
        dist2 = (x - cx - s * dx) ** 2 + (y - cy - s * dy) ** 2
        # pixel-averaged groove: Gaussian widened by the pixel box (variances
        # add, w^2/2 + p^2/12) at constant cross-section area
        w_eff = math.sqrt(wid**2 + 1.0 / (6.0 * W * W))
        scratches = np.maximum(scratches, dep * (wid / w_eff) * np.exp(-dist2 / w_eff**2))
        scr_params.append([cx, cy, ang, half, wid, dep])
    grime, crop = _crop(rng, _get_source(sources, "gravel"), shape, (0.3, 1.0))
    grime = ndimage.gaussian_filter(grime, 0.01 * W, mode="reflect")
    grime, gamma = _contrast(rng, grime, (1.0, 3.0))
    height = (brushed * amp_brush - scratches + 0.0005 * grime) * W

    rough0 = float(rng.uniform(0.04, 0.15))
    roughness = rough0 * (0.8 + 0.4 * grime) * (1.0 + (scratches > 0.0001))
    diff0 = float(rng.uniform(0.003, 0.02))  # polished metal: almost no diffuse
    albedo = diff0 * np.asarray(f0)[None, None, :] * (0.7 + 0.6 * grime)[..., None]
    spec0 = float(rng.uniform(0.85, 1.0))
    specular = spec0 * (1.0 - 0.4 * grime)
    params.update(
        metal=name, f0=f0, brush_axis=axis, brush_noise_seed=noise_seed,
        brush_sigma_side=[float(s) / _NOISE_GRID for s in sig],
        amplitude_brush_side=amp_brush, scratches=scr_params, source="gravel", crop=crop,
        gamma=gamma, roughness_base=rough0, diffuse_base=diff0, specular_base=spec0,
    )
    return height, albedo, roughness, specular, f0


def _stone(rng, shape, sources, params):
    H, W = shape
    src = str(rng.choice(["brick", "gravel"]))
    if src == "brick" and "bricks_rgb" in sources:
        photo, crop = _crop(rng, _get_source(sources, "bricks_rgb"), shape, (0.3, 1.0))
        bright = float(rng.uniform(0.6, 1.0))
        albedo = _srgb_to_linear(photo) * bright
        relief = luminance(photo)
        params.update(source="bricks_rgb", rgb_fallback=False, crop=crop, brightness=bright)
    else:
        relief, crop = _crop(rng, _get_source(sources, src), shape, (0.3, 1.0))
        name = str(rng.choice(sorted(_STONE_TONES)))
        dark = _jitter(rng, _STONE_TONES[name][0], 0.1)
        light = _jitter(rng, _STONE_TONES[name][1], 0.1)
        tone, _ = _contrast(rng, relief, (1.0, 1.0))
        albedo = np.asarray(dark) + (np.asarray(light) - np.asarray(dark)) * tone[..., None]
        params.update(
            source=src, rgb_fallback=src == "brick", crop=crop, tone_name=name,
            tone_dark=dark, tone_light=light,
        )
    relief = ndimage.gaussian_filter(relief, 0.004 * W, mode="reflect")
    if src == "brick":
        # the photographs show light mortar between darker bricks: the mortar
        # joints are recessed, the brick faces are flat plateaus with a
        # little surface texture
        inv = 1.0 - relief
        q_lo, q_hi = np.percentile(inv, [15.0, 55.0])
        face = np.clip((inv - q_lo) / max(q_hi - q_lo, 1e-6), 0.0, 1.0)
        face = face * face * (3.0 - 2.0 * face)  # smoothstep: rounded brick edges
        relief = 0.85 * face + 0.15 * _normalise(inv)
    relief, gamma = _contrast(rng, relief, (0.7, 1.5))
    amp = float(rng.uniform(0.03, 0.06))
    height = relief * amp * W
    rough0 = float(rng.uniform(0.6, 0.95))
    roughness = rough0 * (0.9 + 0.2 * (1.0 - relief))
    spec0 = float(rng.uniform(0.02, 0.1))
    specular = np.full(shape, spec0)
    # mineral grains (mica, quartz facets): a sparse set of smooth, glossy texels
    grains, gcrop = _crop(rng, _get_source(sources, "gravel"), shape, (0.15, 0.4))
    frac = float(rng.uniform(0.03, 0.1))
    thr = np.quantile(grains, 1.0 - frac)
    glint = np.clip((grains - thr) / max(0.02, 0.05 * float(grains.std())) + 0.5, 0.0, 1.0)
    g_rough = float(rng.uniform(0.08, 0.2))
    g_spec = float(rng.uniform(0.5, 1.0))
    roughness = roughness * (1.0 - glint) + g_rough * glint
    specular = specular * (1.0 - glint) + g_spec * glint
    params.update(
        relief="mortar_low" if src == "brick" else "bright_high",
        gamma=gamma, amplitude_side=amp, roughness_base=rough0, specular_base=spec0,
        grain_crop=gcrop, grain_fraction=frac, grain_roughness=g_rough, grain_specular=g_spec,
    )
    return height, albedo, roughness, specular, [DIELECTRIC_F0] * 3


def _carpet(rng, shape, sources, params):
    H, W = shape
    fib, crop = _crop(rng, _get_source(sources, "grass"), shape, (0.3, 0.7))
    fib, gamma = _contrast(rng, fib, (1.0, 2.0))  # gamma > 1: sparse tall tufts
    amp = float(rng.uniform(0.03, 0.06))
    height = fib * amp * W
    colour = _hsv(rng, (0.2, 0.8), (0.2, 0.7))
    albedo = np.asarray(colour)[None, None, :] * (0.35 + 0.65 * fib)[..., None]  # tips lighter
    rough0 = float(rng.uniform(0.7, 1.0))
    roughness = np.full(shape, rough0)
    spec0 = float(rng.uniform(0.0, 0.04))
    specular = spec0 * fib
    params.update(
        source="grass", crop=crop, gamma=gamma, amplitude_side=amp, colour=colour,
        roughness_base=rough0, specular_base=spec0,
    )
    return height, albedo, roughness, specular, [DIELECTRIC_F0] * 3


_MAKERS = {
    "leather": _leather,
    "cloth": _cloth,
    "wood": _wood,
    "metal": _metal,
    "stone": _stone,
    "carpet": _carpet,
}


def make_material(
    class_name: str,
    seed: int,
    shape: tuple[int, int],
    sources: Mapping[str, np.ndarray],
) -> MaterialMaps:
    """Draw one material sample of a class from texture photographs.

    Parameters
    ----------
    class_name : str
        One of :data:`MATERIAL_CLASSES`.
    seed : int
        Seed of ``np.random.default_rng``; the same inputs and seed give
        bit-identical maps.
    shape : tuple of int
        Map grid ``(H, W)`` covering the square sample.
    sources : mapping of str to ndarray
        Texture photographs by name (:data:`SOURCE_NAMES`): ``brick``,
        ``grass``, ``gravel`` as ``(h, w)`` greyscale arrays (uint8 or float
        in [0, 1]); optionally ``bricks_rgb`` and ``wood_rgb`` as
        ``(h, w, 3)`` arrays.  Without the colour ones, wood and stone
        colourise a greyscale source and record ``rgb_fallback=True``.

    Returns
    -------
    maps : MaterialMaps
        Height (column-pitch units, min 0), albedo, GGX roughness, specular
        weight and ``f0``; ``params`` records every random draw.

    Raises
    ------
    ValueError
        Unknown class, bad shape or malformed source.
    KeyError
        A source the class needs is missing.

    Notes
    -----
    Relief amplitudes are drawn in units of the sample side ``s`` and
    converted to pixels, ``h_px = h_side * W``, so that maps drawn at twice
    the resolution describe the same geometry.  Per class (side units):
    leather 0.003-0.008, cloth thread thickness 0.25-0.45 of a period of
    1/16-1/40, wood 0.0005-0.0015, metal < 0.002, stone 0.02-0.05, carpet
    0.03-0.06.
    """
    if class_name not in _MAKERS:
        raise ValueError(f"unknown material class {class_name!r}; choose one of {MATERIAL_CLASSES}")
    H, W = _check_shape(shape)
    seed = int(seed)
    rng = np.random.default_rng(seed)
    params: dict = {"class_name": class_name, "seed": seed, "shape": [H, W]}
    height, albedo, roughness, specular, f0 = _MAKERS[class_name](rng, (H, W), sources, params)
    return _finish(class_name, height, albedo, roughness, specular, f0, params)


def white_standard(shape: tuple[int, int]) -> MaterialMaps:
    """A flat Lambertian white target (albedo 0.99 grey, no specular).

    Parameters
    ----------
    shape : tuple of int
        Map grid ``(H, W)``.

    Returns
    -------
    maps : MaterialMaps
        Height 0, albedo 0.99, specular 0; its BTF is
        ``0.99 / pi * cos(theta_i)`` everywhere.
    """
    maps = flat_material(shape, albedo=(0.99, 0.99, 0.99), roughness=1.0, specular=0.0)
    return MaterialMaps(
        class_name="white_standard", height=maps.height, albedo=maps.albedo,
        roughness=maps.roughness, specular=maps.specular, f0=maps.f0,
        params={"class_name": "white_standard", "albedo": 0.99, "shape": list(maps.shape)},
    )


def flat_material(
    shape: tuple[int, int],
    albedo=(1.0, 1.0, 1.0),
    roughness: float = 0.3,
    specular: float = 0.0,
    f0=(DIELECTRIC_F0,) * 3,
) -> MaterialMaps:
    """A flat, spatially uniform material (for tests and calibration).

    Parameters
    ----------
    shape : tuple of int
        Map grid ``(H, W)``.
    albedo : (3,) array_like
        Diffuse RGB albedo in [0, 1].
    roughness : float
        GGX alpha in (0, 1].
    specular : float
        Specular weight >= 0.
    f0 : (3,) array_like
        Fresnel reflectance at normal incidence.

    Returns
    -------
    maps : MaterialMaps
    """
    H, W = _check_shape(shape)
    a = np.asarray(albedo, dtype=np.float64).reshape(3)
    return MaterialMaps(
        class_name="flat",
        height=np.zeros((H, W), np.float32),
        albedo=np.broadcast_to(a.astype(np.float32), (H, W, 3)).copy(),
        roughness=np.full((H, W), roughness, np.float32),
        specular=np.full((H, W), specular, np.float32),
        f0=np.asarray(f0, dtype=np.float32).reshape(3),
        params={
            "class_name": "flat", "shape": [H, W], "albedo": [float(v) for v in a],
            "roughness": float(roughness), "specular": float(specular),
            "f0": [float(v) for v in np.asarray(f0, dtype=np.float64).reshape(3)],
        },
    )
